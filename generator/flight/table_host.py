"""The flight table code on the host: its sources, compiled through cffi, and its fuzz driver.

HOST ONLY (not flight code): `TableHost` builds the unit's generated table code (the same
sources the flight build takes) with a copy-out and batch helper, so the tests push large
numbers of inputs through the flight validator; the sanitizer driver reuses it.
"""

from __future__ import annotations

import struct

import numpy as np

from generator.flight import host
from generator.flight.chain import np_dtype
from generator.flight.codegen import TABLE_TEMPLATES, _env, render, template_context
from generator.flight.coeffs import CoefficientSet
from generator.flight.tables import TableStatus, n_values, table_context


def flight_sources(cs: CoefficientSet) -> dict:
    """{file name: text}: codegen.render(cs) plus the table files, rendered with the
    table context whether or not codegen renders them itself already."""
    files = render(cs)
    ctx = _table_ctx(cs)
    env = _env()
    for tpl, pattern in TABLE_TEMPLATES:
        name = pattern.format(unit=cs.unit.id)
        if name not in files:
            files[name] = env.get_template(tpl).render(**ctx)
    return dict(sorted(files.items()))



# ---- host build: the flight table code through cffi --------------------------------------

# TEST CODE (not flight code): copy-out and a batch loop over the flight table API, so the
# tests push large numbers of inputs through it quickly; the sanitizer driver uses it too,
# and the Cortex-M4F table runner (arm_tables) links table_host.c for its corrections on
# the manager's prepared set.
HOST_CDEF = """\
typedef enum {
{% for e in table.errors %}
    {{ UNIT }}_TABLE_{{ e.name }} = {{ e.value }},
{% endfor %}
    {{ UNIT }}_TABLE_N_STATUS = {{ table.errors | length }}
} {{ unit }}_table_status_t;
typedef struct {
    uint32_t active_serial;
    uint8_t active_buffer;
    uint8_t transfer_open;
    uint16_t parts_received;
    uint16_t part_count;
    uint32_t transfer_serial;
    {{ unit }}_table_status_t last_status;
    uint32_t last_bad_value;
    uint8_t coeffs_valid;
} {{ unit }}_table_info_t;
typedef struct { uint32_t init_mark; ...; } {{ unit }}_table_mgr_t;
typedef struct { ...; } {{ unit }}_coeffs_t;
typedef struct { ...; } {{ unit }}_table_prepared_t;
extern const uint8_t {{ unit }}_table_default[{{ table.table_bytes }}];
uint32_t {{ unit }}_table_crc32(const uint8_t *buf, uint32_t len);
{{ unit }}_table_status_t {{ unit }}_table_validate(const uint8_t *buf, uint32_t len);
{{ unit }}_table_status_t {{ unit }}_table_validate_detail(const uint8_t *buf, uint32_t len, uint32_t *bad_value_index);
const char *{{ unit }}_table_strerror(int status);
{{ unit }}_table_status_t {{ unit }}_table_init({{ unit }}_table_mgr_t *mgr, const {{ unit }}_coeffs_t *defaults);
{{ unit }}_table_status_t {{ unit }}_table_receive_part({{ unit }}_table_mgr_t *mgr, const uint8_t *part, uint32_t len);
{{ unit }}_table_status_t {{ unit }}_table_commit({{ unit }}_table_mgr_t *mgr);
{{ unit }}_table_status_t {{ unit }}_table_load({{ unit }}_table_mgr_t *mgr, const uint8_t *table, uint32_t len);
void {{ unit }}_table_abort({{ unit }}_table_mgr_t *mgr);
const {{ unit }}_coeffs_t *{{ unit }}_table_active(const {{ unit }}_table_mgr_t *mgr);
const {{ unit }}_table_prepared_t *{{ unit }}_table_prepared(const {{ unit }}_table_mgr_t *mgr);
void {{ unit }}_table_info(const {{ unit }}_table_mgr_t *mgr, {{ unit }}_table_info_t *info);
const {{ unit }}_coeffs_t *host_table_defaults(void);
void host_table_flat(const {{ unit }}_coeffs_t *co, {{ real }} *flat);
long host_table_prepared_size(void);
void host_table_prepared_flat(const {{ unit }}_table_mgr_t *mgr, {{ real }} *flat);
long host_table_fuzz({{ unit }}_table_mgr_t *mgr, const uint8_t *blob, const uint32_t *offsets, const uint32_t *lens, const uint8_t *actions, long n, int32_t *codes);
void host_table_correct_all(const {{ unit }}_table_mgr_t *mgr, const double *raw, const double *temp_C, {{ real }} *field, uint16_t *status);
void host_table_select(const {{ unit }}_table_mgr_t *mgr, const {{ real }} *field, uint16_t *status, {{ real }} *sel_field, int8_t *sel_sensor, uint8_t *sel_reason);
"""

