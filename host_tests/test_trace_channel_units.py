"""Review 17 #9: a channel given in tiny units (a heater's power in MW) makes the
coefficient nT per unit larger than a coefficient file holds: bad input naming the column
and a file that carries it (exit 2), not an internal error after the trace."""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.errors import InputError
from generator.io.telemetry import Telemetry
from generator.trace import tracer as tr

from test_trace import run, small_unit


def test_a_channel_in_tiny_units_is_bad_input_naming_it(tmp_path):
    unit = small_unit()
    truth = sim.random_truth(unit, np.random.default_rng(41))
    truth.H_boom_to_body = np.eye(3)
    src = sim.SquareWave(300.0, 0.4, 0.5, 0.0, 10.0, 3)
    eff = [sim.ChannelBias("mmc2", "heater_A", (250.0, 100.0, -60.0), src)]
    tel, _ = run("thermal", unit, truth, 5, tmp_path, eff)
    cols = dict(tel.columns)
    cols["heater_A"] = cols["heater_A"] * 1e-9          # 250 nT/A -> 2.5e11 nT per unit
    tiny = Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))
    with pytest.raises(InputError, match="column heater_A"):
        tr.trace(unit, [tiny])
