"""docs/table_format.md, written from the table format's one definition (flight/tables.py).

    python3 -m generator.report.table_doc --write-doc
"""

from __future__ import annotations

import sys
from pathlib import Path

from generator.flight.chain import ChainSpec
from generator.flight.tables import (CHECK_ORDER, CONTENT_CHECKS, CRC_BYTES, ERRORS,
                                     HEADER_BYTES, HEADER_FIELDS, HEADER_OFFSETS,
                                     MANAGER_INIT_MARK, NO_TEMP_RANGE_C,
                                     ORDERED_PAIRS, PART_FIELDS, PART_HEADER_BYTES, PART_OFFSETS,
                                     PHYSICAL_LIMITS, PLAUSIBLE_RANGES, SERIAL_CHECKS,
                                     TableStatus)

REPO = Path(__file__).resolve().parents[2]
DOC_PATH = REPO / "docs" / "table_format.md"


# ---- the docs page -----------------------------------------------------------------------


def _doc_example_spec() -> ChainSpec:
    """A chain with every block there is: coils, a boom sensor, every optional stage."""
    from generator.flight.chain import SensorOptions
    from generator.io.unit import SensorSpec, Unit

    unit = Unit("example", (
        SensorSpec("mmc1", "MMC5883MA", "body", ("+z", "+y", "+x"), 25.0, 32768, True),
        SensorSpec("mpu3", "MPU-9255", "boom", ("-y", "-z", "+x"), 150.0, 0, False),
    ), float_type="float32")
    everything = SensorOptions(channels=("heater_A",), thermal_lag=True, nonlinear=True,
                               sr_compensation=True)
    return ChainSpec(unit, coils=("coil_x_A", "coil_y_A", "coil_z_A"),
                     sensor_options=(("mmc1", everything),))


def _cell(text) -> str:
    return str(text).replace("|", "\\|")


