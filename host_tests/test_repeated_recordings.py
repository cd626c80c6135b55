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


# ---- rows repeated in part (overlapping recordings) --------------------------------------

import numpy as np  # noqa: E402
from hypothesis import given, settings, strategies as st  # noqa: E402

from generator.io.recordings import repeated_rows, repeated_rows_warnings  # noqa: E402
from generator.io.telemetry import Telemetry  # noqa: E402


def _tel(path, time_s, values, first_line=2):
    cols = {"time_s": np.asarray(time_s, float)}
    cols.update({f"c{k}": np.asarray(v, float) for k, v in enumerate(values)})
    return Telemetry(str(path), cols, np.arange(first_line, first_line + len(time_s)))


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 60), overlap=st.integers(0, 20), cols=st.integers(1, 4),
       seed=st.integers(0, 2**31 - 1))
def test_an_overlap_is_counted_row_for_row(n, overlap, cols, seed):
    """A recording cut in two with `overlap` rows in both: exactly those rows are found,
    from the first line of the second file; no noise row is ever taken for a repeat."""
    rng = np.random.default_rng(seed)
    overlap = min(overlap, n - 1)
    t = np.cumsum(rng.uniform(0.01, 1.0, 2 * n))
    v = rng.normal(size=(cols, 2 * n))
    a = _tel("a.csv", t[:n], v[:, :n])
    b = _tel("b.csv", t[n - overlap:], v[:, n - overlap:], first_line=10)
    found = repeated_rows([a, b])
    if overlap:
        assert found == [{"path": "b.csv", "rows": overlap, "first_line": 10, "of": "a.csv"}]
    else:
        assert found == []


def test_a_row_written_twice_and_rows_that_only_share_a_time():
    t = np.array([0.0, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0])
    v = np.array([[5.0, 6.0, 6.0, 7.0, 8.0, 7.0, 9.0]])     # line 3 repeats line 2
    found = repeated_rows([_tel("c.csv", t, v)])             # line 7 repeats line 5
    assert found == [{"path": "c.csv", "rows": 2, "first_line": 4, "of": "c.csv"}]
    # the same times with other values: nothing (a coarse clock, not a repeat)
    assert repeated_rows([_tel("d.csv", t, [[1.0, 2, 3, 4, 5, 6, 7]])]) == []


def test_nan_and_signed_zero_compare_as_values_and_unshared_columns_do_not_count():
    t = [0.0, 1.0]
    a = _tel("a.csv", t, [[np.nan, 0.0], [1.0, 2.0]])
    b = _tel("b.csv", [1.0, 2.0], [[-0.0, 3.0], [2.0, 4.0]])
    assert repeated_rows([a, b]) == [{"path": "b.csv", "rows": 1, "first_line": 2,
                                      "of": "a.csv"}]
    # only time_s shared: two runs that both start at 0 are not repeats of each other
    c = Telemetry("c.csv", {"time_s": np.array([0.0, 1.0]), "x": np.array([1.0, 2.0])},
                  np.array([2, 3]))
    d = Telemetry("d.csv", {"time_s": np.array([0.0, 1.0]), "y": np.array([1.0, 2.0])},
                  np.array([2, 3]))
    assert repeated_rows([c, d]) == []
    assert repeated_rows([]) == []


def test_fit_says_an_overlap_in_its_output(tmp_path, capsys):
    unit, data = _fm1("unit.toml"), _fm1("thermal_12pos.csv")
    lines = open(data).read().splitlines(True)
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("time_s")]
    body = lines[len(head):]
    assert len(head) + len(body) == len(lines)
    (tmp_path / "t1.csv").write_text("".join(head + body[:20000]))
    (tmp_path / "t2.csv").write_text("".join(head + body[19000:]))
    rc = main(["fit", unit, str(tmp_path / "t1.csv"), str(tmp_path / "t2.csv"), "-o",
               str(tmp_path / "out"), "--no-report"])
    err = capsys.readouterr().err
    assert rc == 0
    want = (f"WARNING: {tmp_path / 't2.csv'}: 1000 row(s) from line {len(head) + 1} repeat "
            f"rows of {tmp_path / 't1.csv'}")
    assert want in err
    import json
    notes = json.loads((tmp_path / "out" / "coefficients.json").read_text())["fit"]["notes"]
    assert any(n.startswith(want) for n in notes)


def _split_with_overlap(tmp_path, data, cut, overlap):
    lines = open(data).read().splitlines(True)
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("time_s")]
    body = lines[len(head):]
    (tmp_path / "p1.csv").write_text("".join(head + body[:cut]))
    (tmp_path / "p2.csv").write_text("".join(head + body[cut - overlap:]))
    return tmp_path / "p1.csv", tmp_path / "p2.csv", len(head) + 1


