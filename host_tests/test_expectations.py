"""Independent expected values for the flight wrappers and rules, against the C and the
Python reference alike.

The bit-exact suites prove only that the C and the reference agree: both come from the same
`chain.sensor_kernel`. Here every expected value is computed by code in this file that
shares nothing with generator/flight/chain.py: float64 numpy from the documented rules
(docs/chain.md, the chain module's docstring, ICD section 1 for the axis mapping, the
parts' datasheets for the rails). Coefficients are set by hand, so each rule moves the
output by a known, large amount. Tolerances are float32 rounding of the C (about 1e-7
relative per operation, a few dozen operations): 2e-6 x |B| + 0.01 nT.

Rules checked:
* counts -> nT (plain and SET/RESET), frame axes from the ICD's axes strings, b(T), M(T),
  coil coupling, boom rotation H;
* the temperature clamp at both ends, with and without coils: T outside [t_min, t_max]
  is replaced by the end and flagged TEMP_EXTRAPOLATED (informational), and TEMP_CLAMPED
  (invalid) when it lies further out than the sensor's temp_margin_C (0 when the unit
  states no requirement, as here; a case with a 10 degC margin too); at the end exactly,
  not flagged;
* saturation: a count at a rail (MMC5883MA 0 and 65535, 16-bit unsigned; MPU-9255's
  AK8963 -32760 and +32760, its datasheet's range) flags SATURATED, one count inside does not;
* non-finite temperature or current: zeros and exactly NONFINITE;
* |B| outside the plausibility band: IMPLAUSIBLE;
* the thermal-lag filter T_el += dt / (tau + dt) (T - T_el) on normal, zero and backward
  steps (a step back in time HOLDS the filter) and across a non-finite sample (state kept);
* the selection on 1 to 8 sensors with k of n agreeing: a valid sensor with at least two
  valid others that agrees with FEWER THAN HALF of them disagrees; the selected sensor is
  the first in the fallback order (MMC5883 before MPU-9255, boom before body, then unit
  order) that is valid and does not disagree; reasons SINGLE / CONFIRMED / UNCONFIRMED /
  NONE.
"""

from __future__ import annotations

import itertools
import numpy as np
import pytest

from chain_fixtures import SAMSAT_SENSORS, samsat_unit
from generator.fit.calibration import SensorCalibration
from generator.flight.chain import (ChainSpec, SensorOptions, reference_select,
                                    reference_sensor)
from generator.flight.coeffs import CoefficientSet
from generator.flight.host import HostUnit
from generator.io.unit import SensorSpec, Unit

# Status bits and reasons as documented in docs/chain.md (written out, not imported).
NONFINITE, SATURATED, CLAMPED, IMPLAUSIBLE, DISAGREE = 0x01, 0x02, 0x04, 0x08, 0x10
EXTRAPOLATED = 0x40
CONFIRMED, SINGLE, UNCONFIRMED, NONE = 0, 1, 2, 3
# Rails from the parts' datasheets (not from generator.io.unit.PARTS).
RAILS = {"MMC5883MA": (0, 65535), "MPU-9255": (-32760, 32760)}
BAND_nT = (15000.0, 70000.0)          # the plausibility band set below
COILS = ("coil_x_A", "coil_y_A", "coil_z_A")

T_REF, T_MIN, T_MAX = 25.0, -20.0, 55.0
B0 = np.array([120.0, -340.0, 560.0])                 # nT
B1 = np.array([3.0, -5.0, 7.0])                       # nT/degC: the clamp moves b by ~100s nT
M0 = np.array([[1.02, 0.01, -0.02], [0.005, 0.98, 0.015], [-0.01, 0.02, 1.01]])
M1 = np.diag([2e-4, -3e-4, 1e-4])                     # 1/degC
K = np.array([[800.0, -300.0, 150.0], [200.0, 900.0, -100.0], [-50.0, 250.0, 1100.0]])
# boom -> body: 90 degrees about z then a small tilt; exact in float32 is not needed
_c, _s = np.cos(0.1), np.sin(0.1)
H = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ \
    np.array([[1, 0, 0], [0, _c, -_s], [0, _s, _c]])


