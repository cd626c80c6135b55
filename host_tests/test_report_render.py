"""The demo report, looked at: every figure shows something, no section says it could not
draw, no table is empty (generator.report.render_check), every seed 000 figure the demo's
campaigns can give is there, and the page renders in headless chromium. The check itself
must fail on a blank figure, an axes with nothing drawn, a 'not drawn' message and an
empty table.
"""

from __future__ import annotations

import re
from html import unescape
import shutil
import subprocess
import tempfile

import numpy as np
import pytest

from generator.cli import main
from generator.report import figures, render_check
from generator.report.document import Report, Section, Table

from ci import require


@pytest.fixture(scope="module")
def demo_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "demo"
    assert main(["demo", "-o", str(out), "-q"]) == 0
    return out / "report.html"


def test_demo_report_passes_the_render_check(demo_report):
    assert render_check.problems(demo_report) == []


def test_demo_report_has_the_verdict_and_every_seed_figure(demo_report):
    html = demo_report.read_text(encoding="utf-8")
    titles = [unescape(t) for t in re.findall(r"<h2 id=\"sec-\d+\">([^<]*)</h2>", html)]
    assert titles[0] == "Summary and verdict"
    for t in ("Agreement of the two magnetometers (mmc1/mmc2)",         # fig. 10
              "Agreement of the two magnetometers: projections per axis",  # fig. 8-9
              "Example calibration: rotation",                           # fig. 14
              "Example calibration: twelve positions",                   # fig. 16
              "Chamber profile: segments and sensor temperatures",       # fig. 21, 23
              "Calibrated measurements in the positions",                # fig. 26
              "Per-axis RMS before and after calibration",
              "|B| RMS before and after calibration",                    # fig. 27-29
              "Magnetorquer coupling K",
              "SET/RESET offset error while turning",                    # fig. 12-13
              "Fit methods compared: do known vectors close the gap?"):
        assert t in titles, t
    for png in ("setreset_error_maps.png", "setreset_error_maps_relative.png",
                "projections_before_after.png", "example_rotation.png",
                "example_twelve_positions.png", "chamber_profile.png", "positions_1_3.png",
                "axis_rms.png", "alignment_mmc1_mmc2.png"):
        assert f'src="{png}"' in html, png
    # the demo states requirements, so there is a verdict per sensor
    assert "Verdict: none" not in html and ("MEETS" in html or "FAILS" in html)
    # the inputs table lists the three fitted files
    for f in ("thermal_12pos.csv", "rotation.csv", "coils.csv"):
        assert f"data/{f}</td>" in html, f


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def test_demo_report_renders_in_headless_chromium(demo_report, tmp_path):
    exe = _chromium()
    if exe is None:
        require(False, "chromium not installed (apt-get install -y chromium): the demo page "
                       "was not rendered -- CI must install it (.ci/run)")
    shot = tmp_path / "page.png"
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu",
                        "--disable-background-networking", "--no-first-run",
                        f"--user-data-dir={profile}", f"--screenshot={shot}",
                        "--window-size=1280,3000", demo_report.as_uri()],
                       capture_output=True, timeout=180)
    assert shot.is_file()
    # the top of the page as the browser drew it passes the same blank-image check
    assert render_check.png_problems(shot) == []


# ---- the check must be able to fail ------------------------------------------------------
def _report_with(tmp_path, sections):
    rep = Report("t", sections)
    return rep.write(tmp_path)


def _line_png(path):
    fig = figures._figure(3, 2)
    ax = fig.subplots()
    ax.plot(np.arange(10), np.arange(10) ** 2)
    return figures._save(fig, path)


def test_render_check_passes_a_good_report(tmp_path):
    _line_png(tmp_path / "good.png")
    html = _report_with(tmp_path, [Section("s", ["fine"], [Table(["a"], [[1.0]])],
                                           [("good.png", "a line")])])
    assert render_check.problems(html) == []


def test_render_check_fails_on_a_blank_figure(tmp_path):
    from PIL import Image
    Image.new("RGB", (200, 100), (255, 255, 255)).save(tmp_path / "blank.png")
    html = _report_with(tmp_path, [Section("s", [], [Table(["a"], [[1.0]])],
                                           [("blank.png", "nothing")])])
    probs = render_check.problems(html)
    assert len(probs) == 1 and "blank.png: blank" in probs[0]


def test_render_check_fails_on_axes_with_nothing_drawn(tmp_path):
    fig = figures._figure(6, 2)
    a1, a2 = fig.subplots(1, 2)
    a1.plot([0, 1], [0, 1])
    a2.set_title("forgotten")          # frame, ticks and title, but no data
    figures._save(fig, tmp_path / "half.png")
    html = _report_with(tmp_path, [Section("s", [], [Table(["a"], [[1.0]])],
                                           [("half.png", "one empty panel")])])
    probs = render_check.problems(html)
    assert len(probs) == 1 and "axes with nothing drawn: forgotten" in probs[0]


def test_render_check_fails_on_not_drawn_and_empty_tables(tmp_path):
    html = _report_with(tmp_path, [
        Section("a", ["Angle figure not drawn: KeyError: 'x'"]),
        Section("b", [], [Table(["level degC", "b"], [], "per-level estimates")])])
    probs = render_check.problems(html)
    assert any("not drawn" in p for p in probs)
    assert any("no data row" in p and "per-level estimates" in p for p in probs)
    assert len(probs) == 2
