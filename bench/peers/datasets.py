"""The data of the peer comparison: the shared simulated unit samsat_fm1 (truth known),
the project's simulator (full sphere and caps of orientations, several seeds) and real
full-sphere recordings made by others (no truth: held-out |B| scatter).

Every ellipsoid case is one sensor's readings to fit (nT, frame axes). Simulated cases
carry the truth: the offset b, the symmetric polar factor P of W^-1 (all the ellipsoid
determines), the noise-free readings of the same samples (for the Cramér-Rao bound), the
reading noise sigma, and noise-free readings over the whole sphere for the |B| error a
calibration makes in every orientation. Real cases carry the held-out half instead.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from generator.campaign import simulate as sim
from generator.errors import InputError
from generator.fit.ellipsoid import algebraic_ellipsoid, polar_spd
from generator.fit.thermal import fit_data_from
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.truth import load_truth, true_b, true_frame_field, true_W
from generator.io.unitfile import load_unit

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared"
FM1 = SHARED / "data" / "samsat_fm1"
REALDATA = SHARED / "realdata"
ADAPTERS = Path(__file__).resolve().parent / "adapters"

GAUSS_nT = 1e5
uT_nT = 1e3
EVAL_DIRECTIONS = 2000          # noise-free full-sphere evaluation readings per case
HELDOUT_BLOCKS = 10             # alternate time blocks: even -> fold A, odd -> fold B
BROAD_DECIMATION = 10           # 285.7 Hz -> 28.6 Hz (keeps ctef's run time bounded)


@dataclass
class EllipsoidCase:
    id: str
    condition: str                      # table the case belongs to
    sensor: str
    readings_nT: np.ndarray             # (N, 3) what every method fits
    ref_norm_nT: float                  # |B| given to methods that take it
    # simulated only
    b_true_nT: np.ndarray | None = None
    P_true: np.ndarray | None = None    # symmetric polar factor of the true W^-1
    W_true: np.ndarray | None = None
    field_true_nT: np.ndarray | None = None   # noise-free readings of the same samples
    sigma_nT: float | None = None       # per-axis reading noise (incl. quantisation)
    eval_true_nT: np.ndarray | None = None    # noise-free readings over the whole sphere
    # real only
    heldout_nT: np.ndarray | None = None
    notes: dict = field(default_factory=dict)


def field_noise_sigma_nT(spec) -> float:
    """Per-axis noise of the preprocessed field: the part's noise and the count
    quantisation (lsb^2/12) of each reading; SET/RESET averages two readings,
    field = (SET - RESET)/2, which halves the variance."""
    noise = spec.noise_nT if spec.noise_nT is not None else sim.DEFAULT_NOISE_nT[spec.part]
    var = noise ** 2 + spec.lsb_nT ** 2 / 12.0
    return float(np.sqrt(var / (2.0 if spec.set_reset else 1.0)))


def sphere_directions(n, seed) -> np.ndarray:
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1)[:, None]


def _simulated_case(case_id, condition, spec, x, W, b, B_frame, R, eval_seed):
    B_eval = R * sphere_directions(EVAL_DIRECTIONS, eval_seed)
    return EllipsoidCase(
        id=case_id, condition=condition, sensor=spec.name, readings_nT=x, ref_norm_nT=R,
        b_true_nT=b, P_true=polar_spd(np.linalg.inv(W)), W_true=W,
        field_true_nT=B_frame @ W.T + b, sigma_nT=field_noise_sigma_nT(spec),
        eval_true_nT=B_eval @ W.T + b)


# ---------------------------------------------------------------------------------------
# simulated: the shared unit and the project's simulator
# ---------------------------------------------------------------------------------------
def fm1_rotation_cases(condition="samsat_fm1 rotation.csv") -> list:
    """The shared unit's hand rotation (boom deployed, room temperature). Truth: W(T) and
    b(T) of truth.json averaged over the samples' true board temperatures (they drift by
    0.3 degC during the 400 s)."""
    unit = load_unit(FM1 / "unit.toml")
    truth = load_truth(FM1 / "truth.json")
    npz = np.load(FM1 / "rotation.truth.npz")
    data = preprocess(read_telemetry(FM1 / "rotation.csv", unit), unit)
    R = float(unit.lab_field_nT)
    cases = []
    for k, spec in enumerate(unit.sensors):
        d = data[spec.name]
        use = d.usable
        T = npz[f"temp_{spec.frame}_C"][use]
        W = true_W(truth, spec.name, T).mean(axis=0)
        b = true_b(truth, spec.name, T).mean(axis=0)
        B_frame = true_frame_field(truth, spec.frame, npz["b_body_nT"][use], True)
        case = _simulated_case(f"fm1-{spec.name}", condition, spec, d.field_frame_nT[use],
                               W, b, B_frame, R, eval_seed=1000 + k)
        case.notes["temp_span_C"] = float(np.ptp(T))
        cases.append(case)
    return cases


def simulator_rotation_cases(seeds, caps_deg, work: Path, duration_s: float) -> list:
    """The project's simulator: per seed a random unit (random_truth) and one hand-rotation
    campaign per coverage cap (field direction within cap_deg of body +z; 180 = full
    sphere). Condition names: 'simulator, full sphere' / 'simulator, cap 90 deg'."""
    unit = sim.make_example_unit()
    R = float(unit.lab_field_nT)
    cases = []
    for seed in seeds:
        truth = sim.random_truth(unit, np.random.default_rng([seed, 0]))
        for cap in caps_deg:
            name = f"rot_s{seed}_cap{cap:g}"
            _, arr = sim.simulate_campaign("rotation", unit, truth,
                                           np.random.default_rng([seed, 1, int(cap)]), work,
                                           name=name, coverage_cap_deg=float(cap),
                                           duration_s=duration_s)
            data = preprocess(read_telemetry(work / f"{name}.csv", unit), unit)
            condition = ("simulator, full sphere" if cap >= 180 else
                         f"simulator, cap {cap:g} deg")
            for k, spec in enumerate(unit.sensors):
                st = truth.sensors[spec.name]
                d = data[spec.name]
                use = d.usable
                dT = arr[f"temp_{spec.frame}_C"][use] - truth.t_ref_C
                W = st.W(dT).mean(axis=0)
                b = st.b(dT).mean(axis=0)
                B_frame = truth.true_field_frame(spec, arr["b_body_nT"][use], True)
                cases.append(_simulated_case(f"sim-s{seed}-cap{cap:g}-{spec.name}",
                                             condition, spec, d.field_frame_nT[use], W, b,
                                             B_frame, R, eval_seed=[seed, 2, k]))
    return cases


# ---------------------------------------------------------------------------------------
# real recordings (no truth): fit on one half, |B| scatter on the other
# ---------------------------------------------------------------------------------------
REAL_RECORDINGS = {
    "sunsided HMC5883L": {
        "folder": "sunsided_hmc5883l", "file": "hmc5883l_compass.mat", "dataset": "compassBuffer",
        "credit": "sunsided/sensor-fusion @ f16045a, data/set-2/full-sphere (EUPL-1.2)"},
    "ck_explorer": {
        "folder": "ck_explorer", "file": "acc_mag_log.csv",
        "credit": "CK-Explorer/Magnetometer-and-Accelerometer-Calibration @ 61ac766, "
                  "Data Examples/acc_mag_log.csv (Apache-2.0)"},
    "BROAD 02 slow": {
        "folder": "broad", "file": "02_undisturbed_slow_rotation_B.hdf5", "dataset": "imu_mag",
        "credit": "dlaidig/broad @ 7e2f818, data_hdf5/ (BROAD, CC-BY-4.0)"},
    "BROAD 07 fast": {
        "folder": "broad", "file": "07_undisturbed_fast_rotation_B.hdf5", "dataset": "imu_mag",
        "credit": "dlaidig/broad @ 7e2f818, data_hdf5/ (BROAD, CC-BY-4.0)"},
}


def read_real_recordings(h5_python: str | None, work: Path) -> tuple[dict, dict]:
    """{name: (N, 3) readings in nT, time order}, {name: why it could not be read}.
    HDF5 files are read by `h5_python` (a throwaway venv with h5py); the CSV directly."""
    out, failed = {}, {}
    requests = []
    for name, r in REAL_RECORDINGS.items():
        if "dataset" in r:
            requests.append({"name": name, "path": str(REALDATA / r["folder"] / r["file"]),
                             "dataset": r["dataset"], "out": str(work / f"real_{len(requests)}.npy")})
    if requests and h5_python is None:
        failed.update({q["name"]: "h5py venv not available" for q in requests})
    elif requests:
        (work / "h5_requests.json").write_text(json.dumps(requests))
        p = subprocess.run([h5_python, str(ADAPTERS / "read_hdf5.py"),
                            str(work / "h5_requests.json")], capture_output=True, text=True,
                           timeout=300)
        if p.returncode != 0:
            msg = (p.stderr.strip().splitlines() or ["?"])[-1]
            failed.update({q["name"]: f"read_hdf5: {msg}" for q in requests})
        else:
            for q in requests:
                a = np.load(q["out"])
                if q["name"].startswith("sunsided"):
                    out[q["name"]] = a[1:4].T * GAUSS_nT          # rows: time, x, y, z (gauss)
                else:
                    out[q["name"]] = a[::BROAD_DECIMATION] * uT_nT  # imu_mag (uT)
    ck = REALDATA / "ck_explorer" / "acc_mag_log.csv"
    try:
        a = np.loadtxt(ck, delimiter=",", skiprows=1)
        out["ck_explorer"] = a[:, 3:6] * GAUSS_nT                  # mx, my, mz (gauss)
    except OSError as e:
        failed["ck_explorer"] = str(e)
    for name in list(out):
        x = out[name]
        out[name] = x[np.all(np.isfinite(x), axis=1)]
    return {k: out[k] for k in REAL_RECORDINGS if k in out}, failed


def heldout_folds(n) -> tuple[np.ndarray, np.ndarray]:
    block = np.arange(n) * HELDOUT_BLOCKS // n
    a = block % 2 == 0
    return a, ~a


def nominal_magnitude_nT(x) -> float:
    """Stand-in for the local field magnitude a user would enter, in the readings' raw
    scale: the radius of the sphere with the volume of the algebraic ellipsoid of the
    readings, 1 / det(M)^(1/3) for M mapping it to the unit sphere (the RMS distance from
    the mean if no ellipsoid fits). The held-out score is scale-free; the magnitude only
    sets the scale of our fitter's relative uncertainty checks."""
    try:
        _, M, _ = algebraic_ellipsoid(x, 1.0)
        return float(np.linalg.det(M) ** (-1.0 / 3.0))
    except (InputError, np.linalg.LinAlgError):
        return float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))


