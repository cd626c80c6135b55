"""Issue 17, item 1: the significance rule is right for intermittent effects.

An effect that sits in a few blocks only (a heater switched on for a while, one coil run,
a current that switches on once and stays on) must be found; a channel that switches in
the same way but couples nothing must not be. Cases from the project's simulator (the
fast twelve-position chamber test of host_tests/test_trace.py): the data file carries the
effect, a second clean campaign is the --holdout file (the real lab case: fit on one part
of a log, evaluate on another), so every block of the data is a fit block.

The window of the effect covers a fraction of the data's time (2, 5, 10, 20 %: 1 to 10 of
the about 50 cross-validation blocks), placed at random; the size is 5-20 x the sensor's
per-axis field noise. Below about 5 x noise an effect confined to one block (about 9
samples x 3 axes) cannot pass a family-wise 1e-3 test over the ~20 candidates of a round:
the held-out score z is about sqrt(sum u^2) / (2 sigma) = 1.5 k for k x noise on 9
samples, and z > 4.1 is needed (normal tail 1e-3 / 20). So 5 is the floor of what the rule
can promise, not a value read off its output.

Seeds. The rule (ALPHA = 1e-3 family-wise, rule 2 of generator.trace.scoring) was
developed while looking at TUNE_SEEDS; the asserted tests run on REPORT_SEEDS, which were
not looked at before the rule was fixed.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import tracer as tr

from test_trace import run, sigma_field, small_unit, _direction

TUNE_SEEDS = [1, 2, 3]
REPORT_SEEDS = [11, 12, 13]
FRACTIONS = [0.02, 0.05, 0.10, 0.20]
SIZE_RANGE = (5.0, 20.0)       # x per-axis field noise, see the module docstring
CAMPAIGN_S = 2160.0            # the fast thermal campaign's length
PERIOD_S = 1e6                 # a SquareWave this long is one window (on once)


def window(t_on, width_s):
    """A channel that is 1 from t_on for width_s, else 0 (a SquareWave of one period)."""
    return sim.SquareWave(PERIOD_S, width_s / PERIOD_S, 1.0, 0.0, t_on, 3)


def intermittent_case(seed, fraction, out, *, coupled=True, switch_once=False):
    rng = np.random.default_rng(17_000 + seed + int(1000 * fraction) + 7 * switch_once)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = str(rng.choice([x.name for x in unit.sensors]))
    k = float(rng.uniform(*SIZE_RANGE))
    d = _direction(rng)
    if switch_once:     # on from a time in the middle part of the file to its end
        t_on = float(rng.uniform(0.2, 0.8)) * CAMPAIGN_S
        src = window(t_on, PERIOD_S / 2)
    else:
        width = fraction * CAMPAIGN_S
        t_on = float(rng.uniform(0.0, CAMPAIGN_S - width))
        src = window(t_on, width)
    C = tuple(d * k * sigma_field(unit.sensor(s))) if coupled else (0.0, 0.0, 0.0)
    effects = [sim.ChannelBias(s, "payload_A", C, src)]
    cseed = int(rng.integers(1 << 30))
    tel, _ = run("thermal", unit, truth, cseed, out, effects, name="data")
    hold, _ = run("thermal", unit, truth, cseed + 1, out, (), name="later")
    return unit, tel, hold, s, k


def found(res):
    return [(n, st.effect.name, st.effect.explained_by()) for n, st in res.effects]


@pytest.mark.parametrize("seed", REPORT_SEEDS)
@pytest.mark.parametrize("fraction", FRACTIONS)
def test_an_effect_in_a_few_blocks_is_found(fraction, seed, tmp_path):
    unit, tel, hold, s, k = intermittent_case(seed, fraction, tmp_path)
    res = tr.trace(unit, [tel], [hold])
    f = found(res)
    assert (s, "channel_bias", ["payload_A"]) in f, \
        f"{k:.1f} x noise on {s} in {100 * fraction:g} % of the time not found: {f}"
    assert len(f) == 1, f"other effects named too: {f}"


@pytest.mark.parametrize("seed", REPORT_SEEDS)
def test_an_effect_that_switches_once_is_found(seed, tmp_path):
    unit, tel, hold, s, k = intermittent_case(seed, 0.0, tmp_path, switch_once=True)
    res = tr.trace(unit, [tel], [hold])
    f = found(res)
    assert (s, "channel_bias", ["payload_A"]) in f, f"{k:.1f} x noise on {s}: {f}"
    assert len(f) == 1, f"other effects named too: {f}"


@pytest.mark.parametrize("seed", REPORT_SEEDS + [21, 22, 23, 24, 25, 26, 27])
def test_a_channel_that_switches_but_couples_nothing_is_not_an_effect(seed, tmp_path):
    fraction = FRACTIONS[seed % len(FRACTIONS)]
    unit, tel, hold, s, _ = intermittent_case(seed, fraction, tmp_path, coupled=False,
                                              switch_once=seed % 2 == 0)
    res = tr.trace(unit, [tel], [hold])
    assert not found(res), f"invented effects: {found(res)}"
