"""`magcal import`: recordings from elsewhere -> a unit TOML skeleton and ICD telemetry CSV.

    magcal import px4 LOG.ulg... -o DIR [--reference attitude|norm|none] [--as-counts LSB]
    magcal import csv FILE --map mag_x=colA,mag_y=colB,mag_z=colC [--input uT] -o DIR ...

px4: PX4 ULog files (pyulog) or folders of their CSV export (ulog2csv), see
generator/io/px4_ulog.py. csv: a CSV with a header, or an HDF5 / MATLAB v7.3 file, in
physical units with a column map, see generator/io/csv_import.py.
"""

from __future__ import annotations

from generator.io import parts as P
from generator.io.csv_import import import_table, parse_map
from generator.io.px4_ulog import REFERENCES, import_px4
from generator.progress import Progress


def add_import_args(p):
    sub = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    x = sub.add_parser("px4", help="PX4 ULog files (.ulg) or ulog2csv export folders",
                       description="PX4 ULog files (.ulg, pyulog) or ulog2csv export folders: "
                                   "every sensor_mag instance, vehicle_magnetometer, channels "
                                   "worth tracing, and the IGRF reference")
    x.add_argument("logs", nargs="+", help="PX4 logs of one vehicle setup")
    x.add_argument("--reference", default="attitude", choices=REFERENCES,
                   help="attitude: IGRF field at the GNSS position rotated into the body frame "
                        "by vehicle_attitude (ref_x/y/z_nT, ref_norm_nT); norm: its magnitude "
                        "only; none: no reference (default attitude)")
    x.add_argument("--static", type=int, default=None, metavar="N",
                   help="the vehicle stood still: write position = N (ICD static position) "
                        "on every row")
    x.add_argument("--only", default=None, metavar="NAME,...",
                   help="import only these magnetometers (mag<i>, vmag), e.g. --only vmag")
    c = sub.add_parser("csv", help="a CSV (header line) or HDF5/.mat file in physical units",
                       description="a CSV with a header line, or an HDF5 / MATLAB v7.3 file, "
                                   "in physical units, with a column map")
    c.add_argument("file", help="the table")
    c.add_argument("--map", required=True, metavar="TARGET=SOURCE,...",
                   help="ICD column = source column (CSV header name, or HDF5 dataset NAME or "
                        "NAME:k for component k): <s>_x,<s>_y,<s>_z per sensor, optional "
                        "<s>_temp_C, time_s, any channel")
    c.add_argument("--input", default="uT", choices=list(P.INPUT_UNITS_nT),
                   help="unit of the field columns (default uT)")
    c.add_argument("--part", default=P.GENERIC,
                   help=f"catalogue part of every sensor (default generic); known: "
                        f"{', '.join(P.names())}")
    c.add_argument("--range-nT", type=float, default=None,
                   help="full scale per axis, nT (needed for generic)")
    c.add_argument("--rate-hz", type=float, default=None,
                   help="sample rate when the map has no time_s")
    c.add_argument("--time-scale", type=float, default=1.0,
                   help="seconds per unit of the time column (1e-3 for ms, 1e-6 for us)")
    for q in (x, c):
        q.add_argument("-o", "--output", required=True, help="output folder")
        q.add_argument("--unit-id", default=None, help="unit id (default from the file name)")
        q.add_argument("--as-counts", type=float, default=None, metavar="LSB_nT",
                       help="write integer counts of this size instead of physical units, "
                            "with a constant stand-in temperature where none is reported "
                            "(for flight code that takes counts only)")
        q.add_argument("--field-nT", type=float, default=None,
                       help="field magnitude where the recording was made, nT: written as "
                            "lab_field_nT (the reference of an ellipsoid fit without ref_*)")
        q.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
        q.add_argument("--json", action="store_true",
                       help="print a JSON result on stdout (for scripts)")


def cmd_import(args):
    progress = Progress(quiet=getattr(args, "quiet", False))
    if args.format == "px4":
        paths = import_px4(args.logs, args.output, reference=args.reference,
                           as_counts_lsb_nT=args.as_counts, unit_id=args.unit_id,
                           field_nT=args.field_nT, position=args.static,
                           only=[n.strip() for n in args.only.split(",")] if args.only else None)
    else:
        paths = import_table(args.file, args.output, parse_map(args.map),
                             input_unit=args.input, part=args.part, range_nT=args.range_nT,
                             rate_hz=args.rate_hz, time_scale=args.time_scale,
                             unit_id=args.unit_id, as_counts_lsb_nT=args.as_counts,
                             field_nT=args.field_nT)
    progress(f"wrote {paths['unit']} and {', '.join(str(p) for p in paths['data'])}")
    return 0, {"verb": "import", "exit": 0, "unit": str(paths["unit"]),
               "data": [str(p) for p in paths["data"]]}
