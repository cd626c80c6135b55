"""Issue 20: `magcal fit --no-report` writes the coefficients only (no report, no
figures); it excludes --compare-methods, whose only output is in the report."""

from __future__ import annotations

import json

from generator.cli import main


def test_fit_no_report_writes_coefficients_only(tmp_path, fm1_dir, capsys):
    out = tmp_path / "fit"
    rc = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "rotation.csv"), "-o",
               str(out), "--no-report", "--json", "--quiet"])
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == ["coefficients.json"]
    summary = json.loads(capsys.readouterr().out)
    assert summary["report"] is None
    assert summary["coefficients"] == str(out / "coefficients.json")
    assert json.loads((out / "coefficients.json").read_text())["unit"]["id"] == "samsat_fm1"


def test_no_report_excludes_compare_methods(tmp_path, fm1_dir, capsys):
    rc = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "rotation.csv"), "-o",
               str(tmp_path / "f"), "--no-report", "--compare-methods"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--no-report" in err
    assert not (tmp_path / "f").exists()
