"""The flight table manager in Python: the serial rule, the defaults checked at init, and
the whole manager (`<unit>_table_init/load/receive_part/commit/abort`) as a model.

The flight C (templates/table.c.j2) is the manager; this module gives the ground tools and
the differential tests the same decisions with the same codes in the same order: a table
that passes every check of tables.check_table is installed only if its serial is above
the active table's (serial_status), init falls back to NaN coefficients when the
compiled-in defaults fail the content checks (init_status, poisoned_values), and a
manager that init never completed on (TableManager(spec) without defaults: zero-filled
static storage, say) refuses everything with NOT_INITIALISED and hands out NaN.
"""

from __future__ import annotations

import numpy as np

from generator.flight.chain import ChainSpec, prepare_sensor
from generator.flight.tables import (NO_INDEX, Reassembler, TableError, TableStatus,
                                     check_table, check_values, n_prepared_values, n_values,
                                     value_dtype)


def serial_status(active_serial: int, active_values, serial: int, values) -> TableStatus:
    """The serial rule of load and commit for a table that passed every check: a lower
    serial than the active table's is a rollback; an equal one is a replay if the
    coefficients differ (bit for bit), ALREADY_ACTIVE if they are the same (refused too:
    nothing to change, and the ground sees that its table is the one in use)."""
    S = TableStatus
    if serial < active_serial:
        return S.SERIAL_ROLLBACK
    if serial == active_serial:
        a, b = np.asarray(active_values), np.asarray(values)
        same = a.dtype.itemsize == b.dtype.itemsize and a.size == b.size and \
            np.array_equal(a.view(f"u{a.dtype.itemsize}"), b.view(f"u{b.dtype.itemsize}"))
        return S.ALREADY_ACTIVE if same else S.SERIAL_REPLAY
    return S.OK


def poisoned_values(spec: ChainSpec) -> np.ndarray:
    """What the flight manager puts in use when the compiled-in defaults fail their checks
    at init: every coefficient a quiet NaN, so every correction is flagged (the |B| band
    check fails on NaN: STATUS_IMPLAUSIBLE) and select finds no valid sensor."""
    return np.full(n_values(spec), np.nan, dtype=value_dtype(spec).newbyteorder("="))


def prepared_values(spec: ChainSpec, values) -> np.ndarray:
    """`<unit>_table_prepared_t` of flat coefficient values (layout order), as flat values
    in struct order: per sensor its table coefficients, its kernel's prepared vector
    (chain.prepare_sensor, the bits `<unit>_table_prepare` computes) and, for a SET/RESET
    sensor, the SET-only kernel's."""
    dt = value_dtype(spec).newbyteorder("=")
    vals = np.asarray(values).astype(dt, copy=False)
    sizes = [spec.n_sensor_coeffs(s) for s in spec.unit.sensors]
    unit_vals = vals[sum(sizes):]
    parts, k = [], 0
    for s, n in zip(spec.unit.sensors, sizes):
        mine = vals[k:k + n]
        parts.append(mine)
        for set_only in ((False, True) if s.set_reset else (False,)):
            parts.append(prepare_sensor(spec, s, mine, unit_vals, set_only).astype(dt))
        k += n
    return np.concatenate(parts)


def poisoned_prepared(spec: ChainSpec) -> np.ndarray:
    """The all-NaN `<unit>_table_prepared_t` (flat) that the flight manager hands out when
    init never completed on it, and puts in use when the defaults fail at init."""
    return np.full(n_prepared_values(spec), np.nan, dtype=value_dtype(spec).newbyteorder("="))


def init_status(spec: ChainSpec, default_values) -> tuple:
    """(status, bad value index or None) of `<unit>_table_init` on these defaults:
    CONTENT_CHECKS (no header)."""
    try:
        check_values(np.asarray(default_values).astype(value_dtype(spec), copy=False), spec)
    except TableError as e:
        return e.status, e.bad_value_index
    return TableStatus.OK, None


