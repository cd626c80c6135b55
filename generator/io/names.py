"""Names that reach the generated C: checked where they enter (unit file, coefficients.json).

A unit id or sensor name becomes part of C identifiers (`<unit>_<sensor>_correct`,
`<UNIT>_<SENSOR>_N_COEFFS`, a member `<sensor>` of `<unit>_coeffs_t`) and of output CSV
columns (`<sensor>_x_nT`). A coil or channel name is a telemetry column (`coil_x_A`,
`heater_A`) and becomes a macro `<UNIT>_CHANNEL_<NAME>` and a comment. So:

* unit and sensor names: NAME_PATTERN, at most MAX_NAME_CHARS characters, not a C keyword
  (C99 and C11), not a name the generated API reserves (RESERVED_WORDS exactly, and the
  families RESERVED_FAMILIES with anything after an underscore), and no two sensors whose
  identifiers could collide after prefixing (one name a prefix of another at an '_');
* coil and channel names: COLUMN_PATTERN (a C identifier, upper case allowed because
  column names carry units), at most MAX_COLUMN_CHARS, unique after upper-casing.

docs/names.md lists the reserved names; host_tests/test_hardening.py scans templates/ and
fails when the generated API grows a name that these rules do not reserve.
"""

from __future__ import annotations

import re

NAME_PATTERN = "[a-z][a-z0-9_]*"
COLUMN_PATTERN = "[A-Za-z][A-Za-z0-9_]*"
_NAME_RE = re.compile(NAME_PATTERN)
_COLUMN_RE = re.compile(COLUMN_PATTERN)

# C99 guarantees 31 significant initial characters of an external identifier (5.2.4.1);
# `<unit>_<sensor>_set_kernel` must stay readable and unique, so each part is kept short.
MAX_NAME_CHARS = 24
MAX_COLUMN_CHARS = 48

C_KEYWORDS = frozenset("""
auto break case char const continue default do double else enum extern float for goto if
inline int long register restrict return short signed sizeof static struct switch typedef
union unsigned void volatile while _Bool _Complex _Imaginary
_Alignas _Alignof _Atomic _Generic _Noreturn _Static_assert _Thread_local
""".split())

# Names a generated header or program would also define (stdbool, stddef, stdint macros
# that are spelled in lower case, and the CasADi runtime's own prefix).
C_LIBRARY_NAMES = frozenset("""
bool true false casadi errno math_errhandling assert offsetof static_assert alignas alignof
noreturn complex imaginary isfinite isnan isinf isnormal fpclassify signbit isgreater
isgreaterequal isless islessequal islessgreater isunordered setjmp va_start va_arg va_end
va_copy unix linux i386 stdin stdout stderr
""".split())

# Identifiers of the generated API after the `<unit>_` / `<UNIT>_` prefix (templates/*.j2).
# A sensor name equal to one of them, or to its beginning up to an '_', would produce the
# same identifier (sensor `table_off` -> <UNIT>_TABLE_OFF_N_COEFFS next to the table macros).
RESERVED_WORDS = frozenset("""
agree_kernel aux_t coeffs_default coeffs_t fallback_order kernels layout_hash magcal
magcal_h n_coils n_sensors real_t selection_t sel
""".split())
# Families: the API builds names `<UNIT>_<family>_<anything>` (status bits, select reasons,
# sensor indices, channel macros, unit-wide blocks, the table API and its constants, the
# part (chunk) protocol); every sensor name `<family>` or `<family>_...` is reserved.
RESERVED_FAMILIES = frozenset("table status select sensor channel unit part casadi".split())
# `sel` above: the apply output's selected vector (sel_x_nT ...) would get a second column.


# Column prefixes the ICD gives a meaning (ref_x_nT, coil_x_A, rate_x_dps, time_s, lat_deg,
# ecef_x_km, kp_index): a sensor of that name would write or read its columns (apply writes
# <s>_x_nT: a sensor `ref` would write ref_x_nT, the reference field's column).
ICD_PREFIXES = frozenset("ref coil rate time position lat lon alt ecef kp".split())


def reserved_reason(name: str) -> str | None:
    """Why `name` cannot be a unit or sensor name, or None."""
    if name.split("_", 1)[0] in ICD_PREFIXES:
        return (f"starts with '{name.split('_', 1)[0]}', a column prefix of the ICD "
                "(ref_x_nT, coil_x_A, rate_x_dps, ...): its columns would collide")
    if name in C_KEYWORDS:
        return "is a C keyword"
    if name in C_LIBRARY_NAMES:
        return "is a name the C library or the generated code's runtime defines"
    if name in RESERVED_WORDS:
        return "is reserved by the generated API (docs/names.md)"
    for w in RESERVED_WORDS:
        if w.startswith(name + "_"):
            return f"collides with the generated API name '<unit>_{w}' (docs/names.md)"
    first = name.split("_", 1)[0]
    if first in RESERVED_FAMILIES:
        return (f"starts a family the generated API reserves ('{first}_...', "
                "docs/names.md)")
    return None


def name_fault(name, kind: str = "sensor") -> str | None:
    """Fault of a sensor name (kind "sensor") or unit id (kind "unit"), or None when it
    is usable. A unit id prefixes every identifier, so only keywords and the library's
    names are reserved for it; a sensor name follows the prefix, so the API's are too."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        return f"{_short(name)} does not match {NAME_PATTERN}"
    if len(name) > MAX_NAME_CHARS:
        return f"{_short(name)} is longer than {MAX_NAME_CHARS} characters"
    if kind == "unit":
        why = ("is a C keyword" if name in C_KEYWORDS else
               "is a name the C library or the generated code's runtime defines"
               if name in C_LIBRARY_NAMES else None)
    else:
        why = reserved_reason(name)
    if why:
        return f"'{name}' {why}"
    return None


def column_fault(name) -> str | None:
    """Fault of a coil or channel column name that the chain would use, or None."""
    if not isinstance(name, str):
        return f"{name!r} is not a string"
    if not _COLUMN_RE.fullmatch(name):
        return f"{_short(name)} is not a C identifier ({COLUMN_PATTERN})"
    if len(name) > MAX_COLUMN_CHARS:
        return f"{_short(name)} is longer than {MAX_COLUMN_CHARS} characters"
    return None


def prefix_collision(names) -> tuple | None:
    """(a, b) when sensor b starts with a + '_' (their C identifiers could collide:
    sensor `a`'s `<unit>_a_set_raw_t` is sensor `a_set`'s `<unit>_a_set_raw_t`), or None."""
    names = list(names)
    for a in names:
        for b in names:
            if a != b and b.startswith(a + "_"):
                return a, b
    return None


def macro_collision(columns) -> tuple | None:
    """(a, b) when two column names give the same macro after upper-casing, or None."""
    seen = {}
    for c in columns:
        m = c.upper()
        if m in seen and seen[m] != c:
            return seen[m], c
        seen[m] = c
    return None


def _short(text: str, limit: int = 40) -> str:
    """repr of a name for a one-line message (long or hostile text cut)."""
    r = repr(text)
    return r if len(r) <= limit else r[:limit] + "...'"
