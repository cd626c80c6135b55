"""Batch protocol shared by the peer adapters (runs inside a peer's throwaway venv, so it
uses only the standard library and numpy; nothing from the magcal-samsat package).

    python <adapter>.py JOBS.json RESULTS.json

JOBS.json: {"jobs": [{"id": str, "npy": path to (N, 3) float64 readings in uT}, ...]}.
RESULTS.json (rewritten after every job, so a batch cut short by a timeout keeps what it
finished): {"peer": name, "version": installed version, "results": {id: {"offset_uT":
[3], "matrix": [[3x3]], "seconds": fit wall time, "error": null or "Type: first line",
"note": null or what the peer said about its own result (e.g. an optimiser's stop
reason)}}}.

Convention of the returned calibration: B_cal = matrix @ (reading - offset_uT). The scale
of `matrix` is whatever the peer returns (most map to a unit sphere); the harness rescales.
"""

from __future__ import annotations

import json
import sys
import time
import traceback
from importlib import metadata

import numpy as np


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()


def run(peer_name: str, distribution: str | None, fit) -> int:
    """fit(readings_uT (N, 3)) -> (offset_uT (3,), matrix (3, 3)[, note str])."""
    jobs_path, out_path = sys.argv[1], sys.argv[2]
    jobs = json.loads(open(jobs_path).read())["jobs"]
    version = metadata.version(distribution) if distribution else "bench reimplementation"
    out = {"peer": peer_name, "version": version, "python": sys.version.split()[0],
           "results": {}}
    for job in jobs:
        x = np.load(job["npy"])
        entry = {"offset_uT": None, "matrix": None, "seconds": None, "error": None,
                 "note": None}
        t0 = time.perf_counter()
        try:
            offset, matrix, *note = fit(x)
            entry["seconds"] = time.perf_counter() - t0
            entry["note"] = note[0] if note else None
            offset = np.asarray(offset, float).reshape(3)
            matrix = np.asarray(matrix, float).reshape(3, 3)
            if not (np.all(np.isfinite(offset)) and np.all(np.isfinite(matrix))):
                entry["error"] = "non-finite offset or matrix returned"
            else:
                entry["offset_uT"] = offset.tolist()
                entry["matrix"] = matrix.tolist()
        except Exception as exc:  # noqa: BLE001 - the table reports whatever a peer raises
            entry["seconds"] = time.perf_counter() - t0
            entry["error"] = first_line(exc)
            entry["traceback_tail"] = traceback.format_exc().strip().splitlines()[-3:]
        out["results"][job["id"]] = entry
        with open(out_path, "w") as f:
            json.dump(out, f)
    return 0
