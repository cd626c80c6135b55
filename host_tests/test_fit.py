"""Fits on synthetic data with known parameters: ellipsoid, reference-vector fit, segment
finder, the per-sensor temperature fit, and the truth helpers."""

from __future__ import annotations

import json

import numpy as np

from generator.fit.bounds import normalised_residuals
import pytest

from generator.errors import InputError
from generator.fit.ellipsoid import (algebraic_ellipsoid, ellipsoid_fit, polar_spd,
                                     sym_from6, sym_to6)
from generator.fit.thermal import (FitData, find_segments, fit_sensor, group_levels,
                                   reference_fit, temperature_quantum)
from generator.io.truth import (rms_norm_error, true_calibrated_frame, true_frame_field)

R_LAB_NT = 51540.0
B_LAB_NT = np.array([18447.6, 3652.7, 47986.6])
B_LAB_NT *= R_LAB_NT / np.linalg.norm(B_LAB_NT)  # the jig's field vector, |B| = 51540 exactly


# ---------------------------------------------------------------------------------------
# synthetic sensors
# ---------------------------------------------------------------------------------------
def random_sensor(rng, soft=0.05, offset_nT=3000.0):
    W = np.eye(3) + rng.normal(0, soft, (3, 3))
    b = rng.normal(0, offset_nT, 3)
    return W, b


def sphere_directions(rng, n):
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1)[:, None]


def random_rotations(rng, n):
    out = []
    for _ in range(n):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        out.append(np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]))
    return np.array(out)


def twelve_positions(rng):
    """Field in the body frame at twelve static positions (each body axis up and down at
    two headings), as the ground jig gives."""
    up = np.array([0.0, 0.0, 1.0])
    out = []
    for axis in np.eye(3):
        for sign in (1, -1):
            for heading in (0.0, np.pi / 2):
                # a rotation taking body axis `sign*axis` to the vertical, then a heading turn
                a = sign * axis
                v = np.cross(a, up)
                c = float(a @ up)
                if np.linalg.norm(v) < 1e-12:
                    R0 = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
                else:
                    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
                    R0 = np.eye(3) + vx + vx @ vx / (1 + c)
                ch, sh = np.cos(heading), np.sin(heading)
                Rh = np.array([[ch, -sh, 0], [sh, ch, 0], [0, 0, 1]])
                R = Rh @ R0                           # body -> lab
                out.append(R.T @ B_LAB_NT)            # field seen in the body frame
    return np.array(out)


# ---------------------------------------------------------------------------------------
# ellipsoid fit
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(20))
def test_ellipsoid_noise_free_recovers_b_and_M(seed):
    rng = np.random.default_rng(seed)
    W, b = random_sensor(rng)
    R = R_LAB_NT * rng.uniform(0.4, 1.2)
    B = R * sphere_directions(rng, 400)
    m = B @ W.T + b
    bf, Mf, info = ellipsoid_fit(m, R)
    M_true = np.linalg.inv(W)
    assert np.max(np.abs(bf - b)) < 1e-9 * R
    # M is known up to a rotation: the symmetric fit equals the polar factor of W^-1
    assert np.allclose(Mf, Mf.T, atol=0)
    assert np.max(np.abs(Mf.T @ Mf - M_true.T @ M_true)) < 1e-9
    assert np.max(np.abs(Mf - polar_spd(M_true))) < 1e-9
    # both stages are reported, the algebraic one is exact on exact data too
    assert np.max(np.abs(info["algebraic"]["b_nT"] - b)) < 1e-6 * R
    assert info["geometric"]["rms_nT"] < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_ellipsoid_twelve_positions_noise_free(seed):
    rng = np.random.default_rng(100 + seed)
    W, b = random_sensor(rng)
    B = np.repeat(twelve_positions(rng), 50, axis=0)
    bf, Mf, _ = ellipsoid_fit(B @ W.T + b, R_LAB_NT)
    assert np.max(np.abs(bf - b)) < 1e-9 * R_LAB_NT
    assert np.max(np.abs(Mf - polar_spd(np.linalg.inv(W)))) < 1e-9


