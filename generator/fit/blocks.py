"""Contiguous blocks of telemetry rows drawn at random over files (systematic cluster
sampling, seed fixed): the one place where the block length and the draw are decided, for
`magcal fit`'s read cap (fit.read_cap) and `magcal trace`'s cap (trace.subsample).

Both keep whole blocks of consecutive rows, not single rows, because what they compute
reads neighbouring rows: the fit's temperature screen (a running median of 5 samples, the
excursions a board cannot make within BOARD_TAU_MIN_S) and its constant-temperature
segments (a settled hold of at least 10 min after a board's approach, docs/segments.md);
the trace's lag recursions and lag-1 statistics. docs/fit_samples.md.
"""

from __future__ import annotations

import math

import numpy as np

# The block length. The slowest time constant the calibration has to see through is a
# board's thermal lag: 10-20 min for these units' boards (fit.samples BOARD_TAU_MIN_S
# documents the 5-min lower bound); TAU_MAX_S = 20 min. A block spans BLOCK_TAUS = 5 of it
# (100 min): a board's approach to a chamber level (~5 tau to settle within the segment
# finder's band) and the 10-min settled hold the per-level method needs
# (docs/segments.md) fit in one block, and so does a lag's response to the temperature
# within a block (the trace). In rows: the block's duration over the files' shortest median
# sample period, at least MIN_BLOCK_ROWS (statistics over neighbouring rows -- the
# trace's lag-1 correlation, the screens' running median of 5 -- lose one pair or a few
# rows at each gap: under 0.1 % of them), and at most the cap over MIN_BLOCKS (so that the
# data keep at least that many blocks spread over the files' time; a block is then shorter
# than 5 tau of the slowest lag, and the callers' notes say how long it is).
TAU_MAX_S = 1200.0
BLOCK_TAUS = 5.0
MIN_BLOCK_ROWS = 1000
MIN_BLOCKS = 20


def block_rows_of_period(dt_s: float, max_rows: int) -> int:
    """L, the rows of one block at a median sample period dt_s under a cap of max_rows rows
    (see the constants above)."""
    L = max(MIN_BLOCK_ROWS, math.ceil(BLOCK_TAUS * TAU_MAX_S / dt_s))
    return int(min(L, max(MIN_BLOCK_ROWS, max_rows // MIN_BLOCKS)))


def median_period_s(time_s) -> float | None:
    """The median positive step of a time series (None when it has none)."""
    d = np.diff(np.asarray(time_s, float))
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else None


def block_rows(tels, max_rows) -> int:
    """L for these files: the shortest of their median sample periods (1 s if none has
    one)."""
    dts = [p for p in (median_period_s(t.time_s) for t in tels) if p is not None]
    return block_rows_of_period(min(dts) if dts else 1.0, max_rows)


def fractional_systematic(n: int, m: int, rng) -> np.ndarray:
    """m sorted positions of 0..n-1 (m <= n): systematic sampling with the fractional step
    n / m, one position uniformly at random in each interval [floor(i n / m),
    floor((i + 1) n / m)); exactly m positions, spread evenly over the n."""
    if m <= 0 or n <= 0:
        return np.zeros(0, int)
    m = min(m, n)
    edges = (np.arange(m + 1) * n) // m
    return edges[:-1] + rng.integers(0, edges[1:] - edges[:-1])


def _draw(rows, m, rng, L):
    """[(file index, sorted block numbers)]: m blocks drawn over ALL the files' blocks in
    order (one systematic draw over the concatenated block list), grouped by file; rows:
    the files' row counts."""
    nb = np.array([-(-int(n) // L) for n in rows], int)
    first = np.concatenate([[0], np.cumsum(nb)])
    picks = fractional_systematic(int(first[-1]), m, rng)
    fi = np.searchsorted(first, picks, side="right") - 1
    return [(int(f), picks[fi == f] - first[f]) for f in range(len(rows))]


def block_runs(n: int, picks, L: int) -> list:
    """The row numbers of the drawn blocks of a file of n rows (one array per block)."""
    return [np.arange(int(b) * L, min(int(n), (int(b) + 1) * L)) for b in picks]


def draw_blocks(data_rows, hold_rows, max_rows: int, L: int, seed: int):
    """(m_data, m_hold, draws, rows): blocks of L consecutive rows drawn over every file's
    blocks in order, the data files' (row counts data_rows) and the holdout files'
    (hold_rows; may be empty) apart, in proportion to their blocks and at least one each;
    floor(max_rows / L) blocks, or more while files shorter than a block leave the drawn
    rows more than one block under max_rows (a bisection over the count: every count tried
    is drawn and measured, so the one taken holds the cap). draws: [data draw, hold draw],
    each [(file index, sorted block numbers)]; rows: the rows drawn. numpy PCG64 seeded
    from (seed, role) alone: the same row counts give the same blocks."""
    data_rows, hold_rows = [int(n) for n in data_rows], [int(n) for n in hold_rows]
    nb_d = sum(-(-n // L) for n in data_rows)
    nb_h = sum(-(-n // L) for n in hold_rows)
    n_blocks = nb_d + nb_h

    def plan(m):
        """The draws of m blocks (data and holdout apart, in proportion) and their rows."""
        # at least one block each, and the data at least one of the m (m >= 2 with
        # holdout files, the callers' check): data and holdout blocks together m
        m_h = min(nb_h, m - 1, max(1, round(m * nb_h / n_blocks))) if nb_h else 0
        m_d = min(nb_d, max(1, m - m_h))
        draws = []
        for role, (rows, mm) in enumerate(((data_rows, m_d), (hold_rows, m_h))):
            rng = np.random.Generator(np.random.PCG64([seed, role]))
            draws.append(_draw(rows, mm, rng, L))
        got = sum(min(rows[f], (int(b) + 1) * L) - int(b) * L
                  for rows, d in zip((data_rows, hold_rows), draws)
                  for f, picks in d for b in picks)
        return m_d, m_h, draws, got

    m = min(n_blocks, max_rows // L)               # the blocks the cap holds
    m_d, m_h, draws, got = plan(m)
    # files shorter than a block give blocks of fewer than L rows (review #20c N2: 200
    # files of 200 rows beside a long file used a fifth of the cap): more blocks, as many
    # as keep the drawn rows within the cap
    lo, hi = m, n_blocks
    while got < max_rows - L and lo < hi:
        mid = (lo + hi + 1) // 2
        cand = plan(mid)
        if cand[3] <= max_rows:
            lo, (m_d, m_h, draws, got) = mid, cand
        else:
            hi = mid - 1
    return m_d, m_h, draws, got
