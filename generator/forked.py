"""Independent calls run in forked children: plain fork + a pipe per child + waitpid.

    for result in forked_map(fn, items, workers=2, keep=(InputError,)):
        ...

forked_map(fn, items) yields fn(item) for every item, in the items' order, as a serial
loop would; the calls run in up to `workers` forked children (item k in child k %
workers; with on_demand=True each child takes the next item whenever it has finished one,
so that calls of unequal cost keep every child busy), each child sending its results back
through its own pipe (pickle, length prefixed) and ending with os._exit (no atexit, no
buffered output of the parent's written twice). No multiprocessing.Pool and no
concurrent.futures: a Pool runs handler threads in the parent and shares a queue lock
with its workers, and its shutdown was seen to hang for good (a worker left waiting on
that lock). A child shares nothing with the parent but
the calls it was forked to do.

Failures keep the serial behaviour:
* a call that raised an exception of a type in `keep` (e.g. InputError: one line, exit 2)
  raises the same exception, rebuilt in the parent, when its turn comes in the order;
* any other failure (another exception, a result that does not pickle, a child that died)
  re-runs that call in the parent, where it fails, or not, as it would serially (its own
  traceback); a child that died leaves the rest of its share to the parent as well
  (on_demand: the call it had taken; the other children take the items not yet taken,
  and the parent runs any item no child returned once every child has ended);
* an interrupt in the parent (KeyboardInterrupt, the CLI's SIGTERM exception) kills and
  reaps every child before it goes on; a child itself never unwinds into the parent's
  code (os._exit in every case).

Runs serially, in the caller's process, where fork does not exist, with fewer than 2
workers or items, in a forked child already (no nested forks), while other threads run
in the process (forking a multi-threaded process is unsafe: a lock another thread held
stays locked in the child for good), or when the system refuses a pipe or a fork (any
child already forked is killed and reaped first).

Output: the parent flushes sys.stdout and sys.stderr before it forks (a child must not
inherit, and later write, text the parent had buffered) and a child flushes its own
before os._exit (what a call printed is not lost; it may interleave with the parent's).
A caller whose calls report progress returns their lines with the result and prints them
itself, in order (generator.fit.thermal.fit_unit).

`workers` defaults to default_workers(): the MAGCAL_WORKERS environment variable if set
(1: everything serial, in the process), else min(2, os.cpu_count()).
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import sys
import threading

_HEADER = struct.Struct("<Q")
_IN_CHILD = [False]


def default_workers() -> int:
    """MAGCAL_WORKERS if set (1: everything serial), else min(2, os.cpu_count())."""
    env = os.environ.get("MAGCAL_WORKERS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return int(env)
    return min(2, os.cpu_count() or 1)


def can_fork(n_items: int, workers: int) -> bool:
    """Would forked_map fork for n_items calls on `workers` (module doc: when it does not)."""
    return (hasattr(os, "fork") and workers >= 2 and n_items >= 2 and not _IN_CHILD[0]
            and threading.active_count() == 1)


# on_demand hands out item numbers through a pipe filled before the children start: at
# most this many (4 bytes each, within a pipe's 64 KiB buffer); beyond, items are dealt
ON_DEMAND_MAX_ITEMS = 4096
_INDEX = struct.Struct("<I")


def forked_map(fn, items, workers=None, keep=(), before_fork=None, on_demand=False):
    """fn(item) for item in items: an iterator yielding each result in the items' order as
    soon as it is back; the calls spread over forked children (module doc). Iterate it to
    the end (or close it): the children are reaped when it finishes. before_fork(), if
    given, runs in this process just before the children are forked, and only then: the
    work every child would otherwise repeat on its own (lazy imports, loaded fonts), done
    once and inherited. on_demand: each child takes the next item when it has finished
    one (item numbers read from a shared pipe, 4 bytes each: a pipe read that small is
    atomic), instead of items k, k + workers, ...; results the same, in the same order."""
    items = list(items)
    workers = default_workers() if workers is None else workers
    if not can_fork(len(items), workers):
        return (fn(it) for it in items)
    return _run(fn, items, min(workers, len(items)), tuple(keep), before_fork,
                bool(on_demand) and len(items) <= ON_DEMAND_MAX_ITEMS)


# ---- the child ------------------------------------------------------------------------
def _send(fd, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def _exception_state(e):
    """An exception as (class, args, __dict__): rebuilt in the parent without calling the
    class's own __init__ (whose signature pickle does not know, e.g. InputError's)."""
    return (type(e), e.args, dict(getattr(e, "__dict__", {})))


def _rebuild(state):
    cls, args, attrs = state
    e = cls.__new__(cls)
    BaseException.__init__(e, *args)
    e.__dict__.update(attrs)
    return e


def _flush_std() -> None:
    for f in (sys.stdout, sys.stderr):
        try:
            if f is not None:
                f.flush()
        except Exception:
            pass


def _taken(index_fd):
    """The item numbers a child takes from the shared pipe, one at a time, until it is
    empty (its write end closed: end of file)."""
    while True:
        b = os.read(index_fd, _INDEX.size)
        if len(b) < _INDEX.size:
            return
        yield _INDEX.unpack(b)[0]


def _child(fn, items, w, workers, keep, fd, index_fd=None) -> None:
    """Child w: the calls w, w + workers, ... (index_fd: those it takes from that pipe,
    each result preceded by its item number) -> ("ok", value) / ("keep", exception
    state) / ("failed", None) per call, in order; never returns (os._exit, also on an
    interrupt: a KeyboardInterrupt or the CLI's SIGTERM exception is no Exception, so it
    ends the child, whose remaining calls the parent, if it goes on, runs itself)."""
    code = 1
    try:
        _IN_CHILD[0] = True
        ks = range(w, len(items), workers) if index_fd is None else _taken(index_fd)
        for k in ks:
            try:
                msg = ("ok", fn(items[k]))
            except keep as e:
                msg = ("keep", _exception_state(e))
            except Exception:
                msg = ("failed", None)
            if index_fd is not None:
                _send(fd, k)
            try:
                _send(fd, msg)
            except Exception:             # a result (or exception) that does not pickle
                _send(fd, ("failed", None))
        code = 0
    finally:
        try:
            _flush_std()
        finally:
            os._exit(code)


# ---- the parent -----------------------------------------------------------------------
class _Reader:
    """Complete messages from the children's pipes, read as they arrive (poll), so no
    child waits on a full pipe while the parent waits on another (a result may be far
    larger than a pipe's buffer)."""

    def __init__(self, fds):
        self.fds = list(fds)
        self.buf = [bytearray() for _ in self.fds]
        self.msgs = [[] for _ in self.fds]
        self.open = [True] * len(self.fds)

    def _split(self, w):
        b = self.buf[w]
        while len(b) >= _HEADER.size:
            (n,) = _HEADER.unpack_from(b)
            if len(b) < _HEADER.size + n:
                break
            self.msgs[w].append(bytes(b[_HEADER.size:_HEADER.size + n]))
            del b[:_HEADER.size + n]

    def next(self, w):
        """Child w's next message (bytes), or None when its pipe ended without one."""
        while not self.msgs[w] and self.open[w]:
            self.pump()
        return self.msgs[w].pop(0) if self.msgs[w] else None

    def pump(self) -> None:
        """Read what the open pipes have (blocks until one has data or ends)."""
        for i in self._ready():
            chunk = os.read(self.fds[i], 1 << 20)
            if chunk:
                self.buf[i] += chunk
                self._split(i)
            else:                           # end of file: the child has exited
                self.open[i] = False

    def item(self, k, done):
        """on_demand: item k's message (bytes), or None when every pipe ended without it;
        done: {item number: message} of those back before their turn (kept for it)."""
        while k not in done:
            for w in range(len(self.fds)):
                msgs = self.msgs[w]
                while len(msgs) >= 2:        # (item number, message) as the child sent them
                    num = pickle.loads(msgs.pop(0))
                    done[num] = msgs.pop(0)
            if k in done or not any(self.open):
                break
            self.pump()
        return done.pop(k, None)

    def _ready(self):
        """Indices of the open pipes with data or end of file (blocks until one has)."""
        live = [i for i in range(len(self.fds)) if self.open[i]]
        if hasattr(select, "poll"):
            poller = select.poll()
            for i in live:
                poller.register(self.fds[i], select.POLLIN)
            by_fd = {self.fds[i]: i for i in live}
            return [by_fd[fd] for fd, _ in poller.poll()]
        ready, _, _ = select.select([self.fds[i] for i in live], [], [])
        return [self.fds.index(fd) for fd in ready]


_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM") if hasattr(signal, n))


def _start(fn, items, workers, keep, pids, fds, index_fd=None) -> bool:
    """Fork the children (their pids and read ends appended to pids, fds); False if the
    system refused a pipe or a fork (the caller kills and reaps those already started).
    SIGINT and SIGTERM are held back from the fork until its pid is in pids: an
    interrupt between the two would leave a child nobody kills. index_fd: the read end
    of the item numbers' pipe (on_demand), its write end already closed."""
    _flush_std()
    mask = hasattr(signal, "pthread_sigmask")
    for w in range(workers):
        try:
            r, wfd = os.pipe()
        except OSError:
            return False
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS) if mask else None
        try:
            try:
                pid = os.fork()
            except OSError:
                os.close(r)
                os.close(wfd)
                return False
            if pid == 0:                    # the child: only its own write end stays open
                try:
                    os.close(r)
                    for fd in fds:
                        os.close(fd)
                    if mask:
                        signal.pthread_sigmask(signal.SIG_SETMASK, old)
                finally:
                    _child(fn, items, w, workers, keep, wfd, index_fd)
            os.close(wfd)
            pids.append(pid)
            fds.append(r)
        finally:
            if mask:
                signal.pthread_sigmask(signal.SIG_SETMASK, old)
    return True


