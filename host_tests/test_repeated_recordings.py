"""Each recording counts once (generator.io.recordings): fit, check and trace refuse, before
reading anything, two inputs that hold the same bytes -- the same path twice, a copy under
another name, a link -- with exit 2 and one line naming the later path and the first.
Distinct files, of equal size included, pass; a path that cannot be read is left to the
reader's own message."""

from __future__ import annotations

import os
import shutil

import pytest

from generator.cli import main
from generator.errors import InputError
from generator.io.recordings import refuse_repeated_recordings

FM1 = "/work/shared/data/samsat_fm1"


def _fm1(name):
    path = os.path.join(FM1, name)
    if not os.path.exists(path):
        pytest.skip(f"no shared data at {path}")
    return path


def _one_line_error(capsys, argv):
    rc = main(argv + ["-q"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("verb", ["fit", "check", "trace"])
def test_a_copy_is_refused_by_every_verb_that_pools_recordings(tmp_path, capsys, verb):
    unit, data = _fm1("unit.toml"), _fm1("flight_6h.csv" if verb == "trace"
                                         else "thermal_12pos.csv")
    copy = tmp_path / "copy.csv"
    shutil.copyfile(data, copy)
    argv = [verb, unit, data, str(copy)]
    if verb != "check":
        argv += ["-o", str(tmp_path / "out")]
    line = _one_line_error(capsys, argv)
    assert line.startswith(f"magcal {verb}: {copy}: the same recording as {data}"), line
    assert "identical bytes" in line
    assert not (tmp_path / "out").exists()          # refused before anything is written


def test_the_same_path_twice_and_a_link(tmp_path, capsys):
    unit, data = _fm1("unit.toml"), _fm1("thermal_12pos.csv")
    line = _one_line_error(capsys, ["fit", unit, data, data, "-o", str(tmp_path / "o")])
    assert "the same file given twice" in line
    link = tmp_path / "link.csv"
    os.symlink(data, link)
    line = _one_line_error(capsys, ["fit", unit, str(link), data, "-o", str(tmp_path / "o")])
    assert f": {data}: the same recording as {link} (the same file given twice)" in line


def test_distinct_files_of_equal_size_pass(tmp_path):
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    a.write_bytes(b"time_s\n0.0\n1.0\n")
    b.write_bytes(b"time_s\n0.0\n2.0\n")           # same size, one byte differs
    c.write_bytes(b"time_s\n0.0\n1.0\n\n")         # same text and one more byte
    refuse_repeated_recordings([a, b, c])
    with pytest.raises(InputError) as e:
        refuse_repeated_recordings([a, b, c, tmp_path / "missing.csv", a])
    assert e.value.path == str(a)


def test_an_unreadable_path_is_left_to_the_reader(tmp_path, capsys):
    unit, data = _fm1("unit.toml"), _fm1("thermal_12pos.csv")
    missing = tmp_path / "missing.csv"
    refuse_repeated_recordings([missing, missing, tmp_path])   # nothing to compare
    line = _one_line_error(capsys, ["fit", unit, data, str(missing), "-o",
                                    str(tmp_path / "o")])
    assert str(missing) in line and "same recording" not in line



def test_a_held_out_file_that_the_trace_also_fits_is_refused(tmp_path, capsys):
    unit, data = _fm1("unit.toml"), _fm1("flight_6h.csv")
    copy = tmp_path / "copy.csv"
    shutil.copyfile(data, copy)
    line = _one_line_error(capsys, ["trace", unit, data, "-o", str(tmp_path / "out"),
                                    "--holdout", str(copy)])
    assert line.startswith(f"magcal trace: {copy}: held-out file: the same recording as "
                           f"{data} (identical bytes), which the fit uses"), line
    # two held-out copies of one recording: the plain rule (they would count twice)
    other = tmp_path / "other.csv"
    shutil.copyfile(copy, other)
    with pytest.raises(InputError, match="count twice"):
        refuse_repeated_recordings([], held_out=[copy, other])
    assert not (tmp_path / "out").exists()
