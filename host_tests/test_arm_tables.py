"""Issue 14: the flight table validator's new checks on the emulated Cortex-M4F.

The unit's `<unit>_table.c`, built for the target with the flight flags, runs under qemu
mps2-an386 through a runner extension (generator.flight.arm_tables); the same operations
run through the host build (cffi) and the Python ground code. Every result (status, bad
value index, active serial, coeffs_valid, last status; the active coefficients' bits)
must be the same on all three.

The vectors: the hand-built cases of test_table_rules (exact determinants, exact H^T H
entries, serial orders, broken defaults at init), random M and H, and scans across the
thresholds one float at a time (det M0 around 1/27, det M(t_max) around 1/27, (H^T H)_01
around the tolerance), where any difference in the order or rounding of the arithmetic
between the host and the target would flip a verdict.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from chain_fixtures import (edit_coeffs, m_poly, random_coeffs, random_rotation, samsat_unit,
                            with_float)
from ci import require
from generator.flight import table_physics, tables
from generator.flight import target as ta
from generator.flight.arm_tables import ArmTables, host_results, python_results
from generator.flight.coeffs import CoefficientSet
from generator.flight.table_host import TableHost
from generator.flight.tables import TableStatus, chunk_table, encode_table

pytestmark = pytest.mark.arm
S = TableStatus


@pytest.fixture(scope="module")
def toolchain():
    missing = ta.missing_tools()
    require(not missing, f"missing {', '.join(missing)}: install the Debian packages "
                         f"{' '.join(ta.DEBIAN_PACKAGES)}")




def _scan(dtype, centre, n=48):
    """n consecutive floats of dtype around centre."""
    x = dtype.type(centre)
    lo = x
    for _ in range(n // 2):
        lo = np.nextafter(lo, dtype.type(-np.inf))
    out = [lo]
    for _ in range(n - 1):
        out.append(np.nextafter(out[-1], dtype.type(np.inf)))
    return out


def _det_alternatives(m, dt):
    """det of 9 scalars in the validator's order, by the first column, and exactly
    (rational arithmetic) then rounded: what another order or a fused/wider evaluation
    would give."""
    d1 = table_physics.det3(m)
    d2 = m[0] * (m[4] * m[8] - m[5] * m[7]) - m[3] * (m[1] * m[8] - m[2] * m[7]) \
        + m[6] * (m[1] * m[5] - m[2] * m[4])
    f = [Fraction(float(x)) for x in m]
    exact = f[0] * (f[4] * f[8] - f[5] * f[7]) - f[1] * (f[3] * f[8] - f[5] * f[6]) \
        + f[2] * (f[3] * f[7] - f[4] * f[6])
    return d1, d2, dt.type(float(exact))


def _g01_alternatives(h, dt):
    """(H^T H)[0][1] in the validator's order, summed from the right, and exactly."""
    g1 = h[0] * h[1] + h[3] * h[4] + h[6] * h[7]
    g2 = h[0] * h[1] + (h[3] * h[4] + h[6] * h[7])
    f = [Fraction(float(x)) for x in h]
    return g1, g2, dt.type(float(f[0] * f[1] + f[3] * f[4] + f[6] * f[7]))


