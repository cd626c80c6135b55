"""In-flight recalibration (issue 18): orbit telemetry with only a TLE or a GNSS position
(no ref_* column), the ground calibration as the prior, `magcal fit` through cli.main;
the new calibration is judged on a HELD-OUT orbit campaign of the same changed unit.

Done-when criterion: the |B| residual against the field model is within 1.2x of the
floor a perfect calibration would leave, sqrt(noise^2 + model^2) per sensor:
noise = the sensor's per-axis noise as the fit sees it (fit.samples.field_noise_nT; a
perfect calibration leaves exactly that along the field direction), model = the rms of
|B_true| - |B_IGRF| the simulator put into that campaign (crustal and external field).
The 1.2 is the issue's; nothing here was adjusted to the results.

Seeds. Development (the only draws looked at while writing simulate_orbit and the glue):
unit seed 11, orbit seed 111, held-out seed 999. The draws below (unit seeds 21 and 23,
orbit and held-out seeds from SeedSequence(seed) children) were first run when this
file was complete.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate_orbit as so
from generator.campaign.simulate import load_truth, make_example, make_example_unit
from generator.cli import main
from generator.fit.samples import field_noise_nT
from generator.flight.coeffs import CoefficientSet
from generator.io.orbit import KP_DISTURBED
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit
from generator.trace.coefficients import calibrated_field64
from generator.verbs.uplink import make_uplink

DONE_WHEN_RATIO = 1.2          # issue 18: within 1.2x of the combined noise and model floor


def _ground(tmp_path_factory, seed):
    d = tmp_path_factory.mktemp(f"ground{seed}")
    paths = make_example(d, seed=seed, size="example")
    assert main(["fit", str(paths["unit"]), str(paths["thermal_12pos"]),
                 str(paths["rotation"]), str(paths["coils"]), "-o", str(d / "fit"), "-q"]) == 0
    return d, d / "fit" / "coefficients.json"


def _residuals(cs, campaign):
    """Per sensor: (rms |B_cal| - |B_model|, floor, rms |B_cal| - |B_true|) over the
    quiet samples (Kp below the threshold) of a campaign."""
    unit = load_unit(campaign["unit"])
    tel = read_telemetry(campaign["csv"], unit)
    A = campaign["arrays"]
    out = {}
    for s in unit.sensors:
        idx, B = calibrated_field64(cs, tel, s.name)
        quiet = A["kp_index"][idx] < KP_DISTURBED
        n = np.linalg.norm(B, axis=1)[quiet]
        model = A["model_norm_nT"][idx][quiet]
        true = A["true_norm_nT"][idx][quiet]
        model_rms = float(np.sqrt(np.mean((true - model) ** 2)))
        out[s.name] = (float(np.sqrt(np.mean((n - model) ** 2))),
                       float(np.hypot(field_noise_nT(s), model_rms)),
                       float(np.sqrt(np.mean((n - true) ** 2))))
    return out


CASES = {
    # ISS TLE, SGP4 positions, half a day after the TLE epoch (2008)
    "iss_tle": dict(seed=21, position="tle", tle=so.ISS_TLE, storm=None),
    # Vanguard 1 (elliptical, 650 - 3,800 km), GNSS lat/lon/alt columns, another epoch
    # (2000), and a disturbed interval flagged by kp_index that must be left out
    "vanguard_gnss_storm": dict(seed=23, position="gnss", tle=so.VANGUARD1_TLE,
                                storm=(7200.0, 5400.0, 400.0, 6.0)),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def recal(request, tmp_path_factory):
    case = CASES[request.param]
    d, ground = _ground(tmp_path_factory, case["seed"])
    unit = make_example_unit()
    truth = load_truth(d / "truth.json", unit)
    ss_change, ss_orbit, ss_hold = np.random.SeedSequence(case["seed"]).spawn(3)
    changed, shifts = so.post_launch(truth, rng=np.random.default_rng(ss_change))
    effects = ()
    opts = dict(tle=case["tle"], storm=case["storm"], duration_s=6 * 3600.0)
    fit_on = so.simulate_orbit(unit, changed, np.random.default_rng(ss_orbit), d / "orbit",
                               position=case["position"], effects=effects, **opts)
    held = so.simulate_orbit(unit, changed, np.random.default_rng(ss_hold), d / "held",
                             position=case["position"], effects=effects,
                             **{**opts, "duration_s": 3 * 3600.0})
    out = d / "recal"
    assert main(["fit", str(fit_on["unit"]), str(fit_on["csv"]), "--prior", str(ground),
                 "-o", str(out), "-q"]) == 0
    return {"ground": CoefficientSet.load(ground),
            "new": CoefficientSet.load(out / "coefficients.json"),
            "held": held, "fit_on": fit_on, "shifts": shifts}


def test_recalibrates_to_the_noise_and_model_floor(recal):
    after = _residuals(recal["new"], recal["held"])
    for name, (rms, floor, _) in after.items():
        assert rms <= DONE_WHEN_RATIO * floor, (name, rms, floor)


def test_the_ground_calibration_no_longer_fits(recal):
    """The post-launch shift (200 - 1500 nT per axis) is what the recalibration removes:
    with the ground calibration the low-noise MMC5883 sensors are far above the floor."""
    before = _residuals(recal["ground"], recal["held"])
    for name in ("mmc1", "mmc2"):
        rms, floor, _ = before[name]
        assert rms > 3 * floor, (name, rms, floor)


def test_provenance_and_floor_in_the_fit_info(recal):
    info = recal["new"].fit_info
    (prov,) = info["field_reference"].values()
    assert prov["model"] == "IGRF-14" and prov["package"] == "ppigrf"
    assert ("SGP4" in prov["position_source"]) == (recal["fit_on"]["unit"].read_text()
                                                   .count("tle = ") == 1)
    assert any("cannot go below" in n for n in info["notes"])


def test_disturbed_samples_left_out(recal):
    (prov,) = recal["new"].fit_info["field_reference"].values()
    kp = recal["fit_on"]["arrays"]["kp_index"]
    assert prov.get("kp_left_out", 0) == int(np.sum(kp >= KP_DISTURBED))


def test_uplink_of_what_changed(recal):
    up = make_uplink(recal["ground"], recal["new"], onboard_serial=7, chunk_bytes=128)
    s = up["summary"]
    assert s["same_layout"] and s["new_serial"] == 8
    changed = {c.block for c in up["changes"] if c.block}
    assert "b_poly_nT" in changed           # the shifted offsets are in the diff
    assert "K_nT_per_A" not in changed      # the ground's coil coupling is kept
    assert all(len(p) <= 128 for p in up["parts"]) and s["parts"] == len(up["parts"])


def test_uplink_through_magcal_table(recal, tmp_path, capsys):
    """The same uplink from the command line (docs/orbit.md): both tables, the new one
    in parts, and the diff named by the new set's chain."""
    gj, nj = tmp_path / "ground.json", tmp_path / "new.json"
    recal["ground"].save(gj)
    recal["new"].save(nj)
    assert main(["table", str(gj), "-o", str(tmp_path / "onboard.bin"), "--serial", "1",
                 "-q"]) == 0
    assert main(["table", str(nj), "-o", str(tmp_path / "new.bin"), "--serial", "2",
                 "--chunk", "200", "-q"]) == 0
    assert sorted(p.name for p in tmp_path.glob("new.part*.bin"))[0] == "new.part000.bin"
    capsys.readouterr()
    assert main(["table", "--diff", str(tmp_path / "onboard.bin"), str(tmp_path / "new.bin"),
                 "--coeffs", str(nj)]) == 0
    out = capsys.readouterr().out
    assert "header table_serial: 1 -> 2" in out and "b_poly_nT[0]" in out
