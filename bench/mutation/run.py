"""Mutation check: apply each curated mutation (mutations.py) alone to a scratch copy of
the checkout, run only the tests it names (never test_generated.py, never a regenerated
generated/), and count it killed when those tests fail. Writes docs/mutation.md.

    python3 bench/mutation/run.py [--only ID ...] [--out FILE] [--timeout S]
    python3 bench/mutation/run.py --check     # every mutation applies? (no tests run)
    python3 bench/mutation/run.py --list

A mutation whose text no longer occurs (the code moved) is reported NOT-APPLIED, listed,
and counts as a failure of the check; the run goes on with the others. The full run
writes docs/mutation.md; a run with --only writes only where --out says.

Shared data: ../shared beside the checkout, or MAGCAL_SHARED.
"""

from __future__ import annotations

import argparse
import os
import re
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


def _flexible(old: str) -> re.Pattern:
    """`old` with any run of whitespace (also none) between its tokens: re-indented or
    re-wrapped code still matches."""
    return re.compile(r"\s*".join(re.escape(tok) for tok in old.split()))


def locate(text: str, old: str, new: str):
    """The text with `old` replaced by `new`, or (None, why). The exact snippet first; if
    it does not occur exactly once, the whitespace-tolerant match (leading whitespace
    common to old and new dropped, so an inserted line keeps the anchor's indentation)."""
    n = text.count(old)
    if n == 1:
        return text.replace(old, new), None
    lead = old[:len(old) - len(old.lstrip())]
    core_new = new[len(lead):] if new.startswith(lead) else new
    hits = list(_flexible(old).finditer(text)) if old.strip() else []
    if len(hits) == 1:
        h = hits[0]
        return text[:h.start()] + core_new + text[h.end():], None
    return None, f"occurs {n} times (whitespace-tolerant: {len(hits)})"


def apply(root: Path, mutation) -> list:
    """Apply the mutation's edits in `root`. Returns the problems (empty: applied); a
    mutation with a problem is left unapplied (files untouched)."""
    new_texts, problems = {}, []
    for f, old, new in mutation.edits:
        p = root / f
        if not p.is_file():
            problems.append(f"{f}: no such file")
            continue
        text = new_texts.get(p, None)
        text = p.read_text() if text is None else text
        out, why = locate(text, old, new)
        if out is None:
            problems.append(f"{f}: {old.strip()[:60]!r} {why}")
        elif out == text:
            problems.append(f"{f}: the edit changes nothing")
        else:
            new_texts[p] = out
    if not problems:
        for p, text in new_texts.items():
            p.write_text(text)
    return problems


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


