"""Boom alignment H (seed 000 eq. 2-3): Wahba fit, its uncertainty, figures of merit."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.alignment import (SEED_ANGLE_DEG, align_boom, angle_between_deg,
                                     figures_of_merit, fit_H, matrix_from_rotvec,
                                     rotation_error_rad, rotvec_from_matrix, wahba_svd)

FIELD_NT = 50000.0


def _directions(rng, n, cone_deg=None):
    if cone_deg is None:
        u = rng.normal(size=(n, 3))
        return u / np.linalg.norm(u, axis=1, keepdims=True)
    ct = rng.uniform(np.cos(np.radians(cone_deg)), 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct ** 2)
    return np.column_stack([st * np.cos(ph), st * np.sin(ph), ct])


def _pairs(rng, n, H, noise_nT, cone_deg=None):
    """B1 = H B2 + noise; B2 in the boom frame."""
    B1 = FIELD_NT * _directions(rng, n, cone_deg)
    B2 = B1 @ H                      # rows of H^T B1
    return (B1 + rng.normal(0, noise_nT, B1.shape), B2 + rng.normal(0, noise_nT, B1.shape))


def _random_H(rng, max_deg=5.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return matrix_from_rotvec(axis * np.radians(rng.uniform(0.1, max_deg)))


# ---------------------------------------------------------------------------------------
# synthetic pairs
# ---------------------------------------------------------------------------------------
def test_noise_free_pairs_give_H_exactly():
    rng = np.random.default_rng(1)
    H = _random_H(rng)
    B1, B2 = _pairs(rng, 50, H, 0.0)
    r = fit_H(B1, B2)
    assert np.allclose(r.H, H, atol=1e-12)
    assert np.isclose(np.linalg.det(r.H), 1.0)
    assert r.angle_deg == pytest.approx(np.degrees(np.linalg.norm(rotvec_from_matrix(H))))
    assert r.after["angle_max_deg"] < 1e-9


@pytest.mark.parametrize("seed", range(40))
def test_H_recovered_within_stated_sigma(seed):
    rng = np.random.default_rng(100 + seed)
    H = _random_H(rng)
    noise = rng.uniform(10, 300)
    B1, B2 = _pairs(rng, int(rng.integers(30, 400)), H, noise)
    r = fit_H(B1, B2)
    err = rotation_error_rad(r.H, H)
    assert np.all(np.abs(err) < 4.5 * r.sigma_rad), (err, r.sigma_rad)
    # orthogonal, proper
    assert np.allclose(r.H @ r.H.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r.H) > 0


def _monte_carlo(cone_deg, n_trials=300, n=150, noise=40.0):
    H = matrix_from_rotvec(np.radians([1.0, -2.0, 2.5]))
    errs, sig, ang_err, sig_ang = [], [], [], []
    true_angle = np.linalg.norm(rotvec_from_matrix(H))
    for k in range(n_trials):
        rng = np.random.default_rng(7000 + k)
        B1, B2 = _pairs(rng, n, H, noise, cone_deg)
        r = fit_H(B1, B2)
        errs.append(rotation_error_rad(r.H, H))
        sig.append(r.sigma_rad)
        ang_err.append(np.radians(r.angle_deg) - true_angle)
        sig_ang.append(np.radians(r.sigma_angle_deg))
    return (np.array(errs), np.array(sig), np.array(ang_err), np.array(sig_ang))


@pytest.mark.parametrize("cone_deg", [None, 35.0])
def test_sigma_matches_monte_carlo(cone_deg):
    """The stated per-axis sigma (and the angle sigma) agree with the scatter of the
    estimates over many noise draws to ~20 %, for isotropic directions and for directions
    within a cone (where rotation about the cone axis is much less determined)."""
    errs, sig, ang_err, sig_ang = _monte_carlo(cone_deg)
    ratio = errs.std(axis=0) / sig.mean(axis=0)
    assert np.all(np.abs(ratio - 1.0) < 0.2), ratio
    assert abs(ang_err.std() / sig_ang.mean() - 1.0) < 0.2
    # bias well inside the scatter
    assert np.all(np.abs(errs.mean(axis=0)) < 0.25 * errs.std(axis=0))
    if cone_deg is not None:
        # the anisotropy is real and predicted: about z sigma is several times larger
        assert sig.mean(axis=0)[2] > 2.0 * sig.mean(axis=0)[:2].max()


def test_extra_covariance_adds():
    rng = np.random.default_rng(3)
    H = _random_H(rng)
    B1, B2 = _pairs(rng, 200, H, 40.0)
    r0 = fit_H(B1, B2)
    extra = np.diag([1e-8, 4e-8, 9e-8])
    r1 = fit_H(B1, B2, extra_cov_rad2=extra)
    assert np.allclose(r1.H, r0.H)
    assert np.allclose(r1.cov_rad2, r0.cov_stat_rad2 + extra)
    assert np.all(r1.sigma_rad > r0.sigma_rad)


def test_integer_weights_equal_repeated_samples():
    rng = np.random.default_rng(4)
    H = _random_H(rng)
    B1, B2 = _pairs(rng, 60, H, 100.0)
    w = rng.integers(1, 4, size=60).astype(float)
    rw = fit_H(B1, B2, weights=w)
    rr = fit_H(np.repeat(B1, w.astype(int), axis=0), np.repeat(B2, w.astype(int), axis=0))
    assert np.allclose(rw.H, rr.H, atol=1e-12)


def test_wahba_handles_reflection_case():
    """det(U V^T) < 0 would give a reflection without the diag(1, 1, d) correction."""
    rng = np.random.default_rng(5)
    B2 = FIELD_NT * _directions(rng, 5)
    B1 = -B2 + rng.normal(0, 10000, B2.shape)       # roughly a point reflection
    H = wahba_svd(B1, B2)
    assert np.linalg.det(H) == pytest.approx(1.0)


def test_figures_before_and_after():
    rng = np.random.default_rng(6)
    H = matrix_from_rotvec(np.radians([0.0, 0.0, 2.0]))
    B1, B2 = _pairs(rng, 500, H, 20.0)
    r = fit_H(B1, B2)
    b, a = r.before, r.after
    assert a["angle_mean_deg"] < b["angle_mean_deg"] / 10
    assert a["angle_max_deg"] < b["angle_max_deg"]
    for i in (0, 1):      # a rotation about z moves the x and y projections ...
        assert a["proj_diff_mean_pct"][i] < b["proj_diff_mean_pct"][i] / 10
        assert a["proj_diff_max_pct"][i] < b["proj_diff_max_pct"][i]
    # ... but not z: there before and after are both the noise
    assert b["proj_diff_mean_pct"][2] < 0.1 * b["proj_diff_mean_pct"][0]
    assert a["proj_diff_mean_pct"][2] == pytest.approx(b["proj_diff_mean_pct"][2], rel=0.2)
    # after: the mean angle is the noise floor the result states, to ~10 %
    assert a["angle_mean_deg"] == pytest.approx(r.noise_floor_angle_mean_deg, rel=0.1)
    table = r.table()
    assert "0.5" in table and str(SEED_ANGLE_DEG) in table


def test_angle_between_small_angles_accurate():
    a = np.array([[1.0, 0.0, 0.0]])
    b = np.array([[1.0, 1e-9, 0.0]])
    assert angle_between_deg(a, b)[0] == pytest.approx(np.degrees(1e-9), rel=1e-6)
    f = figures_of_merit(a * FIELD_NT, b * FIELD_NT)
    assert f["proj_diff_max_pct"][1] == pytest.approx(1e-7, rel=1e-6)


# ---------------------------------------------------------------------------------------
# degenerate input
# ---------------------------------------------------------------------------------------
def test_too_few_samples():
    with pytest.raises(InputError, match="at least"):
        fit_H(np.array([[1.0, 0, 0], [0, 1.0, 0]]) * FIELD_NT,
              np.array([[1.0, 0, 0], [0, 1.0, 0]]) * FIELD_NT)


def test_parallel_vectors_rotation_undetermined():
    rng = np.random.default_rng(8)
    d = np.array([0.3, -0.5, 0.8])
    d /= np.linalg.norm(d)
    B = FIELD_NT * d + rng.normal(0, 40.0, (500, 3))    # 0.05 deg scatter only
    with pytest.raises(InputError, match="undetermined") as e:
        fit_H(B, B)
    assert "direction" in str(e.value)


def test_non_finite_rejected():
    rng = np.random.default_rng(9)
    B1, B2 = _pairs(rng, 20, np.eye(3), 10.0)
    B2[7, 1] = np.nan
    with pytest.raises(InputError, match="non-finite.*index 7"):
        fit_H(B1, B2)
    B1[3, 0] = np.inf
    with pytest.raises(InputError, match="non-finite"):
        fit_H(B1, B2)


def test_shape_zero_vector_and_weights_rejected():
    rng = np.random.default_rng(10)
    B1, B2 = _pairs(rng, 20, np.eye(3), 10.0)
    with pytest.raises(InputError, match="shape"):
        fit_H(B1[:, :2], B2[:, :2])
    with pytest.raises(InputError, match="same samples"):
        fit_H(B1, B2[:-1])
    Bz = B1.copy()
    Bz[4] = 0.0
    with pytest.raises(InputError, match="zero vector"):
        fit_H(Bz, B2)
    with pytest.raises(InputError, match="weights"):
        fit_H(B1, B2, weights=-np.ones(20))
    with pytest.raises(InputError, match="weights"):
        fit_H(B1, B2, weights=np.ones(5))


# ---------------------------------------------------------------------------------------
# shared example unit: rotation.csv (boom deployed) with calibrations fitted on the jig
# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _fitted(fm1_dir):
    from generator.fit import thermal as fit_thermal
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    unit = load_unit(fm1_dir / "unit.toml")
    cals = fit_thermal.fit_unit(unit, [read_telemetry(fm1_dir / "thermal_12pos.csv", unit)])
    rot = read_telemetry(fm1_dir / "rotation.csv", unit)
    return unit, cals, rot


@pytest.fixture(scope="module")
def shared(fm1_dir):
    from generator.io.truth import load_truth
    unit, cals, rot = _fitted(fm1_dir)
    return unit, cals, rot, load_truth(fm1_dir / "truth.json")


def test_shared_H_matches_truth_within_3_sigma(shared):
    unit, cals, rot, truth = shared
    ba = align_boom(unit, rot, cals)
    assert ba.reference == "mmc1" and ba.fit_sensor == "mmc2"
    H_true = truth["H_boom_to_body"]
    err = rotation_error_rad(ba.H, H_true)
    sig = ba.result.sigma_rad
    assert np.all(np.abs(err) < 3 * sig), (np.degrees(err), np.degrees(sig))
    # the angle itself
    true_angle = np.degrees(np.linalg.norm(rotvec_from_matrix(H_true)))
    assert abs(ba.result.angle_deg - true_angle) < 3 * ba.result.sigma_angle_deg
    # sigma honest but not vacuous: far below the boom tilt itself
    assert ba.result.sigma_angle_deg < 0.01 * true_angle


def test_shared_figures_better_after(shared):
    unit, cals, rot, _ = shared
    ba = align_boom(unit, rot, cals)
    for key, p in ba.pairs.items():
        b, a = p["before"], p["after"]
        assert a["angle_mean_deg"] < b["angle_mean_deg"], key
        assert a["angle_max_deg"] < b["angle_max_deg"], key
        for i in range(3):
            assert a["proj_diff_mean_pct"][i] < b["proj_diff_mean_pct"][i], (key, i)
    # the fitted pair meets the seed's figures on average (noise alone sets the max)
    a = ba.result.after
    assert a["angle_mean_deg"] < SEED_ANGLE_DEG
    assert max(a["proj_diff_mean_pct"]) < 0.5
    assert "mpu1/mpu3" in ba.pairs and "mmc1/mpu3" in ba.pairs


def test_shared_mpu_pair_agrees_with_truth(shared):
    """The MPU pair, fitted alone, gives the same board rotation (within its sigma)."""
    unit, cals, rot, truth = shared
    ba = align_boom(unit, rot, cals)
    r = ba.cross_checks["mpu1/mpu3"]
    err = rotation_error_rad(r.H, truth["H_boom_to_body"])
    assert np.all(np.abs(err) < 3 * r.sigma_rad), (np.degrees(err), r.sigma_deg)
    assert r.sigma_angle_deg > ba.result.sigma_angle_deg     # noisier sensors


def test_align_boom_errors(shared):
    unit, cals, rot, _ = shared
    with pytest.raises(InputError, match="not a boom sensor"):
        align_boom(unit, rot, cals, fit_sensor="mpu1")
    partial = {k: v for k, v in cals.items() if k != "mmc2"}
    with pytest.raises(InputError, match="no calibration for mmc2"):
        align_boom(unit, rot, partial)
