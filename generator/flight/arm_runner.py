"""Running a unit's flight C on the emulated Cortex-M4F, and the shared test vectors.

The QEMU command line, a job for the runner (Job: the commands of templates/arm/runner.c.j2
and the reader of their results), ArmUnit (the target build, callable like host.HostUnit),
and random_inputs (the vectors of the host and the target tests).
"""

from __future__ import annotations

import struct
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from generator.flight.chain import ChainSpec, is_physical, np_dtype
from generator.flight.codegen import template_context
from generator.flight.coeffs import CoefficientSet
from generator.flight.arm_build import (CMD, DONE, JOB_FILE, MACHINE, MAGIC, OUT_FILE,
                                        PROTOCOL, TOOLS, ArmRunError, Entry, build,
                                        chain_features, entry_points, qemu_version)



# ---- running -------------------------------------------------------------------------


def qemu_command(elf: Path, trace_log: Path | None = None, icount: bool = False) -> list:
    cmd = [TOOLS["qemu"], "-M", MACHINE, "-nographic", "-monitor", "none",
           "-semihosting-config", "enable=on,target=native", "-kernel", str(elf)]
    if icount:
        cmd += ["-icount", "shift=0,align=off,sleep=off"]
    if trace_log is not None:
        # one guest instruction per translation block, every block execution logged
        if qemu_version() >= (8, 1):
            cmd += ["-accel", "tcg,one-insn-per-tb=on"]
        else:
            cmd += ["-singlestep"]
        cmd += ["-d", "exec,nochain", "-D", str(trace_log)]
    return cmd


def run_job(elf: Path, job: bytes, trace: bool = False, icount: bool = False,
            timeout: float = 120.0):
    """Run the runner on a job; returns (output bytes, trace log text or None)."""
    with tempfile.TemporaryDirectory(prefix="magcal-qemu-") as d:
        d = Path(d)
        (d / JOB_FILE).write_bytes(job)
        log = d / "trace.log" if trace else None
        cmd = qemu_command(elf, log, icount)
        try:
            p = subprocess.run(cmd, cwd=d, stdin=subprocess.DEVNULL, capture_output=True,
                               timeout=timeout)
        except subprocess.TimeoutExpired:
            raise ArmRunError(f"QEMU did not exit within {timeout} s: {' '.join(cmd)}") \
                from None
        if p.returncode != 0:
            raise ArmRunError(f"runner exit status {p.returncode}: {' '.join(cmd)}\n"
                              f"{p.stdout.decode(errors='replace')}"
                              f"{p.stderr.decode(errors='replace')}")
        out = (d / OUT_FILE).read_bytes()
        text = log.read_text(errors="replace") if log is not None else None
    if len(out) < 8 or struct.unpack_from("<I", out, 0)[0] != MAGIC or \
            struct.unpack_from("<I", out, len(out) - 4)[0] != DONE:
        raise ArmRunError("runner output is incomplete")
    return out[4:-4], text