def _cals(unit: Unit, t_min=T_MIN, t_max=T_MAX) -> dict:
    b = np.zeros((4, 3))
    b[0], b[1] = B0, B1
    M = np.zeros((4, 3, 3))
    M[0], M[1] = M0, M1
    return {s.name: SensorCalibration(s.name, b, M, T_REF, t_min, t_max) for s in unit.sensors}


def hand_coeffs(unit: Unit, coils=False) -> CoefficientSet:
    return CoefficientSet.from_calibrations(
        unit, _cals(unit), H_boom_to_body=H,
        K_nT_per_A={s.name: K for s in unit.sensors} if coils else None,
        coils=COILS if coils else (), agree_nT={s.name: 200.0 for s in unit.sensors},
        field_band_nT=BAND_nT)


# ---- the independent model ---------------------------------------------------------------
def axes_of(spec: SensorSpec):
    """ICD section 1: frame axis k is the sensor axis named axes[k], with its sign."""
    idx = ["xyz".index(a[1]) for a in spec.axes]
    sign = [1.0 if a[0] == "+" else -1.0 for a in spec.axes]
    return idx, sign


def expected(spec: SensorSpec, raw, temp, coil=None, t_el=None, margin_C=0.0):
    """float64 field (N, 3) and status (N,) from the documented chain; t_el: the element
    temperature to use instead of temp (thermal lag); margin_C: the sensor's temp_margin_C
    (the distance outside the range still valid)."""
    raw = np.asarray(raw, float)
    temp = np.asarray(temp, float)
    n = raw.shape[0]
    lo, hi = RAILS[spec.part]
    status = np.zeros(n, dtype=np.uint16)
    status[np.any((raw <= lo) | (raw >= hi), axis=1)] |= SATURATED
    nonfinite = ~np.isfinite(temp)
    if coil is not None:
        nonfinite |= ~np.all(np.isfinite(coil), axis=1)
    if spec.set_reset:
        f_s = (raw[:, 0:3] - raw[:, 3:6]) * 0.5 * spec.lsb_nT
    else:
        f_s = (raw - spec.zero_count) * spec.lsb_nT
    idx, sign = axes_of(spec)
    f = np.stack([sign[k] * f_s[:, idx[k]] for k in range(3)], axis=1)
    T = np.where(nonfinite, T_REF, temp if t_el is None else t_el)
    outside = (T < T_MIN) | (T > T_MAX)
    # the distance outside is exact in float32 for the temperatures used here
    far = (T_MIN - T > margin_C) | (T - T_MAX > margin_C)
    T = np.minimum(np.maximum(T, T_MIN), T_MAX)
    dT = T - T_REF
    x = f - (B0[None, :] + B1[None, :] * dT[:, None])
    if coil is not None:
        x = x - np.where(np.isfinite(coil), coil, 0.0) @ K.T
    M = M0[None] + M1[None] * dT[:, None, None]
    B = np.einsum("nij,nj->ni", M, x)
    if spec.frame == "boom":
        B = B @ H.T
    norm = np.linalg.norm(B, axis=1)
    status[outside & ~nonfinite] |= EXTRAPOLATED
    status[far & ~nonfinite] |= CLAMPED
    status[((norm < BAND_nT[0]) | (norm > BAND_nT[1])) & ~nonfinite] |= IMPLAUSIBLE
    status[nonfinite] |= NONFINITE
    B[nonfinite] = 0.0
    return B, status, norm


def counts_for(spec: SensorSpec, frame_nT):
    """Raw counts (N, 3|6) whose frame-axis field is frame_nT (rounded to whole counts)."""
    idx, sign = axes_of(spec)
    f_s = np.zeros_like(frame_nT)
    for k in range(3):
        f_s[:, idx[k]] = sign[k] * frame_nT[:, k]
    c = np.round(f_s / spec.lsb_nT).astype(np.int64)
    if spec.set_reset:
        return np.concatenate([spec.zero_count + c, spec.zero_count - c], axis=1)
    return spec.zero_count + c


