"""`magcal simulate` (generator/verbs/simulate.py) and the simulator following the test
program (generator/campaign/simulate.py, issue 19 item 4).

* the thermal campaign follows `magcal plan`'s program: its holds come from the boards'
  time constants, so the segment finder finds every level in every position;
* the lab field of the unit file is the field of the campaigns;
* `magcal simulate` then `magcal fit` works for units no test wrote down: hypothesis draws
  1 to 8 sensors of the parts catalogue, counts or physical units, with and without
  temperature, with and without a boom;
* bad input: exit 2 and one line.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from generator.campaign import plan as plan_mod
from generator.campaign import simulate as sim
from generator.cli import main
from generator.fit.segments import find_segments, group_levels
from generator.io import parts as parts_mod
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unit import SensorSpec, Unit
from generator.io.unitfile import load_unit
from generator.flight.coeffs import CoefficientSet

# a small thermal program for the tests: one sample every 2 min, 5 per hold (10 min, the
# segment finder's window)
FAST = ["--sample-period-s", "120", "--samples-per-segment", "5"]


def _sim(tmp_path, unit_path, *extra, name="sim"):
    out = tmp_path / name
    rc = main(["simulate", str(unit_path), "-o", str(out), "-q", *FAST, *extra])
    return rc, out


def test_thermal_campaign_follows_the_plan_and_every_level_is_found(tmp_path):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--campaigns", "thermal_12pos")
    assert rc == 0
    truth = sim.load_truth(out / "truth.json", unit)
    plan = plan_mod.load_plan(out / "plan.json")
    # the holds were computed from the slowest board's true time constant
    assert plan.board_tau_s == pytest.approx(max(truth.board_tau_s.values()))
    arrays = np.load(out / "thermal_12pos.truth.npz")
    tel = read_telemetry(out / "thermal_12pos.csv", load_unit(out / "unit.toml"))
    t, pos = tel.columns["time_s"], tel.columns["position"]
    # every recording window of the program: the board within the plan's settling
    # tolerance of the set-point plus the board's self-heating (a first-order lag settles
    # to tolerance after tau ln(step / tol), which is how the holds were computed)
    for it in plan.chamber_program():
        if it["action"] != "hold":
            continue
        w = (t >= it["record_from_s"]) & (t < it["record_to_s"])
        assert w.sum() == plan.samples_per_segment
        assert np.all(pos[w] == it["position"])
        for board, key in (("body", "temp_body_C"), ("boom", "temp_boom_C")):
            target = it["setpoint_C"] + truth.board_self_heating_C[board]
            assert np.max(np.abs(arrays[key][w] - target)) <= plan.settle_tolerance_C
    # recording pauses while the jig is turned: no sample with position 0
    assert np.all(pos > 0)
    # the fit's segment finder finds all levels in all twelve positions
    for s in unit.sensors:
        segs = find_segments(t, tel.columns[f"{s.name}_temp_C"], pos)
        levels = group_levels(segs, 3.0)
        assert len(levels) == len(plan.levels_C), s.name
        assert all(len({g.position for g in lv}) == 12 for lv in levels), s.name


def test_check_says_the_simulated_campaign_covers_its_plan(tmp_path, capsys):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--campaigns", "thermal_12pos")
    assert rc == 0
    capsys.readouterr()
    rc = main(["check", str(out / "unit.toml"), str(out / "thermal_12pos.csv"), "--plan",
               str(out / "plan.json"), "--json", "-q"])
    res = json.loads(capsys.readouterr().out)
    assert rc == 0 and not res["gaps"]


def test_the_unit_lab_field_is_the_campaign_field(tmp_path):
    unit = sim.make_example_unit()
    unit = Unit(unit.id, unit.sensors, lab_field_nT=23456.0, boom_reference="mmc1")
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc, out = _sim(tmp_path, tmp_path / "unit.toml")
    assert rc == 0
    plan = json.loads((out / "plan.json").read_text())
    assert plan["lab_field_nT"] == 23456.0
    for kind in ("thermal_12pos", "rotation", "coils", "coil_study"):
        a = np.load(out / f"{kind}.truth.npz")
        assert np.allclose(np.linalg.norm(a["b_body_nT"], axis=1), 23456.0), kind
        tel = read_telemetry(out / f"{kind}.csv", load_unit(out / "unit.toml"))
        assert np.all(tel.columns["ref_norm_nT"] == 23456.0), kind


def test_plan_given_is_followed(tmp_path):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    assert main(["plan", str(tmp_path / "unit.toml"), "-o", str(tmp_path / "plan"), "-q",
                 "--levels", "0", "40", "--sample-period-s", "120",
                 "--samples-per-segment", "5", "--board-tau-min", "25"]) == 0
    rc = main(["simulate", str(tmp_path / "unit.toml"), "-o", str(tmp_path / "s"), "-q",
               "--plan", str(tmp_path / "plan" / "plan.json"), "--campaigns",
               "thermal_12pos"])
    assert rc == 0
    written = plan_mod.load_plan(tmp_path / "s" / "plan.json")
    given_ = plan_mod.load_plan(tmp_path / "plan" / "plan.json")
    assert written.levels_C == [0.0, 40.0]
    assert [s.hold_s for s in written.steps] == [s.hold_s for s in given_.steps]
    chamber = np.load(tmp_path / "s" / "thermal_12pos.truth.npz")["temp_chamber_C"]
    assert chamber.min() == pytest.approx(0.0) and chamber.max() == pytest.approx(40.0)


def test_truth_override_sets_the_parameters(tmp_path):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    over = tmp_path / "truth.toml"
    over.write_text('[board_tau_s]\nbody = 300.0\nboom = 420.0\n'
                    '[coil_study]\nexponent = 2.5\n'
                    '[sensors.mpu1]\nnoise_nT = 7.0\nb_poly_frame_nT = [[100.0, -200.0, 300.0]]\n')
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--truth", str(over),
                   "--campaigns", "thermal_12pos")
    assert rc == 0
    tj = json.loads((out / "truth.json").read_text())
    assert tj["board_tau_s"] == {"body": 300.0, "boom": 420.0}
    assert tj["coil_study"]["exponent"] == 2.5
    assert tj["sensors"]["mpu1"]["noise_nT"] == 7.0
    assert tj["sensors"]["mpu1"]["b_poly_frame_nT"] == [[100.0, -200.0, 300.0]]
    assert json.loads((out / "plan.json").read_text())["board_tau_s"] == 420.0
    # the same seed without the override draws the same everything else
    rc, plain = _sim(tmp_path, tmp_path / "unit.toml", "--campaigns", "thermal_12pos",
                     name="plain")
    pj = json.loads((plain / "truth.json").read_text())
    assert pj["sensors"]["mmc1"] == tj["sensors"]["mmc1"]


@pytest.mark.parametrize("content, fault", [
    ('[sensors.nosuch]\nnoise_nT = 1.0\n', "sensors.nosuch"),
    ('[sensors.mpu1]\nW_poly_frame = [[1.0, 0.0]]\n', "sensors.mpu1.W_poly_frame"),
    ('[board_tau_s]\nbody = -5.0\n', "board_tau_s.body"),
    ('H_boom_to_body = [[2.0,0,0],[0,1,0],[0,0,1]]\n', "H_boom_to_body"),
    ('colour = "red"\n', "colour"),
    ('[coil_study]\nexponent = 60.0\n', "coil_study.exponent"),
    ('this is not toml\n', "not a TOML"),
])
def test_bad_truth_override_is_one_line(tmp_path, capsys, content, fault):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    bad = tmp_path / "truth.toml"
    bad.write_text(content)
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--truth", str(bad))
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and fault in err and "truth.toml" in err
    assert not out.exists()


@pytest.mark.parametrize("argv_extra, fault", [
    (["--sample-period-s", "0"], "--sample-period-s"),
    (["--plan", "missing.json"], "missing.json"),
    (["--seed", "-3"], "--seed"),
])
def test_bad_arguments_are_one_line(tmp_path, capsys, argv_extra, fault):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc = main(["simulate", str(tmp_path / "unit.toml"), "-o", str(tmp_path / "o"), "-q",
               *argv_extra])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and fault in err
    assert not (tmp_path / "o").exists()


def test_bad_plan_is_one_line(tmp_path, capsys):
    unit = sim.make_example_unit()
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    assert main(["plan", str(tmp_path / "unit.toml"), "-o", str(tmp_path / "plan"), "-q"]) == 0
    d = json.loads((tmp_path / "plan" / "plan.json").read_text())
    d["steps"][2]["hold_s"] = "long"
    (tmp_path / "bad.json").write_text(json.dumps(d))
    rc = main(["simulate", str(tmp_path / "unit.toml"), "-o", str(tmp_path / "o"), "-q",
               "--plan", str(tmp_path / "bad.json")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "steps[2].hold_s" in err


# ---- any unit: simulate, then fit ------------------------------------------------------

PARTS = parts_mod.names()
PHYSICAL = ("nT", "uT", "mG", "G")


def _sensor(i, part_name, frame, axes, temperature, inp, set_reset):
    part = parts_mod.part(part_name)
    name = f"s{i}"
    if part.generic:
        return SensorSpec(name, part_name, frame, axes, 1.0, 0, set_reset, 100.0, input=inp,
                          temperature=temperature, range_nT=1.6e6)
    res = part.resolutions[0]
    zero = res.zero_count if res.zero_count is not None else part.zero_count
    return SensorSpec(name, part_name, frame, axes, res.lsb_nT, int(zero),
                      set_reset and part.set_reset, None,
                      temperature=temperature and part.temperature)


@st.composite
def units(draw):
    n = draw(st.integers(1, 8))
    boom = draw(st.booleans())
    sensors = []
    for i in range(n):
        perm = draw(st.permutations("xyz"))
        signs = draw(st.lists(st.sampled_from("+-"), min_size=3, max_size=3))
        frame = "boom" if (boom and i > 0 and draw(st.booleans())) else "body"
        part = draw(st.sampled_from(PARTS))
        temperature = draw(st.booleans())
        sensors.append(_sensor(i, part, frame, tuple(sg + a for sg, a in zip(signs, perm)),
                               temperature, draw(st.sampled_from(PHYSICAL)),
                               draw(st.booleans())))
    has_boom = any(s.frame == "boom" for s in sensors)
    field = draw(st.sampled_from((None, 25000.0, 48000.0, 64000.0)))
    return Unit("anyunit", tuple(sensors), lab_field_nT=field,
                boom_reference="s0" if has_boom else None), draw(st.integers(0, 2**32 - 1))


@settings(max_examples=3, deadline=None, derandomize=True, database=None,
          phases=[Phase.explicit, Phase.generate],      # no shrinking: minutes per step
          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                 HealthCheck.too_slow])
@given(drawn=units())
@example(drawn=(Unit("boomed", (
    _sensor(0, "MMC5883MA", "body", ("+z", "+y", "+x"), True, "uT", True),
    _sensor(1, "generic", "body", ("-y", "+x", "+z"), True, "uT", False),
    _sensor(2, "MMC5983MA", "boom", ("-y", "-z", "-x"), True, "uT", True),
    _sensor(3, "MPU-9255", "boom", ("-y", "-z", "+x"), True, "uT", False)),
    lab_field_nT=49800.0, boom_reference="s0"), 11))
def test_simulate_then_fit_any_unit(tmp_path_factory, drawn):
    unit, seed = drawn
    d = tmp_path_factory.mktemp("anyunit")
    sim.write_unit_toml(unit, d / "unit.toml")
    out = d / "sim"
    assert main(["simulate", str(d / "unit.toml"), "-o", str(out), "-q", "--seed", str(seed),
                 *FAST]) == 0
    files = [out / f"{k}.csv" for k in ("thermal_12pos", "rotation", "coils", "coil_study")]
    assert main(["fit", str(out / "unit.toml"), *map(str, files), "-o", str(d / "fit"),
                 "-q"]) == 0
    cs = CoefficientSet.load(d / "fit" / "coefficients.json")
    loaded = load_unit(out / "unit.toml")
    assert set(cs.sensors) == set(loaded.sensor_names)
    truth = sim.load_truth(out / "truth.json", loaded)
    tel = read_telemetry(out / "thermal_12pos.csv", loaded)
    data = preprocess(tel, loaded)
    ref = np.column_stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"])
    for s in loaded.sensors:
        sd = data[s.name]
        ok = sd.usable & np.isfinite(sd.field_frame_nT).all(axis=1)
        raw = np.linalg.norm(sd.field_frame_nT[ok], axis=1) - np.linalg.norm(ref[ok], axis=1)
        B = cs.calibration(s.name).apply64(sd.field_frame_nT[ok], sd.temp_C[ok])
        cal = np.linalg.norm(B, axis=1) - np.linalg.norm(ref[ok], axis=1)
        rms_raw, rms_cal = (float(np.sqrt(np.mean(x ** 2))) for x in (raw, cal))
        if not s.temperature:
            # the truth drifts with temperature, the sensor cannot say how: the fit can only
            # remove what does not change; it must not make things worse
            assert rms_cal < rms_raw, s.name
            continue
        # with temperature the model is the truth's: what is left is the reading noise
        # (halved in variance by SET/RESET) and the quantisation, each per axis; |B| sees
        # one axis' worth, sigma. Over N >= 2000 samples the RMS of that noise scatters by
        # 1/sqrt(2N) < 2 %, and the fitted parameters (p ~ 30 per sensor) add about
        # sqrt(p/N) ~ 12 % in quadrature: 1.25 sigma holds them with room.
        sigma = sim.sensor_noise_nT(s, truth.sensors[s.name])
        q = s.lsb_nT if s.counts else 0.1 * s.nT_per_input
        per_axis = math.sqrt((sigma ** 2 + q ** 2 / 12) / (2 if s.set_reset else 1))
        assert ok.sum() >= 2000
        assert rms_cal < 1.25 * per_axis, (s.name, s.part, rms_cal, rms_raw, per_axis)


def test_boom_unit_with_a_sensor_without_temperature(tmp_path):
    unit = Unit("boomy", (_sensor(0, "MMC5983MA", "body", ("+x", "+y", "+z"), True, "uT", True),
                          _sensor(1, "IST8310", "boom", ("+y", "+x", "-z"), False, "uT", False)),
                lab_field_nT=48000.0, boom_reference="s0")
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--seed", "3")
    assert rc == 0
    files = [out / f"{k}.csv" for k in ("thermal_12pos", "rotation", "coils", "coil_study")]
    assert main(["fit", str(out / "unit.toml"), *map(str, files), "-o",
                 str(tmp_path / "fit"), "-q"]) == 0


def test_gauss_input_fits(tmp_path):
    unit = Unit("gee", (_sensor(0, "generic", "body", ("+x", "+y", "+z"), True, "G", False),),
                lab_field_nT=48000.0)
    sim.write_unit_toml(unit, tmp_path / "unit.toml")
    rc, out = _sim(tmp_path, tmp_path / "unit.toml", "--campaigns", "thermal_12pos")
    assert rc == 0
    assert main(["fit", str(out / "unit.toml"), str(out / "thermal_12pos.csv"), "-o",
                 str(tmp_path / "fit"), "-q"]) == 0