class Job:
    """Writer of a runner job (see runner.c.j2) and reader of what the runner returns."""

    def __init__(self, cs: CoefficientSet):
        self.cs = cs
        self.spec: ChainSpec = cs.spec
        self.ft = np_dtype(self.spec.unit)
        self.dtype = np.dtype(self.ft).newbyteorder("<")
        self.feat = chain_features(cs)
        self.n_sensors = len(self.spec.unit.sensors)
        self.entries = {(e.kind, e.sensor): e for e in entry_points(cs)}
        self.parts = [struct.pack("<IIII", MAGIC, PROTOCOL, self.spec.layout_hash(),
                                  self.dtype.itemsize)]
        self.reads = []   # (entry or "calibrate"/"ext", n, measured) per output command
        r, S, f = self.dtype, self.n_sensors, self.feat
        self.rec_in = {
            "sensor": np.dtype([("raw", "<i4", 6), ("temp", r), ("aux", "<u4"),
                                ("coil", r, max(1, f["n_coils"])),
                                ("channel", r, max(1, f["n_channels"])), ("rate", r, 3),
                                ("dt", r), ("state", "<u4"), ("offset", r, 3),
                                ("reading", r, 6)]),
            "select": np.dtype([("fields", r, (S, 3)), ("status", "<u4", S)]),
        }
        meas = [("stack", "<u4"), ("ticks", "<u4")]
        out_s = [("field", r, 3), ("chip", r, 3), ("offs", r, 3), ("temp_el", r),
                 ("status", "<u4")]
        out_sel = [("status", "<u4", S), ("field", r, 3), ("sensor", "<i4"), ("rank", "<i4"),
                   ("reason", "<u4")]
        self.rec_out = {("sensor", False): np.dtype(out_s),
                        ("sensor", True): np.dtype(out_s + meas),
                        ("select", False): np.dtype(out_sel),
                        ("select", True): np.dtype(out_sel + meas)}

    def entry(self, kind, sensor=None) -> Entry:
        try:
            return self.entries[(kind, sensor)]
        except KeyError:
            raise ValueError(f"the generated API has no {kind} for {sensor}") from None

    # ---- commands ----
    def coeffs(self, flat):
        flat = np.asarray(flat, dtype=np.float64).astype(self.dtype)
        self.parts.append(struct.pack("<II", CMD["COEFFS"], flat.size) + flat.tobytes())

    def defaults(self):
        self.parts.append(struct.pack("<I", CMD["DEFAULTS"]))

    def _sensor_records(self, sensor, raw, temp, coil, set_only, aux=None, state=True,
                        offset_counts=None):
        """The records of one command: successive calls on one sensor state, empty at the
        first (as chain.reference_sensor). aux: {'channels': (N, n), 'rate_dps': (N, 3),
        'dt_s': (N,)} (any present, or coil, makes aux non-NULL); state False: pass NULL;
        offset_counts: _correct_set's stored offset per call (NaN rows: none)."""
        s = self.spec.unit.sensor(sensor)
        physical = is_physical(s)   # readings in the float type (as HostUnit), else counts
        raw = np.asarray(raw, dtype=np.float64).astype(self.ft) if physical \
            else np.asarray(raw, dtype=np.int64)
        n = raw.shape[0]
        assert raw.shape == (n, 3 if set_only or not s.set_reset else 6), raw.shape
        a = np.zeros(n, dtype=self.rec_in["sensor"])
        a["reading" if physical else "raw"][:, :raw.shape[1]] = raw
        a["temp"] = np.asarray(temp, dtype=np.float64).astype(self.ft)
        aux = {k: v for k, v in (aux or {}).items() if v is not None}
        if self.feat["has_aux"] and (coil is not None or aux):
            a["aux"] = 1
        if coil is not None and self.feat["n_coils"]:
            a["coil"][:, :self.feat["n_coils"]] = np.asarray(coil, np.float64).astype(self.ft)
        if "channels" in aux:
            ch = aux["channels"]
            if isinstance(ch, dict):   # {column name: (N,)} as chain.reference_sensor takes
                names = [c["name"] for c in template_context(self.cs).get("channels", [])]
                ch = np.stack([np.asarray(ch.get(nm, np.zeros(n)), np.float64) for nm in names],
                              axis=1) if names else np.zeros((n, 0))
            a["channel"][:, :self.feat["n_channels"]] = np.asarray(ch, np.float64).astype(self.ft)
        if "rate_dps" in aux:
            a["rate"] = np.asarray(aux["rate_dps"], np.float64).astype(self.ft)
        if "dt_s" in aux:
            a["dt"] = np.asarray(aux["dt_s"], np.float64).astype(self.ft)
        a["state"] = 0 if state is False else 1
        a["offset"] = np.nan if offset_counts is None else np.asarray(offset_counts, self.ft)
        return a

    def _select_records(self, fields, statuses):
        st = np.asarray(statuses, dtype=np.int64)
        a = np.zeros(st.shape[0], dtype=self.rec_in["select"])
        a["fields"] = np.asarray(fields, dtype=self.ft)
        a["status"] = st
        return a

    def _add(self, entry: Entry, records, reps):
        n = records.shape[0]
        if reps is None:
            head = struct.pack("<III", CMD["CORRECT"], entry.id, n)
        else:
            head = struct.pack("<IIII", CMD["MEASURE"], entry.id, n, reps)
        self.parts.append(head + records.tobytes())
        self.reads.append((entry, n, reps is not None))

    def correct(self, sensor, raw, temp, coil=None, reps=None, aux=None, state=True):
        self._add(self.entry("correct", sensor),
                  self._sensor_records(sensor, raw, temp, coil, False, aux, state), reps)

    def correct_set(self, sensor, set_counts, temp, offset_counts, coil=None, reps=None,
                    aux=None, state=True):
        self._add(self.entry("correct_set", sensor),
                  self._sensor_records(sensor, set_counts, temp, coil, True, aux, state,
                                       offset_counts), reps)

    def select(self, fields, statuses, reps=None):
        self._add(self.entry("select"), self._select_records(fields, statuses), reps)

    def call(self, kind, *args, reps=None, **kw):
        getattr(self, kind)(*args, reps=reps, **kw)

    def calibrate(self, reps):
        self.parts.append(struct.pack("<II", CMD["CALIBRATE"], reps))
        self.reads.append(("calibrate", reps, False))

    def ext(self, payload: bytes):
        self.parts.append(struct.pack("<II", CMD["EXT"], len(payload)) + payload)
        self.reads.append(("ext", len(payload), False))

    def bytes(self) -> bytes:
        return b"".join(self.parts) + struct.pack("<I", CMD["END"])

    # ---- results ----
    def parse(self, out: bytes) -> list:
        """One result per output-writing command, in order (dicts shaped like HostUnit's)."""
        pos, results = 0, []
        ft = self.ft
        for what, n, meas in self.reads:
            if what == "calibrate":
                t = struct.unpack_from("<II", out, pos)
                pos += 8
                results.append({"ticks_nops": t[0], "ticks_empty": t[1]})
                continue
            if what == "ext":
                rc, k = struct.unpack_from("<iI", out, pos)
                results.append({"rc": rc, "data": out[pos + 8:pos + 8 + k]})
                pos += 8 + k
                continue
            e: Entry = what
            group = "select" if e.kind == "select" else "sensor"
            dt = self.rec_out[(group, meas)]
            if pos + dt.itemsize * n > len(out):
                raise ArmRunError("runner output is shorter than the job asks for")
            a = np.frombuffer(out, dtype=dt, count=n, offset=pos)
            pos += dt.itemsize * n
            if e.kind == "select":
                res = {"status": a["status"].astype(np.uint16),
                       "field_body_nT": a["field"].astype(ft),
                       "sensor": a["sensor"].astype(np.int64),
                       "rank": a["rank"].astype(np.int64),
                       "reason": a["reason"].astype(np.int64)}
            else:
                res = {"field_body_nT": a["field"].astype(ft),
                       "status": a["status"].astype(np.uint16)}
                if e.kind == "correct" and self.spec.unit.sensor(e.sensor).set_reset:
                    res["chip_offset_nT"] = a["chip"].astype(ft)
                    res["offset_counts"] = a["offs"].astype(ft)
            if meas:
                res["stack"] = a["stack"].astype(int)
                res["ticks"] = a["ticks"].astype(int)
            results.append(res)
        if pos != len(out):
            raise ArmRunError(f"runner wrote {len(out)} bytes, expected {pos}")
        return results


