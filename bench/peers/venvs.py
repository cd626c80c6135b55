"""Throwaway virtual environments for the peers: one per peer, in a temporary directory,
populated from PyPI with pip, used through subprocesses only (nothing of a peer is ever
imported into this process or installed into the project's environment)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ADAPTERS = Path(__file__).resolve().parent / "adapters"

# Single-threaded numerics everywhere, so a fit's wall time is comparable between the
# peers' processes and ours (run.py sets the same before importing numpy).
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass
class Venv:
    name: str
    requirement: str | None            # pip requirement, None: run with this interpreter
    path: Path | None = None
    python: str = sys.executable
    ok: bool = False
    install_s: float = 0.0
    error: str | None = None            # why it failed to install
    versions: dict = field(default_factory=dict)   # distribution -> version


def _first_error_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in lines:
        if ln.startswith("ERROR:") or "Error" in ln.split(":")[0]:
            return ln
    return lines[-1] if lines else "(no output)"


def create(name: str, requirement: str | None, root: Path, timeout_s: float = 600.0) -> Venv:
    """python -m venv ROOT/NAME, then pip install REQUIREMENT into it. Never raises: a
    failure is recorded in .error (the first error line pip printed)."""
    v = Venv(name, requirement)
    if requirement is None:
        v.ok = True
        return v
    v.path = root / name
    t0 = time.perf_counter()
    try:
        # A venv without its own pip, populated by this interpreter's pip (--python, pip >=
        # 22.3): saves bootstrapping pip into every venv. --no-compile: no .pyc at install.
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(v.path)],
                       check=True, capture_output=True, text=True, timeout=timeout_s)
        v.python = str(v.path / "bin" / "python")
        p = subprocess.run([sys.executable, "-m", "pip", "--python", v.python, "install",
                            "--disable-pip-version-check", "--no-input", "--no-compile", "-q",
                            requirement], capture_output=True, text=True, timeout=timeout_s)
        if p.returncode != 0 and "no such option: --python" in p.stderr:
            subprocess.run([v.python, "-m", "ensurepip", "-q"], check=True,
                           capture_output=True, text=True, timeout=timeout_s)
            p = subprocess.run([v.python, "-m", "pip", "install", "--disable-pip-version-check",
                                "--no-input", "--no-compile", "-q", requirement],
                               capture_output=True, text=True, timeout=timeout_s)
        if p.returncode != 0:
            v.error = f"pip install {requirement}: " + _first_error_line(p.stderr + p.stdout)
        else:
            v.ok = True
            v.versions = installed_versions(v.python)
    except subprocess.TimeoutExpired:
        v.error = f"pip install {requirement}: no answer within {timeout_s:.0f} s"
    except (subprocess.CalledProcessError, OSError) as e:
        v.error = f"venv: {type(e).__name__}: {e}"
    v.install_s = time.perf_counter() - t0
    return v


def installed_versions(python: str) -> dict:
    code = ("import json, importlib.metadata as m; "
            "print(json.dumps({d.metadata['Name']: d.version for d in m.distributions()}))")
    p = subprocess.run([python, "-c", code], capture_output=True, text=True, timeout=120)
    return json.loads(p.stdout) if p.returncode == 0 else {}


def run_batch(venv: Venv, adapter: str, jobs: list, work: Path, timeout_s: float) -> dict:
    """Run one adapter over all jobs in one subprocess of the venv. Returns the adapter's
    results dict ({"version", "results": {id: ...}}) plus "batch_error" when the process
    failed or timed out (jobs it did not reach are then absent)."""
    jobs_path = work / f"jobs_{venv.name}.json"
    out_path = work / f"results_{venv.name}.json"
    jobs_path.write_text(json.dumps({"jobs": jobs}))
    out_path.unlink(missing_ok=True)
    env = {**os.environ, **THREAD_ENV, "MPLBACKEND": "Agg"}
    env.pop("PYTHONPATH", None)
    batch_error = None
    try:
        p = subprocess.run([venv.python, str(ADAPTERS / adapter), str(jobs_path), str(out_path)],
                           capture_output=True, text=True, timeout=timeout_s, env=env,
                           cwd=str(work))
        if p.returncode != 0:
            batch_error = "adapter exited with status %d: %s" % (
                p.returncode, _first_error_line(p.stderr))
    except subprocess.TimeoutExpired:
        batch_error = f"batch stopped after {timeout_s:.0f} s (time limit)"
    result = json.loads(out_path.read_text()) if out_path.exists() else {"results": {}}
    if batch_error:
        result["batch_error"] = batch_error
    return result