def test_ellipsoid_noisy_errors_match_reported_sigma():
    """Across many seeds the errors, in units of the reported 1-sigma, are ~N(0, 1)."""
    z_b, z_M, better = [], [], []
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        W, b = random_sensor(rng)
        B = R_LAB_NT * sphere_directions(rng, 1500)
        sigma = 250.0
        m = B @ W.T + b + rng.normal(0, sigma, B.shape)
        bf, Mf, info = ellipsoid_fit(m, R_LAB_NT)
        z_b.extend((bf - b) / info["b_sigma_nT"])
        P = polar_spd(np.linalg.inv(W))
        z_M.extend(((sym_to6(Mf) - sym_to6(P)) / sym_to6(info["M_sigma"])))
        # residual sigma is the noise level; the refinement never worsens the fit
        assert abs(info["residual_sigma_nT"] - sigma) < 0.1 * sigma
        # ... on the cost it minimises: the noise-normalised residuals
        def cost(bb, MM):
            return float(np.sum(normalised_residuals(bb, MM, m, R_LAB_NT) ** 2))
        a = info["algebraic"]
        better.append(cost(bf, Mf) <= cost(a["b_nT"], a["M"]) * (1 + 1e-12))
    z_b, z_M = np.array(z_b), np.array(z_M)
    assert np.max(np.abs(z_b)) < 5 and np.max(np.abs(z_M)) < 5
    assert 0.6 < np.mean(z_b ** 2) < 1.6
    assert 0.6 < np.mean(z_M ** 2) < 1.6
    assert all(better)


def test_ellipsoid_per_sample_reference_norm():
    """Orbit-like data: |B| changes along the track; the fit uses it sample by sample."""
    rng = np.random.default_rng(7)
    W, b = random_sensor(rng)
    R = rng.uniform(22000, 50000, 600)
    B = R[:, None] * sphere_directions(rng, 600)
    bf, Mf, info = ellipsoid_fit(B @ W.T + b, R)
    assert np.max(np.abs(bf - b)) < 1e-6
    assert np.max(np.abs(Mf - polar_spd(np.linalg.inv(W)))) < 1e-10
    assert info["algebraic"]["method"] == "linear-rhs"


def test_sym_helpers_roundtrip():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    A = A + A.T
    assert np.array_equal(sym_from6(sym_to6(A)), A)


# ---- degenerate geometry and bad input -------------------------------------------------
def _sensor_readings(B, seed=3):
    W, b = random_sensor(np.random.default_rng(seed))
    return B @ W.T + b


def test_ellipsoid_too_few_samples():
    rng = np.random.default_rng(1)
    m = _sensor_readings(R_LAB_NT * sphere_directions(rng, 8))
    with pytest.raises(InputError, match="at least 9"):
        ellipsoid_fit(m, R_LAB_NT)


def test_ellipsoid_too_few_orientations():
    rng = np.random.default_rng(1)
    m = np.repeat(_sensor_readings(R_LAB_NT * sphere_directions(rng, 6)), 100, axis=0)
    with pytest.raises(InputError, match="distinct readings"):
        ellipsoid_fit(m, R_LAB_NT)


@pytest.mark.parametrize("noise_nT", [0.0, 40.0])
def test_ellipsoid_rotation_about_one_axis_only(noise_nT):
    """Turning about one axis only puts the readings on a circle: not enough."""
    rng = np.random.default_rng(2)
    phi = rng.uniform(0, 2 * np.pi, 500)
    B = R_LAB_NT * np.stack([np.cos(phi) * 0.8, np.sin(phi) * 0.8, np.full_like(phi, 0.6)], 1)
    m = _sensor_readings(B) + rng.normal(0, noise_nT, B.shape)
    with pytest.raises(InputError, match="sphere|quadric|ellipsoid"):
        ellipsoid_fit(m, R_LAB_NT)


