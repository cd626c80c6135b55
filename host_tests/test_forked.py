"""generator.forked.forked_map: independent calls in forked children, results in the
items' order, failures as a serial loop would have them, no child left behind."""

from __future__ import annotations

import os
import pickle
import signal
import threading
from pathlib import Path

import pytest

from generator import forked
from generator.errors import InputError
from generator.forked import forked_map

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this system")


@pytest.fixture
def forks(monkeypatch):
    """The pids of the children forked by the test (os.fork recorded in the parent). Any
    still there after the test (a failed one) are killed and reaped: none outlives it."""
    pids = []
    real = os.fork

    def fork():
        pid = real()
        if pid:
            pids.append(pid)
        return pid
    monkeypatch.setattr(os, "fork", fork)
    yield pids
    for pid in pids:
        try:       # only a child not reaped yet (its pid cannot have been reused)
            if os.waitpid(pid, os.WNOHANG) == (0, 0):
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
        except ChildProcessError:
            pass


def _reaped(pid) -> bool:
    try:
        os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return True
    return False


def _square_with_pid(x):
    return x * x, os.getpid()


def test_results_in_order_from_children(forks):
    parent = os.getpid()
    got = list(forked_map(_square_with_pid, range(7), workers=2))
    assert [v for v, _ in got] == [x * x for x in range(7)]
    assert len(forks) == 2
    # item k ran in child k % 2, never in the parent
    assert [pid for _, pid in got] == [forks[k % 2] for k in range(7)]
    assert parent not in {pid for _, pid in got}
    assert all(_reaped(p) for p in forks)


def test_results_larger_than_a_pipe_buffer(forks):
    # 4 MiB per result from each child at once: a pipe holds 64 KiB, so a parent reading
    # one child only while the other waits on a full pipe would hang here
    big = list(forked_map(lambda k: bytes([k]) * (4 << 20), range(4), workers=2))
    assert [len(b) for b in big] == [4 << 20] * 4
    assert [b[:1] + b[-1:] for b in big] == [bytes([k, k]) for k in range(4)]
    assert len(forks) == 2


def _bad_input_at_3(k):
    if k == 3:
        raise InputError("unit.toml", f"sensor {k}: no usable samples", line=7, column="x")
    return k


def test_input_error_reaches_the_parent_as_the_same_error(forks):
    seen = []
    with pytest.raises(InputError) as ei:
        for v in forked_map(_bad_input_at_3, range(6), workers=2, keep=(InputError,)):
            seen.append(v)
    assert seen == [0, 1, 2]                       # the items before it, in order
    e = ei.value
    assert str(e) == "unit.toml:7: column 'x': sensor 3: no usable samples"
    assert (e.path, e.line, e.column, e.message) == ("unit.toml", 7, "x",
                                                     "sensor 3: no usable samples")
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def test_a_dying_child_is_rerun_in_the_parent(forks):
    parent = os.getpid()

    def fn(k):
        if k == 2 and os.getpid() != parent:
            os._exit(3)                            # the child dies without a word
        return k, os.getpid()
    got = list(forked_map(fn, range(6), workers=2))
    assert [v for v, _ in got] == list(range(6))
    # child 0 died at item 2: items 2 and 4 (its share) ran in the parent, item 0 in it
    assert [pid == parent for _, pid in got] == [False, False, True, False, True, False]
    assert all(_reaped(p) for p in forks)


def test_a_result_that_does_not_pickle_is_computed_in_the_parent(forks):
    parent = os.getpid()

    def fn(k):
        pid = os.getpid()
        if k == 1:
            return lambda: (k, pid)                # a local lambda does not pickle
        return k, pid
    got = list(forked_map(fn, range(4), workers=2))
    assert got[1]() == (1, parent)
    assert [g for i, g in enumerate(got) if i != 1] == [(0, forks[0]), (2, forks[0]),
                                                        (3, forks[1])]


def test_another_exception_is_raised_by_the_parent_rerun(forks):
    parent = os.getpid()
    where = []

    def fn(k):
        if k == 1:
            where.append(os.getpid())              # in the child this list is its copy
            raise ValueError(f"item {k} bad")
        return k
    with pytest.raises(ValueError, match="item 1 bad") as ei:
        list(forked_map(fn, range(4), workers=2))
    assert where == [parent]                       # raised by the re-run, here
    # its own traceback: the frame of fn is in it
    assert any(tb.name == "fn" for tb in _frames(ei.value.__traceback__))
    assert all(_reaped(p) for p in forks)


def _frames(tb):
    import traceback
    return traceback.extract_tb(tb)


def _sleep_after_first(k):
    if k == 0:
        return 0
    signal.pause()                                 # until killed
    return k


def test_interrupt_kills_and_reaps_the_children(forks):
    previous = signal.signal(signal.SIGALRM, _raise_interrupt)
    try:
        g = forked_map(_sleep_after_first, range(4), workers=2)
        assert next(g) == 0
        # the parent now waits for item 1; the timer repeats, so that a parent left
        # waiting for a child it failed to kill fails here instead of hanging
        signal.setitimer(signal.ITIMER_REAL, 0.3, 20.0)
        with pytest.raises(KeyboardInterrupt):
            next(g)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    # both children were paused for good: reaped means they were killed
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


class _Hung(Exception):
    pass