class ArmUnit:
    """A unit's flight C on the emulated Cortex-M4F, callable like host.HostUnit."""

    def __init__(self, cs: CoefficientSet, sources: dict | None = None,
                 extra_sources: dict | None = None, casadi_files: tuple = ()):
        self.cs = cs
        self.spec = cs.spec
        self.dtype = np_dtype(self.spec.unit)
        self.build = build(cs, sources, extra_sources, casadi_files)

    def flat_coeffs(self, cs: CoefficientSet | None = None) -> np.ndarray:
        cs = cs or self.cs
        parts = [cs.flat_sensor(s.name) for s in self.spec.unit.sensors] + [cs.flat_unit()]
        return np.concatenate(parts).astype(self.dtype)

    def run(self, calls, coeffs_flat=None, timeout=120.0) -> list:
        """Many calls in one QEMU run: calls are (kind, *args[, {keyword args}]) with kind
        "correct" (sensor, raw, temp, coil), "correct_set" (sensor, set_counts, temp,
        offset_counts, coil) or "select" (fields, statuses); keyword args: aux, state
        (see Job). coeffs_flat None: the compiled-in defaults, else an uploaded table.
        Returns one dict per call, shaped as HostUnit's methods return them."""
        job = Job(self.cs)
        if coeffs_flat is None:
            job.defaults()
        else:
            job.coeffs(coeffs_flat)
        for kind, *args in calls:
            kw = args.pop() if args and isinstance(args[-1], dict) else {}
            job.call(kind, *args, **kw)
        out, _ = run_job(self.build.elf, job.bytes(), timeout=timeout)
        return job.parse(out)

    def correct(self, sensor, raw_counts, temp_C, coil_A=None, coeffs_flat=None,
                **kw) -> dict:
        return self.run([("correct", sensor, raw_counts, temp_C, coil_A, kw)], coeffs_flat)[0]

    def correct_set(self, sensor, set_counts, temp_C, offset_counts, coil_A=None,
                    coeffs_flat=None, **kw) -> dict:
        return self.run([("correct_set", sensor, set_counts, temp_C, offset_counts, coil_A,
                          kw)], coeffs_flat)[0]

    def select(self, fields, statuses, coeffs_flat=None) -> dict:
        return self.run([("select", fields, statuses)], coeffs_flat)[0]


def random_inputs(rng, sensor, n, n_coils=0, t_range=(-20.0, 55.0)):
    """Counts over the part's range (half near zero field), temperatures across and beyond
    the calibrated range, currents +-0.2 A: the vectors of the host and the target tests."""
    k = 6 if sensor.set_reset else 3
    raw = rng.integers(sensor.count_min, sensor.count_max + 1, (n, k))
    near = rng.random(n) < 0.5
    span = int(80000 / sensor.lsb_nT)
    raw[near] = np.clip(sensor.zero_count + rng.integers(-span, span + 1, (near.sum(), k)),
                        sensor.count_min, sensor.count_max)
    temp = rng.uniform(t_range[0] - 20, t_range[1] + 20, n).astype(np.float32)
    coil = rng.uniform(-0.2, 0.2, (n, n_coils)) if n_coils else None
    return raw, temp, coil