def test_ellipsoid_small_cap_is_undetermined():
    """Directions within 15 degrees of one axis, mpu-like noise: offset undetermined."""
    rng = np.random.default_rng(4)
    u = sphere_directions(rng, 3000)
    u = u[u[:, 2] > np.cos(np.radians(15))]
    m = _sensor_readings(R_LAB_NT * u) + rng.normal(0, 250.0, u.shape)
    with pytest.raises(InputError, match="cover too little of the sphere|quadric|ellipsoid"):
        ellipsoid_fit(m, R_LAB_NT)


def test_ellipsoid_hemisphere_is_fine():
    rng = np.random.default_rng(5)
    u = sphere_directions(rng, 3000)
    u = u[u[:, 2] > 0]
    W, b = random_sensor(rng)
    bf, Mf, info = ellipsoid_fit((R_LAB_NT * u) @ W.T + b + rng.normal(0, 40, u.shape),
                                 R_LAB_NT)
    assert np.all(np.abs(bf - b) < 5 * info["b_sigma_nT"])


def test_ellipsoid_non_finite_and_bad_shapes():
    rng = np.random.default_rng(6)
    m = _sensor_readings(R_LAB_NT * sphere_directions(rng, 50))
    m[3, 1] = np.nan
    with pytest.raises(InputError, match="not finite"):
        ellipsoid_fit(m, R_LAB_NT)
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        ellipsoid_fit(np.zeros((20, 2)), R_LAB_NT)
    with pytest.raises(InputError, match="positive"):
        ellipsoid_fit(_sensor_readings(R_LAB_NT * sphere_directions(rng, 50)), -1.0)


def test_ellipsoid_not_an_ellipsoid():
    """Readings on a hyperboloid (no field of constant magnitude gives that)."""
    rng = np.random.default_rng(8)
    t = rng.uniform(-1.5, 1.5, 800)
    phi = rng.uniform(0, 2 * np.pi, 800)
    x = 30000 * np.stack([np.cosh(t) * np.cos(phi), np.cosh(t) * np.sin(phi), np.sinh(t)], 1)
    with pytest.raises(InputError, match="not an ellipsoid|sphere|positive definite"):
        ellipsoid_fit(x, R_LAB_NT)


def test_algebraic_stage_alone():
    rng = np.random.default_rng(9)
    W, b = random_sensor(rng)
    bf, Mf, det = algebraic_ellipsoid((R_LAB_NT * sphere_directions(rng, 100)) @ W.T + b,
                                      R_LAB_NT)
    assert det["method"] == "li-griffiths"
    assert np.max(np.abs(bf - b)) < 1e-6


# ---------------------------------------------------------------------------------------
# reference-vector fit
# ---------------------------------------------------------------------------------------
def thermal_sensor(rng, soft=0.03):
    """W(T) quadratic and b(T) cubic in dT = T - 25, of the size real parts show."""
    W = np.zeros((3, 3, 3))
    W[0] = np.eye(3) + rng.normal(0, soft, (3, 3))
    W[1] = rng.normal(0, 1e-4, (3, 3)) + np.diag(rng.normal(0, 2e-4, 3))
    W[2] = np.diag(rng.normal(0, 2e-6, 3))
    b = np.zeros((4, 3))
    b[0] = rng.normal(0, 3000, 3)
    b[1] = rng.normal(0, 1.0, 3)
    b[2] = rng.normal(0, 0.02, 3)
    b[3] = rng.normal(0, 3e-4, 3)
    return W, b


def poly(c, dT):
    d = dT.reshape((-1,) + (1,) * (c.ndim - 1))
    return sum(c[k] * d ** k for k in range(c.shape[0]))


def measure(W, b, B, T):
    dT = T - 25.0
    return np.einsum("nij,nj->ni", poly(W, dT), B) + poly(b, dT)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("size", ["small", "realistic"])
