"""Trace on clean data with many decoy channels: the multiple-comparison rule.

docs/effects.md and generator/trace/scoring.py: a candidate is added only if all three
hold, m the number of candidates judged in the round (Bonferroni), ALPHA = 1e-3:
  1. the held-out likelihood ratio against chi^2 with the effect's parameter count,
     p_lr x m < ALPHA;
  2. the held-out score test with each block's own noise (one-sided normal on z),
     p_z x m < ALPHA;
  3. the held-out RMS falls by >= 1 % (1 - sqrt(SSE1_cv / SSE0_cv)).
With 120 decoy telemetry channels (white and random-walk noise, no coupling) on a clean
fast chamber campaign nothing may be added, every score must carry m = the candidates of
its round (every channel effect of the catalogue scores every decoy channel, so m is at
least 120 x the number of channel effects), and its verdict must be the documented rule
recomputed from its own numbers.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
from scipy import stats as sps

from generator.campaign import simulate as sim
from generator.io.telemetry import Telemetry
from generator.io.telemetry_csv import read_telemetry
from generator.io.unit import Unit
from generator.trace import tracer as tr

N_DECOYS = 120
ALPHA = 1e-3             # documented: family-wise level per sensor and round
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
        assert not t.steps, name              # nothing added: the last round is round 1
        # the candidates of the round, listed the way scoring.score_round lists them (one
        # score per candidate instance; a scanned hyper-parameter is chosen inside the
        # candidate, not counted as more candidates)
        cands, _ = tr.candidate_list(t.final_model, t.S_fit)
        assert len(scores) == len(cands), name
        # every decoy channel is scored by the same channel effects, channel_bias among them
        per_channel = defaultdict(list)
        for s in scores:
            ch = getattr(s.effect, "channel", None)      # the channel effects' regressor
            if ch is not None and ch.startswith("decoy"):
                per_channel[ch].append(s.effect.name)
        assert len(per_channel) == N_DECOYS, name
        kinds = sorted(per_channel["decoy000"])
        assert "channel_bias" in kinds and len(set(kinds)) == len(kinds), (name, kinds)
        assert all(sorted(v) == kinds for v in per_channel.values()), name
        n_decoy_scores = sum(any("decoy" in ch for ch in s.effect.explained_by())
                             for s in scores)
        assert n_decoy_scores == N_DECOYS * len(kinds), name
        m = len(scores)
        assert m >= N_DECOYS * len(kinds)
        for s in scores:
            assert s.m == m, (name, s.effect.label(), s.m, m)
            # the stored p-values are the documented tests of the stored statistics
            assert s.p_lr == pytest.approx(sps.chi2.sf(max(s.lr, 0.0), s.dof), rel=1e-9,
                                           abs=1e-300)
            assert s.p_z == pytest.approx(sps.norm.sf(s.z), rel=1e-9, abs=1e-300)
            gain = 1.0 - math.sqrt(s.sse1_cv / s.sse0_cv)
            rule = s.p_lr * m < ALPHA and s.p_z * m < ALPHA and gain >= MIN_GAIN
            assert s.significant == rule, (name, s.effect.label())
            if s.p_lr < ALPHA <= s.p_lr * m or s.p_z < ALPHA <= s.p_z * m:
                assert not s.significant   # significant alone, not among m candidates
            assert s.summary()["candidates_in_round"] == m


# Hand-computed tail probabilities (tables of chi^2 and the normal):
#   chi^2 with 3 degrees of freedom: P(X > 21.1075) = 1.0e-4
#   standard normal: P(Z > 3.7190) = 1.0e-4
LR_P1E4_DOF3 = 21.1075
Z_P1E4 = 3.7190


def _score(**kw):
    """A candidate that passes every criterion by far at any m up to 10^6: likelihood
    ratio and z with p ~ 1e-12 and below, held-out RMS gain 1 - sqrt(0.9) = 5.1 %."""
    v = dict(effect=None, hyper=None, dof=3, sse0_cv=100.0, sse1_cv=90.0,
             block_gain=np.ones(8), z=9.0, p_z=1.1e-19, sse0_full=100.0, sse1_full=90.0,
             n_eff=1000.0, lr=60.0, p_lr=5.9e-13, lr_fit=0.0)
    v.update(kw)
    return tr.Score(**v)


def test_the_hand_computed_tails():
    """The fixtures' p-values are what their statistics give (guards the numbers above)."""
    assert sps.chi2.sf(LR_P1E4_DOF3, 3) == pytest.approx(1e-4, rel=1e-4)
    assert sps.norm.sf(Z_P1E4) == pytest.approx(1e-4, rel=1e-4)
    assert sps.chi2.sf(60.0, 3) == pytest.approx(5.9e-13, rel=0.05)
    assert sps.norm.sf(9.0) == pytest.approx(1.1e-19, rel=0.05)


@pytest.mark.parametrize("which", ["lr", "z"])
def test_the_rule_divides_alpha_by_the_candidates(which):
    """A candidate that passes everything except the family-wise level: p = 1e-4 on one
    test is significant alone (m = 1) and among 9 candidates (p x 9 < 1e-3), not among 10
    or among the decoy round. Without the Bonferroni factor m the last two would pass."""
    kw = {"lr": dict(lr=LR_P1E4_DOF3, p_lr=1e-4), "z": dict(z=Z_P1E4, p_z=1e-4)}[which]
    s = _score(**kw)
    assert s.judge(1, ALPHA, MIN_GAIN)
    assert s.judge(9, ALPHA, MIN_GAIN) and s.m == 9
    assert not s.judge(10, ALPHA, MIN_GAIN) and s.m == 10
    assert len(s.reasons) == 1 and "x 10" in s.reasons[0]
    assert not s.judge(3 * N_DECOYS, ALPHA, MIN_GAIN)


def test_each_of_the_three_criteria_is_required():
    """The documented rule needs all three: p_lr x m < ALPHA, p_z x m < ALPHA, held-out
    RMS gain >= min_gain (1 - sqrt(SSE1/SSE0)). Failing any one alone refuses, with one
    reason; just inside each threshold passes."""
    assert _score().judge(3 * N_DECOYS, ALPHA, MIN_GAIN)
    for crit in ("p_lr", "p_z"):
        s = _score(**{crit: ALPHA})
        assert not s.judge(1, ALPHA, MIN_GAIN) and len(s.reasons) == 1, crit
        assert _score(**{crit: 0.999 * ALPHA}).judge(1, ALPHA, MIN_GAIN), crit
        # at m = 360 the bound is ALPHA / 360
        assert not _score(**{crit: 1.01 * ALPHA / 360}).judge(360, ALPHA, MIN_GAIN), crit
        assert _score(**{crit: 0.99 * ALPHA / 360}).judge(360, ALPHA, MIN_GAIN), crit
    # gain 1 - sqrt(0.985) = 0.75 %: below 1 %; 1 - sqrt(0.97) = 1.5 %: enough
    s = _score(sse1_cv=98.5)
    assert not s.judge(1, ALPHA, MIN_GAIN) and len(s.reasons) == 1
    assert _score(sse1_cv=97.0).judge(1, ALPHA, MIN_GAIN)
    assert not _score(sse1_cv=97.0).judge(1, ALPHA, 0.02)
    # all three failing: three reasons
    s = _score(p_lr=0.5, p_z=0.5, sse1_cv=100.0)
    assert not s.judge(1, ALPHA, MIN_GAIN) and len(s.reasons) == 3
    # the documented constants are the trace's defaults
    assert tr.ALPHA == ALPHA and tr.MIN_REL_GAIN == MIN_GAIN
