"""Progress lines for long work: one line per step on stderr, with elapsed time."""

from __future__ import annotations

import time


class Progress:
    """One line per step on stderr, with elapsed time; silent when quiet."""

    def __init__(self, quiet=False, stream=None):
        import sys

        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()

    def __call__(self, message: str):
        if not self.quiet:
            print(f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=self.stream,
                  flush=True)


class Every:
    """A throttle for progress lines during long work: calling it answers True at most
    once every every_s seconds of clock() (the first time every_s after it was made)."""

    def __init__(self, every_s: float, clock=time.monotonic):
        self.every_s, self.clock = every_s, clock
        self.last = clock()

    def __call__(self) -> bool:
        now = self.clock()
        if now - self.last < self.every_s:
            return False
        self.last = now
        return True
