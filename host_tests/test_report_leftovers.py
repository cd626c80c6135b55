"""Review findings on issue #19 (the report an attitude engineer reads and the campaigns
behind it), each reproduced and then held:

C. a hand-edited plan.json whose summary fields contradict its steps is refused by
   `magcal check` and `magcal simulate` (exit 2, one line naming the plan file and key),
   and a missing key is named as missing;
D. a coil distance law the points do not determine prints "undetermined" instead of
   numbers and is flagged; the seed's with-panel row is scaled by the with-panel law;
E. the H matrix is printed to the digits its 1-sigma supports; the reference sensor is
   drawn on top in the alignment figure;
F. `magcal fit` warns when a temperature level has no settled segment for a sensor.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign import plan as P
from generator.cli import main
from generator.errors import InputError
from generator.io.unitfile import load_unit
from generator.verbs.plan import write_plan


# ---------------------------------------------------------------------------------------
# C. a plan is a contract: contradictions and missing keys are errors naming the key
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def plan_json(tmp_path_factory, fm1_dir):
    """A small program of the example unit as `magcal plan` writes it."""
    out = tmp_path_factory.mktemp("plan")
    unit = load_unit(fm1_dir / "unit.toml")
    write_plan(P.make_plan(unit, levels_C=(0.0, 25.0, 50.0), board_tau_min=5.0,
                           sample_period_s=30.0, samples_per_segment=20), out)
    return json.loads((out / "plan.json").read_text())


def _edited(plan_json, tmp_path, edit):
    d = json.loads(json.dumps(plan_json))
    edit(d)
    path = tmp_path / "edited_plan.json"
    path.write_text(json.dumps(d))
    return path


def _run_both(capsys, fm1_dir, plan_path, tmp_path):
    """(rc, stderr) of check and of simulate given the plan."""
    out = []
    for args in (["check", str(fm1_dir / "unit.toml"), str(fm1_dir / "thermal_12pos.csv"),
                  "--plan", str(plan_path), "-q"],
                 ["simulate", str(fm1_dir / "unit.toml"), "--plan", str(plan_path),
                  "--campaigns", "thermal_12pos", "-o", str(tmp_path / "sim"), "-q"]):
        rc = main(args)
        out.append((rc, capsys.readouterr().err))
    return out


def test_the_plan_as_written_is_read_back(plan_json, tmp_path):
    """The control: the unedited plan and one with a hold lengthened by hand (its derived
    keys left out, as the loader's message says) load in both readers."""
    path = _edited(plan_json, tmp_path, lambda d: None)
    plan = P.load_plan(path)
    assert plan.levels_C == [0.0, 25.0, 50.0] and plan.board_tau_s == 300.0
    assert P.load_profile(path).levels_C == [0.0, 25.0, 50.0]

    def longer(d):
        d["steps"][1]["hold_s"] += 600.0
        for k in ("position_duration_s", "total_duration_s", "samples_total",
                  "chamber_program"):
            del d[k]
    plan = P.load_plan(_edited(plan_json, tmp_path, longer))
    assert plan.steps[1].hold_s == plan_json["steps"][1]["hold_s"] + 600.0
    assert plan.total_duration_s == pytest.approx(plan_json["total_duration_s"] + 12 * 600.0)


def _set(key, value):
    def edit(d):
        d[key] = value
    return edit


@pytest.mark.parametrize("edit, key", [
    (_set("levels_C", [0.0, 20.0, 50.0]), "levels_C"),
    (_set("board_tau_s", 1200.0), "board_tau_s"),
    (_set("settle_tolerance_C", 0.2), "board_tau_s"),        # settle_s = tau ln(step / tol)
    (_set("samples_per_segment", 40), "samples_per_segment"),
    (_set("ramp_C_per_min", 2.0), "ramp_C_per_min"),
    (_set("lab_field_nT", 48000.0), "lab_field_nT"),
    (_set("inclination_deg", 60.0), "positions[0].expected_field_body_nT"),
    (_set("total_duration_s", 1.0), "total_duration_s"),
    (lambda d: d["steps"][1].update(hold_s=d["steps"][1]["hold_s"] + 600.0),
     "position_duration_s"),                                 # derived keys kept, now stale
    (lambda d: d["steps"].reverse(), "levels_C"),
    (lambda d: d["steps"][2].update(hold_s=d["steps"][2]["record_s"] + 60.0),
     "steps[2].hold_s"),                                     # recording before settling
    (lambda d: d.pop("lab_field_nT"), "lab_field_nT"),
    (lambda d: d.pop("levels_C"), "levels_C"),
])
def test_contradicting_plan_is_refused_by_check_and_simulate(plan_json, tmp_path, capsys,
                                                            fm1_dir, edit, key):
    path = _edited(plan_json, tmp_path, edit)
    for rc, err in _run_both(capsys, fm1_dir, path, tmp_path):
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1, err
        assert str(path.name) in lines[0] and f"key {key}:" in lines[0], lines[0]
        assert "Traceback" not in err
    assert not (tmp_path / "sim" / "thermal_12pos.csv").exists()


def test_missing_lab_field_is_named_as_missing(plan_json, tmp_path):
    path = _edited(plan_json, tmp_path, lambda d: d.pop("lab_field_nT"))
    with pytest.raises(InputError) as e:
        P.load_plan(path)
    msg = str(e.value)
    assert "edited_plan.json" in msg and "key lab_field_nT: missing" in msg
    assert "None" not in msg
