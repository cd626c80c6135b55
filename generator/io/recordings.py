"""Each recording counts once.

A fit, a trace or a campaign check treats every sample it is given as an independent
measurement. The same recording given twice (the same path twice, a copy under another
name, a link to it) would count each of its samples twice: the sigmas would come out
smaller by sqrt(2) than the data support, the held-out comparison would hold out one copy
against the other, and the trace would find "effects" in the noise the copies share
(review #20c N8: 15 copies of one flight file gave lagged biases not in the truth). So a
command that takes several recordings refuses, before reading them, two whose bytes are
the same.

Only files of equal size are compared (a stat each); their contents are hashed in chunks
(BLAKE2b), so the check costs nothing for distinct files and one read for true copies.
A path that cannot be read is left to the reader, which reports it with its own message.

Recordings can also overlap in part: two downlinks of one pass, a log cut where the next
one starts, a logger that writes a row twice. repeated_rows finds, after reading, the rows
that repeat an earlier row exactly (the same time and the same value in every column the
files share); the fit, the check and the trace say so in a WARNING (those samples count
twice) rather than drop them: which copy to keep is the user's call. A repeat needs equal
times, so files whose time ranges do not overlap, and a file whose times only increase,
are not compared at all.
"""

from __future__ import annotations

import hashlib
import os

import numpy as np

from generator.errors import InputError

CHUNK_BYTES = 1 << 20


def _digest(path) -> bytes | None:
    """BLAKE2b of the file's bytes, or None when it cannot be read."""
    h = hashlib.blake2b(digest_size=32)
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(CHUNK_BYTES), b""):
                h.update(block)
    except OSError:
        return None
    return h.digest()


def refuse_repeated_recordings(paths, held_out=()) -> None:
    """InputError naming the later of two paths whose files hold the same bytes (the same
    path given twice included); nothing when every recording is distinct. held_out: files
    that judge what paths taught (magcal trace --holdout): one that repeats a recording of
    paths would be no held-out check at all."""
    paths, held_out = list(paths), list(held_out)
    every = paths + held_out            # position >= len(paths): a held-out file
    by_size: dict[int, list] = {}
    for i, p in enumerate(every):
        try:
            st = os.stat(p)
        except OSError:
            continue            # the reader says what is wrong with it
        if not os.path.isfile(p):
            continue
        by_size.setdefault(st.st_size, []).append(i)
    for same_size in by_size.values():
        if len(same_size) < 2:
            continue
        seen: dict[bytes, int] = {}
        for i in same_size:
            d = _digest(every[i])
            if d is None:
                continue
            if d in seen:
                p, first = every[i], every[seen[d]]
                what = ("the same file given twice" if os.path.samefile(p, first)
                        else "identical bytes")
                if i >= len(paths) > seen[d]:
                    same = "file" if what == "the same file given twice" else "content"
                    raise InputError(p, f"held-out file: the same recording as {first} "
                                        f"({what}), which the fit uses (--holdout: the "
                                        f"same {same} as a data file): the held-out "
                                        "figures would be in-sample; hold out another "
                                        "recording")
                raise InputError(p, f"the same recording as {first} ({what}): each sample "
                                    "would count twice (sigmas too small by sqrt(2), "
                                    "effects found in shared noise); give each recording "
                                    "once")
            seen[d] = i


def row_names(columns) -> list:
    """The columns a row's fingerprint covers, in its order: time_s, then the rest sorted."""
    return ["time_s"] + sorted(set(columns) - {"time_s"})


def row_fingerprints(tel, names=None) -> np.ndarray:
    """(n,) uint64: one number per row of the columns `names` (default row_names of the
    file's columns; their float64 bits, NaN made one pattern, -0.0 made 0.0), equal for
    rows whose values are all equal."""
    names = row_names(tel.columns) if names is None else names
    h = np.zeros(tel.n, np.uint64)
    with np.errstate(over="ignore"):
        for c in names:
            v = np.array(tel.columns[c], np.float64)     # a copy: NaNs are rewritten
            v[np.isnan(v)] = np.nan                       # one NaN bit pattern
            v[v == 0] = 0.0                               # -0.0 equals 0.0
            h = h * np.uint64(0x100000001B3) ^ v.view(np.uint64)
    return h


def repeated_rows(tels) -> list:
    """The rows of each file that repeat an earlier row (an earlier file's, or its own):
    the same time_s and the same value in every column all the files share (at least one
    besides time_s, else nothing is compared). [{"path", "rows", "first_line", "of"}]:
    `of` the earlier file (its path; the file itself for a row written twice).

    A file is a Telemetry, or anything with path, n, time_s, columns, line_numbers and
    row_fingerprints (row_fingerprints of its columns, computed as it was read: a file
    a capped trace holds by rows, trace.filerows.FileRows); such a file is compared only
    when its columns are the shared ones (else its fingerprints cover other columns and
    its repeats are not looked for). Each file is one piece of StreamedRepeats, the one
    definition of a repeat."""
    if not tels:
        return []
    cols = [tuple(t.columns) for t in tels]
    shared = set(cols[0]).intersection(*cols[1:])

    def comparable(t):
        return t.n and (getattr(t, "row_fingerprints", None) is None
                        or set(t.columns) == shared)
    times = [np.asarray(t.time_s) if comparable(t) else None for t in tels]
    spans = [(float(ts[0]), float(ts[-1])) if ts is not None else None for ts in times]
    streamed = StreamedRepeats([t.path for t in tels], spans, cols)
    for j, t in enumerate(tels):
        if spans[j] is not None:
            streamed.add(j, t, prints=getattr(t, "row_fingerprints", None))
    return streamed.findings()


