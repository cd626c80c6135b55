"""Issue 6 acceptance: `magcal trace` names effects the model lacks, on data it was not told
about, and leaves clean data alone.

The project's simulator (generator.campaign.simulate) injects each catalogue effect with a random
size (3-20 x the sensor's per-axis field noise, measured as the largest contribution of
the effect that the baseline model cannot absorb), random axis direction, sensor and
channel into fast campaigns; a fixed seed list per effect (not one lucky draw). For every
draw the trace must name exactly that effect on that sensor (and channel) and nothing
else anywhere, and bring the sensor's held-out RMS within 1.2 x the error the true model
has on the same held-out samples (the noise mapped through the true calibration).

Campaigns: thermal effects on the fast twelve-position chamber test (reference vectors);
rotation effects (cubic, SET/RESET, time offset) on the fast hand rotation with the true
field vector written as the reference (a rig with known orientation: without it these
effects, which turn the field rather than change its size, are invisible to |B|). The
nominal SET/RESET delay is set to 0 in the campaigns: clean means "nothing the baseline
lacks"; SetResetDelay injects a delay. The boom alignment of the random truth is set to
the identity so that the rotation rig's body-frame reference holds for the boom sensor.

Also here: the float64 model of the extended chain equals generator.flight.chain's reference
run in float64, the traced coefficients generate flight C that reproduces it, the
correlated-channel cases, and the command-line handler.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from generator.flight import chain
from generator.campaign import simulate as sim
from generator.trace import tracer as tr
from generator.verbs import trace as verbs_trace
from generator.flight.chain import ChainSpec, SensorOptions
from generator.flight.coeffs import CoefficientSet
from generator.errors import InputError
from generator.pipeline import chain_inputs
from generator.io.telemetry import Telemetry
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unit import Unit

from ci import require_gcc

SIZE_RANGE = (3.0, 20.0)       # effect size in units of the per-axis field noise
RATIO_LIMIT = 1.2              # final held-out RMS / truth-model RMS
SEEDS = [1, 2, 3, 4, 5, 6]
CLEAN_SEEDS = list(range(1, 11))
RESULTS = []                   # (effect, seed, outcome) for the summary


# =======================================================================================
# Cases from the project's simulator
# =======================================================================================
def small_unit() -> Unit:
    """Three sensors of the SamSat-ION mounting: MMC5883 body and boom, one MPU-9255."""
    u = sim.make_example_unit("trace_sat")
    keep = ("mmc1", "mpu1", "mmc2")
    return Unit(id=u.id, lab_field_nT=u.lab_field_nT, float_type=u.float_type,
                boom_reference="mmc1", sensors=tuple(s for s in u.sensors if s.name in keep))


def sigma_field(spec) -> float:
    """Per-axis noise of the field: a SET/RESET field averages two readings."""
    return spec.noise_nT / math.sqrt(2.0) if spec.set_reset else spec.noise_nT


def _with_reference_vectors(tel: Telemetry, arrays) -> Telemetry:
    cols = dict(tel.columns)
    for k, a in enumerate("xyz"):
        cols[f"ref_{a}_nT"] = np.round(arrays["b_body_nT"][:, k], 1)
    return Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))


def run(kind, unit, truth, seed, out, effects=(), noise_scale=1.0, name=None):
    """One fast campaign: 'thermal' (twelve positions in the chamber) or 'rotation'
    (hand rotation, reference vectors added). Returns (Telemetry, truth arrays)."""
    camp = {"thermal": "thermal_12pos", "rotation": "rotation"}[kind]
    p, arr = sim.simulate_campaign(camp, unit, truth, np.random.default_rng(seed), out,
                                   effects=effects, fast=True, set_reset_delay_s=0.0,
                                   noise_scale=noise_scale, name=name or f"{kind}_{seed}")
    tel = read_telemetry(p, unit)
    if kind == "rotation":
        tel = _with_reference_vectors(tel, arr)
    return tel, arr


def contribution(kind, unit, truth, seed, out, effects, sensor):
    """Noise-free contribution of the effects to the sensor's frame field, (n, 3)."""
    a, _ = run(kind, unit, truth, seed, out, effects, 0.0, name="nf_effect")
    b, _ = run(kind, unit, truth, seed, out, (), 0.0, name="nf_clean")
    return preprocess(a, unit)[sensor].field_frame_nT - preprocess(b, unit)[sensor].field_frame_nT


