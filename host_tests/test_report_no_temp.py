"""Issue 15: the fit report, its JSON summary and the tracer's baseline on a unit with
sensors that have no temperature (ICD section 4): no crash on the missing t_ref_C /
t_min_C / t_max_C, and the report says the model of those sensors is constant.

The report is built here from a coefficient set (random coefficients of such a unit), the
way `magcal fit` builds it after fitting, so the report is checked on its own; the whole
path of a temperature-free unit through `magcal fit`, `generate` and `apply` is
host_tests/test_fit_no_temperature.py.
"""

from __future__ import annotations

import numpy as np

from chain_fixtures import random_coeffs
from generator.io.unit import SensorSpec, Unit
from generator.report.report import fit_summary, write_fit_report
from generator.trace.tracer import base_from_coefficients

XYZ = ("+x", "+y", "+z")


def _coeffs():
    unit = Unit("rnotemp", (
        SensorSpec("mmc", "MMC5883MA", "body", XYZ, 25.0, 32768, True, 40.0),
        SensorSpec("mpu", "MPU-9255", "body", XYZ, 150.0, 0, False, 250.0, temperature=False),
        SensorSpec("ist", "generic", "boom", ("-y", "+x", "+z"), 1.0, 0, False, 100.0,
                   input="uT", temperature=False, range_nT=1.6e6)),
        lab_field_nT=50000.0, boom_reference="mmc")
    return random_coeffs(np.random.default_rng(51), unit)


def test_fit_report_and_summary_of_a_unit_with_temperature_free_sensors(tmp_path):
    cs = _coeffs()
    html = write_fit_report(cs, tmp_path, ())
    assert html.is_file()
    md = (tmp_path / "report.md").read_text()
    assert "No temperature (temperature = false): mpu, ist" in md
    assert "none: no temperature (constant model)" in md
    assert "mpu, constant: no temperature" in md and "mmc at 25.0 degC" in md
    assert "ist: constant coefficients (no temperature)" in md
    summary = fit_summary(cs, tmp_path / "coefficients.json", html)
    ranges = {n: s["calibrated_range_C"] for n, s in summary["sensors"].items()}
    assert ranges == {"mmc": [-20.0, 55.0], "mpu": None, "ist": None}


def test_tracer_baseline_of_a_temperature_free_sensor_is_constant():
    """The tracer's baseline clamps every temperature to dT = 0 for a sensor with none:
    degree 0, range [0, 0], unit scale (no division by an infinite span)."""
    cs = _coeffs()
    base = base_from_coefficients(cs, "mpu")
    assert base.degree == 0 and base.b_poly.shape == (1, 3)
    assert (base.t_ref_C, base.t_min_C, base.t_max_C, base.t_scale_C) == (0.0, 0.0, 0.0, 1.0)
    with_t = base_from_coefficients(cs, "mmc")
    assert (with_t.t_ref_C, with_t.t_min_C, with_t.t_max_C) == (25.0, -20.0, 55.0)