def repeated_rows_warnings(tels, found=None) -> list:
    """One WARNING line per finding of repeated_rows (found: its result, if already had)."""
    found = repeated_rows(tels) if found is None else found
    return [f"WARNING: {r['path']}: {r['rows']} row(s) from line {r['first_line']} repeat "
            + ("rows of the same file" if r["of"] == r["path"] else f"rows of {r['of']}")
            + " (the same time and values): those samples count twice; give each "
              "sample once (cut the overlap)" for r in found]


class StreamedRepeats:
    """Repeated rows found over files fed piece by piece, in file order: repeated_rows
    feeds each file whole, the fit's every-row pass above its read cap feeds pieces (the
    rows it keeps are blocks, so repeats between rows it did not keep would go unseen).
    Held: for each file, the fingerprints of its rows that lie
    in a later file's time span (memory grows with the overlap, not with the files), and
    the rows of the last time of the piece before (a row written twice across pieces).
    spans: (first, last time) per file; columns: each file's column names."""

    def __init__(self, paths, spans, columns):
        self.paths, self.spans = [str(p) for p in paths], list(spans)
        shared = set(columns[0]) if columns else set()
        for c in columns[1:]:
            shared &= set(c)
        self.names = row_names(shared) if "time_s" in shared and len(shared) > 1 else None
        self.kept = [[] for _ in self.paths]
        self.found = {}                     # (later file, earlier file) -> [rows, line]
        self.tail = None                    # (time, prints, file) of the last time seen

    def _overlap(self, i, j) -> bool:
        a, b = self.spans[i], self.spans[j]
        return a is not None and b is not None and a[0] <= b[1] and b[0] <= a[1]

    def _count(self, j, i, hit, lines):
        if hit.any():
            r = self.found.setdefault((j, i), [0, int(lines[np.argmax(hit)])])
            r[0] += int(hit.sum())

    def add(self, j: int, tel, prints=None) -> None:
        """The next piece of file j (its rows in order); prints: its rows' fingerprints
        where they were computed as it was read (else computed here, only if a row of the
        piece can repeat one: a time span shared with another file, or a time twice)."""
        if self.names is None or not tel.n:
            return
        t = np.asarray(tel.time_s, float)
        lines = np.asarray(tel.line_numbers)
        f = prints

        def fingerprints():
            nonlocal f
            if f is None:
                f = row_fingerprints(tel, self.names)
            return f
        for i in range(j):
            if self._overlap(i, j) and len(self.kept[i]):
                if isinstance(self.kept[i], list):   # file i is done: its prints, once
                    self.kept[i] = np.unique(np.concatenate(self.kept[i]))
                lo, hi = self.spans[i]
                m = (t >= lo) & (t <= hi)
                if m.any():
                    self._count(j, i, m & np.isin(fingerprints(), self.kept[i]), lines)
        later = np.zeros(tel.n, bool)
        for k in range(j + 1, len(self.paths)):
            if self._overlap(j, k):
                later |= (t >= self.spans[k][0]) & (t <= self.spans[k][1])
        if later.any():
            self.kept[j].append(fingerprints()[later])
        # a row written twice: equal rows have equal times, so sorted by (time, print)
        # a repeat follows a row equal to it; the last time of the piece before joins in
        tail = self.tail if self.tail is not None and self.tail[2] == j else None
        if np.any(np.diff(t) == 0) or (tail is not None and tail[0][0] == t[0]):
            prev_t, prev_f = (tail[0], tail[1]()) if tail is not None else (
                np.zeros(0), np.zeros(0, np.uint64))
            T, F = np.concatenate([prev_t, t]), np.concatenate([prev_f, fingerprints()])
            order = np.lexsort((F, T))
            same = np.zeros(len(T), bool)
            same[1:] = (F[order][1:] == F[order][:-1]) & (T[order][1:] == T[order][:-1])
            rows = order[same & (order >= len(prev_t))] - len(prev_t)
            if len(rows):
                hit = np.zeros(tel.n, bool)
                hit[rows] = True
                self._count(j, j, hit, lines)
        last = np.flatnonzero(t == t[-1])
        # the last time's prints, computed only if the next piece starts at that time
        self.tail = (t[last], lambda: fingerprints()[last], j)

    def findings(self) -> list:
        """repeated_rows' findings, in file order."""
        return [{"path": self.paths[j], "rows": r[0], "first_line": r[1],
                 "of": self.paths[i]} for (j, i), r in sorted(self.found.items())]
