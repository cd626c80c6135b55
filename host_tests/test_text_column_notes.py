"""A text column the chain does not read (ICD 2: "anything else: further telemetry") is left
out by the reader (io.telemetry_csv, review 20e F7) and every verb that reads telemetry
says so: apply, fit, check and trace, one line naming the file, the column and the first
non-number with its line."""

from __future__ import annotations

import json
import os

import pytest

from generator.cli import main

FM1 = "/work/shared/data/samsat_fm1"
COEFFS = os.path.join(os.path.dirname(__file__), "..", "generated", "samsat_fm1",
                      "coefficients.json")


@pytest.fixture(scope="module")
def with_text(tmp_path_factory):
    src = os.path.join(FM1, "flight_6h.csv")
    if not os.path.exists(src):
        pytest.skip("no shared data")
    out, header = [], False
    for i, line in enumerate(open(src).read().splitlines(True)):
        if line.startswith("#"):
            out.append(line)
        elif not header:
            out.append(line.rstrip("\n") + ",mode\n")
            header = True
        else:
            out.append(line.rstrip("\n") + (",SAFE\n" if i % 2 else ",NOMINAL\n"))
    p = tmp_path_factory.mktemp("text") / "txt.csv"
    p.write_text("".join(out))
    first = next(i for i, ln in enumerate(out) if not ln.startswith("#")) + 2
    word = "SAFE" if (first - 1) % 2 else "NOMINAL"
    return p, f"{p}: column 'mode': text (first non-number '{word}' at line {first}): not used"


@pytest.mark.parametrize("verb", ["apply", "fit", "check", "trace"])
def test_every_verb_says_the_text_column_it_left_out(verb, with_text, tmp_path, capsys):
    path, note = with_text
    unit = os.path.join(FM1, "unit.toml")
    argv = {"apply": ["apply", COEFFS, str(path), "-o", str(tmp_path / "o.csv")],
            "fit": ["fit", unit, str(path), "-o", str(tmp_path / "fit"), "--no-report"],
            "check": ["check", unit, str(path)],
            "trace": ["trace", unit, str(path), "-o", str(tmp_path / "tr"), "--coeffs",
                      COEFFS, "--max-samples", "5000"]}[verb]
    rc = main(argv)
    cap = capsys.readouterr()
    assert rc in ((0, 2) if verb == "check" else (0,)), cap.err[-2000:]
    assert note in cap.err + cap.out
    if verb == "fit":
        notes = json.loads((tmp_path / "fit" / "coefficients.json").read_text())["fit"]["notes"]
        assert note in notes
    if verb == "trace":
        assert note in json.loads((tmp_path / "tr" / "trace.json").read_text())["notes"]
