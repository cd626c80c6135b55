"""README promise: every verb (for `import`, each of its sub-commands) has --help, -q/--quiet and --json, through `generator.cli.main`.

Each verb runs for real once with -q --json (stdout is exactly one JSON document, stderr
carries no progress) and once without -q (progress appears on stderr). `table` and `trace`
run through cli.main on small inputs (the committed example unit's coefficients; a fast
simulated chamber campaign with one injected heater coupling).
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from chain_fixtures import EXAMPLE_COEFFS
from ci import require
from conftest import REPO
from generator.campaign import simulate as sim
from generator.cli import VERBS, main
from generator.io.unit import Unit

ALL_VERBS = ("fit", "apply", "generate", "demo", "plan", "check", "table", "trace", "import",
             "simulate")
# `magcal import` is a group: its sub-commands are the commands, and they carry -q and --json
SUBCOMMANDS = {"import": ("px4", "csv")}
HELP_CASES = [(v,) + ((s,) if s else ()) for v in ALL_VERBS for s in SUBCOMMANDS.get(v, (None,))]


def _readme_verbs() -> set:
    """The verbs of the README's verb table (`| verb | what it does |`): every
    `magcal VERB` in its first column."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    start = next(i for i, ln in enumerate(lines)
                 if re.match(r"^\|\s*verb\s*\|\s*what it does\s*\|", ln))
    verbs = set()
    for ln in lines[start + 2:]:
        if not ln.startswith("|"):
            break
        verbs |= set(re.findall(r"`magcal ([a-z]+)\b", ln.split("|")[1]))
    return verbs


def test_the_readme_verbs_are_the_cli_verbs():
    assert _readme_verbs() == set(ALL_VERBS) == set(VERBS)


@pytest.mark.parametrize("argv", HELP_CASES, ids=" ".join)
def test_help_names_quiet_and_json(argv, capsys):
    """`--help` is a successful run (exit 0, cli.main returns it) with the usage on stdout
    and nothing on stderr."""
    assert main(list(argv) + ["--help"]) == 0
    cap = capsys.readouterr()
    assert cap.out.startswith("usage: magcal " + " ".join(argv))
    assert cap.err == ""
    for flag in ("-q, --quiet", "--json"):
        assert flag in cap.out, (argv, flag)


