"""Shared by test_hardening.py and test_fuzz.py: paths, small slices of the shared
campaigns, and running `magcal` in-process with its exit status and stderr lines."""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

from ci import require
from generator.cli import main

REPO = Path(__file__).resolve().parent.parent
BASE_COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"


def shared_fm1() -> Path:
    """The shared example unit: ../shared beside the checkout (CI), or beside the folder of
    worktrees (a worktree under wt/); MAGCAL_SHARED overrides."""
    cands = [Path(os.environ["MAGCAL_SHARED"])] if os.environ.get("MAGCAL_SHARED") else []
    cands += [REPO.parent / "shared", REPO.parent.parent / "shared"]
    for c in cands:
        if (c / "data" / "samsat_fm1").is_dir():
            return c / "data" / "samsat_fm1"
    require(False, f"shared example unit not found (looked in {', '.join(map(str, cands))})")


def csv_slice(path: Path, every: int = 1, rows: int | None = None, start: int = 0) -> str:
    """The comment lines and header of a campaign, then every `every`-th data row from
    `start` (at most `rows`)."""
    lines = Path(path).read_text(encoding="utf-8").splitlines(keepends=True)
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    body = lines[hi + 1:][start::every]
    if rows is not None:
        body = body[:rows]
    return "".join(lines[:hi + 1] + body)


def run(argv) -> tuple:
    """(exit status, stdout, [stderr lines]) of `magcal argv...` run in-process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main([str(a) for a in argv])
    # a warning would be printed on stderr by a real `magcal` process: count its lines
    shown = [ln for w in caught for ln in warnings.formatwarning(
        w.message, w.category, w.filename, w.lineno, "").splitlines()]
    return rc, out.getvalue(), err.getvalue().splitlines() + shown


def assert_bad_input(result, *fragments):
    """Exit 2 with exactly one stderr line holding every fragment."""
    rc, _, err = result
    assert rc == 2, (rc, err)
    assert len(err) == 1, err
    for f in fragments:
        assert f in err[0], (f, err[0])
    return err[0]
