"""The flight flop bound (issue 20 item 5): the chain with every constant folded.

chain.fold_sensor_coeffs / folded_sensor_kernel must be the same chain as sensor_kernel
(same field, same band margins, same bridge offset for every kind of sensor and every
optional stage), and arm_measure.flop_bound counts its per-call operations. Runs on the
host (CasADi and numpy only), no ARM toolchain needed.

Equality tolerance: both forms run in float64 on the same values; they differ only by
re-association (scale times a difference vs a difference of scaled values, H (M x) vs
(H M) x), each step good to ~1e-16 relative, over a few tens of operations on numbers up to
~1e5 nT with cancellation in b - field of at most ~1e2 (offsets ~1e3 nT against fields
~5e4): 1e-9 relative to |B| leaves ample margin; a wrong fold (a missing sign, a scale
applied twice, H left out) is wrong by O(1).
"""

from __future__ import annotations

import numpy as np
import pytest

from chain_fixtures import random_coeffs, samsat_unit, with_options
from generator.flight import arm_measure as am
from generator.flight.arm_build import entry_points
from generator.flight.chain import (CoeffView, SensorOptions, fold_sensor_coeffs,
                                    folded_sensor_kernel, is_physical, sensor_kernel)
from generator.io.unit import SensorSpec, Unit

COILS = ("coil_x_A", "coil_y_A", "coil_z_A")
REL_TOL = 1e-9     # see the module docstring


