"""Review fault 6 of issue 16: every coefficient in coefficients.json has an honest
1-sigma. The SET/RESET compensation's c (sr_comp_s_per_deg) and the boom alignment H get
one; the temperature terms a constant model did not fit are not reported as known to
0 +- 0 (they get the part's prior 1-sigma, and the observability says so)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.fit.reference import PART_PRIOR_SIGMA
from generator.pipeline import rotation_sigma


def test_constant_model_temperature_terms_have_the_prior_sigma(tmp_path):
    from test_temp_extrapolation import _one_temperature_fit
    j, _ = _one_temperature_fit(tmp_path)
    u = j["uncertainty_1sigma"]["mpu"]
    bs, Ms = np.asarray(u["b_poly_nT"]), np.asarray(u["M_poly"])
    prior = PART_PRIOR_SIGMA["default"]
    assert np.all(bs[0] > 0) and np.all(Ms[0] > 0)
    for k in range(1, bs.shape[0]):
        assert np.all(bs[k] == prior["b_nT"][k]) and np.all(Ms[k] == prior["M"][k]), k
    obs = j["fit"]["sensors"]["mpu"]["stats"]["observability"]
    assert "not fitted" in obs["temperature_terms"]
    # the degree-0 figures are the fit's own, not inflated by the unfitted terms
    assert j["fit"]["sensors"]["mpu"]["stats"]["predicted_error"]["field_error_nT"] < 150


def test_set_reset_c_has_a_sigma(tmp_path):
    from test_sr_fit_order import LSB_NT, NOISE_NT, ZERO, _turntable
    from generator.io.icd_write import write_unit_toml
    from generator.pipeline import fit
    rng = np.random.default_rng(5)
    unit = write_unit_toml(tmp_path / "unit.toml", "turntable", [
        {"name": "mmc", "part": "MMC5883MA", "frame": "body", "axes": ["+x", "+y", "+z"],
         "lsb_nT": LSB_NT, "zero_count": ZERO, "set_reset": True, "noise_nT": NOISE_NT}],
        unit_keys={"lab_field_nT": 50000.0})
    _turntable(tmp_path / "t.csv", rng, np.eye(3), np.zeros(3), np.zeros(3))
    cs = fit(unit, [tmp_path / "t.csv"])
    c = float(cs.sensors["mmc"]["sr_comp_s_per_deg"])
    sig = float(cs.uncertainty["mmc"]["sr_comp_s_per_deg"])
    # the RMS distance to the c of the part's four measurement times (by hand)
    cs_all = [(t + 1.0) * 1e-3 / 2 * np.pi / 180 for t in (10.0, 5.0, 2.5, 1.6)]
    assert sig == pytest.approx(np.sqrt(np.mean([(x - c) ** 2 for x in cs_all])), rel=1e-12)
    assert 0 < sig < c
    cs.save(tmp_path / "c.json")
    j = json.loads((tmp_path / "c.json").read_text())
    assert j["uncertainty_1sigma"]["mmc"]["sr_comp_s_per_deg"] == pytest.approx(sig)


def test_rotation_sigma_matches_monte_carlo():
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(9)
    H = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    A = rng.normal(size=(3, 3)) * 1e-3
    cov = A @ A.T
    d = rng.multivariate_normal(np.zeros(3), cov, size=40000)
    Hs = Rotation.from_rotvec(d).as_matrix() @ H
    mc = Hs.std(axis=0)
    # 40000 draws: the sample std is within ~4 * 1/sqrt(2 * 40000) = 1.4 % of the true one
    # (second-order terms of exp are ~|d|^2 ~ 1e-6, negligible)
    np.testing.assert_allclose(rotation_sigma(H, cov), mc, rtol=0.02)


def test_boom_sensors_carry_the_sigma_of_H(tmp_path):
    from generator.campaign.simulate import make_example
    from generator.cli import main
    paths = make_example(tmp_path / "ex", seed=3, size="fast")
    out = tmp_path / "fit"
    assert main(["fit", str(paths["unit"]), str(paths["rotation"]), "-o", str(out),
                 "-q"]) == 0
    j = json.loads((out / "coefficients.json").read_text())
    boom = [s["name"] for s in j["unit"]["sensors"] if s["frame"] == "boom"]
    assert boom
    al = j["fit"]["alignment"]
    cov = np.asarray(al["cov_rad2"])
    H = np.asarray(j["unit_coefficients"]["H_boom_to_body"])
    for n in boom:
        sH = np.asarray(j["uncertainty_1sigma"][n]["H_boom_to_body"])
        np.testing.assert_allclose(sH, rotation_sigma(H, cov), rtol=1e-12)
        assert np.all(sH[~np.eye(3, dtype=bool)] > 0)
