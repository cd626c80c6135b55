#!/usr/bin/env python3
"""Side by side with the tools people use today (issue 9): this toolchain's ellipsoid and
temperature fits against PyPI peers and published methods, on the same data, in one run.

    python3 bench/peers/run.py --out docs/peer_comparison.md

Peers are installed from PyPI into throwaway virtual environments (one per peer, in a
temporary directory removed at the end) and run in subprocesses of those environments
through small adapter scripts (bench/peers/adapters/) that read .npy readings and write
the fitted offset and matrix as JSON; a peer that fails to install or to run is reported
with its first error line. Data: the shared simulated unit samsat_fm1 (truth known), the
project's simulator (full sphere and caps of orientations, several seeds) and real
full-sphere recordings by others in ../shared/realdata (no truth: held-out |B| scatter).
Figures: offset and matrix error against the truth, the offset error relative to the
Cramér-Rao bound (generator/fit/bounds.py) and a Monte Carlo of the efficiency, the |B| error over
the whole sphere, held-out |B| scatter, fit time relative to ours; and the PX4 temperature
model (cubic offsets, constant matrix) against ours on the thermal campaigns.

Outside the default test run; takes a few minutes (2-core machine), most of it ctef.
"""

from __future__ import annotations

import os

# Single-threaded numerics before numpy loads, as in the peers' processes (venvs.THREAD_ENV).
for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")