def test_import_help_names_its_subcommands(capsys):
    assert main(["import", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: magcal import")
    for sub in SUBCOMMANDS["import"]:
        assert sub in out


def _run(capsys, argv, quiet=True):
    """main(argv + -q --json): (exit status, parsed JSON, stderr)."""
    rc = main(argv + (["-q"] if quiet else []) + ["--json"])
    cap = capsys.readouterr()
    payload = json.loads(cap.out)         # stdout is one JSON document, nothing else
    return rc, payload, cap.err


@pytest.fixture(scope="module")
def example_coeffs():
    require(EXAMPLE_COEFFS.exists(), f"no committed example unit at {EXAMPLE_COEFFS}")
    return EXAMPLE_COEFFS


@pytest.fixture(scope="module")
def trace_case(tmp_path_factory):
    """A fast chamber campaign of three sensors; mpu1 couples to a heater current."""
    d = tmp_path_factory.mktemp("trace_case")
    u = sim.make_example_unit("cli_sat")
    unit = Unit(id=u.id, lab_field_nT=u.lab_field_nT, float_type=u.float_type,
                boom_reference="mmc1",
                sensors=tuple(s for s in u.sensors if s.name in ("mmc1", "mpu1", "mmc2")))
    truth = sim.random_truth(unit, np.random.default_rng(31))
    src = sim.SquareWave(250.0, 0.5, 0.4, 0.0, 0.0, 3)
    eff = [sim.ChannelBias("mpu1", "heater_A", (2000.0, 0, -900.0), src)]
    p, _ = sim.simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(1), d,
                                 effects=eff, fast=True, name="data")
    h, _ = sim.simulate_campaign("thermal_12pos", unit, truth, np.random.default_rng(2), d,
                                 effects=eff, fast=True, name="later")
    sim.write_unit_toml(unit, d / "unit.toml")
    return d / "unit.toml", p, h


def test_fit_apply_generate(fm1_dir, tmp_path, capsys):
    rc, j, err = _run(capsys, ["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "coils.csv"),
                               str(fm1_dir / "thermal_12pos.csv"), "-o", str(tmp_path / "fit")])
    assert rc == 0 and err == ""
    coeffs = tmp_path / "fit" / "coefficients.json"
    assert j["coefficients"] == str(coeffs) and coeffs.exists()
    assert set(j["sensors"]) == {"mmc1", "mpu1", "mpu2", "mmc2", "mpu3"}
    rc, j, err = _run(capsys, ["apply", str(coeffs), str(fm1_dir / "coils.csv"),
                               "-o", str(tmp_path / "cal.csv")], quiet=False)
    assert rc == 0 and (tmp_path / "cal.csv").exists() and isinstance(j, dict)
    assert err != ""                       # without -q the verb says what it does
    rc, j, err = _run(capsys, ["generate", str(coeffs), "-o", str(tmp_path / "c")])
    assert rc == 0 and err == "" and isinstance(j, dict)
    assert (tmp_path / "c" / "samsat_fm1_magcal.c").exists()


def test_plan_and_check(fm1_dir, tmp_path, capsys):
    rc, j, err = _run(capsys, ["plan", str(fm1_dir / "unit.toml"), "-o", str(tmp_path / "p")])
    assert rc == 0 and err == "" and isinstance(j, dict)
    assert (tmp_path / "p" / "plan.json").exists()
    # the coil steps alone do not cover the thermal program: exit 2, the gaps in the JSON
    rc, j, err = _run(capsys, ["check", str(fm1_dir / "unit.toml"), str(fm1_dir / "coils.csv")])
    assert rc == 2 and isinstance(j, dict) and j
    rc, j, _ = _run(capsys, ["check", str(fm1_dir / "unit.toml"),
                             str(fm1_dir / "thermal_12pos.csv")])
    assert rc in (0, 2) and isinstance(j, dict)


def test_table_through_main(example_coeffs, tmp_path, capsys):
    table = tmp_path / "t.bin"
    rc, j, err = _run(capsys, ["table", str(example_coeffs), "-o", str(table)])
    assert rc == 0 and err == "" and table.stat().st_size > 0 and isinstance(j, dict)
    rc, j, _ = _run(capsys, ["table", "--check", str(table), "--coeffs", str(example_coeffs)])
    assert rc == 0, j
    # a corrupted table: the flight validator rejects it, exit non-zero
    bad = bytearray(table.read_bytes())
    bad[len(bad) // 2] ^= 0x40
    (tmp_path / "bad.bin").write_bytes(bytes(bad))
    rc, j, _ = _run(capsys, ["table", "--check", str(tmp_path / "bad.bin"),
                             "--coeffs", str(example_coeffs)])
    assert rc != 0


@pytest.mark.parametrize("mode", ["decode", "diff", "encode_verbose"])
def test_table_json_stdout_is_only_json(example_coeffs, tmp_path, capsys, mode):
    table = tmp_path / "t.bin"
    assert main(["table", str(example_coeffs), "-o", str(table), "-q"]) == 0
    capsys.readouterr()
    argv = {"decode": (["table", "--decode", str(table)], True),
            "diff": (["table", "--diff", str(table), str(table)], True),
            "encode_verbose": (["table", str(example_coeffs), "-o", str(tmp_path / "u.bin")],
                               False)}[mode]
    rc, j, _ = _run(capsys, argv[0], quiet=argv[1])
    assert rc == 0 and isinstance(j, dict)


def test_trace_through_main(trace_case, tmp_path, capsys):
    unit_toml, data, later = trace_case
    out = tmp_path / "out"
    rc, j, err = _run(capsys, ["trace", str(unit_toml), str(data), "-o", str(out),
                               "--holdout", str(later)])
    assert rc == 0 and err == ""
    assert isinstance(j, dict)
    written = json.loads((out / "trace.json").read_text())
    effects = [(e["sensor"], e["effect"], e["explained_by"]) for e in written["effects"]]
    assert effects == [("mpu1", "channel_bias", ["heater_A"])]


def test_demo(tmp_path, capsys):
    # the demo's result table is its output (on stderr under --json), not progress
    rc, j, _ = _run(capsys, ["demo", "-o", str(tmp_path / "demo")])
    assert rc == 0 and j["exit"] == 0
    assert (tmp_path / "demo" / "report.html").exists()


def test_bad_input_with_json_is_one_line_and_a_json_error(tmp_path, capsys):
    rc = main(["generate", str(tmp_path / "missing.json"), "-o", str(tmp_path / "o"), "--json"])
    cap = capsys.readouterr()
    assert rc == 2
    assert len(cap.err.strip().splitlines()) == 1 and "missing.json" in cap.err
    j = json.loads(cap.out)
    assert j["exit"] == 2 and j["verb"] == "generate"