def test_reference_fit_noise_free(seed, size):
    """M(T) = W(T)^-1 is not a polynomial: its cubic carries a truncation error
    ~(|W2| dT^2)^2 + (|W1| dT)^4: ~1e-6 for parts like the real ones (0.05 nT on 51540 nT),
    below 1e-9 for a weak temperature dependence. The fit minimises the calibrated residual
    in the flight parametrisation, so that truncation is shared between M and b: b(T) is
    recovered to the same level (tol x |B|), exactly (1e-9 relative) when M(T) is nearly
    polynomial."""
    rng = np.random.default_rng(200 + seed)
    W, b = thermal_sensor(rng)
    if size == "small":
        W[1] *= 0.3
        W[2] = 0.0
    B = np.tile(twelve_positions(rng), (60, 1))
    T = rng.uniform(-20, 55, len(B))
    m = measure(W, b, B, T)
    bp, Mp, info = reference_fit(m, B, T, 3)
    tol = 1e-9 if size == "small" else 1e-5
    if size == "small":
        assert np.max(np.abs(bp - b)) / np.abs(b).max() < 1e-9
    else:
        assert np.max(np.abs(bp - b)) < tol * R_LAB_NT
    assert not info["unobservable"]               # noise-free: every parameter from data
    Tg = np.linspace(T.min(), T.max(), 50)
    M_true = np.linalg.inv(poly(W, Tg - 25))
    M_fit = poly(Mp, Tg - 25)
    assert np.max(np.abs(M_fit - M_true)) < tol
    # full matrix to the body frame, not symmetric
    assert np.max(np.abs(Mp[0] - Mp[0].T)) > 1e-3
    # calibrated field equals the reference
    z = np.einsum("nij,nj->ni", poly(Mp, T - 25), m - poly(b, T - 25))
    assert np.max(np.abs(z - B)) < tol * R_LAB_NT


def test_reference_fit_constant_and_noise_sigma():
    z_b = []
    for seed in range(30):
        rng = np.random.default_rng(300 + seed)
        W, b = random_sensor(rng)
        B = np.tile(twelve_positions(rng), (40, 1))
        m = B @ W.T + b + rng.normal(0, 40.0, B.shape)
        bp, Mp, info = reference_fit(m, B)
        assert bp.shape == (1, 3) and Mp.shape == (1, 3, 3)
        z_b.extend((bp[0] - b) / info["b_poly_sigma_nT"][0])
        zM = (Mp[0] - np.linalg.inv(W)) / info["M_poly_sigma"][0]
        assert np.max(np.abs(zM)) < 5
    z_b = np.array(z_b)
    assert np.max(np.abs(z_b)) < 5 and 0.6 < np.mean(z_b ** 2) < 1.6


def test_reference_fit_degenerate():
    rng = np.random.default_rng(11)
    W, b = random_sensor(rng)
    B = np.tile(twelve_positions(rng)[:3], (30, 1))        # three directions only
    with pytest.raises(InputError, match="distinct values"):
        reference_fit(B @ W.T + b, B)
    B = np.tile(twelve_positions(rng), (30, 1))
    T = np.full(len(B), 20.0)                               # one temperature, cubic asked
    T[0] = 20.5                                             # (a span, but hardly any)
    m = B @ W.T + b + rng.normal(0, 40.0, B.shape)
    bp, Mp, info = reference_fit(m, B, T, 3)
    # the temperature terms are not determined: held at the prior (0), reported as such;
    # the constant terms come from the data
    src = {p["name"]: p["source"] for p in info["parameters"]}
    assert all(v == "prior" for k, v in src.items() if k[1] in "23")
    assert all(v == "data" for k, v in src.items() if k[1] == "0")
    assert info["unobservable"]
    # held at the prior: no offset along the unobservable directions, and a coefficient
    # mostly in them stays within a small part of its prior sigma of the prior's value
    assert all(abs(u["offset_from_prior"]) < 1e-6 for u in info["unobservable"])
    assert all(abs(p["value"] - p["prior"]) < 0.1 * p["prior_sigma"]
               for p in info["parameters"] if p["source"] == "prior")
    assert np.max(np.abs(bp[0] - b - 5 * bp[1])) < 5 * 40.0   # b at 20 degC within noise
    with pytest.raises(InputError, match="non-finite"):
        Bn = B.copy()
        Bn[0, 0] = np.nan
        reference_fit(B @ W.T + b, Bn)


