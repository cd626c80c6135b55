"""One segment per hold, and `magcal check` on boards that never settled (review 19b F1, F2).

Campaigns are simulated for small units (MMC5883MA: 0.7 degC temperature steps; ICM-20948;
LIS3MDL; a generic part with nT input) following the plan `magcal plan` writes for the
boards' true time constants (generator.campaign.scenarios.plan_for), 60 s samples and 10
per hold to keep them short. Then:

* every hold of the plan holds exactly one segment (generator.fit.segments.find_segments),
  and no segment lies outside a hold: the board's approach to a level, and its departure
  at the next ramp, are not segments of their own;
* within a segment the true board temperature spans no more than the finder allows the
  reading (its width max(band, 2 q)) plus what the reading cannot see: one reporting step
  q, and 6 sigma of the filtered reading's white noise;
* `magcal check` exits 0 on such a campaign, and exits 2 naming the levels when the
  boards are 2.5 times slower than planned (the reviewer's case: plan 20 min, boards
  50 min), where no hold comes within the plan's tolerance of its set-point.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.campaign.scenarios import plan_for
from generator.cli import main
from generator.fit.segments import find_segments, segment_band_C, step_and_white_noise_C
from generator.io.parts import temperature_lsb_C
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit

UNITS = {
    "mmc": """[unit]
id = "mmcpair"
lab_field_nT = 33000.0
[boom]
reference = "a"
[[sensor]]
name = "a"
part = "MMC5883MA"
frame = "body"
axes = ["+x", "+y", "+z"]
lsb_nT = 25.0
zero_count = 32768
set_reset = true
[[sensor]]
name = "b"
part = "MMC5883MA"
frame = "boom"
axes = ["-x", "+z", "+y"]
lsb_nT = 25.0
zero_count = 32768
set_reset = true
""",
    "icm_lis_gen": """[unit]
