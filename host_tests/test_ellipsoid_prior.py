"""Review fault 3 of issue 16: `--prior coefficients.json` on the ellipsoid (magnitude-only)
path. What the magnitudes do not determine is held at the prior, and every coefficient
says whether it came from the data or the prior (fit.ellipsoid_prior).

A one-sensor unit written here (an MPU-9255), the simulator's truth for it; a ground
calibration from a turntable with a wide wobble (the whole sphere nearly), then a
near-planar rotation (about body y, wobble under 2 deg) fitted from magnitudes only.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign.simulate import random_truth, simulate_campaign
from generator.cli import main
from generator.io.icd_write import write_unit_toml
from generator.io.unitfile import load_unit


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("ellprior")
    write_unit_toml(d / "unit.toml", "ellprior", [
        {"name": "mpu", "part": "MPU-9255", "frame": "body", "axes": ["+x", "+y", "+z"],
         "lsb_nT": 150.0, "zero_count": 0, "set_reset": False, "noise_nT": 300.0}],
        unit_keys={"lab_field_nT": 51540.0})
    unit = load_unit(d / "unit.toml")
    truth = random_truth(unit, np.random.default_rng(33))
    ground, _ = simulate_campaign("planar_rotation", unit, truth, np.random.default_rng(34),
                                  d, name="ground", wobble_deg=70.0, duration_s=200.0,
                                  rate_dps=10.0)
    flat, _ = simulate_campaign("planar_rotation", unit, truth, np.random.default_rng(35),
                                d, name="flat", wobble_deg=1.0, duration_s=200.0,
                                rate_dps=10.0)
    assert main(["fit", str(d / "unit.toml"), str(ground), "-o", str(d / "g"), "-q",
                 "--method", "ellipsoid"]) == 0
    return d, unit, truth, ground, flat


def _obs(path):
    j = json.loads(path.read_text())
    return j, {p["name"]: p for p in
               j["fit"]["sensors"]["mpu"]["stats"]["observability"]["parameters"]}


def test_ground_fit_has_every_coefficient_from_the_data(setup):
    d, *_ = setup
    _, obs = _obs(d / "g" / "coefficients.json")
    assert len(obs) == 9
    assert all(p["source"] == "data" for p in obs.values()), obs


def test_flat_rotation_without_a_prior_is_refused(setup, tmp_path, capsys):
    d, _, _, _, flat = setup
    assert main(["fit", str(d / "unit.toml"), str(flat), "-o", str(tmp_path / "o"), "-q",
                 "--method", "ellipsoid"]) == 2
    assert "ellipsoid fit" in capsys.readouterr().err   # not determined: exit 2 as before


def test_flat_rotation_with_the_ground_prior_holds_the_axis_at_it(setup, tmp_path):
    d, unit, truth, _, flat = setup
    prior = d / "g" / "coefficients.json"
    assert main(["fit", str(d / "unit.toml"), str(flat), "-o", str(tmp_path / "o"), "-q",
                 "--method", "ellipsoid", "--prior", str(prior)]) == 0
    j, obs = _obs(tmp_path / "o" / "coefficients.json")
    gj = json.loads(prior.read_text())
    st = j["fit"]["sensors"]["mpu"]["stats"]["observability"]
    assert "coefficients.json" in st["prior_source"]
    held = {n for n, p in obs.items() if p["source"] == "prior"}
    data = {n for n, p in obs.items() if p["source"] == "data"}
    # the offset along the turntable axis (body y) is what a planar rotation cannot see
    assert "b0_y" in held, obs
    assert {"b0_x", "b0_z"} <= data, obs
    assert st["unobservable"] and all(abs(u["offset_from_prior"]) < 1e-6
                                      for u in st["unobservable"])
    b = np.asarray(j["sensors"]["mpu"]["b_poly_nT"])[0]
    bg = np.asarray(gj["sensors"]["mpu"]["b_poly_nT"])[0]
    # held: b_y is the prior's (to the rounding of the held direction's mix, 1e-6 sigma)
    assert abs(b[1] - bg[1]) < 1.0, (b, bg)
    # the data's offsets are the truth's within 5 of their stated sigma (plus the
    # truth's and ground fit's own: both small against a 300 nT sensor)
    T = np.mean(j["fit"]["sensors"]["mpu"]["stats"]["temperature_range_C"])
    bt = truth.sensors["mpu"].b(T - truth.t_ref_C)
    sig = np.asarray(j["uncertainty_1sigma"]["mpu"]["b_poly_nT"])[0]
    sig_g = np.asarray(gj["uncertainty_1sigma"]["mpu"]["b_poly_nT"])[0]
    assert np.all(sig > 0) and np.all(np.isfinite(sig))
    # held: its sigma is the prior's at the data's temperature, sqrt(sum_k s_k^2 dT^2k)
    # (the ground fit's polynomial 1-sigma; its unfitted degrees carry the part's)
    sig_poly = np.asarray(gj["uncertainty_1sigma"]["mpu"]["b_poly_nT"])
    dT = T - float(gj["sensors"]["mpu"]["t_ref_C"])
    held_sig = np.sqrt(np.sum(sig_poly[:, 1] ** 2 * dT ** (2 * np.arange(len(sig_poly)))))
    assert sig[1] == pytest.approx(held_sig, rel=0.05)
    # fitted: within 5 sigma of the truth (5 sigma: a two-sided 6e-7 tail per axis)
    for k in (0, 2):
        assert abs(b[k] - bt[k]) < 5 * sig[k], (k, b, bt, sig)
    # held: as close to the truth as the ground calibration is
    assert abs(b[1] - bt[1]) < 5 * held_sig, (b, bt, held_sig)
