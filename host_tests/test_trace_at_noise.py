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


def test_files_at_different_noise_levels_are_at_the_noise():
    """Review #20c N9: white noise, one file at 10 nT and one at 100 nT. The residual's
    mean square is the rows' mean of the two variances; one MAD over the pooled
    differences sat near the quiet file's and called the rest "unexplained"."""
    rng = np.random.default_rng(7)
    n = 3000
    S = _samples(n)
    S.file_index = np.repeat([0, 1], n // 2)
    sigma = np.where(np.repeat(S.file_index, 3) == 0, 10.0, 100.0)
    white = rng.normal(0.0, 1.0, 3 * n) * sigma
    out = rv.noise_floor(S, white)
    expected = np.sqrt((10.0 ** 2 + 100.0 ** 2) / 2)
    assert abs(out["floor_nT"] / expected - 1) < 0.1, out     # MAD: ~3 % standard error
    assert out["at_noise"], out
    # the pooled MAD this replaces would have put the floor near the quiet file's noise
    d = np.diff(white.reshape(n, 3)[:, 0])
    pooled = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)
    assert pooled < 0.6 * expected
    # structure on top of the mixed noise is still above it (1.5 x in RMS)
    t = np.repeat(np.arange(n), 3)
    slow = np.sqrt(2 * 1.25) * expected * np.sin(2 * np.pi * t / 400.0)
    assert not rv.noise_floor(S, white + slow)["at_noise"]


def test_many_small_files_are_pooled():
    """Files too short for their own noise estimate (here 40 rows each) are pooled into
    one estimate instead of being dropped or trusted alone."""
    rng = np.random.default_rng(8)
    n = 4000
    S = _samples(n)
    S.file_index = np.repeat(np.arange(100), n // 100)
    out = rv.noise_floor(S, rng.normal(0.0, 30.0, 3 * n))
    assert abs(out["floor_nT"] / 30.0 - 1) < 0.1, out
    assert out["at_noise"], out
