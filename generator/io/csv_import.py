"""Generic import: a table in physical units -> unit TOML skeleton + ICD telemetry CSV
(`magcal import csv FILE --map mag_x=colA,mag_y=colB,mag_z=colC --input uT ...`).

Sources: a CSV file with a header line (columns by name), or an HDF5 file (also MATLAB
v7.3 .mat) whose datasets are named; a 2-D dataset's components are written NAME:k (k-th
component along its short axis, e.g. imu_mag:0 of an (N, 3) or compassBuffer:1 of a (4, N)
dataset). The map's targets are ICD columns: <s>_x, <s>_y, <s>_z define sensor <s>;
<s>_temp_C its temperature (without one the sensor gets temperature = false); time_s the
sample time (times --time-scale, e.g. 1e-6 for microseconds); anything else is a channel.
Without time_s, --rate-hz gives the sample times.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.io import parts as P
from generator.io.icd_write import (STANDIN_TEMP_C, Staging, unit_id_from, write_telemetry_csv,
                                     write_unit_toml)

_TARGET_RE = re.compile(r"[a-z][a-z0-9_]*|[a-z][a-z0-9_]*_[A-Za-z]+")
_SOURCE_RE = re.compile(r"(.+?)(?::(\d+))?")


def parse_map(text: str) -> dict:
    """'mag_x=colA,mag_y=colB' -> {"mag_x": ("colA", None), ...}; 'x=ds:1' -> ("ds", 1)."""
    out = {}
    for item in (s.strip() for s in text.split(",") if s.strip()):
        if "=" not in item:
            raise InputError(None, f"--map: {item!r} is not TARGET=SOURCE")
        target, source = (x.strip() for x in item.split("=", 1))
        if "=" in source:
            raise InputError(None, f"--map: {item!r} is not TARGET=SOURCE (separate the "
                                   "pairs with commas)")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", target):
            raise InputError(None, f"--map: target {target!r} is not a column name")
        if target in out:
            raise InputError(None, f"--map: target {target!r} is given twice")
        m = _SOURCE_RE.fullmatch(source)
        if not source or not m:
            raise InputError(None, f"--map: source of {target!r} is empty")
        out[target] = (m.group(1), int(m.group(2)) if m.group(2) else None)
    if not out:
        raise InputError(None, "--map: no TARGET=SOURCE pairs")
    return out


def _read_source(path: Path):
    """name -> array getter for a CSV or HDF5 file."""
    try:
        head = path.read_bytes()[:8]
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    if head.startswith(b"\x89HDF") or path.suffix.lower() in (".h5", ".hdf5", ".mat"):
        try:
            import h5py
            f = h5py.File(path, "r")
        except Exception as e:
            raise InputError(path, f"not a readable HDF5 / MATLAB v7.3 file: {e}") from None

        def get(name, k):
            if name not in f:
                raise InputError(path, f"no dataset {name!r} (it has {', '.join(f.keys())})")
            a = np.asarray(f[name][()], dtype=float)
            if a.ndim == 1:
                if k is not None:
                    raise InputError(path, f"dataset {name!r} is 1-D: no component :{k}")
                return a
            if a.ndim != 2 or k is None:
                raise InputError(path, f"dataset {name!r} has shape {a.shape}: name a "
                                       f"component, e.g. {name}:0")
            a = a if a.shape[0] >= a.shape[1] else a.T
            if not 0 <= k < a.shape[1]:
                raise InputError(path, f"dataset {name!r} has {a.shape[1]} components, not :{k}")
            return a[:, k]
        return get
    from generator.io.telemetry_csv import _parse_fast, _parse_slow, _read_text, _split_lines
    text = _read_text(path)
    header, _, rows, row_lines, _, _ = _split_lines(path, text)
    names = [c.strip() for c in header.split(",")]
    values = _parse_fast(rows, len(names))
    if values is None:
        values = _parse_slow(path, names, rows, row_lines)

    def get(name, k):
        if k is not None:
            name = f"{name}:{k}"
        if name not in names:
            raise InputError(path, f"no column {name!r} (the header has {', '.join(names)})")
        return values[:, names.index(name)]
    return get


def import_table(path, out_dir, mapping: dict, *, input_unit="uT", part=P.GENERIC,
                 range_nT=None, rate_hz=None, time_scale=1.0, unit_id=None,
                 as_counts_lsb_nT=None, field_nT=None) -> dict:
    """Writes DIR/unit.toml and DIR/<file>.csv; returns their paths."""
    path = Path(path)
    if input_unit not in P.INPUT_UNITS_nT:
        raise InputError(None, f"--input {input_unit!r} is not one of "
                               f"{', '.join(P.INPUT_UNITS_nT)}")
    cat = P.find(part)
    if cat is None:
        raise InputError(None, f"--part {part!r} is not a known part; known parts: "
                               f"{P.known_text()}")
    if cat.generic and not range_nT:
        raise InputError(None, "--part generic needs --range-nT (full scale per axis)")
    get = _read_source(path)
    sensors = [t[:-2] for t in mapping if t.endswith("_x")]
    for s in sensors:
        for a in "yz":
            if f"{s}_{a}" not in mapping:
                raise InputError(None, f"--map: sensor {s!r} has {s}_x but no {s}_{a}")
    if not sensors:
        raise InputError(None, "--map: no sensor (map <s>_x, <s>_y, <s>_z)")
    data = {t: get(*src) for t, src in mapping.items()}
    n = {len(v) for v in data.values()}
    if len(n) != 1:
        raise InputError(path, f"the mapped columns differ in length: {sorted(n)}")
    n = n.pop()
    if "time_s" in data:
        time_s = data.pop("time_s") * float(time_scale)
        time_s = time_s - time_s[0]
    elif rate_hz:
        time_s = np.arange(n) / float(rate_hz)
    else:
        raise InputError(None, "no time: map time_s=COLUMN or give --rate-hz")
    factor = P.INPUT_UNITS_nT[input_unit]
    cols = {"time_s": time_s}
    specs = []
    for s in sensors:
        spec = {"name": s, "part": part, "frame": "body", "axes": ["+x", "+y", "+z"]}
        if as_counts_lsb_nT:
            lsb = float(as_counts_lsb_nT)
            spec["_comment"] = [f"written as counts of {lsb:g} nT (--as-counts); part {part}"]
            spec.update(part=P.GENERIC, input="counts", lsb_nT=lsb, zero_count=0,
                        range_nT=float(range_nT or cat.range_nT))
            for a in "xyz":
                cols[f"{s}_{a}"] = np.round(data.pop(f"{s}_{a}") * factor / lsb)
        else:
            spec["input"] = input_unit
            if range_nT:
                spec["range_nT"] = float(range_nT)
            for a in "xyz":
                cols[f"{s}_{a}"] = data.pop(f"{s}_{a}")
        if f"{s}_temp_C" in data:
            cols[f"{s}_temp_C"] = data.pop(f"{s}_temp_C")
        elif as_counts_lsb_nT:
            cols[f"{s}_temp_C"] = np.full(n, STANDIN_TEMP_C)
            spec["_comment"].append(f"no temperature: {s}_temp_C is a constant stand-in "
                                    f"({STANDIN_TEMP_C:g} degC), not a reading")
        else:
            spec["temperature"] = False
        specs.append(spec)
    cols.update(data)                                         # the rest: channels
    uid = unit_id or unit_id_from("csv_", path.stem)
    meta = {"unit": uid, "source": path.name,
            "map": ",".join(f"{t}={s}" + (f":{k}" if k is not None else "")
                            for t, (s, k) in mapping.items())}
    with Staging(out_dir) as st:
        csv = write_telemetry_csv(st.dir / (path.stem + ".csv"), cols, meta=meta)
        write_unit_toml(st.dir / "unit.toml", uid, specs,
                        unit_keys={"lab_field_nT": float(field_nT)} if field_nT else None,
                        header=[f"Unit file skeleton written by `magcal import csv` from "
                                f"{path.name}.",
                                "Check part, frame and axes; add noise_nT as needed."])
        return st.commit("unit.toml", [csv.name])
