"""The correction chain: its one definition.

Everything that knows the chain's structure reads it from here:

* the CasADi SX expressions (``codegen.py`` builds one CasADi Function per sensor from
  :func:`sensor_kernel` and emits C with CasADi's CodeGenerator);
* the Python reference (:func:`reference_sensor`), which runs the very same
  :func:`sensor_kernel` on numpy float32 values, so every + - * is the same IEEE
  operation, in the same order, as in the generated C;
* the coefficient layout (:class:`ChainSpec` blocks, in order): the C coefficient
  arrays, the uplink table payload and the docs are all made from it.

Per sensor, per sample (seed 000, fig. 30; equations [4], [1], [7], [5]):

    SET/RESET   field_s = (set - reset) * 0.5 * lsb       offset_s = ((set + reset) * 0.5 - zero) * lsb
    or plain    field_s = (count - zero) * lsb
    axes        field_f[k] = sign[k] * field_s[idx[k]]                      (eq. 1, structural)
    temperature T = clamp(temp_C, t_min, t_max),  dT = T - t_ref             (clamp in the wrapper)
    offset      b_i(T)  = ((b3_i dT + b2_i) dT + b1_i) dT + b0_i             (Horner, eq. 7)
    matrix      m_ij(T) = ((m3_ij dT + m2_ij) dT + m1_ij) dT + m0_ij
    coils       x_i = field_f_i - b_i(T) - (K_i0 i_0 + K_i1 i_1 + ...)       (when coils are in the chain)
    calibrate   B_i = m_i0 x_0 + m_i1 x_1 + m_i2 x_2                        (eq. 5)
    boom        B_body_i = H_i0 B_0 + H_i1 B_1 + H_i2 B_2                    (boom sensors, eq. 2-3)

The kernels use only + - * (and the wrapper only comparisons), so float32 results are
reproducible bit for bit on any IEEE-754 machine that rounds each operation to nearest
(C built without FMA contraction: -ffp-contract=off).

Status bits (the wrapper, C and Python alike): a sample with a non-finite temperature or
current gets zeros and STATUS_NONFINITE; a count at a rail of the part's range gets
STATUS_SATURATED; a temperature outside the calibrated range is clamped and gets
STATUS_TEMP_CLAMPED. ``valid`` is ``status == 0``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np

from .unit import SensorSpec, Unit

CHAIN_VERSION = 1  # bump when the meaning of an existing block or stage changes

STATUS_NONFINITE = 0x01
STATUS_SATURATED = 0x02
STATUS_TEMP_CLAMPED = 0x04
STATUS_BITS = {
    "NONFINITE": STATUS_NONFINITE,
    "SATURATED": STATUS_SATURATED,
    "TEMP_CLAMPED": STATUS_TEMP_CLAMPED,
}


@dataclass(frozen=True)
class Block:
    """One named block of coefficients, stored row-major in the flat coefficient vector."""

    name: str
    shape: tuple
    unit: str
    kind: str   # what plausibility range applies (table validation), see tables
    doc: str

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1


@dataclass(frozen=True)
class Input:
    name: str
    size: int
    unit: str
    doc: str


@dataclass(frozen=True)
class ChainSpec:
    """The structure of the chain for one unit: what the layout hash covers.

    poly_degree: degree of b(T) and M(T) in dT (seed: cubic).
    coils: names of the telemetry columns of the magnetorquer currents whose coupling
        K (nT/A, one column per coil) is subtracted; empty when the chain has no coils.
    """

    unit: Unit
    poly_degree: int = 3
    coils: tuple = ()

    # ---- structure -------------------------------------------------------------------
    @property
    def has_boom(self) -> bool:
        return any(s.frame == "boom" for s in self.unit.sensors)

    def sensor_blocks(self, sensor: SensorSpec) -> tuple:
        n = self.poly_degree + 1
        blocks = [
            Block("lsb_nT", (), "nT/count", "lsb", "field per count"),
            Block("zero_count", (), "count", "zero_count", "count at zero field"),
            Block("t_ref_C", (), "degC", "temp", "reference temperature of the polynomials"),
            Block("t_min_C", (), "degC", "temp", "lowest calibrated temperature (clamp)"),
            Block("t_max_C", (), "degC", "temp", "highest calibrated temperature (clamp)"),
            Block("b_poly_nT", (n, 3), "nT/degC^k", "offset_poly",
                  "offset b(T) = sum_k b_poly_nT[k] dT^k, frame axes"),
            Block("M_poly", (n, 3, 3), "1/degC^k", "matrix_poly",
                  "calibration matrix M(T) = sum_k M_poly[k] dT^k"),
        ]
        if self.coils:
            blocks.append(Block("K_nT_per_A", (3, len(self.coils)), "nT/A", "coupling",
                                "magnetorquer coupling, one column per coil, frame axes"))
        return tuple(blocks)

    def unit_blocks(self) -> tuple:
        blocks = []
        if self.has_boom:
            blocks.append(Block("H_boom_to_body", (3, 3), "1", "rotation",
                                "orthogonal boom->body alignment (seed 000 eq. 2-3)"))
        return tuple(blocks)

    def sensor_inputs(self, sensor: SensorSpec) -> tuple:
        if sensor.set_reset:
            raw = Input("raw_counts", 6, "count", "SET x,y,z then RESET x,y,z, sensor axes")
        else:
            raw = Input("raw_counts", 3, "count", "x, y, z, sensor axes")
        ins = [raw, Input("temp_C", 1, "degC", "sensor temperature, already clamped")]
        if self.coils:
            ins.append(Input("coil_A", len(self.coils), "A", "magnetorquer currents"))
        return tuple(ins)

    def sensor_outputs(self, sensor: SensorSpec) -> tuple:
        outs = [Input("field_body_nT", 3, "nT", "calibrated field, body frame")]
        if sensor.set_reset:
            outs.append(Input("chip_offset_nT", 3, "nT", "SET/RESET bridge offset, sensor axes"))
        return tuple(outs)

    def n_sensor_coeffs(self, sensor) -> int:
        return sum(b.size for b in self.sensor_blocks(sensor))

    def n_unit_coeffs(self) -> int:
        return sum(b.size for b in self.unit_blocks())

    def offsets(self, blocks) -> dict:
        out, k = {}, 0
        for b in blocks:
            out[b.name] = k
            k += b.size
        return out

    # ---- identity ----------------------------------------------------------------------
    def structure(self) -> dict:
        """Everything the generated code depends on except coefficient values."""
        return {
            "chain_version": CHAIN_VERSION,
            "float": self.unit.float_type,
            "poly_degree": self.poly_degree,
            "coils": list(self.coils),
            "sensors": [
                {
                    "name": s.name, "part": s.part, "frame": s.frame, "axes": list(s.axes),
                    "set_reset": s.set_reset,
                    "blocks": [[b.name, list(b.shape)] for b in self.sensor_blocks(s)],
                }
                for s in self.unit.sensors
            ],
            "unit_blocks": [[b.name, list(b.shape)] for b in self.unit_blocks()],
        }

    def layout_hash(self) -> int:
        """32-bit hash of the structure: a table is only accepted by code generated for it."""
        text = json.dumps(self.structure(), sort_keys=True, separators=(",", ":"))
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")

    def to_dict(self) -> dict:
        return {"poly_degree": self.poly_degree, "coils": list(self.coils)}

    @staticmethod
    def from_dict(unit: Unit, d: dict) -> "ChainSpec":
        return ChainSpec(unit, poly_degree=int(d.get("poly_degree", 3)),
                         coils=tuple(d.get("coils", ())))


# ---- the kernel: one definition, run on CasADi SX or on numpy float32 -----------------


class CoeffView:
    """Block access into a flat coefficient vector (values or symbols), row-major."""

    def __init__(self, flat, blocks):
        self._flat = flat
        self._blocks = {b.name: b for b in blocks}
        k = 0
        self._offsets = {}
        for b in blocks:
            self._offsets[b.name] = k
            k += b.size

    def scalar(self, name):
        return self._flat[self._offsets[name]]

    def get(self, name):
        b = self._blocks[name]
        k0 = self._offsets[name]
        vals = [self._flat[k0 + i] for i in range(b.size)]
        return _nest(vals, b.shape)


def _nest(vals, shape):
    if len(shape) <= 1:
        return vals if shape else vals[0]
    step = int(np.prod(shape[1:]))
    return [_nest(vals[i * step:(i + 1) * step], shape[1:]) for i in range(shape[0])]


def _horner(poly, dT):
    """poly[k] is the dT^k coefficient: ((p3 dT + p2) dT + p1) dT + p0."""
    acc = poly[-1]
    for k in range(len(poly) - 2, -1, -1):
        acc = acc * dT + poly[k]
    return acc


def _dot3(row, v):
    return row[0] * v[0] + row[1] * v[1] + row[2] * v[2]


def sensor_kernel(spec: ChainSpec, sensor: SensorSpec, raw, temp_C, coil_A, c: CoeffView,
                  u: CoeffView | None, half):
    """The arithmetic of the chain for one sensor and one sample.

    raw, coil_A: lists of scalars; temp_C: scalar (already clamped); c, u: coefficient
    views; half: the constant 0.5 in the backend's type. Works on any scalar type with
    + - * (CasADi SX, numpy float32/float64 arrays). Returns {output name: [scalars]}.
    """
    lsb = c.scalar("lsb_nT")
    zero = c.scalar("zero_count")
    out = {}
    # counts -> nT, sensor axes (seed 000 eq. 4 for SET/RESET)
    if sensor.set_reset:
        s, r = raw[0:3], raw[3:6]
        field_s = [(s[i] - r[i]) * half * lsb for i in range(3)]
        out["chip_offset_nT"] = [((s[i] + r[i]) * half - zero) * lsb for i in range(3)]
    else:
        field_s = [(raw[i] - zero) * lsb for i in range(3)]
    # axis mapping to the board frame (seed 000 eq. 1): structural, signs are exact
    idx, sign = sensor.axis_map()
    field_f = [field_s[idx[k]] if sign[k] > 0 else -field_s[idx[k]] for k in range(3)]
    # temperature polynomials by Horner (eq. 7)
    dT = temp_C - c.scalar("t_ref_C")
    b_poly = c.get("b_poly_nT")           # [k][i]
    M_poly = c.get("M_poly")              # [k][i][j]
    n = spec.poly_degree + 1
    b = [_horner([b_poly[k][i] for k in range(n)], dT) for i in range(3)]
    M = [[_horner([M_poly[k][i][j] for k in range(n)], dT) for j in range(3)] for i in range(3)]
    # offset and magnetorquer interference
    x = [field_f[i] - b[i] for i in range(3)]
    if spec.coils:
        K = c.get("K_nT_per_A")
        coil_nT = []
        for i in range(3):
            acc = K[i][0] * coil_A[0]
            for j in range(1, len(spec.coils)):
                acc = acc + K[i][j] * coil_A[j]
            coil_nT.append(acc)
        x = [x[i] - coil_nT[i] for i in range(3)]
    # calibration (eq. 5)
    B = [_dot3(M[i], x) for i in range(3)]
    # boom -> body (eq. 2-3)
    if sensor.frame == "boom":
        H = u.get("H_boom_to_body")
        B = [_dot3(H[i], B) for i in range(3)]
    out["field_body_nT"] = B
    return out


# ---- the Python reference: the wrapper logic and the kernel in float32 ----------------


def np_dtype(unit: Unit):
    return np.float32 if unit.float_type == "float32" else np.float64


def reference_sensor(spec: ChainSpec, sensor: SensorSpec, coeffs_sensor, coeffs_unit,
                     raw_counts, temp_C, coil_A=None):
    """Python reference of `<unit>_<sensor>_correct`, vectorised over samples.

    Each chain scalar is a numpy array over samples of the unit's float type, and every
    operation is an elementwise IEEE operation in the order of `sensor_kernel`: no BLAS,
    no reductions. raw_counts: int array (N, 6 or 3); temp_C: (N,) float (converted to the
    float type first, as the C API takes it); coil_A: (N, ncoil) or None (zeros).
    Returns dict of outputs (N, 3) arrays plus 'status' (N,) uint16.
    """
    ft = np_dtype(spec.unit)
    raw_counts = np.asarray(raw_counts)
    n = raw_counts.shape[0]
    temp = np.asarray(temp_C, dtype=np.float64).astype(ft)
    coeffs_sensor = np.asarray(coeffs_sensor, dtype=ft)
    blocks = spec.sensor_blocks(sensor)
    c = CoeffView([coeffs_sensor[k] for k in range(coeffs_sensor.size)], blocks)
    u = None
    if spec.unit_blocks():
        cu = np.asarray(coeffs_unit, dtype=ft)
        u = CoeffView([cu[k] for k in range(cu.size)], spec.unit_blocks())
    status = np.zeros(n, dtype=np.uint16)

    # wrapper: non-finite inputs
    nonfinite = ~np.isfinite(temp)
    coils = []
    if spec.coils:
        cA = np.zeros((n, len(spec.coils)), dtype=ft) if coil_A is None else \
            np.asarray(coil_A, dtype=np.float64).astype(ft)
        nonfinite |= ~np.all(np.isfinite(cA), axis=1)
        coils = [np.where(nonfinite, ft(0), cA[:, j]) for j in range(cA.shape[1])]
    status[nonfinite] |= STATUS_NONFINITE
    # wrapper: saturation at the part's rails
    sat = np.any((raw_counts <= sensor.count_min) | (raw_counts >= sensor.count_max), axis=1)
    status[sat] |= STATUS_SATURATED
    # wrapper: clamp to the calibrated range (C: if (t < t_min) ... else if (t > t_max) ...)
    t_min, t_max = c.scalar("t_min_C"), c.scalar("t_max_C")
    t = np.where(nonfinite, ft(0), temp)
    below, above = t < t_min, t > t_max
    t = np.where(below, t_min, np.where(above, t_max, t)).astype(ft)
    status[(below | above) & ~nonfinite] |= STATUS_TEMP_CLAMPED

    raw = [raw_counts[:, i].astype(ft) for i in range(raw_counts.shape[1])]
    with np.errstate(all="ignore"):
        out = sensor_kernel(spec, sensor, raw, t, coils, c, u, ft(0.5))
    result = {}
    for name, vals in out.items():
        arr = np.stack([np.broadcast_to(np.asarray(v, dtype=ft), (n,)) for v in vals], axis=1)
        arr = np.where(nonfinite[:, None], ft(0), arr).astype(ft)
        result[name] = arr
    result["status"] = status
    return result
