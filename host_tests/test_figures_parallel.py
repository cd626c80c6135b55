"""generator.report.figures.parallel: the deferred figures are handed out to the forked
children as they ask for them (not dealt in advance), every figure is drawn once, and a
figure that failed in a child is drawn again in the parent, which raises its error."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from generator.report import figures

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this system")


def _fake_figure(path, wait_for=(), fail=False, die=False, parent=None):
    """A 'figure': writes the pid of the process that drew it. wait_for: paths that must
    exist first (drawn by another process); fail: raise; die: end the process at once if
    it is a child (parent: the test's pid)."""
    deadline = time.monotonic() + 20.0   # another process writes a file: far less
    while not all(Path(p).exists() for p in wait_for):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path}: waited for {wait_for}")
        time.sleep(0.01)
    if die and os.getpid() != parent:
        os._exit(3)
    if fail:
        raise ValueError(f"cannot draw {Path(path).name}")
    Path(path).write_text(str(os.getpid()))
    return path


fake = figures._deferrable(lambda path, *a, **k: Path(path))(_fake_figure)


def _drawn_by(paths):
    return [int(Path(p).read_text()) for p in paths]


def test_figures_are_handed_out_as_children_ask(tmp_path):
    """Figure 0 waits until figures 1-5 exist: it can only end if the other child draws
    all of them. Dealt in advance (item k to child k % 2), figures 2 and 4 would wait for
    the child stuck on figure 0 and it would time out."""
    paths = [tmp_path / f"f{k}.txt" for k in range(6)]
    with figures.parallel(workers=2):
        got = [fake(paths[0], wait_for=paths[1:])] + [fake(p) for p in paths[1:]]
    assert got == paths                        # the paths, at once, in call order
    pids = _drawn_by(paths)
    parent = os.getpid()
    assert parent not in pids                  # all drawn in children
    assert len(set(pids[1:])) == 1 and pids[0] != pids[1]


def test_failed_figure_is_raised_by_the_parent_and_the_rest_drawn(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(5)]
    with pytest.raises(ValueError, match="cannot draw f2.txt"):
        with figures.parallel(workers=2):
            for k, p in enumerate(paths):
                fake(p, fail=(k == 2))
    assert [p.exists() for p in paths] == [True, True, False, True, True]
    assert figures._DEFERRED is None


def test_a_dying_child_leaves_its_figures_to_the_parent(tmp_path):
    parent = os.getpid()
    paths = [tmp_path / f"f{k}.txt" for k in range(6)]
    with figures.parallel(workers=2):
        for k, p in enumerate(paths):
            fake(p, die=(k == 3), parent=parent)
    assert all(p.exists() for p in paths)
    assert _drawn_by(paths)[3] == parent      # the one whose child died: drawn here


def test_one_worker_draws_in_this_process(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(3)]
    with figures.parallel(workers=1):
        for p in paths:
            fake(p)
    assert _drawn_by(paths) == [os.getpid()] * 3


def test_outside_the_block_a_figure_is_drawn_at_once(tmp_path):
    p = tmp_path / "now.txt"
    assert fake(p) == p and _drawn_by([p]) == [os.getpid()]
