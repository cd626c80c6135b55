"""Review 17 #7: an effect that no data file shows on its own (its term detectable and
its held-out gain beyond chance in at least one file) is not kept: on large two-level
jumps (no catalogue effect) a thermal lag with a time constant of days was kept with
`shown_in: []`. Cases: test_trace_unexplained.case (the project's simulator, jumps and
a slow wander of 5-20 x the noise), plus the twelve-position test with the jump and a
rotation without it."""

from __future__ import annotations

import pytest

from generator.trace import tracer as tr

from test_trace_unexplained import SEEDS, case


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", ["jumps", "wander"])
def test_every_kept_effect_is_shown_by_a_file(kind, seed, tmp_path):
    unit, tel, s = case(kind, seed, tmp_path)
    out = tr.trace(unit, [tel]).to_json()
    for e in out["effects"]:
        assert e["files"]["shown_in"], (e["sensor"], e["effect"], e["files"])
