"""Issue 17, item 1: the false-positive rate on clean draws does not rise with the new
significance rule and the new catalogue entries.

40 clean draws (random truth, the fast twelve-position chamber test and the hand rotation
with reference vectors, nothing the baseline lacks), seeds 101-140, none used while the
rule was developed. The rule's family-wise level is ALPHA = 1e-3 per sensor and round
(rules 1 and 2 must both pass, so less in practice); with three sensors a draw has at
most about 3e-3 chance of any false effect, 40 draws about 0.12 expected: two or more
false draws would happen by chance with probability about C(40,2) (3e-3)^2 ~ 0.7 %, so
at most one is allowed (the rule before issue 17 had 0 in 40).
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import tracer as tr

from test_trace import run, small_unit

SEEDS = list(range(101, 141))


@pytest.mark.slow
def test_clean_draws_stay_clean(tmp_path):
    false = []
    for seed in SEEDS:
        rng = np.random.default_rng(5000 + seed)
        unit = small_unit()
        truth = sim.random_truth(unit, rng)
        truth.H_boom_to_body = np.eye(3)
        out = tmp_path / str(seed)
        out.mkdir()
        tels = [run("thermal", unit, truth, seed, out)[0],
                run("rotation", unit, truth, seed + 100, out)[0]]
        res = tr.trace(unit, tels)
        found = [(n, st.effect.label()) for n, st in res.effects]
        if found:
            false.append((seed, found))
    print(f"\nfalse positives: {len(false)} of {len(SEEDS)} clean draws: {false}")
    assert len(false) <= 1, false