def real_cases(recordings: dict) -> list:
    """Two cases per recording: fit on fold A (even time blocks), score on fold B, and
    the reverse; the magnitude given to methods that take one is nominal_magnitude_nT of
    the fit half."""
    cases = []
    for name, x in recordings.items():
        a, b = heldout_folds(len(x))
        for fold, (fit_mask, test_mask) in (("A", (a, b)), ("B", (b, a))):
            xf = x[fit_mask]
            R = nominal_magnitude_nT(xf)
            cases.append(EllipsoidCase(id=f"real-{name}-{fold}", condition=name, sensor=fold,
                                       readings_nT=xf, ref_norm_nT=R, heldout_nT=x[test_mask]))
    return cases


# ---------------------------------------------------------------------------------------
# thermal campaigns (reference vectors in the jig) for the temperature-model variants
# ---------------------------------------------------------------------------------------
@dataclass
class ThermalCase:
    id: str
    condition: str
    sensor: str
    fit_data: object                 # generator.fit.thermal.FitData, all samples usable
    W_poly: np.ndarray               # (k, 3, 3) truth, polynomials in T - t_ref
    b_poly_nT: np.ndarray            # (k, 3)
    t_ref_C: float
    B_frame_nT: np.ndarray           # (N, 3) true field in the frame (jig: body)
    label: str = ""                  # data column of the per-sensor table


