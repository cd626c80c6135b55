"""`magcal plan` (the ground-test program) and `magcal check` (does a campaign cover it?).

check must pass on the shared thermal campaign and find the gaps in campaigns made from it
by removing positions or a temperature plateau (rows filtered into tmp_path), and in
simulated campaigns whose holds are too short; its predicted coefficient uncertainty must
agree with what a fit actually gets.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from generator.campaign import plan as P
from generator.verbs.plan import write_plan
from generator.campaign.check import (B_NAMES, M_NAMES, MIN_DIRECTION_EIG, MIN_ICOSA_FRACTION,
                             direction_coverage, poly_covariance, up_axis_and_heading)
from generator.cli import main
from generator.fit.thermal import reference_fit
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------
def filter_rows(src, dst, keep):
    """Copy a telemetry CSV keeping comment lines, the header and the rows for which
    keep(time_s, position) is true."""
    lines = src.read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    header = lines[h].split(",")
    it, ip = header.index("time_s"), header.index("position")
    body = [line for line in lines[h + 1:]
            if keep(float(line.split(",")[it]), int(float(line.split(",")[ip])))]
    dst.write_text("\n".join(lines[:h + 1] + body) + "\n")
    return dst


def hold_windows(csv_path, unit):
    """(position, level index within the position) of every row of the shared thermal
    campaign: the chamber steps through its levels in equal windows per position."""
    tel = read_telemetry(csv_path, unit)
    pos = tel.columns["position"].astype(int)
    t = tel.time_s
    window = np.zeros(len(t), int)
    for p in np.unique(pos):
        m = pos == p
        t0, t1 = t[m].min(), t[m].max() + (t[1] - t[0])
        window[m] = np.floor((t[m] - t0) / ((t1 - t0) / 6)).astype(int)
    return dict(zip(t.tolist(), window.tolist()))


def run_check(capsys, *args):
    rc = main(["check", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def fm1_unit(fm1_dir):
    return load_unit(fm1_dir / "unit.toml")


@pytest.fixture(scope="module")
def default_plan_json(tmp_path_factory, fm1_dir):
    out = tmp_path_factory.mktemp("plan")
    assert main(["plan", str(fm1_dir / "unit.toml"), "-o", str(out), "-q"]) == 0
    return out / "plan.json"


# ---------------------------------------------------------------------------------------
# plan
# ---------------------------------------------------------------------------------------
def test_positions_cover_every_axis_up_twice_and_match_the_simulator():
    from generator.campaign.simulate import twelve_positions as sim_positions

    F, inc = 51540.0, 68.0
    pos = P.positions(F, inc)
    assert len(pos) == 12
    ups = [p.up for p in pos]
    assert sorted(set(ups)) == sorted(f"{s}{a}" for s in "+-" for a in "XYZ")
    assert all(ups.count(u) == 2 for u in set(ups))
    for p in pos:
        B = np.array(p.expected_field_body_nT)
        assert np.linalg.norm(B) == pytest.approx(F, rel=1e-12)
        k = "XYZ".index(p.up[1])
        up = np.zeros(3)
        up[k] = 1.0 if p.up[0] == "+" else -1.0
        # the field dips: its component along the up axis is -F sin(I)
        assert B @ up == pytest.approx(-F * math.sin(math.radians(inc)), abs=1e-6)
        R = np.array(p.R_body_to_ned)
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        # the recorded up axis of this field is the planned one
        assert up_axis_and_heading(B)[0] == p.up
    # the same two headings per up axis, 90 deg apart
    for u in set(ups):
        h = [up_axis_and_heading(p.expected_field_body_nT)[1] for p in pos if p.up == u]
        assert abs((h[0] - h[1] + 180) % 360 - 180) == pytest.approx(90.0, abs=1e-6)
    for R_plan, R_sim in zip(P.twelve_positions(), sim_positions()):
        assert np.allclose(R_plan, R_sim)


def test_holds_follow_the_settling_formula(fm1_unit):
    plan = P.make_plan(fm1_unit, board_tau_min=12.0, settle_tol_C=0.25,
                       levels_C=(-30.0, 0.0, 20.0, 60.0), sample_period_s=2.0,
                       samples_per_segment=90, ramp_C_per_min=2.0)
    tau = 12.0 * 60
    prev = None
    for i, s in enumerate(plan.steps):
        if i == 0:   # entered from room or from the last level, whichever is farther
            assert s.step_C == max(abs(-30.0 - 25.0), abs(-30.0 - 60.0))
        else:
            assert s.step_C == abs(s.level_C - prev)
        need = tau * math.log(s.step_C / 0.25) + 90 * 2.0
        assert s.hold_s >= need and s.hold_s - need < 60.0
        assert s.hold_s % 60 == 0
        assert s.ramp_s == pytest.approx(abs(s.level_C - (prev if i else 25.0)) / 2.0 * 60)
        prev = s.level_C
    per_pos = plan.reposition_s + sum(s.ramp_s + s.hold_s for s in plan.steps) + \
        plan.return_ramp_s
    assert plan.total_duration_s == pytest.approx(12 * per_pos)
    # the first-order model over the whole program: every recording window is settled
    chk = P.window_check(plan)
    assert set(chk) == {-30.0, 0.0, 20.0, 60.0}
    assert all(v["max_dev_C"] <= 0.25 for v in chk.values())


def test_holds_planned_for_a_faster_board_do_not_settle_a_slower_one(fm1_unit):
    """The hold formula matters: a plan made for tau = 5 min leaves a 20 min board
    outside the tolerance in its recording windows."""
    short = P.make_plan(fm1_unit, board_tau_min=5.0)
    real = P.make_plan(fm1_unit, board_tau_min=20.0)
    short.board_tau_s = real.board_tau_s          # the boards are slower than assumed
    chk = P.window_check(short)
    assert max(v["max_dev_C"] for v in chk.values()) > 5 * short.settle_tolerance_C


def test_plan_cli_writes_document_profile_and_figures(tmp_path, fm1_dir, capsys):
    out = tmp_path / "plan"
    rc = main(["plan", str(fm1_dir / "unit.toml"), "-o", str(out), "--json",
               "--levels", "-10", "20", "50", "--board-tau-min", "10",
               "--inclination-deg", "65", "--lab-field-nT", "50000"])
    stdout, err = capsys.readouterr()
    assert rc == 0
    js = json.loads(stdout)
    assert js["levels_C"] == [-10.0, 20.0, 50.0] and js["board_tau_s"] == 600.0
    assert len(js["positions"]) == 12 and js["inclination_deg"] == 65.0
    for name in ("plan.html", "plan.md", "plan.json", "plan_positions.png", "plan_profile.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    # the machine-readable profile reads back for check
    prof = P.load_profile(out / "plan.json")
    assert prof.levels_C == [-10.0, 20.0, 50.0]
    assert [p["number"] for p in prof.positions] == list(range(1, 13))
    assert np.allclose(prof.positions[0]["expected_field_body_nT"],
                       js["positions"][0]["expected_field_body_nT"])
    # the document names every level and every position's expected field
    md = (out / "plan.md").read_text()
    for p in js["positions"]:
        assert f"| {p['number']} | {p['up']} |" in md
    html = (out / "plan.html").read_text()
    assert 'src="plan_positions.png"' in html and 'src="plan_profile.png"' in html
    # holds in the JSON agree with the formula for the chosen tau
    for s in js["steps"]:
        assert s["hold_s"] >= 600.0 * math.log(s["step_C"] / 0.5) + s["record_s"]
    # chamber program: holds with recording windows inside them, in time order
    prog = js["chamber_program"]
    starts = [i["start_s"] for i in prog]
    assert starts == sorted(starts)
    for i in prog:
        if i["action"] == "hold":
            assert i["start_s"] <= i["record_from_s"] < i["record_to_s"] <= \
                i["start_s"] + i["duration_s"] + 1e-9
    assert prog[-1]["start_s"] + prog[-1]["duration_s"] == pytest.approx(js["total_duration_s"])


@pytest.mark.parametrize("extra,fragment", [
    (["--levels", "10", "10"], "repeated temperature level"),
    (["--board-tau-min", "-3"], "board time constant"),
    (["--sample-period-s", "0"], "sample period"),
])
def test_plan_bad_input_exits_2(tmp_path, fm1_dir, capsys, extra, fragment):
    rc = main(["plan", str(fm1_dir / "unit.toml"), "-o", str(tmp_path / "p"), *extra])
    _, err = capsys.readouterr()
    assert rc == 2
    assert fragment in err and len(err.strip().splitlines()) == 1


def test_plan_needs_a_lab_field(tmp_path, capsys):
    from generator.campaign.simulate import make_example_unit, write_unit_toml
    from dataclasses import replace

    unit = replace(make_example_unit(), lab_field_nT=None)
    write_unit_toml(unit, tmp_path / "u.toml")
    assert main(["plan", str(tmp_path / "u.toml"), "-o", str(tmp_path / "p")]) == 2
    assert "--lab-field-nT" in capsys.readouterr().err
    assert main(["plan", str(tmp_path / "u.toml"), "-o", str(tmp_path / "p"), "-q",
                 "--lab-field-nT", "49000"]) == 0


def test_load_profile_rejects_other_files(tmp_path):
    from generator.errors import InputError
    bad = tmp_path / "x.json"
    bad.write_text('{"format": "magcal-coefficients"}')
    with pytest.raises(InputError, match="not a magcal-test-plan"):
        P.load_profile(bad)
    bad.write_text('{"format": "magcal-test-plan", "format_version": 1, "positions": '
                   '[{"number": 1, "expected_field_body_nT": [1, 2]}], "levels_C": [0], '
                   '"samples_per_segment": 5, "sample_period_s": 1}')
    with pytest.raises(InputError, match="expected_field_body_nT"):
        P.load_profile(bad)


# ---------------------------------------------------------------------------------------
# check: the shared campaign and campaigns with gaps
# ---------------------------------------------------------------------------------------
def test_check_passes_on_the_shared_thermal_campaign(fm1_dir, capsys):
    rc, out, err = run_check(capsys, fm1_dir / "unit.toml", fm1_dir / "thermal_12pos.csv",
                             "--json", "-q")
    res = json.loads(out)
    assert rc == 0, res["gaps"]
    assert res["adequate"] and res["gaps"] == []
    assert err.strip() == "magcal check: campaign covers the plan"
    assert all(c["status"] == "ok" for c in res["cells"])
    assert len(res["cells"]) == 12 * 6
    for name, s in res["sensors"].items():
        assert s["prediction"]["poorly_determined"] == [], name
        assert s["coverage"]["static_positions"]["eig"][0] > 0.2
    # every signed axis up at two headings
    assert sorted(res["up_axes"]) == sorted(f"{s}{a}" for s in "+-" for a in "XYZ")
    assert all(len(v) == 2 for v in res["up_axes"].values())


def test_check_names_missing_positions_and_undetermined_coefficients(fm1_dir, fm1_unit,
                                                                      tmp_path, capsys):
    keep = {1, 5, 9}
    f = filter_rows(fm1_dir / "thermal_12pos.csv", tmp_path / "three_positions.csv",
                    lambda t, p: p in keep)
    rc, out, err = run_check(capsys, fm1_dir / "unit.toml", f, "-q")
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "does not cover the plan" in err
    missing = sorted(set(range(1, 13)) - keep)
    for p in missing:
        assert f"position {p}: not recorded" in out
    assert "positions 2-4, 6-8, 10-12 missing" in err
    # three field directions cannot determine W and b: every sensor says so
    for s in fm1_unit.sensors:
        line = next(g for g in out.splitlines() if g.strip().startswith(f"- {s.name}: coef"))
        assert "undetermined" in line and "distinct reference field direction" in line
    # the signed axes that are never up are named
    for axis in ("+Z", "-X", "+Y"):
        assert f"no position with body {axis} up" in out


def test_check_names_the_coefficients_a_weaker_campaign_leaves_poor(fm1_dir, fm1_unit,
                                                                    tmp_path, capsys):
    """Positions 1, 2, 5, 6 only: the fit is possible, but the prediction must name the
    coefficients above the limits, and they must be those whose predicted 1-sigma is
    above the limits (checked against the numbers in the JSON)."""
    f = filter_rows(fm1_dir / "thermal_12pos.csv", tmp_path / "four.csv",
                    lambda t, p: p in (1, 2, 5, 6))
    rc, out, _ = run_check(capsys, fm1_dir / "unit.toml", f, "--json", "-q",
                           "--limit-b-nT", "20", "--limit-m", "5e-4")
    res = json.loads(out)
    assert rc == 2
    flagged = {}
    for name, s in res["sensors"].items():
        pred = s["prediction"]
        for c in B_NAMES + M_NAMES:
            sig = pred["sigma_max"][c]["sigma"]
            limit = 20.0 if c.startswith("b") else 5e-4
            assert (c in pred["poorly_determined"]) == (sig is None or sig > limit), (name, c)
        if pred["poorly_determined"]:
            flagged[name] = pred["poorly_determined"]
            assert any(g.startswith(f"{name}: coefficients poorly determined") and
                       pred["poorly_determined"][0] in g for g in res["gaps"])
    # the noisy MPU-9255s are hit, the MMC5883s (6x less noise) are not
    assert {"mpu1", "mpu2", "mpu3"} <= set(flagged)
    assert "mmc1" not in flagged and "mmc2" not in flagged


@pytest.mark.parametrize("window,level", [(5, 55), (2, 10)])
def test_check_names_a_removed_temperature_plateau(fm1_dir, fm1_unit, tmp_path, capsys,
                                                   default_plan_json, window, level):
    win = hold_windows(fm1_dir / "thermal_12pos.csv", fm1_unit)
    f = filter_rows(fm1_dir / "thermal_12pos.csv", tmp_path / f"no_{level}.csv",
                    lambda t, p: win[t] != window)
    rc, out, err = run_check(capsys, fm1_dir / "unit.toml", f, "--plan", default_plan_json,
                             "--json", "-q", "--min-samples", "100")
    res = json.loads(out)
    assert rc == 2
    gap = [g for g in res["gaps"] if g.startswith(f"level {level} degC")]
    assert len(gap) == 1, res["gaps"]
    assert f"level {level} degC" in err
    # the other levels are all settled everywhere
    for c in res["cells"]:
        assert (c["status"] == "ok") == (c["level_C"] != level)
    if level == 55:      # the top of the range is gone: the calibration would be clamped
        assert "never reached" in gap[0]
        top = max(s["temperature_range_C"][1] for s in res["sensors"].values())
        assert top < 55.0 - res["plan"]["level_match_tolerance_C"]
        assert f"..{top:.1f} degC" in gap[0]
    else:                # ramps pass through 10 degC, it just never settles
        assert "never settled" in gap[0]
    # positions are numbered differently from this plan in the shared data: a note, no gap
    assert any("numbered differently" in n for n in res["notes"])


def test_check_with_holds_too_short_for_the_boards(tmp_path, capsys):
    """A simulated campaign whose holds are shorter than the boards need: check names the
    unsettled levels; the same campaign with the plan's holds passes against that plan."""
    from generator.campaign.simulate import make_example_unit, random_truth, simulate_campaign
    from generator.campaign.simulate import write_unit_toml

    unit = make_example_unit()
    write_unit_toml(unit, tmp_path / "unit.toml")
    truth = random_truth(unit, np.random.default_rng(3))
    tau_scale = 240.0 / max(truth.board_tau_s.values())     # boards: tau <= 4 min
    plan = P.make_plan(unit, levels_C=(-20.0, 25.0, 55.0), board_tau_min=4.0,
                       sample_period_s=20.0, samples_per_segment=40)
    write_plan(plan, tmp_path / "plan")
    hold = max(s.hold_s + s.ramp_s for s in plan.steps)
    good, _ = simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(4),
                                tmp_path, name="good", levels_C=plan.levels_C, hold_s=hold,
                                sample_period_s=20.0, board_tau_scale=tau_scale)
    rc, out, _ = run_check(capsys, tmp_path / "unit.toml", good, "--plan",
                           tmp_path / "plan" / "plan.json", "--json", "-q")
    res = json.loads(out)
    assert rc == 0, res["gaps"]
    assert not any("numbered differently" in n for n in res["notes"])
    assert all(p["angle_to_plan_deg"] < 1.0 for p in res["positions"])
    # holds of 6 min for boards with a 12-24 min time constant
    short, _ = simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(4),
                                 tmp_path, name="short", levels_C=plan.levels_C, hold_s=360.0,
                                 sample_period_s=20.0, board_tau_scale=3 * tau_scale)
    rc, out, err = run_check(capsys, tmp_path / "unit.toml", short, "--plan",
                             tmp_path / "plan" / "plan.json", "--json", "-q")
    res = json.loads(out)
    assert rc == 2
    gaps = {L: next((g for g in res["gaps"] if g.startswith(f"level {L:g} degC")), "")
            for L in plan.levels_C}
    # the boards pass through room temperature but never settle there, and never get near
    # the extremes: the calibration would be clamped to what they reached
    assert "never settled" in gaps[25.0]
    assert "never reached" in gaps[-20.0] and "never reached" in gaps[55.0]
    assert all(c["status"] != "ok" for c in res["cells"])
    assert {"not settled"} <= {c["status"] for c in res["cells"]}
    assert any("the cubic is extrapolated" in g for g in res["gaps"])


