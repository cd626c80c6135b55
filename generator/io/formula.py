"""User-declared regressors of the unit file: a formula over telemetry channels.

    [[trace.regressor]]
    name = "heater_w"
    formula = "v_heater * i_heater"

A formula is parsed by a small recursive-descent parser, never evaluated by Python:
numbers (``2``, ``0.5``, ``1e-3``), channel names (``[A-Za-z_][A-Za-z0-9_]*``, columns of
the telemetry), ``+ - * /``, ``**`` (right-associative, binds tighter than a unary minus:
``-x**2`` is ``-(x**2)``), unary ``+``/``-`` and parentheses. Anything else (a function
call, an attribute, a comparison, a string, ``;``, ...) is refused with the key and the
character where it stops (InputError: exit 2, one line).

Evaluation works on numpy columns, row by row; a row where an input is missing or the
result is not finite (a division by zero, an overflow) is missing (NaN) in the result.

Where the regressor lives in flight: it is a channel computed BEFORE the chain. The
extended coefficients name it like any telemetry channel (`channels` of the chain
options, `<UNIT>_CHANNEL_<NAME>` in the generated header); the flight software computes
it from its own inputs with the same formula and passes it in the aux struct
(docs/effects.md).
"""

from __future__ import annotations

import re

import numpy as np

from generator.errors import InputError

MAX_FORMULA_CHARS = 500      # a formula is a short expression; longer is not one
MAX_DEPTH = 40               # nesting: parentheses, unary signs and exponents in a chain
#                              (each one level; a few Python frames each: no recursion bombs)
MAX_REGRESSORS = 16

_TOKEN = re.compile(r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
                    r"|(?P<name>[A-Za-z_][A-Za-z0-9_]*)|(?P<op>\*\*|[-+*/()]))")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,62}\Z")


class FormulaError(ValueError):
    """A fault in a formula: the message and the character (1-based) where it is."""

    def __init__(self, message, pos):
        super().__init__(message)
        self.message, self.pos = message, pos


def _tokens(text):
    out, i = [], 0
    while i < len(text):
        if text[i:].strip() == "":
            break
        m = _TOKEN.match(text, i)
        if m is None or m.end() == i:
            j = i + len(text[i:]) - len(text[i:].lstrip())
            raise FormulaError(f"unexpected {text[j]!r}: only numbers, channel names, "
                               "+ - * / **, and parentheses", j + 1)
        kind = m.lastgroup
        start = m.start(kind)
        out.append((kind, m.group(kind), start + 1))
        i = m.end()
    out.append(("end", "", len(text) + 1))
    return out


def parse(text: str):
    """The formula's tree: ("num", value) | ("name", name) | ("neg", a) |
    (op, a, b) with op one of + - * / **. FormulaError on any fault."""
    if not isinstance(text, str):
        raise FormulaError("must be a string", 1)
    if len(text) > MAX_FORMULA_CHARS:
        raise FormulaError(f"longer than {MAX_FORMULA_CHARS} characters", MAX_FORMULA_CHARS)
    toks = _tokens(text)
    k = 0

    def peek():
        return toks[k]

    def take():
        nonlocal k
        k += 1
        return toks[k - 1]

    def expect_operand(depth):
        if depth > MAX_DEPTH:
            raise FormulaError(f"nested deeper than {MAX_DEPTH}", peek()[2])

    def expr(depth):
        expect_operand(depth)
        a = term(depth)
        while peek()[1] in ("+", "-") and peek()[0] == "op":
            op = take()[1]
            a = (op, a, term(depth))
        return a

    def term(depth):
        expect_operand(depth)
        a = unary(depth)
        while peek()[1] in ("*", "/") and peek()[0] == "op":
            op = take()[1]
            a = (op, a, unary(depth))
        return a

    def unary(depth):
        expect_operand(depth)
        if peek()[0] == "op" and peek()[1] in ("+", "-"):
            op = take()[1]
            a = unary(depth + 1)
            return ("neg", a) if op == "-" else a
        return power(depth)

    def power(depth):
        expect_operand(depth)
        a = atom(depth)
        if peek()[0] == "op" and peek()[1] == "**":
            take()
            return ("**", a, unary(depth + 1))
        return a

    def atom(depth):
        expect_operand(depth)
        kind, val, pos = take()
        if kind == "num":
            v = float(val)
            if not np.isfinite(v):
                raise FormulaError(f"number {val} is not finite", pos)
            return ("num", v)
        if kind == "name":
            if peek()[0] == "op" and peek()[1] == "(":
                raise FormulaError(f"'{val}(': function calls are not allowed", pos)
            return ("name", val)
        if kind == "op" and val == "(":
            a = expr(depth + 1)
            kind2, val2, pos2 = take()
            if val2 != ")":
                raise FormulaError("missing ')'", pos2)
            return a
        if kind == "end":
            raise FormulaError("ends where a number, a channel or '(' is expected", pos)
        raise FormulaError(f"unexpected {val!r} where a number, a channel or '(' is "
                           "expected", pos)

    tree = expr(0)
    if peek()[0] != "end":
        raise FormulaError(f"unexpected {peek()[1]!r} after a complete expression",
                           peek()[2])
    return tree


