"""`magcal table`: encode a coefficient set as an uplink table, decode, diff, split, check."""

from __future__ import annotations

import os
from pathlib import Path

from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.outputs import check_output_file, refuse_inputs, write_bytes
from generator.flight.table_host import TableHost
from generator.flight.tables import (NO_INDEX, TableError, TableStatus, check_table,
                                     chunk_table, diff_tables, dump_table, encode_table,
                                     join_parts, n_values, value_layout)


def add_table_args(p) -> None:
    """Arguments of `magcal table` (an argparse parser)."""
    p.add_argument("coeffs_json", nargs="?", metavar="COEFFS.json",
                   help="coefficients.json to encode as a table")
    p.add_argument("-o", "--output", metavar="TABLE.bin",
                   help="table to write (the dump TABLE.txt goes beside it)")
    p.add_argument("--serial", type=int, default=1, help="table serial, u32 (default 1)")
    p.add_argument("--created-s", type=int, default=None,
                   help="creation time, s since 1970 UTC (default: SOURCE_DATE_EPOCH or 0)")
    p.add_argument("--chunk", type=int, metavar="N",
                   help="also write TABLE.part000.bin ... of at most N bytes each")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--decode", metavar="TABLE.bin", help="print a table as text")
    mode.add_argument("--diff", nargs=2, metavar=("A.bin", "B.bin"),
                      help="print the changes from table A to table B")
    mode.add_argument("--check", metavar="TABLE.bin",
                      help="run the flight C validator (needs --coeffs): exit 0 if accepted")
    p.add_argument("--coeffs", metavar="COEFFS.json",
                   help="the unit's coefficients.json: its chain names the values "
                        "(--decode, --diff) and builds the validator (--check)")


def _read_bytes(path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None


def _load_coeffs(path):
    return CoefficientSet.load(path) if path else None


def cmd_table(args) -> int:
    """`magcal table`: encode, --decode, --diff or --check (see add_table_args)."""
    import sys

    quiet = getattr(args, "quiet", False)
    want_json = getattr(args, "json", False)
    human = sys.stderr if want_json else sys.stdout   # under --json stdout is the JSON only

    def say(text):
        if not quiet:
            print(text, file=human)

    cs = _load_coeffs(getattr(args, "coeffs", None))
    spec = cs.spec if cs is not None else None
    if args.decode or args.diff or args.check:
        if args.coeffs_json or args.output or args.chunk:
            raise InputError(None, "--decode, --diff and --check take no COEFFS.json, "
                                   "-o or --chunk (give the unit's file as --coeffs)")
    if args.decode:
        data = _read_bytes(args.decode)
        try:
            text = dump_table(data, spec, title=str(args.decode))
        except TableError as e:
            raise e.at(args.decode) from None
        print(text, end="", file=human)
        return 0, {"verb": "table", "exit": 0, "decode": str(args.decode), "text": text}
    if args.diff:
        tables = []
        for path in args.diff:
            data = _read_bytes(path)
            try:
                check_table(data, spec)
            except TableError as e:
                raise e.at(path) from None
            tables.append(data)
        changes = diff_tables(tables[0], tables[1], spec)
        for c in changes:
            print(c, file=human)
        if not changes:
            print("no differences", file=human)
        return 0, {"verb": "table", "exit": 0, "diff": [str(p) for p in args.diff],
                   "changes": [str(c) for c in changes]}
    if args.check:
        if cs is None:
            raise InputError(None, "--check needs --coeffs COEFFS.json (the unit and chain "
                                   "whose flight validator to run)")
        data = _read_bytes(args.check)
        host = TableHost(cs)
        st, bad = host.validate_detail(data)
        if st != TableStatus.OK:
            detail = f"flight validator of {cs.unit.id}"
            if bad != NO_INDEX and bad < n_values(cs.spec):
                info = value_layout(cs.spec)[bad]
                detail += f"; first bad value {info.label}"
            raise TableError(st, detail, args.check, None if bad == NO_INDEX else bad)
        say(f"{args.check}: accepted by the flight validator of {cs.unit.id} "
            f"(layout 0x{cs.spec.layout_hash():08x})")
        return 0
    # encode: everything is computed and checked first, then written (each file atomically)
    if not args.coeffs_json or not args.output:
        raise InputError(None, "usage: magcal table COEFFS.json -o TABLE.bin "
                               "(or --decode, --diff, --check)")
    out = check_output_file(args.output)
    txt = out.with_suffix(".txt")
    if txt == out:
        raise InputError(args.output, "-o: the table must not end in .txt (its text dump "
                                      "TABLE.txt is written beside it)")
    check_output_file(txt)
    refuse_inputs(out, [args.coeffs_json, args.coeffs])
    refuse_inputs(txt, [args.coeffs_json, args.coeffs])
    if args.serial == 0:
        raise InputError(None, "--serial: 0 is the compiled-in default's serial; the flight "
                               "code never accepts it from the ground (docs/table_format.md)")
    src = CoefficientSet.load(args.coeffs_json)
    created = args.created_s
    if created is None:
        env = os.environ.get("SOURCE_DATE_EPOCH", "0")
        try:
            created = int(env)
        except ValueError:
            raise InputError(None, f"SOURCE_DATE_EPOCH={env!r} is not an integer") from None
    try:
        table = encode_table(src, args.serial, created)
    except TableError as e:
        raise e.at(args.coeffs_json) from None
    dump = dump_table(table, src.spec, title=out.name)
    files = [(out, table), (txt, dump.encode("utf-8"))]
    parts = []
    if args.chunk is not None:
        try:
            parts = chunk_table(table, args.chunk)
        except InputError as e:
            raise InputError(args.output, f"--chunk {args.chunk}: {e.message}") from None
        if join_parts(parts, src.spec) != table:   # the ground checks its own parts
            raise RuntimeError("chunked parts do not reassemble into the table")
        for i, part in enumerate(parts):
            p = check_output_file(out.with_name(f"{out.stem}.part{i:03d}.bin"))
            if p in (out, txt):
                raise InputError(args.output, f"-o: part {p.name} would overwrite the table")
            files.append((p, part))
    for path, data in files:
        write_bytes(path, data)
    say(f"wrote {out} ({len(table)} bytes, serial {args.serial}) and {txt}")
    if parts:
        say(f"wrote {len(parts)} parts {out.stem}.part000.bin .. "
            f"{out.stem}.part{len(parts) - 1:03d}.bin of at most {args.chunk} bytes")
    return 0
