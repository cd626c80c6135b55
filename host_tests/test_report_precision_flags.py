"""Review of issue 19, report side: numbers to their sigma (document.pm, the one helper),
the coil-study flags (chi2/dof beyond its quantile, a law used outside its measured
distances) in the tables and the summary's warnings, and the render check's refusal of
numpy reprs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from generator.fit.coils import CHI2_QUANTILE, CoilStudy, DistanceLaw, fit_distance_law
from generator.report import render_check
from generator.report.document import Report, Section, Table, pm
from generator.report.summary import coil_study_warnings


# ---- pm: sigma to 2 significant digits, the value to the same decimal place -------------
@pytest.mark.parametrize("value, sigma, text", [
    (1234.5678, 45.6, "1235 ± 46"),
    (2696.0, 107.0, "2700 ± 110"),           # sigma >= 100: rounded to its 2nd digit
    (362513.0, 97.0, "362513 ± 97"),
    (1.061063, 0.000141, "1.06106 ± 0.00014"),
    (0.0123, 0.004, "0.0123 ± 0.0040"),
    (-1e-5, 0.02, "0.000 ± 0.020"),           # rounded to zero: no '-0.000'
    (1.234e-6, 3.2e-8, "1.234e-06 ± 0.032e-06"),
    (1.5e8, 2.0e5, "1.5000e+08 ± 0.0020e+08"),
])
def test_pm_rounds_to_the_sigma(value, sigma, text):
    assert pm(value, sigma) == text


def test_pm_sign_and_numpy_scalars():
    assert pm(np.float64(0.8451), np.float64(0.0071), sign=True) == "+0.8451 ± 0.0071"
    assert pm(np.float32(-2.5), np.float32(0.25)) == "-2.50 ± 0.25"
    assert pm(3.0, None) == "3"


# ---- the distance law's flags ----------------------------------------------------------
R_CM = np.array([10.0, 12.0, 15.0, 18.0, 20.0])


def _law(scatter, seed=1):
    K = 1000.0 * (30.0 / R_CM) ** 3
    rng = np.random.default_rng(seed)
    return fit_distance_law(R_CM, K * np.exp(scatter * rng.normal(size=R_CM.size)), K * 0.01,
                            sensor="mag", coil="coil_x_A")


def test_law_records_its_span_and_flags_extrapolation():
    law = _law(0.01)
    assert (law.r_min_cm, law.r_max_cm) == (10.0, 20.0)
    assert law.extrapolated(10.0) is None and law.extrapolated(20.0) is None
    assert law.extrapolated(15.0) is None
    for r in (5.0, 30.0):
        assert "outside the measured 10..20 cm" in law.extrapolated(r)


def test_chi2_flag_at_the_quantile_of_the_laws_dof():
    lim = chi2.ppf(CHI2_QUANTILE, R_CM.size - 2) / (R_CM.size - 2)
    tight, loose = _law(0.01), _law(0.2)          # claimed 1 %: 1 % and 20 % scatter
    assert tight.chi2_limit_per_dof() == pytest.approx(lim)
    assert loose.chi2_per_dof > lim and "chi2/dof" in loose.misfit()
    # at the limit and just above it (the same law otherwise)
    kw = {k: getattr(tight, k) for k in ("sensor", "coil", "panel", "n_points", "exponent",
                                         "exponent_sigma", "K_30cm_nT_per_A",
                                         "K_30cm_sigma_nT_per_A", "r_min_cm", "r_max_cm")}
    assert DistanceLaw(chi2_per_dof=lim, **kw).misfit() is None
    assert DistanceLaw(chi2_per_dof=lim * 1.001, **kw).misfit() is not None
    # two points: no dof, no chi2 flag, but flagged unchecked (nothing tests the law)
    two = fit_distance_law([10.0, 20.0], [8000.0, 1000.0], [10.0, 10.0])
    assert two.misfit() is None and two.flags(15.0) == [two.unchecked()]


def test_summary_warns_of_the_flags_at_the_points_the_report_uses():
    law = _law(0.2)                                 # misfit, measured 10..20 cm
    study = CoilStudy(points=[], laws=[law], sources=["s.csv"])
    analysis = SimpleNamespace(coil_study=lambda: study, coil_interference=lambda c: None,
                               tels=[])
    warns = coil_study_warnings(analysis)
    assert all(w[0] == "mag" for w in warns)
    text = " | ".join(w[1] for w in warns)
    assert "chi2/dof" in text and "extrapolated to 30 cm" in text
    assert "extrapolated to 5 cm" not in text       # no coil campaign: 30 cm only
    # with a coil campaign: the seed's 5 cm, and a sensor's distance beyond the span
    rows = [{"sensor": "mag", "coil": "coil_x_A", "law": law, "distance_cm": 15.0},
            {"sensor": "far", "coil": "coil_x_A", "law": law, "distance_cm": 41.0},
            {"sensor": "far", "coil": "coil_y_A", "law": None, "distance_cm": None}]
    analysis.coil_interference = lambda c: (None, None, rows)
    text = " | ".join(f"{w[0]}: {w[1]}" for w in coil_study_warnings(analysis))
    assert "extrapolated to 5 cm" in text and "far: coil_x_A" in text and "41 cm" in text
    assert "coil_y_A" not in text and "to 15 cm" not in text
    assert coil_study_warnings(SimpleNamespace(coil_study=lambda: None, tels=[])) == []
    assert coil_study_warnings(None) == []


# ---- the render check refuses numpy reprs ----------------------------------------------
@pytest.mark.parametrize("text", ["b = np.float64(1.2) nT", "k = array([1., 2.])",
                                  "x (np.int64(3), np.int64(4))"])
def test_render_check_fails_on_a_numpy_repr(tmp_path, text):
    html = Report("t", [Section("s", [text], [Table(["a"], [[1.0]])])]).write(tmp_path)
    probs = render_check.problems(html)
    assert len(probs) >= 1 and all("numpy repr" in p for p in probs)


def test_render_check_passes_plain_numbers(tmp_path):
    html = Report("t", [Section("s", ["n = 2.9971 ± 0.0035, an array of 12 points"],
                                [Table(["a"], [[1.0]])])]).write(tmp_path)
    assert render_check.problems(html) == []


def test_coil_study_section_shows_the_span_and_flags(tmp_path):
    """The law table of the report's coil-study section: measured span, chi2/dof beside
    its quantile, and the flags (here: misfit, and 30 cm outside the measured 10..20 cm)."""
    from generator.fit.coils import StudyPoint
    from generator.report.coil_study import coil_study_sections

    law = _law(0.2)
    K = 1000.0 * (30.0 / R_CM) ** 3
    points = [StudyPoint("mag", "coil_x_A", 0, float(r), np.array([k, 0.0, 0.0]),
                         np.array([0.01 * k] * 3), float(k), 0.01 * float(k), 60)
              for r, k in zip(R_CM, K)]
    study = CoilStudy(points=points, laws=[law], sources=["s.csv"])
    cs = SimpleNamespace(unit=None)
    [sec] = coil_study_sections(cs, SimpleNamespace(coil_study=lambda: study), tmp_path)
    table = sec.tables[0]
    row = dict(zip(table.header, table.rows[0]))
    assert row["measured cm"] == "10..20"
    assert f"(99 %: {law.chi2_limit_per_dof():.2f})" in row["chi2/dof"]
    assert "chi2/dof" in row["flags"] and "extrapolated to 30 cm" in row["flags"]
    assert " ± " in row["exponent n"] and "np." not in repr(table.rows)
    assert (tmp_path / sec.figures[0][0]).stat().st_size > 10000
