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
