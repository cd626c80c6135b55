"""Trace on clean data with many decoy channels: the multiple-comparison rule.

docs (generator/trace/tracer.py): a candidate is added only if p_lr x m < ALPHA, m the
number of candidates in the round (Bonferroni), the block t-test gives p < 0.01 and the
held-out RMS falls by >= 1 %. With 120 decoy telemetry channels (white and random-walk
noise, no coupling) on a clean fast chamber campaign nothing may be added, every score
must carry m = the candidates of its round (>= 120), and its verdict must be the
documented rule recomputed from its own numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.io.telemetry import Telemetry
from generator.io.telemetry_csv import read_telemetry
from generator.io.unit import Unit
from generator.trace import tracer as tr

N_DECOYS = 120
BLOCK_LEVEL = 0.01       # documented: one-sided t-test over the blocks
MIN_GAIN = 0.01          # documented: 1 % held-out RMS


def _unit() -> Unit:
    u = sim.make_example_unit("decoy_sat")
    return Unit(id=u.id, lab_field_nT=u.lab_field_nT, float_type=u.float_type,
                boom_reference="mmc1",
                sensors=tuple(s for s in u.sensors if s.name in ("mmc1", "mpu1", "mmc2")))


@pytest.fixture(scope="module", params=[1, 2])
def decoy_trace(request, tmp_path_factory):
    seed = request.param
    out = tmp_path_factory.mktemp(f"decoy{seed}")
    rng = np.random.default_rng(9000 + seed)
    unit = _unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    p, _ = sim.simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(seed), out,
                                 fast=True, set_reset_delay_s=0.0, name="clean")
    tel = read_telemetry(p, unit)
    cols = dict(tel.columns)
    n = len(cols["time_s"])
    for j in range(N_DECOYS):
        x = rng.normal(size=n)
        cols[f"decoy{j:03d}"] = np.cumsum(x) if j % 2 else x
    tel = Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))
    return tr.trace(unit, [tel])


def test_nothing_is_added(decoy_trace):
    found = [(n, st.effect.label()) for n, st in decoy_trace.effects]
    assert found == []


def test_every_score_is_judged_against_all_candidates_of_its_round(decoy_trace):
    for name, t in decoy_trace.traces.items():
        scores = t.last_scores
        decoys = [s for s in scores if "decoy" in s.effect.label()]
        assert len(decoys) == N_DECOYS, name
        for s in scores:
            assert s.m == len(scores), (name, s.effect.label(), s.m, len(scores))
            rule = (s.p_lr * len(scores) < tr.ALPHA and s.p_t < BLOCK_LEVEL
                    and s.rel_rms_gain >= MIN_GAIN)
            assert s.significant == rule, (name, s.effect.label())
            if s.p_lr < tr.ALPHA <= s.p_lr * len(scores):
                assert not s.significant   # significant alone, not among m candidates


def test_the_rule_divides_alpha_by_the_candidates():
    """Score.judge on a candidate that passes everything except the family-wise level."""
    s = tr.Score(effect=None, hyper=None, dof=3, sse0_cv=100.0, sse1_cv=90.0,
                 block_gain=np.ones(8), t=9.0, p_t=1e-6, sse0_full=100.0, sse1_full=90.0,
                 n_eff=1000.0, lr=1000 * math.log(100 / 90), p_lr=tr.ALPHA / 10, lr_fit=0.0)
    assert s.judge(1, tr.ALPHA, MIN_GAIN)
    assert s.judge(9, tr.ALPHA, MIN_GAIN)
    assert not s.judge(10, tr.ALPHA, MIN_GAIN)
    assert not s.judge(N_DECOYS, tr.ALPHA, MIN_GAIN)


def _score(**kw):
    v = dict(effect=None, hyper=None, dof=3, sse0_cv=100.0, sse1_cv=90.0,
             block_gain=np.ones(8), t=9.0, p_t=1e-6, sse0_full=100.0, sse1_full=90.0,
             n_eff=1000.0, lr=100.0, p_lr=1e-9, lr_fit=0.0)
    v.update(kw)
    return tr.Score(**v)


def test_each_of_the_three_criteria_is_required():
    """The documented rule needs all three: p_lr x m < ALPHA, block p_t < 0.01, held-out
    RMS gain >= min_gain (1 - sqrt(SSE1/SSE0))."""
    assert _score().judge(N_DECOYS, tr.ALPHA, MIN_GAIN)
    assert not _score(p_lr=tr.ALPHA).judge(1, tr.ALPHA, MIN_GAIN)
    assert not _score(p_t=BLOCK_LEVEL).judge(1, tr.ALPHA, MIN_GAIN)
    assert _score(p_t=0.999 * BLOCK_LEVEL).judge(1, tr.ALPHA, MIN_GAIN)
    # gain 1 - sqrt(0.985) = 0.75 %: below 1 %; 1 - sqrt(0.97) = 1.5 %: enough
    assert not _score(sse1_cv=98.5).judge(1, tr.ALPHA, MIN_GAIN)
    assert _score(sse1_cv=97.0).judge(1, tr.ALPHA, MIN_GAIN)
    assert not _score(sse1_cv=97.0).judge(1, tr.ALPHA, 0.02)
    assert tr.BLOCK_LEVEL == BLOCK_LEVEL and tr.MIN_REL_GAIN == MIN_GAIN

