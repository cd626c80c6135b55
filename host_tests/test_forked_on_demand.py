"""generator.forked.forked_map(on_demand=True): each child takes the next item when it has
finished one; results in the items' order and failures as a serial loop would have them,
as with the items dealt in advance (test_forked.py)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from generator import forked
from generator.errors import InputError
from generator.forked import forked_map
from test_forked import _hung, _reaped, _square_with_pid, forks  # noqa: F401 (fixture)

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this system")

# Item 0 keeps its child this long; the other child's items take microseconds each, so on
# demand it takes all of them long before (a shared machine's scheduling delays are
# ~10 ms; dealt in advance, items 2 and 4 would wait behind item 0 in its child).
SLOW_S = 1.5


def _slow_first(k):
    if k == 0:
        time.sleep(SLOW_S)
    return k, os.getpid()


def test_a_slow_item_does_not_hold_the_others(forks):
    parent = os.getpid()
    got = list(forked_map(_slow_first, range(6), workers=2, on_demand=True))
    assert [k for k, _ in got] == list(range(6))
    assert len(forks) == 2 and parent not in {pid for _, pid in got}
    slow_pid = got[0][1]
    assert {pid for _, pid in got[1:]} == set(forks) - {slow_pid}
    assert all(_reaped(p) for p in forks)


def test_results_in_order_and_larger_than_a_pipe_buffer(forks):
    big = list(forked_map(lambda k: bytes([k]) * (1 << 20), range(5), workers=2,
                          on_demand=True))
    assert [b[:1] + b[-1:] for b in big] == [bytes([k, k]) for k in range(5)]
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def test_input_error_in_order(forks):
    def fn(k):
        if k == 3:
            raise InputError("unit.toml", f"sensor {k}: no usable samples", line=7)
        return k
    seen = []
    with pytest.raises(InputError) as ei:
        for v in forked_map(fn, range(6), workers=2, keep=(InputError,), on_demand=True):
            seen.append(v)
    assert seen == [0, 1, 2]
    assert str(ei.value) == "unit.toml:7: sensor 3: no usable samples"
    assert all(_reaped(p) for p in forks)


def test_a_dying_child_leaves_its_item_to_the_parent(forks):
    parent = os.getpid()

    def fn(k):
        if k == 2 and os.getpid() != parent:
            os._exit(3)                     # the child that took item 2 dies with it
        return k, os.getpid()
    got = list(forked_map(fn, range(6), workers=2, on_demand=True))
    assert [k for k, _ in got] == list(range(6))
    assert got[2][1] == parent              # re-run here
    # the items after it were taken by the child still alive (or by the dying one before)
    assert all(pid in forks for _, pid in got[:2] + got[3:])
    assert all(_reaped(p) for p in forks)


def test_a_result_that_does_not_pickle_is_computed_in_the_parent(forks):
    parent = os.getpid()

    def fn(k):
        pid = os.getpid()
        return (lambda: (k, pid)) if k == 1 else (k, pid)
    got = list(forked_map(fn, range(4), workers=2, on_demand=True))
    assert got[1]() == (1, parent)
    assert [g[0] for i, g in enumerate(got) if i != 1] == [0, 2, 3]
    assert all(g[1] in forks for i, g in enumerate(got) if i != 1)


def test_closing_early_kills_and_reaps_the_children(forks):
    previous = signal.signal(signal.SIGALRM, _hung)   # a failure, not a hang
    signal.setitimer(signal.ITIMER_REAL, 20.0)
    try:
        g = forked_map(lambda k: time.sleep(3600) if k else k, range(4), workers=2,
                       on_demand=True)
        assert next(g) == 0
        g.close()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert len(forks) == 2 and all(_reaped(p) for p in forks)


def test_more_items_than_the_pipe_holds_are_dealt(forks, monkeypatch):
    monkeypatch.setattr(forked, "ON_DEMAND_MAX_ITEMS", 4)
    got = list(forked_map(_square_with_pid, range(7), workers=2, on_demand=True))
    assert [v for v, _ in got] == [x * x for x in range(7)]
    assert [pid for _, pid in got] == [forks[k % 2] for k in range(7)]


def test_serial_with_one_worker():
    parent = os.getpid()
    assert list(forked_map(_square_with_pid, range(3), workers=1, on_demand=True)) == \
        [(x * x, parent) for x in range(3)]