def test_check_bad_input_exits_2(fm1_dir, tmp_path, capsys):
    rc, _, err = run_check(capsys, fm1_dir / "unit.toml", tmp_path / "nope.csv")
    assert rc == 2 and "nope.csv" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "p.json").write_text("{")
    rc, _, err = run_check(capsys, fm1_dir / "unit.toml", fm1_dir / "thermal_12pos.csv",
                           "--plan", tmp_path / "p.json")
    assert rc == 2 and "p.json" in err
    rc, _, err = run_check(capsys, fm1_dir / "unit.toml", fm1_dir / "thermal_12pos.csv",
                           "--limit-m", "-1")
    assert rc == 2 and "--limit-m" in err


def test_check_rotation_campaign_is_judged_on_sphere_coverage(fm1_dir, tmp_path, capsys):
    rc, out, _ = run_check(capsys, fm1_dir / "unit.toml", fm1_dir / "rotation.csv",
                           "--json", "-q")
    res = json.loads(out)
    assert rc == 0, res["gaps"]
    cov = res["sensors"]["mmc1"]["coverage"]["moving"]
    assert cov["icosa_fraction"] >= 0.9 and cov["eig"][0] > 0.2
    # the first 20 s only: a small cap of orientations
    lines = (fm1_dir / "rotation.csv").read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    (tmp_path / "cap.csv").write_text("\n".join(lines[:h + 1 + 200]) + "\n")
    rc, out, _ = run_check(capsys, fm1_dir / "unit.toml", tmp_path / "cap.csv", "--json", "-q")
    res = json.loads(out)
    assert rc == 2
    assert any("sphere cells" in g for g in res["gaps"])


