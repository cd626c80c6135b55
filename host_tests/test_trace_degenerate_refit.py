"""Review 17 #4: a refit after an effect that reflects or collapses M(t_ref) is refused
as a degenerate solution (the check the coefficient file would make later, which then
reported the trace's own output as bad user input)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from generator.trace import tracer as tr


def _model(M0):
    return SimpleNamespace(values=lambda: {"M_poly": np.asarray(M0, float)[None]})


def test_a_reflected_or_collapsed_M_is_degenerate():
    assert tr._bad_gain(_model(np.diag([1.02, 0.98, 1.01]))) == ""
    assert "det" in tr._bad_gain(_model(np.diag([0.3, 0.2, -0.05])))        # reflected
    assert "degenerate" in tr._bad_gain(_model(np.diag([1.0, 1.0, 1e-5])))  # collapsed
