"""The fit report of the smallest unit ICD section 4 allows, looked at (review of issue 19):
one sensor, no temperature column, physical units (nT or G), no boom -- without and with
coil files. Every section either shows its content or is left out with a stated reason:
no empty table, no empty figure, no "not drawn" (generator.report.render_check), and the
page renders in headless chromium.

The unit files are written here; the campaigns come from `magcal simulate`, the report
from `magcal fit`, both run in-process through the command line.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile

import pytest

from generator.cli import main
from generator.report import render_check

from ci import require

UNIT = """[unit]
id = "{uid}"
lab_field_nT = 48000.0
float = "float32"

[[sensor]]
name = "mag"
part = "generic"
frame = "body"
axes = ["+x", "-z", "+y"]
input = "{input}"
range_nT = 800000.0
temperature = false
noise_nT = 50.0

[requirements]
field_error_nT = 150.0
angle_deg = 0.5
"""

# a short thermal program: one sample every 2 min, 5 per hold (test_simulate_verb's FAST)
FAST = ["--sample-period-s", "120", "--samples-per-segment", "5"]


def _fit(tmp_path, input_unit, files, seed):
    uid = f"one_{input_unit.lower()}"
    unit = tmp_path / "unit.toml"
    unit.write_text(UNIT.format(uid=uid, input=input_unit))
    sim = tmp_path / "sim"
    assert main(["simulate", str(unit), "-o", str(sim), "-q", "--seed", str(seed), *FAST]) == 0
    out = tmp_path / "fit"
    assert main(["fit", str(sim / "unit.toml"), *(str(sim / f) for f in files),
                 "-o", str(out), "-q"]) == 0
    return out / "report.html"


def _section(md, title):
    parts = md.split(f"\n## {title}")
    assert len(parts) == 2, f"no section '{title}'"
    return parts[1].split("\n## ")[0]


@pytest.fixture(scope="module", params=[("nT", ["thermal_12pos.csv", "rotation.csv"], 3),
                                        ("G", ["thermal_12pos.csv", "rotation.csv",
                                               "coils.csv", "coil_study.csv"], 5)],
                ids=["nT-no-coils", "G-coils-and-study"])
def report(request, tmp_path_factory):
    input_unit, files, seed = request.param
    return input_unit, files, _fit(tmp_path_factory.mktemp(f"one_{input_unit}"),
                                   input_unit, files, seed)


def test_report_of_a_one_sensor_unit_passes_the_render_check(report):
    _, _, html = report
    assert render_check.problems(html) == []


def test_no_temperature_sensor_is_shown_as_such_everywhere(report):
    """The comparison of fit methods has the sensor's rows (it was empty: samples without a
    temperature were dropped); no temperature bin or level of the stand-in temperature."""
    _, _, html = report
    md = (html.parent / "report.md").read_text()
    comp = _section(md, "Fit methods compared")
    rows = [ln for ln in comp.splitlines() if ln.startswith("| mag |")]
    assert len(rows) >= 4            # raw, ellipsoid, analytic, auto (+ rotation)
    rms = _section(md, "|B| RMS before and after calibration")
    assert "| mag | temperature | all (no temperature) |" in rms
    assert not re.search(r"\| mag \| temperature \| [-0-9.]+\.\.[-0-9.]+ degC", rms)
    levels = _section(md, "Known vectors")
    assert "| all (no temperature) |" in levels and "| 25.0 |" not in levels


def test_coil_sections_of_a_one_sensor_unit(report):
    """With coils: K with its 1-sigma (not zeros from an LSB that physical input does not
    have), rows of coils the study never measured say so, the study's law carries its
    measured span and flags."""
    input_unit, files, html = report
    md = (html.parent / "report.md").read_text()
    if "coils.csv" not in files:
        assert "## Magnetorquer" not in md and "## Coil study" not in md
        return
    K = _section(md, "Magnetorquer coupling K")
    cells = [c.strip() for ln in K.splitlines() if ln.startswith("| mag |")
             for c in ln.strip("|").split("|")[2:]]
    assert len(cells) == 9 and all(" ± " in c for c in cells), cells
    inter = _section(md, "Magnetorquer interference at 0.1 A")
    assert "| mag | coil_x_A |" in inter and "this sensor's law" in inter
    for coil in ("coil_y_A", "coil_z_A"):        # the study steps coil_x_A only
        row = next(ln for ln in inter.splitlines() if ln.startswith(f"| mag | {coil} |"))
        assert "not measured" in row
    law = _section(md, "Coil study")
    assert "| measured cm |" in law and "| flags |" in law


def test_sections_left_out_say_why(report):
    """No boom, no SET/RESET part, no temperature: those sections are not in the report,
    and the Inputs section says why (without coils: why no coil sections either)."""
    _, files, html = report
    md = (html.parent / "report.md").read_text()
    gone = next(ln for ln in _section(md, "Inputs").splitlines()
                if ln.startswith("Left out for this unit and these files:"))
    assert "chamber profile (seed 000 fig. 21, 23): no sensor reports a temperature" in gone
    assert "the unit has no boom sensor" in gone and "no SET/RESET part" in gone
    assert ("no coil campaign" in gone) == ("coils.csv" not in files)
    assert ("no coil-study file" in gone) == ("coil_study.csv" not in files)
    for title in ("Chamber profile", "Agreement of the two magnetometers", "SET/RESET"):
        assert f"\n## {title}" not in md


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


@pytest.mark.slow
def test_one_sensor_report_renders_in_headless_chromium(report, tmp_path):
    exe = _chromium()
    if exe is None:
        require(False, "chromium not installed (apt-get install -y chromium): the page was "
                       "not rendered")
    _, _, html = report
    shot = tmp_path / "page.png"
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu",
                        "--disable-background-networking", "--no-first-run",
                        f"--user-data-dir={profile}", f"--screenshot={shot}",
                        "--window-size=1280,3000", html.as_uri()],
                       capture_output=True, timeout=180)
    assert shot.is_file()
    assert render_check.png_problems(shot) == []