HOST_HELPER_H = """\
/* TEST CODE (host, and the target table runner): helpers around the flight table code
 * of {{ unit }}. */
#include <stdint.h>
#include "{{ unit }}_magcal.h"
#include "{{ unit }}_table.h"

const {{ unit }}_coeffs_t *host_table_defaults(void);
void host_table_flat(const {{ unit }}_coeffs_t *co, {{ unit }}_real_t *flat);
long host_table_prepared_size(void);
void host_table_prepared_flat(const {{ unit }}_table_mgr_t *mgr, {{ unit }}_real_t *flat);
#define HOST_ABORT_BEFORE 1u   /* actions: {{ unit }}_table_abort before the input */
#define HOST_COMMIT_AFTER 2u   /* actions: {{ unit }}_table_commit after the input */
long host_table_fuzz({{ unit }}_table_mgr_t *mgr, const uint8_t *blob, const uint32_t *offsets,
    const uint32_t *lens, const uint8_t *actions, long n, int32_t *codes);
void host_table_correct_all(const {{ unit }}_table_mgr_t *mgr, const double *raw,
    const double *temp_C, {{ unit }}_real_t *field, uint16_t *status);
void host_table_select(const {{ unit }}_table_mgr_t *mgr, const {{ unit }}_real_t *field,
    uint16_t *status, {{ unit }}_real_t *sel_field, int8_t *sel_sensor, uint8_t *sel_reason);
"""

