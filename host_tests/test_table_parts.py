"""`magcal table --check` on parts and `magcal table --join` (review of issue 18, #14):
a valid part is not a BAD_MAGIC table; the parts of a table reassemble into it, checked
as on board. Data: the committed example unit's coefficients (generated/samsat_fm1)."""

from __future__ import annotations

from pathlib import Path

import pytest

from generator.cli import main

COEFFS = Path(__file__).resolve().parents[1] / "generated" / "samsat_fm1" / "coefficients.json"


@pytest.fixture()
def parts(tmp_path):
    assert main(["table", str(COEFFS), "-o", str(tmp_path / "t.bin"), "--serial", "7",
                 "--chunk", "200", "-q"]) == 0
    ps = sorted(tmp_path.glob("t.part*.bin"))
    assert len(ps) > 2
    return tmp_path / "t.bin", ps


def test_check_one_part(parts, capsys):
    _, ps = parts
    assert main(["table", "--check", str(ps[1]), "--coeffs", str(COEFFS)]) == 0
    out = capsys.readouterr().out
    assert "part checks" in out and f"of {len(ps)}" in out


def test_check_all_parts_validates_the_table(parts, capsys):
    _, ps = parts
    assert main(["table", "--check", *map(str, ps), "--coeffs", str(COEFFS)]) == 0
    assert "accepted by the flight validator" in capsys.readouterr().out


def test_damaged_part_is_refused(parts, tmp_path, capsys):
    _, ps = parts
    bad = tmp_path / "bad.part.bin"
    data = bytearray(ps[1].read_bytes())
    data[20] ^= 0x01                               # one bit of the payload: the CRC fails
    bad.write_bytes(bytes(data))
    assert main(["table", "--check", str(bad), "--coeffs", str(COEFFS)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "PART_BAD_CRC" in err[0] and str(bad) in err[0]


def test_join_reassembles_the_table(parts, tmp_path):
    table, ps = parts
    out = tmp_path / "joined.bin"
    assert main(["table", "--join", *map(str, reversed(ps)), "-o", str(out),
                 "--coeffs", str(COEFFS), "-q"]) == 0
    assert out.read_bytes() == table.read_bytes()


def test_join_with_a_part_missing_writes_nothing(parts, tmp_path, capsys):
    _, ps = parts
    out = tmp_path / "joined.bin"
    assert main(["table", "--join", *map(str, ps[:-1]), "-o", str(out),
                 "--coeffs", str(COEFFS), "-q"]) == 2
    assert "PARTS_MISSING" in capsys.readouterr().err and not out.exists()