def test_a_capped_trace_warns_from_the_fingerprints_it_holds(tmp_path, capsys):
    """Above the cap the trace holds files by rows (trace.filerows.FileRows, never the
    whole file): the overlap is still found, from the fingerprints held per row."""
    unit, data = _fm1("unit.toml"), _fm1("flight_6h.csv")
    coeffs = os.path.join(os.path.dirname(__file__), "..", "generated", "samsat_fm1",
                          "coefficients.json")
    p1, p2, line = _split_with_overlap(tmp_path, data, 6000, 1000)
    from generator.io.unitfile import load_unit
    from generator.trace.filerows import FileRows
    held = [FileRows(str(p), load_unit(unit)) for p in (p1, p2)]
    assert repeated_rows(held) == [{"path": str(p2), "rows": 1000, "first_line": line,
                                    "of": str(p1)}]
    rc = main(["trace", unit, str(p1), str(p2), "-o", str(tmp_path / "out"),
               "--max-samples", "6000", "--coeffs", coeffs, "-q"])
    capsys.readouterr()
    assert rc == 0
    import json
    warnings = json.loads((tmp_path / "out" / "trace.json").read_text())["warnings"]
    assert any(w.startswith(f"WARNING: {p2}: 1000 row(s) from line {line} repeat rows "
                            f"of {p1}") for w in warnings), warnings


def test_a_held_out_file_with_the_fitted_rows_in_other_bytes_is_refused(tmp_path, capsys):
    """Review 20f N3: a held-out copy in other bytes (CR LF line endings here) of a fitted
    recording was only warned about, as rows counted twice; it holds nothing out."""
    unit, data = _fm1("unit.toml"), _fm1("flight_6h.csv")
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(open(data, "rb").read().replace(b"\n", b"\r\n"))
    line = _one_line_error(capsys, ["trace", unit, data, "-o", str(tmp_path / "out"),
                                    "--holdout", str(crlf)])
    assert line.startswith(f"magcal trace: {crlf}: held-out file: "), line
    assert f"repeat rows of {data}, which the fit uses" in line
    assert not (tmp_path / "out").exists()


# ---- above the fit's read cap: every row, streamed (review 20f N1) -----------------------

from generator.io.recordings import StreamedRepeats  # noqa: E402


def _pieces(tel, size):
    for a in range(0, tel.n, size):
        idx = np.arange(a, min(tel.n, a + size))
        yield Telemetry(tel.path, {c: v[idx] for c, v in tel.columns.items()},
                        tel.line_numbers[idx])


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 50), overlap=st.integers(0, 20), twice=st.integers(0, 3),
       piece=st.integers(1, 17), seed=st.integers(0, 2**31 - 1))
def test_streamed_repeats_find_what_repeated_rows_finds(n, overlap, twice, piece, seed):
    """Fed piece by piece (pieces of any size), StreamedRepeats finds what repeated_rows
    finds on the whole files: an overlap between files and rows written twice, whatever
    piece they fall in."""
    rng = np.random.default_rng(seed)
    overlap = min(overlap, n - 1)
    t = np.cumsum(rng.uniform(0.01, 1.0, 2 * n))
    v = rng.normal(size=(2, 2 * n))
    a_rows = np.arange(n)
    dup = np.sort(rng.choice(n, size=min(twice, n), replace=False))
    a_rows = np.sort(np.concatenate([a_rows, dup]))            # rows written twice in a
    a = _tel("a.csv", t[a_rows], v[:, a_rows])
    b = _tel("b.csv", t[n - overlap:], v[:, n - overlap:], first_line=10)
    want = repeated_rows([a, b])
    sr = StreamedRepeats(["a.csv", "b.csv"], [(a.time_s[0], a.time_s[-1]),
                                              (b.time_s[0], b.time_s[-1])],
                         [tuple(a.columns), tuple(b.columns)])
    for j, tel in enumerate((a, b)):
        for p in _pieces(tel, piece):
            sr.add(j, p)
    key = lambda r: (r["path"], r["of"])  # noqa: E731
    assert sorted(sr.findings(), key=key) == sorted(want, key=key)


def test_a_capped_fit_warns_on_overlaps_among_rows_it_did_not_read(tmp_path):
    """Review 20f N1: above the read cap the fit keeps blocks; an overlap outside them went
    unseen. Now the every-row pass finds it, and the fit's notes say it."""
    from generator import pipeline
    unit, data = _fm1("unit.toml"), _fm1("thermal_12pos.csv")
    lines = open(data).read().splitlines(True)
    head = [ln for ln in lines if ln.startswith("#") or ln.startswith("time_s")]
    body = lines[len(head):]
    (tmp_path / "t1.csv").write_text("".join(head + body[:30000]))
    (tmp_path / "t2.csv").write_text("".join(head + body[29000:31000]))
    cs = pipeline.fit(unit, [str(tmp_path / "t1.csv"), str(tmp_path / "t2.csv")],
                      max_rows=5000)
    notes = cs.fit_info["notes"]
    assert any(n.startswith("read cap:") for n in notes)
    want = (f"WARNING: {tmp_path / 't2.csv'}: 1000 row(s) from line {len(head) + 1} repeat "
            f"rows of {tmp_path / 't1.csv'}")
    assert any(n.startswith(want) for n in notes), notes
