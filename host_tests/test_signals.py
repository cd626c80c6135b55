"""A long verb stopped by SIGINT or SIGTERM: the shell's exit status (128 + signal number),
one line on stderr, and no temporary output left behind (the `with` blocks unwind)."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _start_demo(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "generator.cli", "demo", "-o", "out"],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for_tmp(proc, tmp_path, limit_s=120.0):
    """Wait until the demo is writing its temporary folder (so the signal lands mid-work)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < limit_s:
        if proc.poll() is not None:
            pytest.fail(f"demo ended before the signal: {proc.returncode}")
        if any(p.name.endswith(".tmp") for p in tmp_path.iterdir()):
            return
        time.sleep(0.05)
    pytest.fail("the demo never started writing")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_exits_by_convention_and_leaves_nothing(tmp_path, sig):
    proc = _start_demo(tmp_path)
    _wait_for_tmp(proc, tmp_path)
    time.sleep(0.5)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    lines = [ln for ln in err.splitlines() if ln.strip() and ln.startswith("magcal")]
    assert lines and lines[-1] in ("magcal: interrupted", "magcal: terminated"), err
    assert "Traceback" not in err
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == [], left


def test_a_report_with_figure_workers_leaves_stderr_clean(tmp_path, fm1_dir):
    """The report draws its figures in forked workers, which the pool ends with SIGTERM:
    they inherit the verb's SIGTERM handler, which must end them quietly (no
    '_Terminated' traceback on the stderr of a successful fit)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    data = Path(fm1_dir)
    proc = subprocess.run([sys.executable, "-m", "generator.cli", "fit", str(data / "unit.toml"),
                           str(data / "rotation.csv"), "-o", "fit"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "Terminated" not in proc.stderr, proc.stderr