def format_doc() -> str:
    """docs/table_format.md, from the definitions above (a test keeps the file equal)."""
    L = []
    a = L.append
    a("# Uplink coefficient table format")
    a("")
    a("<!-- DO NOT EDIT: generated from generator/flight/tables.py by "
      "`python -m generator.report.table_doc --write-doc`; host_tests/test_tables.py checks it. -->")
    a("")
    a("A table carries one unit's complete coefficient set from the ground to the flight "
      "code. Everything is little-endian. A table is")
    a("")
    a(f"    header ({HEADER_BYTES} bytes) | payload (payload_bytes) | CRC-32 ({CRC_BYTES} bytes)")
    a("")
    a("and the flight code accepts it only if every check below passes; otherwise the "
      "table in use stays in use (double buffer, switched by one assignment after "
      "validation). The definitions live in `generator/flight/tables.py` (`HEADER_FIELDS`, "
      "`PART_FIELDS`, `ERRORS`, `PLAUSIBLE_RANGES`) and the chain's blocks in "
      "`generator/flight/chain.py`; the encoder, the ground decoder, the flight C "
      "(`<unit>_table.h/.c`) and this page are all made from them.")
    a("")
    a("## Header")
    a("")
    a("| offset | bytes | type | field | meaning | checked before the CRC |")
    a("| ---: | ---: | --- | --- | --- | --- |")
    for f in HEADER_FIELDS:
        a(f"| {HEADER_OFFSETS[f.name]} | {f.size} | {f.type_name} | `{f.name}` | {f.doc} | "
          f"{('`' + f.check + '`') if f.check else '-'} |")
    a("")
    a(f"The payload starts at offset {HEADER_BYTES}. The CRC-32 (IEEE 802.3, as "
      "`zlib.crc32`: reflected polynomial 0xEDB88320, initial value and final XOR "
      "0xFFFFFFFF) covers the header and the payload and follows them as a uint32.")
    a("")
    a("The unit id is checked by hash and as text; either mismatch is `WRONG_UNIT`. "
      "The compiled-in default coefficients are the same format: "
      "`<unit>_table_default[]` (serial 0, created_s 0) is made by the same encoder.")
    a("")
    a("## Payload")
    a("")
    a("The coefficients as IEEE-754 float32 or float64 (`value_bytes`, the unit's "
      "`float`), in the order of the chain definition: sensor by sensor in the unit "
      "file's order, each sensor's blocks in order, every block row-major; then the "
      "unit-wide blocks. This is exactly the flat contents of `<unit>_coeffs_t`. "
      "With three coils and every optional stage (one channel), a sensor's blocks are:")
    a("")
    spec = _doc_example_spec()
    a("| block | shape | unit | kind | meaning |")
    a("| --- | --- | --- | --- | --- |")
    for b in spec.sensor_blocks(spec.unit.sensors[0]):
        a(f"| `{b.name}` | {list(b.shape) if b.shape else 'scalar'} | {_cell(b.unit)} | "
          f"{b.kind} | {_cell(b.doc)} |")
    a("")
    a("and the unit-wide blocks:")
    a("")
    a("| block | shape | unit | kind | meaning |")
    a("| --- | --- | --- | --- | --- |")
    for b in spec.unit_blocks():
        a(f"| `{b.name}` | {list(b.shape) if b.shape else 'scalar'} | {_cell(b.unit)} | "
          f"{b.kind} | {_cell(b.doc)} |")
    a("")
    a("`K_nT_per_A` is there only when the chain has coils, the blocks after it up to "
      "`agree_nT` only for the sensor's optional stages, `H_boom_to_body` only when the "
      "unit has a boom sensor; `layout_hash` covers which blocks there are and their "
      "shapes, so `payload_bytes` follows from the layout.")
    a("")
    a("## Plausible ranges")
    a("")
    a("Every value must lie in the closed range of its block's kind. For polynomial "
      "blocks (first axis = order k) the range of the order-k coefficients is the "
      "kind's range divided by span^k: every term c_k dT^k stays in the kind's range "
      "for |dT| up to the span.")
    a("")
    a("| kind | range | span | why |")
    a("| --- | --- | --- | --- |")
    for r in PLAUSIBLE_RANGES.values():
        rng = "part's raw count range" if r.part_counts else f"[{r.lo:g}, {r.hi:g}]"
        span = f"{r.poly_span_C:g} degC" if r.poly_span_C else "-"
        a(f"| {r.kind} | {rng} | {span} | {_cell(r.why)} |")
    a("")
    a("The bounds are rounded to the unit's float type, as the values are, in the flight "
      "C (one range table per block and order, `<unit>_table.c`) and in the ground "
      "decoder alike. The header temperature range must lie in the `temp` range with "
      "t_min_C < t_max_C. It is the min of t_min_C and the max of t_max_C over the "
      "sensors that have a temperature; a sensor without one (ICD section 4, "
      "`temperature = false`) has no t_ref_C, t_min_C, t_max_C blocks and no part in it. "
      "A unit none of whose sensors has a temperature has a constant model that holds at "
      f"any temperature: its header range is the whole `temp` range, "
      f"[{NO_TEMP_RANGE_C[0]:g}, {NO_TEMP_RANGE_C[1]:g}] degC.")
    a("")
    lim = PHYSICAL_LIMITS
    a("## Physical checks")
    a("")
    a("Beyond the range of each value, the coefficients must mean something physical "
      "(`PHYSICAL_LIMITS` in `generator/flight/table_physics.py`, which also holds the "
      "ground validator's arithmetic), computed in the unit's float type with + - * only, "
      "in the same "
      "order in the flight C and the ground validator, so both give the same verdict bit "
      "for bit (on the host and on the Cortex-M4F):")
    a("")
    a(f"- `BAD_DETERMINANT`: for every sensor, det M(T) within [1/27, 27] "
      f"(rounded to the float type: [{lim.det_M_lo:.9g}, {lim.det_M_hi:g}]) at T = t_ref_C "
      "(the constant term M0) and at t_min_C and t_max_C (M(T) by Horner, the chain's "
      "order; det by the first row). det M is the product of M's singular values: with "
      "every gain within [1/3, 3] (the matrix_poly range allows 3; below 1/3 the part's "
      "lsb would be wrong by 3x) it lies within [3^-3, 3^3]. An all-zero or singular M "
      "gives 0, a reflected axis a negative determinant: both refused. The first bad "
      "value named is the sensor's `M_poly[0][0][0]`.")
    a(f"- `NOT_A_ROTATION`: `H_boom_to_body` must be a rotation: every element of "
      f"H^T H - I (i <= j) within +-{lim.rotation_tol:.4g} and det H > 0. The tolerance is "
      f"a float32 rounding bound, 2^-21 = {lim.rotation_rounding:.3g} (each stored "
      "element within 2^-24 relative, 2 x 2^-24 on (H^T H)_ij, and the float32 "
      "evaluation's 4 roundings), plus a physical allowance of "
      f"{lim.rotation_allowance:g}: |H v|^2 = |v|^2 + v^T (H^T H - I) v, so |B| changes "
      "by at most 1.5e-5 relative, 0.8 nT at 55 000 nT, far below the parts' lsb and "
      "noise. The first bad value named is H[i][j] of the failing (i, j).")
    a("")
    a("## Serials")
    a("")
    a("A table that passes every check is installed only if its serial is above the "
      "active table's (`SERIAL_CHECKS`; the Python model of the manager is "
      "`generator/flight/table_manager.py`), in `<unit>_table_load` and `_commit`, after "
      "`SERIAL_MISMATCH`: a lower serial is `SERIAL_ROLLBACK`; an equal serial with "
      "other coefficients (compared bit for bit) is `SERIAL_REPLAY`; an equal serial "
      "with the same coefficients is refused too, as `ALREADY_ACTIVE`: nothing changes, "
      "and the ground sees that its table is the one in use (as `PART_REPEATED` does for "
      "a part). Only the coefficients count as the contents: `created_s` is not "
      "compared. The compiled-in default has serial 0, so on first boot any valid table "
      "with serial >= 1 is accepted and serial 0 is never accepted from the ground "
      "(`magcal table` writes serial 1 unless told otherwise). Serials do not wrap: "
      "after 4294967295 nothing newer can be loaded. The manager keeps its serial in "
      "RAM: after a reset it starts again from the compiled-in default at serial 0, so a "
      "rollback across a reset is only refused if the flight software keeps the last "
      "accepted table in non-volatile memory and loads it (`<unit>_table_load`) at boot, "
      "before it accepts uplinks: that restores the serial the rule compares against.")
    a("")
    a("## The compiled-in default at init")
    a("")
    a("`<unit>_table_init(mgr, defaults)` runs the content checks of a table on the "
      "default coefficients, without a header (in this order: "
      + ", ".join(f"`{c}`" for c in CONTENT_CHECKS) + "). If they pass, the defaults "
      "are in use at serial 0 and init returns `OK`. If one fails, init returns that "
      "check's status (also in `last_status`, with the first bad value in "
      "`last_bad_value`) and falls back to coefficients that are all quiet NaN: every "
      "correction then returns `STATUS_IMPLAUSIBLE` (the |B| band check fails on NaN) "
      "and `<unit>_select` finds no valid sensor (`SELECT_NONE`), so no number computed "
      "from a broken default reaches attitude control. `info.coeffs_valid` is 0 in "
      "that state and becomes 1 when a valid table (serial >= 1) is loaded.")
    a("")
    a("## A manager never initialised")
    a("")
    a("A `<unit>_table_mgr_t` that `<unit>_table_init` never completed on (zero-filled "
      "static storage, erased memory, a task or an interrupt that runs before init) holds "
      "no coefficients: on its zeros every correction returns a zero field that passes "
      "the |B| band check (0 - 0 >= 0), flagged valid wherever the temperature check "
      "passes too (a sensor without a temperature; 0 degC, the zeroed range). The "
      "manager therefore knows whether init completed: init clears the whole struct "
      "first and, as its last step (after the OK or the NaN-fallback state is "
      "complete), stores "
      f"`<UNIT>_TABLE_INIT_MARK` = 0x{MANAGER_INIT_MARK:08X} in `init_mark` (the bytes "
      f"\"{MANAGER_INIT_MARK.to_bytes(4, 'little').decode('ascii')}\" in a little-endian "
      "dump; its bytes are not all equal, so no single-byte fill, 0x00 or 0xFF or any "
      "other, looks initialised). Every other manager function tests it, as cFS table "
      "services answer `CFE_TBL_ERR_NEVER_LOADED` for a table never loaded. On a manager "
      "not initialised:")
    a("")
    a("- `<unit>_table_load`, `_receive_part` and `_commit` return `NOT_INITIALISED` "
      f"(code {int(TableStatus.NOT_INITIALISED)}) and change nothing (a NULL manager or "
      "part is still `NULL_ARGUMENT`, checked first); `<unit>_table_abort` does nothing;")
    a("- `<unit>_table_info` reports `coeffs_valid` 0, `last_status` `NOT_INITIALISED`, "
      "`last_bad_value` `NO_INDEX` and zero in every other field;")
    a("- `<unit>_table_active` and `<unit>_table_prepared` return compiled-in sets whose "
      "every value is a quiet NaN (the sets the init fallback puts in use), never NULL and "
      "never the manager's unchecked bytes: every correction on them returns "
      "`STATUS_IMPLAUSIBLE` and `<unit>_select` on those outputs finds no valid sensor "
      "(`SELECT_NONE`; with 3 or more sensors it finds none on the NaN set even when "
      "told every sensor is valid, as the NaN agreement tolerance fails every "
      "comparison; with 1 or 2 it follows the statuses it is given). "
      "The same holds for a NULL manager.")
    a("")
    a("NaN rather than NULL: the corrections do not test their pointer, and on a "
      "Cortex-M address 0 is readable memory (the vector table), so a NULL passed on by a "
      "caller that forgot to check would not stop the program but would be read as "
      "coefficients. The NaN sets cost constant memory, sizeof(`<unit>_coeffs_t`) + "
      "sizeof(`<unit>_table_prepared_t`) (the number is in `<unit>_table.h`; "
      "docs/flight_target.md gives the table object's constants). The mark is not a lock: "
      "init must complete before another context uses the manager. "
      "`generator.flight.table_manager.TableManager(spec)` (no defaults) models this state.")
    a("")
    a("## Prepared coefficients")
    a("")
    a("The corrections (`<unit>_<sensor>_correct`, `_correct_set`) and `<unit>_select` "
      "take a `<unit>_table_prepared_t`, not the table's coefficients: what the chain "
      "needs once every constant is folded that can be folded when a table is loaded "
      "(the count-to-nT scale and the axis signs into b(T) and M(T), H M(T) for a boom "
      "sensor without SET/RESET rate compensation, the band limits squared; "
      "docs/flight_target.md, *The flop bound*). "
      "`<unit>_table_prepare(coeffs, prepared)` computes them (+ - * / in the unit's "
      "float type, fixed size). The manager runs it when a table is activated, into the "
      "prepared copy of the inactive buffer, so a refused table keeps both the old table "
      "and its prepared copy; `<unit>_table_prepared(mgr)` returns the prepared copy of "
      "the table in use (`<unit>_table_active(mgr)` its coefficients). "
      "`<unit>_table_prepared_default` is the compiled-in default prepared at generate "
      "time. Flight software that fills a coefficient struct itself calls "
      "`<unit>_table_prepare` before the corrections: a coefficient struct passed to "
      "them is an incompatible pointer, which C99 compilers diagnose (an error with "
      "-Werror, as the flight flags have, and by default from GCC 14; a warning only "
      "in older GCC without it). `<unit>_table_prepared_default` holds the defaults "
      "as they are, without the table checks: flight software takes the "
      "prepared copy from the manager, which falls back to NaN when the defaults fail "
      "them. The Python "
      "reference prepares in the same order (`generator.flight.chain.prepare_sensor`); "
      "host_tests/test_prepare.py compares the two bit for bit.")
    a("")
    a("## Checks, in order")
    a("")
    a("`<unit>_table_validate` runs these checks in this order and returns the status of "
      "the first that fails; a flipped bit in a field checked before the CRC gives that "
      "field's status, any other flipped bit `BAD_CRC`.")
    a("")
    a("| code | status | meaning |")
    a("| ---: | --- | --- |")
    for i, (n, r) in enumerate(ERRORS):
        a(f"| {i} | `{n}` | {_cell(r)} |")
    a("")
    first_part = int(TableStatus.PART_TRUNCATED)
    first_commit = int(TableStatus.NOTHING_STAGED)
    last_commit = int(TableStatus.SERIAL_MISMATCH)
    codes = ", ".join(str(int(TableStatus[c])) for c in CHECK_ORDER)
    a("Codes are never renumbered: a check added later gets the next free code, so the "
      "code values do not give the check order. The table checks (`CHECK_ORDER`, codes "
      f"{codes}) run in this order: a NULL "
      "buffer; the length against the header; the header fields in header order (magic, "
      "version, value width, unit id hash and text, layout hash, payload length); the "
      "length against the payload length; the CRC; then the content: the header "
      "temperature range, finiteness of every value, the plausible range of every value, "
      "every lower limit below its upper limit (`ORDERED_PAIRS`: "
      + ", ".join(f"{lo} < {hi}" for lo, hi in ORDERED_PAIRS) + "), the header "
      "range equal to the min/max over the sensors with a temperature (in float32), det M, H a rotation. "
      f"Codes {first_part} to {first_commit - 1} come from `receive_part`, in that order; "
      f"{first_commit} to {last_commit} from `commit` (nothing staged and missing "
      "parts before the table checks of the reassembled table, the serial mismatch after "
      "them); then load and commit apply the serial rule ("
      + ", ".join(f"`{c}`" for c in SERIAL_CHECKS) + "). "
      f"`NOT_INITIALISED` (code {int(TableStatus.NOT_INITIALISED)}) comes from load, "
      "receive_part and commit on a manager that init never completed on, before any "
      "other check but the NULL pointers (*A manager never initialised*). "
      "`<unit>_table_strerror(code)` gives the meaning.")
    a("")
    a("## Parts")
    a("")
    a("For the link, a table is cut into parts of at most N bytes "
      "(`magcal table ... --chunk N`), each:")
    a("")
    a(f"    part header ({PART_HEADER_BYTES} bytes) | part_bytes table bytes | "
      f"CRC-32 of header and bytes ({CRC_BYTES} bytes)")
    a("")
    a("| offset | bytes | type | field | meaning | checked before the CRC |")
    a("| ---: | ---: | --- | --- | --- | --- |")
    for f in PART_FIELDS:
        a(f"| {PART_OFFSETS[f.name]} | {f.size} | {f.type_name} | `{f.name}` | {f.doc} | "
          f"{('`' + f.check + '`') if f.check else '-'} |")
    a("")
    a("The flight code collects parts into a staging buffer (bytes), never into the "
      "coefficients in use. Parts may arrive in any order (each goes at "
      "part_index * chunk_bytes, and the numbering must tile the table exactly); a part "
      "already received is refused (`PART_REPEATED` if identical, `PART_CONFLICT` if "
      "not) and changes nothing; a part of another serial while a transfer is in "
      "progress is refused (`PART_FOREIGN_SERIAL`; `<unit>_table_abort` drops the "
      "transfer); so is a change of part count or chunk size (`PART_COUNT_CHANGED`). "
      "`<unit>_table_commit` refuses an incomplete transfer (`PARTS_MISSING`, the "
      "transfer stays open for the missing parts), then validates the whole table, "
      "checks that its serial is the parts' serial, applies the serial rule, decodes "
      "it into the inactive buffer and switches the active index. A commit that fails validation drops "
      "the transfer. `<unit>_table_load` does the same for a table received in one "
      "piece.")
    a("")
    a("## Commands")
    a("")
    a("    magcal table COEFFS.json -o TABLE.bin [--serial N] [--created-s T] [--chunk N]")
    a("    magcal table --decode TABLE.bin [--coeffs COEFFS.json]")
    a("    magcal table --diff A.bin B.bin [--coeffs COEFFS.json]")
    a("    magcal table --check TABLE.bin --coeffs COEFFS.json")
    a("")
    a("The first writes TABLE.bin, the dump TABLE.txt beside it and, with --chunk N, "
      "TABLE.part000.bin ... of at most N bytes each. `--created-s` defaults to "
      "SOURCE_DATE_EPOCH if set, else 0, so the output is reproducible. `--check` runs "
      "the flight C validator, compiled on the host, and exits 0 if it accepts the "
      "table, 2 with the status code and reason if not.")
    return "\n".join(L) + "\n"


def write_format_doc(path=DOC_PATH) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(format_doc())
    return path


def main(argv=None) -> int:
    """`python -m generator.report.table_doc --write-doc`: regenerate docs/table_format.md."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m generator.report.table_doc")
    p.add_argument("--write-doc", action="store_true", help=f"write {DOC_PATH}")
    args = p.parse_args(argv)
    if args.write_doc:
        print(f"wrote {write_format_doc()}")
        return 0
    p.print_help()
    return 2


if __name__ == "__main__":
    sys.exit(main())
