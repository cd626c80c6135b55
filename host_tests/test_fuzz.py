"""Seeded fuzzing of every verb, in-process (issue 14 item 6).

Inputs are small slices of the shared campaigns, the shared unit file and the committed
example coefficients, mutated by seeded random edits: truncation, cells replaced with
NaN / inf / huge / text, header edits, column swaps and deletions, other encodings, line
endings, long cells, TOML values of every type, JSON values of every type and shape,
flipped bits of uplink tables. Each case runs `generator.cli.main` and must end in

* exit 0 with the sanity properties of its output (coefficients load, finite, det M > 0,
  temperatures in the physical range, unique output columns, valid = status 0), or
* exit 2 with exactly one line on stderr,

and never leave a temporary or half-written file. Exit 1 (an internal fault) fails.

The default run holds more than 10^4 cases; most fail at reading or validation and take
milliseconds, and every family also sends a share of cases that pass validation through
the whole verb. MAGCAL_FUZZ_SCALE=N multiplies the counts (docs/fuzzing.md has the
figures of a long run); MAGCAL_FUZZ_SEED changes the seed. A failure names the family,
the case number and the mutations, so `fuzz_case(family, seed, i)` reproduces it.
"""

from __future__ import annotations

import json
import os
import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from hardening_fixtures import BASE_COEFFS, csv_slice, run, shared_fm1

SCALE = float(os.environ.get("MAGCAL_FUZZ_SCALE", "1"))
SEED = int(os.environ.get("MAGCAL_FUZZ_SEED", "14"))

# cases per family in the default run (sum > 10^4); see docs/fuzzing.md for the timing
COUNTS = {"csv": 3400, "unit": 3200, "coeffs": 1800, "table_bin": 1800, "deep": 24}

TEXT_CELLS = ["nan", "NaN", "inf", "-inf", "Infinity", "1e300", "-1e300", "1e309", "1e39",
              "abc", "0x10", "1e", "--1", "+", ".", "1.2.3", " ", "\t", "1,5", "1;2", '"1"',
              "१२", "1_000", "0b1", "∞", "\x00", "é", "-0", "1e-320", "9" * 400,
              "1" * 5000 + "x", "nan(0x1)"]
HEADER_JUNK = ["", " ", "a b", "coil_z */ * 100 /*_A", "coil_q_A", "x" * 300, "ref_x_nT",
               "time_s", "mmc1_set_x", "é", "\"q\"", "#c", "coil_1_A", "int"]

TOML_VALUES = ['"int"', '"if"', '"sel"', '"table_off"', '"unit"', '"x */ y"', '"Mpu"',
               '"mpu1"', 'true', 'false', '"false"', '"true"', '0', '-1', '1e300', 'inf',
               'nan', '-0.0', '1.5', '32768', '[]', '{}', '["+x", "+x", "+z"]',
               '["+x", "+y"]', '["+z", "+y", "+x"]', '"MMC5883MA"', '"MPU-9255"',
               '"boom"', '"body"', '"float64"', '"float16"', '"' + "a" * 300 + '"',
               '{a = 1}', '[[1]]', '"mmc1"', '"mmc2"', '""', "'''x'''"]

JSON_VALUES = [1e300, -1e300, 1e39, 0, -1, 1.5, 1e-300, "x", "int", "table",
               "coil_z */ * 100 /*_A", None, True, False, [], {}, [1, 2], {"a": 1},
               [[0.0] * 3] * 3, "mmc1", "MMC5883MA", 3, 6, -3, "0x1", [None], 2 ** 64]


