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
"""

from __future__ import annotations

import hashlib
import os

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
                    raise InputError(p, f"held-out file: the same recording as {first} "
                                        f"({what}), which the fit uses: it would hold "
                                        "nothing out; hold out another recording")
                raise InputError(p, f"the same recording as {first} ({what}): each sample "
                                    "would count twice (sigmas too small by sqrt(2), "
                                    "effects found in shared noise); give each recording "
                                    "once")
            seen[d] = i
