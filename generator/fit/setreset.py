"""MMC5883 SET/RESET self-calibration while the satellite turns (seed 000, eq. 4).

The sensor reads once after a SET pulse and once after a RESET pulse, which flips the sign
of its sensitivity but not its bridge offset o:

    SET:    out1 =  B  + o
    RESET:  out2 = -B' + o          (taken t_delay later)
    offset = (out1 + out2) / 2 = o + (B - B') / 2
    field  = (out1 - out2) / 2 = (B + B') / 2

t_delay = 1 ms settling + the measurement time t_TM (10, 5, 2.5 or 1.6 ms). While the body
turns at rate w (body axes) the field it sees, fixed in inertial space, moves as
dB/dt = -w x B, so B' = R B with R = exp(-[w]x t_delay): the offset picks up the error
(B - B')/2. The field (mean of the two) is the field at mid-interval; the offset error
matters because the stored offset is used for the readings that come without a pair
(`StoredOffset`), where it goes one-to-one into the field.

* The seed's case: plane rotation with the field along the measuring axis: the axis
  projection goes B -> B cos(phi), phi = w t_delay, offset error B (1 - cos phi)/2:
  second order, below 0.001 % of B at 10 deg/s.
* In general the projection on an axis at angle theta from the field changes to first
  order: B (cos(theta) - cos(theta - phi)) / 2 ~ B sin(theta) phi / 2 for a rotation in the
  plane of field and axis. Over every geometry the worst axis error is B sin(phi/2).
  `offset_error_maps` computes it exactly (Rodrigues rotation of the field vector) over
  rate x t_TM x theta (x tilt of the rotation axis out of that plane's normal).
* Compensation with the gyro: with the measured rate, R_m = exp(-[w_m]x t_delay), the
  pair gives B exactly: out1 - out2 = (I + R) B, so B = (I + R_m)^-1 (out1 - out2) and
  o = out1 - B ("exact"); or to first order o = (out1 + out2)/2 - (w_m x B^) t_delay / 2
  with B^ = (out1 - out2)/2 ("first_order"). What is left comes from the gyro error:
  about |B| |dw| t_delay / 2. `compensation_gain` measures it by Monte Carlo.

On telemetry (`chip_offset_compensated`), the raw reading is W B + b (+ the bridge offset),
so the prediction uses the calibrated field and W = M^-1, in the sensor's frame axes, and
the gyro rate (body axes; rotated by H^T for boom sensors).
"""

from __future__ import annotations

import os

import numpy as np

from generator.errors import InputError

T_SETTLE_MS = 1.0
T_TM_MS = (10.0, 5.0, 2.5, 1.6)
SEED_OFFSET_ERROR_BOUND_PCT = 0.001      # seed 000: effect on the offset below 0.001 %
DEFAULT_FIELD_NT = 51540.0               # lab field of the shared example unit


# =======================================================================================
# (a) The formulas, float64
# =======================================================================================
def offset_and_field(set_nT, reset_nT):
    """(field, offset) = ((out1 - out2)/2, (out1 + out2)/2), any matching shapes (nT)."""
    s = np.asarray(set_nT, float)
    r = np.asarray(reset_nT, float)
    return 0.5 * (s - r), 0.5 * (s + r)


def offset_and_field_from_counts(set_counts, reset_counts, lsb_nT, zero_count):
    """As offset_and_field from raw counts: field = (set - reset)/2 lsb,
    offset = ((set + reset)/2 - zero) lsb (the chain's formulas, in float64)."""
    s = np.asarray(set_counts, float)
    r = np.asarray(reset_counts, float)
    return 0.5 * (s - r) * lsb_nT, (0.5 * (s + r) - zero_count) * lsb_nT


def t_delay_ms(t_TM_ms, settle_ms: float = T_SETTLE_MS):
    """RESET reading delay after the SET one: settling + measurement time (ms)."""
    return np.asarray(t_TM_ms, float) + settle_ms


def rotation_angle_rad(rate_dps, t_delay_ms_):
    """phi = w t_delay (rad) for a rate in deg/s and a delay in ms."""
    return np.radians(np.asarray(rate_dps, float)) * np.asarray(t_delay_ms_, float) * 1e-3


