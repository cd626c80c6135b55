"""Review #20d F2: a count's zero point is subtracted from the count on every call, not
folded into the constant term of b(T). count - zero is exact in float32 (integers below
2^24); a constant term holding a large zero point (8,388,608 for a 24-bit offset-binary
part) rounds each temperature term added to it to its ulp, up to half a count.

Bound: the float32 chain's own rounding, a few roundings of 2^-24 relative on each
product and sum of M (x - b): |error| <= 8 2^-24 sum_j |M_ij| (|x_j| + |b_j|) per axis
(the bound test_any_unit uses between physical-unit forms). With the zero point folded in,
lsb 1 nT and zero 16,000,000 the error reached 0.8 nT, about 10x that bound."""

from __future__ import annotations

import numpy as np

from chain_fixtures import random_coeffs
from generator.flight.chain import CoeffView, fold_sensor_coeffs, folded_sensor_kernel, \
    sensor_kernel
from generator.io.unit import SensorSpec, Unit


def _unit(zero, lsb):
    return Unit("zp", (SensorSpec("gen", "generic", "body", ("+x", "+y", "+z"), lsb, zero,
                                  False, 100.0, range_nT=4e6),), lab_field_nT=50000.0)


def _worst_excess(zero, lsb, seed=4):
    cs = random_coeffs(np.random.default_rng(seed), _unit(zero, lsb))
    spec, s = cs.spec, cs.unit.sensors[0]
    c64 = CoeffView(list(cs.flat_sensor(s.name)), spec.sensor_blocks(s))
    u64 = CoeffView(list(cs.flat_unit()), spec.unit_blocks())
    f32 = np.float32
    c32 = CoeffView([f32(v) for v in cs.flat_sensor(s.name)], spec.sensor_blocks(s))
    u32 = CoeffView([f32(v) for v in cs.flat_unit()], spec.unit_blocks())
    fold = fold_sensor_coeffs(spec, s, c32, u32, f32(0.5))
    rng = np.random.default_rng(seed + 1)
    worst = 0.0
    for _ in range(300):
        raw = [float(zero + np.round(v)) for v in rng.normal(0, 50000.0 / lsb, 3)]
        temp = float(rng.uniform(-30, 60))
        ref = sensor_kernel(spec, s, raw, temp, [], c64, u64, 0.5)
        got = folded_sensor_kernel(spec, s, [f32(v) for v in raw], f32(temp), [], fold,
                                   f32(0.5))
        B = np.array(ref["field_body_nT"], float)
        # the bound: M and b at this temperature in float64, x the scaled difference
        dT = temp - c64.scalar("t_ref_C")
        n = len(c64.get("b_poly_nT"))
        M = sum(np.array(c64.get("M_poly")[k], float) * dT ** k for k in range(n))
        b = sum(np.array(c64.get("b_poly_nT")[k], float) * dT ** k for k in range(n))
        x = (np.array(raw) - zero) * lsb
        bound = 8 * 2.0 ** -24 * (np.abs(M) @ (np.abs(x) + np.abs(b)))
        err = np.abs(np.array(got["field_body_nT"], float) - B)
        worst = max(worst, float(np.max(err / bound)))
    return worst


def test_a_large_zero_point_costs_no_precision():
    for zero, lsb in ((8_388_608, 0.09), (16_000_000, 1.0), (131_072, 0.0625)):
        assert _worst_excess(zero, lsb) <= 1.0, (zero, lsb)


def test_the_bound_catches_a_folded_zero_point():
    """The same comparison with the zero point folded the old way (into b0) exceeds the
    bound: the test above can fail."""
    import generator.flight.chain as chain
    orig = chain.fold_sensor_coeffs

    def folded_zero(spec, sensor, c, u, half, set_only=False):
        f = orig(spec, sensor, c, u, half, set_only=set_only)
        z = f.pop("zero_count")
        f["b_poly"][0] = [f["b_poly"][0][i] + z for i in range(3)]
        f["zero_count"] = type(z)(0)
        return f
    chain.fold_sensor_coeffs = folded_zero
    try:
        globals()["fold_sensor_coeffs"] = folded_zero
        assert _worst_excess(16_000_000, 1.0) > 1.0
    finally:
        chain.fold_sensor_coeffs = orig
        globals()["fold_sensor_coeffs"] = orig
