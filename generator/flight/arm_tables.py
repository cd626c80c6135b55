"""The flight table code on the emulated Cortex-M4F, and the same operations on the host.

The unit's `<unit>_table.c` is part of its flight sources and is built for the target with
the flight flags like the rest (generator.flight.arm_build.build). A small runner extension
(templates/arm/table_ext.c.j2, test code only) drives its API through the runner's EXT
command: init (compiled-in or given defaults), validate, load, receive_part, commit,
abort, and the active coefficients. `ArmTables.run(ops)` runs a list of operations in one
QEMU run; `host_results(TableHost, ops)` runs the same list through the cffi build, and
`python_results(spec, ops)` through the ground code (table_manager.TableManager), so the tests
compare the three result by result.

    ops: ("init",) | ("init_values", flat) | ("validate", table) | ("load", table)
         | ("receive_part", part) | ("commit",) | ("abort",) | ("active",)
         | ("fill", byte) | ("prepared",) | ("correct", readings, temps_C)

("fill", b) makes the manager one that init never ran on, every byte b (its Python model:
TableManager(spec) without defaults). ("correct", readings, temps_C) runs one cycle of
every sensor's correction and select on the prepared set the manager hands out
(table_host.c, linked into the runner too): readings[k] sensor k's 3 (SET/RESET: 6)
values. Each result is (status, bad value index, active serial, coeffs_valid, last
status) as ints, or for "active" / "prepared" the bit pattern of the coefficients /
prepared coefficients handed out, for "correct" the outputs' bytes (correct_bytes); the
Python model answers None to "correct" (the chain's own tests compare the corrections
with the Python reference).
"""

from __future__ import annotations

import struct

import numpy as np

from generator.flight.coeffs import CoefficientSet
from generator.flight.table_manager import TableManager
from generator.flight.tables import (NO_INDEX, TableError, TableStatus,
                                     check_table, value_dtype)
from generator.flight.arm_build import EXT_MAX, ArmRunError, _arm_env
from generator.flight.arm_runner import ArmUnit, Job, run_job
from generator.flight.codegen import template_context
from generator.flight.table_host import host_sources

OPS = {"init": 0, "init_values": 1, "validate": 2, "load": 3, "receive_part": 4,
       "commit": 5, "abort": 6, "active": 7, "fill": 8, "prepared": 9, "correct": 10}
BYTES_OPS = ("active", "prepared", "correct")   # answered with bytes
EXT_FILE = "table_ext.c"


def ext_source(cs: CoefficientSet) -> str:
    return _arm_env().get_template("table_ext.c.j2").render(**template_context(cs))


def _cycle_input(spec, readings, temps_C) -> np.ndarray:
    """(S, 9) float64: per sensor 8 reading slots (3, or SET then RESET 6) and its
    temperature, the layout of host_table_correct_all and of the runner's op 10."""
    sensors = spec.unit.sensors
    out = np.zeros((len(sensors), 9))
    for k, s in enumerate(sensors):
        v = np.asarray(readings[k], dtype=np.float64)
        assert v.shape == ((6,) if s.set_reset else (3,)), (s.name, v.shape)
        out[k, :v.size] = v
        out[k, 8] = float(temps_C[k])
    return out


def correct_bytes(c: dict) -> bytes:
    """A TableHost.correct_all result as the runner's op 10 answers it (little-endian):
    fields, statuses of the corrections, statuses after select, the selected field, its
    sensor and reason."""
    def le(a, dt):
        return np.ascontiguousarray(a).astype(np.dtype(dt).newbyteorder("<")).tobytes()
    real = c["field_body_nT"].dtype
    return (le(c["field_body_nT"], real) + le(c["status"], np.uint16)
            + le(c["sel_status"], np.uint16) + le(c["sel_field_body_nT"], real)
            + struct.pack("<bB", c["sel_sensor"], c["sel_reason"]))


def _payload(spec, op) -> bytes:
    kind, *args = op
    code = bytes([OPS[kind]])
    if kind == "init_values":
        flat = np.asarray(args[0]).astype(value_dtype(spec), copy=False)
        return code + flat.tobytes()
    if kind in ("validate", "load", "receive_part"):
        return code + bytes(args[0])
    if kind == "fill":
        return code + bytes([args[0]])
    if kind == "correct":
        return code + _cycle_input(spec, *args).astype("<f8").tobytes()
    return code