# ---- C and Python ---------------------------------------------------------------------
_HOSTS = {}


def host(cs, key):
    if key not in _HOSTS:
        _HOSTS[key] = HostUnit(cs)
    return _HOSTS[key]


def both(cs, key, sensor, raw, temp, coil=None, dt=None):
    spec = cs.spec
    s = spec.unit.sensor(sensor)
    c_out = host(cs, key).correct(sensor, raw, temp, coil, dt_s=dt)
    py_out = reference_sensor(spec, s, cs.flat_sensor(sensor), cs.flat_unit(), raw, temp,
                              coil, dt_s=dt)
    return {"C": c_out, "Python": py_out}


def tol(norm):
    return 2e-6 * np.asarray(norm)[:, None] + 0.01


def check(outs, B, status, norm, what):
    for impl, out in outs.items():
        np.testing.assert_array_equal(out["status"], status, err_msg=f"{impl} {what} status")
        err = np.abs(out["field_body_nT"].astype(float) - B)
        bad = np.nonzero(np.any(err > tol(norm), axis=1))[0]
        assert bad.size == 0, (f"{impl} {what}: {bad.size} samples off; first {bad[0]}: "
                               f"{out['field_body_nT'][bad[0]]} vs expected {B[bad[0]]}")


UNIT = samsat_unit("expect")
CASES = {"nocoils": hand_coeffs(UNIT), "coils": hand_coeffs(samsat_unit("expectc"), coils=True)}
MARGIN_C = 10.0                 # the "margin" case: samples up to 10 degC outside stay valid


def _with_margin(cs: CoefficientSet, margin_C: float) -> CoefficientSet:
    sensors = {n: dict(v) for n, v in cs.sensors.items()}
    for v in sensors.values():
        v["temp_margin_C"] = np.array(margin_C)
    return CoefficientSet(cs.spec, sensors, cs.unit_values, cs.uncertainty, cs.fit_info)


CASES["margin"] = _with_margin(hand_coeffs(samsat_unit("expectm")), MARGIN_C)
# no [requirements] field_error_nT in these units: the documented margin is 0
MARGINS = {"nocoils": 0.0, "coils": 0.0, "margin": MARGIN_C}


