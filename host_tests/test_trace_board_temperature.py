"""Review 17 #8: a sensor without temperature (an RM3100 in nT) on a board whose other
sensor reports one: that temperature column is a candidate channel of the sensor without
temperature (and so among its correlates), not of the sensor that has it; and the body
rates appear once among the correlates (as the rate_*_dps channels)."""

from __future__ import annotations

import numpy as np

from generator.campaign import simulate as sim
from generator.io.unitfile import load_unit
from generator.trace import residual as rv
from generator.trace.samples import candidate_channels, gather_samples

from test_trace import run

UNIT = """[unit]
id = "boardtemp"
lab_field_nT = 49800.0

[[sensor]]
name = "rm"
part = "RM3100"
frame = "body"
axes = ["+x", "+y", "+z"]
input = "nT"
noise_nT = 15.0

[[sensor]]
name = "lis"
part = "LIS3MDL"
frame = "body"
axes = ["-y", "+x", "+z"]
lsb_nT = 14.62
zero_count = 0
noise_nT = 320.0
"""


def test_the_boards_temperature_is_a_channel_of_the_sensor_without_one(tmp_path):
    (tmp_path / "unit.toml").write_text(UNIT)
    unit = load_unit(tmp_path / "unit.toml")
    assert not unit.sensor("rm").temperature and unit.sensor("lis").temperature
    truth = sim.random_truth(unit, np.random.default_rng(17))
    tel, _ = run("rotation", unit, truth, 17, tmp_path)
    channels, _ = candidate_channels(unit, [tel])
    assert "lis_temp_C" in channels
    S = gather_samples(unit, [tel], [0], channels=channels)
    assert "lis_temp_C" in S["rm"].channels and "lis_temp_C" not in S["lis"].channels
    q = rv.quantities(S["rm"])
    assert "lis_temp_C" in q
    rates = [k for k in q if k.replace(" ", "_").startswith("rate_") and k[5] in "xyz"]
    assert len(rates) == len({k.replace(" ", "_") for k in rates}), rates
