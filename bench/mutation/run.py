"""Mutation check: apply each curated mutation (mutations.py) alone to a scratch copy of
the checkout, run only the tests it names (never test_generated.py, never a regenerated
generated/), and count it killed when those tests fail. Writes docs/mutation.md.

    python3 bench/mutation/run.py [--only ID ...] [--out docs/mutation.md] [--timeout S]

Shared data: ../shared beside the checkout, or MAGCAL_SHARED.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path.insert(0, str(HERE))
from mutations import MUTATIONS  # noqa: E402


def scratch_copy(dest: Path) -> None:
    files = subprocess.run(["git", "-C", str(REPO), "ls-files", "-co", "--exclude-standard"],
                           capture_output=True, text=True, check=True).stdout.split("\n")
    for f in filter(None, files):
        src = REPO / f
        if src.is_file():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f)


def apply(root: Path, mutation) -> None:
    for f, old, new in mutation.edits:
        p = root / f
        text = p.read_text()
        n = text.count(old)
        if n != 1:
            raise ValueError(f"{mutation.id}: {f}: the text to replace occurs {n} times")
        p.write_text(text.replace(old, new))


def run_tests(root: Path, tests, timeout) -> tuple:
    env = dict(os.environ, PYTHONPATH=str(root), PYTHONDONTWRITEBYTECODE="1")
    env.setdefault("MAGCAL_SHARED", str(REPO.parent / "shared"))
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
           "--deselect", "host_tests/test_generated.py", *tests]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True,
                           timeout=timeout)
        rc, out = p.returncode, p.stdout
    except subprocess.TimeoutExpired:
        rc, out = "timeout", ""
    fails = [ln for ln in out.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    last = (out.strip().splitlines() or [""])[-1]
    return rc, time.perf_counter() - t0, fails[0] if fails else last


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--out", default=str(REPO / "docs" / "mutation.md"))
    ap.add_argument("--timeout", type=float, default=900)
    args = ap.parse_args(argv)
    todo = [m for m in MUTATIONS if args.only is None or m.id in args.only]
    assert not any("test_generated" in t for m in todo for t in m.tests)
    rows = []
    with tempfile.TemporaryDirectory(prefix="magcal_mut_") as tmp:
        base = Path(tmp) / "base"
        base.mkdir()
        scratch_copy(base)
        # the unmutated tests must pass first, else a "kill" means nothing
        tests = sorted({t for m in todo for t in m.tests})
        rc, secs, line = run_tests(base, tests, args.timeout)
        print(f"baseline: exit {rc} in {secs:.0f} s: {line}", flush=True)
        if rc != 0:
            print("the unmutated tests fail: no mutation run", file=sys.stderr)
            return 1
        for m in todo:
            root = Path(tmp) / m.id
            shutil.copytree(base, root)
            apply(root, m)
            rc, secs, line = run_tests(root, list(m.tests), args.timeout)
            killed = rc not in (0, 5)          # 5: no tests collected
            rows.append((m, killed, rc, secs, line))
            print(f"{'KILLED ' if killed else 'SURVIVED'} {m.id:32s} exit {rc} {secs:5.0f} s  "
                  f"{line[:110]}", flush=True)
            shutil.rmtree(root, ignore_errors=True)
    n_k = sum(r[1] for r in rows)
    lines = ["# Mutation check", "",
             "_Written by `python3 bench/mutation/run.py`; the mutations are in "
             "`bench/mutation/mutations.py`._", "",
             "Each mutation is a deliberate bug applied alone to a scratch copy of the checkout; "
             "only the tests it names run (`pytest -x`), never `test_generated.py` and never "
             "with `generated/` regenerated, so a kill comes from a behavioural test. The "
             "unmutated tests pass first in the same run.", "",
             f"**Killed {n_k} of {len(rows)} ({100 * n_k / max(len(rows), 1):.0f} %).**", "",
             "| mutation | what | tests | result | first failure |", "|---|---|---|---|---|"]
    for m, killed, rc, secs, line in rows:
        tests = ", ".join(Path(t).name for t in m.tests)
        res = "killed" if killed else "**survived**"
        lines.append(f"| `{m.id}` | {m.what} | {tests} | {res} ({secs:.0f} s) | "
                     f"`{line[:120].replace('|', '/')}` |")
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"killed {n_k} of {len(rows)}; wrote {args.out}")
    return 0 if n_k == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
