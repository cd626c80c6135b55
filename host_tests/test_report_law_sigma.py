"""The coil study's distance law with its uncertainty, also with two distances, and its
values printed to their 1-sigma (review of issue 19, 19b F4 and F5; docs/coil_study.md).

Two points leave no degree of freedom: the law goes through both, its 1-sigma is the
points' propagated plainly, and a flag says no misfit test checks it. The law's values
(at 30 cm, at the points, at the seed's 5 and 15 cm) and the distance r of the
interference table carry that 1-sigma (first order, with the covariance of ln K30 and n);
the checks below compare it with the closed form and with Monte Carlo draws of the points.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.cli import main
from generator.fit.coils import (CoilFit, CoilStudy, SensorCoilFit, StudyPoint,
                                 fit_distance_law, interference_table)
from generator.report.coil_study import coil_study_sections
from generator.report.document import pm, significant

# Monte Carlo: N draws give a sample standard deviation whose relative error is about
# 1/sqrt(2 N) (normal draws): 1.1 % at N = 4000. The points' relative errors are 1 %, so
# the first-order propagation is exact to O(1 %^2); 5 % is over 4 standard errors.
N_DRAWS = 4000
MC_REL_TOL = 0.05


def test_two_points_give_the_plain_propagation_and_are_flagged_unchecked():
    # the reviewer's case: 45540 +- 530 nT/A at 10 cm, 1970 +- 590 at 30 cm
    r, K, s = [10.0, 30.0], [45540.0, 1970.0], [530.0, 590.0]
    law = fit_distance_law(r, K, s)
    rel = np.array(s) / np.array(K)
    assert law.exponent == pytest.approx(np.log(K[0] / K[1]) / np.log(3.0))
    # n = ln(K1 / K2) / ln(r2 / r1): sigma_n = sqrt(s1^2 + s2^2) / ln(r2 / r1), s relative
    assert law.exponent_sigma == pytest.approx(np.hypot(*rel) / np.log(3.0), rel=1e-9)
    # the law goes through the 30 cm point: its value and 1-sigma there are the point's
    assert law.K_30cm_nT_per_A == pytest.approx(1970.0, rel=1e-9)
    assert law.K_30cm_sigma_nT_per_A == pytest.approx(590.0, rel=1e-9)
    assert law.chi2_per_dof is None and law.misfit() is None
    assert law.unchecked() == "unchecked: 2 points, no misfit test"
    assert law.unchecked() in law.flags(20.0)
    # a third distance: a misfit test exists, no 'unchecked'
    three = fit_distance_law(r + [20.0], K + [1970.0 * 1.5 ** 2.86], s + [100.0])
    assert three.unchecked() is None and three.unchecked() not in three.flags(20.0)


def test_law_through_two_points_has_their_values_and_sigma_at_the_points():
    r, K, s = np.array([5.0, 30.0]), np.array([200000.0, 1000.0]), np.array([3000.0, 40.0])
    law = fit_distance_law(r, K, s)
    for ri, Ki, si in zip(r, K, s):
        assert float(law.at(ri)) == pytest.approx(Ki, rel=1e-9)
        assert float(law.sigma_at(ri)) == pytest.approx(si, rel=1e-9)


@pytest.mark.parametrize("r_cm", [[10.0, 30.0], [5.0, 12.0, 30.0]])
def test_sigma_at_and_distance_match_monte_carlo(r_cm):
    """The law's 1-sigma at 5 cm (an extrapolation, where the covariance of ln K30 and n
    matters) and of the distance where it gives a measured |K|, against the spread of
    refits to points drawn with their 1-sigma (noiseless points: chi2 = 0, so no Birge
    scaling in the nominal law either)."""
    rng = np.random.default_rng(19)
    r = np.array(r_cm)
    K_true = 1500.0 * (30.0 / r) ** 2.8
    s = 0.01 * K_true
    K_meas, K_meas_sigma = 8000.0, 80.0          # the interference table's |K column|
    nominal = fit_distance_law(r, K_true, s)
    r0, r0_sigma = nominal.distance_cm(K_meas, K_meas_sigma)
    assert float(nominal.at(r0)) == pytest.approx(K_meas)
    at5, dist = [], []
    for _ in range(N_DRAWS):
        law = fit_distance_law(r, K_true + s * rng.standard_normal(r.size), s)
        at5.append(float(law.at(5.0)))
        dist.append(law.distance_cm(K_meas + K_meas_sigma * rng.standard_normal())[0])
    assert np.std(at5, ddof=1) == pytest.approx(float(nominal.sigma_at(5.0)), rel=MC_REL_TOL)
    assert np.std(dist, ddof=1) == pytest.approx(r0_sigma, rel=MC_REL_TOL)
    # the covariance matters: the 1-sigma at 5 cm is not the two independent ones summed
    C = np.asarray(nominal.cov_lnK30_n)
    assert abs(C[0, 1]) > 0.1 * np.sqrt(C[0, 0] * C[1, 1])


def test_significant_digits():
    assert significant(28077.5) == "28100"
    assert significant(0.32571, 2) == "0.33"
    assert significant(167.87) == "168"
    assert significant(5.0) == "5.00"


def _two_point_study(current_A=0.1):
    pts = []
    for panel, K10, K30 in ((0, 45540.0, 1970.0), (1, 82550.0, 2460.0)):
        for r, K, s in ((10.0, K10, 530.0), (30.0, K30, 600.0)):
            pts.append(StudyPoint("ist", "coil_x_A", panel, r, np.array([K, 0.0, 0.0]),
                                  np.array([s, s, s]), K, s, 60))
    laws = [fit_distance_law([10.0, 30.0], [p.K_norm_nT_per_A for p in pts if p.panel == pn],
                             [p.K_norm_sigma_nT_per_A for p in pts if p.panel == pn],
                             sensor="ist", coil="coil_x_A", panel=pn) for pn in (0, 1)]
    return CoilStudy(points=pts, laws=laws, sources=["two_dist.csv"])


def _rows(table, **match):
    h = table.header
    return [dict(zip(h, r)) for r in table.rows
            if all(dict(zip(h, r))[k] == v for k, v in match.items())]


def test_coil_study_section_prints_the_two_point_law_to_its_sigma(tmp_path):
    study = _two_point_study()
    analysis = SimpleNamespace(coil_study=lambda: study)
    (sec,) = coil_study_sections(None, analysis, tmp_path)
    laws, points = sec.tables
    for row in _rows(laws):
        w = study.law("ist", "coil_x_A", 0 if row["panel"] == "without panel" else 1)
        assert row["exponent n"] == (pm(w.exponent, w.exponent_sigma)
                                     + " (2 points, unchecked)")
        # the 30 cm figure is the 30 cm point's, to that point's 1-sigma
        p30 = next(p for p in study.points if p.panel == w.panel and p.distance_cm == 30.0)
        assert row["at 30 cm, 0.1 A nT"] == pm(0.1 * p30.K_norm_nT_per_A,
                                               0.1 * p30.K_norm_sigma_nT_per_A)
        assert " ± " in row["ratio to seed"]
        assert "unchecked: 2 points, no misfit test" in row["flags"]
        assert "no degree of freedom" in row["chi2/dof"]
    for row in _rows(points):   # the law through two points: its value at each is the point's
        assert row["law nT"] == row["at 0.1 A nT"] and " ± " in row["law nT"]
    factor = next(p for p in sec.paragraphs if p.startswith("Panel factor"))
    assert re.search(r"coil_x_A: \d\.\d+ ± \d\.\d+\.$", factor), factor


class _Unit:
    lab_field_nT = 47000.0

    def sensor(self, name):
        return SimpleNamespace(name=name, frame="boom")


def _coil_fit(K_norm, K_sigma):
    f = SensorCoilFit("ist", ("coil_x_A",), np.array([[K_norm], [0.0], [0.0]]),
                      np.array([[K_sigma], [K_sigma], [K_sigma]]), np.ones(3), 100, 2,
                      np.zeros((2, 3)))
    return CoilFit(coils=("coil_x_A",), sensors={"ist": f})


def test_interference_rows_carry_the_distance_and_values_sigma():
    study = _two_point_study()
    law = study.law("ist", "coil_x_A", 0)
    (row,) = interference_table(_Unit(), _coil_fit(10230.0, 290.0), study=study)
    r0, r0_sigma = law.distance_cm(10230.0, 290.0)
    assert row["distance_cm"] == pytest.approx(r0) and row["distance_sigma_cm"] == r0_sigma
    assert 0 < r0_sigma < r0
    for p, sig in row["at_cm_sigma"].items():
        assert sig == pytest.approx(float(law.sigma_at(p, 0.1)))
    # no study: the distance is assumed (no 1-sigma), the values carry K's alone
    (row,) = interference_table(_Unit(), _coil_fit(10230.0, 290.0))
    assert row["distance_source"] == "assumed" and row["distance_sigma_cm"] is None
    for p, sig in row["at_cm_sigma"].items():
        assert sig / row["at_cm"][p] == pytest.approx(290.0 / 10230.0)


def _keep_distances(path, keep_cm):
    lines = path.read_text().splitlines()
    h = next(i for i, l in enumerate(lines) if not l.startswith("#"))
    k = lines[h].split(",").index("coil_distance_cm")
    body = [l for l in lines[h + 1:] if float(l.split(",")[k]) in keep_cm]
    path.write_text("\n".join(lines[:h + 1] + body) + "\n")


def test_fit_report_two_distance_study_has_sigmas_and_the_flag(tmp_path):
    """magcal fit with a study at two distances (5 and 30 cm of the fast example): the law
    rows of both tables to their 1-sigma, r with its 1-sigma, the flag among the warnings,
    and no value printed to 0.1 nT without a 1-sigma in the coil sections."""
    paths = sim.make_example(tmp_path / "ex", seed=2, size="fast")
    _keep_distances(paths["coil_study"], {5.0, 30.0})
    out = tmp_path / "fit"
    assert main(["fit", str(paths["unit"]), str(paths["thermal_12pos"]), str(paths["coils"]),
                 str(paths["coil_study"]), "-o", str(out), "-q"]) == 0
    md = (out / "report.md").read_text()
    assert "coil study, law of coil_x_A without panel: unchecked: 2 points, no misfit test" in md
    inter = md.split("## Magnetorquer interference")[1].split("\n## ")[0]
    study = md.split("## Coil study")[1].split("\n## ")[0]
    law_rows = [l for l in inter.splitlines() if l.startswith("| law |")]
    assert law_rows
    for l in law_rows:
        cells = [c.strip() for c in l.strip("|").split("|")]
        assert "(2 points, unchecked)" in cells[5]
        assert all(" ± " in c for c in cells[7:10]), cells       # at 5, 15, 30 cm
    own = [l for l in inter.splitlines() if l.startswith("| mmc2 | coil_x_A |")]
    assert own and " ± " in own[0].split("|")[7]                  # r cm
    seed = [l for l in inter.splitlines() if l.startswith("| seed 000 |")]
    for l in seed:                         # 5 and 15 cm scaled by the law: its n's 1-sigma
        cells = [c.strip() for c in l.strip("|").split("|")]
        assert " ± " in cells[7] and " ± " in cells[8], cells
    # a value to 0.1 nT with no 1-sigma beside it (the fault reported) is gone from the
    # interference table and the study's tables (the coil term's |B| RMS table after the
    # interference table is not a law value)
    for sec in (inter.split("The coil term in the chain")[0], study):
        for l in sec.splitlines():
            if l.startswith("| ") and not l.startswith("| sensor"):
                for c in l.strip("|").split("|"):
                    c = c.strip()
                    assert not re.fullmatch(r"\d{3,}\.\d", c), (c, l)