import argparse                                          # noqa: E402
import dataclasses                                       # noqa: E402
import datetime                                          # noqa: E402
import platform                                          # noqa: E402
import shutil                                            # noqa: E402
import sys                                               # noqa: E402
import tempfile                                          # noqa: E402
import time                                              # noqa: E402
from concurrent.futures import ThreadPoolExecutor        # noqa: E402
from dataclasses import dataclass, field                 # noqa: E402
from pathlib import Path                                 # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
for _p in (str(HERE), str(REPO)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import numpy as np                                       # noqa: E402

import datasets                                          # noqa: E402
import metrics                                           # noqa: E402
import variants                                          # noqa: E402
import venvs                                             # noqa: E402
from generator.errors import InputError                  # noqa: E402
from generator.io.truth import true_calibrated_frame        # noqa: E402

OURS = "ours (ellipsoid_fit)"
VARIANT = "ours, plain geometric refinement (before)"


@dataclass
class Method:
    label: str
    fit: object = None                  # in-process: fit(x_nT, R_nT) -> (b_nT, M)
    requirement: str | None = None      # peers: pip requirement (None: this interpreter)
    adapter: str | None = None          # peers: adapters/<file>
    distribution: str | None = None     # peers: distribution whose version is reported
    scale_free: bool = False            # returns a unit-sphere (or arbitrary) scale
    slow: bool = False                  # peers: run its batch first (the long pole)
    note: str = ""

    @property
    def is_peer(self) -> bool:
        return self.adapter is not None

    @property
    def venv_name(self) -> str:
        return (self.requirement or "bench-python").replace("/", "_")


METHODS = [
    Method(OURS, fit=variants.ours_fit,
           note="generator.fit.ellipsoid.ellipsoid_fit: algebraic Li-Griffiths start in "
                "normalised coordinates, Levenberg-Marquardt refinement of the "
                "noise-normalised residuals (|M(x-b)|-R)/|M^T u|, refuses fits the data do "
                "not determine"),
    Method("ours, algebraic stage only", fit=variants.ours_algebraic,
           note="generator.fit.ellipsoid.algebraic_ellipsoid alone"),
    Method(VARIANT, fit=variants.geometric_fit,
           note="same start; refinement of the plain |M(x-b)|-R (ellipsoid_fit("
                "residual='geometric')), the pipeline's default until the peer comparison "
                "showed its bias on caps"),
    Method("Li & Griffiths 2004 (bench reimplementation)", adapter="peer_li_griffiths.py",
           scale_free=True, note="paper's k=4 ellipsoid-specific fit on raw uT readings, "
                                 "bench/peers/adapters/peer_li_griffiths.py"),
    Method("magcal (PyPI)", requirement="magcal", adapter="peer_magcal.py",
           distribution="magcal", scale_free=True,
           note="MagnetometerCalibrator.calibrate('ellipsoid'): centre = mean of readings"),
    Method("circuitpython-mag-cal (PyPI)", requirement="circuitpython-mag-cal",
           adapter="peer_circuitpython_mag_cal.py", distribution="circuitpython-mag-cal",
           scale_free=True, note="Sensor('+X+Y+Z').fit_ellipsoid: 9-term quadric = 1 by "
                                 "least squares"),
    Method("ctef (PyPI)", requirement="ctef", adapter="peer_ctef.py", distribution="ctef",
           scale_free=True, slow=True, note="ctef(X) with defaults: Cayley-transform ellipsoid fit, "
                                 "trust-region least squares of norm(L(x-c))^2 - 1 in bounds"),
]
DATA_VENV = ("h5py", "h5py")        # reads the HDF5 / MATLAB v7.3 recordings


@dataclass
class Result:
    method: str
    case_id: str
    b_nT: np.ndarray | None = None
    M: np.ndarray | None = None
    seconds: float | None = None
    error: str | None = None
    note: str | None = None             # what a peer said about its result

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class Run:
    args: object
    t0: float
    work: Path
    cases: list = field(default_factory=list)
    results: dict = field(default_factory=dict)     # (method, case id) -> Result
    venv_info: dict = field(default_factory=dict)   # venv name -> venvs.Venv
    peer_batches: dict = field(default_factory=dict)
    real_failed: dict = field(default_factory=dict)
    recordings: dict = field(default_factory=dict)
    mc: list = field(default_factory=list)
    thermal: list = field(default_factory=list)

    def log(self, msg):
        print(f"[{time.perf_counter() - self.t0:6.1f} s] {msg}", file=sys.stderr, flush=True)


def first_line(exc) -> str:
    if isinstance(exc, InputError):
        return f"InputError: {exc.message}"
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"


# ---------------------------------------------------------------------------------------
# fitting
# ---------------------------------------------------------------------------------------
def run_in_process(run: Run, method: Method):
    for case in run.cases:
        t0 = time.perf_counter()
        try:
            b, M = method.fit(case.readings_nT, case.ref_norm_nT)
            r = Result(method.label, case.id, np.asarray(b), np.asarray(M),
                       time.perf_counter() - t0)
        except (InputError, np.linalg.LinAlgError, ValueError) as e:
            r = Result(method.label, case.id, seconds=time.perf_counter() - t0,
                       error=first_line(e))
        run.results[(method.label, case.id)] = r


def run_peers(run: Run, venv_futures: dict, jobs: list):
    """Sequentially, each peer's whole batch in one subprocess of its venv; slow ones
    first, so that they overlap with the work done in this process."""
    for method in sorted((m for m in METHODS if m.is_peer), key=lambda m: not m.slow):
        v = venv_futures[method.venv_name].result()
        run.venv_info[method.venv_name] = v
        if not v.ok:
            run.log(f"{method.label}: not installed: {v.error}")
            continue
        run.log(f"{method.label}: running {len(jobs)} fits")
        t0 = time.perf_counter()
        run.peer_batches[method.label] = venvs.run_batch(v, method.adapter, jobs, run.work,
                                                         run.args.peer_timeout_s)
        run.log(f"{method.label}: done in {time.perf_counter() - t0:.0f} s")


def collect_peer_results(run: Run):
    by_id = {c.id: c for c in run.cases}
    for method in (m for m in METHODS if m.is_peer):
        v = run.venv_info.get(method.venv_name)
        batch = run.peer_batches.get(method.label)
        for case in run.cases:
            if v is None or not v.ok:
                err = f"not installed: {v.error if v else 'venv not created'}"
                run.results[(method.label, case.id)] = Result(method.label, case.id, error=err)
                continue
            entry = (batch or {}).get("results", {}).get(case.id)
            if entry is None:
                err = (batch or {}).get("batch_error", "no result")
                run.results[(method.label, case.id)] = Result(method.label, case.id, error=err)
                continue
            if entry["error"]:
                run.results[(method.label, case.id)] = Result(
                    method.label, case.id, seconds=entry["seconds"], error=entry["error"])
                continue
            c = by_id[case.id]
            b = np.asarray(entry["offset_uT"]) * datasets.uT_nT
            M = np.asarray(entry["matrix"])
            if method.scale_free:
                M = metrics.rescale_to_magnitude(b, M, c.readings_nT, c.ref_norm_nT)
            run.results[(method.label, case.id)] = Result(method.label, case.id, b, M,
                                                          entry["seconds"],
                                                          note=entry.get("note"))


# ---------------------------------------------------------------------------------------
# Monte Carlo of the efficiency: fixed geometry, fresh Gaussian noise per draw
# ---------------------------------------------------------------------------------------
def efficiency_monte_carlo(run: Run):
    estimators = [(OURS, variants.ours_fit),
                  (VARIANT, variants.geometric_fit)]
    seed = run.args.seeds[0]
    for cap in [180.0] + list(run.args.caps):
        draws = run.args.mc_draws if cap >= 180 else run.args.mc_draws_cap
        for k_sensor, sensor in enumerate(("mmc1", "mpu1")):
            case = next(c for c in run.cases
                        if c.id == f"sim-s{seed}-cap{cap:g}-{sensor}")
            crb = metrics.offset_crb(case)
            tr = crb.offset_trace_nT2
            rng = np.random.default_rng([seed, 9, int(cap), k_sensor])
            noises = [rng.normal(size=case.field_true_nT.shape) * case.sigma_nT
                      for _ in range(draws)]
            row = {"cap_deg": cap, "sensor": sensor, "sigma_nT": case.sigma_nT,
                   "n": len(case.field_true_nT), "draws": draws,
                   "crb_sigma_nT": crb.offset_sigma_nT,
                   "crb_known_M_trace_ratio": float(np.trace(crb.offset_cov_known_M_nT2) / tr),
                   "estimators": {}}
            for label, fit in estimators:
                errs, refused = [], 0
                for noise in noises:
                    try:
                        b, _ = fit(case.field_true_nT + noise, case.ref_norm_nT)
                        errs.append(b - case.b_true_nT)
                    except (InputError, np.linalg.LinAlgError):
                        refused += 1
                e = np.array(errs).reshape(-1, 3)
                q = np.sum(e ** 2, axis=1) / tr
                mse, mse_hw = metrics.ratio_with_interval(q)
                cov_ratio = float(np.trace(np.cov(e.T)) / tr) if len(e) > 2 else float("nan")
                bias_sig = (np.abs(e.mean(axis=0)) / crb.offset_sigma_nT) if len(e) else None
                row["estimators"][label] = {
                    "mse_ratio": mse, "mse_ratio_hw": mse_hw, "cov_ratio": cov_ratio,
                    "refused": refused, "max_bias_in_crb_sigma":
                        float(np.max(bias_sig)) if bias_sig is not None else float("nan")}
            run.mc.append(row)
            run.log(f"Monte Carlo cap {cap:g} {sensor}: " + ", ".join(
                f"{k.split(' (')[0]} {v['mse_ratio']:.3f}" for k, v in row["estimators"].items()))


# ---------------------------------------------------------------------------------------
# temperature model: ours vs PX4's
# ---------------------------------------------------------------------------------------
def _true_poly(poly, dT):
    return sum(poly[k] * dT ** k for k in range(len(poly)))


def thermal_comparison(run: Run, cases):
    models = [("ours: fit_sensor (b(T) and M(T) cubic, held-out choice)", variants.ours_thermal_fit),
              ("PX4 model: cubic b(T), constant M (variant)", variants.px4_thermal_fit)]
    for case in cases:
        fd = case.fit_data
        a, b = datasets.heldout_folds(len(fd.time_s))
        row = {"case": case.id, "condition": case.condition, "label": case.label,
               "sensor": case.sensor, "models": {}}
        use = fd.usable & np.isfinite(fd.temp_C)
        for label, fit in models:
            out = {}
            try:
                t0 = time.perf_counter()
                cal = fit(case.sensor, [fd])
                out["seconds"] = time.perf_counter() - t0
                grid = np.linspace(cal.t_min_C, cal.t_max_C, 60)
                dT = grid - case.t_ref_C
                db = cal.b_at(grid) - _true_poly(case.b_poly_nT, dT[:, None])
                Mt = np.linalg.inv(_true_poly(case.W_poly, dT[:, None, None]))
                dM = cal.M_at(grid) - Mt
                out["offset_err_nT"] = float(np.sqrt(np.mean(np.sum(db ** 2, axis=1))))
                out["matrix_err_ppm"] = float(np.sqrt(np.mean(np.sum(dM ** 2, axis=(1, 2))))
                                              * metrics.PPM)
                held = []
                for fit_mask, test_mask in ((a, b), (b, a)):
                    c = fit(case.sensor, [dataclasses.replace(fd, usable=fd.usable & fit_mask)])
                    t = use & test_mask
                    e = c.apply64(fd.field_frame_nT[t], fd.temp_C[t]) - case.B_frame_nT[t]
                    held.append(e)
                out["heldout_vector_rms_nT"] = float(np.sqrt(np.mean(np.concatenate(held) ** 2)))
            except InputError as e:
                out["error"] = first_line(e)
            row["models"][label] = out
        truth_cal = _true_calibration_floor(case, use)
        row["floor_vector_rms_nT"] = truth_cal
        run.thermal.append(row)


def _true_calibration_floor(case, use):
    """Vector RMS of the TRUE parameters applied at the reported temperature: what no
    calibration of this model can beat on these readings."""
    truth = {"t_ref_C": case.t_ref_C,
             "sensors": {case.sensor: {"W_poly": case.W_poly, "b_poly_nT": case.b_poly_nT,
                                       "K_nT_per_A": None}}}
    fd = case.fit_data
    best = true_calibrated_frame(truth, case.sensor, fd.field_frame_nT[use], fd.temp_C[use])
    return float(np.sqrt(np.mean((best - case.B_frame_nT[use]) ** 2)))


# ---------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------
def fmt(v, digits=2):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    if abs(v) >= 100:
        return f"{v:.0f}"
    return f"{v:.{digits}f}"


def simulated_rows(run: Run, condition):
    """Per method: normalised figures (error / Cramér-Rao bound, RMS over all fits it
    returned: comparable across sensors) and absolute ones per sensor type."""
    cases = [c for c in run.cases if c.condition == condition]
    crbs = {c.id: metrics.offset_crb(c) for c in cases}
    t_ours = {c.id: run.results[(OURS, c.id)].seconds for c in cases}
    rows = []
    for m in METHODS:
        res = [(c, run.results[(m.label, c.id)]) for c in cases]
        ok = [(c, r) for c, r in res if r.ok]
        row = {"method": m.label, "returned": f"{len(ok)}/{len(res)}", "by_type": {}}
        if ok:
            eb = [np.sum(metrics.offset_error_nT(r.b_nT, c) ** 2) for c, r in ok]
            eM = [(metrics.matrix_error_ppm(r.M, c) / metrics.PPM) ** 2 for c, r in ok]
            eS = [metrics.full_sphere_norm_error_nT(r.b_nT, r.M, c) ** 2 for c, r in ok]
            row["offset_crb"] = float(np.sqrt(np.mean(
                [e / crbs[c.id].offset_trace_nT2 for e, (c, _) in zip(eb, ok)])))
            row["matrix_crb"] = float(np.sqrt(np.mean(
                [e / metrics.matrix_bound_sq(crbs[c.id]) for e, (c, _) in zip(eM, ok)])))
            row["sphere_crb"] = float(np.sqrt(np.mean(
                [e / metrics.full_sphere_norm_bound_sq_nT2(c, crbs[c.id])
                 for e, (c, _) in zip(eS, ok)])))
            for kind in SENSOR_TYPES:
                sel = [i for i, (c, _) in enumerate(ok) if c.sensor.startswith(kind)]
                if sel:
                    row["by_type"][kind] = {
                        "offset_nT": float(np.sqrt(np.mean([eb[i] for i in sel]))),
                        "matrix_ppm": float(np.sqrt(np.mean([eM[i] for i in sel]))) * metrics.PPM,
                        "sphere_nT": float(np.sqrt(np.mean([eS[i] for i in sel])))}
        timed = [(c, r) for c, r in res if r.seconds is not None and r.ok]
        if timed:
            row["ms"] = float(np.median([r.seconds for _, r in timed]) * 1e3)
            ratios = [r.seconds / t_ours[c.id] for c, r in timed if t_ours[c.id]]
            row["time_ratio"] = float(np.median(ratios)) if ratios else None
        rows.append(row)
    return rows


SENSOR_TYPES = {"mmc": "MMC5883MA", "mpu": "MPU-9255"}


def simulated_table(rows) -> list:
    def per_type(r, key, digits):
        return "; ".join(fmt(r["by_type"].get(k, {}).get(key), digits) for k in SENSOR_TYPES)
    kinds = " ; ".join(SENSOR_TYPES)
    out = ["| method | fits returned | offset err / CRB | matrix err / CRB | "
           "full-sphere abs(B) err / bound | "
           f"offset err RMS (nT) {kinds} | matrix err RMS (ppm) {kinds} | "
           f"full-sphere abs(B) err RMS (nT) {kinds} | time per fit (ms) | time / ours |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['method']} | {r['returned']} | {fmt(r.get('offset_crb'))} | "
                   f"{fmt(r.get('matrix_crb'))} | {fmt(r.get('sphere_crb'))} | "
                   f"{per_type(r, 'offset_nT', 1)} | {per_type(r, 'matrix_ppm', 0)} | "
                   f"{per_type(r, 'sphere_nT', 1)} | {fmt(r.get('ms'), 1)} | "
                   f"{fmt(r.get('time_ratio'), 2)} |")
    return out


def real_rows(run: Run):
    names = list(run.recordings)
    t_ours = {c.id: run.results[(OURS, c.id)].seconds for c in run.cases if c.heldout_nT is not None}
    rows = []
    for m in METHODS:
        row = {"method": m.label, "scatter": {}, "ratios": []}
        for name in names:
            vals = []
            for fold in ("A", "B"):
                cid = f"real-{name}-{fold}"
                r = run.results[(m.label, cid)]
                case = next(c for c in run.cases if c.id == cid)
                if r.ok:
                    vals.append(metrics.heldout_scatter_rel(r.b_nT, r.M, case))
                    if t_ours.get(cid):
                        run_ratio = r.seconds / t_ours[cid]
                        row["ratios"].append(run_ratio)
            row["scatter"][name] = float(np.mean(vals)) * 100 if len(vals) == 2 else None
            row.setdefault("partial", {})[name] = (float(vals[0]) * 100 if len(vals) == 1
                                                   else None)
        rows.append(row)
    return rows


def conditions_section(run: Run, elapsed_s) -> list:
    a = run.args
    sim_cases = [c for c in run.cases if c.id.startswith("sim-")]
    n_sim = sorted({len(c.readings_nT) for c in sim_cases})
    fm1 = [c for c in run.cases if c.id.startswith("fm1-")]
    sig = sorted({(c.sensor[:3], round(c.sigma_nT, 1)) for c in fm1 + sim_cases})
    h5 = run.venv_info.get(DATA_VENV[0])
    lines = [
        "## Conditions",
        "",
        f"* Generated by `python3 bench/peers/run.py --out {a.out}` on "
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; the whole run took "
        f"{elapsed_s:.0f} s. Options: seeds {', '.join(map(str, a.seeds))}; caps "
        f"{', '.join(f'{c:g}' for c in a.caps)} deg; simulated campaign {a.duration_s:g} s; "
        f"Monte Carlo {a.mc_draws} draws (full sphere), {a.mc_draws_cap} (each cap).",
        f"* Machine: {platform.platform()}, {os.cpu_count()} CPU(s) "
        f"({platform.processor() or platform.machine()}), Python {platform.python_version()}, "
        f"numpy {np.__version__}; numerics single-threaded in every process "
        "(OMP/OPENBLAS/MKL_NUM_THREADS=1). Peer fits run in one subprocess per peer "
        "while this process fits ours, so two fits share the two cores.",
        f"* **samsat_fm1 rotation.csv** (shared simulated unit, truth.json): 5 sensors, "
        f"{', '.join(str(len(c.readings_nT)) for c in fm1)} usable samples, full sphere by hand, "
        "boom deployed; truth = W(T), b(T) averaged over the samples' true board "
        "temperatures.",
        f"* **Project simulator** (generator.campaign.simulate, `random_truth` per seed, "
        f"`simulate_campaign('rotation', coverage_cap_deg=...)`): 5 sensors per seed, N = "
        f"{', '.join(map(str, n_sim))} samples per sensor; field direction over the full sphere "
        f"or within a cap of half-angle {', '.join(f'{c:g}' for c in a.caps)} deg about body "
        "+z (a satellite that cannot turn freely).",
        "* Reading noise (per axis, of the preprocessed field; part noise and count "
        "quantisation, SET/RESET halving the variance): " + ", ".join(
            f"{'MMC5883MA' if p == 'mmc' else 'MPU-9255'} {s:g} nT" for p, s in
            sorted(set(sig))) + ". |B| = 51,540 nT.",
        "* **Real recordings** (no truth), fit on alternate time blocks (10 blocks: even / "
        "odd), scored on the other half, both ways, averaged: " + "; ".join(
            f"{k}: {len(x)} samples" for k, x in run.recordings.items())
        + (f" (BROAD decimated 1:{datasets.BROAD_DECIMATION})" if any(
            k.startswith("BROAD") for k in run.recordings) else "")
        + (". Not read: " + "; ".join(f"{k}: {v}" for k, v in run.real_failed.items())
           if run.real_failed else "") + ".",
        "* Peers get the readings in uT; offsets come back to nT; unit-sphere matrices are "
        "scaled so that the mean |B_cal| over the fitted readings equals the known |B| (what "
        "a user with a known field does). Ours gets nT and the reference |B| (real "
        "recordings: a nominal one, the radius of the sphere with the volume of the fit "
        "half's algebraic ellipsoid, standing in for the local field a user would enter).",
        "* The HDF5 / MATLAB v7.3 recordings are read with "
        + (f"h5py {_version_of(h5.versions, 'h5py')}" if h5 and h5.ok else "h5py (not installed)")
        + " in a throwaway venv of its own (adapters/read_hdf5.py).",
        "",
        "Peers, each installed with pip into its own throwaway venv (created in a temporary "
        "directory, removed after the run):",
        "",
        "| peer | requirement | installed | version | install time (s) | how it is called |",
        "|---|---|---|---|---|---|",
    ]
    for m in METHODS:
        if not m.is_peer:
            continue
        v = run.venv_info.get(m.venv_name)
        if m.requirement is None:
            lines.append(f"| {m.label} | — (this interpreter) | yes | bench code | — | {m.note} |")
            continue
        if v is None:
            lines.append(f"| {m.label} | `pip install {m.requirement}` | not attempted | — | — "
                         f"| {m.note} |")
            continue
        status = "yes" if v.ok else f"**no**: {v.error}"
        version = _version_of(v.versions, m.distribution) if v.ok else "—"
        if v.ok:
            deps = [f"{d} {_version_of(v.versions, d)}" for d in KEY_DEPENDENCIES
                    if _version_of(v.versions, d) != "?"]
            version += f" (with {', '.join(deps)})" if deps else ""
        lines.append(f"| {m.label} | `pip install {m.requirement}` | {status} | {version} | "
                     f"{v.install_s:.0f} | {m.note} |")
    return lines


KEY_DEPENDENCIES = ("numpy", "scipy", "scikit-learn")


def _version_of(versions: dict, distribution) -> str:
    want = (distribution or "").lower().replace("_", "-")
    for name, version in versions.items():
        if name.lower().replace("_", "-") == want:
            return version
    return "?"


def mc_section(run: Run) -> list:
    lines = ["## Efficiency against the Cramér-Rao bound (Monte Carlo)", "",
             f"Fixed geometry: the noise-free readings of seed {run.args.seeds[0]}'s simulated "
             "campaign (same directions, true W and b), fresh Gaussian reading noise of the "
             "sensor's sigma in every draw. Ratio = mean over draws of |b_hat - b|^2 / trace of "
             "the marginal CRB (1 = efficient; includes bias), with its 95 % interval; "
             "cov = trace of the empirical covariance / CRB trace (bias removed); bias = "
             "largest |mean error| per axis in CRB sigmas. 'M known' is the conditional bound's "
             "trace relative to the marginal one (how much the nuisance matrix costs).", "",
             "| coverage | sensor (sigma) | N | draws | CRB sigma b (nT) | M known / marginal | "
             "ours: MSE / CRB | ours: cov / CRB | ours: bias (sigma) | ours: refused | "
             "variant: MSE / CRB | variant: cov / CRB | variant: bias (sigma) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in run.mc:
        o = row["estimators"][OURS]
        v = row["estimators"][VARIANT]
        cov = "full sphere" if row["cap_deg"] >= 180 else f"cap {row['cap_deg']:g} deg"
        lines.append(
            f"| {cov} | {row['sensor']} ({row['sigma_nT']:.1f} nT) | {row['n']} | {row['draws']} | "
            f"{', '.join(fmt(s, 1) for s in row['crb_sigma_nT'])} | "
            f"{row['crb_known_M_trace_ratio']:.3f} | "
            f"{fmt(o['mse_ratio'], 3)} ± {fmt(o['mse_ratio_hw'], 3)} | {fmt(o['cov_ratio'], 3)} | "
            f"{fmt(o['max_bias_in_crb_sigma'], 2)} | {o['refused']} | "
            f"{fmt(v['mse_ratio'], 3)} ± {fmt(v['mse_ratio_hw'], 3)} | {fmt(v['cov_ratio'], 3)} | "
            f"{fmt(v['max_bias_in_crb_sigma'], 2)} |")
    return lines


TIE_REL = 0.05     # figures within 5 % of the lowest are listed together as the best


def _best_within(rows, key, digits=2, unit="") -> str:
    low = min(r[key] for r in rows)
    tied = [r for r in rows if r[key] <= low * (1 + TIE_REL)]
    return ", ".join(f"{r['method']} {r[key]:.{digits}f}{unit}"
                     for r in sorted(tied, key=lambda r: r[key])) \
        + (" (within 5 % of each other)" if len(tied) > 1 else "")


def summary_section(run: Run, sim_tables: dict, real: list) -> list:
    lines = ["## Summary (computed from the tables below)", ""]
    full = [r for r in run.mc if r["cap_deg"] >= 180]
    if full:
        parts, within, upper = [], True, []
        for r in full:
            o = r["estimators"][OURS]
            upper.append(o["mse_ratio"] + o["mse_ratio_hw"])
            within &= o["mse_ratio"] <= 1.10
            parts.append(f"{r['sensor']} {o['mse_ratio']:.3f} ± {o['mse_ratio_hw']:.3f}")
        verdict = "**met**" if within else "**not met**"
        verdict += (" (point estimates <= 1.10; upper 95 % limits "
                    + ", ".join(f"{u:.3f}" for u in upper) + ")")
        lines.append("* **Full sphere, efficiency** (Monte Carlo): our fit's offset MSE / CRB = "
                     + "; ".join(parts) + ". Target 'within 10 % of the bound': " + verdict + ".")
    for cond, rows in sim_tables.items():
        ok = [r for r in rows if r.get("offset_crb") is not None]
        if not ok:
            continue
        ours = next(r for r in rows if r["method"] == OURS)
        lines.append(
            f"* **{cond}**: lowest offset err/CRB: {_best_within(ok, 'offset_crb')}; lowest "
            f"full-sphere |B| err/bound: {_best_within(ok, 'sphere_crb')}. Ours: returned "
            f"{ours['returned']}, offset err/CRB {fmt(ours.get('offset_crb'))}, full-sphere "
            f"|B| err/bound {fmt(ours.get('sphere_crb'))}.")
    if real:
        names = list(run.recordings)
        best = []
        for name in names:
            vals = [r for r in real if r["scatter"][name] is not None]
            if vals:
                rows = [{"method": r["method"], "v": r["scatter"][name]} for r in vals]
                o = next(r for r in real if r["method"] == OURS)["scatter"][name]
                best.append(f"{name}: lowest {_best_within(rows, 'v', 3, ' %')}; ours "
                            + (f"{o:.3f} %" if o is not None else "— (no fit on one fold or both)"))
        lines.append("* **Real recordings, held-out |B| scatter**: " + "; ".join(best) + ".")
    th = thermal_aggregate(run)
    for cond in dict.fromkeys(c for c, _ in th):
        parts = [f"{label.split(':')[0]}: offset {fmt(a['b'], 1)} nT, matrix "
                 f"{fmt(a['M'], 0)} ppm, held-out/floor {a['h']:.3f}"
                 for (c, label), a in th.items() if c == cond]
        lines.append(f"* **Temperature model, {cond}**: " + "; ".join(parts) + ".")
    return lines


def thermal_section(run: Run) -> list:
    lines = ["## Temperature model: ours against PX4's (cubic offsets, constant matrix)", "",
             "Reference-vector thermal campaigns (twelve positions in the jig, chamber -20..55 "
             "degC). Both fitted with the pipeline's sample gathering; PX4's model is the "
             "variant in bench/peers/variants.py (PX4 TC_M*: cubic offset polynomial per axis "
             "in temperature, no temperature terms in the scale/cross-axis matrix). Errors "
             "against the truth over the fitted temperature range (60-point grid): |b_hat(T) - "
             "b(T)| and |M_hat(T) - W(T)^-1|_F, RMS over the grid. Held-out: fit on alternate "
             "time blocks, vector error of the calibrated field (per axis RMS, reported "
             "temperature) on the other half, both ways; 'floor' is what the true parameters "
             "give on the same readings.", "",
             "| data | sensor | model | offset err RMS (nT) | matrix err RMS (ppm) | "
             "held-out vector RMS (nT) | floor (nT) | fit time (ms) |",
             "|---|---|---|---|---|---|---|---|"]
    for row in run.thermal:
        for label, m in row["models"].items():
            if "error" in m:
                lines.append(f"| {row['label']} | {row['sensor']} | {label} | "
                             f"failed: {m['error']} | | | | |")
                continue
            lines.append(f"| {row['label']} | {row['sensor']} | {label} | "
                         f"{fmt(m['offset_err_nT'], 1)} | {fmt(m['matrix_err_ppm'], 0)} | "
                         f"{fmt(m['heldout_vector_rms_nT'], 1)} | "
                         f"{fmt(row['floor_vector_rms_nT'], 1)} | {fmt(m['seconds'] * 1e3, 0)} |")
    agg = thermal_aggregate(run)
    if agg:
        lines += ["", "Over the sensors (RMS of the per-sensor figures; held-out as the mean "
                      "ratio to the floor):", "",
                  "| data | model | offset err RMS (nT) | matrix err RMS (ppm) | "
                  "held-out / floor |", "|---|---|---|---|---|"]
        for (cond, label), a in agg.items():
            lines.append(f"| {cond} | {label} | {fmt(a['b'], 1)} | {fmt(a['M'], 0)} | "
                         f"{a['h']:.3f} |")
    return lines


def thermal_aggregate(run: Run) -> dict:
    acc = {}
    for row in run.thermal:
        for label, m in row["models"].items():
            if "error" not in m:
                a = acc.setdefault((row["condition"], label), {"b": [], "M": [], "h": []})
                a["b"].append(m["offset_err_nT"])
                a["M"].append(m["matrix_err_ppm"])
                a["h"].append(m["heldout_vector_rms_nT"] / row["floor_vector_rms_nT"])
    return {k: {"b": float(np.sqrt(np.mean(np.square(a["b"])))),
                "M": float(np.sqrt(np.mean(np.square(a["M"])))),
                "h": float(np.mean(a["h"]))} for k, a in acc.items()}


def failures_section(run: Run) -> list:
    lines = ["## Failures and refusals", "",
             "Every fit that returned no calibration, grouped by method and first error line "
             "(a refusal by our fitter is deliberate: it reports what the data do not "
             "determine instead of returning a number).", ""]
    groups = {}
    for (label, cid), r in run.results.items():
        if not r.ok:
            cond = next(c.condition for c in run.cases if c.id == cid)
            groups.setdefault((label, r.error), []).append(f"{cond}: {cid}")
    if not groups:
        lines.append("None.")
    else:
        lines += ["| method | error (first line) | fits | which |", "|---|---|---|---|"]
        for (label, err), which in sorted(groups.items()):
            shown = ", ".join(w.split(": ")[1] for w in which[:6]) + (" ..." if len(which) > 6 else "")
            lines.append(f"| {label} | {err.replace('|', '/')} | {len(which)} | {shown} |")
    notes = {}
    for (label, cid), r in run.results.items():
        if r.ok and r.note:
            cond = next(c.condition for c in run.cases if c.id == cid)
            notes.setdefault((label, r.note), {}).setdefault(cond, 0)
            notes[(label, r.note)][cond] += 1
    if notes:
        lines += ["", "What peers reported about the fits they returned (e.g. why the "
                      "optimiser stopped):", "", "| method | note | fits per condition |",
                  "|---|---|---|"]
        for (label, note), per in sorted(notes.items()):
            lines.append(f"| {label} | {note.replace('|', '/')} | "
                         + ", ".join(f"{c}: {n}" for c, n in per.items()) + " |")
    return lines


METHOD_NOTES = """## How to read this

* **Error / CRB** columns divide each fit's squared error by the Cramér-Rao bound of that
  very fit (generator/fit/bounds.py: Fisher information of |M (x - b)| = |B| + noise with
  Gaussian per-axis reading noise sigma propagated into the residual, variance
  sigma^2 |M^T u|^2, and the six entries of M as nuisance parameters, so the bound on b is
  the marginal one) and take the square root of the mean over the fits the method
  returned: 1 is what an efficient unbiased estimator reaches on average, whatever the
  sensor's noise. Offset: |b_hat - b|^2 against the trace of the bound on b. Matrix:
  |P_hat - P|_F^2 against the bound on the six entries of M (off-diagonal ones twice).
  Full-sphere |B|: the mean square error below against the parameter bound propagated to
  the same directions. Over n fits these figures scatter statistically by roughly
  +-sqrt(1/(2n)) (one dominant axis) to +-sqrt(1/(6n)) (three equal ones): about
  +-10..20 % for 15 fits; the Monte Carlo table measures the efficiency precisely.
* **Matrix err** compares symmetric polar factors P = sqrt(M^T M) (the ellipsoid
  determines M only up to a rotation), Frobenius norm, parts per million.
* **Full-sphere |B| err** applies each calibration to noise-free readings of the true
  sensor in 2,000 directions over the whole sphere: what a calibration fitted on a cap
  does once the satellite sees every direction.
* Absolute errors are given per sensor type (MMC5883MA; MPU-9255): their noise differs
  by a factor of nine, so pooled absolute figures would mostly show which sensors a method
  returned a fit for.
* **Time / ours** is the median over the condition's fits of the fit time (the fit call
  only, not imports or I/O) relative to ours on the same readings.
* A method that returns nothing for a fit counts in 'fits returned' and in the failures
  table, not in the error columns.

## Why the plain geometric refinement loses on a cap, and the fix

The pipeline refines the ellipsoid by least squares of r_i = |M (x_i - b)| - R. The same
reading noise gives a residual of standard deviation sigma |M^T u_i| (u_i the calibrated
direction), so the unweighted cost can be lowered by shrinking M along the directions the
data's normals point to. On a full sphere those cover every direction and the pull
averages out; on a cap they all point near the cap axis and the fit trades the offset
along that axis against the matrix: a bias that grows with sigma / |B| and with a
narrower cap (compare the bias columns of the Monte Carlo table, full sphere against
caps). Dividing each residual by |M^T u_i| (evaluated at the current parameters, inside
the least squares: the row 'ours + normalised residuals (variant)') gives every residual the
variance sigma^2, i.e. the first-order likelihood, the estimator the Cramér-Rao bound is
attained by. That residual in generator/fit_ellipsoid.ellipsoid_fit (same algebraic
start, same Levenberg-Marquardt, the 9-column analytic Jacobian of
bench/peers/variants.py), with its uncertainty checks computed from the same normalised
Jacobian, is the change this comparison points to for partial coverage; the variant's
rows show what it gives.
"""


def credits_section(run: Run) -> list:
    lines = ["## Data credits", "",
             "* samsat_fm1: simulated unit in ../shared/data/samsat_fm1 (made by a simulator "
             "that is not part of the project).",
             "* Simulated campaigns: this project's generator/campaign/simulate.py."]
    for name, r in datasets.REAL_RECORDINGS.items():
        lines.append(f"* {name}: {r['credit']}; read from ../shared/realdata/{r['folder']}, "
                     "not copied into the project.")
    lines.append("* The ellipsoid algorithm of Li & Griffiths: Q. Li, J. G. Griffiths, "
                 "'Least squares ellipsoid specific fitting', Geometric Modeling and "
                 "Processing 2004, pp. 335-340.")
    return lines


def write_document(run: Run, path: Path, elapsed_s: float):
    conditions = [c for c in dict.fromkeys(c.condition for c in run.cases
                                           if c.b_true_nT is not None)]
    sim_tables = {cond: simulated_rows(run, cond) for cond in conditions}
    real = real_rows(run) if run.recordings else []
    doc = ["# Peer comparison: ellipsoid and temperature fits side by side", "",
           "Written by `bench/peers/run.py` (issue 9); regenerate, do not edit. What users "
           "would pick instead of this toolchain, fitted on the same readings in the same run.",
           ""]
    doc += summary_section(run, sim_tables, real) + [""]
    doc += conditions_section(run, elapsed_s) + [""]
    doc += ["## Ellipsoid fits on simulated data (truth known)", ""]
    for cond, rows in sim_tables.items():
        n = sum(1 for c in run.cases if c.condition == cond)
        doc += [f"### {cond} ({n} fits)", ""] + simulated_table(rows) + [""]
    doc += mc_section(run) + [""]
    if real:
        names = list(run.recordings)
        doc += ["## Real recordings (no truth): held-out |B| scatter", "",
                "std(|B_cal|) / mean(|B_cal|) on the half not fitted, in percent, mean of the "
                "two folds (— where a fold returned nothing; the other fold's figure is then "
                "given alone).", "",
                "| method | " + " | ".join(names) + " | time / ours (median) |",
                "|---|" + "---|" * (len(names) + 1)]
        for r in real:
            doc.append(f"| {r['method']} | " + " | ".join(
                fmt(r['scatter'][n], 3) if r['partial'][n] is None else
                f"— (one fold: {r['partial'][n]:.3f})" for n in names)
                       + f" | {fmt(float(np.median(r['ratios'])) if r['ratios'] else None, 2)} |")
        doc.append("")
    if run.thermal:
        doc += thermal_section(run) + [""]
    doc += failures_section(run) + [""]
    doc += [METHOD_NOTES.strip(), ""]
    doc += ["Methods compared:", ""] + [f"* **{m.label}**: {m.note}." for m in METHODS] + [""]
    doc += credits_section(run) + [""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(doc))


# ---------------------------------------------------------------------------------------
def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/peer_comparison.md",
                    help="markdown file to write (default: %(default)s)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                    help="simulator seeds (default: %(default)s)")
    ap.add_argument("--caps", type=float, nargs="+", default=[90.0, 60.0],
                    help="coverage cap half-angles in deg besides the full sphere")
    ap.add_argument("--duration-s", type=float, default=300.0,
                    help="simulated rotation campaign length at 10 Hz (default: %(default)s)")
    ap.add_argument("--mc-draws", type=int, default=400,
                    help="Monte Carlo draws on the full sphere (default: %(default)s)")
    ap.add_argument("--mc-draws-cap", type=int, default=300,
                    help="Monte Carlo draws on each cap (default: %(default)s)")
    ap.add_argument("--thermal-seeds", type=int, nargs="*", default=[1, 2],
                    help="simulator seeds for the thermal campaigns (default: %(default)s)")
    ap.add_argument("--peer-timeout-s", type=float, default=540.0,
                    help="time limit of one peer's batch (default: %(default)s)")
    ap.add_argument("--keep-venvs", action="store_true",
                    help="keep the temporary directory with the venvs (printed)")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    if not datasets.FM1.is_dir():
        print(f"shared data not found at {datasets.FM1}", file=sys.stderr)
        return 2
    jac_err = variants.check_normalised_jacobian()
    if not jac_err < 1e-5:
        print(f"variants: analytic Jacobian of the normalised residuals is off by {jac_err:.2g} "
              "(relative) from central differences", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="magcal-peers-"))
    run = Run(args, t_start, work)
    out = Path(args.out)
    if not out.is_absolute():
        out = Path.cwd() / out
    try:
        # 1. peers' venvs install in the background while the data are prepared
        pool = ThreadPoolExecutor(max_workers=5)
        wanted = {m.venv_name: m.requirement for m in METHODS if m.is_peer}
        wanted[DATA_VENV[0]] = DATA_VENV[1]
        futures = {name: pool.submit(venvs.create, name, req, work / "venvs")
                   for name, req in wanted.items()}
        run.log(f"installing {', '.join(r for r in wanted.values() if r)} into venvs under {work}")

        # 2. data
        run.cases = datasets.fm1_rotation_cases()
        run.cases += datasets.simulator_rotation_cases(args.seeds, [180.0] + list(args.caps),
                                                       work / "sim", args.duration_s)
        run.log(f"simulated: {len(run.cases)} ellipsoid cases")
        h5 = futures[DATA_VENV[0]].result()
        run.venv_info[DATA_VENV[0]] = h5
        run.recordings, run.real_failed = datasets.read_real_recordings(
            h5.python if h5.ok else None, work)
        if not h5.ok:
            run.real_failed.setdefault("HDF5 reader", h5.error)
        run.cases += datasets.real_cases(run.recordings)
        run.log(f"real recordings: {', '.join(f'{k} ({len(v)})' for k, v in run.recordings.items())}")
        (work / "npy").mkdir()
        jobs = []
        for c in run.cases:
            p = work / "npy" / f"{c.id}.npy".replace(" ", "_")
            np.save(p, c.readings_nT / datasets.uT_nT)
            jobs.append({"id": c.id, "npy": str(p)})

        # 3. peers in the background (one subprocess each, one after the other) ...
        peers_done = pool.submit(run_peers, run, futures, jobs)
        # 4. ... while ours and its variants run here
        for m in METHODS:
            if not m.is_peer:
                run_in_process(run, m)
                run.log(f"{m.label}: {len(run.cases)} fits")
        efficiency_monte_carlo(run)
        if args.thermal_seeds is not None:
            tcases = datasets.fm1_thermal_cases() + datasets.simulator_thermal_cases(
                args.thermal_seeds, work / "sim")
            thermal_comparison(run, tcases)
            run.log(f"thermal comparison: {len(tcases)} sensors")
        peers_done.result()
        pool.shutdown()
        collect_peer_results(run)
        elapsed = time.perf_counter() - t_start
        write_document(run, out, elapsed)
        run.log(f"wrote {out}")
    finally:
        if args.keep_venvs:
            print(f"kept {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
