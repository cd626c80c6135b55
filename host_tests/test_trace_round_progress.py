"""Issue 20 F5 (review 20e): a long scoring round is not silent. While the candidates of a
round are scored, trace.scoring.RoundProgress says where the round is (candidate i of n,
the scan's value j of m, the refits of a relinearised candidate) through the trace's
progress callback, at most every PROGRESS_EVERY_S (10 s) of wall time."""

from __future__ import annotations

import re

import numpy as np

from generator.trace import scoring
from generator.trace import tracer as tr
from generator.trace.samples import assign_blocks

from test_trace_jacobian import samples


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class E:
    def label(self):
        return "thermal_lag(mmc1_temp_C)"


def test_at_most_one_line_every_ten_seconds():
    clock, said = FakeClock(), []
    p = scoring.RoundProgress(said.append, "mmc1: round 1: ", clock=clock)
    assert p.every_s == 10.0
    p.candidate(1, 6, E())
    for j in range(100):              # 100 scan values 0.5 s apart: 50 s in all
        clock.t += 0.5
        p.tick(f"scan value {j + 1} of 100")
    assert len(said) == 5             # at 10, 20, 30, 40, 50 s: never closer than 10 s
    assert said[0] == ("mmc1: round 1: scoring candidate 1 of 6 (thermal_lag(mmc1_temp_C)): "
                       "scan value 20 of 100")
    clock.t += 3.0
    p.candidate(2, 6, E())            # 3 s after the last line: nothing
    assert len(said) == 5
    quiet = scoring.RoundProgress(None, clock=clock)     # no callback (-q): no line
    clock.t += 100.0
    quiet.tick("x")


def test_a_round_says_its_candidates_and_scan(tmp_path, monkeypatch):
    # every tick said (interval 0): the lines name each candidate of the round in order,
    # and a scanned candidate's values
    monkeypatch.setattr(scoring, "PROGRESS_EVERY_S", 0.0)
    cs, S = samples(tmp_path, "vec")
    base = tr.base_from_coefficients(cs, "mmc1", 2)
    model = tr.SensorModel.for_samples(base, S)
    S.block = assign_blocks(S)
    n_blocks = int(S.block.max()) + 1
    fold_of_block = np.arange(n_blocks) % tr.N_FOLDS
    said = []
    scores, _ = scoring.score_round(model, S, fold_of_block, n_blocks, tr.ALPHA,
                                    tr.MIN_REL_GAIN,
                                    scoring.RoundProgress(said.append, "mmc1: round 1: "))
    n = len(scores)
    assert n >= 2
    heads = [re.match(r"mmc1: round 1: scoring candidate (\d+) of (\d+) \(", s) for s in said]
    assert all(heads), said
    assert {int(h.group(2)) for h in heads} == {n}
    assert sorted({int(h.group(1)) for h in heads}) == list(range(1, n + 1))
    scans = [s for s in said if re.search(r"\(thermal_lag\(.*\)\): scan value \d+ of \d+$", s)]
    assert scans, said