# ---------------------------------------------------------------------------------------
# constant-temperature segments
# ---------------------------------------------------------------------------------------
LEVELS_C = (-20.0, -5.0, 10.0, 25.0, 40.0, 55.0)


def chamber_profile(n_pos=3, dt_s=5.0, hold_s=1800.0, rate_C_per_s=1.0 / 60, tau_s=300.0,
                    board_offset_C=0.8):
    """Chamber steps with holds per position; the board follows with a first-order lag.
    Returns time, board temperature, position, and the hold intervals (pos, t0, t1, level)."""
    t, chamber, pos, holds = [], [], [], []
    now, temp = 0.0, 25.0
    for p in range(1, n_pos + 1):
        for target, hold in [(lev, True) for lev in LEVELS_C] + [(25.0, False)]:
            while abs(temp - target) > 1e-9:        # ramp
                temp += np.clip(target - temp, -rate_C_per_s * dt_s, rate_C_per_s * dt_s)
                t.append(now), chamber.append(temp), pos.append(p)
                now += dt_s
            if hold:
                t0 = now
                for _ in range(int(hold_s / dt_s)):
                    t.append(now), chamber.append(temp), pos.append(p)
                    now += dt_s
                holds.append((p, t0, now, target))
    t, chamber, pos = np.array(t), np.array(chamber), np.array(pos)
    board = np.empty_like(chamber)
    board[0] = 25.0
    a = dt_s / tau_s
    for i in range(1, len(t)):
        board[i] = board[i - 1] + a * (chamber[i] + board_offset_C - board[i - 1])
    return t, board, pos, holds


def _check_one_segment_per_hold(segs, holds, lag_s=1500.0):
    assert len(segs) == len(holds)
    for s, (p, t0, t1, level) in zip(segs, holds):
        assert s.position == p
        assert t0 <= s.t_start_s and s.t_stop_s <= t1 + lag_s
        assert s.duration_s >= 600.0
        assert abs(s.temp_C - level) < 1.5


def test_segments_with_lag_and_mmc_quantisation():
    t, board, pos, holds = chamber_profile()
    reported = np.round(board / 0.7) * 0.7                  # MMC5883-like 0.7 degC steps
    assert abs(temperature_quantum(reported) - 0.7) < 1e-9
    segs = find_segments(t, reported, pos)
    _check_one_segment_per_hold(segs, holds)
    levels = group_levels(segs, 5.0)
    assert len(levels) == len(LEVELS_C)
    assert all(len(lev) == 3 for lev in levels)


def test_segments_fine_resolution_and_no_position_column():
    t, board, pos, holds = chamber_profile(n_pos=1)
    rng = np.random.default_rng(1)
    reported = np.round((board + rng.normal(0, 0.003, len(t))) / 0.01) * 0.01
    segs = find_segments(t, reported)            # no position column: one run
    _check_one_segment_per_hold(segs, holds)


def test_segments_not_split_by_noise_and_spikes():
    t, board, pos, holds = chamber_profile(n_pos=2)
    rng = np.random.default_rng(2)
    reported = board + rng.normal(0, 0.08, len(t))
    spikes = rng.choice(len(t), 40, replace=False)
    reported[spikes] += rng.choice([-4.0, 4.0], 40)
    segs = find_segments(t, reported, pos)
    _check_one_segment_per_hold(segs, holds)


def test_segments_none_in_a_slow_ramp_and_moving_samples():
    t = np.arange(0, 20000, 5.0)
    ramp = -20 + t * (75 / 20000)                   # 0.225 degC/min, never settles
    assert find_segments(t, ramp) == []
    # position 0 (moving) is never a segment, however quiet the temperature
    assert find_segments(t, np.full_like(t, 24.0), np.zeros_like(t)) == []


