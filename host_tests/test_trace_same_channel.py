"""Review 17 #2: a channel scale and a channel bias in the same channel share one
channel of the flight chain (its C column and its g column), in either order."""

from __future__ import annotations

import numpy as np
import pytest

from generator.flight.chain import SensorOptions
from generator.trace import effects as fx


@pytest.mark.parametrize("scale_first", [True, False])
def test_scale_and_bias_in_one_channel_are_one_channel(scale_first):
    values = {"b_poly_nT": np.zeros((1, 3))}
    options = {}
    sc = fx.ChannelScale("vbus_V", 0.3)
    bi = fx.ChannelBias("vbus_V", 0.3)
    p_sc, p_bi = np.array([1.0, -2.0, 3.0]), np.array([30.0, 60.0, -90.0])
    order = [(sc, p_sc), (bi, p_bi)] if scale_first else [(bi, p_bi), (sc, p_sc)]
    for e, p in order:
        e.to_flight(p, values, options, None)
    assert options["channels"] == ["vbus_V"]
    assert values["C_nT_per_unit"].shape == (3, 1)
    np.testing.assert_array_equal(values["C_nT_per_unit"][:, 0], bi.C_nT_per_unit(p_bi))
    np.testing.assert_array_equal(values["_g_by_channel"]["vbus_V"], sc.g_per_unit(p_sc))
    o = SensorOptions.from_dict(options)
    assert o.channels == ("vbus_V",) and o.channel_scale


def test_a_trace_with_scale_and_bias_in_one_channel_writes_coefficients(tmp_path):
    """End to end (the simulator, the twelve-position test): a supply voltage scales one
    sensor's reading and adds a bias to it; the traced set carries the channel once."""
    from generator.campaign import simulate as sim
    from generator.trace import tracer as tr
    from test_trace import run, sigma_field, small_unit
    from test_trace_channel_scale import ScaledBySupply
    rng = np.random.default_rng(75_001)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = "mmc1"
    src = sim.SquareWave(370.0, 0.5, 1.0, 0.0, 40.0, 3)
    sig = sigma_field(unit.sensor(s))
    g = np.array([0.7, -1.0, 0.5]) * 15 * sig / (unit.lab_field_nT or 50_000.0)
    C = np.array([-0.4, 0.9, 0.6]) * 15 * sig

    class ScaledAndBiased(ScaledBySupply):
        def frame_nT(self, ctx):
            return super().frame_nT(ctx) + ctx.channels[self.channel][:, None] * C

    effs = [ScaledAndBiased(s, "supply_V", tuple(g), src)]
    tel, _ = run("thermal", unit, truth, int(rng.integers(1 << 30)), tmp_path, effs)
    res = tr.trace(unit, [tel])
    found = sorted(st.effect.name for n, st in res.effects if n == s)
    assert {"channel_scale", "channel_bias"} <= set(found) or \
        {"channel_scale", "lagged_channel_bias"} <= set(found), found
    o = res.coefficients.spec.opts(s)
    assert o.channels.count("supply_V") == 1 and o.channel_scale
