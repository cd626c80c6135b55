"""The same recording gives the same blocks above the fit's read cap whatever its line
endings (review 20f N2: a CR-only copy kept 399 blocks where the LF file kept 400, and 505
of 714 coefficients differed): the file's row bound discounts its final line break, CR
included."""

from __future__ import annotations

import os

import pytest

from generator import pipeline

FM1 = "/work/shared/data/samsat_fm1"


@pytest.mark.parametrize("ending", [b"\r", b"\r\n"])
def test_line_endings_do_not_change_the_blocks(tmp_path, ending):
    src = os.path.join(FM1, "thermal_12pos.csv")
    if not os.path.exists(src):
        pytest.skip("no shared data")
    lf = tmp_path / "lf.csv"
    other = tmp_path / "other.csv"
    raw = open(src, "rb").read()
    lf.write_bytes(raw)
    other.write_bytes(raw.replace(b"\n", ending))
    unit = os.path.join(FM1, "unit.toml")
    a = pipeline.fit(unit, [str(lf)], max_rows=20_000)
    b = pipeline.fit(unit, [str(other)], max_rows=20_000)
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    a.save(pa)
    b.save(pb)
    ta = pa.read_text().replace(str(lf), "F")
    tb = pb.read_text().replace(str(other), "F")
    assert "read cap" in ta
    assert ta == tb
