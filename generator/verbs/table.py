"""`magcal table`: encode a coefficient set as an uplink table, decode, diff, split, check
(a table or its parts), join parts into the table."""

from __future__ import annotations

import os
from pathlib import Path

from generator.errors import InputError
from generator.flight.coeffs import CoefficientSet
from generator.io.outputs import check_output_file, refuse_inputs, write_bytes
from generator.flight.table_host import TableHost
from generator.flight.tables import (NO_INDEX, PART_MAGIC, Reassembler, TableError,
                                     TableStatus, check_table, chunk_table, diff_tables,
                                     dump_table, encode_table, join_parts, n_values,
                                     value_layout)


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
    mode.add_argument("--check", nargs="+", metavar="TABLE.bin",
                      help="run the flight C validator (needs --coeffs): exit 0 if accepted; "
                           "parts (TABLE.partNNN.bin) get the flight's part checks, and "
                           "when all are given the table they reassemble into is validated")
    mode.add_argument("--join", nargs="+", metavar="PART.bin",
                      help="reassemble parts into -o TABLE.bin (needs --coeffs): the "
                           "flight's part checks, then its validator on the table")
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
    join = getattr(args, "join", None)
    if args.decode or args.diff or args.check or join:
        if args.coeffs_json or (args.output and not join) or args.chunk:
            raise InputError(None, "--decode, --diff, --check and --join take no "
                                   "COEFFS.json or --chunk, only --join takes -o (give the "
                                   "unit's file as --coeffs)")
    if join:
        return _join(args, cs, say)
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
        host = TableHost(cs)
        parts = []
        for path in args.check:
            data = _read_bytes(path)
            if data[:4] == PART_MAGIC:
                parts.append((path, data))
                continue
            _validate(host, cs, data, path)
            say(f"{path}: accepted by the flight validator of {cs.unit.id} "
                f"(layout 0x{cs.spec.layout_hash():08x})")
        if parts:
            r = _receive(cs, parts)
            names = ", ".join(str(p) for p, _ in parts)
            if len(r.seen) < r.count:
                say(f"{names}: part(s) {', '.join(str(i) for i in sorted(r.seen))} of "
                    f"{r.count} (serial {r.serial}) pass the flight's part checks (magic, "
                    f"length, CRC, table size, numbering); give all {r.count} parts to "
                    "validate the table they make")
            else:
                table = _commit(r, cs, parts)
                _validate(host, cs, table, parts[-1][0])
                say(f"{names}: all {r.count} parts pass the flight's part checks and "
                    f"reassemble into table serial {r.serial}, accepted by the flight "
                    f"validator of {cs.unit.id} (layout 0x{cs.spec.layout_hash():08x})")
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


def _validate(host, cs, data, path) -> None:
    """The flight C validator on a table; TableError naming the first bad value."""
    st, bad = host.validate_detail(data)
    if st != TableStatus.OK:
        detail = f"flight validator of {cs.unit.id}"
        if bad != NO_INDEX and bad < n_values(cs.spec):
            detail += f"; first bad value {value_layout(cs.spec)[bad].label}"
        raise TableError(st, detail, path, None if bad == NO_INDEX else bad)


def _receive(cs, parts) -> Reassembler:
    """The flight's part checks (flight.tables.Reassembler, the C's order and codes) on
    every (path, bytes); TableError naming the first part it rejects."""
    r = Reassembler(cs.spec)
    for path, data in parts:
        st = r.receive(data)
        if st != TableStatus.OK:
            raise TableError(st, f"part checks of {cs.unit.id}", path)
    return r


def _commit(r, cs, parts) -> bytes:
    st, table = r.commit()
    if st != TableStatus.OK:
        raise TableError(st, f"the {len(parts)} parts reassembled ({cs.unit.id})",
                         parts[-1][0])
    return table


def _join(args, cs, say) -> int:
    """--join PART.bin ... -o TABLE.bin: the parts reassembled, checked as on board (part
    checks, commit, the flight C validator), then written atomically."""
    if cs is None or not args.output:
        raise InputError(None, "usage: magcal table --join PART.bin ... -o TABLE.bin "
                               "--coeffs COEFFS.json")
    out = check_output_file(args.output)
    refuse_inputs(out, [*args.join, args.coeffs])
    parts = [(p, _read_bytes(p)) for p in args.join]
    r = _receive(cs, parts)
    if len(r.seen) < r.count:
        missing = sorted(set(range(r.count)) - r.seen)
        raise TableError(TableStatus.PARTS_MISSING,
                         f"part(s) {', '.join(map(str, missing))} of {r.count} not given",
                         parts[-1][0])
    table = _commit(r, cs, parts)
    _validate(TableHost(cs), cs, table, out)
    write_bytes(out, table)
    say(f"wrote {out} ({len(table)} bytes, serial {r.serial}) from {r.count} parts, "
        f"accepted by the flight validator of {cs.unit.id}")
    return 0
