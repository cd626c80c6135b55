"""Regression tests of issue 14 (hardening) and issue 15 item 5 (names): one class of fault
per test, each through `magcal` in-process: exit 2 with one line naming the file and the
key, line or column, nothing written; or exit 0 with sane output."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import stat
from pathlib import Path

import numpy as np
import pytest

from hardening_fixtures import (BASE_COEFFS, REPO, assert_bad_input, csv_slice, run,
                                shared_fm1)

from generator.errors import InputError
from generator.io import names
from generator.io.outputs import atomic_file, output_folder


@pytest.fixture(scope="module")
def fm1():
    return shared_fm1()


@pytest.fixture(scope="module")
def unit_text(fm1):
    return (fm1 / "unit.toml").read_text()


@pytest.fixture(scope="module")
def base_doc():
    return json.loads(BASE_COEFFS.read_text())


def listing(folder: Path) -> list:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ---- names (issue 15 item 5, issue 14 item 3) --------------------------------------------

BAD_SENSOR_NAMES = ["int", "if", "double", "while", "unit", "table_off", "table", "sel",
                    "status", "select_x", "coeffs", "real", "bool", "Mpu", "9a", "a-b",
                    "x" * 25]


@pytest.mark.parametrize("bad", BAD_SENSOR_NAMES)
def test_bad_sensor_name_is_refused_at_the_unit_file(tmp_path, unit_text, bad):
    unit = tmp_path / "unit.toml"
    unit.write_text(unit_text.replace('name = "mpu2"', f'name = "{bad}"', 1))
    line = assert_bad_input(run(["plan", unit, "-o", tmp_path / "out", "-q"]), str(unit),
                            "name")
    assert bad[:20] in line
    assert not (tmp_path / "out").exists()


def test_bad_unit_id_and_prefix_collision(tmp_path, unit_text):
    unit = tmp_path / "unit.toml"
    unit.write_text(unit_text.replace('id = "samsat_fm1"', 'id = "struct"', 1))
    assert_bad_input(run(["plan", unit, "-o", tmp_path / "o"]), "id", "C keyword")
    # sensor a and a_set: <unit>_a_set_raw_t would be defined twice
    unit.write_text(unit_text.replace('name = "mpu1"', 'name = "mpu"', 1)
                    .replace('name = "mpu2"', 'name = "mpu_set"', 1))
    assert_bad_input(run(["plan", unit, "-o", tmp_path / "o"]), "mpu_set", "collide")


def test_every_generated_api_name_is_reserved():
    """Every identifier the templates define after the unit prefix is a name (or the start
    of a name) that names.reserved_reason refuses: a new API name cannot slip through."""
    words = set()
    for f in (REPO / "templates").rglob("*.j2"):
        for m in re.finditer(r"\{\{-? *(unit|UNIT) *-?\}\}_([A-Za-z0-9_]*)(\{\{)?",
                             f.read_text()):
            w = m.group(2).lower().rstrip("_")
            if w:
                words.add(w)
    assert len(words) > 50        # the scan sees the API (table, status, select, ...)
    unreserved = [w for w in sorted(words) if names.reserved_reason(w) is None]
    assert not unreserved, unreserved
    # and the prefix rule: the first word of each is refused as a sensor name too
    assert all(names.reserved_reason(w.split("_")[0]) for w in words)


def test_set_reset_as_a_string_is_refused(tmp_path, unit_text):
    unit = tmp_path / "unit.toml"
    unit.write_text(unit_text.replace("set_reset = true", 'set_reset = "false"', 1))
    assert_bad_input(run(["plan", unit, "-o", tmp_path / "o"]), "set_reset", "true or false")


# ---- coefficients.json is untrusted (issue 14 item 2) ------------------------------------

def _tamper(doc, how):
    d = json.loads(json.dumps(doc))
    s0 = d["unit"]["sensors"][0]["name"]
    if how == "unknown part":
        d["unit"]["sensors"][0]["part"] = "XYZ-1"
    elif how == "sensors as list":
        d["sensors"] = list(d["sensors"].values())
    elif how == "unit sensors as dict":
        d["unit"]["sensors"] = {"a": 1}
    elif how == "bad sensor name":
        d["unit"]["sensors"][0]["name"] = "m */ int x; /*"
    elif how == "keyword sensor name":
        d["unit"]["sensors"][0]["name"] = "int"
    elif how == "coefficient 1e300":
        d["sensors"][s0]["b_poly_nT"][0][0] = 1e300
    elif how == "coefficient 1e39 (beyond float32)":
        d["sensors"][s0]["K_nT_per_A"][0][0] = 1e39
    elif how == "injected coil name":
        d["chain"]["coils"][2] = "coil_z */ * 100 /*_A"
    elif how == "injected channel name":
        d["chain"]["sensor_options"] = {s0: {"channels": ["x */ #include </etc/passwd> /*"]}}
    elif how == "unknown option":
        d["chain"]["sensor_options"] = {s0: {"hack": True}}
    elif how == "options for an unknown sensor":
        d["chain"]["sensor_options"] = {"nobody": {}}
    elif how == "unknown sensor block":
        d["sensors"][s0]["evil"] = 1.0
    elif how == "unknown sensor":
        d["sensors"]["ghost"] = d["sensors"][s0]
    elif how == "bool as number":
        d["sensors"][s0]["t_ref_C"] = True
    elif how == "H scaled by 1.2":
        d["unit_coefficients"]["H_boom_to_body"] = (
            np.array(d["unit_coefficients"]["H_boom_to_body"]) * 1.2).tolist()
    elif how == "M singular":
        d["sensors"][s0]["M_poly"][0] = [[0.0] * 3] * 3
    elif how == "M reflection":
        d["sensors"][s0]["M_poly"][0][0] = [-x for x in d["sensors"][s0]["M_poly"][0][0]]
    elif how == "temperature 1e6":
        d["sensors"][s0]["t_max_C"] = 1e6
    elif how == "poly degree as string":
        d["chain"]["poly_degree"] = "3"
    elif how == "string shape":
        d["sensors"][s0]["M_poly"] = "abc"
    elif how == "set_reset as string":
        d["unit"]["sensors"][0]["set_reset"] = "false"
    else:
        raise AssertionError(how)
    return d


TAMPERS = ["unknown part", "sensors as list", "unit sensors as dict", "bad sensor name",
           "keyword sensor name", "coefficient 1e300", "coefficient 1e39 (beyond float32)",
           "injected coil name", "injected channel name", "unknown option",
           "options for an unknown sensor", "unknown sensor block", "unknown sensor",
           "bool as number", "H scaled by 1.2", "M singular", "M reflection",
           "temperature 1e6", "poly degree as string", "string shape",
           "set_reset as string"]


@pytest.mark.parametrize("how", TAMPERS)
def test_tampered_coefficients_are_refused_by_every_verb(tmp_path, base_doc, how):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(_tamper(base_doc, how)))
    for argv in (["generate", path, "-o", tmp_path / "gen", "--compile"],
                 ["table", path, "-o", tmp_path / "t.bin"],
                 ["apply", path, tmp_path / "nodata.csv", "-o", tmp_path / "out.csv"]):
        assert_bad_input(run(argv), str(path))
    assert listing(tmp_path) == ["c.json"]


def test_injected_coil_column_in_a_campaign_is_refused(tmp_path, fm1):
    """A CSV column `coil_z */ * 100 /*_A` must not become a coil of the flight C."""
    text = csv_slice(fm1 / "coils.csv", every=2)
    text = text.replace("coil_z_A", "coil_z */ * 100 /*_A", 1)
    data = tmp_path / "coils.csv"
    data.write_text(text)
    assert_bad_input(run(["fit", fm1 / "unit.toml", data, "-o", tmp_path / "fit", "-q"]),
                     "coil column", "C identifier")
    assert not (tmp_path / "fit").exists()


def test_generated_c_holds_only_validated_text(tmp_path, base_doc):
    """Every comment of the generated C: no text from the file that is not a validated
    name or a number the generator formatted (the file's free text, `fit`, stays out)."""
    d = json.loads(json.dumps(base_doc))
    d["fit"] = {"notes": ["*/ int injected; /*"], "sources": ["*/ evil /*"]}
    path = tmp_path / "c.json"
    path.write_text(json.dumps(d))
    rc, _, err = run(["generate", path, "-o", tmp_path / "gen", "-q"])
    assert rc == 0, err
    text = "".join(p.read_text() for p in (tmp_path / "gen").iterdir())
    assert "injected" not in text and "evil" not in text


# ---- outputs: atomic, never where a folder or file is ------------------------------------

def test_output_paths_that_cannot_be_outputs(tmp_path, fm1):
    afile = tmp_path / "afile"
    afile.write_text("x")
    adir = tmp_path / "adir"
    adir.mkdir()
    c = BASE_COEFFS
    cases = [["table", c, "-o", adir], ["table", c, "-o", afile / "t.bin"],
             ["generate", c, "-o", afile], ["generate", c, "-o", afile / "sub"],
             ["apply", c, fm1 / "coils.csv", "-o", adir],
             ["plan", fm1 / "unit.toml", "-o", afile],
             ["fit", fm1 / "unit.toml", fm1 / "coils.csv", "-o", afile / "x"],
             ["trace", fm1 / "unit.toml", fm1 / "coils.csv", "-o", afile],
             ["demo", "-o", afile], ["demo", "-o", afile / "d"]]
    for argv in cases:
        assert_bad_input(run(argv + ["-q"]), "output")
    assert listing(tmp_path) == ["adir", "afile"]
    assert afile.read_text() == "x"


def test_table_dump_never_overwrites_the_table(tmp_path):
    assert_bad_input(run(["table", BASE_COEFFS, "-o", tmp_path / "t.txt"]), ".txt")
    assert listing(tmp_path) == []


def test_table_chunk_too_small_writes_nothing(tmp_path):
    assert_bad_input(run(["table", BASE_COEFFS, "-o", tmp_path / "t.bin", "--chunk", "10"]),
                     "--chunk 10")
    assert listing(tmp_path) == []
    rc, _, err = run(["table", BASE_COEFFS, "-o", tmp_path / "t.bin", "--chunk", "200", "-q"])
    assert rc == 0, err
    assert "t.bin" in listing(tmp_path) and "t.txt" in listing(tmp_path)
    assert not [p for p in listing(tmp_path) if p.startswith(".")]


def test_atomic_file_and_folder_leave_nothing_on_error(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_file(target) as f:
            f.write("new, half")
            raise RuntimeError("boom")
    assert target.read_text() == "old" and listing(tmp_path) == ["f.txt"]
    with pytest.raises(RuntimeError):
        with output_folder(tmp_path / "a" / "b") as of:
            (of.tmp / "x.txt").write_text("x")
            raise RuntimeError("boom")
    assert listing(tmp_path) == ["f.txt"]
    with output_folder(tmp_path / "a" / "b") as of:
        (of.tmp / "x.txt").write_text("x")
    assert (tmp_path / "a" / "b" / "x.txt").read_text() == "x"
    with output_folder(tmp_path / "a" / "b") as of:       # into an existing folder
        (of.tmp / "y.txt").write_text("y")
    assert listing(tmp_path / "a" / "b") == ["x.txt", "y.txt"]
    assert listing(tmp_path / "a") == ["b", "b/x.txt", "b/y.txt"]


# ---- apply: coils, missing samples, nothing left behind ----------------------------------

@pytest.fixture(scope="module")
def flight_slice(fm1, tmp_path_factory):
    d = tmp_path_factory.mktemp("flight")
    p = d / "flight.csv"
    p.write_text(csv_slice(fm1 / "flight_6h.csv", rows=40))
    return p


def test_apply_without_coil_columns_is_refused(tmp_path, flight_slice):
    lines = flight_slice.read_text().splitlines()
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    cols = lines[hi].split(",")
    keep = [j for j, c in enumerate(cols) if not c.startswith("coil_")]
    out = lines[:hi] + [",".join(r.split(",")[j] for j in keep) for r in lines[hi:]]
    data = tmp_path / "nocoil.csv"
    data.write_text("\n".join(out) + "\n")
    assert_bad_input(run(["apply", BASE_COEFFS, data, "-o", tmp_path / "o.csv"]),
                     "coil_x_A", "never assumed")
    assert listing(tmp_path) == ["nocoil.csv"]
    # with --coils-off the user states the currents were 0 A
    rc, _, err = run(["apply", BASE_COEFFS, data, "-o", tmp_path / "o.csv", "--coils-off",
                      "-q"])
    assert rc == 0, err


def test_missing_samples_are_not_status_zero(tmp_path, flight_slice):
    lines = flight_slice.read_text().splitlines()
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    cols = lines[hi].split(",")
    j = cols.index("mpu1_x")
    row = lines[hi + 5].split(",")
    row[j] = ""
    lines[hi + 5] = ",".join(row)
    data = tmp_path / "gap.csv"
    data.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.csv"
    rc, _, err = run(["apply", BASE_COEFFS, data, "-o", out, "-q"])
    assert rc == 0, err
    text = out.read_text().splitlines()
    body = [ln for ln in text if not ln.startswith("#")]
    header = body[0].split(",")
    assert len(set(header)) == len(header)
    rows = [r.split(",") for r in body[1:]]
    valid, status = header.index("mpu1_valid"), header.index("mpu1_status")
    for r in rows:     # the header's promise: valid means status 0, both ways
        assert (r[valid] == "1") == (r[status] == "0"), r
    assert rows[4][valid] == "0" and int(rows[4][status]) & 0x8000
    assert not [p for p in listing(tmp_path) if p.startswith(".") or p.endswith(".part")]


# ---- telemetry: absurd values, long cells ------------------------------------------------

@pytest.mark.parametrize("column,value,verb", [("ref_x_nT", "1e300", "fit"),
                                               ("mmc1_temp_C", "1e300", "trace"),
                                               ("mmc1_temp_C", "-1e6", "fit"),
                                               ("mpu1_temp_C", "-300", "check"),
                                               ("ref_z_nT", "-2e7", "check"),
                                               ("time_s", "1e300", "fit")])
def test_absurd_values_name_the_row(tmp_path, fm1, column, value, verb):
    lines = csv_slice(fm1 / "thermal_12pos.csv", every=60).splitlines()
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    cols = lines[hi].split(",")
    r = lines[-1].split(",")
    r[cols.index(column)] = value
    lines[-1] = ",".join(r)
    data = tmp_path / "d.csv"
    data.write_text("\n".join(lines) + "\n")
    argv = [verb, fm1 / "unit.toml", data] + ([] if verb == "check" else
                                              ["-o", tmp_path / "o"])
    assert_bad_input(run(argv + ["-q"]), f"d.csv:{len(lines)}", column)
    assert not (tmp_path / "o").exists()


def test_a_60kB_cell_is_rejected_without_backtracking(tmp_path, fm1):
    """The number pattern was quadratic (97 s for one 60 KB cell); a hang guard of 20 s,
    not a speed claim: linear matching takes milliseconds."""
    lines = csv_slice(fm1 / "coils.csv", rows=20).splitlines()
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    r = lines[hi + 3].split(",")
    r[3] = "1" * 60000 + "x"
    lines[hi + 3] = ",".join(r)
    lines.insert(1, "# note: " + " " * 60000 + "x")          # and a long comment
    data = tmp_path / "d.csv"
    data.write_text("\n".join(lines) + "\n")

    def timeout(*_):
        raise TimeoutError("a 60 KB cell took more than 20 s")

    old = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(20)
    try:
        line = assert_bad_input(run(["check", fm1 / "unit.toml", data]), "not a number")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert len(line) < 1000            # the one line is bounded too


def test_all_zero_reference_vectors_are_flagged_not_a_crash(tmp_path, fm1):
    lines = csv_slice(fm1 / "thermal_12pos.csv", every=24).splitlines()
    hi = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    cols = lines[hi].split(",")
    idx = [cols.index(f"ref_{a}_nT") for a in "xyz"]
    for i in range(hi + 1, len(lines)):
        r = lines[i].split(",")
        for j in idx:
            r[j] = "0"
        lines[i] = ",".join(r)
    data = tmp_path / "z.csv"
    data.write_text("\n".join(lines) + "\n")
    rc, out, err = run(["check", fm1 / "unit.toml", data, "-q"])
    assert rc == 2 and len(err) == 1, err
    assert "zero reference vector" in out
    assert_bad_input(run(["fit", fm1 / "unit.toml", data, "-o", tmp_path / "o", "-q"]),
                     "z.csv")


# ---- plan limits ---------------------------------------------------------------------------

@pytest.mark.parametrize("args,fragment", [
    (["--samples-per-segment", "1000000", "--sample-period-s", "3600"], "one day"),
    (["--sample-period-s", "0.001"], "rows"),
    (["--board-tau-min", "10000", "--ramp-C-per-min", "0.001"], "rows")])
def test_plan_refuses_absurd_sizes(tmp_path, fm1, args, fragment):
    assert_bad_input(run(["plan", fm1 / "unit.toml", "-o", tmp_path / "p", *args]),
                     fragment)
    assert listing(tmp_path) == []


# ---- internal faults -----------------------------------------------------------------------

def test_internal_fault_is_one_line_and_traceback_only_with_debug(tmp_path, monkeypatch):
    from generator.verbs import table as table_verb

    def broken(*a, **k):
        raise ZeroDivisionError("simulated fault\nsecond line")

    monkeypatch.setattr(table_verb, "encode_table", broken)
    rc, _, err = run(["table", BASE_COEFFS, "-o", tmp_path / "t.bin"])
    assert rc == 1 and len(err) == 1 and "internal error" in err[0], err
    rc, _, err = run(["--debug", "table", BASE_COEFFS, "-o", tmp_path / "t.bin"])
    assert rc == 1 and any("Traceback" in e for e in err)
    assert listing(tmp_path) == []


def test_bad_usage_is_one_line(tmp_path):
    rc, _, err = run(["table", "--serial", "x"])
    assert rc == 2 and len(err) == 1, err
    rc, _, err = run(["nosuchverb"])
    assert rc == 2 and len(err) == 1, err
    rc, _, err = run([])
    assert rc == 2 and len(err) == 1, err


# ---- the build cache (issue 14 item 4) -----------------------------------------------------

def _tiny(value):
    return {"t.c": f'#include "t.h"\nint t_value(void) {{ return {value}; }}\n',
            "t.h": "int t_value(void);\n"}


def test_build_cache_is_private_and_verified(tmp_path, monkeypatch):
    from generator.flight import host

    cache = tmp_path / "cache"
    monkeypatch.setenv("MAGCAL_CACHE", str(cache))
    lib, _ = host.cffi_module("_hardening_t", _tiny(1), "t.h", '#include "t.h"\n')
    assert lib.t_value() == 1
    assert stat.S_IMODE(os.stat(cache).st_mode) == 0o700
    (mod,) = cache.glob("_hardening_t_*/*.so")
    assert mod.with_name(mod.name + ".sha256").read_text().strip() == host._sha256_file(mod)
    # a planted module (another build's .so under this key, the sidecar unchanged) is not
    # loaded: the build is redone and the right code runs
    lib2, _ = host.cffi_module("_hardening_u", _tiny(2), "t.h", '#include "t.h"\n')
    assert lib2.t_value() == 2
    (other,) = cache.glob("_hardening_u_*/*.so")
    # plant by rename (a new file): the module loaded above stays mapped from its own
    # inode, as it would in another process
    shutil.copy(other, tmp_path / "planted.so")
    os.replace(tmp_path / "planted.so", mod)
    assert host._verified_module(mod.parent, mod.parent.name) is None
    host.cffi_module("_hardening_t", _tiny(1), "t.h", '#include "t.h"\n')
    (rebuilt,) = cache.glob("_hardening_t_*/*.so")
    assert host._verified_module(rebuilt.parent, rebuilt.parent.name) == rebuilt
    assert host._sha256_file(rebuilt) != host._sha256_file(other)
    # a cache folder others can write to, or a symlink, is refused
    os.chmod(cache, 0o777)
    with pytest.raises(InputError, match="writable by group or others"):
        host.cache_dir()
    os.chmod(cache, 0o700)
    link = tmp_path / "link"
    link.symlink_to(cache)
    monkeypatch.setenv("MAGCAL_CACHE", str(link))
    with pytest.raises(InputError, match="symlink"):
        host.cache_dir()


def test_a_coefficient_without_a_c_literal_is_bad_input_not_a_crash():
    """A set built in Python (no schema on the way) with a value beyond float32: the
    generator refuses it naming the coefficient, as bad input."""
    from generator.flight.codegen import render
    from generator.flight.coeffs import CoefficientSet

    cs = CoefficientSet.load(BASE_COEFFS)
    name = cs.unit.sensors[0].name
    cs.sensors[name]["b_poly_nT"] = cs.sensors[name]["b_poly_nT"].copy()
    cs.sensors[name]["b_poly_nT"][0, 0] = 1e39
    with pytest.raises(InputError, match=f"sensors.{name}.b_poly_nT"):
        render(cs)


@pytest.mark.parametrize("key,value", [("noise_nT = 40.0", "noise_nT = 1e300"),
                                       ("lsb_nT = 25.0", "lsb_nT = 1e300"),
                                       ("lab_field_nT = 51540.0", "lab_field_nT = 1e300")])
def test_absurd_unit_numbers_are_refused(tmp_path, fm1, unit_text, key, value):
    """Found by the fuzzer: noise_nT = 1e300 overflowed in check (exit 1)."""
    unit = tmp_path / "unit.toml"
    unit.write_text(unit_text.replace(key, value, 1))
    data = tmp_path / "c.csv"
    data.write_text(csv_slice(fm1 / "coils.csv", rows=6))
    assert_bad_input(run(["check", unit, data, "-q"]), value.split()[0], "plausible")


def test_names_page_lists_every_reserved_name():
    text = (REPO / "docs" / "names.md").read_text()
    for w in sorted(names.RESERVED_WORDS | names.RESERVED_FAMILIES | names.C_LIBRARY_NAMES
                    | names.ICD_PREFIXES):
        assert f"`{w}`" in text or f" {w} " in text or f"`{w} " in text or f" {w}`" in text, w
    for kw in sorted(k for k in names.C_KEYWORDS if k.islower()):
        assert kw in text, kw


@pytest.mark.parametrize("value", ["1e300", "inf", "nan", "-1", "0"])
def test_check_noise_option_is_bounded(tmp_path, fm1, value):
    """--noise-nT 1e300 overflowed in the prediction (exit 1)."""
    data = tmp_path / "c.csv"
    data.write_text(csv_slice(fm1 / "coils.csv", rows=6))
    assert_bad_input(run(["check", fm1 / "unit.toml", data, "--noise-nT", value, "-q"]),
                     "--noise-nT")


def test_folders_and_deep_nesting_where_files_go(tmp_path, fm1):
    """Found by probing: a folder as COEFFS.json or plan.json, and JSON or TOML nested
    100,000 deep, crashed (IsADirectoryError, RecursionError)."""
    adir = tmp_path / "adir"
    adir.mkdir()
    deep_json = tmp_path / "deep.json"
    deep_json.write_text("[" * 100000 + "]" * 100000)
    deep_toml = tmp_path / "deep.toml"
    deep_toml.write_text("a = " + "[" * 100000 + "]" * 100000 + "\n")
    data = tmp_path / "c.csv"
    data.write_text(csv_slice(fm1 / "coils.csv", rows=6))
    for argv in (["table", adir, "-o", tmp_path / "t.bin"],
                 ["table", deep_json, "-o", tmp_path / "t.bin"],
                 ["check", fm1 / "unit.toml", data, "--plan", adir, "-q"],
                 ["check", fm1 / "unit.toml", data, "--plan", deep_json, "-q"],
                 ["check", deep_toml, data, "-q"]):
        assert_bad_input(run(argv))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "c.csv", "deep.json",
                                                          "deep.toml"]


def test_bad_input_is_one_line_even_with_progress(tmp_path, fm1):
    """Without -q the verbs print progress on stderr; a fault found early in the input
    (the lines of the first second are held back) still leaves exactly one line."""
    lines = csv_slice(fm1 / "coils.csv", rows=6).splitlines()
    lines[-1] = lines[-1].replace(",", ",abc,", 1).rsplit(",", 1)[0]
    data = tmp_path / "d.csv"
    data.write_text("\n".join(lines) + "\n")
    assert_bad_input(run(["fit", fm1 / "unit.toml", data, "-o", tmp_path / "o"]), "d.csv")
    assert_bad_input(run(["check", fm1 / "unit.toml", data]), "d.csv")
    rc, _, err = run(["table", BASE_COEFFS, "-o", tmp_path / "t.bin"])
    assert rc == 0
