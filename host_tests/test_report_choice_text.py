"""Report text that must agree with the report's own tables and the fit (review of issue 19,
19b F9): the "Left out" sentence names every seed section the report does not show; the
method choice is printed with the digits its table shows and that tell the scores apart;
the summary's noise column is the noise the fit used and says where it came from; the
coil study's distance ticks do not overlap.
"""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.cli import main
from generator.report.coil_study import distance_ticks
from generator.report.document import significant
from generator.report.report import CHOICE_DECIMALS_MAX, _held_out_choice
from generator.report.summary import noise_used

# seed 000 sections of the fit report (title prefix) and how the Left-out sentence names
# each when it is not there
SEED_SECTIONS = {
    "Per-axis RMS": "per-axis RMS",
    "Chamber profile": "chamber profile",
    "Calibrated measurements in the positions": "calibrated measurements in the positions",
    "Example calibration: rotation": "Example calibration: rotation",
    "Example calibration: twelve positions": "Example calibration: twelve positions",
    "Agreement of the two magnetometers": "agreement of the two magnetometers",
    "Magnetorquer": "magnetorquer",
    "Coil study": "coil study",
    "Fit methods compared": "fit methods compared",
}


@pytest.fixture(scope="module")
def no_rotation(tmp_path_factory):
    """The fast example fitted without its rotation file (as the reviewer's r_ok)."""
    tmp = tmp_path_factory.mktemp("choice")
    paths = sim.make_example(tmp / "ex", seed=2, size="fast")
    out = tmp / "fit"
    assert main(["fit", str(paths["unit"]), str(paths["thermal_12pos"]), str(paths["coils"]),
                 "-o", str(out), "-q"]) == 0
    md = (out / "report.md").read_text()
    return SimpleNamespace(md=md, out=out, paths=paths,
                           coeffs=json.loads((out / "coefficients.json").read_text()))


def _left_out(md):
    return next(l for l in md.splitlines() if l.startswith("Left out for this unit"))


def test_left_out_names_every_seed_section_not_shown(no_rotation):
    titles = [l[3:] for l in no_rotation.md.splitlines() if l.startswith("## ")]
    gone = _left_out(no_rotation.md)
    assert "Example calibration: rotation (seed 000 fig. 14): no rotation" in gone
    for prefix, named in SEED_SECTIONS.items():
        shown = any(t.startswith(prefix) for t in titles)
        assert shown or named in gone, (prefix, gone)
        assert not (shown and named + " (" in gone), (prefix, gone)   # shown and left out


def _table(md, caption):
    lines = md.splitlines()
    k = next(i for i, l in enumerate(lines) if caption in l and l.startswith("**Table"))
    rows = []
    for l in lines[k + 2:]:
        if not l.startswith("|"):
            break
        rows.append([c.strip() for c in re.split(r"(?<!\\)\|", l.strip())[1:-1]])
    return [dict(zip(rows[0], r)) for r in rows[2:]]


def test_summary_noise_is_what_the_fit_used_and_says_its_source(no_rotation):
    unit = {s["name"]: s for s in _unit_sensors(no_rotation.paths["unit"])}
    for row in _table(no_rotation.md, "Per sensor: errors before and after"):
        cell = row["noise the fit used nT/axis"]
        used = no_rotation.coeffs["fit"]["sensors"][row["sensor"]]["stats"]["noise_goodness"]
        # the figure the noise test used, to 3 digits (the unit's 40 nT per reading is
        # 28.7 nT per field axis after quantisation and the SET/RESET pair)
        assert cell.startswith(significant(used["noise_nT"]) + " ("), (cell, used)
        if unit[row["sensor"]].get("noise_nT"):
            assert f"(unit file: {unit[row['sensor']]['noise_nT']:g} per reading" in cell


def _unit_sensors(path):
    try:
        import tomllib
    except ImportError:            # Python 3.10
        import tomli as tomllib
    return tomllib.loads(path.read_text())["sensor"]