HOST_HELPER_C = """\
/* TEST CODE (not flight code): helpers for the tests of {{ unit }}_table.c, built on the
 * host (cffi) and into the Cortex-M4F table runner. */
#include <string.h>
#include "table_host.h"

const {{ unit }}_coeffs_t *host_table_defaults(void)
{
    return &{{ unit }}_coeffs_default;
}

long host_table_prepared_size(void)
{
    return (long)(sizeof({{ unit }}_table_prepared_t) / sizeof({{ unit }}_real_t));
}

/* The prepared coefficients in use, as flat values (reals only: no padding). */
void host_table_prepared_flat(const {{ unit }}_table_mgr_t *mgr, {{ unit }}_real_t *flat)
{
    memcpy(flat, {{ unit }}_table_prepared(mgr), sizeof({{ unit }}_table_prepared_t));
}

void host_table_flat(const {{ unit }}_coeffs_t *co, {{ unit }}_real_t *flat)
{
    size_t k = 0;
{% for s in sensors %}
    memcpy(flat + k, co->{{ s.name }}, sizeof co->{{ s.name }});
    k += {{ UNIT }}_{{ s.NAME }}_N_COEFFS;
{% endfor %}
{% if n_unit_coeffs %}
    memcpy(flat + k, co->unit, sizeof co->unit);
{% else %}
    (void)k;
{% endif %}
}

/* One sample of every sensor through its {{ unit }}_<sensor>_correct on the prepared set
 * the manager hands out ({{ unit }}_table_prepared(mgr); aux NULL, state NULL), as flight
 * software calls it. raw[8 k ..]: sensor k's readings (3; SET then RESET: 6), temp_C[k];
 * out: field[3 k ..], status[k]. */
void host_table_correct_all(const {{ unit }}_table_mgr_t *mgr, const double *raw,
    const double *temp_C, {{ unit }}_real_t *field, uint16_t *status)
{
    const {{ unit }}_table_prepared_t *co = {{ unit }}_table_prepared(mgr);
    int i;
{% for s in sensors %}
{% set rt = (unit ~ "_real_t") if s.physical else "int32_t" %}
    {
        {{ unit }}_{{ s.name }}_raw_t in;
        {{ unit }}_{{ s.name }}_out_t out;
        memset(&in, 0, sizeof in);
        for (i = 0; i < 3; ++i) {
{% if s.set_reset %}
            in.{{ s.raw_fields.set }}[i] = ({{ rt }})raw[8 * {{ s.index }} + i];
            in.{{ s.raw_fields.reset }}[i] = ({{ rt }})raw[8 * {{ s.index }} + 3 + i];
{% else %}
            in.{{ s.raw_fields.plain }}[i] = ({{ rt }})raw[8 * {{ s.index }} + i];
{% endif %}
        }
        in.temp_C = ({{ unit }}_real_t)temp_C[{{ s.index }}];
        status[{{ s.index }}] = {{ unit }}_{{ s.name }}_correct(co, &in,
            {%- if has_aux %} 0,{% endif %}{% if s.has_state %} 0,{% endif %} &out);
        memcpy(field + 3 * {{ s.index }}, out.field_body_nT, sizeof out.field_body_nT);
    }
{% endfor %}
}

/* {{ unit }}_select on the prepared set the manager hands out: field[3 k ..] and status[k]
 * of sensor k (status updated in place, as select does), the selection's field, sensor
 * and reason. */
void host_table_select(const {{ unit }}_table_mgr_t *mgr, const {{ unit }}_real_t *field,
    uint16_t *status, {{ unit }}_real_t *sel_field, int8_t *sel_sensor, uint8_t *sel_reason)
{
    {{ unit }}_real_t fields[{{ UNIT }}_N_SENSORS][3];
    {{ unit }}_selection_t sel;
    memcpy(fields, field, sizeof fields);
    (void){{ unit }}_select({{ unit }}_table_prepared(mgr),
                            (const {{ unit }}_real_t (*)[3])fields, status, &sel);
    memcpy(sel_field, sel.field_body_nT, sizeof sel.field_body_nT);
    *sel_sensor = sel.sensor;
    *sel_reason = sel.reason;
}

/* Each input goes through validate_detail, load and receive_part, with an abort before it
 * and a commit after it as actions[i] says. codes[4 i ..]: validate, load, receive,
 * commit (-1: not run). Returns the number of switches to a new table, or -(i + 1) when
 * input i broke an invariant: the active table changed without an accepted load or
 * commit, load and validate disagreed (load may only add the serial rule to a table
 * validate accepts), or a code is not a status code. */
long host_table_fuzz({{ unit }}_table_mgr_t *mgr, const uint8_t *blob, const uint32_t *offsets,
    const uint32_t *lens, const uint8_t *actions, long n, int32_t *codes)
{
    {{ unit }}_coeffs_t before;
    {{ unit }}_table_prepared_t prepared_before;
    {{ unit }}_table_info_t info;
    uint32_t serial_before;
    const int32_t n_status = (int32_t){{ UNIT }}_TABLE_N_STATUS;
    long i, switches = 0;
    for (i = 0; i < n; ++i) {
        const uint8_t *in = blob + offsets[i];
        uint32_t bad = 0u;
        int32_t v, l, r, c = -1;
        memcpy(&before, {{ unit }}_table_active(mgr), sizeof before);
        memcpy(&prepared_before, {{ unit }}_table_prepared(mgr), sizeof prepared_before);
        {{ unit }}_table_info(mgr, &info);
        serial_before = info.active_serial;
        if ((actions[i] & HOST_ABORT_BEFORE) != 0u) {
            {{ unit }}_table_abort(mgr);
        }
        v = (int32_t){{ unit }}_table_validate_detail(in, lens[i], &bad);
        l = (int32_t){{ unit }}_table_load(mgr, in, lens[i]);
        r = (int32_t){{ unit }}_table_receive_part(mgr, in, lens[i]);
        if ((actions[i] & HOST_COMMIT_AFTER) != 0u) {
            c = (int32_t){{ unit }}_table_commit(mgr);
        }
        codes[4 * i] = v;
        codes[4 * i + 1] = l;
        codes[4 * i + 2] = r;
        codes[4 * i + 3] = c;
        if ((v != l && !(v == 0 && (l == (int32_t){{ UNIT }}_TABLE_SERIAL_ROLLBACK ||
                                    l == (int32_t){{ UNIT }}_TABLE_SERIAL_REPLAY ||
                                    l == (int32_t){{ UNIT }}_TABLE_ALREADY_ACTIVE))) ||
            v < 0 || v >= n_status || r < 0 || r >= n_status || c < -1 || c >= n_status) {
            return -(i + 1);
        }
        switches += (l == 0) + (c == 0);
        if (l != 0 && c != 0) {
            {{ unit }}_table_info(mgr, &info);
            if (memcmp(&before, {{ unit }}_table_active(mgr), sizeof before) != 0 ||
                memcmp(&prepared_before, {{ unit }}_table_prepared(mgr),
                       sizeof prepared_before) != 0 ||
                info.active_serial != serial_before) {
                return -(i + 1);
            }
        }
    }
    return switches;
}
"""