# ---- seeds -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    fm1 = shared_fm1()
    d = tmp_path_factory.mktemp("fuzz_seeds")
    csvs = {"coils": csv_slice(fm1 / "coils.csv", rows=6),
            "flight": csv_slice(fm1 / "flight_6h.csv", rows=6),
            "thermal": csv_slice(fm1 / "thermal_12pos.csv", every=3000, rows=8),
            "rotation": csv_slice(fm1 / "rotation.csv", every=400, rows=8)}
    unit = (fm1 / "unit.toml").read_text()
    coeffs = json.loads(BASE_COEFFS.read_text())
    coeffs["fit"] = {"note": "free text, not fuzzed"}     # reports only; keeps cases fast
    (d / "unit.toml").write_text(unit)
    (d / "coeffs.json").write_text(json.dumps(coeffs))
    for k, v in csvs.items():
        (d / f"{k}.csv").write_text(v)
    rc, _, err = run(["table", d / "coeffs.json", "-o", d / "table.bin", "-q"])
    assert rc == 0, err
    return {"dir": d, "fm1": fm1, "csv": csvs, "unit": unit, "coeffs": coeffs,
            "table": (d / "table.bin").read_bytes()}


# ---- mutators ----------------------------------------------------------------------------

def _split_csv(text):
    lines = text.split("\n")
    hi = next((i for i, ln in enumerate(lines) if not ln.startswith("#")), len(lines) - 1)
    return lines, hi


def m_cell(rng, text):
    lines, hi = _split_csv(text)
    rows = [i for i in range(hi + 1, len(lines)) if lines[i]]
    if not rows:
        return text, "no row for a cell"
    i = rng.choice(rows)
    cells = lines[i].split(",")
    j = rng.randrange(len(cells))
    cells[j] = rng.choice(TEXT_CELLS + ["", "", "0", str(rng.uniform(-1e6, 1e6))])
    lines[i] = ",".join(cells)
    return "\n".join(lines), f"cell {i},{j}={cells[j][:12]!r}"


def m_header(rng, text):
    lines, hi = _split_csv(text)
    cols = lines[hi].split(",")
    j = rng.randrange(len(cols))
    kind = rng.randrange(4)
    if kind == 0:
        cols[j] = rng.choice(HEADER_JUNK)
    elif kind == 1:
        cols[j] = cols[rng.randrange(len(cols))]            # duplicate
    elif kind == 2:
        cols[j] = cols[j].upper()
    else:
        cols[j] = " " + cols[j] + " "
    lines[hi] = ",".join(cols)
    return "\n".join(lines), f"header col {j}={cols[j][:20]!r}"


def m_swap_columns(rng, text):
    lines, hi = _split_csv(text)
    n = len(lines[hi].split(","))
    a, b = rng.randrange(n), rng.randrange(n)
    both = rng.random() < 0.5          # swap data too (a consistent file) or header only

    def sw(line):
        c = line.split(",")
        if len(c) == n:
            c[a], c[b] = c[b], c[a]
        return ",".join(c)
    lines = [sw(ln) if (i == hi or (both and i > hi)) else ln for i, ln in enumerate(lines)]
    return "\n".join(lines), f"swap columns {a},{b} data={both}"


def m_drop_column(rng, text):
    lines, hi = _split_csv(text)
    n = len(lines[hi].split(","))
    j = rng.randrange(n)

    def drop(line):
        c = line.split(",")
        return ",".join(c[:j] + c[j + 1:]) if len(c) == n else line
    return "\n".join(drop(ln) if i >= hi else ln for i, ln in enumerate(lines)), \
        f"drop column {j}"


def m_truncate(rng, text):
    k = rng.randrange(len(text) + 1)
    return text[:k], f"truncate at {k}"


def m_rows(rng, text):
    lines, hi = _split_csv(text)
    kind = rng.randrange(4)
    body = lines[hi + 1:]
    if kind == 0 and body:
        body.pop(rng.randrange(len(body)))
    elif kind == 1 and body:
        body.insert(rng.randrange(len(body) + 1), rng.choice(body))
    elif kind == 2 and len(body) > 1:
        rng.shuffle(body)                              # time goes backwards
    else:
        body = []                                      # header only
    return "\n".join(lines[:hi + 1] + body), f"rows kind {kind}"


def m_line_endings(rng, text):
    kind = rng.choice(["\r\n", "\r", "\n\n", "\n \n"])
    return text.replace("\n", kind), f"line endings {kind!r}"


def m_comment(rng, text):
    lines, hi = _split_csv(text)
    junk = rng.choice(["# unit: other", "# key: " + " " * 5000 + "x", "#", "# " + "x" * 20000,
                       "## unit: samsat_fm1", "# unit:"])
    lines.insert(rng.randrange(hi + 1), junk)
    return "\n".join(lines), f"comment {junk[:20]!r}"


