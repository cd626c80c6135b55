"""Parquet columns of other types than numbers (bool, timestamps, ...) that the chain does
not read are left out with a note, as a CSV's text column is (review 20f N5: a timestamp
column made the whole file exit 2 where the same values in CSV were left out); a named
column of such a type is still refused naming the column."""

from __future__ import annotations

import os

import numpy as np
import pytest

from generator.cli import main

FM1 = "/work/shared/data/samsat_fm1"
COEFFS = os.path.join(os.path.dirname(__file__), "..", "generated", "samsat_fm1",
                      "coefficients.json")


def _parquet(tmp_path, extra):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    src = os.path.join(FM1, "flight_6h.csv")
    if not os.path.exists(src):
        pytest.skip("no shared data")
    tel = read_telemetry(src, load_unit(os.path.join(FM1, "unit.toml")))
    n = 500
    cols = {c: pa.array(v[:n]) for c, v in tel.columns.items()}
    cols.update({k: f(pa, n) for k, f in extra.items()})
    p = tmp_path / "t.parquet"
    pq.write_table(pa.table(cols), p)
    return p


@pytest.mark.parametrize("kind", ["bool", "timestamp", "date"])
def test_an_unused_column_of_another_type_is_left_out(tmp_path, capsys, kind):
    make = {"bool": lambda pa, n: pa.array(np.arange(n) % 2 == 0),
            "timestamp": lambda pa, n: pa.array(np.arange(n).astype("datetime64[ms]")),
            "date": lambda pa, n: pa.array(np.arange(n).astype("datetime64[D]"))}[kind]
    p = _parquet(tmp_path, {"odd": make})
    rc = main(["apply", COEFFS, str(p), "-o", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert f"{p}: column 'odd': text (Parquet type " in err and "): not used" in err


def test_a_named_column_of_another_type_is_refused(tmp_path, capsys):
    p = _parquet(tmp_path, {"position": lambda pa, n: pa.array(np.arange(n) % 2 == 0)})
    rc = main(["apply", COEFFS, str(p), "-o", str(tmp_path / "o.csv"), "-q"])
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "column 'position'" in lines[0], lines