def discriminating(cs, n=12, seed=77):
    """Coefficient sets on which the validator's verdict depends on the exact order and
    rounding of its float arithmetic: another order of the same operations, or an exact
    evaluation rounded once, gives the other verdict (det M0 at 1/27; (H^T H)_01 at the
    tolerance). Found by search in the unit's float type; (det sets, rotation sets)."""
    dt = np.dtype(tables.value_dtype(cs.spec))
    lim = tables.PHYSICAL_LIMITS
    lo, tol = dt.type(lim.det_M_lo), dt.type(lim.rotation_tol)
    rng = np.random.default_rng(seed)
    dets, rots = [], []
    for _ in range(20000):
        if len(dets) >= n:
            break
        A = np.eye(3) + rng.normal(0, 0.3, (3, 3))
        d = np.linalg.det(A)
        if d <= 0.05:
            continue
        m = (A * (lim.det_M_lo / d) ** (1 / 3)).astype(dt).ravel()
        k = int(rng.integers(9))
        m[k] = m[k] + dt.type(rng.integers(-3, 4)) * np.spacing(m[k])
        m = [dt.type(x) for x in m]
        if len({bool(x >= lo) for x in _det_alternatives(m, dt)}) > 1:
            dets.append(edit_coeffs(cs, "mpu2", M_poly=m_poly(np.array(m, np.float64)
                                                          .reshape(3, 3))))
    for _ in range(5000):
        if len(rots) >= n:
            break
        R = random_rotation(rng, 0.5)
        h = [dt.type(x) for x in R.ravel()]
        x = dt.type(R[0, 1] + float(tol) / R[0, 0])
        below = x
        for _ in range(64):      # walk down to the last h01 whose g01 is within tol
            h[1] = below
            if _g01_alternatives(h, dt)[0] <= tol:
                break
            below = np.nextafter(below, dt.type(-1))
        for h01 in (below, np.nextafter(below, dt.type(1))):
            h[1] = h01
            if len({bool(g <= tol) for g in _g01_alternatives(h, dt)}) > 1:
                rots.append(edit_coeffs(cs, H_boom_to_body=np.array(h, np.float64).reshape(3, 3)))
    return dets, rots


def _validation_sets(cs):
    """Coefficient sets to validate: hand-built, random, and threshold scans."""
    dt = np.dtype(tables.value_dtype(cs.spec))
    lim = tables.PHYSICAL_LIMITS
    out = []
    # hand-built: exact determinants and rotations
    for m0 in (np.eye(3), np.zeros((3, 3)), np.diag([1.0, 1, -1]), np.diag([0.3] * 3),
               np.diag([0.34] * 3), np.diag([3.0] * 3),
               np.array([[3, -1, 0], [1, 3, 0], [0, 0, 3.0]])):
        out.append(edit_coeffs(cs, "mpu1", M_poly=m_poly(m0)))
    for m1 in (-np.eye(3) / 30, np.eye(3) / 45, -np.eye(3) / 60):
        out.append(edit_coeffs(cs, "mmc2", M_poly=m_poly(np.eye(3), m1), t_ref_C=25.0,
                         t_min_C=-20.0, t_max_C=55.0))
    shear = np.zeros((3, 3))
    shear[0, 1] = 1e-4
    for H in (np.eye(3), 1.0005 * np.eye(3), 1.2 * np.eye(3), np.eye(3) + shear,
              np.eye(3) + shear / 20, np.diag([1.0, -1, 1]), np.zeros((3, 3)),
              random_rotation(np.random.default_rng(5), 0.5)):
        out.append(edit_coeffs(cs, H_boom_to_body=H))
    # random M0 (any determinant, sign included) and H near a rotation
    rng = np.random.default_rng(41)
    for _ in range(40):
        s = cs.unit.sensors[rng.integers(len(cs.unit.sensors))].name
        out.append(edit_coeffs(cs, s, M_poly=m_poly(rng.uniform(-1.5, 1.5, (3, 3)))))
        H = random_rotation(rng, 1.0) + rng.normal(0, 10 ** rng.uniform(-7, -3), (3, 3))
        out.append(edit_coeffs(cs, H_boom_to_body=np.clip(H, -1.0, 1.0)))
    dets, rots = discriminating(cs)
    out += dets + rots
    # det M0 = c^3 det(A) around the lower bound, c one float at a time
    A = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    c0 = (lim.det_M_lo / np.linalg.det(A)) ** (1 / 3)
    for c in _scan(dt, c0):
        out.append(edit_coeffs(cs, "mpu2", M_poly=m_poly((A * float(c)).astype(dt))))
    # det M(t_max) = (1 + 30 m)^3 around 1/27: m around -1/45
    for m in _scan(dt, -1 / 45):
        out.append(edit_coeffs(cs, "mpu2", M_poly=m_poly(np.eye(3), float(m) * np.eye(3)),
                         t_ref_C=25.0, t_min_C=-20.0, t_max_C=55.0))
    # (H^T H)_01 around the tolerance: a rotation with H[0][1] moved by ~tol / H[0][0]
    R = random_rotation(rng, 0.3).astype(dt)
    for h01 in _scan(dt, float(R[0, 1]) + lim.rotation_tol / float(R[0, 0])):
        H = R.astype(np.float64)
        H[0, 1] = float(h01)
        out.append(edit_coeffs(cs, H_boom_to_body=H))
    return out


