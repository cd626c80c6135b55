"""generator.report.drawer: the figure drawer forked before the figures are asked for
draws the calls recorded by figures.parallel() in its own workers; a figure that failed
there is drawn again (and raises) in this process; whatever the drawer cannot take
(unpicklable calls, a dead drawer) is drawn by parallel()'s own path; the drawer never
outlives its block."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from generator.report import drawer, figures

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this system")


def fake_figure(path, fail=False, note=None, die_unless=None):
    """A 'figure': writes the pid of the process that drew it and of its parent; fail:
    raise; die_unless: end the process at once unless it is that pid."""
    if die_unless is not None and os.getpid() != die_unless:
        os._exit(3)
    if fail:
        raise ValueError(f"cannot draw {Path(path).name}")
    Path(path).write_text(f"{os.getpid()} {os.getppid()}")
    return path


# the module attribute is the deferrable wrapper: the drawer finds the call by its name
fake_figure = figures._deferrable(lambda path, *a, **k: Path(path))(fake_figure)


def _drawn_by(paths):
    return [int(Path(p).read_text().split()[0]) for p in paths]


def _parents(paths):
    return {int(Path(p).read_text().split()[1]) for p in paths}


def _gone(pid) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_the_drawer_draws_the_figures_in_its_workers(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(5)]
    with drawer.early_drawer(workers=2) as d:
        assert d is not None and figures._EARLY is d
        pid = d.pid
        with figures.parallel(workers=2):
            got = [fake_figure(p) for p in paths]
        assert figures._EARLY is None                  # used once
    assert got == paths
    pids = _drawn_by(paths)
    assert os.getpid() not in pids and pid not in pids
    assert _parents(paths) == {pid}                      # by the drawer's workers
    assert _gone(pid)


def test_a_failed_figure_is_raised_here_and_the_rest_drawn(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(4)]
    with pytest.raises(ValueError, match="cannot draw f1.txt"):
        with drawer.early_drawer(workers=2):
            with figures.parallel(workers=2):
                for k, p in enumerate(paths):
                    fake_figure(p, fail=(k == 1))
    assert [p.exists() for p in paths] == [True, False, True, True]
    assert figures._EARLY is None and figures._DEFERRED is None


def test_calls_that_do_not_pickle_are_drawn_by_parallel(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(3)]
    with drawer.early_drawer(workers=2) as d:
        pid = d.pid
        with figures.parallel(workers=2):
            for p in paths:
                fake_figure(p, note=lambda: None)       # a lambda does not pickle
    assert all(p.exists() for p in paths)
    assert _parents(paths) == {os.getpid()} and _gone(pid)     # parallel()'s workers


def test_a_dead_drawer_leaves_the_figures_to_parallel(tmp_path):
    paths = [tmp_path / f"f{k}.txt" for k in range(3)]
    with drawer.early_drawer(workers=2) as d:
        pid = d.pid
        os.killpg(pid, signal.SIGKILL)
        with figures.parallel(workers=2):
            for p in paths:
                fake_figure(p)
    assert all(p.exists() for p in paths)
    assert _parents(paths) == {os.getpid()} and _gone(pid)     # parallel()'s workers


def test_an_unused_or_failed_block_kills_and_reaps_the_drawer():
    with drawer.early_drawer(workers=2) as d:
        pid = d.pid
    assert _gone(pid) and figures._EARLY is None
    with pytest.raises(KeyError):
        with drawer.early_drawer(workers=2) as d:
            pid = d.pid
            raise KeyError("x")
    assert _gone(pid) and figures._EARLY is None


def test_no_drawer_with_one_worker(tmp_path):
    p = tmp_path / "f.txt"
    with drawer.early_drawer(workers=1) as d:
        assert d is None
        with figures.parallel(workers=1):
            fake_figure(p)
    assert _drawn_by([p]) == [os.getpid()]


def test_a_figure_is_drawn_while_the_block_goes_on(tmp_path):
    """The first figure exists before the parallel() block ends: the drawer had it as
    soon as it was asked for."""
    first, second = tmp_path / "f0.txt", tmp_path / "f1.txt"
    with drawer.early_drawer(workers=2) as d:
        pid = d.pid
        with figures.parallel(workers=2):
            fake_figure(first)
            deadline = time.monotonic() + 20.0      # a fork and a file write: far less
            while not first.exists() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert first.exists()
            fake_figure(second)
    assert _parents([first, second]) == {pid}


def test_a_dying_worker_leaves_its_figure_to_this_process(tmp_path):
    parent = os.getpid()
    paths = [tmp_path / f"f{k}.txt" for k in range(4)]
    with drawer.early_drawer(workers=2):
        with figures.parallel(workers=2):
            for k, p in enumerate(paths):
                fake_figure(p, die_unless=parent if k == 2 else None)
    assert all(p.exists() for p in paths)
    assert _drawn_by(paths)[2] == parent
