"""Issue 3 acceptance: the whole measurement chain of seed 000 on the shared unit.

Fit on the ground campaigns (thermal twelve positions, rotation for H, coils for K), then
`magcal apply` (the flight C through cffi) on coils.csv and on flight_6h.csv (coils
switching): per sensor |B| RMS against the truth within 1.15x of what the true parameters
give, and the angle between the mmc2 output and the true body-frame field within 1.15x
of the angle the true parameters give. The true parameters are applied to the CSV's counts
by the ICD's mapping in host_tests/truth_icd.py, not by the project's preprocessing (a
wrong mapping there must not move the baseline). 1.15 stays: the fit comes from other
campaigns (out of sample), so its parameter error, not only the noise, is in the ratio.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.io import truth as truth_mod
from generator.cli import main
from generator.io.unitfile import load_unit
from test_cli import read_apply_csv
from truth_icd import (icd_frame_field, load_truth_json, read_csv, true_parameters_field,
                       unit_sensors)

COILS = ["coil_x_A", "coil_y_A", "coil_z_A"]


def rms_angle_deg(B, B_true) -> float:
    cos = np.sum(B * B_true, axis=1) / np.linalg.norm(B, axis=1) / np.linalg.norm(B_true, axis=1)
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))


@pytest.fixture(scope="module")
def ground_fit(tmp_path_factory, fm1_dir):
    out = tmp_path_factory.mktemp("ground_fit")
    files = [str(fm1_dir / f) for f in ("thermal_12pos.csv", "rotation.csv", "coils.csv")]
    assert main(["fit", str(fm1_dir / "unit.toml"), *files, "-o", str(out), "-q"]) == 0
    return out / "coefficients.json"


@pytest.mark.parametrize("campaign,deployed", [("coils", False), ("flight_6h", True)])
def test_apply_through_the_flight_chain_is_within_1p15_of_the_truth(
        campaign, deployed, ground_fit, fm1_dir, tmp_path):
    out_csv = tmp_path / f"{campaign}.out.csv"
    args = ["apply", str(ground_fit), str(fm1_dir / f"{campaign}.csv"), "-o", str(out_csv), "-q"]
    if not deployed:
        args += ["--boom-stowed", "--at-rest"]    # the coil campaign: the jig stands still
    assert main(args) == 0
    got = read_apply_csv(out_csv)
    unit = load_unit(fm1_dir / "unit.toml")
    cols = read_csv(fm1_dir / f"{campaign}.csv")
    specs = unit_sensors(fm1_dir / "unit.toml")
    truth = load_truth_json(fm1_dir / "truth.json")
    H_true = np.asarray(truth["H_boom_to_body"])
    b_true = np.load(fm1_dir / f"{campaign}.truth.npz")["b_body_nT"]
    coil = np.stack([cols[c] for c in COILS], axis=1)
    assert np.count_nonzero(coil) > 0.2 * coil.size / 3   # the coils do switch
    lines = []
    for s in unit.sensors:
        B = np.stack([got[f"{s.name}_{a}_nT"] for a in "xyz"], axis=1)
        valid = got[f"{s.name}_valid"] == 1
        assert valid.mean() > 0.99, (s.name, valid.mean())
        B_tp = true_parameters_field(truth, s.name, icd_frame_field(cols, specs[s.name]),
                                     cols[f"{s.name}_temp_C"], coil_A=coil)
        if s.frame == "boom" and deployed:
            B_tp = B_tp @ H_true.T
        ours = truth_mod.rms_norm_error(B[valid], b_true[valid])
        best = truth_mod.rms_norm_error(B_tp[valid], b_true[valid])
        lines.append(f"{campaign} {s.name}: |B| RMS ours {ours:.1f} nT, true parameters "
                     f"{best:.1f} nT ({ours / best:.3f})")
        assert ours <= 1.15 * best, "\n".join(lines)
        if s.name == "mmc2":
            a_ours = rms_angle_deg(B[valid], b_true[valid])
            a_best = rms_angle_deg(B_tp[valid], b_true[valid])
            lines.append(f"{campaign} mmc2 angle to the true body field: ours {a_ours:.4f} deg, "
                         f"true parameters {a_best:.4f} deg ({a_ours / a_best:.3f})")
            assert a_ours <= 1.15 * a_best, "\n".join(lines)
    # the attitude system gets the boom MMC5883 vector, confirmed by the others
    assert set(got["sel_sensor"]) == {"mmc2"}
    assert set(got["sel_reason"]) == {"CONFIRMED"}
    print("\n".join(lines))


def test_without_the_coil_coupling_flight_is_worse(ground_fit, fm1_dir, tmp_path):
    """The coil term matters on flight_6h: zero K and the error grows (the test above is
    not passing by accident)."""
    import json

    d = json.loads(ground_fit.read_text())
    for s in d["sensors"].values():
        s["K_nT_per_A"] = [[0.0] * 3 for _ in range(3)]
    no_k = tmp_path / "no_k.json"
    no_k.write_text(json.dumps(d))
    errs = {}
    for name, coeffs in (("with K", ground_fit), ("without K", no_k)):
        out = tmp_path / f"{name}.csv"
        assert main(["apply", str(coeffs), str(fm1_dir / "flight_6h.csv"), "-o", str(out),
                     "-q"]) == 0
        got = read_apply_csv(out)
        b_true = np.load(fm1_dir / "flight_6h.truth.npz")["b_body_nT"]
        B = np.stack([got[f"mmc1_{a}_nT"] for a in "xyz"], axis=1)
        errs[name] = truth_mod.rms_norm_error(B, b_true)
    assert errs["without K"] > 1.5 * errs["with K"], errs


def test_fit_report_has_the_seed_000_chain_results(ground_fit):
    """Issue 3: the before/after tables of H and the coils, the coil interference by
    distance beside the seed's figures and the SET/RESET error maps are in the report."""
    out = ground_fit.parent
    md = (out / "report.md").read_text()
    for title in ("Agreement of the two magnetometers: figures of merit",
                  "Magnetorquer interference at 0.1 A",
                  "Magnetorquer interference against distance",
                  "SET/RESET offset error while turning"):
        assert f"## {title}" in md, title
    assert "seed 000, after" in md and "167.9" in md and "307.6" in md
    for png in ("coil_distance.png", "setreset_error_maps.png"):
        assert (out / png).stat().st_size > 10_000, png
