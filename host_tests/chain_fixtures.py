"""Coefficient sets and input generators shared by the bit-exact tests."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from generator.fit.calibration import SensorCalibration
from generator.flight.coeffs import CoefficientSet
from generator.flight.target import random_inputs  # noqa: F401  (the shared test vectors)
from generator.io.unit import SensorSpec, Unit

REPO = Path(__file__).resolve().parent.parent
EXAMPLE_COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"

# The SamSat-ION mounting of ICD section 1, written out here so these tests need no
# unit file and no fit.
SAMSAT_SENSORS = (
    SensorSpec("mmc1", "MMC5883MA", "body", ("+z", "+y", "+x"), 25.0, 32768, True, 40.0),
    SensorSpec("mpu1", "MPU-9255", "body", ("-z", "-y", "-x"), 150.0, 0, False, 250.0),
    SensorSpec("mpu2", "MPU-9255", "body", ("-z", "+y", "+x"), 150.0, 0, False, 250.0),
    SensorSpec("mmc2", "MMC5883MA", "boom", ("-y", "-z", "-x"), 25.0, 32768, True, 40.0),
    SensorSpec("mpu3", "MPU-9255", "boom", ("-y", "-z", "+x"), 150.0, 0, False, 250.0),
)


def samsat_unit(unit_id="testsat", float_type="float32") -> Unit:
    return Unit(id=unit_id, sensors=SAMSAT_SENSORS, lab_field_nT=51540.0,
                float_type=float_type, boom_reference="mmc1")


def random_rotation(rng, max_angle_rad=0.05) -> np.ndarray:
    v = rng.normal(size=3)
    v *= rng.uniform(0, max_angle_rad) / np.linalg.norm(v)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    th = np.linalg.norm(v)
    if th == 0:
        return np.eye(3)
    K /= th
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def random_coeffs(rng, unit: Unit, coils=(), t_range=(-20.0, 55.0)) -> CoefficientSet:
    """A plausible random coefficient set (cubic b(T), M(T); optional coil coupling)."""
    cals = {}
    for s in unit.sensors:
        b = rng.normal(0, 1, (4, 3)) * np.array([2000, 5, 0.1, 2e-3])[:, None]
        M = rng.normal(0, 1, (4, 3, 3)) * np.array([0.02, 2e-4, 3e-6, 5e-8])[:, None, None]
        M[0] += np.eye(3) * rng.uniform(0.93, 1.07, 3)
        cals[s.name] = SensorCalibration(s.name, b, M, 25.0, t_range[0], t_range[1])
    K = {s.name: rng.normal(0, 3000, (3, len(coils))) for s in unit.sensors} if coils else None
    return CoefficientSet.from_calibrations(unit, cals, H_boom_to_body=random_rotation(rng),
                                            K_nT_per_A=K, coils=coils)


def with_float(cs: CoefficientSet, float_type: str) -> CoefficientSet:
    unit = replace(cs.unit, float_type=float_type)
    spec = replace(cs.spec, unit=unit)
    return CoefficientSet(spec, cs.sensors, cs.unit_values, cs.uncertainty, cs.fit_info)


def bits(a) -> np.ndarray:
    """Bit patterns of a float array (uint32 for float32, uint64 for float64)."""
    a = np.ascontiguousarray(a)
    return a.view(np.uint32 if a.dtype == np.float32 else np.uint64)


def assert_bit_identical(c_out: dict, py_out: dict, context=""):
    assert set(c_out) == set(py_out), (set(c_out), set(py_out))
    for key in c_out:
        a, b = c_out[key], py_out[key]
        assert a.dtype == b.dtype and a.shape == b.shape, (key, a.dtype, b.dtype, a.shape, b.shape)
        if key == "status":
            bad = np.nonzero(a != b)[0]
        else:
            bad = np.nonzero(np.any(bits(a) != bits(b), axis=-1))[0]
        assert bad.size == 0, (
            f"{context} {key}: {bad.size} of {a.shape[0]} samples differ; first at {bad[0]}: "
            f"C {a[bad[0]]!r} vs Python {b[bad[0]]!r}")


def with_options(rng, cs: CoefficientSet, options: dict, poly_degree=None) -> CoefficientSet:
    """cs with optional stages (chain.SensorOptions per sensor name) and random plausible
    values for their blocks; a higher poly_degree pads b(T), M(T) with small terms."""
    from generator.flight.chain import ChainSpec

    deg = cs.spec.poly_degree if poly_degree is None else poly_degree
    spec = ChainSpec(cs.unit, poly_degree=deg, coils=cs.spec.coils,
                     sensor_options=tuple(sorted(options.items())))
    sensors = {}
    for s in cs.unit.sensors:
        v = dict(cs.sensors[s.name])
        for key, scale in (("b_poly_nT", 1e-5), ("M_poly", 1e-9)):
            old = np.asarray(v[key])
            new = np.zeros((deg + 1,) + old.shape[1:])
            k = min(deg + 1, old.shape[0])
            new[:k] = old[:k]
            new[k:] = rng.normal(0, scale, new[k:].shape)
            v[key] = new
        o = spec.opts(s)
        if o.channels:
            v["C_nT_per_unit"] = rng.normal(0, 500, (3, len(o.channels)))
        if o.thermal_lag:
            v["lag_tau_s"] = np.array(rng.uniform(30, 900))
        if o.lagged_channels:
            v["C_lag_nT_per_unit"] = rng.normal(0, 500, (3, len(o.lagged_channels)))
            v["lag_channel_tau_s"] = rng.uniform(30, 900, len(o.lagged_channels))
        if o.channel_scale:
            v["g_per_unit"] = rng.normal(0, 1e-3, (3, len(o.channels)))
        if o.nonlinear:
            v["cubic_per_nT2"] = rng.normal(0, 1e-11, 3)
        if o.sr_compensation:
            v["sr_comp_s_per_deg"] = np.array(0.006 * np.pi / 180)
        sensors[s.name] = v
    return CoefficientSet(spec, sensors, cs.unit_values, cs.uncertainty, cs.fit_info)


def random_aux(rng, spec, n, nan_fraction=0.0):
    """Channels {name: (n,)}, rate_dps (n, 3), dt_s (n,) for a spec's optional stages."""
    channels = {c: rng.normal(0, 1, n) for c in spec.aux_channels} or None
    rate = rng.normal(0, 5, (n, 3)) if spec.needs_rate else None
    dt = None
    if spec.needs_dt:   # mostly forward steps; some zero, negative (clock steps) and huge
        dt = rng.uniform(0.05, 20, n)
        odd = rng.random(n)
        dt[odd < 0.03] = 0.0
        dt[(odd >= 0.03) & (odd < 0.06)] = -rng.uniform(0.01, 1000, ((odd >= 0.03) & (odd < 0.06)).sum())
        dt[(odd >= 0.06) & (odd < 0.07)] = 1e7
    if nan_fraction:
        for a in [dt, rate] + list((channels or {}).values()):
            if a is not None:
                a[rng.random(a.shape[0]) < nan_fraction] = np.nan
    return channels, rate, dt


def edit_coeffs(cs: CoefficientSet, sensor=None, **blocks) -> CoefficientSet:
    """A copy of cs with blocks replaced (sensor blocks if sensor is given, else unit)."""
    sensors = {k: dict(v) for k, v in cs.sensors.items()}
    unit_values = dict(cs.unit_values)
    target = sensors[sensor] if sensor else unit_values
    for name, value in blocks.items():
        target[name] = np.array(value, dtype=np.float64)
    return CoefficientSet(cs.spec, sensors, unit_values, cs.uncertainty, cs.fit_info)


def m_poly(m0, m1=None, orders=4):
    """M_poly with constant term m0 (3x3), first-order term m1, higher orders zero."""
    p = np.zeros((orders, 3, 3))
    p[0] = m0
    if m1 is not None:
        p[1] = m1
    return p
