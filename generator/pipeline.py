"""The verbs' work, callable from Python: fit, apply, generate (the CLI is a thin shell)."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

from .chain import ChainSpec
from .coeffs import CoefficientSet
from .errors import InputError
from .telemetry import Telemetry, read_telemetry
from .unit import Unit, load_unit


class Progress:
    """One line per step on stderr, with elapsed time; silent when quiet."""

    def __init__(self, quiet=False, stream=None):
        import sys

        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()

    def __call__(self, message: str):
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=self.stream,
                  flush=True)


# ---- raw inputs of the chain from telemetry --------------------------------------------


def chain_inputs(tel: Telemetry, spec: ChainSpec, sensor_name: str) -> dict:
    """Raw counts, temperature and currents of one sensor as the flight API takes them.

    Returns raw_counts (N, 6|3) int64, temp_C (N,), coil_A (N, ncoil) or None, and
    present (N,) bool: False where a needed cell is missing (those rows are not run
    through the chain: a missing value is not a number the flight code would see).
    """
    s = spec.unit.sensor(sensor_name)
    if s.set_reset:
        cols = [f"{s.name}_set_{a}" for a in "xyz"] + [f"{s.name}_reset_{a}" for a in "xyz"]
    else:
        cols = [f"{s.name}_{a}" for a in "xyz"]
    counts = np.stack([tel.columns[c] for c in cols], axis=1)
    temp = tel.columns[f"{s.name}_temp_C"]
    present = np.all(np.isfinite(counts), axis=1) & np.isfinite(temp)
    raw = np.where(np.isfinite(counts), counts, s.zero_count).astype(np.int64)
    coil = None
    if spec.coils:
        if all(c in tel.columns for c in spec.coils):
            coil = np.stack([tel.columns[c] for c in spec.coils], axis=1)
            present &= np.all(np.isfinite(coil), axis=1)
            coil = np.where(np.isfinite(coil), coil, 0.0)
    return {"raw_counts": raw, "temp_C": np.where(np.isfinite(temp), temp, 0.0),
            "coil_A": coil, "present": present}


# ---- fit ----------------------------------------------------------------------------------


def fit(unit_path, data_paths, progress=None, method="auto") -> CoefficientSet:
    from .fit_thermal import fit_unit

    progress = progress or Progress(quiet=True)
    unit = load_unit(unit_path)
    progress(f"unit {unit.id}: {len(unit.sensors)} sensors")
    tels = []
    for p in data_paths:
        tel = read_telemetry(p, unit)
        progress(f"read {p}: {tel.n} samples, {len(tel.columns)} columns")
        tels.append(tel)
    cals = fit_unit(unit, tels, progress=progress)
    info = {"sources": [str(p) for p in data_paths], "unit_file": str(unit_path),
            "method": method}
    return CoefficientSet.from_calibrations(unit, cals, fit_info=info)


# ---- apply --------------------------------------------------------------------------------


def apply(cs: CoefficientSet, data_path, out_path, host=None, progress=None) -> dict:
    """Correct a telemetry file through the compiled flight C; write the ICD output CSV.

    Returns per-sensor outputs (field_body_nT, status, valid) for callers and tests.
    """
    from .host import HostUnit

    progress = progress or Progress(quiet=True)
    tel = read_telemetry(data_path, cs.unit)
    host = host or HostUnit(cs)
    results = {}
    for s in cs.unit.sensors:
        inp = chain_inputs(tel, cs.spec, s.name)
        out = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"])
        valid = (out["status"] == 0) & inp["present"]
        results[s.name] = {"field_body_nT": out["field_body_nT"], "status": out["status"],
                           "valid": valid, "present": inp["present"]}
        progress(f"{s.name}: {int(valid.sum())} of {tel.n} samples valid")
    write_apply_csv(out_path, tel, cs.unit, results)
    return results


def write_apply_csv(out_path, tel: Telemetry, unit: Unit, results: dict):
    header = ["time_s"]
    for s in unit.sensors:
        header += [f"{s.name}_x_nT", f"{s.name}_y_nT", f"{s.name}_z_nT", f"{s.name}_valid",
                   f"{s.name}_status"]
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_suffix(out_path.suffix + ".part")
    with open(tmp, "w", newline="") as f:
        f.write(f"# magcal apply: calibrated field in the body frame, from {tel.path}\n")
        f.write("# <s>_status: bits NONFINITE=1 SATURATED=2 TEMP_CLAMPED=4; valid = status 0\n")
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        t = tel.time_s
        cols = []
        for s in unit.sensors:
            r = results[s.name]
            cols.append((r["field_body_nT"], r["valid"], r["status"], r["present"]))
        for i in range(tel.n):
            row = [_fmt(t[i])]
            for field, valid, status, present in cols:
                if present[i]:
                    row += [_fmt(field[i, 0]), _fmt(field[i, 1]), _fmt(field[i, 2])]
                else:
                    row += ["", "", ""]
                row += ["1" if valid[i] else "0", str(int(status[i]))]
            w.writerow(row)
    tmp.replace(out_path)   # nothing half-written


def _fmt(v) -> str:
    # shortest repr that round-trips the value (float32 outputs stay exact)
    return str(v.item() if hasattr(v, "item") else v) if np.isfinite(v) else ""


def save_json(path, obj):
    Path(path).write_text(json.dumps(obj, indent=1, default=_default) + "\n")


def _default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(type(o))


__all__ = ["Progress", "chain_inputs", "fit", "apply", "write_apply_csv", "InputError"]
