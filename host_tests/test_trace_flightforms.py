"""Issue 17, item 5: the flight form of channel_scale (a scale factor following a
telemetry channel), the `channel_scale` option of generator.flight.chain.

* the float64 model trace fits (SensorModel with ChannelScale effects, read back from a
  coefficient set by from_flight) is the chain's arithmetic, run by
  chain.reference_sensor in float64: agreement to 1e-6 nT (float64 round-off of a chain
  of ~100 operations on 5e4 nT is ~1e-10 nT; the margin covers the order of the sums);
* the generated C, compiled on the host, is the float32 reference bit for bit;
* a traced channel scale reaches the extended coefficients (g_per_unit, the channel among
  the sensor's channels), `generate --compile`, `table` (encoded and decoded) and
  `apply`;
* a chain without the option has the structure (and layout hash) it had before: the
  option is written only where it is used.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.flight import chain
from generator.flight.chain import ChainSpec, SensorOptions
from generator.flight.coeffs import CoefficientSet
from generator.pipeline import chain_inputs
from generator.trace import tracer as tr

from ci import require_gcc
from test_trace import _extended_set, rotation_with_channels, run, sigma_field, small_unit  # noqa: F401
from test_trace_channel_scale import ScaledBySupply


def _with_scale(cs: CoefficientSet, rng) -> CoefficientSet:
    """cs with channel_scale on every sensor: g random, ~1e-3 per unit (a 0.1 % scale
    change per unit of the channel: 50 nT at 50 uT)."""
    opts = tuple((n, replace(o, channel_scale=True)) for n, o in cs.spec.sensor_options)
    spec = ChainSpec(cs.unit, poly_degree=cs.spec.poly_degree, coils=cs.spec.coils,
                     sensor_options=opts)
    sensors = {}
    for s in cs.unit.sensors:
        v = dict(cs.sensors[s.name])
        v["g_per_unit"] = rng.normal(size=(3, len(spec.opts(s).channels))) * 1e-3
        sensors[s.name] = {b.name: np.asarray(v[b.name], float).reshape(b.shape)
                           for b in spec.sensor_blocks(s)}
    return CoefficientSet(spec, sensors, cs.unit_values, {}, {})



def _model_is_the_float64_chain(unit, cs, tel):
    """Trace's float64 model of the calibrated field (tr.calibrated_field64) against the
    chain's reference run in float64 on the same inputs: the same function up to the
    order of float64 operations (both float64, not the C: no bit comparison here), so
    1e-6 nT on fields of ~5e4 nT."""
    unit64 = replace(unit, float_type="float64")
    spec64 = ChainSpec(unit64, poly_degree=5, coils=(), sensor_options=cs.spec.sensor_options)
    for s in unit.sensors:
        rows, B64 = tr.calibrated_field64(cs, tel, s.name)
        inp = _inputs(tel, cs, s.name)
        ref = chain.reference_sensor(spec64, unit64.sensor(s.name), cs.flat_sensor(s.name),
                                     cs.flat_unit(), inp["raw_counts"], inp["temp_C"],
                                     inp["coil_A"], channels=inp["channels"],
                                     rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        assert np.all(ref["status"][rows] == 0)
        np.testing.assert_allclose(B64, ref["field_body_nT"][rows], rtol=0, atol=1e-6)

def test_the_model_is_the_chain_with_channel_scale(rotation_with_channels):
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _with_scale(_extended_set(unit, base, truth, rng), np.random.default_rng(4))
    _model_is_the_float64_chain(unit, cs, tel)
    # the stage is live: a change of g changes the model
    cs2 = CoefficientSet(cs.spec, {n: dict(v) for n, v in cs.sensors.items()},
                         cs.unit_values, {}, {})
    cs2.sensors["mmc2"]["g_per_unit"] = cs2.sensors["mmc2"]["g_per_unit"] * 1.5
    assert np.abs(tr.calibrated_field64(cs2, tel, "mmc2")[1]
                  - tr.calibrated_field64(cs, tel, "mmc2")[1]).max() > 0.01


def test_the_c_is_the_reference_with_channel_scale(rotation_with_channels):
    require_gcc()
    from chain_fixtures import assert_bit_identical
    from generator.flight.host import HostUnit
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _with_scale(_extended_set(unit, base, truth, rng), np.random.default_rng(5))
    host = HostUnit(cs)
    for s in unit.sensors:
        inp = chain_inputs(tel, cs.spec, s.name)
        got = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                           channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        py = chain.reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                    inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                                    channels=inp["channels"], rate_dps=inp["rate_dps"],
                                    dt_s=inp["dt_s"])
        assert_bit_identical(got, py, f"channel_scale {s.name}")


def test_without_the_option_the_structure_is_unchanged():
    unit = small_unit()
    o = SensorOptions(channels=("heater_A",), thermal_lag=True)
    assert "channel_scale" not in o.to_dict()
    assert SensorOptions.from_dict(o.to_dict()) == o
    a = ChainSpec(unit, sensor_options=(("mmc1", o),))
    b = ChainSpec(unit, sensor_options=(("mmc1", replace(o, channel_scale=True)),))
    assert "g_per_unit" not in [blk.name for blk in a.sensor_blocks(unit.sensor("mmc1"))]
    assert "g_per_unit" in [blk.name for blk in b.sensor_blocks(unit.sensor("mmc1"))]
    assert a.layout_hash() != b.layout_hash()


def test_a_traced_channel_scale_goes_through_generate_table_apply(tmp_path):
    require_gcc()
    from generator.cli import main
    rng = np.random.default_rng(71_001)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = "mmc1"
    src = sim.SquareWave(300.0, 0.5, 1.0, 0.0, 40.0, 3)
    g = np.array([0.8, -0.5, 1.0]) * 15.0 * sigma_field(unit.sensor(s)) / \
        (unit.lab_field_nT or 50_000.0)          # 15 x the per-axis noise at most
    tel, _ = run("thermal", unit, truth, 7, tmp_path, [ScaledBySupply(s, "supply_V", tuple(g),
                                                                       src)])
    res = tr.trace(unit, [tel])
    assert [(n, st.effect.name) for n, st in res.effects][:1] == [(s, "channel_scale")]
    out = tmp_path / "trace"
    res.write(out)
    cs = CoefficientSet.load(out / "coefficients.json")
    o = cs.spec.opts(s)
    assert o.channel_scale and "supply_V" in o.channels
    got_g = cs.sensors[s]["g_per_unit"][:, o.channels.index("supply_V")]
    # the fitted scale is the simulated one within its statistical error: the simulator's
    # g is 15 x the per-axis noise at the field's magnitude, so a third of it is ~5 sigma
    assert np.all(np.abs(got_g - g) < np.abs(g).max() / 3), (got_g, g)
    cj = str(out / "coefficients.json")
    assert main(["generate", cj, "-o", str(tmp_path / "gen"), "--compile", "-q"]) == 0
    c_text = "".join(p.read_text() for p in (tmp_path / "gen").glob("*.[ch]"))
    assert "supply_V" in c_text
    assert main(["table", cj, "-o", str(tmp_path / "t.bin"), "-q"]) == 0
    assert main(["table", "--decode", str(tmp_path / "t.bin"), "-q"]) == 0
    assert main(["apply", cj, str(tel.path), "-o", str(tmp_path / "a.csv"), "-q"]) == 0
    assert (tmp_path / "a.csv").stat().st_size > 0


# ---- lagged_channel_bias: the lagged_channels option --------------------------------
def _with_lag(cs: CoefficientSet, rng, tau_s=25.0) -> CoefficientSet:
    """cs with heater_A also through a first-order lag (tau_s) on every sensor: C_lag
    random, 50 nT per unit (as the direct channels' scale)."""
    opts = tuple((n, replace(o, lagged_channels=("heater_A",)))
                 for n, o in cs.spec.sensor_options)
    spec = ChainSpec(cs.unit, poly_degree=cs.spec.poly_degree, coils=cs.spec.coils,
                     sensor_options=opts)
    sensors = {}
    for s in cs.unit.sensors:
        v = dict(cs.sensors[s.name])
        v["C_lag_nT_per_unit"] = rng.normal(size=(3, 1)) * 50
        v["lag_channel_tau_s"] = np.array([tau_s])
        sensors[s.name] = {b.name: np.asarray(v[b.name], float).reshape(b.shape)
                           for b in spec.sensor_blocks(s)}
    return CoefficientSet(spec, sensors, cs.unit_values, {}, {})


def _inputs(tel, cs, name):
    inp = chain_inputs(tel, cs.spec, name, aux_off=True)
    t = tel.time_s
    np.testing.assert_array_equal(inp["dt_s"], np.diff(t, prepend=t[0]))   # as apply does
    if "heater_A" in tel.columns:
        np.testing.assert_array_equal(inp["channels"]["heater_A"], tel.columns["heater_A"])
    inp["dt_s"] = inp["dt_s"].copy()
    return inp


def test_the_model_is_the_chain_with_lagged_channels(rotation_with_channels):
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _with_lag(_with_scale(_extended_set(unit, base, truth, rng),
                               np.random.default_rng(6)), np.random.default_rng(7))
    assert np.ptp(tel.columns["heater_A"]) > 0
    _model_is_the_float64_chain(unit, cs, tel)
    # the filter is live: another time constant changes the model
    cs2 = CoefficientSet(cs.spec, {n: dict(v) for n, v in cs.sensors.items()},
                         cs.unit_values, {}, {})
    cs2.sensors["mmc2"]["lag_channel_tau_s"] = cs2.sensors["mmc2"]["lag_channel_tau_s"] * 3
    assert np.abs(tr.calibrated_field64(cs2, tel, "mmc2")[1]
                  - tr.calibrated_field64(cs, tel, "mmc2")[1]).max() > 0.01


def test_the_c_is_the_reference_with_lagged_channels(rotation_with_channels, tmp_path):
    require_gcc()
    from chain_fixtures import assert_bit_identical
    from generator.cli import main
    from generator.flight.host import HostUnit
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _with_lag(_extended_set(unit, base, truth, rng), np.random.default_rng(8))
    host = HostUnit(cs)
    for s in unit.sensors:
        inp = _inputs(tel, cs, s.name)
        inp["dt_s"][::53] = -1.0                 # clock steps back: the filter holds
        got = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                           channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        py = chain.reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                    inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                                    channels=inp["channels"], rate_dps=inp["rate_dps"],
                                    dt_s=inp["dt_s"])
        assert_bit_identical(got, py, f"lagged channels {s.name}")
    path = tmp_path / "c.json"
    cs.save(path)
    assert main(["generate", str(path), "-o", str(tmp_path / "gen"), "--compile", "-q"]) == 0
    assert main(["table", str(path), "-o", str(tmp_path / "t.bin"), "-q"]) == 0


