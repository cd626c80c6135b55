"""Issue 16 item 4: outside the calibrated temperature range the chain sets the
informational STATUS_TEMP_EXTRAPOLATED and the sample stays valid (ICD valid = 1), unless
the temperature lies further out than the sensor's temp_margin_C, the distance at which
the extrapolated error reaches the unit's requirement; then STATUS_TEMP_CLAMPED (invalid).

Checked: the C against the Python reference bit for bit around the margins (sensor calls
and the selection), the validity rule, the margin from the requirement and the fit's
growth estimate, and that estimate against a drift it must reproduce exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from chain_fixtures import assert_bit_identical, random_coeffs, samsat_unit
from generator.fit.calibration import SensorCalibration
from generator.fit.thermal import extrapolation_growth
from generator.flight import chain
from generator.flight.chain import reference_select, reference_sensor
from generator.flight.coeffs import TEMP_MARGIN_MAX_C, CoefficientSet, temp_margin_C
from generator.flight.host import HostUnit

MARGIN_C = 3.0
T_RANGE = (-20.0, 55.0)


@pytest.fixture(scope="module")
def built():
    cs = random_coeffs(np.random.default_rng(16), samsat_unit("extrap"), t_range=T_RANGE)
    for s in cs.unit.sensors:
        cs.sensors[s.name]["temp_margin_C"] = np.array(MARGIN_C)
    return cs, HostUnit(cs)


def _raw(s, n):
    """A reading of about 28,000-40,000 nT (inside the plausible band, so that the
    temperature bits are the only ones)."""
    if s.set_reset:   # (SET - RESET) / 2 = (800, 600, -500) counts of 25 nT
        return np.tile(np.array([33568, 33368, 32268, 31968, 32168, 33268]), (n, 1))
    return np.tile(np.array([200, -150, 100]), (n, 1))


def test_status_and_validity_around_the_margins(built):
    cs, host = built
    lo, hi = T_RANGE
    # inside, at the ends, within the margin, exactly at it (d == margin: still valid),
    # and beyond it, on both sides
    temps = np.array([20.0, lo, hi, lo - 0.5, hi + 0.5, lo - MARGIN_C, hi + MARGIN_C,
                      lo - 3.5, hi + 3.5, lo - 40.0, hi + 40.0], dtype=np.float32)
    inside = np.array([1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0], bool)
    within = np.array([0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0], bool)
    beyond = ~inside & ~within
    for s in cs.unit.sensors:
        raw = _raw(s, len(temps))
        got = host.correct(s.name, raw, temps)
        py = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw, temps)
        assert_bit_identical(got, py, s.name)
        st = got["status"].astype(int)
        ext = (st & chain.STATUS_TEMP_EXTRAPOLATED) != 0
        clamp = (st & chain.STATUS_TEMP_CLAMPED) != 0
        assert not ext[inside].any() and not clamp[inside].any(), s.name
        assert ext[within].all() and not clamp[within].any(), s.name
        assert ext[beyond].all() and clamp[beyond].all(), s.name
        ok = (st & ~(chain.STATUS_TEMP_EXTRAPOLATED | chain.STATUS_TEMP_CLAMPED)) == 0
        assert ok.all(), (s.name, st)          # no other bit: validity is the temperature's
        assert np.array_equal(chain.is_valid(st)[ok], (inside | within)[ok]), s.name
        # the polynomials see the end of the range: the same field as at the end
        f = np.asarray(got["field_body_nT"])
        np.testing.assert_array_equal(f[3], f[1])
        np.testing.assert_array_equal(f[4], f[2])


def test_selection_takes_an_extrapolated_sensor(built):
    """A sensor with only TEMP_EXTRAPOLATED is valid for the selection: chosen, compared;
    C and reference agree."""
    cs, host = built
    S = len(cs.unit.sensors)
    fields = np.tile(np.array([20000.0, -5000.0, 40000.0], np.float32), (4, S, 1))
    st = np.zeros((4, S), np.uint16)
    st[1, :] = chain.STATUS_TEMP_EXTRAPOLATED
    st[2, :] = chain.STATUS_TEMP_CLAMPED | chain.STATUS_TEMP_EXTRAPOLATED
    st[3, 0] = chain.STATUS_TEMP_EXTRAPOLATED
    flat = {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors}
    py = reference_select(cs.spec, flat, fields, st)
    got = host.select(fields, st)
    for k in ("status", "sensor", "reason"):
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(py[k]), k)
    first = cs.spec.fallback_order()[0]
    assert py["sensor"][0] == first and py["sensor"][1] == first and py["sensor"][3] == first
    assert py["sensor"][2] == -1


def test_margin_is_requirement_over_growth():
    unit = samsat_unit("req")
    cal = SensorCalibration.constant("mmc1", np.zeros(3), np.eye(3))
    cal.stats["extrapolation"] = {"growth_nT_per_C": 50.0}
    assert temp_margin_C(unit, cal) == 0.0          # no requirement: the old behaviour
    with_req = dataclasses.replace(unit, extra={"requirements": {"field_error_nT": 150.0}})
    assert temp_margin_C(with_req, cal) == pytest.approx(3.0, rel=1e-15)
    # the calibration's own error comes first: (150 - 50) / 50
    cal.stats["predicted_error"] = {"field_error_nT": 50.0}
    assert temp_margin_C(with_req, cal) == pytest.approx(2.0, rel=1e-15)
    cal.stats["predicted_error"] = {"field_error_nT": 200.0}   # already above it
    assert temp_margin_C(with_req, cal) == 0.0
    cal.stats = {}
    assert temp_margin_C(with_req, cal) == 0.0      # no growth estimate


def test_growth_of_a_linear_drift_is_its_slope():
    """b(T) = s dT exactly known (1-sigma 0), M = I: held at the end of the range, the
    error at d degC outside is |s| d, so the growth must be |s| per degC."""
    s = np.array([3.0, -4.0, 12.0])              # |s| = 13 nT/degC
    b = np.zeros((4, 3))
    b[1] = s
    M = np.zeros((4, 3, 3))
    M[0] = np.eye(3)
    cal = SensorCalibration("x", b, M, 25.0, 0.0, 40.0, b_poly_sigma_nT=np.zeros((4, 3)),
                            M_poly_sigma=np.zeros((4, 3, 3)))
    g = extrapolation_growth(cal, np.array([50000.0]))
    assert g["growth_nT_per_C"] == pytest.approx(13.0, rel=1e-12)
    T = 47.0                                     # 7 degC above the range
    true_err = np.linalg.norm(cal.apply64(np.zeros(3), 40.0) - (-(s * (T - 25.0))))
    assert true_err == pytest.approx(13.0 * 7.0, rel=1e-12)


def test_constant_model_growth_is_the_part_prior_slope():
    """A degree-0 fit determines no slope: the growth is the part's prior 1-sigma of it
    (20 nT/degC per offset axis, 1e-3 /degC per matrix element), not zero."""
    cal = SensorCalibration.constant("x", np.zeros(3), np.eye(3))
    F = 50000.0
    g = extrapolation_growth(cal, np.array([F]))["growth_nT_per_C"]
    assert g == pytest.approx(np.sqrt(9 * 1e-6 * F ** 2 / 3 + 3 * 20.0 ** 2), rel=1e-12)


def _one_temperature_fit(tmp_path, requirement=150.0):
    """A unit file with [requirements] field_error_nT and a fit from one temperature
    (21.5 degC): the constant model. Returns (coefficients.json dict, its path)."""
    import json
    from test_fit_no_temperature import _data
    from generator.cli import main
    from generator.io.icd_write import write_unit_toml

    tables = {"requirements": {"field_error_nT": requirement}} if requirement else None
    unit = write_unit_toml(tmp_path / "unit.toml", "notemp", [   # _data's unit id
        {"name": "mpu", "part": "MPU-9255", "frame": "body", "axes": ["+x", "+y", "+z"],
         "lsb_nT": 15.0, "zero_count": 0, "set_reset": False, "noise_nT": 30.0}],
        unit_keys={"lab_field_nT": 50000.0}, tables=tables)
    data = _data(tmp_path / "d.csv", np.random.default_rng(8))
    # _data writes two sensors without temperature; give this unit's one a temperature
    text = data.read_text().splitlines()
    hdr = next(i for i, l in enumerate(text) if not l.startswith("#"))
    text[hdr] += ",mpu_temp_C"
    for i in range(hdr + 1, len(text)):
        text[i] += ",21.5"
    data.write_text("\n".join(text) + "\n")
    assert main(["fit", str(unit), str(data), "-o", str(tmp_path / "fit"), "-q"]) == 0
    path = tmp_path / "fit" / "coefficients.json"
    return json.loads(path.read_text()), path


def test_fit_writes_a_margin_from_the_unit_requirement(tmp_path):
    """The whole path with a constant model (one temperature): its calibrated range is
    the measured one; its margin is where the error of its unfitted temperature terms
    (the part's prior slope 1-sigma, extrapolation_growth) reaches the requirement,
    (requirement - predicted error) / growth, not the largest margin (issue 16 review 1);
    without a requirement nothing bounds it: valid everywhere, the largest margin (a
    one-temperature ground calibration must not make every orbit sample invalid)."""
    for req in (150.0, None):
        (tmp_path / str(req)).mkdir()
        j, _ = _one_temperature_fit(tmp_path / str(req), req)
        st = j["fit"]["sensors"]["mpu"]["stats"]
        g = st["extrapolation"]["growth_nT_per_C"]
        own = st["predicted_error"]["field_error_nT"]
        assert g > 0
        assert 0 < own < 150.0
        s = j["sensors"]["mpu"]
        assert (s["t_min_C"], s["t_max_C"]) == (21.5, 21.5)
        if req:
            assert s["temp_margin_C"] == pytest.approx((150.0 - own) / g, rel=1e-12)
            assert s["temp_margin_C"] < TEMP_MARGIN_MAX_C
        else:
            assert s["temp_margin_C"] == TEMP_MARGIN_MAX_C


def test_one_temperature_fit_flags_extrapolation_and_clamps_past_the_margin(tmp_path):
    """After a single-temperature fit the extrapolated bit fires outside the measured
    temperature; within the margin the sample stays valid (TEMP_EXTRAPOLATED only),
    beyond it it is TEMP_CLAMPED and invalid; C and reference agree bit for bit."""
    j, path = _one_temperature_fit(tmp_path)
    cs = CoefficientSet.load(path)
    host = HostUnit(cs)
    s = cs.unit.sensor("mpu")
    m = float(j["sensors"]["mpu"]["temp_margin_C"])
    assert 0.5 < m < 100.0
    inside = [21.5 - 0.5 * m, 21.5 + 0.5 * m]
    outside = [21.5 - m - 1.0, 21.5 + m + 1.0, -99.0, 149.0]
    temps = np.array([21.5] + inside + outside, dtype=np.float32)
    raw = np.tile(np.array([2000, -1500, 1000]), (len(temps), 1))
    got = host.correct("mpu", raw, temps)
    py = reference_sensor(cs.spec, s, cs.flat_sensor("mpu"), cs.flat_unit(), raw, temps)
    assert_bit_identical(got, py, "mpu")
    st = np.asarray(got["status"]).astype(int)
    ext = (st & chain.STATUS_TEMP_EXTRAPOLATED) != 0
    clamped = (st & chain.STATUS_TEMP_CLAMPED) != 0
    assert not ext[0] and ext[1:].all(), st
    assert not clamped[:3].any() and clamped[3:].all(), st
    valid = chain.is_valid(st)
    assert valid[:3].all() and not valid[3:].any(), st
    # the constant model gives the same field at every temperature
    f = np.asarray(got["field_body_nT"])
    assert (f == f[0]).all()


@pytest.mark.arm
def test_margins_bit_identical_on_the_cortex_m4f(built):
    """The same temperatures and an extrapolated-only selection on the emulated M4F."""
    from generator.flight import target as ta
    missing = ta.missing_tools()
    if missing:
        pytest.skip(f"missing {', '.join(missing)}")
    cs, _ = built
    arm = ta.ArmUnit(cs)
    lo, hi = T_RANGE
    f32 = np.float32
    temps = np.array([20.0, lo, hi, lo - 0.5, hi + 0.5, lo - MARGIN_C, hi + MARGIN_C,
                      np.nextafter(f32(lo - MARGIN_C), f32(-np.inf)),
                      np.nextafter(f32(hi + MARGIN_C), f32(np.inf)), lo - 40.0, hi + 40.0,
                      np.nan], dtype=np.float32)
    calls, refs = [], []
    for s in cs.unit.sensors:
        raw = _raw(s, len(temps))
        calls.append(("correct", s.name, raw, temps, None))
        refs.append(reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw,
                                     temps))
    outs = arm.run(calls, coeffs_flat=arm.flat_coeffs())
    for s, ref, got in zip(cs.unit.sensors, refs, outs):
        assert_bit_identical(got, ref, f"m4f {s.name}")
    st = np.concatenate([o["status"] for o in outs]).astype(int)
    assert np.any(st == chain.STATUS_TEMP_EXTRAPOLATED)
    assert np.any(st & chain.STATUS_TEMP_CLAMPED)
    S = len(cs.unit.sensors)
    fields = np.tile(np.array([20000.0, -5000.0, 40000.0], np.float32), (2, S, 1))
    sts = np.zeros((2, S), np.uint16)
    sts[1, :] = chain.STATUS_TEMP_EXTRAPOLATED
    got = arm.select(fields, sts)
    ref = reference_select(cs.spec, {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors},
                           fields, sts)
    for k in ("status", "sensor", "reason"):
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(ref[k]), k)