def peak(c) -> float:
    return float(np.nanmax(np.abs(c)))


def truth_error(kind, unit, truth, seed, out, effects, sensor, rows) -> float:
    """Per-axis RMS, on the given sample rows, of the noise mapped through the true
    calibration W(T)^-1: the held-out error of the true model."""
    a, arr = run(kind, unit, truth, seed, out, effects, 1.0, name="te_noisy")
    b, _ = run(kind, unit, truth, seed, out, effects, 0.0, name="te_clean")
    fa = preprocess(a, unit)[sensor].field_frame_nT[rows]
    fb = preprocess(b, unit)[sensor].field_frame_nT[rows]
    spec = unit.sensor(sensor)
    T = arr["temp_body_C" if spec.frame == "body" else "temp_boom_C"][rows]
    W = truth.sensors[sensor].W(T - truth.t_ref_C)
    e = np.linalg.solve(W, (fa - fb)[..., None])[..., 0]
    return float(np.sqrt(np.nanmean(e ** 2)))


@dataclass
class LinearDrift(sim.Effect):
    """Test-only effect: the offset drifts linearly in time (nT/s, frame axes)."""
    sensor: str
    nT_per_s: tuple
    name = "linear_drift"

    def frame_nT(self, ctx):
        return (ctx.time_s - ctx.time_s[0])[:, None] * np.asarray(self.nT_per_s, float)


@dataclass
class TabulatedChannel(sim.Effect):
    """Test-only: a telemetry channel given as a table of (time, value), no field."""
    sensor: str
    channel: str
    times: tuple
    values: tuple
    name = "tabulated_channel"

    def channels(self, time_s):
        return {self.channel: (np.interp(time_s, self.times, self.values), 4)}


CHANNEL_NAMES = ["heater_A", "payload_current_A", "radio_tx_A", "bus_current_A", "camera_on"]


def _direction(rng):
    d = rng.normal(size=3)
    return d / np.max(np.abs(d))


@dataclass
class Case:
    unit: Unit
    truth: object
    kind: str
    effects: list
    sensor: str
    effect: str
    channel: str | None
    seed: int
    size: float
    holdout_effects: list | None = None    # a later campaign (bias step: after the event)