def m_long_cell(rng, text):
    lines, hi = _split_csv(text)
    rows = [i for i in range(hi + 1, len(lines)) if lines[i]]
    if not rows:
        return text, "no row for a long cell"
    i = rng.choice(rows)
    cells = lines[i].split(",")
    j = rng.randrange(len(cells))
    cells[j] = rng.choice(["1" * 60000 + "x", "1" * 60000, " " * 60000, "e" * 60000,
                           "1." + "0" * 60000])
    lines[i] = ",".join(cells)
    return "\n".join(lines), f"long cell {i},{j}"


def m_extra_comma(rng, text):
    lines, hi = _split_csv(text)
    i = rng.randrange(hi, len(lines))
    lines[i] = lines[i] + "," if rng.random() < 0.5 else "," + lines[i]
    return "\n".join(lines), f"extra comma line {i}"


CSV_MUTATORS = [m_cell, m_cell, m_cell, m_header, m_swap_columns, m_drop_column, m_truncate,
                m_rows, m_line_endings, m_comment, m_long_cell, m_extra_comma]


def encode(rng, text) -> tuple:
    kind = rng.choice(["utf-8"] * 6 + ["utf-8-sig", "utf-16", "latin-1", "nul", "bad"])
    if kind == "nul":
        b = text.encode()
        k = rng.randrange(len(b) + 1)
        return b[:k] + b"\x00" + b[k:], kind
    if kind == "bad":
        b = text.encode()
        k = rng.randrange(len(b) + 1)
        return b[:k] + bytes([rng.randrange(0x80, 0x100)]) + b[k:], kind
    if kind == "latin-1":
        return (text + "\n# caf\u00e9\n").encode("latin-1", "replace"), kind
    return text.encode(kind), kind


def mutate_csv(rng, text):
    how = []
    for _ in range(rng.choice([1, 1, 1, 2, 3])):
        text, h = rng.choice(CSV_MUTATORS)(rng, text)
        how.append(h)
    data, enc = encode(rng, text)
    how.append(enc)
    return data, how


def mutate_unit(rng, text):
    lines = text.split("\n")
    how = []
    for _ in range(rng.choice([1, 1, 2])):
        kind = rng.randrange(7)
        keyed = [i for i, ln in enumerate(lines) if "=" in ln and not ln.startswith("#")]
        if kind <= 2 and keyed:
            i = rng.choice(keyed)
            key = lines[i].split("=")[0]
            lines[i] = key + "= " + rng.choice(TOML_VALUES)
            how.append(f"value line {i}: {lines[i][:40]!r}")
        elif kind == 3 and keyed:
            i = rng.choice(keyed)
            how.append(f"delete {lines.pop(i)[:30]!r}")
        elif kind == 4 and any(ln.strip() == "[[sensor]]" for ln in lines):
            starts = [i for i, ln in enumerate(lines) if ln.strip() == "[[sensor]]"]
            s = rng.choice(starts)
            end = next((j for j in starts if j > s), len(lines))
            lines[end:end] = lines[s:end]                     # duplicate a sensor
            how.append(f"duplicate sensor at {s}")
        elif kind == 5:
            i = rng.randrange(len(lines) + 1)
            junk = rng.choice(["[unit]", "[[sensor]]", "[boom]", "x = ", "= 1", "[", "\"",
                               "name = \"q\"", "extra = 1", "[sensor]", "sensor = 1"])
            lines.insert(i, junk)
            how.append(f"insert {junk!r} at {i}")
        else:
            t = "\n".join(lines)
            k = rng.randrange(len(t) + 1)
            lines = t[:k].split("\n")
            how.append(f"truncate at {k}")
    data, enc = encode(rng, "\n".join(lines))
    return data, how + [enc]


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _get(obj, path):
    for p in path:
        obj = obj[p]
    return obj