@pytest.mark.parametrize("spec, stats, text", [
    (dict(noise_nT=40.0, counts=True, set_reset=True), {"noise_nT": 28.74, "noise_from": "stated"},
     "28.7 (unit file: 40 per reading, with the LSB's quantisation, averaged over the "
     "SET/RESET pair)"),
    (dict(noise_nT=None, counts=False, set_reset=False),
     {"noise_nT": 300.0, "noise_from": "stated"},
     "300 (part catalogue)"),
    (dict(noise_nT=None, counts=True, set_reset=False),
     {"noise_nT": 15.2, "noise_from": "part catalogue (typical)"},
     "15.2 (part catalogue, typical: with the LSB's quantisation)"),
    (dict(noise_nT=None, counts=True, set_reset=False),
     {"noise_nT": 13.9746, "noise_from": "sample-to-sample differences"},
     "14.0 (estimated from sample-to-sample differences)"),
    (dict(noise_nT=None, counts=True, set_reset=False),
     {"noise_nT": 13.9746, "noise_from": "a source the report has not seen"},
     "14.0 (a source the report has not seen)"),
    (dict(noise_nT=None, counts=True, set_reset=False), None, "-"),
])
def test_noise_used_names_any_source(spec, stats, text):
    assert noise_used(SimpleNamespace(**spec), {"noise_goodness": stats}) == text


def test_method_choice_prints_the_digits_that_tell_the_scores_apart():
    cells, why = _held_out_choice({"joint": 29.5512, "segments": 29.5534}, "joint",
                                  "smaller held-out error: joint 29.55 nT, segments 29.55 nT")
    assert cells == ["29.551", "29.553"]
    assert why == "smaller held-out error: joint 29.551 nT, segments 29.553 nT"
    cells, why = _held_out_choice({"joint": 12.31, "segments": 45.6}, "joint",
                                  "smaller held-out error: ...")
    assert cells == ["12.3", "45.6"]
    # equal to CHOICE_DECIMALS_MAX decimals: a tie, said so
    cells, why = _held_out_choice({"joint": 29.35001, "segments": 29.35002}, "joint",
                                  "smaller held-out error: ...")
    assert cells == ["29.350", "29.350"] and CHOICE_DECIMALS_MAX == 3
    assert why.startswith("a tie within rounding (joint 29.350 nT, segments 29.350 nT")
    assert why.endswith("joint kept")
    # another why (no comparison) is left as the fit wrote it
    assert _held_out_choice({"joint": 3.0, "segments": None}, "joint",
                            "segments method not available") == ([3.0, None],
                                                                 "segments method not available")


def test_method_table_and_its_why_agree(no_rotation):
    for row in _table(no_rotation.md, "Held-out comparison"):
        j, s = row["joint RMS nT"], row["segments RMS nT"]
        if row["why"].startswith(("smaller held-out error", "a tie")):
            assert f"joint {j} nT" in row["why"] and f"segments {s} nT" in row["why"], row
            assert (j == s) == row["why"].startswith("a tie"), row


def _label_boxes(fig, ax):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    return [t.get_window_extent(r) for t in ax.get_xticklabels() if t.get_text()]


@pytest.mark.parametrize("distances, must", [
    ([0.05, 0.1, 0.15, 0.2, 0.25, 0.3], [0.05, 0.3, 30.0]),      # the reviewer's mm file
    ([0.2, 0.25, 0.3], [0.2, 0.3, 30.0]),
    ([5.0, 10.0, 15.0, 20.0, 25.0, 30.0], [5.0, 10.0, 15.0, 20.0, 25.0, 30.0]),
])
def test_distance_tick_labels_do_not_overlap(distances, must):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 4.2))        # the coil-study figure's size and layout
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    r = np.array(distances)
    grid = np.geomspace(r.min() * 0.9, max(r.max(), 30.0) * 1.1, 50)
    ax.loglog(grid, 1e3 * (30.0 / grid) ** 3)
    ax.tick_params(labelsize=7)
    fig.subplots_adjust(left=0.13, right=0.98, top=0.9, bottom=0.13)
    kept = distance_ticks(ax, r, extra_cm=(30.0,), fontsize=7)
    assert set(must) <= set(kept), kept
    boxes = sorted(_label_boxes(fig, ax), key=lambda b: b.x0)
    assert len(boxes) == len(kept)
    for a, b in zip(boxes, boxes[1:]):
        assert a.x1 < b.x0, (kept, a, b)        # rendered labels apart


def test_the_report_passes_the_render_check(no_rotation):
    """The fast example's holds are too short for a segment: the chamber profile says so
    instead of showing an empty segments table; nothing else the check catches."""
    from generator.report import render_check
    assert render_check.problems(no_rotation.out / "report.html") == []
    assert "No segment was found" in no_rotation.md
