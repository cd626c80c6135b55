"""Coil-study input rules are enforced when the file is read (review of issue 19, item 1):
one distance, a distance <= 0, a panel flag other than 0/1, an unknown coil_test_sensor,
a coil_test_sensor key without distances, a current that never steps. Every verb that
reads the file refuses it the same way, before any fitting: `fit` with and without
--no-report, `check` and `trace`; exit 2, one line on stderr naming the file, the line
and the column (or the key), numbers without numpy reprs."""

from __future__ import annotations

import re

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.cli import main
from generator.errors import InputError
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return sim.make_example(tmp_path_factory.mktemp("ex"), seed=3, size="fast")


def _rows(path):
    lines = path.read_text().splitlines()
    h = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    return lines, h, lines[h].split(",")


def _write_edited(src, dst, column, edit):
    """A copy of src where edit(row index, old cell) -> new cell, on `column` of every data
    row. Returns the path."""
    lines, h, header = _rows(src)
    k = header.index(column)
    for i in range(h + 1, len(lines)):
        cells = lines[i].split(",")
        cells[k] = edit(i - h - 1, cells[k])
        lines[i] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def _line_of_row(path, row):
    _, h, _ = _rows(path)
    return h + 2 + row                                   # 1-based file line of data row `row`


def _bad_files(example, tmp_path):
    """{case: (path, the text the one line must carry)}"""
    study = example["coil_study"]
    out = {}
    p = _write_edited(study, tmp_path / "one_distance.csv", "coil_distance_cm",
                      lambda i, c: "15.0")
    out["one distance"] = (p, f"one_distance.csv:{_line_of_row(p, 0)}: column "
                              "'coil_distance_cm': panel 0: every static row is at 15 cm")
    for name, value in (("negative", "-5.0"), ("zero", "0")):
        p = _write_edited(study, tmp_path / f"{name}.csv", "coil_distance_cm",
                          lambda i, c, v=value: v if i == 7 else c)
        out[f"{name} distance"] = (p, f"{name}.csv:{_line_of_row(p, 7)}: column "
                                      f"'coil_distance_cm': {float(value):g} is not a "
                                      "positive distance")
    p = _write_edited(study, tmp_path / "panel2.csv", "panel",
                      lambda i, c: "2" if i == 9 else c)
    out["panel 2"] = (p, f"panel2.csv:{_line_of_row(p, 9)}: column 'panel': 2 is not 0 "
                         "(without) or 1")
    p = tmp_path / "sensor.csv"
    p.write_text(study.read_text().replace("# coil_test_sensor: mmc2",
                                           "# coil_test_sensor: mmc2, mmc9"))
    out["unknown test sensor"] = (p, "sensor.csv: '# coil_test_sensor: mmc2, mmc9': unit "
                                     "demo_sat has no sensor 'mmc9'")
    p = _write_edited(study, tmp_path / "no_step.csv", "coil_x_A", lambda i, c: "0.0500")
    out["current never steps"] = (p, f"no_step.csv:{_line_of_row(p, 0)}: column 'coil_x_A': "
                                     "at 5 cm, panel 0: the current never changes")
    # the key without the distance column: the file would pass as a flight coil campaign
    lines = example["coils"].read_text().splitlines()
    p = tmp_path / "key_only.csv"
    p.write_text("# coil_test_sensor: mmc2\n" + "\n".join(lines) + "\n")
    out["key without distances"] = (p, "key_only.csv: '# coil_test_sensor' is given but "
                                       "there is no coil_distance_cm column")
    return out


CASES = ["one distance", "negative distance", "zero distance", "panel 2",
         "unknown test sensor", "current never steps", "key without distances"]


@pytest.mark.parametrize("case", CASES)
def test_read_refuses_the_bad_study(example, tmp_path, case):
    path, text = _bad_files(example, tmp_path)[case]
    unit = load_unit(example["unit"])
    with pytest.raises(InputError) as e:
        read_telemetry(path, unit)
    assert text in str(e.value)
    assert "np." not in str(e.value) and "float64" not in str(e.value)


def _verb_argv(verb, example, path, out):
    if verb == "fit":
        return ["fit", str(example["unit"]), str(example["thermal_12pos"]), str(path),
                "-o", str(out)]
    if verb == "fit --no-report":
        return ["fit", str(example["unit"]), str(example["thermal_12pos"]), str(path),
                "-o", str(out), "--no-report"]
    if verb == "check":
        return ["check", str(example["unit"]), str(example["thermal_12pos"]), str(path)]
    if verb == "trace":
        return ["trace", str(example["unit"]), str(example["thermal_12pos"]), str(path),
                "-o", str(out)]
    raise AssertionError(verb)


@pytest.mark.parametrize("verb", ["fit", "fit --no-report", "check", "trace"])
@pytest.mark.parametrize("case", ["one distance", "negative distance", "panel 2",
                                  "unknown test sensor"])
def test_every_verb_refuses_it_before_fitting(example, tmp_path, capsys, verb, case):
    path, text = _bad_files(example, tmp_path)[case]
    out = tmp_path / "out"
    rc = main(_verb_argv(verb, example, path, out) + ["-q"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"magcal {verb.split()[0]}: ") and text in lines[0]
    assert "Traceback" not in err and not re.search(r"np\.\w+\(", err)
    assert not out.exists()                      # nothing written, not even half a folder


def test_a_good_study_passes_and_a_missing_cell_is_allowed(example, tmp_path):
    """The rules refuse faults only: the simulator's study reads, and an empty distance or
    panel cell (a missing value, ICD section 2) is left out, not refused."""
    unit = load_unit(example["unit"])
    tel = read_telemetry(example["coil_study"], unit)
    assert np.unique(tel.columns["coil_distance_cm"]).size >= 2
    p = _write_edited(example["coil_study"], tmp_path / "gaps.csv", "coil_distance_cm",
                      lambda i, c: "" if i in (3, 40) else c)
    p = _write_edited(p, tmp_path / "gaps2.csv", "panel", lambda i, c: "" if i == 5 else c)
    tel = read_telemetry(p, unit)
    assert np.isnan(tel.columns["coil_distance_cm"]).sum() == 2


def test_a_panel_state_with_one_distance_is_refused(example, tmp_path):
    """Every panel state needs two distances (its own distance law): the panel measured
    at one distance only is refused, naming the panel state."""
    unit = load_unit(example["unit"])
    lines, h, header = _rows(example["coil_study"])
    kd, kp = header.index("coil_distance_cm"), header.index("panel")
    keep = lines[:h + 1]
    for ln in lines[h + 1:]:
        c = ln.split(",")
        if c[kp] == "0" or float(c[kd]) == 30.0:
            keep.append(ln)
    p = tmp_path / "panel_at_30.csv"
    p.write_text("\n".join(keep) + "\n")
    with pytest.raises(InputError, match=r"column 'coil_distance_cm': panel 1: every static "
                                         r"row is at 30 cm"):
        read_telemetry(p, unit)
