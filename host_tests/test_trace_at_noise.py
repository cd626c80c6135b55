"""Review 17 #5: "nothing significant left" only when the residual is statistically
consistent with the noise floor (residual.noise_floor: F test of mean(r^2) / floor^2),
not "within 2 x"."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from generator.trace import residual as rv


def _samples(n, noise_nT=None):
    return SimpleNamespace(idx=(np.arange(n), np.zeros(0, int), np.zeros(0, int)),
                           spec=SimpleNamespace(noise_nT=noise_nT, set_reset=False),
                           row_sample=np.repeat(np.arange(n), 3),
                           row_axis=np.tile(np.arange(3), n), order=np.arange(n),
                           file_index=np.zeros(n, int))


def test_white_noise_is_at_the_noise_and_structure_above_it_is_not():
    rng = np.random.default_rng(5)
    n = 1500
    S = _samples(n)
    white = rng.normal(0.0, 50.0, 3 * n)
    assert rv.noise_floor(S, white)["at_noise"]
    # a slow structure that makes the residual 1.5 x the noise: 1.25 x the noise's
    # variance on top of it, far beyond chance for 4500 rows
    t = np.repeat(np.arange(n), 3)
    slow = np.sqrt(2 * 1.25) * 50.0 * np.sin(2 * np.pi * t / 400.0)
    out = rv.noise_floor(S, white + slow)
    assert 1.3 < out["ratio"] < 1.7, out
    assert not out["at_noise"], out


def test_the_part_noise_is_a_known_floor():
    rng = np.random.default_rng(6)
    n = 1500
    S = _samples(n, noise_nT=50.0)
    S.idx = (np.zeros(0, int), np.arange(n), np.zeros(0, int))   # magnitudes: part floor
    S.row_sample, S.row_axis = np.arange(n), np.full(n, 3)
    out = rv.noise_floor(S, rng.normal(0.0, 50.0, n))
    assert out["source"] == "part" and out["at_noise"], out
    # a slow structure on top: 1.2 x the noise in RMS (0.44 x its variance added)
    slow = np.sqrt(2 * 0.44) * 50.0 * np.sin(2 * np.pi * np.arange(n) / 300.0)
    out = rv.noise_floor(S, rng.normal(0.0, 50.0, n) + slow)
    assert not out["at_noise"], out
