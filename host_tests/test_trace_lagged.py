"""Issue 17, item 5: a bias that follows a channel through a first-order lag (a heater
warming a board) is named as such, with its time constant, on the right sensor; the
plain channel bias of the same channel is not what is kept.

Cases from the project's simulator (the fast twelve-position chamber test): a heater
switched as a square wave (period 400-900 s) whose field on one sensor follows the current
through a first-order lag of tau = 60-200 s (long enough against the 5 s sampling and
short against the period, so that the lagged and the plain regressors differ: the plain
channel bias leaves the exponential settling after each switch). Size 5-20 x the
per-axis noise (see test_trace_intermittent.py for the floor of 5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import tracer as tr
from generator.trace.effects import lag_filter

from test_trace import run, sigma_field, small_unit, _direction

SEEDS = [1, 2, 3]


@dataclass
class LaggedHeater(sim.Effect):
    """Test-only: a heater channel; the field follows it through a first-order lag."""
    sensor: str
    channel: str
    nT_per_unit: tuple
    tau_s: float
    source: sim.SquareWave
    name = "lagged_heater"

    def channels(self, time_s):
        return {self.channel: (self.source.values(time_s), self.source.decimals)}

    def frame_nT(self, ctx):
        f = lag_filter(ctx.time_s, ctx.channels[self.channel], self.tau_s)
        return f[:, None] * np.asarray(self.nT_per_unit, float)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_lagged_heater_is_named_with_its_time_constant(seed, tmp_path):
    rng = np.random.default_rng(61_000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = str(rng.choice([x.name for x in unit.sensors]))
    k = float(rng.uniform(5.0, 20.0))
    tau = float(rng.uniform(60.0, 200.0))
    src = sim.SquareWave(float(rng.uniform(400, 900)), 0.5, 1.0, 0.0,
                         float(rng.uniform(0, 300)), 3)
    d = _direction(rng)
    eff = LaggedHeater(s, "heater_A", tuple(d * k * sigma_field(unit.sensor(s))), tau, src)
    tel, _ = run("thermal", unit, truth, int(rng.integers(1 << 30)), tmp_path, [eff])
    res = tr.trace(unit, [tel])
    found = [(n, st.effect.name) for n, st in res.effects]
    assert (s, "lagged_channel_bias") in found, f"{k:.1f} x noise, tau {tau:.0f} s: {found}"
    assert all(n == s for n, _ in found), found
    assert (s, "channel_bias") not in found, found
    st = [x for n, x in res.effects if n == s and x.effect.name == "lagged_channel_bias"][0]
    tau_fit = st.effect.describe(st.params)["tau_s"]
    # the grid is refined within exp(+-0.3) of the best coarse value; the 5 s sampling
    # and the noise leave tau known to some tens of percent: a factor 1.5 either way
    assert tau / 1.5 < tau_fit < tau * 1.5, (tau, tau_fit)