def _physical_unit() -> Unit:
    return Unit("physb", (
        SensorSpec("ist", "generic", "body", ("+y", "-x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6),
        SensorSpec("hmg", "generic", "boom", ("-z", "+y", "+x"), 1.0, 0, True, 100.0,
                   input="G", temperature=True, range_nT=8e5),
        SensorSpec("mmc", "MMC5883MA", "body", ("+x", "+y", "+z"), 25.0, 32768, True, 40.0)),
        lab_field_nT=50000.0, boom_reference="mmc")


def _cases():
    rng = np.random.default_rng(20)
    base = random_coeffs(rng, samsat_unit("bnd"), coils=COILS)
    everything = {s.name: SensorOptions(channels=("heater_A",), nonlinear=True,
                                        sr_compensation=True, channel_scale=True,
                                        lagged_channels=("bus_V",))
                  for s in base.unit.sensors}
    some = {"mpu3": SensorOptions(channels=("heater_A", "bus_V"), nonlinear=True),
            "mmc1": SensorOptions(sr_compensation=True)}
    return [("samsat, coils", base),
            ("samsat, every option", with_options(rng, base, everything)),
            ("samsat, some options", with_options(rng, base, some)),
            ("physical and no temperature", random_coeffs(rng, _physical_unit(), coils=COILS))]


def _inputs(rng, spec, s, set_only):
    """One sample's per-call inputs in float64: raw values around a plausible field."""
    if is_physical(s):
        raw = list(rng.normal(0, 50000.0 / (1000.0 if s.input == "uT" else 1e5), 6))
    else:
        raw = list(s.zero_count + np.round(rng.normal(0, 50000.0 / s.lsb_nT, 6)))
    temp = float(rng.uniform(-10, 40))
    coil = list(rng.normal(0, 0.1, len(spec.coils)))
    channels = list(rng.normal(0, 1, len(spec.opts(s).kernel_channels)))
    rate = list(rng.normal(0, 5, 3))
    return raw, temp, coil, channels, rate


@pytest.mark.parametrize("label,cs", _cases(), ids=lambda v: v if isinstance(v, str) else "")
def test_folded_chain_is_the_chain(label, cs):
    rng = np.random.default_rng(3)
    spec = cs.spec
    u = CoeffView(list(cs.flat_unit()), spec.unit_blocks())
    half = np.float64(0.5)
    for s in cs.unit.sensors:
        c = CoeffView(list(cs.flat_sensor(s.name)), spec.sensor_blocks(s))
        for set_only in ([False, True] if s.set_reset else [False]):
            f = fold_sensor_coeffs(spec, s, c, u, half, set_only=set_only)
            for _ in range(20):
                raw, temp, coil, ch, rate = _inputs(rng, spec, s, set_only)
                if set_only:   # SET, then the stored (SET + RESET) / 2
                    raw = raw[:3] + [(raw[i] + raw[3 + i]) * 0.5 for i in range(3)]
                ref = sensor_kernel(spec, s, raw, temp, coil, c, u, half, set_only=set_only,
                                    channels=ch, rate_dps=rate)
                got = folded_sensor_kernel(spec, s, raw, temp, coil, f, half,
                                           set_only=set_only, channels=ch, rate_dps=rate)
                assert set(got) == set(ref), (label, s.name)
                B = np.array(ref["field_body_nT"], float)
                scale = float(np.linalg.norm(B))
                for key in ref:
                    a, b = np.array(got[key], float), np.array(ref[key], float)
                    tol = REL_TOL * (scale * scale if key == "band_margin_nT2" else
                                     max(scale, float(np.max(np.abs(b)))))
                    assert np.all(np.abs(a - b) <= tol), (label, s.name, set_only, key, a, b)


def _unfolded_flops(spec, s, set_only=False):
    """Per-call operations of the unfolded chain (chain.sensor_kernel on the table's
    coefficients, as the generated kernel was before the prepare step)."""
    import casadi as ca
    ins = spec.sensor_inputs(s, set_only)
    sym = {i.name: ca.SX.sym(i.name, i.size) for i in ins}
    c_sym = ca.SX.sym("c", spec.n_sensor_coeffs(s))
    u_sym = ca.SX.sym("u", spec.n_unit_coeffs())
    c = CoeffView([c_sym[k] for k in range(c_sym.numel())], spec.sensor_blocks(s))
    u = CoeffView([u_sym[k] for k in range(u_sym.numel())], spec.unit_blocks())

    def elems(name):
        return [sym[name][k] for k in range(sym[name].numel())] if name in sym else []
    temp = sym["temp_C"][0] if "temp_C" in sym else None
    out = sensor_kernel(spec, s, elems("raw_counts"), temp, elems("coil_A"), c, u,
                        ca.SX(0.5), set_only=set_only, channels=elems("channels"),
                        rate_dps=elems("rate_dps"))
    f = ca.Function("unfolded", [sym[i.name] for i in ins] + [c_sym, u_sym],
                    [ca.vertcat(*out[o.name]) for o in spec.sensor_outputs(s, set_only)])
    return am.per_call_flops(f, len(ins))


def test_bound_counts_the_folds_the_issue_names():
    """A plain counts sensor's unfolded chain does per call 3 multiplications by lsb and
    squares the two band limits: the bound has none of them. Its 3 subtractions of the
    zero count stay per call: count - zero is exact, a zero point folded into b(T) would
    round the temperature terms added to it (review #20d F2). A boom sensor without rate compensation also applies H (9 multiplications, 6
    additions), which folds into M. The generated kernel is the folded chain: its per-call
    operations are the bound's."""
    cs = random_coeffs(np.random.default_rng(6), samsat_unit("fb"), coils=COILS)
    plain_body, plain_boom = cs.unit.sensor("mpu1"), cs.unit.sensor("mpu3")
    assert not plain_body.set_reset and plain_boom.frame == "boom"
    for s, saved in ((plain_body, 3 + 2), (plain_boom, 3 + 2 + 15)):
        b = am.flop_bound(cs.spec, s)
        unfolded = _unfolded_flops(cs.spec, s)
        total = unfolded["flops"] + unfolded["coeff_only"]
        assert total - b["flops"] == saved, (s.name, unfolded, b)
        # the squares of the band limits were the unfolded chain's only coefficient-only
        # operations; the generated kernel has none left
        assert unfolded["coeff_only"] == 2
        assert b["kernel_coeff_only"] == 0 and b["kernel_per_call"] == b["flops"]
        assert am.min_flops(cs.spec, s)["flops"] == b["flops"]


def test_bound_never_exceeds_the_kernel():
    for _, cs in _cases():
        for e in entry_points(cs):
            b = am.entry_bound(cs.spec, e)
            k = am.function_flops(e.kernel(cs.spec))["flops"]
            assert 0 < b["flops"] <= b["kernel_per_call"] <= k, (e.fn, b, k)


def test_per_call_count_ignores_coefficient_only_operations():
    import casadi as ca
    x, c = ca.SX.sym("x", 2), ca.SX.sym("c", 2)
    f = ca.Function("f", [x, c], [x[0] * c[0] + c[1] * c[1] - (c[0] + c[1]) * x[1]])
    n = am.per_call_flops(f, 1)
    assert n["flops"] == 4 and n["coeff_only"] == 2      # x0 c0, (..) x1, +, -; c1^2, c0 + c1
    assert am.per_call_flops(f, 2)["flops"] == 6


def test_bound_data_movement():
    """moves: one load per folded coefficient and input element, one store per output.
    A plain counts sensor with a cubic b(T), M(T) and three coils reads 4 x 3 offsets,
    4 x 9 matrix entries, 3 x 3 couplings, t_ref, its zero count and the two squared band
    limits, takes
    3 counts, a temperature and 3 currents, writes 3 field components and 2 margins; a
    boom sensor's H is folded into M, so it reads no more."""
    cs = random_coeffs(np.random.default_rng(6), samsat_unit("fm"), coils=COILS)
    for name in ("mpu1", "mpu3"):
        b = am.flop_bound(cs.spec, cs.unit.sensor(name))
        assert b["moves"] == (12 + 36 + 9 + 1 + 1 + 2) + (3 + 1 + 3) + (3 + 2), (name, b)


def test_every_optional_stage_has_a_folded_form():
    """A stage added to SensorOptions (and sensor_kernel) without a folded form makes the
    bound refuse instead of silently leaving the stage out."""
    from generator.flight import chain
    import dataclasses
    # the dataclass's fields, not to_dict (which leaves out stages a unit does not use)
    assert {f.name for f in dataclasses.fields(SensorOptions)} == set(chain._FOLDED_OPTIONS)