# ---------------------------------------------------------------------------------------
# the prediction itself
# ---------------------------------------------------------------------------------------
def test_covariance_matches_the_reference_fit_and_the_prediction_matches_the_fit(fm1_dir,
                                                                                 fm1_unit):
    tel = read_telemetry(fm1_dir / "thermal_12pos.csv", fm1_unit)
    pre = preprocess(tel, fm1_unit)
    ref = np.stack([tel.columns[f"ref_{c}_nT"] for c in "xyz"], 1)
    for name in ("mmc1", "mpu1"):
        sd = pre[name]
        ok = sd.usable
        x, T, B = sd.field_frame_nT[ok], sd.temp_C[ok], ref[ok]
        b, M, info = reference_fit(x, B, T, 3)
        rng = (float(T.min()), float(T.max()))
        # Gauss-Newton covariance at the fit == the fit's own (propagated) 1-sigma from the
        # readings' noise (the fit adds the temperature reporting error on top: >= it)
        pc = poly_covariance(x, T, B, degree=3, t_range_C=rng, b_poly=b, M_poly=M)
        bs, Ms = pc.poly_sigma()
        assert np.allclose(bs, info["b_poly_sigma_noise_nT"], rtol=0.1)
        assert np.allclose(Ms, info["M_poly_sigma_noise"], rtol=0.1)
        assert np.all(info["M_poly_sigma"] >= info["M_poly_sigma_noise"] * (1 - 1e-9))
        # the a-priori prediction (design only, the unit's noise figure) is the fit's
        # uncertainty scaled by noise / residual: it predicts what the fit then gets
        pred = poly_covariance(x, T, B, degree=3, t_range_C=rng, b_poly=b[:1], M_poly=M[:1],
                               noise_nT=fm1_unit.sensor(name).noise_nT, noise_free=True)
        ratio = fm1_unit.sensor(name).noise_nT / np.mean(info["residual_sigma_nT"])
        pb, _ = pred.poly_sigma()
        assert np.allclose(pb / info["b_poly_sigma_noise_nT"], ratio, rtol=0.15)
        # subsampling the rows keeps the information
        sub = poly_covariance(x, T, B, degree=3, t_range_C=rng, b_poly=b, M_poly=M,
                              max_rows=5000)
        assert np.allclose(sub.poly_sigma()[0], bs, rtol=0.1)