def test_segment_drift_is_cut_not_merged():
    """A slow drift over hours is not one 'constant' segment spanning many degrees."""
    t = np.arange(0, 30000, 5.0)
    T = 20 + 6 * (t / t[-1])                        # 6 degC over 8 h: each 10 min quiet
    segs = find_segments(t, T, band_C=0.5)
    assert segs and all(s.temp_range_C <= 1.0 + 1e-9 for s in segs)


# ---------------------------------------------------------------------------------------
# temperature calibration of one sensor
# ---------------------------------------------------------------------------------------
def thermal_campaign(rng, W, b, noise_nT=0.0, quantum_C=0.01, n_pos=12):
    t, board, pos, _ = chamber_profile(n_pos=n_pos, hold_s=1800.0)
    dirs = twelve_positions(rng)
    B = dirs[(pos - 1) % 12]
    m = measure(W, b, B, board) + rng.normal(0, noise_nT, B.shape) if noise_nT else \
        measure(W, b, B, board)
    reported = np.round(board / quantum_C) * quantum_C
    return t, pos, B, m, reported


def _fitdata(t, pos, B, m, T, vectors=True, coil=None):
    n = len(t)
    return FitData(source="synthetic.csv", time_s=t, field_frame_nT=m, temp_C=T,
                   usable=np.ones(n, bool), position=pos.astype(float),
                   ref_body_nT=B if vectors else None,
                   ref_norm_nT=np.linalg.norm(B, axis=1), coil_A=coil,
                   reference_kind="synthetic")


def test_fit_sensor_reference_vectors_noise_free():
    rng = np.random.default_rng(21)
    W, b = thermal_sensor(rng)
    t, pos, B, m, T = thermal_campaign(rng, W, b, quantum_C=1e-9)
    cal = fit_sensor("s1", [_fitdata(t, pos, B, m, T)])
    assert cal.body_frame
    assert cal.t_min_C == pytest.approx(T.min()) and cal.t_max_C == pytest.approx(T.max())
    assert np.max(np.abs(cal.b_poly_nT - b)) / np.abs(b).max() < 1e-8
    Tg = np.linspace(T.min(), T.max(), 40)
    # cubic truncation of W(T)^-1 (see test_reference_fit_noise_free)
    assert np.max(np.abs(cal.M_at(Tg) - np.linalg.inv(poly(W, Tg - 25)))) < 1e-5
    st = cal.stats
    json.dumps(st)                                  # JSON-able
    assert st["chosen"] in ("joint", "segments")
    assert len(st["segments"]["levels"]) == len(LEVELS_C)
    assert {"joint", "segments"} <= set(st["holdout"])
    # beyond the calibrated range the temperature is clamped
    assert np.array_equal(cal.b_at(T.max() + 30), cal.b_at(T.max()))


def test_fit_sensor_noisy_picks_the_better_method_and_reports_sigma():
    rng = np.random.default_rng(22)
    W, b = thermal_sensor(rng)
    t, pos, B, m, T = thermal_campaign(rng, W, b, noise_nT=40.0, quantum_C=0.7)
    cal = fit_sensor("s1", [_fitdata(t, pos, B, m, T)])
    st = cal.stats
    h = st["holdout"]
    best = min(("joint", "segments"), key=lambda k: h[k]["rms_vector_nT"])
    assert st["chosen"] == best
    # calibrated |B| error close to the noise floor of an exact calibration
    z = cal.apply64(m, T)
    exact = np.einsum("nij,nj->ni", np.linalg.inv(poly(W, T - 25)), m - poly(b, T - 25))
    assert rms_norm_error(z, B) < 1.05 * rms_norm_error(exact, B)
    # b(T) within a few reported sigma at the reference temperature
    assert np.all(np.abs(cal.b_poly_nT[0] - b[0]) < 5 * cal.b_poly_sigma_nT[0])
    assert cal.M_poly_sigma.shape == cal.M_poly.shape