def fm1_thermal_cases() -> list:
    unit = load_unit(FM1 / "unit.toml")
    truth = load_truth(FM1 / "truth.json")
    npz = np.load(FM1 / "thermal_12pos.truth.npz")
    tel = read_telemetry(FM1 / "thermal_12pos.csv", unit)
    data = preprocess(tel, unit)
    out = []
    for spec in unit.sensors:
        s = truth["sensors"][spec.name]
        out.append(ThermalCase(f"fm1-thermal-{spec.name}", "samsat_fm1 thermal_12pos.csv",
                               spec.name, fit_data_from(tel, data[spec.name], unit),
                               s["W_poly"], s["b_poly_nT"], truth["t_ref_C"],
                               npz["b_body_nT"], label="samsat_fm1"))
    return out


def simulator_thermal_cases(seeds, work: Path) -> list:
    unit = sim.make_example_unit()
    out = []
    for seed in seeds:
        truth = sim.random_truth(unit, np.random.default_rng([seed, 0]))
        name = f"thermal_s{seed}"
        _, arr = sim.simulate_campaign("thermal_12pos", unit, truth,
                                       np.random.default_rng([seed, 3]), work, name=name,
                                       **sim.EXAMPLE_SIZES["example"]["thermal_12pos"])
        tel = read_telemetry(work / f"{name}.csv", unit)
        data = preprocess(tel, unit)
        for spec in unit.sensors:
            st = truth.sensors[spec.name]
            out.append(ThermalCase(f"sim-thermal-s{seed}-{spec.name}",
                                   "simulator thermal_12pos (example size)",
                                   spec.name, fit_data_from(tel, data[spec.name], unit),
                                   st.W_poly_frame, st.b_poly_frame_nT, truth.t_ref_C,
                                   arr["b_body_nT"], label=f"simulator seed {seed}"))
    return out
