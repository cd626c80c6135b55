"""`magcal fit --accept-misfit` (brief fits3, fault 2): the goodness refusal (fit.goodness,
exit 2 when the vector residual is far beyond the noise) has a command-line opt-in; the
calibration is then written, and coefficients.json and the report carry the warning.
Data: test_fit_frame_mismatch's ENU reference against NED readings (refused without the
flag)."""

from __future__ import annotations

import json

import numpy as np

from generator.cli import main

from test_fit_frame_mismatch import _data, _unit


def test_accept_misfit_writes_with_a_warning(tmp_path, capsys):
    unit = _unit(tmp_path)
    data = _data(tmp_path / "enu.csv", np.random.default_rng(21), enu=True)
    assert main(["fit", str(unit), str(data), "-o", str(tmp_path / "refused"), "-q"]) == 2
    capsys.readouterr()
    out = tmp_path / "fit"
    assert main(["fit", str(unit), str(data), "-o", str(out), "-q", "--accept-misfit"]) == 0
    cj = json.loads((out / "coefficients.json").read_text())
    st = cj["fit"]["sensors"]["mpu"]["stats"]
    assert st["goodness_of_fit"]["refuse"] and st["goodness_of_fit"]["accepted"]
    warn = [w for w in st["sanity"]["warnings"] if "--accept-misfit" in w]
    assert len(warn) == 1 and "another frame" in warn[0]
    report = (out / "report.md").read_text()
    assert "misfit accepted with --accept-misfit" in report


def test_help_names_the_flag(capsys):
    try:
        main(["fit", "--help"])
    except SystemExit:
        pass
    assert "--accept-misfit" in capsys.readouterr().out