def mutate_coeffs(rng, doc):
    d = json.loads(json.dumps(doc))
    how = []
    # focus on what matters: unit, chain, sensors, unit_coefficients (fit is free text)
    paths = [p for p in _paths(d) if p and p[0] in ("unit", "chain", "sensors",
                                                     "unit_coefficients", "format_version",
                                                     "layout_hash")]
    for _ in range(rng.choice([1, 1, 2])):
        p = rng.choice(paths)
        parent, key = _get(d, p[:-1]), p[-1]
        kind = rng.randrange(6)
        try:
            old = parent[key]
        except (KeyError, IndexError, TypeError):
            continue
        if kind <= 1:
            parent[key] = rng.choice(JSON_VALUES)
        elif kind == 2 and isinstance(old, (int, float)) and not isinstance(old, bool):
            parent[key] = old * rng.choice([1.2, -1.0, 1e6, 1e-6, 0.0, 1.0 + 1e-7])
        elif kind == 3 and isinstance(parent, dict):
            del parent[key]
        elif kind == 4 and isinstance(parent, dict):
            parent[rng.choice(["evil", "int", "coil_z */ x /*_A", key + "_2"])] = old
        elif kind == 5 and isinstance(old, list) and old:
            parent[key] = old[:-1] if rng.random() < 0.5 else old + [old[-1]]
        else:
            parent[key] = rng.choice(JSON_VALUES)
        how.append(f"{'.'.join(map(str, p))} kind {kind}")
        paths = [q for q in _paths(d) if q and q[0] in ("unit", "chain", "sensors",
                                                         "unit_coefficients")]
    text = json.dumps(d)
    if rng.random() < 0.05:
        k = rng.randrange(len(text) + 1)
        text = text[:k]
        how.append(f"truncate at {k}")
    return text.encode(), how


def mutate_table(rng, data):
    b = bytearray(data)
    how = []
    for _ in range(rng.choice([1, 1, 2, 3])):
        kind = rng.randrange(4)
        if kind <= 1 and b:
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
            how.append(f"flip byte {i}")
        elif kind == 2:
            k = rng.randrange(len(b) + 1)
            del b[k:]
            how.append(f"truncate {k}")
        else:
            b += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
            how.append("extend")
    return bytes(b), how


# ---- sanity of a successful run ---------------------------------------------------------

def sane_coefficients(path):
    """A coefficients.json that a verb accepted or wrote: loads (schema), finite values,
    det M(t_ref) > 0, calibrated range physical."""
    from generator.flight.coeffs import CoefficientSet

    cs = CoefficientSet.load(path)
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        assert all(np.all(np.isfinite(a)) for a in v.values()), s.name
        assert np.linalg.det(np.asarray(v["M_poly"])[0]) > 0, s.name
        assert -273.15 < float(v["t_min_C"]) <= float(v["t_max_C"]) < 300.0, s.name
    return cs