def names(tree) -> list:
    """The channel names a tree reads, in first-use order."""
    out = []

    def walk(t):
        if t[0] == "name":
            if t[1] not in out:
                out.append(t[1])
        elif t[0] != "num":
            for a in t[1:]:
                walk(a)
    walk(tree)
    return out


def evaluate(tree, columns: dict) -> np.ndarray:
    """The formula over columns {name: (n,) array} in float64; non-finite results NaN."""
    def ev(t):
        if t[0] == "num":
            return t[1]
        if t[0] == "name":
            return np.asarray(columns[t[1]], float)
        if t[0] == "neg":
            return -ev(t[1])
        a, b = ev(t[1]), ev(t[2])
        return {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide,
                "**": np.power}[t[0]](a, b)
    with np.errstate(all="ignore"):
        v = np.asarray(ev(tree), float)
    n = len(next(iter(columns.values()))) if columns else v.size
    v = np.broadcast_to(v, (n,)).astype(float)
    return np.where(np.isfinite(v), v, np.nan)


def text(tree) -> str:
    """The tree written back with every operation in parentheses (for reports)."""
    if tree[0] == "num":
        return repr(tree[1])
    if tree[0] == "name":
        return tree[1]
    if tree[0] == "neg":
        return f"(-{text(tree[1])})"
    return f"({text(tree[1])} {tree[0]} {text(tree[2])})"


def read_regressors(path, trace_table, line_of=None) -> list:
    """[{name, formula, inputs}] of the unit file's [[trace.regressor]] entries, checked;
    InputError naming the key on any fault. line_of(index, key): the line, if known."""
    if trace_table is None:
        return []
    where = "trace"
    if not isinstance(trace_table, dict):
        raise InputError(path, f"{where}: must be a table ([[trace.regressor]] entries)")
    regs = trace_table.get("regressor", [])
    if not isinstance(regs, list) or not all(isinstance(r, dict) for r in regs):
        raise InputError(path, "trace.regressor: must be written as [[trace.regressor]] "
                               "tables")
    if len(regs) > MAX_REGRESSORS:
        raise InputError(path, f"trace.regressor: more than {MAX_REGRESSORS} regressors")
    out, seen = [], set()
    for i, r in enumerate(regs, start=1):
        key = f"trace.regressor[{i}]"
        line = line_of(i, None) if line_of else None
        unknown = sorted(set(r) - {"name", "formula"})
        if unknown:
            raise InputError(path, f"{key}.{unknown[0]}: unknown key (name, formula)",
                             line=line)
        name = r.get("name")
        if not isinstance(name, str) or not _NAME.match(name):
            raise InputError(path, f"{key}.name: must be a channel name (letters, digits, "
                                   "_; not starting with a digit; at most 63 characters)",
                             line=line)
        from generator.io.names import ICD_PREFIXES
        if name.split("_")[0] in ICD_PREFIXES:
            raise InputError(path, f"{key}.name: '{name}' is a column name the ICD reserves "
                                   f"(prefixes {', '.join(sorted(ICD_PREFIXES))}: ref_x_nT, "
                                   "coil_x_A, rate_x_dps, time_s, ...)", line=line)
        if name in seen:
            raise InputError(path, f"{key}.name: '{name}' is declared twice", line=line)
        seen.add(name)
        f = r.get("formula")
        if f is None:
            raise InputError(path, f"{key}.formula: missing", line=line)
        try:
            tree = parse(f)
        except FormulaError as err:
            raise InputError(path, f"{key}.formula: character {err.pos}: {err.message}",
                             line=line) from None
        ins = names(tree)
        if not ins:
            raise InputError(path, f"{key}.formula: reads no channel (a constant is no "
                                   "regressor)", line=line)
        if name in ins:
            raise InputError(path, f"{key}.formula: '{name}' uses itself", line=line)
        out.append({"name": name, "formula": f, "inputs": ins, "tree": tree})
    return out


def add_regressors(regressors, tel):
    """The telemetry with each regressor as a column where the file has all its inputs
    (a new Telemetry; the given one is not changed). A file that already has a column of
    the regressor's name is bad input (which would it be?)."""
    if not regressors:
        return tel
    from generator.io.telemetry import Telemetry
    cols = dict(tel.columns)
    for r in regressors:
        if r["name"] in tel.columns:
            raise InputError(tel.path, f"column '{r['name']}' is also a regressor the unit "
                                       "file declares ([[trace.regressor]]): rename one")
        if all(c in tel.columns for c in r["inputs"]):
            cols[r["name"]] = evaluate(r["tree"], {c: tel.columns[c] for c in r["inputs"]})
    return Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))