def rotation_matrix(rotvec_rad):
    """Rodrigues: exp([a]x) for rotation vectors a (..., 3) -> (..., 3, 3)."""
    a = np.asarray(rotvec_rad, float)
    ang = np.linalg.norm(a, axis=-1)[..., None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(ang[..., 0] > 0, a / np.where(ang[..., 0] > 0, ang[..., 0], 1.0), 0.0)
    K = np.zeros(a.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + np.sin(ang) * K + (1.0 - np.cos(ang)) * (K @ K)


def field_after(field_nT, rate_dps, t_delay_ms_):
    """B' = exp(-[w]x t) B: the body-frame field t_delay later, w (..., 3) in deg/s."""
    w = np.radians(np.asarray(rate_dps, float))
    R = rotation_matrix(-w * (np.asarray(t_delay_ms_, float)[..., None] * 1e-3))
    return np.einsum("...ij,...j->...i", R, np.asarray(field_nT, float))


def offset_error_vector(field_nT, rate_dps, t_delay_ms_):
    """Offset error per axis (B - B')/2, exact, (..., 3) nT."""
    B = np.asarray(field_nT, float)
    return 0.5 * (B - field_after(B, rate_dps, t_delay_ms_))


def plane_rotation_offset_error(field_nT, rate_dps, t_delay_ms_):
    """The seed's case: B (1 - cos phi) / 2 (nT)."""
    phi = rotation_angle_rad(rate_dps, t_delay_ms_)
    return np.asarray(field_nT, float) * (1.0 - np.cos(phi)) / 2.0


def worst_case_offset_error(field_nT, rate_dps, t_delay_ms_):
    """Largest axis error over every geometry: |B| sin(phi/2) (nT)."""
    phi = rotation_angle_rad(rate_dps, t_delay_ms_)
    return np.asarray(field_nT, float) * np.abs(np.sin(phi / 2.0))


# =======================================================================================
# (b) Error maps
# =======================================================================================
def _geometry(theta_deg, tilt_deg):
    """Measuring axis x; field (cos t, sin t, 0); rotation axis: z tilted by `tilt`
    about x (tilt 0: rotation in the plane of field and axis, the seed's plane rotation)."""
    th = np.radians(np.asarray(theta_deg, float))
    ps = np.radians(np.asarray(tilt_deg, float))
    u = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=-1)
    n = np.stack([np.zeros_like(ps), -np.sin(ps), np.cos(ps)], axis=-1)
    return u, n


def offset_error_maps(field_nT: float = DEFAULT_FIELD_NT, rates_dps=None, t_TM_ms=T_TM_MS,
                      theta_deg=None, tilt_deg=(0.0,), settle_ms: float = T_SETTLE_MS) -> dict:
    """Exact offset error on the measuring axis over rate x t_TM x theta x tilt.

    Geometry: the measuring axis is x, the field makes angle theta with it (in the x-y
    plane), the body turns about z tilted by `tilt` about x (tilt 0: the plane rotation of
    the seed; theta 0 is then exactly the seed's case). Returns a dict of numpy arrays:
      rate_dps (R,), t_TM_ms (K,), t_delay_ms (K,), theta_deg (Th,), tilt_deg (P,),
      field_nT, error_nT (K, R, Th, P) signed measuring-axis error, error_abs_nT,
      error_pct (|error| / |B| in %), error_vec_nT (K, R, Th, P, 3) all three axes,
      first_order_nT (K, R, Th) B sin(theta) phi / 2 (tilt 0), seed_plane_nT (K, R)
      B (1 - cos phi)/2, seed_plane_pct, worst_nT (K, R) = |B| sin(phi/2) over all
      geometries, worst_pct, and worst_case: list of table rows (see worst_case_table).
    """
    rates = np.arange(0.0, 10.0001, 1.0) if rates_dps is None else np.asarray(rates_dps, float)
    theta = np.arange(0.0, 180.0001, 15.0) if theta_deg is None else np.asarray(theta_deg, float)
    tTM = np.asarray(t_TM_ms, float).reshape(-1)
    tilt = np.asarray(tilt_deg, float).reshape(-1)
    if not (np.isfinite(field_nT) and field_nT > 0):
        raise InputError(None, f"setreset: field_nT must be positive, got {field_nT}")
    for nm, a in (("rates_dps", rates), ("t_TM_ms", tTM), ("theta_deg", theta),
                  ("tilt_deg", tilt)):
        if a.size == 0 or not np.isfinite(a).all():
            raise InputError(None, f"setreset: {nm} must be a non-empty finite array")
    if (tTM < 0).any() or settle_ms < 0:
        raise InputError(None, "setreset: t_TM_ms and settle_ms must be >= 0")
    td = t_delay_ms(tTM, settle_ms)
    u, n = _geometry(theta[:, None], tilt[None, :])          # (Th, P, 3) each
    B = field_nT * u
    # rotation vectors: -w n t, shape (K, R, Th, P, 3)
    wt = np.radians(rates)[None, :] * td[:, None] * 1e-3       # (K, R) = phi
    rv = -wt[:, :, None, None, None] * n[None, None, :, :, :]
    R = rotation_matrix(rv)
    Bp = np.einsum("krtpij,tpj->krtpi", R, B)
    ev = 0.5 * (B[None, None] - Bp)
    err = ev[..., 0]
    phi = wt
    out = {
        "field_nT": float(field_nT), "rate_dps": rates, "t_TM_ms": tTM, "t_delay_ms": td,
        "settle_ms": float(settle_ms), "theta_deg": theta, "tilt_deg": tilt,
        "error_nT": err, "error_abs_nT": np.abs(err), "error_pct": 100.0 * np.abs(err) / field_nT,
        "error_vec_nT": ev,
        "first_order_nT": field_nT * np.sin(np.radians(theta))[None, None, :] * phi[:, :, None] / 2,
        "seed_plane_nT": field_nT * (1.0 - np.cos(phi)) / 2.0,
        "worst_nT": field_nT * np.abs(np.sin(phi / 2.0)),
    }
    out["seed_plane_pct"] = 100.0 * out["seed_plane_nT"] / field_nT
    out["worst_pct"] = 100.0 * out["worst_nT"] / field_nT
    out["worst_case"] = worst_case_table(out)
    return out


def worst_case_table(maps) -> list:
    """Rows per t_TM at the highest rate of the grid: t_TM_ms, t_delay_ms, rate_dps,
    phi_deg, seed plane error (theta = 0) nT and %, the largest error on the grid (nT, %,
    at theta), the largest over every geometry |B| sin(phi/2) (nT, %), ratio to the seed
    case, and whether the seed's < 0.001 % holds for each."""
    rows = []
    B = maps["field_nT"]
    r = int(np.argmax(maps["rate_dps"]))
    for k, tTM in enumerate(maps["t_TM_ms"]):
        grid = maps["error_abs_nT"][k, r]                       # (Th, P)
        it, ip = np.unravel_index(int(np.argmax(grid)), grid.shape)
        seed = float(maps["seed_plane_nT"][k, r])
        worst = float(maps["worst_nT"][k, r])
        rows.append({
            "t_TM_ms": float(tTM), "t_delay_ms": float(maps["t_delay_ms"][k]),
            "rate_dps": float(maps["rate_dps"][r]),
            "phi_deg": float(np.degrees(rotation_angle_rad(maps["rate_dps"][r],
                                                           maps["t_delay_ms"][k]))),
            "seed_plane_nT": seed, "seed_plane_pct": 100 * seed / maps["field_nT"],
            "grid_max_nT": float(grid[it, ip]),
            "grid_max_pct": float(100 * grid[it, ip] / maps["field_nT"]),
            "grid_max_theta_deg": float(maps["theta_deg"][it]),
            "grid_max_tilt_deg": float(maps["tilt_deg"][ip]),
            "worst_nT": worst, "worst_pct": 100 * worst / maps["field_nT"],
            "worst_over_seed": (worst / seed) if seed > 0 else float("inf"),
            "seed_bound_holds_plane": bool(100 * seed / B < SEED_OFFSET_ERROR_BOUND_PCT),
            "seed_bound_holds_general": bool(100 * worst / B < SEED_OFFSET_ERROR_BOUND_PCT),
        })
    return rows


def format_worst_case_table(rows) -> str:
    lines = ["| t_TM ms | t_delay ms | rate deg/s | phi deg | seed plane (theta=0) nT | % | "
             "general worst nT | % | ratio | seed < 0.001 %: plane / general |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['t_TM_ms']:g} | {r['t_delay_ms']:g} | {r['rate_dps']:g} | "
                     f"{r['phi_deg']:.4f} | {r['seed_plane_nT']:.3e} | {r['seed_plane_pct']:.2e} | "
                     f"{r['worst_nT']:.2f} | {r['worst_pct']:.4f} | {r['worst_over_seed']:.0f} | "
                     f"{'yes' if r['seed_bound_holds_plane'] else 'no'} / "
                     f"{'yes' if r['seed_bound_holds_general'] else 'no'} |")
    return "\n".join(lines)


def plot_error_maps(maps, out_dir, *, tilt_index: int = 0, annotate: bool = True) -> list:
    """Heatmaps of |offset error| (nT) rate vs theta, one PNG per t_TM (numbers in the
    cells), and a summary PNG of the seed-plane vs general worst case against rate.
    Returns the list of PNG paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    rates, theta = maps["rate_dps"], maps["theta_deg"]
    vmax = float(maps["error_abs_nT"][..., tilt_index].max()) or 1.0
    for k, tTM in enumerate(maps["t_TM_ms"]):
        Z = maps["error_abs_nT"][k, :, :, tilt_index]          # (R, Th)
        fig, ax = plt.subplots(figsize=(1.0 + 0.75 * len(theta), 1.2 + 0.45 * len(rates)))
        im = ax.imshow(Z, origin="lower", aspect="auto", cmap="viridis", vmin=0, vmax=vmax)
        ax.set_xticks(range(len(theta)))
        ax.set_xticklabels([f"{t:g}" for t in theta])
        ax.set_yticks(range(len(rates)))
        ax.set_yticklabels([f"{r:g}" for r in rates])
        ax.set_xlabel("angle theta between field and measuring axis, deg")
        ax.set_ylabel("body rate, deg/s")
        ax.set_title(f"MMC5883 SET/RESET offset error |(B - B')/2|, nT: t_TM = {tTM:g} ms, "
                     f"t_delay = {maps['t_delay_ms'][k]:g} ms, |B| = {maps['field_nT']:.0f} nT, "
                     f"rotation-axis tilt {maps['tilt_deg'][tilt_index]:g} deg", fontsize=9)
        if annotate and Z.size <= 600:
            for i in range(Z.shape[0]):
                for j in range(Z.shape[1]):
                    v = Z[i, j]
                    txt = f"{v:.1f}" if v >= 0.1 else (f"{v:.0e}" if v > 0 else "0")
                    ax.text(j, i, txt, ha="center", va="center", fontsize=6,
                            color="white" if v < 0.6 * vmax else "black")
        fig.colorbar(im, ax=ax, label="nT")
        fig.tight_layout()
        tag = f"{tTM:g}".replace(".", "p")
        p = os.path.join(out_dir, f"setreset_offset_error_tTM_{tag}ms.png")
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    # summary: seed plane vs general worst case against rate
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k, tTM in enumerate(maps["t_TM_ms"]):
        sel = rates > 0
        ax.semilogy(rates[sel], maps["worst_pct"][k, sel], "-", color=f"C{k}",
                    label=f"general worst, t_TM {tTM:g} ms")
        ax.semilogy(rates[sel], maps["seed_plane_pct"][k, sel], "--", color=f"C{k}",
                    label=f"seed plane (theta=0), t_TM {tTM:g} ms")
    ax.axhline(SEED_OFFSET_ERROR_BOUND_PCT, color="k", lw=0.8, ls=":", label="seed bound 0.001 %")
    ax.set_xlabel("body rate, deg/s")
    ax.set_ylabel("offset error, % of |B|")
    ax.set_title("SET/RESET offset error while turning", fontsize=10)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    p = os.path.join(out_dir, "setreset_offset_error_vs_rate.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


# =======================================================================================
# (c) Compensation with the gyro rate
# =======================================================================================
def compensate_offset(set_nT, reset_nT, rate_dps, t_delay_ms_, method: str = "exact"):
    """Offset from a SET/RESET pair corrected for the body turn measured by the gyro.

    set_nT, reset_nT (..., 3) in a right-handed frame whose rate is rate_dps (..., 3).
    method "exact": B = (I + R_m)^-1 (out1 - out2), o = out1 - B;
    "first_order": o = (out1 + out2)/2 - (w_m x B^) t_delay / 2, B^ = (out1 - out2)/2.
    """
    s = np.asarray(set_nT, float)
    r = np.asarray(reset_nT, float)
    w = np.radians(np.asarray(rate_dps, float))
    t = np.asarray(t_delay_ms_, float) * 1e-3
    if method == "exact":
        R = rotation_matrix(-w * t[..., None] if np.ndim(t) else -w * t)
        A = np.broadcast_to(np.eye(3), R.shape) + R
        B = np.linalg.solve(A, (s - r)[..., None])[..., 0]
        return s - B
    if method == "first_order":
        Bh = 0.5 * (s - r)
        tt = t[..., None] if np.ndim(t) else t
        return 0.5 * (s + r) - 0.5 * np.cross(w, Bh) * tt
    raise ValueError(f"compensate_offset: method must be 'exact' or 'first_order', got {method!r}")


def _random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def compensation_gain(field_nT: float = DEFAULT_FIELD_NT, rates_dps=(1.0, 10.0),
                      t_TM_ms=T_TM_MS, gyro_noise_dps=(0.0, 0.01, 0.03, 0.1),
                      gyro_bias_dps: float = 0.0, *, settle_ms: float = T_SETTLE_MS,
                      method: str = "exact", n_trials: int = 4000, seed: int = 0) -> dict:
    """How much of the offset error the gyro compensation removes (Monte Carlo).

    Per trial: random field direction, random rotation axis at the given rate, exact
    SET/RESET pair with a zero bridge offset; the gyro reads the rate plus per-axis
    Gaussian noise (sigma gyro_noise_dps) plus a bias of magnitude gyro_bias_dps in a
    random direction. Returns arrays over (rate, t_TM, gyro noise):
      rms_before_nT, rms_after_nT, max_before_nT, max_after_nT, removed = 1 - rms_after /
      rms_before (fraction of the RMS error removed), expected_after_nT (|B| sqrt(2/3)
      |dw| t_delay / 2, dw the RMS gyro error), and the axes rate_dps, t_TM_ms, gyro_noise_dps.
    """
    rates = np.asarray(rates_dps, float).reshape(-1)
    tTM = np.asarray(t_TM_ms, float).reshape(-1)
    noise = np.asarray(gyro_noise_dps, float).reshape(-1)
    if n_trials < 10:
        raise InputError(None, "setreset: n_trials must be >= 10")
    if (noise < 0).any() or gyro_bias_dps < 0:
        raise InputError(None, "setreset: gyro noise and bias must be >= 0")
    rng = np.random.default_rng(seed)
    u = _random_unit(rng, n_trials)
    axis = _random_unit(rng, n_trials)
    z = rng.normal(size=(n_trials, 3))
    bias_dir = _random_unit(rng, n_trials)
    B = field_nT * u
    shape = (len(rates), len(tTM), len(noise))
    out = {k: np.zeros(shape) for k in ("rms_before_nT", "rms_after_nT", "max_before_nT",
                                         "max_after_nT", "removed", "expected_after_nT")}
    for a, rate in enumerate(rates):
        w = rate * axis
        for k, tm in enumerate(tTM):
            td = float(t_delay_ms(tm, settle_ms))
            Bp = field_after(B, w, td)
            out1, out2 = B, -Bp                                   # o = 0
            before = 0.5 * (out1 + out2)
            for j, sg in enumerate(noise):
                wm = w + sg * z + gyro_bias_dps * bias_dir
                after = compensate_offset(out1, out2, wm, td, method)
                rb = np.sqrt(np.mean(before ** 2))
                ra = np.sqrt(np.mean(after ** 2))
                out["rms_before_nT"][a, k, j] = rb
                out["rms_after_nT"][a, k, j] = ra
                out["max_before_nT"][a, k, j] = np.abs(before).max()
                out["max_after_nT"][a, k, j] = np.abs(after).max()
                out["removed"][a, k, j] = 1.0 - ra / rb if rb > 0 else np.nan
                dw = np.sqrt(3 * sg ** 2 + gyro_bias_dps ** 2)
                # |dw x B| RMS per axis: |B| |dw| sqrt(2/3)/sqrt(3)
                out["expected_after_nT"][a, k, j] = (field_nT * np.radians(dw) * td * 1e-3 / 2
                                                     * np.sqrt(2.0 / 9.0))
    out.update({"rate_dps": rates, "t_TM_ms": tTM, "gyro_noise_dps": noise,
                "gyro_bias_dps": float(gyro_bias_dps), "method": method,
                "field_nT": float(field_nT), "n_trials": int(n_trials)})
    return out


def format_compensation_table(g) -> str:
    lines = ["| rate deg/s | t_TM ms | gyro noise deg/s | RMS before nT | RMS after nT "
             "| removed % |",
             "|---:|---:|---:|---:|---:|---:|"]
    for a, rate in enumerate(g["rate_dps"]):
        for k, tm in enumerate(g["t_TM_ms"]):
            for j, sg in enumerate(g["gyro_noise_dps"]):
                lines.append(f"| {rate:g} | {tm:g} | {sg:g} | "
                             f"{g['rms_before_nT'][a, k, j]:.3f} | "
                             f"{g['rms_after_nT'][a, k, j]:.3g} | "
                             f"{100 * g['removed'][a, k, j]:.2f} |")
    return "\n".join(lines)


# =======================================================================================
# Stored offset for SET-only readings (float64 reference of the flight routine)
# =======================================================================================
class StoredOffset:
    """Keep the offset of the last SET/RESET pair for readings taken after SET only.

    update(set, reset[, rate_dps]) stores the pair's offset (gyro-compensated when a rate
    is given and t_delay_ms is set); field_from_set(set) = set - offset. A frame of
    nT vectors (3,) or (N, 3); before the first update field_from_set raises.
    """

    def __init__(self, t_delay_ms_: float | None = None, method: str = "exact"):
        self.t_delay_ms = t_delay_ms_
        self.method = method
        self.offset_nT = None
        self.n_updates = 0

    def update(self, set_nT, reset_nT, rate_dps=None):
        if rate_dps is not None:
            if self.t_delay_ms is None:
                raise ValueError("StoredOffset: a rate was given but t_delay_ms is not set")
            off = compensate_offset(set_nT, reset_nT, rate_dps, self.t_delay_ms, self.method)
        else:
            off = offset_and_field(set_nT, reset_nT)[1]
        if not np.isfinite(off).all():
            raise ValueError("StoredOffset: non-finite SET/RESET pair; offset kept")
        self.offset_nT = np.array(off, float)
        self.n_updates += 1
        return self.offset_nT

    def field_from_set(self, set_nT):
        if self.offset_nT is None:
            raise ValueError("StoredOffset: no SET/RESET pair yet")
        return np.asarray(set_nT, float) - self.offset_nT

    @staticmethod
    def field_from_pair(set_nT, reset_nT):
        return offset_and_field(set_nT, reset_nT)[0]


# =======================================================================================
# On telemetry: the bridge offset of a SET/RESET sensor, gyro-compensated
# =======================================================================================
def chip_offset_compensated(spec, sensor_data, calibration, rate_body_dps, *,
                            t_delay_ms_: float, H_boom_to_body=None):
    """The bridge offset (sensor axes, nT) of a SET/RESET sensor with the body turn during
    the pair removed.

    spec: SensorSpec; sensor_data: preprocess(...)[name] (its field_frame_nT is the mean of
    the pair, its chip_offset_sensor_nT the uncorrected offset); calibration: the sensor's
    SensorCalibration (gives W = M^-1 and b); rate_body_dps (N, 3) gyro rate in body axes;
    t_delay_ms_: RESET delay after SET; H_boom_to_body for boom sensors (default I).
    In frame axes the pair reads F = W B + b and F' = W R B + b, so the mean gives
    B = 2 (I + R)^-1 M (F_mean - b) and the offset error is W (I - R) B / 2.
    """
    if not spec.set_reset or sensor_data.chip_offset_sensor_nT is None:
        raise InputError(None, f"setreset: {spec.name} has no SET/RESET readings")
    w = np.asarray(rate_body_dps, float)
    if spec.frame == "boom" and H_boom_to_body is not None:
        w = w @ np.asarray(H_boom_to_body, float)               # H^T w, as rows
    T = sensor_data.temp_C
    M = calibration.M_at(T)
    b = calibration.b_at(T)
    R = rotation_matrix(-np.radians(w) * t_delay_ms_ * 1e-3)
    eye = np.broadcast_to(np.eye(3), R.shape)
    x = np.einsum("nij,nj->ni", M, sensor_data.field_frame_nT - b)
    B = np.linalg.solve(eye + R, 2.0 * x[..., None])[..., 0]
    dB = np.einsum("nij,nj->ni", eye - R, B) / 2.0
    err_frame = np.linalg.solve(M, dB[..., None])[..., 0]      # W dB
    idx, sign = spec.axis_map()
    err_sensor = np.zeros_like(err_frame)
    for k in range(3):                                         # frame[k] = sign sensor[idx]
        err_sensor[:, idx[k]] = sign[k] * err_frame[:, k]
    return sensor_data.chip_offset_sensor_nT - err_sensor


# =======================================================================================
# (e) Whether a sensor needs the gyro compensation (decided by the fit)
# =======================================================================================
# Compensate when the SET/RESET rotation error, RMS over the recorded body rates, passes
# this fraction of the field noise: an uncorrected error of half the noise raises the
# total error by sqrt(1 + 0.5^2) - 1 = 12 %, and it is systematic (it follows the rate).
SR_NOISE_FRACTION = 0.5
# The unit file does not say which measurement time the sensor runs at: take the longest
# (t_TM = 10 ms, delay 11 ms), the one with the largest error.
SR_DECISION_T_TM_MS = max(T_TM_MS)


def compensation_decision(spec, rate_dps, field_nT: float = DEFAULT_FIELD_NT,
                          noise_nT: float | None = None) -> dict:
    """Should the chain compensate this sensor's SET/RESET rotation error with the gyro?

    spec: the sensor (SensorSpec); rate_dps: (N, 3) body rates from the telemetry, or None;
    field_nT: the unit's field; noise_nT: 1-sigma noise of one axis of the field the chain
    computes. The error map's worst case over geometry, |B| sin(w t_delay / 2), at each
    recorded rate, RMS over the samples, against SR_NOISE_FRACTION x noise. Returns a
    JSON-able dict: enabled, why, and the figures."""
    if not spec.set_reset:
        return {"enabled": False, "why": "the sensor reports no SET/RESET pair"}
    w = None if rate_dps is None else np.asarray(rate_dps, float)
    if w is not None:
        w = w[np.all(np.isfinite(w), axis=1)]
    if w is None or len(w) == 0:
        return {"enabled": False, "why": "the telemetry carries no body rates "
                                         "(rate_x/y/z_dps): the gyro compensation needs them"}
    rate = np.linalg.norm(w, axis=1)
    delay = float(t_delay_ms(SR_DECISION_T_TM_MS))
    err = worst_case_offset_error(field_nT, rate, delay)
    err_rms = float(np.sqrt(np.mean(err ** 2)))
    noise = float(noise_nT) if noise_nT else float(spec.lsb_nT)
    limit = SR_NOISE_FRACTION * noise
    enabled = err_rms > limit
    why = (f"SET/RESET rotation error {err_rms:.1f} nT RMS over the recorded rates "
           f"(RMS {float(np.sqrt(np.mean(rate ** 2))):.2f} deg/s, delay {delay:g} ms, |B| "
           f"{field_nT:.0f} nT) {'passes' if enabled else 'is below'} {SR_NOISE_FRACTION:g} x "
           f"the noise ({noise:.1f} nT)")
    # the chain's coefficient c = delay / 2 * pi / 180 (s rad/deg, chain.SensorOptions), at
    # the delay the decision assumed (the unit file does not state t_TM; trace refines c)
    c = delay * 1e-3 / 2.0 * np.pi / 180.0
    # its 1-sigma: the RMS distance to the c of every measurement time the part has (the
    # unit file does not say which one runs); trace can measure it
    c_all = t_delay_ms(np.asarray(T_TM_MS)) * 1e-3 / 2.0 * np.pi / 180.0
    c_sig = float(np.sqrt(np.mean((c_all - c) ** 2)))
    return {"enabled": bool(enabled), "why": why, "sr_comp_s_per_deg": float(c),
            "sr_comp_sigma_s_per_deg": c_sig,
            "error_rms_nT": err_rms,
            "error_p95_nT": float(np.percentile(err, 95)), "noise_nT": noise,
            "threshold_nT": limit, "rate_rms_dps": float(np.sqrt(np.mean(rate ** 2))),
            "delay_ms": delay, "field_nT": float(field_nT)}
