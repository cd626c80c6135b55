"""The report's summary and verdict (ICD section 4 [requirements]) and the per-level
temperature method on a campaign whose holds are long enough for the boards to settle.

The campaign: the example unit in the chamber, three levels held 40 min each with the
boards' time constants scaled to a third (200-400 s): several time constants per hold, so
the segment finder (10 min of steady temperature) finds every level in every position.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from generator.report import render_check
from generator.report.document import COLLAPSE_ROWS, Report, Section, Table, resolved
from generator.report.report import CampaignAnalysis, fit_report
from generator.report.summary import sensor_figures, summary_section, verdict

LEVELS_C = (-20.0, 10.0, 40.0)


@pytest.fixture(scope="module")
def long_holds(tmp_path_factory):
    from generator import pipeline
    from generator.campaign import simulate

    out = tmp_path_factory.mktemp("long_holds")
    unit = simulate.make_example_unit()
    unit_path = out / "unit.toml"
    simulate.write_unit_toml(unit, unit_path)
    with open(unit_path, "a", encoding="utf-8") as f:
        f.write("\n[requirements]\nfield_error_nT = 150.0\nangle_deg = 0.5\n")
    rng = np.random.default_rng(3)
    truth = simulate.random_truth(unit, rng)
    csv, _ = simulate.simulate_campaign("thermal_12pos", unit, truth, rng, out,
                                        levels_C=LEVELS_C, hold_s=2400.0,
                                        sample_period_s=20.0, board_tau_scale=1 / 3)
    cs = pipeline.fit(unit_path, [csv])
    rep_dir = out / "report"
    rep = fit_report(cs, rep_dir, [csv])
    return cs, csv, rep, rep.write(rep_dir)


def test_per_level_tables_show_every_level(long_holds):
    cs, csv, rep, html = long_holds
    for s in cs.unit.sensors:
        sec = next(x for x in rep.sections if x.title == f"Temperature dependence: {s.name}")
        per_level = [t for t in sec.tables if "per-level estimates" in t.caption]
        assert len(per_level) == 1, s.name
        temps = sorted(float(r[0]) for r in per_level[0].rows)
        # one row per chamber level, at the sensor's settled temperature: the board sits
        # within a few degC of the chamber (self-heating), never at another level
        assert len(temps) == len(LEVELS_C), (s.name, temps)
        assert all(abs(t - L) < 5.0 for t, L in zip(temps, LEVELS_C)), (s.name, temps)
        assert not any("constant-temperature level(s) found" in p for p in sec.paragraphs)
    prof = next(x for x in rep.sections if x.title.startswith("Chamber profile"))
    assert all(r[4] == len(LEVELS_C) for r in prof.tables[0].rows)
    assert render_check.problems(html) == []


def test_summary_numbers_agree_with_the_rms_bars_and_the_noise(long_holds):
    cs, csv, rep, html = long_holds
    an = CampaignAnalysis(cs, [csv])
    for s in cs.unit.sensors:
        f = sensor_figures(cs, an, s.name)
        label, n, before, after = an.rms_groups(s.name)["temperature"][-1]
        assert label == "all" and n == f["n"]
        assert math.isclose(f["norm_before_nT"], before, rel_tol=1e-12)
        assert math.isclose(f["norm_after_nT"], after, rel_tol=1e-12)
        # the angle between a vector and its reference with isotropic per-axis error
        # sigma is sigma_perp / |B|, sigma_perp^2 = 2 sigma^2 (two of the three axes):
        # RMS angle = sqrt(2) sigma / |B|. sigma from the calibrated per-axis residual;
        # 10 %: the RMS of ~4000 samples is known to ~1 %, the residual is not exactly
        # isotropic (axis scale errors differ by a few %)
        S = an.samples[s.name]
        r = cs.calibration(s.name).apply64(S.x, S.T) - S.ref
        sigma = math.sqrt(np.mean(r ** 2))
        expect = math.degrees(math.sqrt(2) * sigma / float(np.median(S.norm)))
        assert math.isclose(f["angle_after_deg"], expect, rel_tol=0.10), (s.name, f, expect)
        assert f["valid_fraction"] == 1.0      # every sample lies in the calibrated range


def test_valid_fraction_counts_the_samples_outside_the_range(long_holds):
    cs, csv, rep, html = long_holds
    an = CampaignAnalysis(cs, [csv])
    name = cs.unit.sensors[0].name
    T = np.asarray(an.tels[0].columns[f"{name}_temp_C"], float)
    v = cs.sensors[name]
    saved = {k: v[k] for k in ("t_max_C", "temp_margin_C")}
    v["t_max_C"] = 15.0               # the chain keeps valid up to t_max + margin
    v["temp_margin_C"] = 2.0
    try:
        f = sensor_figures(cs, an, name)
    finally:
        v.update(saved)
    assert f["valid_fraction"] == pytest.approx(np.mean(T <= 17.0), abs=0.5 / len(T))
    assert 0.3 < f["valid_fraction"] < 0.9


def test_verdict_against_the_requirements(long_holds):
    cs, csv, rep, html = long_holds
    sec = rep.sections[0]
    assert sec.title == "Summary and verdict"
    rows = {r[0]: r for r in sec.tables[0].rows}
    for s in cs.unit.sensors:
        after, angle, text = rows[s.name][4], rows[s.name][6], rows[s.name][-1]
        ok = after <= 150.0 and angle <= 0.5
        assert text.startswith("MEETS" if ok else "FAILS"), (s.name, after, angle, text)
    # the MPU-9255s (250 nT noise per axis) cannot meet 150 nT; the MMC5883s (40 nT) can
    parts = {s.name: s.part for s in cs.unit.sensors}
    assert all(rows[n][-1].startswith("FAILS") for n, p in parts.items() if p == "MPU-9255")
    assert all(rows[n][-1].startswith("MEETS") for n, p in parts.items() if p == "MMC5883MA")


def test_verdict_rules():
    req = {"field_error_nT": 150.0, "angle_deg": 0.5}
    assert verdict({"norm_after_nT": 100.0, "angle_after_deg": 0.1}, req) == ("MEETS", [])
    v, why = verdict({"norm_after_nT": 200.0, "angle_after_deg": 0.1}, req)
    assert v == "FAILS" and "200.0 nT > 150 nT" in why[0]
    v, why = verdict({"norm_after_nT": 100.0}, req)       # no reference vectors
    assert v == "NOT ASSESSED" and "angle" in why[0]
    assert verdict({"norm_after_nT": 100.0}, {}) == ("no requirements given", [])


def test_no_requirements_no_verdict(long_holds):
    cs, csv, rep, html = long_holds
    import dataclasses
    from types import SimpleNamespace
    # the same fit from a unit file without [requirements] (what summary_section reads)
    cs2 = SimpleNamespace(unit=dataclasses.replace(cs.unit, extra={}), sensors=cs.sensors,
                          fit_info=dict(cs.fit_info, unit_file=None))
    sec = summary_section(cs2, None)
    assert sec.paragraphs[0] == "Verdict: none (no requirements given)."
    assert all(r[-1] == "no requirements given" for r in sec.tables[0].rows)


def test_numbers_to_their_resolution_and_long_tables_collapsed(tmp_path):
    assert resolved(-4.466e-15, 0.625) == "0"
    assert resolved(-1022.777, 0.625) == "-1022.8"
    assert resolved(12.0, 6.25) == "12"
    rep = Report("t", [Section("s", [], [Table(["a"], [[k] for k in range(COLLAPSE_ROWS)]),
                                         Table(["b"], [[k] for k in range(COLLAPSE_ROWS + 1)])])])
    html = rep.html()
    assert html.count("<details>") == 1
    assert html.index("<details>") > html.index('id="table-1"')
    assert "(31 rows" in html and "(31 rows" in rep.markdown()