def test_a_traced_lagged_heater_goes_through_generate_table_and_the_c(tmp_path):
    """The lagged heater of test_trace_lagged (one of its draws: 12 x the noise, tau
    120 s): traced, written (lagged_channels, its tau), generated and compiled; the C
    over the data is the float32 reference bit for bit and the trace's float64 model to
    float32 rounding (0.1 nT: float32 carries ~7 digits of 5e4 nT)."""
    require_gcc()
    from chain_fixtures import assert_bit_identical
    from generator.cli import main
    from generator.flight.host import HostUnit
    from test_trace import _direction
    from test_trace_lagged import LaggedHeater
    rng = np.random.default_rng(61_001)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = "mmc2"
    src = sim.SquareWave(600.0, 0.5, 1.0, 0.0, 100.0, 3)
    eff = LaggedHeater(s, "heater_A", tuple(_direction(rng) * 12.0 * sigma_field(unit.sensor(s))),
                       120.0, src)
    tel, _ = run("thermal", unit, truth, 5, tmp_path, [eff])
    res = tr.trace(unit, [tel])
    assert (s, "lagged_channel_bias") in [(n, st.effect.name) for n, st in res.effects]
    out = tmp_path / "trace"
    res.write(out)
    cs = CoefficientSet.load(out / "coefficients.json")
    o = cs.spec.opts(s)
    assert o.lagged_channels == ("heater_A",)
    assert 120.0 / 1.5 < float(cs.sensors[s]["lag_channel_tau_s"][0]) < 120.0 * 1.5
    cj = str(out / "coefficients.json")
    assert main(["generate", cj, "-o", str(tmp_path / "gen"), "--compile", "-q"]) == 0
    assert main(["table", cj, "-o", str(tmp_path / "t.bin"), "-q"]) == 0
    assert main(["apply", cj, str(tel.path), "-o", str(tmp_path / "a.csv"), "-q"]) == 0
    host = HostUnit(cs)
    inp = _inputs(tel, cs, s)
    got = host.correct(s, inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                       channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
    py = chain.reference_sensor(cs.spec, unit.sensor(s), cs.flat_sensor(s), cs.flat_unit(),
                                inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                                channels=inp["channels"], rate_dps=inp["rate_dps"],
                                dt_s=inp["dt_s"])
    assert_bit_identical(got, py, "traced lagged heater")
    rows, B64 = tr.calibrated_field64(cs, tel, s)
    np.testing.assert_allclose(got["field_body_nT"][rows], B64, rtol=0, atol=0.1)


def test_bad_options_in_coefficients_json_name_the_key(rotation_with_channels):
    """coefficients.json is user input: the new options are checked like the others."""
    import json
    from generator.errors import InputError
    unit, truth, base, (thermal, tel), rng = rotation_with_channels
    cs = _with_lag(_with_scale(_extended_set(unit, base, truth, rng),
                               np.random.default_rng(9)), np.random.default_rng(10))
    doc = json.loads(json.dumps(cs.to_json_dict(), default=float))
    CoefficientSet.from_json_dict(json.loads(json.dumps(doc)))        # as written: valid
    for key, value in (("lagged_channels", "heater_A"), ("lagged_channels", [1]),
                       ("lagged_channels", ["heater_A", "heater_A"]),
                       ("channel_scale", "yes")):
        bad = json.loads(json.dumps(doc))
        bad["chain"]["sensor_options"]["mmc1"][key] = value
        with pytest.raises(InputError, match=key):
            CoefficientSet.from_json_dict(bad)
