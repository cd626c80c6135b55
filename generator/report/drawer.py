"""The report's figure drawer started before the figures are asked for.

Drawing the figures of a report begins with importing matplotlib and a first draw (its
fonts): ~0.3 s of one core, the same every time, before the figures' forked workers can
start (figures.parallel). A report first computes what its figures show (the telemetry
read again, the segments, the per-level fits: CampaignAnalysis, ~0.5 s): a process
forked at that point (the drawer) imports matplotlib and makes its first draw on the
other core meanwhile, then waits for the figures. When the parallel() block ends, its
recorded calls are sent to the drawer (pickled through a pipe: the arrays drawn, ~15 MB
for the thermal campaign, ~0.1 s to pickle and load), which draws them with its own
forked workers (generator.forked.forked_map, on demand, as parallel() does) and answers
with which figures it drew.

    with early_drawer():            # forks the drawer (or does nothing: see below)
        ...                         # the report's own work
        with figures.parallel():    # the figures recorded, then sent to the drawer
            ...

Failures keep parallel()'s behaviour: a figure that raised in the drawer's workers is
drawn again in this process, where its error is raised; a drawer that died, calls that do
not pickle, or a pipe that broke leave every figure to parallel()'s own path (forked
workers of this process). An exception or interrupt in this process kills the drawer and
its workers (its own process group) and reaps it; a drawer never used (no figure asked
for) reads the end of its pipe and exits. This process never imports matplotlib when the
drawer draws everything.

No drawer (parallel() as before) where generator.forked would not fork: fewer than 2
workers (MAGCAL_WORKERS=1), no fork, in a forked child, while other threads run.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import pickle
import signal

from generator.report import figures

_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM") if hasattr(signal, n))


def _ref(fn):
    """(module, name, via draw_now) naming the figure function fn by where it is found:
    a module attribute, or the draw_now of one (figures._deferrable)."""
    mod, name = fn.__module__, fn.__name__
    attr = getattr(importlib.import_module(mod), name, None)
    if attr is fn:
        return mod, name, False
    if getattr(attr, "draw_now", None) is fn:
        return mod, name, True
    raise pickle.PicklingError(f"{mod}.{name}: not found by its name")


def _resolve(ref):
    mod, name, via = ref
    attr = getattr(importlib.import_module(mod), name)
    return attr.draw_now if via else attr


def _read_all(fd) -> bytes:
    chunks = []
    while True:
        b = os.read(fd, 1 << 20)
        if not b:
            return b"".join(chunks)
        chunks.append(b)


def _write_all(fd, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _drawer_main(calls_fd, result_fd, workers) -> None:
    """The drawer: matplotlib imported and warmed up, then the calls read to the end of
    the pipe (none: exit), drawn by forked workers; the ok flags written back. Never
    returns (os._exit)."""
    code = 1
    try:
        from contextlib import closing

        from generator.forked import forked_map
        figures._warm_up()
        data = _read_all(calls_fd)
        if data:
            calls = [(_resolve(ref), args, kwargs) for ref, args, kwargs in pickle.loads(data)]
            figures._DEFERRED = calls
            with closing(forked_map(figures._draw_or_report, range(len(calls)), workers,
                                    on_demand=True)) as done:
                ok = [bool(x) for x in done]
            _write_all(result_fd, pickle.dumps(ok))
        code = 0
    except BaseException:       # noqa: BLE001 -- the parent draws what is not reported
        pass
    finally:
        try:
            from generator.forked import _flush_std
            _flush_std()
        finally:
            os._exit(code)


class _Drawer:
    def __init__(self, workers):
        from generator.forked import _flush_std
        self.pid = None
        calls_r, calls_w = os.pipe()
        try:
            result_r, result_w = os.pipe()
        except OSError:
            os.close(calls_r)
            os.close(calls_w)
            raise
        _flush_std()        # the child must not inherit (and write) buffered output
        mask = hasattr(signal, "pthread_sigmask")
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS) if mask else None
        try:
            try:
                pid = os.fork()
            except OSError:
                for fd in (calls_r, calls_w, result_r, result_w):
                    os.close(fd)
                raise
            if pid == 0:
                try:
                    os.setpgid(0, 0)        # its own group: killed with its workers
                    os.close(calls_w)
                    os.close(result_r)
                    if mask:
                        signal.pthread_sigmask(signal.SIG_SETMASK, old)
                finally:
                    _drawer_main(calls_r, result_w, workers)
            try:
                os.setpgid(pid, pid)        # also here: whichever runs first
            except OSError:
                pass
            self.pid = pid
        finally:
            if mask:
                signal.pthread_sigmask(signal.SIG_SETMASK, old)
        os.close(calls_r)
        os.close(result_w)
        self.calls_w, self.result_r = calls_w, result_r

    def draw(self, calls):
        """Send the calls [(fn, args, kwargs)]; the drawer's ok flag per call, or None when
        it did not draw them (calls that do not pickle, a broken pipe, a drawer that
        died). Any exception or interrupt here kills the drawer before it goes on."""
        try:
            try:
                data = pickle.dumps([(_ref(fn), args, kwargs) for fn, args, kwargs in calls],
                                    protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:       # noqa: BLE001 -- not for the drawer: parallel() draws
                self.close(kill=True)
                return None
            try:
                _write_all(self.calls_w, data)
            except OSError:          # the drawer is gone
                self.close(kill=True)
                return None
            os.close(self.calls_w)
            self.calls_w = None
            raw = _read_all(self.result_r)
            try:
                ok = pickle.loads(raw) if raw else None
            except Exception:       # noqa: BLE001 -- cut short: the drawer died
                ok = None
            self.close(kill=ok is None)
            if ok is not None and len(ok) != len(calls):
                return None
            return ok
        except BaseException:
            self.close(kill=True)
            raise

    def close(self, kill=False):
        """Close the pipes (an unused drawer then exits), kill its group if asked, reap."""
        for name in ("calls_w", "result_r"):
            fd = getattr(self, name, None)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, None)
        if self.pid is None:
            return
        if kill:
            try:
                os.killpg(self.pid, signal.SIGKILL)
            except OSError:
                try:
                    os.kill(self.pid, signal.SIGKILL)
                except OSError:
                    pass
        while True:
            try:
                os.waitpid(self.pid, 0)
                break
            except InterruptedError:
                continue
            except OSError:
                break
        self.pid = None


@contextlib.contextmanager
def early_drawer(workers=None):
    """Start the drawer now for the figures.parallel() block inside (module doc); no
    drawer where forked_map would not fork."""
    from generator.forked import can_fork, default_workers
    workers = workers or default_workers()
    drawer = None
    if figures._EARLY is None and can_fork(2, workers):
        try:
            drawer = _Drawer(workers)
        except OSError:             # no pipe or fork to be had: parallel() as before
            drawer = None
    if drawer is None:
        yield None
        return
    figures._EARLY = drawer
    try:
        yield drawer
    finally:
        figures._EARLY = None
        # used: already reaped; unused (no figure asked for) or failed: nothing of its
        # is wanted, and killing it saves waiting for its warm-up to end
        drawer.close(kill=True)