def _hung(signum, frame):
    raise _Hung("still waiting for a child after 20 s")


def test_closing_early_kills_and_reaps_the_children(forks):
    previous = signal.signal(signal.SIGALRM, _hung)   # a failure, not a hang, if not killed
    signal.setitimer(signal.ITIMER_REAL, 20.0)
    try:
        g = forked_map(_sleep_after_first, range(4), workers=2)
        assert next(g) == 0
        g.close()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def test_serial_when_fork_is_refused(monkeypatch):
    def no_fork():
        raise OSError(11, "Resource temporarily unavailable")
    monkeypatch.setattr(os, "fork", no_fork)
    parent = os.getpid()
    assert list(forked_map(_square_with_pid, range(3), workers=2)) == \
        [(x * x, parent) for x in range(3)]


def test_serial_while_other_threads_run(forks):
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        got = list(forked_map(_square_with_pid, range(3), workers=2))
    finally:
        stop.set()
        t.join()
    assert forks == [] and {pid for _, pid in got} == {os.getpid()}


def test_serial_with_one_worker_and_inside_a_child(forks, monkeypatch):
    parent = os.getpid()
    assert list(forked_map(_square_with_pid, range(3), workers=1)) == \
        [(x * x, parent) for x in range(3)]
    monkeypatch.setenv("MAGCAL_WORKERS", "1")
    assert list(forked_map(_square_with_pid, range(3))) == [(x * x, parent) for x in range(3)]
    assert forks == []

    def nested(k):          # a child maps serially: no forks of forks
        return [pid for _, pid in forked_map(_square_with_pid, range(2), workers=2)]
    got = list(forked_map(nested, range(2), workers=2))
    assert got == [[forks[0]] * 2, [forks[1]] * 2]


# ---- the per-sensor fits ---------------------------------------------------------------
def _fit(tmp_path, fm1_dir, monkeypatch, capsys, workers, name):
    from generator.cli import main
    monkeypatch.setenv("MAGCAL_WORKERS", str(workers))
    (tmp_path / name).mkdir()
    monkeypatch.chdir(tmp_path / name)    # the same relative output path in both runs
    out = Path("fit")
    rc = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
               "-o", str(out), "--no-report"])
    err = capsys.readouterr().err
    assert rc == 0, err
    # the progress lines without their elapsed-time prefix "[   1.2 s] "
    lines = [ln.split("] ", 1)[-1] for ln in err.splitlines()]
    return (out / "coefficients.json").read_bytes(), lines


def test_forked_fit_is_byte_identical_to_the_serial_one(tmp_path, fm1_dir, monkeypatch,
                                                        capsys, forks):
    serial, serial_lines = _fit(tmp_path, fm1_dir, monkeypatch, capsys, 1, "serial")
    assert forks == []
    par, par_lines = _fit(tmp_path, fm1_dir, monkeypatch, capsys, 2, "forked")
    assert len(forks) == 2                          # the five sensors ran in two children
    assert par == serial
    assert par_lines == serial_lines                # progress lines in the serial order
    assert sum("held-out winner" in ln for ln in par_lines) == 5


def test_input_error_in_a_forked_sensor_fit_is_exit_2_one_line(tmp_path, fm1_dir,
                                                                monkeypatch, capsys, forks):
    from generator.cli import main
    from generator.fit import thermal
    real = thermal.fit_sensor
    parent = os.getpid()
    marks = tmp_path / "marks"
    marks.mkdir()

    def fit_sensor(name, datas, **kw):
        (marks / f"{name}.{os.getpid()}").touch()
        if name == "mpu2":
            raise InputError("bad.csv", f"{name}: refused for the test", line=3)
        return real(name, datas, **kw)
    monkeypatch.setattr(thermal, "fit_sensor", fit_sensor)
    monkeypatch.setenv("MAGCAL_WORKERS", "2")
    out = tmp_path / "fit"
    rc = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
               "-o", str(out), "--no-report", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err == "magcal fit: bad.csv:3: mpu2: refused for the test"
    # every sensor fit ran in a child (mpu2 raised there, not in a re-run in the
    # parent), and nothing half-written
    ran = {p.name.split(".")[0]: int(p.name.split(".")[1]) for p in marks.iterdir()}
    assert ran.get("mpu2") in forks and parent not in ran.values()
    assert not out.exists() or not any(out.iterdir())
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def test_exception_state_round_trips_through_pickle():
    e = InputError(Path("u.toml"), "bad key", line=2, column="k")
    back = forked._rebuild(pickle.loads(pickle.dumps(forked._exception_state(e))))
    assert type(back) is InputError and str(back) == str(e)
    assert (back.path, back.line, back.column) == (e.path, e.line, e.column)


def test_before_fork_runs_once_in_the_parent_and_only_when_forking(forks):
    calls = []
    marker = []

    def prepare():
        calls.append(os.getpid())
        marker.append("ready")

    got = list(forked_map(lambda k: (k, list(marker)), range(3), workers=2,
                          before_fork=prepare))
    assert calls == [os.getpid()] and len(forks) == 2
    assert got == [(k, ["ready"]) for k in range(3)]      # the children inherited it
    calls.clear()
    assert list(forked_map(lambda k: k, range(3), workers=1, before_fork=prepare)) == \
        [0, 1, 2]
    assert calls == []
