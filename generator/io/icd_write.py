"""Write a unit file skeleton (ICD sections 1, 4) and a telemetry CSV (ICD section 2), as the
importers produce them. Files are written to a temporary name and renamed into place, so a
failure never leaves a half-written file.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from generator.errors import OutputError
from generator.io.names import MAX_NAME_CHARS
from generator.io.outputs import STORAGE_ERRNOS
from generator.io.outputs import _reason as storage_reason


STANDIN_TEMP_C = 20.0   # --as-counts: the constant temperature of a sensor that reports none
UNIT_ID_MAX = MAX_NAME_CHARS   # the names' limit (io/names.py), within the table header's 32 bytes


def unit_id_from(prefix: str, stem: str) -> str:
    """A unit id [a-z][a-z0-9_]* of at most UNIT_ID_MAX characters from a file name."""
    s = "".join(c if c.isalnum() and c.isascii() else "_" for c in stem.lower()).strip("_")
    s = s[len(prefix):] if s.startswith(prefix) else s
    return (prefix + s)[:UNIT_ID_MAX].rstrip("_")


class Staging:
    """Write an import's files into DIR/.import-<pid>/, check that the toolchain reads them
    (unit file and every telemetry file), then move them into DIR. On any fault nothing
    is left in DIR and the InputError names the fault."""

    def __init__(self, out_dir):
        self.out = Path(out_dir)
        self.dir = self.out / f".import-{os.getpid()}"

    def __enter__(self):
        self.made = [q for q in (self.out, *self.out.parents) if not q.exists()]
        self.out.mkdir(parents=True, exist_ok=True)
        self.dir.mkdir(exist_ok=True)
        return self

    def __exit__(self, exc_type, exc, tb):
        for p in self.dir.glob("*"):
            p.unlink()
        self.dir.rmdir()
        if exc_type is not None:         # a failed import leaves no folder it made
            for q in self.made:
                try:
                    q.rmdir()
                except OSError:
                    break
        if isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS:
            # a full disk (or quota, read-only filesystem): one line naming the output,
            # exit 1, as every other verb's outputs (io.outputs)
            raise OutputError(self.out, storage_reason(exc)) from None
        return False

    def commit(self, unit_name: str, data_names: list) -> dict:
        from generator.io.telemetry_csv import read_telemetry
        from generator.io.unitfile import load_unit

        from generator.errors import InputError
        try:
            unit = load_unit(self.dir / unit_name)
            for n in data_names:
                read_telemetry(self.dir / n, unit)
        except InputError as e:
            where = Path(e.path).name if e.path else ""
            line = f":{e.line}" if e.line is not None else ""
            col = f" column '{e.column}':" if e.column is not None else ""
            raise InputError(None, f"the imported {where}{line} would not load:{col} "
                                   f"{e.message} (check --unit-id and the --map names); "
                                   "nothing written") from None
        moved = {"unit": self.out / unit_name, "data": [self.out / n for n in data_names]}
        for n in data_names:
            os.replace(self.dir / n, self.out / n)
        os.replace(self.dir / unit_name, self.out / unit_name)
        return moved


def _atomic_write(path: Path, text: str) -> Path:
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {v!r}")


def write_unit_toml(path, unit_id: str, sensors: list, *, header: list = (),
                    unit_keys: dict | None = None, tables: dict | None = None) -> Path:
    """sensors: dicts of [[sensor]] keys in order; a key "_comment" (list of lines) is
    written as comments above the table. header: comment lines at the top. tables: further
    top-level tables {name: {key: value}} (e.g. requirements)."""
    out = [f"# {h}" if h else "#" for h in header]
    out += ["[unit]", f"id = {_toml_value(unit_id)}"]
    for k, v in (unit_keys or {}).items():
        out.append(f"{k} = {_toml_value(v)}")
    for s in sensors:
        out.append("")
        out += [f"# {c}" for c in s.get("_comment", ())]
        out.append("[[sensor]]")
        for k, v in s.items():
            if not k.startswith("_") and v is not None:
                out.append(f"{k} = {_toml_value(v)}")
    for name, d in (tables or {}).items():
        out += ["", f"[{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in d.items()]
    return _atomic_write(path, "\n".join(out) + "\n")


def _cell(x: float, digits: int) -> str:
    if not math.isfinite(x):
        return ""
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return f"{x:.{digits}g}"


def write_telemetry_csv(path, columns: dict, *, meta: dict | None = None,
                        comments: list = (), digits: int = 10) -> Path:
    """columns: {name: (N,) float array}, time_s first; NaN is written as an empty cell.
    meta: '# key: value' lines; comments: free '# ...' lines; digits: significant digits."""
    names = list(columns)
    if names[0] != "time_s":
        raise ValueError("the first column must be time_s")
    arrays = [np.asarray(columns[n], dtype=np.float64) for n in names]
    n = arrays[0].shape[0]
    lines = [f"# {k}: {v}" for k, v in (meta or {}).items()]
    lines += [f"# {c}" for c in comments]
    lines.append(",".join(names))
    cols = [[_cell(float(x), digits) for x in a] for a in arrays]
    lines += [",".join(c[i] for c in cols) for i in range(n)]
    return _atomic_write(path, "\n".join(lines) + "\n")
