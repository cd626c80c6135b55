"""The coil-study file format (docs/coil_study.md): its names and its input rules.

A telemetry file with a `coil_distance_cm` column is a coil study: a test coil at known
distances from the sensor(s) named by `# coil_test_sensor:`, without and with the solar
panel (`panel` 0/1). Its rules are checked where the file is read
(io/telemetry_csv.read_telemetry and iter_telemetry), so every verb that reads it (fit,
with or without a report, check, trace, apply) refuses a bad study before any fitting:

* check_meta (when the header is known): every `# coil_test_sensor` name is a sensor of
  the unit; the key without a coil_distance_cm column is refused (the file would
  otherwise be taken as a flight coil campaign); a study has a coil_*_A current column;
* check_cells (every chunk): a distance that is not > 0, a panel other than 0 or 1;
* check_file (the whole file): every panel state holds two or more distances among its
  static rows (the distance law |K|(r) needs them), and at every distance each coil
  current steps (else K is undetermined there).

Each fault is one InputError naming the file, the line (Parquet: the data row) and the
column or key. Numbers are formatted with :g, never as numpy reprs.
The fit itself is generator/fit/coils.py (fit_coil_study).
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError

DISTANCE_COLUMN = "coil_distance_cm"
PANEL_COLUMN = "panel"
TEST_SENSOR_KEY = "coil_test_sensor"
POSITION_COLUMN = "position"
PANEL_STATES = (0.0, 1.0)                  # 0: without the solar panel, 1: with it


def is_coil_study(tel) -> bool:
    """A coil-study file: it has a coil_distance_cm column."""
    return DISTANCE_COLUMN in tel.columns


def coil_columns(tel) -> list:
    """The magnetorquer current columns of a telemetry file: coil_<name>_A, sorted."""
    return sorted(_coil_names(tel.columns))


def _coil_names(names) -> list:
    return [c for c in names if c.startswith("coil_") and c.endswith("_A")]


def study_sensors(path, meta: dict, unit) -> list:
    """The sensors a study's distances are measured to: the `# coil_test_sensor:` names,
    every sensor of the unit when the key is absent or empty. An unknown name: InputError."""
    text = (meta or {}).get(TEST_SENSOR_KEY)
    if not text:
        return list(unit.sensor_names)
    names = [x.strip() for x in text.split(",") if x.strip()]
    for n in names:
        if n not in unit.sensor_names:
            raise InputError(path, f"'# {TEST_SENSOR_KEY}: {text}': unit {unit.id} has no "
                                   f"sensor {n!r} (it has {', '.join(unit.sensor_names)})")
    return names


def check_meta(path, names, meta: dict, unit) -> None:
    """Rules known once the header and the metadata are read (names: the columns)."""
    names = list(names)
    study = DISTANCE_COLUMN in names
    if TEST_SENSOR_KEY in (meta or {}) and not study:
        raise InputError(path, f"'# {TEST_SENSOR_KEY}' is given but there is no "
                               f"{DISTANCE_COLUMN} column: a coil study needs the distance of "
                               "every sample (docs/coil_study.md)")
    if not study:
        return
    study_sensors(path, meta, unit)
    if not _coil_names(names):
        raise InputError(path, f"a coil study ({DISTANCE_COLUMN} column) needs the test "
                               "coil's current in a coil_<name>_A column; the header has none")


def check_cells(path, columns: dict, line_numbers) -> None:
    """Distances > 0 and panel flags 0 or 1 (empty cells: missing, allowed)."""
    dist = columns.get(DISTANCE_COLUMN)
    if dist is None:
        return
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(np.isfinite(dist) & ~(dist > 0))
    if bad.size:
        i = bad[0]
        raise InputError(path, f"{float(dist[i]):g} is not a positive distance (cm from the "
                               "test coil's centre to the sensor)",
                         line=int(line_numbers[i]), column=DISTANCE_COLUMN)
    panel = columns.get(PANEL_COLUMN)
    if panel is None:
        return
    bad = np.flatnonzero(np.isfinite(panel) & ~np.isin(panel, PANEL_STATES))
    if bad.size:
        i = bad[0]
        raise InputError(path, f"{float(panel[i]):g} is not 0 (without) or 1 (with the solar "
                               "panel)", line=int(line_numbers[i]), column=PANEL_COLUMN)


def static_rows(tel) -> np.ndarray:
    """Rows a study fit uses: a distance and a panel flag given, the unit in a static
    position (position > 0; no position column: the file is one static position)."""
    dist = np.asarray(tel.columns[DISTANCE_COLUMN], float)
    ok = np.isfinite(dist) & np.isfinite(panel_flags(tel))
    if POSITION_COLUMN in tel.columns:
        pos = np.asarray(tel.columns[POSITION_COLUMN], float)
        with np.errstate(invalid="ignore"):
            ok &= np.isfinite(pos) & (pos > 0)
    return ok


def panel_flags(tel) -> np.ndarray:
    """The panel column, 0 (without the panel) where the file has none."""
    if PANEL_COLUMN in tel.columns:
        return np.asarray(tel.columns[PANEL_COLUMN], float)
    return np.zeros(tel.n)


def check_study(tel, unit) -> None:
    """Every rule at once, for a Telemetry built in memory rather than read from a file
    (read_telemetry has run them already; running them again changes nothing)."""
    if TEST_SENSOR_KEY in tel.meta or is_coil_study(tel):
        check_meta(tel.path, tel.columns, tel.meta, unit)
        check_cells(tel.path, tel.columns, tel.line_numbers)
        check_file(tel)


def check_file(tel) -> None:
    """Whole-file rules of a coil study (no-op for another file): per panel state two or
    more distances among the static rows, and at each distance a current that steps."""
    if not is_coil_study(tel):
        return
    dist = np.asarray(tel.columns[DISTANCE_COLUMN], float)
    panel = panel_flags(tel)
    ok = static_rows(tel)
    if not ok.any():
        raise InputError(tel.path, "no static row with a distance (a coil study needs rows "
                                   "with a position > 0 and a distance)",
                         column=DISTANCE_COLUMN)
    coils = coil_columns(tel)
    current = np.column_stack([np.asarray(tel.columns[c], float) for c in coils])
    for p in np.unique(panel[ok]):
        in_p = ok & (panel == p)
        rs = np.unique(dist[in_p])
        first = int(tel.line_numbers[np.argmax(in_p)])
        if rs.size < 2:
            raise InputError(tel.path, f"panel {p:g}: every static row is at {rs[0]:g} cm; "
                                       "a coil study needs two or more distances per panel "
                                       "state (the distance law is fitted to them)",
                             line=first, column=DISTANCE_COLUMN)
        for r in rs:
            sel = in_p & (dist == r)
            for j, c in enumerate(coils):
                I = current[sel, j]
                I = I[np.isfinite(I)]
                if I.size == 0 or I.max() == I.min():
                    raise InputError(tel.path, f"at {r:g} cm, panel {p:g}: the current never "
                                               "changes, so the coil's interference there is "
                                               "undetermined: step it (0, +a, -a, ...)",
                                     line=int(tel.line_numbers[np.argmax(sel)]), column=c)
