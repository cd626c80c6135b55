"""`magcal simulate -o DIR` and its output folder (review of issue 19, item 2).

* DIR must be new or empty: the campaigns of two runs in one folder would be fitted
  against the other run's truth; a non-empty DIR is exit 2 with one line, nothing written;
* --force writes into it: this run's files replace their namesakes, the others are kept
  (and named in a note), whole or not at all (a failure midway leaves DIR as it was);
* truth.json records the seed, the magcal version and the options, and the same record
  reproduces the same bytes.
"""

from __future__ import annotations

import json

import pytest

import generator
from generator.campaign import simulate as sim
from generator.cli import main

# the two quick campaigns (well under a second each); the thermal one is not needed here
QUICK = ["--campaigns", "coils", "coil_study"]


@pytest.fixture()
def unit_toml(tmp_path):
    p = tmp_path / "unit.toml"
    sim.write_unit_toml(sim.make_example_unit(), p)
    return p


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _run(unit_toml, out, *extra):
    return main(["simulate", str(unit_toml), "-o", str(out), "-q", *QUICK, *extra])


def test_non_empty_folder_is_refused_and_left_as_it_was(unit_toml, tmp_path, capsys):
    out = tmp_path / "sim"
    assert _run(unit_toml, out, "--seed", "1") == 0
    (out / "notes.txt").write_text("mine\n")
    before = _snapshot(out)
    capsys.readouterr()
    assert _run(unit_toml, out, "--seed", "2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"magcal simulate: {out}: output folder: "
                                               "not empty") and "--force" in err[0], err
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim", "unit.toml"]   # no temp left


def test_empty_existing_folder_is_accepted(unit_toml, tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    assert _run(unit_toml, out, "--seed", "1") == 0
    assert (out / "coils.csv").is_file()


def test_force_replaces_only_the_files_of_the_run(unit_toml, tmp_path, capsys):
    out, fresh = tmp_path / "sim", tmp_path / "fresh"
    assert main(["simulate", str(unit_toml), "-o", str(out), "-q", "--seed", "1",
                 "--campaigns", "coils"]) == 0
    (out / "notes.txt").write_text("mine\n")
    old_coils = (out / "coils.csv").read_bytes()
    assert _run(unit_toml, fresh, "--seed", "2") == 0
    capsys.readouterr()
    assert main(["simulate", str(unit_toml), "-o", str(out), "--seed", "2", *QUICK,
                 "--force", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    now, new = _snapshot(out), _snapshot(fresh)
    for name, data in new.items():           # this run's files: the fresh run's bytes
        assert now[name] == data, name
    assert now["coils.csv"] != old_coils     # replaced, not kept
    assert now["notes.txt"] == b"mine\n"     # not this run's: kept
    assert set(now) == set(new) | {"notes.txt"}
    assert result["kept_files"] == ["notes.txt"]
    assert any("notes.txt" in n and "--force" in n for n in result["notes"])
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_force_is_whole_or_nothing(unit_toml, tmp_path, monkeypatch, capsys):
    out = tmp_path / "sim"
    assert _run(unit_toml, out, "--seed", "1") == 0
    before = _snapshot(out)
    real = sim.simulate_campaign

    def fails_on_the_second(kind, *a, **k):
        if kind == "coil_study":             # the first campaign is written by then
            raise RuntimeError("disk full")
        return real(kind, *a, **k)

    monkeypatch.setattr(sim, "simulate_campaign", fails_on_the_second)
    assert _run(unit_toml, out, "--seed", "2", "--force") == 1
    assert "disk full" in capsys.readouterr().err
    assert _snapshot(out) == before
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_truth_records_the_seed_and_reproduces_the_run(unit_toml, tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    assert _run(unit_toml, a, "--seed", "7") == 0
    rec = json.loads((a / "truth.json").read_text())["simulation"]
    assert rec["seed"] == 7 and rec["magcal_version"] == generator.__version__
    assert rec["campaigns"] == ["coils", "coil_study"]
    assert set(rec["files"]) == {p.name for p in a.iterdir()}
    assert "--seed 7" in rec["reproduce"] and "--campaigns coils coil_study" in rec["reproduce"]
    # the record is enough: the same seed and options give the same bytes
    assert _run(unit_toml, b, "--seed", str(rec["seed"]), "--campaigns", *rec["campaigns"]) == 0
    assert _snapshot(a) == _snapshot(b)
    assert _run(unit_toml, c, "--seed", "8") == 0
    assert _snapshot(c)["coils.csv"] != _snapshot(a)["coils.csv"]


def test_truth_override_is_recorded(unit_toml, tmp_path):
    override = tmp_path / "o.toml"
    override.write_text("[coil_study]\nexponent = 2.8\n")
    out = tmp_path / "sim"
    assert _run(unit_toml, out, "--seed", "3", "--truth", str(override)) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["simulation"]["truth_override"] == {"coil_study": {"exponent": 2.8}}
    assert truth["coil_study"]["exponent"] == 2.8


def test_example_truth_records_its_seed(tmp_path):
    paths = sim.make_example(tmp_path / "ex", seed=4, size="fast")
    rec = json.loads(paths["truth"].read_text())["simulation"]
    assert rec["seed"] == 4 and rec["magcal_version"] == generator.__version__
    assert rec["size"] == "fast"
