"""Issue 17, item 5: a scale factor that follows a telemetry channel (a bridge supply
voltage) is named as such on the right sensor, not as a bias in that channel.

Cases from the project's simulator (the fast twelve-position chamber test, reference
vectors in twelve field directions, about 180 s each): a channel switching as a square
wave (period 200-600 s: it switches within and between positions) scales one sensor's
reading by (1 + g ch) on each axis; g chosen so that the largest contribution is
5-20 x the per-axis noise (see test_trace_intermittent.py for the floor of 5). A bias in
the channel cannot take it: the field it adds turns with the field direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import tracer as tr

from test_trace import run, sigma_field, small_unit

SEEDS = [1, 2, 3]


@dataclass
class ScaledBySupply(sim.Effect):
    """Test-only: each axis reads (1 + g_i ch) of its field."""
    sensor: str
    channel: str
    g_per_unit: tuple
    source: sim.SquareWave
    name = "scaled_by_supply"

    def channels(self, time_s):
        return {self.channel: (self.source.values(time_s), self.source.decimals)}

    def frame_nT(self, ctx):
        ch = ctx.channels[self.channel]
        return ch[:, None] * np.asarray(self.g_per_unit, float) * ctx.field_frame_nT


@pytest.mark.parametrize("seed", SEEDS)
def test_a_scale_following_a_channel_is_named(seed, tmp_path):
    rng = np.random.default_rng(71_000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = str(rng.choice([x.name for x in unit.sensors]))
    k = float(rng.uniform(5.0, 20.0))
    src = sim.SquareWave(float(rng.uniform(200, 600)), 0.5, 1.0, 0.0,
                         float(rng.uniform(0, 300)), 3)
    g = rng.uniform(0.3, 1.0, 3) * rng.choice([-1.0, 1.0], 3)
    g *= k * sigma_field(unit.sensor(s)) / (unit.lab_field_nT or 50_000.0) / np.max(np.abs(g))
    eff = ScaledBySupply(s, "supply_V", tuple(g), src)
    tel, _ = run("thermal", unit, truth, int(rng.integers(1 << 30)), tmp_path, [eff])
    res = tr.trace(unit, [tel])
    found = [(n, st.effect.name) for n, st in res.effects]
    assert found and found[0] == (s, "channel_scale"), f"{k:.1f} x noise on {s}: {found}"
    assert all(n == s for n, _ in found), found
