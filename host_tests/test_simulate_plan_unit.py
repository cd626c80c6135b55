"""`magcal simulate UNIT --plan PLAN` checks that the plan is the unit's (review #19 F6).

A plan records its unit (plan.json "unit", the unit file's [unit] id) and its lab field.
* a plan of another unit: exit 2, one line naming the plan file and both ids;
* a plan whose lab_field_nT differs from the unit file's: exit 2 (the unit file is the
  authority on its own lab; one run, one lab field), one line naming the plan file, the key
  and both fields;
* a unit file without lab_field_nT: the plan's field is the field of every campaign.
Nothing is written on exit 2.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.cli import main
from generator.io.unit import Unit


def _unit(tmp_path, name, unit_id="demo_sat", lab_field_nT=47000.0):
    u = sim.make_example_unit(unit_id)
    u = Unit(u.id, u.sensors, lab_field_nT=lab_field_nT, boom_reference="mmc1")
    sim.write_unit_toml(u, tmp_path / name)
    return tmp_path / name


def _plan(tmp_path, unit_path, name="plan", *extra):
    assert main(["plan", str(unit_path), "-o", str(tmp_path / name), "-q", "--levels", "0",
                 "40", "--sample-period-s", "120", "--samples-per-segment", "5",
                 "--board-tau-min", "25", *extra]) == 0
    return tmp_path / name / "plan.json"


def _simulate(unit_path, plan, out, *campaigns):
    return main(["simulate", str(unit_path), "-o", str(out), "-q", "--plan", str(plan),
                 "--campaigns", *(campaigns or ("thermal_12pos",))])


def test_plan_of_another_unit_is_refused(tmp_path, capsys):
    plan = _plan(tmp_path, _unit(tmp_path, "a.toml", "unit_a"))
    other = _unit(tmp_path, "b.toml", "unit_b")
    capsys.readouterr()
    rc = _simulate(other, plan, tmp_path / "o")
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert str(plan) in err and "'unit_a'" in err and "'unit_b'" in err
    assert not (tmp_path / "o").exists()


def test_plan_with_another_lab_field_is_refused(tmp_path, capsys):
    unit = _unit(tmp_path, "a.toml", lab_field_nT=47000.0)
    d = json.loads(_plan(tmp_path, unit).read_text())
    d["lab_field_nT"] = 61234.5                     # e.g. made with --lab-field-nT
    (tmp_path / "other_lab.json").write_text(json.dumps(d))
    capsys.readouterr()
    rc = _simulate(unit, tmp_path / "other_lab.json", tmp_path / "o")
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "other_lab.json" in err and "lab_field_nT" in err
    assert "61234.5" in err and "47000" in err
    assert not (tmp_path / "o").exists()


def test_the_units_own_plan_is_followed(tmp_path):
    unit = _unit(tmp_path, "a.toml", lab_field_nT=47000.0)
    assert _simulate(unit, _plan(tmp_path, unit), tmp_path / "o", "thermal_12pos",
                     "rotation") == 0
    for kind in ("thermal_12pos", "rotation"):
        a = np.load(tmp_path / "o" / f"{kind}.truth.npz")
        assert np.allclose(np.linalg.norm(a["b_body_nT"], axis=1), 47000.0), kind


def test_unit_without_lab_field_takes_the_plans_everywhere(tmp_path, capsys):
    """One run, one lab field: the plan's (magcal plan --lab-field-nT) in every campaign."""
    unit = _unit(tmp_path, "a.toml", lab_field_nT=None)
    plan = _plan(tmp_path, unit, "plan", "--lab-field-nT", "38000")
    main(["simulate", str(unit), "-o", str(tmp_path / "o"), "--plan", str(plan),
          "--campaigns", "thermal_12pos", "rotation", "coils", "--json", "-q"])
    res = json.loads(capsys.readouterr().out)
    assert any("the plan's 38000 nT is the lab field of every campaign" in n
               for n in res["notes"])
    assert not any("seed 000" in n for n in res["notes"])
    for kind in ("thermal_12pos", "rotation", "coils"):
        a = np.load(tmp_path / "o" / f"{kind}.truth.npz")
        assert np.allclose(np.linalg.norm(a["b_body_nT"], axis=1), 38000.0), kind