# Standalone driver for the sanitizer build: every input of a file, each in its own
# exact-size heap block (so a read past its end is caught), through host_table_fuzz;
# prints "column code count" lines (columns: validate, load, receive, commit).
# File: u32 n, then n times (u32 length, u8 actions, bytes); all little-endian.
SANITIZER_DRIVER_C = """\
/* HOST ONLY: sanitizer driver for {{ unit }}_table.c (see generator/flight/tables.py). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "table_host.h"

static uint32_t rd32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static {{ unit }}_table_mgr_t mgr;
static long hist[4][{{ table.errors | length }} + 1];

int main(int argc, char **argv)
{
    FILE *f;
    long size, i, n, switches = 0, one;
    uint8_t *data;
    uint32_t pos, len, zero = 0u;
    uint8_t action;
    int32_t codes[4];
    int col, k;
    if (argc != 2 || (f = fopen(argv[1], "rb")) == NULL) {
        fprintf(stderr, "usage: %s INPUTS.bin\\n", argv[0]);
        return 2;
    }
    fseek(f, 0, SEEK_END);
    size = ftell(f);
    fseek(f, 0, SEEK_SET);
    data = (uint8_t *)malloc((size_t)size + 1u);
    if (data == NULL || size < 4 || fread(data, 1, (size_t)size, f) != (size_t)size) {
        fprintf(stderr, "cannot read %s\\n", argv[1]);
        return 2;
    }
    fclose(f);
    n = (long)rd32(data);
    if ({{ unit }}_table_init(&mgr, &{{ unit }}_coeffs_default) != {{ UNIT }}_TABLE_OK) {
        return 1;
    }
    pos = 4u;
    for (i = 0; i < n; ++i) {
        uint8_t *copy;
        if ((long)pos + 5 > size) {
            fprintf(stderr, "truncated input file\\n");
            return 2;
        }
        len = rd32(data + pos);
        action = data[pos + 4u];
        pos += 5u;
        if ((long)pos + (long)len > size) {
            fprintf(stderr, "truncated input file\\n");
            return 2;
        }
        copy = (uint8_t *)malloc(len > 0u ? len : 1u);
        if (copy == NULL) {
            return 2;
        }
        memcpy(copy, data + pos, len);
        pos += len;
        one = host_table_fuzz(&mgr, copy, &zero, &len, &action, 1, codes);
        free(copy);
        if (one < 0) {
            printf("invariant broken at input %ld\\n", i);
            return 1;
        }
        switches += one;
        for (col = 0; col < 4; ++col) {
            hist[col][codes[col] + 1] += 1;
        }
    }
    for (col = 0; col < 4; ++col) {
        for (k = 0; k <= {{ table.errors | length }}; ++k) {
            if (hist[col][k] != 0) {
                printf("%d %d %ld\\n", col, k - 1, hist[col][k]);
            }
        }
    }
    printf("inputs %ld switches %ld\\n", n, switches);
    free(data);
    return 0;
}
"""