class TableManager(Reassembler):
    """The whole flight table manager in Python (`<unit>_table_init/load/receive_part/
    commit/abort`): the reassembly, the table checks, the serial rule and the fallback
    of init, with the same codes in the same order; the differential tests run it
    beside the flight C.

    TableManager(spec, defaults) is a manager after `<unit>_table_init(mgr, defaults)`;
    TableManager(spec) one that init never completed on: load, receive_part and commit
    return NOT_INITIALISED and change nothing, abort does nothing, and what
    `<unit>_table_info` reports (coeffs_valid, active_serial, last_status, last_bad) and
    `_table_active` / `_table_prepared` hand out (active_values, prepared) is NaN and
    NOT_INITIALISED, until init(defaults)."""

    def __init__(self, spec, default_values=None):
        self.initialised = False
        super().__init__(spec)          # its abort() does nothing yet: not initialised
        Reassembler.abort(self)         # the empty transfer state
        self.init_status, self.init_bad = TableStatus.NOT_INITIALISED, None
        self.coeffs_valid = False
        self.active_values = poisoned_values(self.spec)
        self.active_serial = 0
        self.last_status = TableStatus.NOT_INITIALISED
        self.last_bad = NO_INDEX
        if default_values is not None:
            self.init(default_values)

    def init(self, default_values) -> TableStatus:
        """`<unit>_table_init(mgr, defaults)`: everything cleared, the defaults checked,
        then (last) the manager marked initialised, in the OK and the fallback case."""
        Reassembler.abort(self)
        self.staging[:] = bytes(len(self.staging))
        vals = np.asarray(default_values).astype(value_dtype(self.spec).newbyteorder("="))
        self.init_status, self.init_bad = init_status(self.spec, vals)
        self.coeffs_valid = self.init_status == TableStatus.OK
        self.active_values = vals if self.coeffs_valid else poisoned_values(self.spec)
        self.active_serial = 0
        self.last_status = self.init_status
        self.last_bad = NO_INDEX if self.init_bad is None else self.init_bad
        self.initialised = True
        return self.init_status

    @property
    def prepared(self) -> np.ndarray:
        """What `<unit>_table_prepared(mgr)` hands out, flat in struct order: the prepared
        active coefficients, or the all-NaN set (not initialised; the init fallback)."""
        if not self.coeffs_valid:
            return poisoned_prepared(self.spec)
        return prepared_values(self.spec, self.active_values)

    def abort(self):
        """`<unit>_table_abort`: drop the transfer in progress (nothing when not
        initialised)."""
        if self.initialised:
            super().abort()

    def _accept(self, table, parts_serial=None) -> TableStatus:
        """Checks, the parts' serial (commit), the serial rule, the switch; sets
        last_status and last_bad as the flight manager does."""
        try:
            h, values = check_table(table, self.spec)
        except TableError as e:
            self.last_status = e.status
            self.last_bad = NO_INDEX if e.bad_value_index is None else e.bad_value_index
            return e.status
        self.last_bad = NO_INDEX
        if parts_serial is not None and h["table_serial"] != parts_serial:
            st = TableStatus.SERIAL_MISMATCH
        else:
            st = serial_status(self.active_serial, self.active_values, h["table_serial"],
                               values)
        if st == TableStatus.OK:
            self.active_serial = h["table_serial"]
            self.active_values = values.astype(values.dtype.newbyteorder("="))
            self.coeffs_valid = True
        self.last_status = st
        return st

    def receive_part(self, part) -> TableStatus:
        """`<unit>_table_receive_part` (Reassembler.receive under the flight API's name)."""
        if not self.initialised:
            return TableStatus.NOT_INITIALISED
        return self.receive(part)

    def load(self, table) -> TableStatus:
        if not self.initialised:
            return TableStatus.NOT_INITIALISED
        return self._accept(bytes(table))

    def commit(self) -> tuple:
        S = TableStatus
        if not self.initialised:
            return S.NOT_INITIALISED, None
        if not self.open:
            return S.NOTHING_STAGED, None
        if len(self.seen) != self.count:
            return S.PARTS_MISSING, None
        self.open = False
        table = bytes(self.staging)
        st = self._accept(table, self.serial)
        return st, (table if st == S.OK else None)
