"""The uplink of a recalibration: what changed between the calibration on board and a
new one, ready to send: the new table (serial one above the one on board), the table
diff in physical terms, and the table in parts for the link. The table format, diff,
parts and the ground validator are generator/flight/tables.py's; this module only puts
them together (after an in-flight recalibration: `magcal fit UNIT ORBIT.csv --prior
ONBOARD.json`). The same from the command line, with `magcal table`:

    magcal table ONBOARD.json -o onboard.bin --serial 1
    magcal table NEW.json -o new.bin --serial 2 --chunk 200
    magcal table --diff onboard.bin new.bin --coeffs NEW.json

Files written into the output folder (all or nothing):
    table.bin, table.txt        the new table and its dump
    diff.txt                    one line per change (header fields, then coefficients)
    table.partNNN.bin           the parts (--chunk bytes each at most)
    uplink.json                 serials, sizes, the changes, the parts' names
"""

from __future__ import annotations

import json

from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.flight.tables import (TableError, check_table, chunk_table, diff_tables,
                                     dump_table, encode_table, join_parts)

DEFAULT_CHUNK_BYTES = 200      # a typical CubeSat UHF frame's payload


def make_uplink(onboard: CoefficientSet, new: CoefficientSet, *, onboard_serial: int = 1,
                chunk_bytes: int = DEFAULT_CHUNK_BYTES, created_s: int = 0) -> dict:
    """The uplink of `new` over `onboard`: {"table", "dump", "changes", "parts",
    "summary"}. The new table passes the ground validator (the flight checks in the
    flight order) and its parts reassemble into it, or this raises."""
    if onboard.unit.id != new.unit.id:
        raise InputError(None, f"the calibration on board is for unit '{onboard.unit.id}', "
                               f"the new one for '{new.unit.id}'")
    if not 0 < onboard_serial < 0xFFFFFFFF:
        raise InputError(None, f"--onboard-serial {onboard_serial}: must be 1 .. 2^32 - 2 "
                               "(the new table's serial must be larger)")
    old_tbl = encode_table(onboard, onboard_serial, created_s)
    table = encode_table(new, onboard_serial + 1, created_s)
    check_table(table, new.spec)
    same_layout = onboard.spec.layout_hash() == new.spec.layout_hash()
    changes = diff_tables(old_tbl, table, new.spec if same_layout else None)
    parts = chunk_table(table, chunk_bytes)
    if join_parts(parts, new.spec) != table:
        raise RuntimeError("the parts do not reassemble into the table")
    coeff_changes = [c for c in changes if not c.name.startswith("header ")]
    summary = {"unit": new.unit.id, "onboard_serial": onboard_serial,
               "new_serial": onboard_serial + 1, "table_bytes": len(table),
               "same_layout": same_layout, "values_changed": len(coeff_changes),
               "changes": [str(c) for c in changes], "chunk_bytes": chunk_bytes,
               "parts": len(parts)}
    if not same_layout:
        summary["note"] = ("the chain's layout changed (another set of blocks): the values "
                           "do not correspond one to one, the whole table is sent")
    return {"table": table, "dump": dump_table(table, new.spec, title="table.bin"),
            "changes": changes, "parts": parts, "summary": summary}


def write_uplink(up: dict, folder) -> dict:
    """Write make_uplink's result into a folder (caller makes it atomic); returns paths."""
    from pathlib import Path
    folder = Path(folder)
    paths = {"table": folder / "table.bin", "dump": folder / "table.txt",
             "diff": folder / "diff.txt", "summary": folder / "uplink.json"}
    paths["table"].write_bytes(up["table"])
    paths["dump"].write_text(up["dump"], encoding="utf-8")
    lines = [str(c) for c in up["changes"]] or ["no differences"]
    paths["diff"].write_text("\n".join(lines) + "\n", encoding="utf-8")
    names = []
    for i, part in enumerate(up["parts"]):
        p = folder / f"table.part{i:03d}.bin"
        p.write_bytes(part)
        names.append(p.name)
    paths["summary"].write_text(json.dumps({**up["summary"], "part_files": names}, indent=1)
                                + "\n", encoding="utf-8")
    return paths