def _table_ctx(cs: CoefficientSet) -> dict:
    ctx = template_context(cs)
    ctx.setdefault("table", table_context(cs))
    return ctx


def host_sources(cs: CoefficientSet) -> dict:
    """What the table code needs: the unit's flight sources (the manager prepares a table
    when it activates it: `<unit>_table_prepare` in magcal.c and its CasADi kernels), the
    table files, and the host helper table_host.c/.h; plus the cffi cdef as
    "table_host.cdef"."""
    ctx = _table_ctx(cs)
    env = _env()
    unit = cs.unit.id
    files = render(cs, tables=False)
    for tpl, pattern in TABLE_TEMPLATES:
        files[pattern.format(unit=unit)] = env.get_template(tpl).render(**ctx)
    files["table_host.h"] = env.from_string(HOST_HELPER_H).render(**ctx)
    files["table_host.c"] = env.from_string(HOST_HELPER_C).render(**ctx)
    files["table_host.cdef"] = env.from_string(HOST_CDEF).render(**ctx)
    return files


def sanitizer_driver(cs: CoefficientSet) -> str:
    return _env().from_string(SANITIZER_DRIVER_C).render(**_table_ctx(cs))


FUZZ_ABORT_BEFORE = 1   # host_table_fuzz actions
FUZZ_COMMIT_AFTER = 2


def fuzz_actions(n: int, commit_every: int = 0) -> np.ndarray:
    """Actions with a commit after every commit_every-th input (0: none)."""
    actions = np.zeros(n, dtype=np.uint8)
    if commit_every:
        actions[commit_every - 1::commit_every] = FUZZ_COMMIT_AFTER
    return actions


def write_fuzz_file(path, inputs, actions) -> None:
    """Inputs for the sanitizer driver (format: see SANITIZER_DRIVER_C)."""
    with open(path, "wb") as f:
        f.write(struct.pack("<I", len(inputs)))
        for x, a in zip(inputs, actions):
            f.write(struct.pack("<IB", len(x), int(a)) + bytes(x))