def test_fit_sensor_magnitude_only_gives_symmetric_M():
    rng = np.random.default_rng(23)
    W, b = thermal_sensor(rng)
    t, pos, B, m, T = thermal_campaign(rng, W, b, noise_nT=40.0, quantum_C=0.01)
    cal = fit_sensor("s1", [_fitdata(t, pos, B, m, T, vectors=False)])
    assert not cal.body_frame
    for k in range(cal.M_poly.shape[0]):
        assert np.allclose(cal.M_poly[k], cal.M_poly[k].T)
    z = cal.apply64(m, T)
    exact = np.einsum("nij,nj->ni", np.linalg.inv(poly(W, T - 25)), m - poly(b, T - 25))
    assert rms_norm_error(z, B) < 1.05 * rms_norm_error(exact, B)


def test_fit_sensor_single_temperature_is_constant_ellipsoid():
    rng = np.random.default_rng(24)
    W, b = random_sensor(rng)
    n = 3000
    B = R_LAB_NT * sphere_directions(rng, n)
    m = B @ W.T + b + rng.normal(0, 40.0, B.shape)
    t = np.arange(n) * 0.1
    d = FitData("rot.csv", t, m, np.full(n, 23.7), np.ones(n, bool),
                ref_norm_nT=np.full(n, R_LAB_NT))
    cal = fit_sensor("s1", [d])
    assert cal.stats["chosen"] == "constant" and not cal.body_frame
    assert np.all(cal.b_poly_nT[1:] == 0) and np.all(cal.M_poly[1:] == 0)
    assert np.all(np.abs(cal.b_poly_nT[0] - b) < 5 * cal.b_poly_sigma_nT[0])


def test_fit_sensor_coil_samples_excluded_and_counted():
    rng = np.random.default_rng(25)
    W, b = thermal_sensor(rng)
    t, pos, B, m, T = thermal_campaign(rng, W, b, noise_nT=40.0, n_pos=12)
    coil = np.zeros((len(t), 3))
    on = np.arange(len(t)) % 7 == 3
    coil[on, 1] = 0.05
    m_coil = m.copy()
    m_coil[on] += 3000.0                             # a coil field the model does not have
    cal = fit_sensor("s1", [_fitdata(t, pos, B, m_coil, T, coil=coil)])
    assert cal.stats["files"][0]["coil_current_excluded"] == int(on.sum())
    assert any("coil current" in n for n in cal.stats["notes"])
    assert cal.stats["samples_used"] == len(t) - int(on.sum())
    z = cal.apply64(m[~on], T[~on])
    assert rms_norm_error(z, B[~on]) < 45.0


def test_fit_sensor_without_reference_raises():
    n = 100
    d = FitData("x.csv", np.arange(n, dtype=float), np.ones((n, 3)), np.full(n, 20.0),
                np.ones(n, bool))
    with pytest.raises(InputError, match="no usable sample"):
        fit_sensor("s1", [d])


# ---------------------------------------------------------------------------------------
# truth helpers
# ---------------------------------------------------------------------------------------
def test_truth_calibrated_frame_inverts_the_truth_model():
    rng = np.random.default_rng(31)
    W, b = thermal_sensor(rng)
    K = rng.normal(0, 3000, (3, 3))
    truth = {"t_ref_C": 25.0, "H_boom_to_body": random_rotations(rng, 1)[0],
             "sensors": {"s": {"W_poly": W, "b_poly_nT": b, "K_nT_per_A": K,
                               "chip_offset_poly_sensor_nT": None}}}
    B = R_LAB_NT * sphere_directions(rng, 200)
    T = rng.uniform(-20, 55, 200)
    i = rng.normal(0, 0.05, (200, 3))
    m = measure(W, b, B, T) + i @ K.T
    assert np.max(np.abs(true_calibrated_frame(truth, "s", m, T, i) - B)) < 1e-8
    assert rms_norm_error(B * 1.001, B) == pytest.approx(0.001 * R_LAB_NT)
    H = truth["H_boom_to_body"]
    assert np.allclose(true_frame_field(truth, "boom", B, True), B @ H)
    assert np.array_equal(true_frame_field(truth, "boom", B, False), B)
    assert np.array_equal(true_frame_field(truth, "body", B, True), B)