def check_all(todo) -> dict:
    """Mutation id -> problems, each mutation applied alone to a scratch copy of the
    files it edits (no tests run)."""
    out = {}
    with tempfile.TemporaryDirectory(prefix="magcal_mutcheck_") as tmp:
        for m in todo:
            root = Path(tmp) / m.id
            for f in {e[0] for e in m.edits}:
                if (REPO / f).is_file():
                    (root / f).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(REPO / f, root / f)
            out[m.id] = apply(root, m)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--out", default=None,
                    help="report file (default: docs/mutation.md for a full run, "
                         "none with --only)")
    ap.add_argument("--timeout", type=float, default=900)
    ap.add_argument("--check", action="store_true",
                    help="only check that every mutation applies; no tests run")
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args(argv)
    ids = {m.id for m in MUTATIONS}
    unknown = sorted(set(args.only or ()) - ids)
    if unknown:
        print(f"unknown mutation ids: {', '.join(unknown)}", file=sys.stderr)
        return 2
    todo = [m for m in MUTATIONS if args.only is None or m.id in args.only]
    assert not any("test_generated" in t for m in todo for t in m.tests)
    if args.list:
        for m in todo:
            print(f"{m.id:32s} {m.what}")
        return 0
    problems = check_all(todo)
    for mid, why in problems.items():
        if why:
            print(f"NOT-APPLIED {mid}: {'; '.join(why)}", flush=True)
    if args.check:
        bad = sum(bool(w) for w in problems.values())
        print(f"{len(todo) - bad} of {len(todo)} mutations apply")
        return 0 if bad == 0 else 1
    out = Path(args.out) if args.out else (None if args.only is not None
                                           else REPO / "docs" / "mutation.md")
    rows = []
    # the commit tested: taken with the scratch copy, not at the end of a long run
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--",
                            "generator", "templates", "host_tests", "bench"],
                           capture_output=True, text=True).stdout.strip()
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with tempfile.TemporaryDirectory(prefix="magcal_mut_") as tmp:
        base = Path(tmp) / "base"
        base.mkdir()
        scratch_copy(base)
        # the unmutated tests must pass first, else a "kill" means nothing
        tests = sorted({t for m in todo if not problems[m.id] for t in m.tests})
        rc, secs, line = run_tests(base, tests, args.timeout)
        print(f"baseline: exit {rc} in {secs:.0f} s: {line}", flush=True)
        if rc != 0:
            print("the unmutated tests fail: no mutation run", file=sys.stderr)
            return 1
        for m in todo:
            if problems[m.id]:
                rows.append((m, "not-applied", None, 0.0, "; ".join(problems[m.id])))
                continue
            root = Path(tmp) / m.id
            shutil.copytree(base, root)
            apply(root, m)
            rc, secs, line = run_tests(root, list(m.tests), args.timeout)
            result = "killed" if rc not in (0, 5) else "survived"   # 5: no tests collected
            rows.append((m, result, rc, secs, line))
            print(f"{result.upper():11s} {m.id:32s} exit {rc} {secs:5.0f} s  "
                  f"{line[:110]}", flush=True)
            shutil.rmtree(root, ignore_errors=True)
    n_k = sum(r[1] == "killed" for r in rows)
    n_na = sum(r[1] == "not-applied" for r in rows)
    lines = ["# Mutation check", "",
             "_Written by `python3 bench/mutation/run.py`; the mutations are in "
             "`bench/mutation/mutations.py`._", "",
             "Each mutation is a deliberate bug applied alone to a scratch copy of the checkout; "
             "only the tests it names run (`pytest -x`), never `test_generated.py` and never "
             "with `generated/` regenerated, so a kill comes from a behavioural test. The "
             "unmutated tests pass first in the same run. A mutation whose text no longer "
             "occurs in the code is NOT-APPLIED and counts as a failure of the check.", "",
             f"Run started {when} on commit `{head}`"
             f"{' (with uncommitted changes)' if dirty else ''}.",
             "",
             f"**Killed {n_k} of {len(rows)} ({100 * n_k / max(len(rows), 1):.0f} %)"
             + (f"; {n_na} NOT-APPLIED" if n_na else "") + ".**", "",
             "| mutation | what | tests | result | first failure |", "|---|---|---|---|---|"]
    for m, result, rc, secs, line in rows:
        tests = ", ".join(Path(t).name for t in m.tests)
        res = {"killed": f"killed ({secs:.0f} s)", "survived": f"**survived** ({secs:.0f} s)",
               "not-applied": "**NOT-APPLIED**"}[result]
        lines.append(f"| `{m.id}` | {m.what.replace('|', '/')} | {tests} | {res} | "
                     f"`{line[:120].replace('|', '/')}` |")
    summary = f"killed {n_k} of {len(rows)}" + (f", {n_na} NOT-APPLIED" if n_na else "")
    if out is not None:
        # the hand-written part (from "## Notes" on: equivalents, history) is kept
        notes = out.read_text().partition("\n## Notes")[2] if out.is_file() else ""
        out.write_text("\n".join(lines) + "\n" + ("\n## Notes" + notes if notes else ""))
        summary += f"; wrote {out}"
    print(summary)
    return 0 if n_k == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