id = "mixed"
lab_field_nT = 50000.0
[boom]
reference = "lis"
[[sensor]]
name = "lis"
part = "LIS3MDL"
frame = "body"
axes = ["-y", "+x", "+z"]
input = "mG"
[[sensor]]
name = "icm"
part = "ICM-20948"
frame = "boom"
axes = ["+x", "+y", "+z"]
lsb_nT = 150.0
zero_count = 0
[[sensor]]
name = "gen"
part = "generic"
frame = "boom"
axes = ["+x", "+y", "+z"]
input = "nT"
range_nT = 200000.0
noise_nT = 50.0
""",
}

SLOW_TAU_S = 3000.0      # the reviewer's boards: 50 min where the plan assumed 20


def _campaign(tmp_path, unit_key, seed, slow=False):
    (tmp_path / "unit.toml").write_text(UNITS[unit_key], encoding="utf-8")
    unit = load_unit(tmp_path / "unit.toml")
    truth = sim.random_truth(unit, np.random.default_rng(seed))
    if slow:
        plan = plan_for(unit, truth, sample_period_s=60.0, samples_per_segment=10,
                        board_tau_min=20.0)
        truth.board_tau_s.update({b: SLOW_TAU_S for b in truth.board_tau_s})
    else:
        plan = plan_for(unit, truth, sample_period_s=60.0, samples_per_segment=10)
    path, arrays = sim.simulate_campaign("thermal_12pos", unit, truth,
                                         np.random.default_rng(seed + 100), tmp_path, plan=plan)
    (tmp_path / "plan.json").write_text(json.dumps(plan.to_json_dict()), encoding="utf-8")
    return unit, plan, path, arrays, truth


@pytest.mark.parametrize("unit_key,seed", [("mmc", 5), ("mmc", 6), ("icm_lis_gen", 5),
                                           ("icm_lis_gen", 7)])
def test_one_segment_per_hold(tmp_path, unit_key, seed):
    unit, plan, path, arrays, _ = _campaign(tmp_path, unit_key, seed)
    tel = read_telemetry(path, unit)
    pre = preprocess(tel, unit)
    holds = [it for it in plan.chamber_program() if it["action"] == "hold"]
    t = tel.time_s
    for s in unit.sensors:
        d = pre[s.name]
        use = d.usable & np.isfinite(d.field_frame_nT).all(axis=1)
        lsb = temperature_lsb_C(s.part)
        segs = find_segments(t, d.temp_C, tel.get("position"), use, temp_lsb_C=lsb)
        count = np.zeros(len(holds), int)
        for g in segs:
            # a hold's segment ends before the hold's ramp is over (the board lags)
            inside = [k for k, it in enumerate(holds)
                      if it["start_s"] <= g.t_start_s and g.t_stop_s <= it["start_s"]
                      + it["duration_s"] + plan.sample_period_s * 10 + 900.0]
            assert inside, (s.name, g.position, g.t_start_s, g.t_stop_s, g.temp_C)
            count[inside[0]] += 1
        assert count.tolist() == [1] * len(holds), (s.name, count.tolist())
        # "at least 10 min" from first to last sample, as the report prints it
        assert all(g.duration_s >= 600.0 for g in segs), (s.name, min(g.duration_s for g in segs))
        # the true board temperature inside a segment: the reading's span (at most the
        # width max(band, 2 q)) plus a step q and 6 sigma of white noise it cannot see
        q, sigma_w = step_and_white_noise_C(d.temp_C[use], lsb)
        width = max(segment_band_C(d.temp_C[use], temp_lsb_C=lsb), 2 * q)
        board = arrays["temp_boom_C" if s.frame == "boom" else "temp_body_C"]
        for g in segs:
            assert np.ptp(board[g.index]) <= width + q + 6 * sigma_w, (s.name, g)


def _check(capsys, tmp_path):
    rc = main(["check", str(tmp_path / "unit.toml"), str(tmp_path / "thermal_12pos.csv"),
               "--plan", str(tmp_path / "plan.json"), "-q"])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("unit_key", ["mmc", "icm_lis_gen"])
def test_check_passes_a_settled_campaign(tmp_path, capsys, unit_key):
    _campaign(tmp_path, unit_key, 5)
    rc, out, err = _check(capsys, tmp_path)
    assert rc == 0, out
    assert "campaign covers the plan" in err


@pytest.mark.parametrize("unit_key", ["mmc", "icm_lis_gen"])
def test_check_fails_boards_that_never_settled(tmp_path, capsys, unit_key):
    unit, plan, _, arrays, truth = _campaign(tmp_path, unit_key, 5, slow=True)
    # the premise: at the end of every hold of the first position, each board (less its
    # self-heating) is further from its set-point than the plan's tolerance plus one
    # MMC5883 step (0.7 degC), so no reading can place it within the tolerance
    holds = [it for it in plan.chamber_program() if it["action"] == "hold"
             and it["position"] == 1]
    t = arrays["time_s"]
    for board in ("body", "boom"):
        T = arrays[f"temp_{board}_C"]
        for it in holds:
            k = np.searchsorted(t, it["start_s"] + it["duration_s"]) - 1
            lag_C = T[k] - truth.board_self_heating_C[board] - it["setpoint_C"]
            assert abs(lag_C) > plan.settle_tolerance_C + 0.7, (board, it, lag_C)
    # the segment finder: still at most one segment per hold (the boards drift through
    # each hold; what is left of a hold is not cut into pieces)
    tel = read_telemetry(tmp_path / "thermal_12pos.csv", unit)
    pre = preprocess(tel, unit)
    all_holds = [it for it in plan.chamber_program() if it["action"] == "hold"]
    for s in unit.sensors:
        d = pre[s.name]
        segs = find_segments(tel.time_s, d.temp_C, tel.get("position"), d.usable,
                             temp_lsb_C=temperature_lsb_C(s.part))
        for it in all_holds:
            end = it["start_s"] + it["duration_s"]
            n = sum(1 for g in segs if it["start_s"] <= g.t_start_s < end)
            assert n <= 1, (s.name, it, n)
    rc, out, err = _check(capsys, tmp_path)
    assert rc == 2, out
    assert len(err.strip().splitlines()) == 1 and "does not cover the plan" in err
    gaps = out[out.index("GAPS"):]
    for L in plan.levels_C:
        assert f"level {L:g} degC" in gaps, (L, gaps)
