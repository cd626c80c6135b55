"""Review 17 #10: between statistically equivalent explanations the one with fewer
parameters is chosen (a channel bias over the same channel through a lag whose time
constant is below the sample period), then the higher prior."""

from __future__ import annotations

import numpy as np

from generator.trace import effects as fx
from generator.trace import scoring as sc


def _score(effect, sse1, explained):
    s = sc.Score(effect, None, effect.n_dof, 100.0, sse1, np.zeros(3), 5.0, 1e-7, 100.0,
                 sse1, 1000.0, 50.0, 1e-9, 50.0, explained=explained)
    s.significant = True
    return s


def test_the_simpler_of_two_equivalent_explanations_wins():
    rng = np.random.default_rng(1)
    x = rng.normal(size=500)
    lagged = fx.LaggedChannelBias("heater_pw", 1.0)
    lagged.hyper = 1.14
    plain = fx.ChannelBias("heater_pw", 1.0)
    a = _score(lagged, 38.240, x)                 # slightly better, one more parameter
    b = _score(plain, 38.241, x + 1e-3 * rng.normal(size=500))
    assert lagged.n_dof > plain.n_dof
    assert sc.equivalent(a, b)
    assert sc.choose([a, b]) is b
    # not equivalent (clearly better held-out fit): the better one stays
    c = _score(plain, 45.0, x)
    assert not sc.equivalent(a, c)
    assert sc.choose([a, c]) is a