def make_case(effect, seed, out) -> Case:
    """One random draw: truth, sensor, size, direction, channel, time, all from the seed."""
    rng = np.random.default_rng(1000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    k = float(rng.uniform(*SIZE_RANGE))
    cseed = int(rng.integers(1 << 30))
    names = [s.name for s in unit.sensors]
    pool = [s.name for s in unit.sensors if s.set_reset] \
        if effect in ("thermal_lag", "set_reset_rotation") else names
    s = str(rng.choice(pool))
    target = k * sigma_field(unit.sensor(s))
    d = _direction(rng)
    case = Case(unit, truth, "thermal", [], s, effect, None, cseed, k)
    if effect == "channel_bias":
        ch, other = (str(c) for c in rng.choice(CHANNEL_NAMES, 2, replace=False))
        high = round(float(rng.uniform(0.1, 1.0)), 3)
        src = sim.SquareWave(float(rng.uniform(200, 600)), float(rng.uniform(0.3, 0.6)), high,
                             0.0, float(rng.uniform(0, 300)), 3)
        decoy = sim.SquareWave(float(rng.uniform(200, 600)), float(rng.uniform(0.3, 0.6)), 1.0,
                               0.0, float(rng.uniform(0, 300)), 3)
        case.effects = [sim.ChannelBias(s, ch, tuple(d * target / high), src),
                        sim.ChannelBias(s, other, (0.0, 0.0, 0.0), decoy)]   # a decoy channel
        case.channel = ch
        return case
    if effect == "thermal_lag":      # bisect tau for the largest contribution
        lo, hi = math.log(0.5), math.log(300.0)
        for _ in range(14):
            tau = math.exp(0.5 * (lo + hi))
            c = contribution("thermal", unit, truth, cseed, out, [sim.ThermalLag(s, tau)], s)
            lo, hi = (math.log(tau), hi) if peak(c) < target else (lo, math.log(tau))
        case.effects = [sim.ThermalLag(s, tau)]
        return case
    if effect == "temperature_polynomial":
        # size: the part of b4 dT^4 that a cubic in the campaign's temperatures cannot take
        _, arr = run("thermal", unit, truth, cseed, out, (), 0.0, name="nf_clean")
        dT = arr["temp_body_C" if unit.sensor(s).frame == "body" else "temp_boom_C"] - 25.0
        P = np.vander(dT, 4)
        q = dT ** 4 - P @ np.linalg.lstsq(P, dT ** 4, rcond=None)[0]
        case.effects = [sim.QuarticBias(s, tuple(d * target / peak(q)))]
        return case
    kind, make = {
        "cubic_nonlinearity": ("rotation", lambda a: sim.CubicNonlinearity(s, tuple(a * d))),
        "bias_step": ("thermal", lambda a: sim.BiasStep(s, t0, tuple(a * d))),
        "time_drift": ("thermal", lambda a: LinearDrift(s, tuple(a * d))),
        "set_reset_rotation": ("rotation", lambda a: sim.SetResetDelay(s, a * 0.01)),
        "time_offset": ("rotation", lambda a: sim.TimeOffset(s, a * 0.01 * sign)),
    }[effect]
    sign = float(rng.choice([-1.0, 1.0]))
    t0 = float(rng.uniform(0.2, 0.8)) * 2160.0           # inside the fast thermal campaign
    case.kind = kind
    a = 1.0
    for _ in range(4):          # linear in a, up to count rounding
        c = contribution(kind, unit, truth, cseed, out, [make(a)], s)
        a *= min(max(target / max(peak(c), 1e-9), 1e-3), 1e3)
    case.effects = [make(a)]
    if effect == "bias_step":   # evaluated on a later campaign, after the event
        case.holdout_effects = [sim.BiasStep(s, -1.0, tuple(a * d))]
    return case


def trace_case(case: Case, out):
    tel, _ = run(case.kind, case.unit, case.truth, case.seed, out, case.effects)
    hold = []
    if case.holdout_effects is not None:
        h, _ = run(case.kind, case.unit, case.truth, case.seed + 1, out, case.holdout_effects,
                   name="later")
        hold = [h]
    return tr.trace(case.unit, [tel], hold), tel


def found_effects(res):
    return [(n, st.effect.name, st.effect.explained_by(), st) for n, st in res.effects]


# =======================================================================================
# Injected effects, across seeds
# =======================================================================================
EFFECTS = ["channel_bias", "thermal_lag", "temperature_polynomial", "cubic_nonlinearity",
           "bias_step", "time_drift", "set_reset_rotation", "time_offset"]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("effect", EFFECTS)
def test_trace_names_the_injected_effect_and_reaches_the_noise_floor(effect, seed, tmp_path):
    case = make_case(effect, seed, tmp_path)
    res, tel = trace_case(case, tmp_path)
    found = found_effects(res)
    summary = [(n, e, by) for n, e, by, _ in found]
    right = [f for f in found if f[0] == case.sensor and f[1] == effect]
    if not right and effect == "time_offset" and case.unit.sensor(case.sensor).set_reset:
        # with an inertially fixed field a time offset is a rotation error w x B too; the
        # trace may name the SET/RESET error if it reports the offset as equivalent
        right = [f for f in found if f[0] == case.sensor and f[1] == "set_reset_rotation"
                 and f[3].runner_up is not None and f[3].runner_up.effect.name == "time_offset"
                 and tr.equivalent(f[3].score, f[3].runner_up)]
    outcome = "found" if right and len(found) == 1 else ("missed" if not right else "extra")
    RESULTS.append((effect, seed, case.sensor, case.size, outcome, summary))
    assert right, f"{effect} on {case.sensor} (size {case.size:.1f} x noise) not named: {summary}"
    assert len(found) == 1, f"other effects named too: {summary}"
    if case.channel is not None:
        assert right[0][2] == [case.channel]
    tr_s = res.traces[case.sensor]
    step = right[0][3]
    assert step.rms_after_nT < step.rms_before_nT
    n_data = tel.n if res.evaluated_on == "holdout" else 0
    rows = tr_s.S_eval.order - n_data
    err = truth_error(case.kind, case.unit, case.truth,
                      case.seed + (1 if res.evaluated_on == "holdout" else 0), tmp_path,
                      case.holdout_effects if res.evaluated_on == "holdout" else case.effects,
                      case.sensor, rows)
    ratio = tr_s.final_rms_nT / err
    RESULTS[-1] = RESULTS[-1] + (ratio,)
    assert ratio <= RATIO_LIMIT, (f"held-out RMS {tr_s.final_rms_nT:.1f} nT is {ratio:.2f} x "
                                  f"the true model's {err:.1f} nT")


@pytest.mark.parametrize("seed", CLEAN_SEEDS)
def test_clean_data_comes_back_with_no_effect(seed, tmp_path):
    rng = np.random.default_rng(5000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    tels = [run("thermal", unit, truth, seed, tmp_path)[0],
            run("rotation", unit, truth, seed + 100, tmp_path)[0]]
    res = tr.trace(unit, tels)
    found = [(n, st.effect.label()) for n, st in res.effects]
    RESULTS.append(("clean", seed, "-", 0.0, "clean" if not found else "false positive", found))
    assert not found, f"invented effects in clean data: {found}"
    assert json.loads(json.dumps(res.to_json(), default=tr._json_default))["effects"] == []
    # no traced stage; the SET/RESET gyro compensation is the fit's decision (the baseline
    # carries it, as magcal fit does: M is fitted to the compensated output), not an effect
    from dataclasses import replace
    from generator.flight.chain import SensorOptions
    for _, o in res.coefficients.spec.sensor_options:
        assert replace(o, sr_compensation=False) == SensorOptions(), o


# =======================================================================================
# Correlated channels must not fool it
# =======================================================================================
def correlated_case(which, seed, out):
    """'lag': the truth is a thermal lag; a heater current regulated on the element
    temperature follows the temperature closely. 'channel': the truth is a bias linear in
    a solar-array current that follows the chamber (so the temperature too)."""
    rng = np.random.default_rng(7000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    cseed = int(rng.integers(1 << 30))
    s = str(rng.choice(["mmc1", "mmc2"]))
    _, arr = run("thermal", unit, truth, cseed, out, (), 0.0, name="pre")
    t = arr["time_s"]
    T = arr["temp_boom_C" if unit.sensor(s).frame == "boom" else "temp_body_C"]
    if which == "lag":
        tau = float(rng.uniform(15.0, 30.0))
        T_el = sim.first_order_lag(t, T, tau)
        ch_name, ch = "heater_A", np.clip(0.6 - 0.012 * (T_el - 25.0), 0.0, None)
        effects = [TabulatedChannel(s, ch_name, tuple(t), tuple(ch)), sim.ThermalLag(s, tau)]
        true_effect = "thermal_lag"
    else:
        ch_name = "sa_current_A"
        ch = 0.35 + 0.006 * (arr["temp_chamber_C"] - 25.0) + 0.05 * np.sin(2 * np.pi * t / 700)
        C = _direction(rng) * rng.uniform(5, 15) * sigma_field(unit.sensor(s)) / 0.3
        effects = [TabulatedChannel(s, ch_name, tuple(t), tuple(ch)),
                   sim.ChannelBias(s, ch_name, tuple(C))]
        true_effect = "channel_bias"
    return unit, truth, cseed, s, effects, true_effect, ch_name, float(np.corrcoef(ch, T)[0, 1])


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("which", ["lag", "channel"])
def test_a_channel_correlated_with_temperature_does_not_fool_it(which, seed, tmp_path):
    unit, truth, cseed, s, effects, true_effect, ch, corr = correlated_case(which, seed, tmp_path)
    assert abs(corr) > 0.5, f"the scenario is not correlated enough ({corr:.2f})"
    tel, _ = run("thermal", unit, truth, cseed, tmp_path, effects)
    res = tr.trace(unit, [tel])
    steps = res.traces[s].steps
    assert steps, "nothing found"
    first = steps[0]
    assert first.effect.name == true_effect, [st.effect.label() for st in steps]
    assert all(n == s for n, _ in res.effects), [(n, st.effect.label()) for n, st in res.effects]
    entry = res.to_json()["effects"][0]
    ru = entry["runner_up"]
    print(f"\n{which} seed {seed}: corr(channel, T) = {corr:.2f}; chose {first.effect.label()} "
          f"({entry['rms_before_nT']:.1f} -> {entry['rms_after_nT']:.1f} nT); runner-up "
          f"{ru['effect']} {ru['explained_by']}: {ru['why_it_lost']}")
    if which == "lag":
        # the heater competed (it explains part of the lag) and lost, with the reason shown
        chan = [c for c in res.to_json()["rounds"][s][0]["candidates"]
                if c["explained_by"] == [ch]]
        assert chan and chan[0]["cv_rms_gain_pct"] > 2.0, chan
        assert ru["explained_by"] == [ch]
        assert ru["cv_rms_gain_pct"] < 100 * first.score.rel_rms_gain
        assert ru["why_it_lost"]
    else:
        assert first.effect.explained_by() == [ch]
        assert not any(st.effect.name in ("temperature_polynomial", "thermal_lag")
                       for st in steps), [st.effect.label() for st in steps]
        assert ru["why_it_lost"]


# =======================================================================================
# The model is the flight chain; the extended coefficients make flight C
# =======================================================================================
def _extended_set(unit, base: CoefficientSet, truth, rng) -> CoefficientSet:
    """Every optional stage on every sensor, degree 5, random effect coefficients."""
    opts = []
    for s in unit.sensors:
        opts.append((s.name, SensorOptions(channels=("heater_A", "rate_x_dps"), thermal_lag=True,
                                           nonlinear=True, sr_compensation=s.set_reset)))
    spec = ChainSpec(unit, poly_degree=5, coils=(), sensor_options=tuple(opts))
    sensors = {}
    for s in unit.sensors:
        v = {k: np.array(a, float) for k, a in base.sensors[s.name].items()}
        b = np.zeros((6, 3))
        b[:4] = v["b_poly_nT"]
        b[4] = rng.normal(size=3) * 1e-4
        b[5] = rng.normal(size=3) * 1e-6
        M = np.zeros((6, 3, 3))
        M[:4] = v["M_poly"]
        v.update(b_poly_nT=b, M_poly=M, C_nT_per_unit=rng.normal(size=(3, 2)) * 50,
                 lag_tau_s=np.array(15.0), cubic_per_nT2=rng.normal(size=3) * 1e-11,
                 sr_comp_s_per_deg=np.array(0.01 / 2 * math.pi / 180))
        sensors[s.name] = {blk.name: np.asarray(v[blk.name], float).reshape(blk.shape)
                           for blk in spec.sensor_blocks(s)}
    uv = dict(base.unit_values)
    uv["H_boom_to_body"] = sim.random_truth(unit, rng).H_boom_to_body   # a real rotation
    return CoefficientSet(spec, sensors, uv, {}, {})


@pytest.fixture(scope="module")
def rotation_with_channels(tmp_path_factory):
    out = tmp_path_factory.mktemp("flightform")
    unit = small_unit()
    rng = np.random.default_rng(11)
    truth = sim.random_truth(unit, rng)
    heater = sim.heater_bias("mmc1", (0.0, 0.0, 0.0), period_s=20.0, current_A=0.5)
    thermal, _ = run("thermal", unit, truth, 1, out)
    tel, _ = run("rotation", unit, truth, 2, out, [heater])
    base = tr.baseline_coefficients(unit, [thermal])[0]
    return unit, truth, base, (thermal, tel), rng


def test_the_float64_model_is_the_flight_chain(rotation_with_channels):
    """SensorModel (what trace fits) against generator.flight.chain.reference_sensor run in
    float64, with every optional stage: channels, thermal lag, degree 5, cubic, SET/RESET
    rate compensation with the boom's H^T w."""
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _extended_set(unit, base, truth, rng)
    unit64 = replace(unit, float_type="float64")
    spec64 = ChainSpec(unit64, poly_degree=5, coils=(), sensor_options=cs.spec.sensor_options)
    for s, tel in ((s, t) for t in (thermal, tel) for s in unit.sensors):
        rows, B64 = tr.calibrated_field64(cs, tel, s.name)
        # the thermal campaign has no heater_A or rate columns: heater off, unit still (as
        # trace takes it)
        inp = chain_inputs(tel, cs.spec, s.name, aux_off=True)
        ref = chain.reference_sensor(spec64, unit64.sensor(s.name), cs.flat_sensor(s.name),
                                     cs.flat_unit(), inp["raw_counts"], inp["temp_C"],
                                     inp["coil_A"], channels=inp["channels"],
                                     rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        assert len(rows) == tel.n
        assert np.all(ref["status"][rows] == 0)
        np.testing.assert_allclose(B64, ref["field_body_nT"][rows], rtol=0, atol=1e-6)
    # and a change of any effect coefficient changes the model (the stages are live)
    for block, data in (("C_nT_per_unit", tel), ("lag_tau_s", thermal),
                        ("cubic_per_nT2", tel), ("sr_comp_s_per_deg", tel)):
        cs2 = CoefficientSet(cs.spec, {n: dict(v) for n, v in cs.sensors.items()},
                             cs.unit_values, {}, {})
        cs2.sensors["mmc2"][block] = cs2.sensors["mmc2"][block] * 1.5
        assert np.abs(tr.calibrated_field64(cs2, data, "mmc2")[1]
                      - tr.calibrated_field64(cs, data, "mmc2")[1]).max() > 0.01, block


def test_traced_coefficients_generate_flight_c_with_the_effects(tmp_path):
    """Trace a channel bias and a thermal lag, write the extended coefficients, run
    `magcal generate --compile`, and run the compiled C over the data: it agrees with the
    float64 model of the trace within float32 rounding."""
    require_gcc()
    from generator.cli import main
    from generator.flight.host import HostUnit
    unit = small_unit()
    truth = sim.random_truth(unit, np.random.default_rng(21))
    src = sim.SquareWave(300.0, 0.4, 0.5, 0.0, 10.0, 3)
    effects = [sim.ChannelBias("mmc1", "heater_A", (300.0, -150.0, 80.0), src),
               sim.ThermalLag("mmc2", 20.0)]
    tel, _ = run("thermal", unit, truth, 3, tmp_path, effects)
    res = tr.trace(unit, [tel])
    assert {(n, st.effect.name) for n, st in res.effects} == {("mmc1", "channel_bias"),
                                                              ("mmc2", "thermal_lag")}
    out = tmp_path / "trace"
    res.write(out)
    cs = CoefficientSet.load(out / "coefficients.json")
    assert cs.spec.opts("mmc1").channels == ("heater_A",)
    assert cs.spec.opts("mmc2").thermal_lag
    assert main(["generate", str(out / "coefficients.json"), "-o", str(tmp_path / "gen"),
                 "--compile", "-q"]) == 0
    c_text = "".join(p.read_text() for p in (tmp_path / "gen").glob("*.[ch]"))
    assert "heater_A" in c_text and "lag" in c_text
    host = HostUnit(cs)
    for s in unit.sensors:
        inp = chain_inputs(tel, cs.spec, s.name)
        got = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                           channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        # the flight C of the extended chain is the float32 reference, bit for bit ...
        from chain_fixtures import assert_bit_identical
        from generator.flight.chain import reference_sensor
        py = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                              inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                              channels=inp["channels"], rate_dps=inp["rate_dps"],
                              dt_s=inp["dt_s"])
        assert_bit_identical(got, py, f"traced chain {s.name}")
        # ... and agrees with trace's float64 model to float32 rounding (a model check)
        rows, B64 = tr.calibrated_field64(cs, tel, s.name)
        np.testing.assert_allclose(got["field_body_nT"][rows], B64, rtol=0, atol=0.1)


# =======================================================================================
# The verb
# =======================================================================================
def test_cmd_trace_writes_the_icd_outputs(tmp_path):
    import argparse
    unit = small_unit()
    truth = sim.random_truth(unit, np.random.default_rng(31))
    src = sim.SquareWave(250.0, 0.5, 0.4, 0.0, 0.0, 3)
    p, _ = sim.simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(1), tmp_path,
                                 effects=[sim.ChannelBias("mpu1", "heater_A", (2000.0, 0, -900.0),
                                                          src)], fast=True, name="data")
    h, _ = sim.simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(2), tmp_path,
                                 effects=[sim.ChannelBias("mpu1", "heater_A", (2000.0, 0, -900.0),
                                                          src)], fast=True, name="later")
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    parser = argparse.ArgumentParser()
    verbs_trace.add_trace_args(parser)
    parser.add_argument("-q", "--quiet", action="store_true")
    out = tmp_path / "out"
    args = parser.parse_args([str(tmp_path / "unit.toml"), str(p), "-o", str(out),
                              "--holdout", str(h), "-q"])
    assert verbs_trace.cmd_trace(args) == 0
    j = json.loads((out / "trace.json").read_text())
    assert j["evaluated_on"] == "holdout"
    assert set(j["baseline"]) == set(j["final"]) == {"mmc1", "mpu1", "mmc2"}
    for n in j["baseline"]:
        assert j["baseline"][n]["rms_nT"] > 0 and j["final"][n]["rms_nT"] > 0
    (e,) = j["effects"]
    for key in ("sensor", "effect", "explained_by", "rms_before_nT", "rms_after_nT", "evidence"):
        assert key in e
    assert (e["sensor"], e["effect"], e["explained_by"]) == ("mpu1", "channel_bias", ["heater_A"])
    assert e["rms_after_nT"] < 0.8 * e["rms_before_nT"]
    cs = CoefficientSet.load(out / "coefficients.json")
    assert cs.spec.opts("mpu1").channels == ("heater_A",)
    assert (out / "trace_report.md").exists() and (out / "trace_report.html").exists()
    assert list(out.glob("trace_mpu1_1_channel_bias.png"))
    # bad input: a coefficient set of another unit, a missing file
    other = sim.make_example_unit("other")
    bad = CoefficientSet.from_calibrations(other, {
        s.name: tr.SensorCalibration.constant(s.name, np.zeros(3), np.eye(3))
        for s in other.sensors})
    bad.save(tmp_path / "bad.json")
    with pytest.raises(InputError):
        tr.trace(str(tmp_path / "unit.toml"), [str(p)], coeffs=str(tmp_path / "bad.json"))
    with pytest.raises(InputError):
        tr.trace(str(tmp_path / "unit.toml"), [str(tmp_path / "nope.csv")])


def test_supplied_coefficients_with_effects_are_the_baseline(tmp_path):
    """Tracing again with the extended coefficients as the baseline: the effect already
    in them is part of the model, so nothing new is found."""
    unit = small_unit()
    truth = sim.random_truth(unit, np.random.default_rng(41))
    truth.H_boom_to_body = np.eye(3)
    src = sim.SquareWave(300.0, 0.4, 0.5, 0.0, 10.0, 3)
    eff = [sim.ChannelBias("mmc2", "heater_A", (250.0, 100.0, -60.0), src)]
    tel, _ = run("thermal", unit, truth, 5, tmp_path, eff)
    first = tr.trace(unit, [tel])
    assert [(n, st.effect.name) for n, st in first.effects] == [("mmc2", "channel_bias")]
    again = tr.trace(unit, [tel], coeffs=first.coefficients)
    assert not again.effects
    j = again.to_json()
    assert j["baseline"]["mmc2"]["effects_already_in_model"] == ["channel_bias(heater_A)"]
    assert j["baseline"]["mmc2"]["rms_nT"] < 1.1 * first.traces["mmc2"].final_rms_nT


def test_zz_summary():
    """Found / missed / extra per effect across the seeds (shown with -s)."""
    if not RESULTS:
        pytest.skip("no trace results in this run")
    lines = ["", "effect                  seeds found missed extra   worst ratio"]
    by = {}
    for r in RESULTS:
        by.setdefault(r[0], []).append(r)
    for eff, rs in by.items():
        found = sum(r[4] in ("found", "clean") for r in rs)
        missed = sum(r[4] == "missed" for r in rs)
        extra = sum(r[4] in ("extra", "false positive") for r in rs)
        ratios = [r[6] for r in rs if len(r) > 6]
        worst = f"{max(ratios):.3f}" if ratios else "-"
        lines.append(f"{eff:24s}{len(rs):5d}{found:6d}{missed:7d}{extra:6d}   {worst}")
    print("\n".join(lines))


def test_docs_list_every_catalogue_effect():
    from conftest import REPO
    from generator.trace.effects import CATALOGUE
    text = (REPO / "docs" / "effects.md").read_text()
    for cls in CATALOGUE:
        assert f"`{cls.name}`" in text, f"docs/effects.md does not describe {cls.name}"