def _cases():
    rng = np.random.default_rng(1414)
    f32 = random_coeffs(rng, samsat_unit("armtbl"))
    f64 = with_float(random_coeffs(rng, samsat_unit("armtbl64", "float64")), "float64")
    return [("f32", f32), ("f64_softfloat", f64)]


CASES = _cases()


@pytest.fixture(scope="module", params=CASES, ids=[c[0] for c in CASES])
def unit(request, toolchain):
    label, cs = request.param
    return label, cs, ArmTables(cs), TableHost(cs)


def _ops(cs):
    """The operations: validations, the serial rule through load and parts, init with
    broken defaults and the fallback, the active coefficients along the way."""
    other = edit_coeffs(cs, "mpu1", lsb_nT=151.0)
    sets = _validation_sets(cs)
    ops = [("init",)]
    ops += [("validate", encode_table(x, 3, 0, check=False)) for x in sets]
    ops += [("load", encode_table(other, 5, 0)), ("active",),
            ("load", encode_table(cs, 1, 0)), ("load", encode_table(cs, 5, 0)),
            ("load", encode_table(other, 5, 0)), ("load", encode_table(cs, 0, 0))]
    ops += [("receive_part", p) for p in chunk_table(encode_table(cs, 4, 0), 400)]
    ops += [("commit",)]
    ops += [("receive_part", p) for p in chunk_table(encode_table(cs, 6, 0), 400)]
    ops += [("commit",), ("active",)]
    flat = tables.flat_values(cs).astype(tables.value_dtype(cs.spec))
    for bad in (edit_coeffs(cs, H_boom_to_body=1.0005 * np.eye(3)),
                edit_coeffs(cs, "mmc1", M_poly=m_poly(np.zeros((3, 3)))),
                edit_coeffs(cs, H_boom_to_body=1.2 * np.eye(3))):
        bflat = tables.flat_values(bad).astype(flat.dtype)
        ops += [("init_values", bflat), ("active",), ("load", encode_table(cs, 0, 0)),
                ("load", encode_table(cs, 2, 0)), ("active",)]
    ops += [("init_values", flat), ("active",)]
    return ops


def test_table_checks_bit_for_bit_on_the_target(unit):
    label, cs, arm, host = unit
    ops = _ops(cs)
    flat = tables.flat_values(cs).astype(tables.value_dtype(cs.spec))
    got = arm.run(ops)
    want_host = host_results(host, ops)
    want_py = python_results(cs.spec, flat, ops)
    assert len(got) == len(want_host) == len(want_py) == len(ops)
    for i, (op, a, h, p) in enumerate(zip(ops, got, want_host, want_py)):
        assert a == h == p, (i, op[0], a, h, p)
    # the vectors reach every new rule and both sides of each threshold
    statuses = [r[0] for op, r in zip(ops, got) if op[0] != "active"]
    for st in (S.OK, S.BAD_DETERMINANT, S.NOT_A_ROTATION, S.VALUE_OUT_OF_RANGE,
               S.SERIAL_ROLLBACK, S.SERIAL_REPLAY, S.ALREADY_ACTIVE):
        assert st in statuses, st.name
    n_sets = len(_validation_sets(cs))
    scans = [r[0] for r in got[1 + n_sets - 3 * 48:1 + n_sets]]
    for k in range(3):     # each scan flips its verdict
        part = scans[48 * k:48 * (k + 1)]
        assert S.OK in part and (S.BAD_DETERMINANT in part or S.NOT_A_ROTATION in part), k
    # the vectors are sensitive: on each of these another arithmetic order would differ
    dets, rots = discriminating(cs)
    assert len(dets) >= 10 and len(rots) >= 10, (len(dets), len(rots))
    # the broken defaults leave NaN in use on the target too
    nan_states = [r for op, r, prev in zip(ops[1:], got[1:], ops) if op[0] == "active"
                  and prev[0] == "init_values"]
    dt = np.dtype(tables.value_dtype(cs.spec)).newbyteorder("<")
    assert sum(np.all(np.isnan(np.frombuffer(b, dt))) for b in nan_states) == 3
