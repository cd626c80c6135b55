"""An output folder that already holds a run: the files this run did not write (a figure
the new report no longer has) are kept, never deleted, and named in one line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import FM1
from generator.io.outputs import output_folder


def test_files_of_an_earlier_run_are_named(tmp_path):
    out = tmp_path / "fit"
    with output_folder(out) as f:
        (f.tmp / "coefficients.json").write_text("{}")
        (f.tmp / "old_figure.png").write_bytes(b"x")
    assert f.earlier == [] and f.stale_note() == ""          # a new folder: nothing earlier
    with output_folder(out) as g:
        (g.tmp / "coefficients.json").write_text("{ }")
    assert (out / "old_figure.png").read_bytes() == b"x"     # kept
    assert (out / "coefficients.json").read_text() == "{ }"  # replaced
    assert g.earlier == [out / "old_figure.png"]
    note = g.stale_note()
    assert note.count("\n") == 0 and "1 file(s)" in note and "old_figure.png" in note


def test_many_earlier_files_are_summed_up(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    for i in range(8):
        (out / f"f{i}.png").write_bytes(b"x")
    with output_folder(out) as g:
        (g.tmp / "report.md").write_text("r")
    assert len(g.earlier) == 8
    assert "8 file(s)" in g.stale_note() and "and 3 more" in g.stale_note()



def test_plan_names_the_earlier_runs_files(tmp_path):
    """The verbs that write a folder say so too (plan here; fit, trace and demo print the
    same OutputFolder.stale_note)."""
    unit_toml = FM1 / "unit.toml"
    if not unit_toml.exists():
        pytest.skip("shared unit file not present")
    out = tmp_path / "plan"
    cmd = [sys.executable, "-m", "generator.cli", "plan", str(unit_toml), "-o", str(out)]
    assert subprocess.run(cmd, capture_output=True, text=True).returncode == 0
    (out / "old_figure.png").write_bytes(b"x")
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0
    assert "old_figure.png" in r.stderr and "earlier run" in r.stderr
    assert (out / "old_figure.png").read_bytes() == b"x"