class TableHost:
    """The generated flight table code of one unit, compiled with cffi (as host.py builds
    the correction: -std=c99 -O2 -ffp-contract=off; -Wall -Wextra -Werror -pedantic)."""

    def __init__(self, cs: CoefficientSet):
        self.cs = cs
        self.spec = cs.spec
        self.unit = cs.unit.id
        self.dtype = np.dtype(np_dtype(cs.unit))
        files = host_sources(cs)
        self.lib, self.ffi = host.cffi_module("_magcal_table", files, "table_host.cdef",
                                              '#include "table_host.h"\n')

    def _fn(self, name):
        return getattr(self.lib, f"{self.unit}_table_{name}")

    @staticmethod
    def _buf(data):
        return bytes(data)

    def crc32(self, data) -> int:
        return int(self._fn("crc32")(self._buf(data), len(data)))

    def validate(self, data) -> TableStatus:
        return TableStatus(self._fn("validate")(self._buf(data), len(data)))

    def validate_detail(self, data) -> tuple:
        bad = self.ffi.new("uint32_t *")
        st = self._fn("validate_detail")(self._buf(data), len(data), bad)
        return TableStatus(st), int(bad[0])

    def strerror(self, status) -> str:
        return self.ffi.string(self._fn("strerror")(int(status))).decode()

    def manager(self, defaults=None):
        """A new table manager initialised with the compiled-in default coefficients
        (which must pass init's checks: see init for a manager whose defaults fail)."""
        mgr, st = self.init(defaults)
        assert st == TableStatus.OK, st
        return mgr

    def init(self, defaults=None, mgr=None) -> tuple:
        """(manager, status of <unit>_table_init): defaults None: the compiled-in
        <unit>_coeffs_default; else a pointer to a <unit>_coeffs_t, or flat values in
        layout order (put into a struct first). mgr: init this manager (else a new one)."""
        if mgr is None:
            mgr = self.ffi.new(f"{self.unit}_table_mgr_t *")
        if defaults is None:
            defaults = self.lib.host_table_defaults()
        elif isinstance(defaults, np.ndarray):
            flat = np.ascontiguousarray(defaults, dtype=self.dtype)
            assert flat.size == n_values(self.spec)
            co = self.ffi.new(f"{self.unit}_coeffs_t *")
            self.ffi.memmove(co, flat.tobytes(), flat.nbytes)   # no padding (table.c checks)
            defaults = co
        st = TableStatus(self._fn("init")(mgr, defaults))
        return mgr, st

    def uninitialised(self, fill: int = 0):
        """A manager that `<unit>_table_init` never ran on: every byte `fill` (0: static
        storage; 0xFF: erased memory)."""
        mgr = self.ffi.new(f"{self.unit}_table_mgr_t *")
        n = self.ffi.sizeof(f"{self.unit}_table_mgr_t")
        self.ffi.memmove(mgr, bytes([fill]) * n, n)
        return mgr

    def correct_all(self, mgr, raw, temp_C) -> dict:
        """One sample of every sensor through its correction on `<unit>_table_prepared(mgr)`
        (host_table_correct_all), then select on the same set (select): raw (S, 3 or 6)
        readings, temp_C (S,)."""
        sensors = self.spec.unit.sensors
        r = np.zeros((len(sensors), 8))
        for k, s in enumerate(sensors):
            v = np.asarray(raw[k], dtype=np.float64)
            assert v.shape == ((6,) if s.set_reset else (3,)), (s.name, v.shape)
            r[k, :v.size] = v
        t = np.ascontiguousarray(temp_C, dtype=np.float64)
        assert t.shape == (len(sensors),)
        field = np.zeros((len(sensors), 3), dtype=self.dtype)
        status = np.zeros(len(sensors), dtype=np.uint16)
        ct = "float" if self.dtype == np.float32 else "double"
        ffi = self.ffi
        self.lib.host_table_correct_all(
            mgr, ffi.cast("double *", r.ctypes.data), ffi.cast("double *", t.ctypes.data),
            ffi.cast(f"{ct} *", field.ctypes.data), ffi.cast("uint16_t *", status.ctypes.data))
        out = {"field_body_nT": field, "status": status.copy()}
        out.update(self.select(mgr, field, status))
        return out

    def select(self, mgr, field, status) -> dict:
        """`<unit>_select` on `<unit>_table_prepared(mgr)`: field (S, 3), status (S,) of one
        cycle. Returns the statuses after select (DISAGREE bits) and the selection."""
        f = np.ascontiguousarray(field, dtype=self.dtype)
        st = np.array(status, dtype=np.uint16)
        assert f.shape == (len(self.spec.unit.sensors), 3) and st.shape == (f.shape[0],)
        sel_field = np.zeros(3, dtype=self.dtype)
        sel_sensor = self.ffi.new("int8_t *")
        sel_reason = self.ffi.new("uint8_t *")
        ct = "float" if self.dtype == np.float32 else "double"
        ffi = self.ffi
        self.lib.host_table_select(
            mgr, ffi.cast(f"{ct} *", f.ctypes.data), ffi.cast("uint16_t *", st.ctypes.data),
            ffi.cast(f"{ct} *", sel_field.ctypes.data), sel_sensor, sel_reason)
        return {"sel_status": st, "sel_field_body_nT": sel_field,
                "sel_sensor": int(sel_sensor[0]), "sel_reason": int(sel_reason[0])}

    def receive_part(self, mgr, part) -> TableStatus:
        return TableStatus(self._fn("receive_part")(mgr, self._buf(part), len(part)))

    def commit(self, mgr) -> TableStatus:
        return TableStatus(self._fn("commit")(mgr))

    def load(self, mgr, table) -> TableStatus:
        return TableStatus(self._fn("load")(mgr, self._buf(table), len(table)))

    def abort(self, mgr) -> None:
        self._fn("abort")(mgr)

    def info(self, mgr) -> dict:
        out = self.ffi.new(f"{self.unit}_table_info_t *")
        self._fn("info")(mgr, out)
        return {k: (TableStatus(getattr(out, k)) if k == "last_status" else
                    int(getattr(out, k)))
                for k in ("active_serial", "active_buffer", "transfer_open", "parts_received",
                          "part_count", "transfer_serial", "last_status", "last_bad_value",
                          "coeffs_valid")}

    def _flat(self, co_ptr) -> np.ndarray:
        out = np.zeros(n_values(self.spec), dtype=self.dtype)
        ct = "float" if self.dtype == np.float32 else "double"
        self.lib.host_table_flat(co_ptr, self.ffi.cast(f"{ct} *", out.ctypes.data))
        return out

    def active_flat(self, mgr) -> np.ndarray:
        """The active coefficients, flat in layout order (HostUnit.correct's coeffs_flat)."""
        return self._flat(self._fn("active")(mgr))

    def prepared_flat(self, mgr) -> np.ndarray:
        """The prepared coefficients in use (`<unit>_table_prepared`), flat in struct order."""
        out = np.zeros(int(self.lib.host_table_prepared_size()), dtype=self.dtype)
        ct = "float" if self.dtype == np.float32 else "double"
        self.lib.host_table_prepared_flat(mgr, self.ffi.cast(f"{ct} *", out.ctypes.data))
        return out

    def default_flat(self) -> np.ndarray:
        return self._flat(self.lib.host_table_defaults())

    def default_table(self) -> bytes:
        return bytes(self.ffi.buffer(getattr(self.lib, f"{self.unit}_table_default")))

    def fuzz(self, mgr, inputs, actions=0) -> tuple:
        """(result of host_table_fuzz, codes (n, 4) int32): see HOST_HELPER_C. actions:
        per input (FUZZ_ABORT_BEFORE | FUZZ_COMMIT_AFTER), or an int: commit after every
        that many inputs (0: never)."""
        if isinstance(actions, (int, np.integer)):
            actions = fuzz_actions(len(inputs), int(actions))
        acts = np.ascontiguousarray(actions, dtype=np.uint8)
        assert acts.shape == (len(inputs),)
        lens = np.array([len(x) for x in inputs], dtype=np.uint32)
        offsets = np.zeros(len(inputs), dtype=np.uint32)
        if len(inputs) > 1:
            offsets[1:] = np.cumsum(lens[:-1], dtype=np.uint64).astype(np.uint32)
        blob = np.frombuffer(b"".join(bytes(x) for x in inputs) + b"\0", dtype=np.uint8)
        codes = np.zeros((len(inputs), 4), dtype=np.int32)
        ffi = self.ffi
        res = self.lib.host_table_fuzz(
            mgr, ffi.cast("uint8_t *", blob.ctypes.data),
            ffi.cast("uint32_t *", offsets.ctypes.data), ffi.cast("uint32_t *", lens.ctypes.data),
            ffi.cast("uint8_t *", acts.ctypes.data), len(inputs),
            ffi.cast("int32_t *", codes.ctypes.data))
        return int(res), codes