def sane_apply_csv(path):
    lines = [ln for ln in Path(path).read_text().splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    assert len(set(header)) == len(header), header
    for row in lines[1:]:
        cells = row.split(",")
        assert len(cells) == len(header)
        for j, h in enumerate(header):
            if h.endswith("_valid"):
                status = cells[header.index(h[:-len("_valid")] + "_status")]
                assert (cells[j] == "1") == (status == "0"), row


def no_leftovers(folder: Path):
    left = [p.name for p in folder.rglob("*") if p.name.startswith(".")
            or p.name.endswith((".part", ".tmp"))]
    assert not left, left


# ---- one case ------------------------------------------------------------------------------

def fuzz_case(family, seeds, i, work: Path):
    """Run case i of a family; returns None when it passed, else a failure description."""
    rng = random.Random(f"{SEED}-{family}-{i}")
    d = seeds["dir"]
    out = work / "out"
    inp = work / "in"
    for p in (out, inp):
        shutil.rmtree(p, ignore_errors=True)
    inp.mkdir(parents=True)
    unit = d / "unit.toml"
    if family == "csv":
        name = rng.choice(sorted(seeds["csv"]))
        data, how = mutate_csv(rng, seeds["csv"][name])
        f = inp / f"{name}.csv"
        f.write_bytes(data)
        argv = ["check", unit, f, "-q"]
    elif family == "unit":
        data, how = mutate_unit(rng, seeds["unit"])
        unit = inp / "unit.toml"
        unit.write_bytes(data)
        argv = ["check", unit, d / rng.choice(["coils.csv", "flight.csv"]), "-q"]
    elif family == "coeffs":
        data, how = mutate_coeffs(rng, seeds["coeffs"])
        c = inp / "c.json"
        c.write_bytes(data)
        argv = ["table", c, "-o", out / "t.bin", "-q"]
    elif family == "table_bin":
        data, how = mutate_table(rng, seeds["table"])
        t = inp / "t.bin"
        t.write_bytes(data)
        argv = ["table", "--decode", t, "-q"] if rng.random() < 0.7 else \
            ["table", "--diff", d / "table.bin", t, "-q"]
    else:     # deep: mutated inputs through the expensive verbs
        verb = ["apply", "generate", "fit", "trace", "plan", "apply", "generate",
                "check"][i % 8]
        how = [verb]
        if verb in ("apply", "generate"):
            if rng.random() < 0.5:
                cdata, h = mutate_coeffs(rng, seeds["coeffs"])
            else:
                cdata, h = json.dumps(seeds["coeffs"]).encode(), ["coeffs unchanged"]
            c = inp / "c.json"
            c.write_bytes(cdata)
            how += h
            if verb == "apply":
                data, h = mutate_csv(rng, seeds["csv"]["flight"])
                f = inp / "flight.csv"
                f.write_bytes(data)
                how += h
                argv = ["apply", c, f, "-o", out / "o.csv", "-q"]
            else:
                argv = ["generate", c, "-o", out / "gen", "--compile", "-q"]
        elif verb in ("fit", "trace", "check"):
            big = csv_slice(seeds["fm1"] / "thermal_12pos.csv", every=30)
            data, how2 = mutate_csv(rng, big)
            f = inp / "thermal.csv"
            f.write_bytes(data)
            how += how2
            argv = [verb, unit, f, "-q"] + ([] if verb == "check" else ["-o", out / "o"])
        else:
            data, h = mutate_unit(rng, seeds["unit"])
            unit = inp / "unit.toml"
            unit.write_bytes(data)
            how += h
            argv = ["plan", unit, "-o", out / "p", "-q"]
    try:
        rc, stdout, err = run(argv)
    except BaseException as e:     # main itself must never raise
        return f"{family} #{i} {how}: raised {type(e).__name__}: {e}"
    try:
        if rc == 2:
            assert len(err) == 1, err
        elif rc == 0:
            assert argv[0] == "check" or not err, err
            if family == "coeffs" or (family == "deep" and argv[0] in ("apply", "generate")):
                sane_coefficients(argv[1])
            if argv[0] == "apply":
                sane_apply_csv(out / "o.csv")
            if argv[0] in ("fit", "trace"):
                sane_coefficients(out / "o" / "coefficients.json")
        else:
            raise AssertionError(f"exit {rc}: {err[-3:]}")
        if out.exists():
            no_leftovers(out)
        no_leftovers(work)
    except AssertionError as e:
        return f"{family} #{i} {how}: rc {rc}: {str(e)[:300]}"
    return None


def run_family(family, seeds, work, n):
    failures = []
    for i in range(n):
        f = fuzz_case(family, seeds, i, work)
        if f:
            failures.append(f)
            if len(failures) >= 10:
                break
    return failures


@pytest.fixture
def work(tmp_path):
    """Where the cases write: a RAM disk when there is one (outputs are fsynced, which on
    a disk would dominate the cases' time), else the test's temporary folder."""
    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        import tempfile
        d = Path(tempfile.mkdtemp(prefix="magcal-fuzz-", dir=shm))
        yield d
        shutil.rmtree(d, ignore_errors=True)
    else:
        yield tmp_path


@pytest.mark.parametrize("family", ["csv", "unit", "coeffs", "table_bin", "deep"])
def test_fuzz(family, seeds, work):
    n = int(COUNTS[family] * SCALE)
    failures = run_family(family, seeds, work, n)
    assert not failures, "\n".join(failures)
