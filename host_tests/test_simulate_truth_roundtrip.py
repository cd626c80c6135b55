"""A truth.json written by `magcal simulate` is accepted back by `--truth` (review #19 F9 d).

truth.json carries, besides the parameters, t_ref_C, a "simulation" record (seed, version,
options) and per sensor "frame" and "note". Given back: the parameters are the run's (the
new run draws nothing of its own), the record is ignored (the seed is --seed), t_ref_C and
frame must agree with the simulator and the unit, unknown keys are still refused.
"""

from __future__ import annotations

import json

import pytest

from generator.campaign import simulate as sim
from generator.cli import main

PARAMS = ("H_boom_to_body", "sensors", "board_tau_s", "board_self_heating_C", "coil_study",
          "t_ref_C")


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("rt")
    sim.write_unit_toml(sim.make_example_unit(), d / "unit.toml")
    assert main(["simulate", str(d / "unit.toml"), "-o", str(d / "a"), "-q", "--seed", "1",
                 "--campaigns", "rotation"]) == 0
    return d, json.loads((d / "a" / "truth.json").read_text())


def _again(d, truth_path, out):
    return main(["simulate", str(d / "unit.toml"), "-o", str(out), "-q", "--seed", "2",
                 "--campaigns", "rotation", "--truth", str(truth_path)])


def test_truth_json_given_back_gives_the_same_unit(first_run, tmp_path):
    d, truth = first_run
    assert _again(d, d / "a" / "truth.json", tmp_path / "b") == 0
    again = json.loads((tmp_path / "b" / "truth.json").read_text())
    for k in PARAMS:
        assert again[k] == truth[k], k
    assert again["simulation"]["seed"] == 2          # the record is this run's, not the file's
    # another seed without --truth draws another unit (so the equality above means something)
    assert main(["simulate", str(d / "unit.toml"), "-o", str(tmp_path / "c"), "-q", "--seed",
                 "2", "--campaigns", "rotation"]) == 0
    drawn = json.loads((tmp_path / "c" / "truth.json").read_text())
    assert drawn["H_boom_to_body"] != truth["H_boom_to_body"]


@pytest.mark.parametrize("edit, fault", [
    (lambda t: t.update(t_ref_C=20.0), "t_ref_C"),
    (lambda t: t["sensors"]["mmc1"].update(frame="boom"), "sensors.mmc1.frame"),
    (lambda t: t.update(simulation="seed 3"), "simulation"),
    (lambda t: t.update(colour="red"), "colour"),
    (lambda t: t["sensors"]["mmc1"].update(colour="red"), "sensors.mmc1.colour"),
])
def test_truth_json_with_a_wrong_record_is_one_line(first_run, tmp_path, capsys, edit, fault):
    d, truth = first_run
    t = json.loads(json.dumps(truth))
    edit(t)
    (tmp_path / "truth.json").write_text(json.dumps(t))
    capsys.readouterr()
    rc = _again(d, tmp_path / "truth.json", tmp_path / "b")
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert f"key {fault}" in err and "truth.json" in err
    assert not (tmp_path / "b").exists()
