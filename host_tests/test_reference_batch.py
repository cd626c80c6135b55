"""fit.reference_batch: constant reference fits run side by side (their Gauss-Newton
iterates stacked) against the same fits run one by one (fit.reference.reference_fit).

Tolerance. The stacked iterates do the scalar ones' arithmetic in another order (masks
over the whole eigenbasis instead of the fitted columns, K = 1 sums written out), so the
iterates agree to float64 rounding (~1e-16 relative per operation, times the
conditioning); and a run whose last step lands within rounding of the stopping threshold
may take one iterate more or fewer, which moves chi^2 by < 1e-10 (the stopping rule),
i.e. the coefficients by < 1e-5 of their posterior 1-sigma. So the bound is 1e-5 sigma
per coefficient; a wrong term of the cost, gradient or J^T W J, a wrong mask or a
line search that stops early is off by a sizable fraction of a sigma or more.
"""

from __future__ import annotations


import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.reference import reference_fit
from generator.fit.reference_batch import reference_fits

SIGMAS = 1e-5


def _sigma_diff(got, want):
    """Largest |difference| of b and M over the scalar fit's 1-sigma."""
    (b1, M1, _), (b0, M0, i0) = got, want
    sb, sM = i0["b_poly_sigma_nT"], i0["M_poly_sigma"]
    return max(float(np.max(np.abs(b1 - b0) / sb)), float(np.max(np.abs(M1 - M0) / sM)))


def _problem(rng, n, noise_nT, flat=False):
    """A constant fit: readings of a unit with offset and soft iron over random
    attitudes (or, flat: nearly one attitude, so that directions are held)."""
    M = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = rng.normal(0, 300, 3)
    u = rng.normal(size=(n, 3))
    if flat:        # attitudes within ~1 deg of one direction: most of M is held at the prior
        u = np.array([0.3, -0.5, 0.8]) + 0.01 * u
    B = 50_000 * u / np.linalg.norm(u, axis=1)[:, None]
    x = np.linalg.solve(M, B.T).T + b + rng.normal(0, noise_nT, (n, 3))
    return x, B


@pytest.mark.parametrize("seed", range(4))
def test_random_constant_fits_equal_the_scalar_fits(seed):
    rng = np.random.default_rng(seed)
    calls = []
    for j in range(12):
        n = int(rng.integers(60, 3000))
        noise = float(rng.choice([5.0, 40.0, 250.0]))
        x, B = _problem(rng, n, noise, flat=bool(j % 3 == 0))
        group = None if j % 4 else (np.arange(n) * 3 // n)        # some with three files
        calls.append(((x, B, None), dict(noise_nT=noise if j % 5 else None, group=group,
                                         uncertainty=bool(j % 6 == 0))))
    got = reference_fits(calls)
    for (args, kw), g in zip(calls, got):
        want = reference_fit(*args, **kw)
        assert _sigma_diff(g, want) <= SIGMAS


def test_the_campaign_level_fits_equal_the_scalar_fits(fm1_dir, monkeypatch):
    """The recorded calls of the shared thermal campaign's held-out per-level fits."""
    from generator import pipeline
    from generator.fit import reference_batch

    monkeypatch.setenv("MAGCAL_WORKERS", "1")
    recorded = []

    def record(calls):
        out = reference_fits(calls)
        recorded.extend(zip(calls, out))
        return out

    monkeypatch.setattr(reference_batch, "reference_fits", record)
    pipeline.fit(fm1_dir / "unit.toml", [fm1_dir / "thermal_12pos.csv"])
    assert len(recorded) >= 100          # 4 sensors x 5 folds x 6 levels on this campaign
    worst = 0.0
    for (args, kw), got in recorded:
        worst = max(worst, _sigma_diff(got, reference_fit(*args, **kw)))
    assert worst <= SIGMAS


def test_other_fits_and_errors_go_through_unchanged():
    rng = np.random.default_rng(7)
    x, B = _problem(rng, 400, 40.0)
    T = rng.uniform(-10, 50, 400)
    calls = [((x, B, T, 2), {}),                              # degree 2: run on its own
             ((x[:3], B[:3], None), {"source": "f.csv"}),     # too few samples
             ((x, np.tile(B[:1], (400, 1)), None), {})]       # one reference direction
    got = reference_fits(calls)
    want = reference_fit(*calls[0][0])
    for a, b in zip(got[0][:2], want[:2]):
        assert np.array_equal(a, b)
    for g, (args, kw) in zip(got[1:], calls[1:]):
        assert isinstance(g, InputError)
        with pytest.raises(InputError) as e:
            reference_fit(*args, **kw)
        assert str(g) == str(e.value)


def test_random_problems_hold_directions():
    # the flat problems above exercise the held directions (the start's projection)
    rng = np.random.default_rng(0)
    x, B = _problem(rng, 500, 40.0, flat=True)
    assert reference_fit(x, B, None, noise_nT=40.0)[2]["unobservable"]
