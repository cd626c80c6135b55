"""The `magcal` command end to end, as a user runs it (ICD section 3)."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest

from generator.io import truth as truth_mod
from generator.cli import main
from generator.io.unitfile import load_unit
from truth_icd import (icd_frame_field, load_truth_json, ratio_bound, read_csv,
                       true_parameters_field, unit_sensors)


def read_apply_csv(path) -> dict:
    with open(path) as f:
        rows = [r for r in csv.reader(line for line in f if not line.startswith("#"))]
    header, body = rows[0], rows[1:]
    cols = {}
    for j, name in enumerate(header):
        if name in ("sel_sensor", "sel_reason"):
            cols[name] = np.array([r[j] for r in body])
        else:
            cols[name] = np.array([float(r[j]) if r[j] != "" else np.nan for r in body])
    return cols


@pytest.fixture(scope="module")
def fm1_fit(tmp_path_factory, fm1_dir):
    out = tmp_path_factory.mktemp("fit")
    assert main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
                 "-o", str(out), "-q"]) == 0
    return out


@pytest.mark.parametrize("campaign,fit_files", [
    ("thermal_12pos", ["thermal_12pos.csv"]),
    ("rotation", ["rotation.csv"]),
])
def test_fit_then_apply_is_at_the_truth_floor(campaign, fit_files, fm1_dir, tmp_path):
    """Issue 2 acceptance: fit a campaign, apply the result to the same file through the
    flight C; per sensor the |B| RMS error against the truth is at most what the true
    parameters give on the same raw data times truth_icd.ratio_bound (1 + z / sqrt(2N),
    z Bonferroni over the 10 ratios here: 1.013 for 36000 samples, 1.042 for 4000; was
    1.15). The true parameters are applied to the CSV's counts by the ICD's mapping
    (host_tests/truth_icd.py), not by the project's preprocessing. float32 rounding of the
    C output (~1e-7 x 50000 nT) is far below the noise."""
    unit_path = fm1_dir / "unit.toml"
    assert main(["fit", str(unit_path), *[str(fm1_dir / f) for f in fit_files],
                 "-o", str(tmp_path / "fit"), "-q"]) == 0
    out_csv = tmp_path / "out.csv"
    data = fm1_dir / f"{campaign}.csv"
    assert main(["apply", str(tmp_path / "fit" / "coefficients.json"), str(data),
                 "-o", str(out_csv), "-q"]) == 0
    got = read_apply_csv(out_csv)
    unit = load_unit(unit_path)
    cols, specs = read_csv(data), unit_sensors(unit_path)
    truth = load_truth_json(fm1_dir / "truth.json")
    b_true_body = np.load(fm1_dir / f"{campaign}.truth.npz")["b_body_nT"]
    report = []
    for s in unit.sensors:
        B = np.stack([got[f"{s.name}_{a}_nT"] for a in "xyz"], axis=1)
        valid = got[f"{s.name}_valid"] == 1
        assert valid.mean() > 0.99, f"{s.name}: only {valid.mean():.1%} valid"
        ours = truth_mod.rms_norm_error(B[valid], b_true_body[valid])
        B_truth = true_parameters_field(truth, s.name, icd_frame_field(cols, specs[s.name]),
                                        cols[f"{s.name}_temp_C"])
        best = truth_mod.rms_norm_error(B_truth[valid], b_true_body[valid])
        bound = ratio_bound(int(valid.sum()), 10)
        report.append(f"{s.name}: ours {ours:.1f} nT, true parameters {best:.1f} nT, "
                      f"ratio {ours / best:.4f} (bound {bound:.4f})")
        assert ours <= bound * best, "\n".join(report)
    print("\n".join(report))


def test_apply_output_columns_follow_the_icd(fm1_fit, fm1_dir, tmp_path):
    out_csv = tmp_path / "coils_out.csv"
    assert main(["apply", str(fm1_fit / "coefficients.json"), str(fm1_dir / "coils.csv"),
                 "-o", str(out_csv), "-q"]) == 0
    got = read_apply_csv(out_csv)
    names = list(got)
    assert names[0] == "time_s"
    for s in ["mmc1", "mpu1", "mpu2", "mmc2", "mpu3"]:
        for c in (f"{s}_x_nT", f"{s}_y_nT", f"{s}_z_nT", f"{s}_valid"):
            assert c in names
        assert set(np.unique(got[f"{s}_valid"])) <= {0.0, 1.0}


def test_fit_writes_coefficients_and_a_report(fm1_fit):
    assert (fm1_fit / "coefficients.json").stat().st_size > 0
    assert (fm1_fit / "report.html").stat().st_size > 0
    assert (fm1_fit / "report.md").stat().st_size > 0


@pytest.mark.parametrize("mutate,expect", [
    (lambda t: t.replace("34701,30570", "34701,abc", 1), "not a number"),
    (lambda t: t.replace("\n5,1,", "\n-5,1,", 1), "backwards"),
    (lambda t: t.replace("mmc1_temp_C", "mmc1_temperature", 1), "mmc1_temp_C"),
])
def test_bad_input_exit_2_with_one_line(mutate, expect, fm1_dir, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(mutate((fm1_dir / "thermal_12pos.csv").read_text()))
    code = main(["fit", str(fm1_dir / "unit.toml"), str(bad), "-o", str(tmp_path / "o"), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and str(bad) in err and expect in err, err
    assert not (tmp_path / "o" / "coefficients.json").exists()


def test_missing_file_exit_2(tmp_path, capsys):
    code = main(["generate", str(tmp_path / "nope.json"), "-o", str(tmp_path / "o")])
    assert code == 2
    assert "nope.json" in capsys.readouterr().err


def test_console_command_is_installed_and_has_help():
    p = subprocess.run([sys.executable, "-m", "generator.cli", "--help"], capture_output=True,
                       text=True)
    assert p.returncode == 0
    for v in ("fit", "apply", "generate", "demo"):
        assert v in p.stdout


def test_demo_runs_and_checks_bit_exactness(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "demo"), "-q"]) == 0
    out = capsys.readouterr().out
    assert "identical" in out and "DIFFERENT" not in out
    assert (tmp_path / "demo" / "report.html").exists()
    assert (tmp_path / "demo" / "flight_c" / "demo_sat_magcal.c").exists()


def test_fit_method_analytic_is_reachable_from_the_command(fm1_dir, tmp_path):
    import json

    assert main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
                 "--method", "analytic", "-o", str(tmp_path), "-q"]) == 0
    d = json.loads((tmp_path / "coefficients.json").read_text())
    for s in d["fit"]["sensors"].values():
        assert s["stats"]["method"] == "analytic", s["method"]