class ArmTables:
    """The unit's flight table code on the emulated Cortex-M4F (qemu mps2-an386)."""

    def __init__(self, cs: CoefficientSet):
        self.cs = cs
        self.spec = cs.spec
        helpers = host_sources(cs)
        self.arm = ArmUnit(cs, extra_sources={EXT_FILE: ext_source(cs),
                                              "table_host.c": helpers["table_host.c"],
                                              "table_host.h": helpers["table_host.h"]})

    def run(self, ops, timeout=300.0) -> list:
        job = Job(self.cs)
        for op in ops:
            payload = _payload(self.spec, op)
            if len(payload) > EXT_MAX:
                raise ValueError(f"{op[0]}: {len(payload)} bytes, the runner takes {EXT_MAX}")
            job.ext(payload)
        out, _ = run_job(self.arm.build.elf, job.bytes(), timeout=timeout)
        results = []
        for op, r in zip(ops, job.parse(out)):
            if op[0] in BYTES_OPS:
                if r["rc"] != 0:
                    raise ArmRunError(f"{op[0]}: runner extension answered {r['rc']}")
                results.append(bytes(r["data"]))
                continue
            if len(r["data"]) != 20:
                raise ArmRunError(f"{op[0]}: runner extension answered {r['rc']} with "
                                  f"{len(r['data'])} bytes")
            results.append(struct.unpack("<5I", r["data"]))
        return results


def host_results(h, ops) -> list:
    """The same operations through the flight table code built for the host
    (table_host.TableHost)."""
    results, mgr = [], None
    for kind, *args in ops:
        bad = None
        if kind == "init":
            mgr, st = h.init()
        elif kind == "init_values":
            mgr, st = h.init(np.asarray(args[0]).astype(h.dtype))
        elif kind == "validate":
            st, bad = h.validate_detail(args[0])
        elif kind == "active":
            results.append(h.active_flat(mgr).tobytes())
            continue
        elif kind == "prepared":
            results.append(h.prepared_flat(mgr).tobytes())
            continue
        elif kind == "correct":
            results.append(correct_bytes(h.correct_all(mgr, *args)))
            continue
        elif kind == "fill":
            mgr = h.uninitialised(args[0])
            st = TableStatus.OK
        elif kind == "abort":
            h.abort(mgr)
            st = TableStatus.OK
        else:
            st = getattr(h, kind)(mgr, *args)
        info = h.info(mgr) if mgr is not None else None
        if bad is None:
            bad = info["last_bad_value"]
        results.append(_row(st, bad, info))
    return results


def _row(st, bad, info) -> tuple:
    if info is None:
        return (int(st), int(bad), 0, 0, 0)
    return (int(st), int(bad), int(info["active_serial"]), int(info["coeffs_valid"]),
            int(info["last_status"]))


def python_results(spec, default_values, ops) -> list:
    """The same operations through the ground code (tables.check_table, TableManager);
    ("init",) starts from default_values (the unit's compiled-in defaults)."""
    results, m = [], None
    for kind, *args in ops:
        if kind in ("init", "init_values"):
            m = TableManager(spec, default_values if kind == "init" else args[0])
            st = m.init_status
        elif kind == "fill":      # a single-byte fill is never the init mark
            m = TableManager(spec)
            st = TableStatus.OK
        elif kind == "validate":
            try:
                check_table(args[0], spec)
                st, bad = TableStatus.OK, NO_INDEX
            except TableError as e:
                st = e.status
                bad = NO_INDEX if e.bad_value_index is None else e.bad_value_index
            tail = (0, 0, 0) if m is None else \
                (m.active_serial, int(m.coeffs_valid), int(m.last_status))
            results.append((int(st), int(bad)) + tuple(int(x) for x in tail))
            continue
        elif kind == "correct":
            results.append(None)
            continue
        elif kind in BYTES_OPS:
            v = m.active_values if kind == "active" else m.prepared
            results.append(np.ascontiguousarray(v).astype(
                v.dtype.newbyteorder("<")).tobytes())
            continue
        elif kind == "abort":
            m.abort()
            st = TableStatus.OK
        elif kind == "commit":
            st = m.commit()[0]
        else:
            st = getattr(m, kind)(*args)
        results.append((int(st), int(m.last_bad), int(m.active_serial), int(m.coeffs_valid),
                        int(m.last_status)))
    return results