def test_three_directions_leave_the_vector_fit_undetermined():
    rng = np.random.default_rng(0)
    dirs = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]) * 50000
    B = np.repeat(dirs, 100, axis=0)
    x = B + rng.normal(0, 30, B.shape) + [1000, -2000, 500]
    T = np.full(len(x), 20.0)
    pc = poly_covariance(x, T, B, degree=0, t_range_C=(20, 20), noise_nT=30,
                         b_poly=[[1000, -2000, 500]], noise_free=True)
    assert np.all(np.isinf(pc.sigma_at([20.0])))
    # a fourth direction off the plane of... any three: determined
    B4 = np.vstack([B, np.repeat([[30000.0, 30000.0, 30000.0]], 100, axis=0)])
    x4 = B4 + rng.normal(0, 30, B4.shape) + [1000, -2000, 500]
    pc = poly_covariance(x4, np.full(len(x4), 20.0), B4, degree=0, t_range_C=(20, 20),
                         noise_nT=30, b_poly=[[1000, -2000, 500]], noise_free=True)
    s = pc.sigma_at([20.0])[0]
    assert np.all(np.isfinite(s)) and s[:3].max() < 30


def test_direction_coverage():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(5000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    full = direction_coverage(u)
    assert full["icosa_fraction"] == 1.0 and full["eig"][0] > 0.3
    cap = direction_coverage(u[u[:, 2] > 0.8])          # a 37 deg cap
    assert cap["icosa_fraction"] <= 0.4 and cap["eig"][0] < MIN_DIRECTION_EIG
    # a hemisphere: u u^T cannot tell it from the sphere, the cells can
    half = direction_coverage(u[u[:, 2] > 0])
    assert half["eig"][0] > 0.3
    assert 0.4 <= half["icosa_fraction"] < MIN_ICOSA_FRACTION


def test_check_counts_saturated_and_missing_samples(fm1_dir, tmp_path, capsys):
    lines = (fm1_dir / "thermal_12pos.csv").read_text().splitlines()
    h = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    header = lines[h].split(",")
    ip, isat, imiss = (header.index("position"), header.index("mpu1_x"),
                       header.index("mmc2_set_y"))
    out, n_sat, n_miss = lines[:h + 1], 0, 0
    for k, line in enumerate(lines[h + 1:]):
        cells = line.split(",")
        if int(cells[ip]) == 3 and n_sat < 40:
            cells[isat] = "32760"              # the AK8963's rail: saturated
            n_sat += 1
        if k % 12 == 0:
            cells[imiss] = ""                  # an empty cell: missing
            n_miss += 1
        out.append(",".join(cells))
    (tmp_path / "damaged.csv").write_text("\n".join(out) + "\n")
    rc, stdout, _ = run_check(capsys, fm1_dir / "unit.toml", tmp_path / "damaged.csv",
                              "--json", "-q")
    res = json.loads(stdout)
    assert rc == 2
    assert res["sensors"]["mpu1"]["excluded"]["saturated"] == n_sat
    assert res["sensors"]["mmc2"]["excluded"]["missing"] == n_miss
    assert any(g.startswith(f"mpu1: {n_sat} saturated samples (positions 3)")
               for g in res["gaps"])
    assert any(g.startswith(f"mmc2: {n_miss} of 36000 samples missing") for g in res["gaps"])
    p3 = next(p for p in res["positions"] if p["position"] == 3)
    assert p3["saturated"]["mpu1"] == n_sat and p3["saturated"]["mmc1"] == 0
    assert sum(p["missing"]["mmc2"] for p in res["positions"]) == n_miss
    # the saturated samples open position 3's cycle, at room temperature (the 25 degC cell)
    cell = next(c for c in res["cells"] if c["position"] == 3 and c["level_C"] == 25.0)
    assert cell["sensors"]["mpu1"]["saturated"] == n_sat
    assert all(c["sensors"]["mpu1"]["saturated"] == 0 for c in res["cells"]
               if (c["position"], c["level_C"]) != (3, 25.0))