def _frame_fields(rng, n):
    """Frame-axis fields of 25-60 uT in random directions (well inside every range)."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None] * rng.uniform(25000, 60000, n)[:, None]


@pytest.mark.parametrize("case", ["nocoils", "coils", "margin"])
@pytest.mark.parametrize("sensor", [s.name for s in SAMSAT_SENSORS])
def test_clamp_both_ends_and_the_chain(case, sensor):
    cs = CASES[case]
    spec = cs.unit.sensor(sensor)
    for v in cs.sensors.values():
        assert float(v["temp_margin_C"]) == MARGINS[case]
    f32 = np.float32
    # -30 and 65: exactly the 10 degC margin outside (valid); -30.5 and 65.5 beyond it
    temps = np.array([-60.0, -30.5, -30.0, -20.5, float(np.nextafter(f32(T_MIN), f32(-1))),
                      T_MIN, -19.5, 0.0, T_REF, 40.0, 54.5, T_MAX,
                      float(np.nextafter(f32(T_MAX), f32(99))), 55.5, 65.0, 65.5, 70.0, 125.0,
                      1e30, -1e30])
    rng = np.random.default_rng(7)
    n = temps.size * 8
    temp = np.tile(temps, 8)
    raw = counts_for(spec, _frame_fields(rng, n))
    coil = rng.uniform(-0.2, 0.2, (n, 3)) if case == "coils" else None
    B, status, norm = expected(spec, raw, temp, coil, margin_C=MARGINS[case])
    # the clamp is visible: far outside, the output equals the output at the end
    assert np.any(status & CLAMPED) and np.any((status & CLAMPED) == 0)
    # every flagged sample is outside: TEMP_CLAMPED only with TEMP_EXTRAPOLATED
    clamped, extrapolated = (status & CLAMPED) != 0, (status & EXTRAPOLATED) != 0
    assert np.all(extrapolated[clamped])
    if MARGINS[case] > 0:   # outside but within the margin: informational only
        assert np.any(extrapolated & ~clamped)
    check(both(cs, case, sensor, raw, temp, coil), B, status, norm, f"{case}/{sensor} clamp")


@pytest.mark.parametrize("case", ["nocoils", "coils"])
def test_the_upper_clamp_holds_the_value_at_t_max(case):
    """Zero field, T = 55 (t_max) vs T = 100 and 1e30: identical outputs, the latter two
    flagged. A missing upper clamp extrapolates b(T) by 45 x 7 nT and more."""
    cs = CASES[case]
    for spec in cs.unit.sensors:
        raw = counts_for(spec, np.zeros((3, 3)))
        temp = np.array([T_MAX, 100.0, 1e30])
        coil = np.zeros((3, 3)) if case == "coils" else None
        for impl, out in both(cs, case, spec.name, raw, temp, coil).items():
            f = out["field_body_nT"]
            np.testing.assert_array_equal(f[1], f[0], err_msg=f"{impl} {spec.name}")
            np.testing.assert_array_equal(f[2], f[0], err_msg=f"{impl} {spec.name}")
            assert list(out["status"] & CLAMPED) == [0, CLAMPED, CLAMPED], impl
            B, _, _ = expected(spec, raw, temp, coil)
            assert np.allclose(f[0], B[0], atol=0.05), (impl, f[0], B[0])


@pytest.mark.parametrize("case", ["nocoils", "coils"])
@pytest.mark.parametrize("sensor", [s.name for s in SAMSAT_SENSORS])
def test_saturation_at_the_rails_only(case, sensor):
    cs = CASES[case]
    spec = cs.unit.sensor(sensor)
    lo, hi = RAILS[spec.part]
    rng = np.random.default_rng(11)
    base = counts_for(spec, _frame_fields(rng, 1))[0]
    rows = []
    for v in (lo, lo + 1, hi - 1, hi, lo - 5, hi + 5):
        for j in range(base.size):
            r = base.copy()
            r[j] = v
            rows.append(r)
    raw = np.array(rows)
    n = raw.shape[0]
    temp = np.full(n, 20.0)
    coil = np.zeros((n, 3)) if case == "coils" else None
    _, status, _ = expected(spec, raw, temp, coil)
    at_rail = np.any((raw <= lo) | (raw >= hi), axis=1)
    assert at_rail.sum() == 4 * base.size and (~at_rail).sum() == 2 * base.size
    for impl, out in both(cs, case, sensor, raw, temp, coil).items():
        assert np.all(out["status"][at_rail] & SATURATED), impl
        assert not np.any(out["status"][~at_rail] & SATURATED), impl
        np.testing.assert_array_equal(out["status"] & SATURATED, status & SATURATED)


@pytest.mark.parametrize("case", ["nocoils", "coils"])
@pytest.mark.parametrize("sensor", [s.name for s in SAMSAT_SENSORS])
def test_non_finite_inputs_give_zeros_and_only_that_flag(case, sensor):
    cs = CASES[case]
    spec = cs.unit.sensor(sensor)
    rng = np.random.default_rng(13)
    n = 12
    raw = counts_for(spec, _frame_fields(rng, n))
    temp = np.array([np.nan, np.inf, -np.inf, 20.0, 20.0, 20.0, 100.0, -50.0, 20.0, 20.0,
                     np.nan, 30.0])
    coil = None
    if case == "coils":
        coil = np.zeros((n, 3))
        coil[3, 0], coil[4, 1], coil[5, 2], coil[6, 0], coil[7, 1] = \
            np.nan, np.inf, -np.inf, np.nan, np.inf
    B, status, norm = expected(spec, raw, temp, coil)
    bad = ~np.isfinite(temp) if coil is None else \
        ~np.isfinite(temp) | ~np.all(np.isfinite(coil), axis=1)
    assert np.all(status[bad] == NONFINITE)
    check(both(cs, case, sensor, raw, temp, coil), B, status, norm, f"{case}/{sensor} nonfinite")
    for impl, out in both(cs, case, sensor, raw, temp, coil).items():
        assert np.all(out["field_body_nT"][bad] == 0), impl


@pytest.mark.parametrize("sensor", ["mmc1", "mpu1", "mmc2"])
def test_implausible_band(sensor):
    cs = CASES["nocoils"]
    spec = cs.unit.sensor(sensor)
    rng = np.random.default_rng(17)
    v = rng.normal(size=(200, 3))
    mags = np.concatenate([rng.uniform(2000, 13000, 60), rng.uniform(17000, 68000, 80),
                           rng.uniform(72000, 90000, 60)])
    f = v / np.linalg.norm(v, axis=1)[:, None] * mags[:, None]
    raw = counts_for(spec, f)
    temp = np.full(200, 25.0)
    B, status, norm = expected(spec, raw, temp)
    assert np.any(status & IMPLAUSIBLE) and np.any((status & IMPLAUSIBLE) == 0)
    check(both(cs, "nocoils", sensor, raw, temp), B, status, norm, f"{sensor} band")


# ---- thermal lag -------------------------------------------------------------------------
TAU_S = 100.0


def lag_coeffs() -> CoefficientSet:
    base = hand_coeffs(samsat_unit("lagx"))
    opts = {"mmc1": SensorOptions(thermal_lag=True), "mpu1": SensorOptions(thermal_lag=True)}
    spec = ChainSpec(base.unit, poly_degree=3, sensor_options=tuple(sorted(opts.items())))
    sensors = {n: dict(v) for n, v in base.sensors.items()}
    for name in opts:
        sensors[name]["lag_tau_s"] = np.array(TAU_S)
    return CoefficientSet(spec, sensors, base.unit_values, base.uncertainty, base.fit_info)


def expected_lag(temp, dt):
    """T_el per call: the first finite call starts the filter at T; then
    T_el += dt / (tau + dt) (T - T_el) for dt >= 0, held for dt < 0; a call with a
    non-finite input (temperature or dt) leaves the state alone."""
    out = np.full(temp.size, np.nan)
    el = None
    for k in range(temp.size):
        if not (np.isfinite(temp[k]) and np.isfinite(dt[k])):
            continue
        if el is None:
            el = temp[k]
        elif dt[k] >= 0:
            el = el + dt[k] / (TAU_S + dt[k]) * (temp[k] - el)
        out[k] = el
    return out


@pytest.mark.parametrize("sensor", ["mmc1", "mpu1"])
def test_thermal_lag_normal_zero_and_backward_steps(sensor):
    cs = lag_coeffs()
    spec = cs.unit.sensor(sensor)
    # a 30 degC step, forward steps, a zero step, backward steps (one huge), a NaN dt and a
    # NaN temperature, then forward again
    temp = np.array([0.0, 30, 30, 30, 30, 30, 30, 30, 30, 30, 30, 30, 45, 45])
    dt = np.array([1.0, 10, 10, 0, -5, -1000, 20, np.nan, 20, 10, 10, -50, 100, 0])
    temp[10] = np.nan
    n = temp.size
    raw = counts_for(spec, np.tile([[30000.0, -20000.0, 25000.0]], (n, 1)))
    t_el = expected_lag(temp, dt)
    B, status, norm = expected(spec, raw, temp, t_el=np.where(np.isfinite(t_el), t_el, 25.0))
    bad = ~np.isfinite(t_el)
    B[bad] = 0.0
    status[bad] = NONFINITE
    # the filter moved: the element temperature is neither the start nor the reported one
    assert 0 < t_el[2] < 30 and t_el[3] == t_el[2] and t_el[5] == t_el[2]
    check(both(cs, "lag", sensor, raw, temp, dt=dt), B, status, norm, f"{sensor} lag")


@pytest.mark.parametrize("sensor", ["mmc1", "mpu1"])
def test_thermal_lag_backward_step_holds_exactly(sensor):
    """After a backward step the output equals the previous call's bit for bit (same
    counts, same reported temperature): the filter held."""
    cs = lag_coeffs()
    spec = cs.unit.sensor(sensor)
    temp = np.array([0.0, 40.0, 40.0, 40.0])
    dt = np.array([1.0, 30.0, -30.0, -1e6])
    raw = counts_for(spec, np.tile([[30000.0, -20000.0, 25000.0]], (4, 1)))
    for impl, out in both(cs, "lag", sensor, raw, temp, dt=dt).items():
        f = out["field_body_nT"]
        assert not np.array_equal(f[1], f[0]), impl       # the step moved the filter
        np.testing.assert_array_equal(f[2], f[1], err_msg=impl)
        np.testing.assert_array_equal(f[3], f[1], err_msg=impl)


# ---- selection -----------------------------------------------------------------------
KINDS = [("MMC5883MA", "body"), ("MPU-9255", "boom"), ("MPU-9255", "body"),
         ("MMC5883MA", "boom"), ("MPU-9255", "body"), ("MMC5883MA", "body"),
         ("MPU-9255", "boom"), ("MMC5883MA", "boom")]


def select_unit(n) -> Unit:
    sensors = []
    for i in range(n):
        part, frame = KINDS[i]
        sr = part == "MMC5883MA"
        sensors.append(SensorSpec(f"s{i}", part, frame, ("+x", "+y", "+z"),
                                  25.0 if sr else 150.0, 32768 if sr else 0, sr,
                                  40.0 if sr else 250.0))
    return Unit(id=f"sel{n}", sensors=tuple(sensors), lab_field_nT=50000.0,
                boom_reference="s0" if any(f == "boom" for _, f in KINDS[:n]) else None)


def documented_order(unit: Unit):
    """docs/chain.md: MMC5883 before MPU-9255, boom before body, then unit order."""
    def key(i):
        s = unit.sensors[i]
        return (0 if s.part == "MMC5883MA" else 1, 0 if s.frame == "boom" else 1, i)
    return sorted(range(len(unit.sensors)), key=key)


def expected_select(labels, order):
    """labels[i]: -1 invalid, else a cluster id (sensors agree iff same cluster)."""
    n = len(labels)
    valid = [lab >= 0 for lab in labels]
    dis = [False] * n
    n_cmp, n_agr = [0] * n, [0] * n
    for i in range(n):
        if valid[i]:
            others = [j for j in range(n) if j != i and valid[j]]
            n_cmp[i] = len(others)
            n_agr[i] = sum(labels[j] == labels[i] for j in others)
            dis[i] = n_cmp[i] >= 2 and n_agr[i] < n_cmp[i] / 2      # fewer than half
    for rank, i in enumerate(order):
        if valid[i] and not dis[i]:
            why = SINGLE if n_cmp[i] == 0 else CONFIRMED if n_agr[i] > 0 else UNCONFIRMED
            return dis, i, why, rank
    return dis, -1, NONE, -1


CLUSTER_FIELDS = np.array([[30000.0, 10000.0, -20000.0], [-25000.0, 30000.0, 5000.0],
                           [5000.0, -35000.0, 20000.0], [20000.0, 20000.0, 30000.0]])


def _patterns(n, rng):
    """Every labelling with labels in {-1, 0, 1, 2, 3} for n <= 5, else 3000 random ones
    plus every 'k of n in cluster 0, the rest in cluster 1' and 'rest scattered' case."""
    if n <= 5:
        pats = list(itertools.product(range(-1, 4), repeat=n))
    else:
        pats = [tuple(p) for p in rng.integers(-1, 4, (3000, n))]
    for k in range(n + 1):
        for rest in ("one", "scattered"):
            for first in (True, False):
                lab = [0] * k + [1 if rest == "one" else 1 + (j % 3) for j in range(n - k)]
                pats.append(tuple(lab if first else lab[::-1]))
    return pats


@pytest.mark.parametrize("n", range(1, 9))
def test_selection_k_of_n(n):
    unit = select_unit(n)
    cs = hand_coeffs(unit)
    order = documented_order(unit)
    rng = np.random.default_rng(100 + n)
    pats = _patterns(n, rng)
    N = len(pats)
    fields = np.zeros((N, n, 3))
    statuses = np.zeros((N, n), dtype=np.uint16)
    bits = [NONFINITE, SATURATED, CLAMPED, IMPLAUSIBLE]
    for r, lab in enumerate(pats):
        for i, c in enumerate(lab):
            # clusters: the same field within 50 nT (agree_nT 200 each: tolerance 400 nT)
            fields[r, i] = CLUSTER_FIELDS[max(c, 0)] + rng.uniform(-25, 25, 3)
            if c < 0:
                statuses[r, i] = bits[(r + i) % 4]
    exp_status = statuses.copy()
    exp_sensor = np.zeros(N, int)
    exp_reason = np.zeros(N, int)
    exp_rank = np.zeros(N, int)
    for r, lab in enumerate(pats):
        dis, i, why, rank = expected_select(lab, order)
        for j in range(n):
            if dis[j]:
                exp_status[r, j] |= DISAGREE
        exp_sensor[r], exp_reason[r], exp_rank[r] = i, why, rank
    flat = {s.name: cs.flat_sensor(s.name) for s in unit.sensors}
    outs = {"Python": reference_select(cs.spec, flat, fields, statuses.copy())}
    _check_select(outs, exp_status, exp_sensor, exp_reason, exp_rank, fields, n)
    outs = {"C": HostUnit(cs).select(fields, statuses.copy())}
    _check_select(outs, exp_status, exp_sensor, exp_reason, exp_rank, fields, n)
    if n >= 3:   # the exactly-half case is exercised: agrees with half of the others
        assert any(sum(a == lab[0] for a in lab[1:] if a >= 0) * 2
                   == sum(a >= 0 for a in lab[1:]) >= 2 for lab in pats if lab[0] >= 0)


def _check_select(outs, exp_status, exp_sensor, exp_reason, exp_rank, fields, n):
    for impl, out in outs.items():
        np.testing.assert_array_equal(out["status"], exp_status, err_msg=f"{impl} n={n}")
        np.testing.assert_array_equal(out["sensor"], exp_sensor, err_msg=f"{impl} n={n}")
        np.testing.assert_array_equal(out["reason"], exp_reason, err_msg=f"{impl} n={n}")
        np.testing.assert_array_equal(out["rank"], exp_rank, err_msg=f"{impl} n={n}")
        chosen = exp_sensor >= 0
        np.testing.assert_allclose(out["field_body_nT"][chosen],
                                   fields[chosen, exp_sensor[chosen]], rtol=1e-6)
        assert np.all(out["field_body_nT"][~chosen] == 0)


def test_selection_agreement_boundary_is_inclusive():
    """|B_i - B_j| equal to agree_i + agree_j agrees (margin >= 0); one step beyond does not.
    Three sensors: s1 sits exactly at the tolerance from s0, s2 far away."""
    unit = select_unit(3)
    cs = hand_coeffs(unit)          # agree_nT = 200 each: tolerance 400 nT
    f = np.array([[[20000.0, 0, 0], [20400.0, 0, 0], [-20000.0, 0, 0]],
                  [[20000.0, 0, 0], [20400.0 + 1 / 64, 0, 0], [-20000.0, 0, 0]]])
    st = np.zeros((2, 3), np.uint16)
    flat = {s.name: cs.flat_sensor(s.name) for s in unit.sensors}
    for impl, out in {"C": HostUnit(cs).select(f, st.copy()),
                      "Python": reference_select(cs.spec, flat, f, st.copy())}.items():
        # row 0: s0 and s1 agree; s2 agrees with none of its two others -> DISAGREE
        assert list(out["status"][0]) == [0, 0, DISAGREE], impl
        # row 1: nobody agrees; each agrees with 0 of 2 -> all disagree, none selected
        assert list(out["status"][1]) == [DISAGREE] * 3, impl
        assert list(out["reason"]) == [CONFIRMED, NONE], impl
