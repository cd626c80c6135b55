"""Review fault 2 of issue 16: a reference in another frame by a proper rotation (ENU
against NED data: x and y swapped, z negated; det +1, so not the reflection that
fit.sanity refuses) must not give exit 0 with M held at the prior and a residual the
size of the field. fit.goodness refuses it (exit 2, one line naming the file and the
likely cause) unless the caller accepts the misfit; the right frame passes.

The unit and its data are written here: one MPU-9255 (counts), twelve static positions
plus a slow tumble, a reference vector per sample (a rig: exact), 25 degC.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.io.icd_write import write_telemetry_csv, write_unit_toml

LSB = 150.0
NOISE = 300.0
FIELD = 49000.0


def _unit(tmp_path):
    return write_unit_toml(tmp_path / "unit.toml", "framecheck", [
        {"name": "mpu", "part": "MPU-9255", "frame": "body", "axes": ["+x", "+y", "+z"],
         "lsb_nT": LSB, "zero_count": 0, "set_reset": False, "noise_nT": NOISE}],
        unit_keys={"lab_field_nT": FIELD})


def _data(path, rng, enu=False):
    from scipy.spatial.transform import Rotation
    n = 1200
    R = Rotation.random(n, random_state=np.random.RandomState(rng.integers(2**31)))
    B = R.apply(FIELD * np.array([0.35, 0.05, 0.935]) / np.linalg.norm([0.35, 0.05, 0.935]))
    W = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    b = rng.normal(0, 2000.0, 3)
    x = B @ W.T + b + rng.normal(0, NOISE, (n, 3))
    c = np.round(x / LSB)
    ref = np.stack([B[:, 1], B[:, 0], -B[:, 2]], axis=1) if enu else B
    cols = {"time_s": np.arange(n) * 0.1}
    for k, a in enumerate("xyz"):
        cols[f"mpu_{a}"] = c[:, k]
    cols["mpu_temp_C"] = np.full(n, 25.0)
    for k, a in enumerate("xyz"):
        cols[f"ref_{a}_nT"] = ref[:, k]
    return write_telemetry_csv(path, cols, meta={"unit": "framecheck"})


def test_enu_reference_is_refused_with_one_line(tmp_path, capsys):
    from generator.cli import main
    unit = _unit(tmp_path)
    data = _data(tmp_path / "enu.csv", np.random.default_rng(21), enu=True)
    rc = main(["fit", str(unit), str(data), "-o", str(tmp_path / "fit"), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1
    assert "enu.csv" in err and "another frame" in err and "ENU" in err
    assert not (tmp_path / "fit").exists()


def test_right_frame_passes_and_says_how_well(tmp_path):
    from generator.pipeline import fit
    unit = _unit(tmp_path)
    data = _data(tmp_path / "ned.csv", np.random.default_rng(21))
    cs = fit(unit, [data])
    gof = cs.fit_info["sensors"]["mpu"]["stats"]["goodness_of_fit"]
    assert not gof["refuse"]
    # the residual is the reading noise (a rig reference is exact): chi2 per dof against
    # the generous reference allowance is far below 1
    assert gof["rms_vector_per_axis_nT"] < 1.5 * NOISE
    assert gof["chi2_per_dof"] < 0.1


def test_the_caller_may_accept_the_misfit(tmp_path):
    from generator.pipeline import fit
    unit = _unit(tmp_path)
    data = _data(tmp_path / "enu.csv", np.random.default_rng(21), enu=True)
    msgs = []
    cs = fit(unit, [data], accept_misfit=True, progress=msgs.append)
    gof = cs.fit_info["sensors"]["mpu"]["stats"]["goodness_of_fit"]
    assert gof["refuse"] and gof["chi2_per_dof"] > gof["limit"]
    assert any("accepted" in m and "another frame" in m for m in msgs)


def test_threshold_is_the_chi_square_quantile():
    """The limit is chi2_{3 N_eff}(1 - alpha) / (3 N_eff): for white residuals N_eff is N,
    and a residual exactly at the stated sigma gives chi2/dof ~ 1, below the limit."""
    from scipy.stats import chi2
    from generator.fit.calibration import SensorCalibration
    from generator.fit.goodness import MISFIT_ALPHA, REF_ANGLE_SIGMA_DEG, vector_misfit
    from generator.fit.samples import _Samples
    rng = np.random.default_rng(3)
    n = 3000
    B = rng.normal(size=(n, 3))
    B *= FIELD / np.linalg.norm(B, axis=1)[:, None]
    sig = np.sqrt(NOISE ** 2 + (2 / 3) * (np.radians(REF_ANGLE_SIGMA_DEG) * FIELD) ** 2
                  + 0.02 ** 2 * FIELD ** 2 / 3)
    x = B + rng.normal(0, sig, (n, 3))
    S = _Samples(x, np.full(n, 25.0), B, np.full(n, FIELD), np.ones(n, bool),
                 np.zeros(n, int), file_id=np.zeros(n, int), noise_nT=NOISE)
    cal = SensorCalibration.constant("s", np.zeros(3), np.eye(3), body_frame=True)
    g = vector_misfit(cal, S)
    assert abs(g["chi2_per_dof"] - 1) < 5 * np.sqrt(2 / (3 * n))
    assert g["n_eff"] == pytest.approx(n, rel=0.1)
    dof = 3 * g["n_eff"]
    assert g["limit"] == pytest.approx(chi2.ppf(1 - MISFIT_ALPHA, dof) / dof, rel=1e-12)
    assert not g["refuse"]
    S.x = B + rng.normal(0, 2 * sig, (n, 3))        # twice the stated error: refused
    assert vector_misfit(cal, S)["refuse"]