def _stop(pids, fds, kill) -> None:
    for pid in pids:      # done: reaped; failed or interrupted: killed first
        try:
            if kill:
                os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
        while True:
            try:
                os.waitpid(pid, 0)
                break
            except InterruptedError:
                continue
            except OSError:
                break
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass
    del pids[:], fds[:]


def _index_pipe(n):
    """on_demand: a pipe holding the item numbers 0..n-1, its write end closed (the
    children read it to its end); its read end, or None if the system refused a pipe."""
    try:
        r, w = os.pipe()
    except OSError:
        return None
    try:
        data = memoryview(b"".join(_INDEX.pack(k) for k in range(n)))
        while data:                         # within the pipe's buffer: never blocks
            data = data[os.write(w, data):]
    finally:
        os.close(w)
    return r


def _run(fn, items, workers, keep, before_fork, on_demand=False):
    pids, fds = [], []
    finished = False
    index_fd = None
    try:
        if before_fork is not None:
            before_fork()
        if on_demand:
            index_fd = _index_pipe(len(items))
        started = (not on_demand or index_fd is not None) and _start(
            fn, items, workers, keep, pids, fds, index_fd)
        if index_fd is not None:            # the children hold their own read ends
            os.close(index_fd)
            index_fd = None
        if not started:
            _stop(pids, fds, kill=True)     # no fork to be had: the serial loop
            for it in items:
                yield fn(it)
            finished = True
            return
        reader = _Reader(fds)
        done = {}
        for k in range(len(items)):
            raw = reader.item(k, done) if on_demand else reader.next(k % workers)
            try:
                kind, payload = pickle.loads(raw) if raw is not None else ("failed", None)
            except Exception:
                kind, payload = "failed", None
            if kind == "keep":
                try:
                    err = _rebuild(payload)
                except Exception:           # not rebuilt: the call fails here instead
                    kind = "failed"
                else:
                    raise err
            # "failed": run as it would serially, in this process
            yield payload if kind == "ok" else fn(items[k])
        finished = True
    finally:
        if index_fd is not None:
            os.close(index_fd)
        _stop(pids, fds, kill=not finished)
