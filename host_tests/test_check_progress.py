"""`magcal check`'s progress line per sensor counts what its grid shows: the position/level
cells where that sensor settled (issue 19: it printed "12 segments" while the grid showed
none settled, the segments being at temperatures or in places the grid does not count)."""

from __future__ import annotations

import re

import numpy as np

from generator.campaign import simulate
from generator.campaign.check import check_campaign, format_text
from generator.io.unitfile import load_unit


def test_progress_counts_the_cells_the_grid_shows(tmp_path):
    unit0 = simulate.make_example_unit()
    simulate.write_unit_toml(unit0, tmp_path / "unit.toml")
    unit = load_unit(tmp_path / "unit.toml")
    rng = np.random.default_rng(5)
    # the demo's campaign: 600 s holds against board time constants of a few minutes
    csv, _ = simulate.simulate_campaign("thermal_12pos", unit, simulate.random_truth(unit, rng),
                                        rng, tmp_path, hold_s=600.0, sample_period_s=10.0,
                                        board_tau_scale=1 / 3)
    lines = []
    res = check_campaign(unit, [csv], progress=lines.append)
    for s in unit.sensors:
        line = next(m for m in lines if m.startswith(f"{s.name}: "))
        n = int(re.search(r"(\d+) position/level cell\(s\) of the grid settled", line).group(1))
        ok = sum(1 for c in res["cells"] if c["sensors"][s.name]["status"] == "ok")
        assert n == ok, (line, ok)
    assert "the worst of the sensors" in format_text(res)
