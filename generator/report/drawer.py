"""The report's figure drawer, started before the figures are asked for.

Drawing a report's figures begins with importing matplotlib and a first draw (its
fonts): ~0.3 s of one core, the same every time, before figures.parallel() can fork its
workers. A report first computes what its figures show (the telemetry read again, the
segments, the per-level fits: CampaignAnalysis, ~0.5 s). The drawer is a process forked
at that point: it imports matplotlib and makes its first draw on the other core
meanwhile, then forks its workers (they inherit both) and waits. Inside the parallel()
block each figure call is sent to it as soon as it is recorded (pickled through a pipe:
the arrays drawn, ~15 MB for the thermal campaign) and handed to an idle worker, so the
figures are drawn while this process computes the data of the next ones; at the end of
the block the drawer answers with which calls it drew.

    with early_drawer():            # forks the drawer (or does nothing: see below)
        ...                         # the report's own work
        with figures.parallel():    # each figure call sent to the drawer as recorded
            ...

Failures keep parallel()'s behaviour: a figure that raised in a worker, or whose worker
died, is drawn again in this process, where its error is raised; a call that does not
pickle, a broken pipe or a dead drawer leave every figure to parallel()'s own path
(forked workers of this process; files a worker had written are written again, the same
bytes). An exception or interrupt in this process kills the drawer and its workers (its
own process group) and reaps it; so does the end of the block when no figure was asked
for. This process does not import matplotlib when the drawer draws everything.

No drawer (parallel() as before) where generator.forked would not fork: fewer than 2
workers (MAGCAL_WORKERS=1), no fork, in a forked child, while other threads run.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import pickle
import signal
import struct

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


_MSG = struct.Struct("<iQ")      # item number (-1: the end, n in the length), length


def _write_all(fd, data) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


class _Messages:
    """Length-prefixed messages (_MSG) read from a pipe as they arrive."""

    def __init__(self, fd):
        self.fd, self.buf, self.open = fd, bytearray(), True

    def pump(self) -> list:
        """Read what the pipe has (one read): the complete messages [(k, bytes)]."""
        chunk = os.read(self.fd, 1 << 20)
        if not chunk:
            self.open = False
        self.buf += chunk
        out = []
        while len(self.buf) >= _MSG.size:
            k, n = _MSG.unpack_from(self.buf)
            if k < 0:                   # the end: n is the number of calls
                out.append((k, n))
                del self.buf[:_MSG.size]
                continue
            if len(self.buf) < _MSG.size + n:
                break
            out.append((k, bytes(self.buf[_MSG.size:_MSG.size + n])))
            del self.buf[:_MSG.size + n]
        return out

    def next(self):
        """The next complete message, or None at the end of the pipe (blocks)."""
        while True:
            if len(self.buf) >= _MSG.size:
                k, n = _MSG.unpack_from(self.buf)
                if k < 0:
                    del self.buf[:_MSG.size]
                    return k, n
                if len(self.buf) >= _MSG.size + n:
                    data = bytes(self.buf[_MSG.size:_MSG.size + n])
                    del self.buf[:_MSG.size + n]
                    return k, data
            if not self.open:
                return None
            chunk = os.read(self.fd, 1 << 20)
            if not chunk:
                self.open = False
            self.buf += chunk


def _exit_child(code) -> None:
    """End a forked process (the drawer or one of its workers): its buffered output
    flushed, then os._exit (no parent's cleanup run twice)."""
    try:
        from generator.forked import _flush_std
        _flush_std()
    finally:
        os._exit(code)


def _worker_main(calls_fd, result_fd) -> None:
    """A drawing worker: each call it is given drawn, (k, ok) written back; ends at the end
    of its pipe. Never returns (os._exit)."""
    code = 1
    try:
        msgs = _Messages(calls_fd)
        while True:
            m = msgs.next()
            if m is None:
                break
            k, data = m
            try:
                ref, args, kwargs = pickle.loads(data)
                _resolve(ref)(*args, **kwargs)
                ok = True
            except Exception:       # noqa: BLE001 -- drawn again (and raised) by the parent
                ok = False
            _write_all(result_fd, _RESULT.pack(k, ok))
        code = 0
    except BaseException:       # noqa: BLE001 -- the drawer reports its call as failed
        pass
    finally:
        _exit_child(code)


_RESULT = struct.Struct("<i?")


def _drawer_main(calls_fd, result_fd, workers) -> None:
    """The drawer: matplotlib imported and warmed up, its workers forked (they inherit
    both), then each call that arrives handed to an idle worker, and at the end the ok
    flag of every call written back (a call whose worker died: not ok). Never returns."""
    code = 1
    try:
        import select
        figures._warm_up()
        pool = {}               # result read end -> [pid, calls write end, call or None]
        for _ in range(workers):
            cr, cw = os.pipe()
            rr, rw = os.pipe()
            pid = os.fork()
            if pid == 0:
                try:           # only its own two ends stay open
                    for fd in [cw, rr, calls_fd, result_fd] + [v[1] for v in pool.values()] \
                            + list(pool):
                        os.close(fd)
                finally:
                    _worker_main(cr, rw)
            os.close(cr)
            os.close(rw)
            pool[rr] = [pid, cw, None]
        parent = _Messages(calls_fd)
        queue, ok, end = [], {}, None
        partial = {rr: b"" for rr in pool}
        while end is None or len(ok) < end:
            for rr, w in pool.items():          # hand out: the next call to an idle worker
                if w[2] is None and w[1] is not None and queue:
                    k, data = queue.pop(0)
                    try:
                        _write_all(w[1], _MSG.pack(k, len(data)) + data)
                        w[2] = k
                    except OSError:             # the worker is gone
                        ok[k] = False
            live = [rr for rr, w in pool.items() if w[1] is not None]
            if not live and queue:              # no worker left: not drawn here
                for k, _ in queue:
                    ok[k] = False
                queue = []
            watch = live + ([calls_fd] if parent.open else [])
            if not watch:
                break
            ready, _, _ = select.select(watch, [], [])
            for fd in ready:
                if fd == calls_fd:
                    for k, data in parent.pump():
                        if k < 0:
                            end = data
                        else:
                            queue.append((k, data))
                    continue
                chunk = os.read(fd, 4096)
                w = pool[fd]
                if not chunk:                   # the worker died: its call not drawn
                    if w[2] is not None:
                        ok[w[2]] = False
                    os.close(w[1])
                    w[1], w[2] = None, None
                    continue
                partial[fd] += chunk
                while len(partial[fd]) >= _RESULT.size:
                    k, good = _RESULT.unpack_from(partial[fd])
                    partial[fd] = partial[fd][_RESULT.size:]
                    ok[k] = bool(good)
                    w[2] = None
            if end is None and not parent.open:     # the parent went away
                break
        if end is not None:
            _write_all(result_fd, pickle.dumps([ok.get(k, False) for k in range(end)]))
        for rr, w in pool.items():
            if w[1] is not None:
                os.close(w[1])                  # the worker ends at the end of its pipe
        for rr, w in pool.items():
            try:
                os.waitpid(w[0], 0)
            except OSError:
                pass
        code = 0
    except BaseException:       # noqa: BLE001 -- the parent draws what is not reported
        pass
    finally:
        _exit_child(code)


class _Drawer:
    def __init__(self, workers):
        from generator.forked import _flush_std
        self.pid = None
        self.broken = False
        self.calls_w = self.result_r = None
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
            os.close(calls_r)
            os.close(result_w)
            self.calls_w, self.result_r = calls_w, result_r
        finally:
            try:
                if mask:    # an interrupt held back during the fork is raised here
                    signal.pthread_sigmask(signal.SIG_SETMASK, old)
            except BaseException:
                self.close(kill=True)       # not left running with nobody to end it
                raise

    def send(self, k, fn, args, kwargs) -> None:
        """Call k, sent to the drawer as soon as it is recorded: its workers draw it while
        this process goes on. A call that does not pickle or a drawer gone: the drawer is
        given up (parallel() then draws every call itself)."""
        if self.broken:
            return
        try:
            try:
                data = pickle.dumps((_ref(fn), args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
                _write_all(self.calls_w, _MSG.pack(k, len(data)) + data)
            except Exception:       # noqa: BLE001 -- not for the drawer: parallel() draws
                self.broken = True
                self.close(kill=True)
        except BaseException:
            self.close(kill=True)
            raise

    def finish(self, n):
        """The drawer's ok flag for each of the n calls sent, or None when it did not draw
        them (module doc). An exception or interrupt here kills the drawer first."""
        if self.broken:
            return None
        try:
            try:
                _write_all(self.calls_w, _MSG.pack(-1, n))
            except OSError:          # the drawer is gone
                self.close(kill=True)
                return None
            os.close(self.calls_w)
            self.calls_w = None
            chunks = []
            while True:
                b = os.read(self.result_r, 1 << 16)
                if not b:
                    break
                chunks.append(b)
            try:
                ok = pickle.loads(b"".join(chunks)) if chunks else None
            except Exception:       # noqa: BLE001 -- cut short: the drawer died
                ok = None
            self.close(kill=ok is None)
            if ok is not None and len(ok) != n:
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
