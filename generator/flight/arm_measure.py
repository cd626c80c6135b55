"""What the flight code costs on the Cortex-M4F, measured on the emulated target.

Code size and worst-case stack from the linked ELF and -fstack-usage, instructions per
call counted exactly from QEMU's execution trace and cross-checked with -icount, the
minimum flops of the chain's CasADi algorithm, the static checks of the generated C, the
measured variant P1, and the Markdown report:

    python -m generator.flight.target report COEFFS.json -o docs/flight_target.md

Size: the measurements of one target (size, stack, instructions per call, the flops
bound) and their report; split out of target.py already.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from generator.flight.chain import ChainSpec
from generator.flight.codegen import render
from generator.flight.coeffs import CoefficientSet
from generator.flight.arm_build import (ALLOWED_EXTERNAL, ARCH_FLAGS, CAL_NOPS, CC,
                                        CPPCHECK_FLAGS, DEBIAN_PACKAGES, EXTRA_WARNINGS,
                                        FP_FLAGS, HEAP_SYMBOLS, KERNEL_FLAGS, MACHINE,
                                        MEASURE_FLAGS, PAINT_WORDS, STRICT_FLAGS, TOOLS,
                                        ArmBuildError, ArmRunError, ArmToolchainMissing,
                                        Entry, _arm_env, _run, entry_points, flags_for,
                                        require_toolchain, tool_versions, unit_c_files)
from generator.flight.arm_runner import ArmUnit, Job, qemu_command, random_inputs, run_job



# ---- static analysis of the ELF ------------------------------------------------------


@dataclass
class Func:
    name: str
    addr: int
    size: int
    insns: dict = field(default_factory=dict)   # addr -> (mnemonic, operands)
    callees: set = field(default_factory=set)
    indirect: bool = False


def elf_functions(elf: Path) -> dict:
    """{name: Func} of the ELF's functions (symbols with a size: every C function, and the
    runner's assembly ones, which declare theirs), with their disassembly and direct
    callees (bl, and b/b.w to another function's entry: tail calls)."""
    p = _run([TOOLS["nm"], "-S", "--defined-only", str(elf)])
    funcs = {}
    for line in p.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[2] in "tTwW":
            addr, size = int(parts[0], 16) & ~1, int(parts[1], 16)
            funcs[parts[3]] = Func(parts[3], addr, size)
    p = _run([TOOLS["objdump"], "-d", "--no-show-raw-insn", str(elf)])
    by_addr = {f.addr: f for f in funcs.values()}
    cur = None
    head = re.compile(r"^([0-9a-f]+) <([^>]+)>:$")
    ins = re.compile(r"^\s+([0-9a-f]+):\s+(\S+)\s*(.*)$")
    for line in p.stdout.splitlines():
        m = head.match(line)
        if m:
            addr = int(m.group(1), 16)
            cur = by_addr.get(addr)
            continue
        m = ins.match(line)
        if m and cur is not None:
            a = int(m.group(1), 16)
            if cur.addr <= a < cur.addr + cur.size:
                mnem = m.group(2)
                ops = m.group(3).split(";")[0].split("@")[0].strip()
                cur.insns[a] = (mnem, ops)
    for f in funcs.values():
        for a, (mnem, ops) in f.insns.items():
            base = mnem.split(".")[0]
            if base in ("bl", "b", "blx", "bx") or (base.startswith("b") and
                                                    base[1:] in _CONDS):
                t = re.match(r"([0-9a-f]+)\s*<([^>+]+)>", ops)
                if t:
                    target = int(t.group(1), 16)
                    g = by_addr.get(target)
                    if g is not None and g is not f and (base == "bl" or target == g.addr):
                        f.callees.add(g.name)
                elif base == "blx":
                    f.indirect = True
    return funcs


_CONDS = {"eq", "ne", "cs", "cc", "hs", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt",
          "gt", "le", "al"}


def reachable(funcs: dict, root: str) -> list:
    seen, todo = [], [root]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.append(n)
        todo.extend(sorted(funcs[n].callees))
    return seen


def stack_usage(build_dir: Path) -> dict:
    """{function: (bytes, qualifier)} from the .su files of a build."""
    out = {}
    for su in sorted(build_dir.glob("*.su")):
        for line in su.read_text().splitlines():
            parts = line.split("\t")
            if len(parts) != 3:
                continue
            name = _base_name(parts[0].rsplit(":", 1)[-1])
            out[name] = (int(parts[1]), parts[2])
    return out


def _base_name(sym: str) -> str:
    """A GCC clone's name as .su files write it: f.constprop.0.isra.0 -> f.constprop.isra."""
    return re.sub(r"\.\d+", "", sym)


def worst_stack(funcs: dict, su: dict, root: str, _depth=0) -> int:
    """Worst-case stack of a call of root: its frame plus the deepest callee chain."""
    if _depth > 32:
        raise ArmBuildError(f"call graph too deep or recursive at {root}")
    f = funcs[root]
    if _base_name(root) not in su:
        raise ArmBuildError(f"no -fstack-usage data for {root}")
    frame, qual = su[_base_name(root)]
    if qual != "static":
        raise ArmBuildError(f"{root}: stack usage is {qual}, not static")
    if f.indirect:
        raise ArmBuildError(f"{root}: indirect call, no static stack bound")
    deeper = [worst_stack(funcs, su, c, _depth + 1) for c in sorted(f.callees)]
    return frame + max(deeper, default=0)


def defined_symbols(obj: Path) -> set:
    p = _run([TOOLS["nm"], "--defined-only", str(obj)])
    return {ln.split()[-1] for ln in p.stdout.splitlines() if len(ln.split()) >= 3}


def undefined_symbols(objs) -> set:
    """Symbols the objects need from outside themselves (after resolving among them)."""
    need, have = set(), set()
    for o in objs:
        p = _run([TOOLS["nm"], "-u", str(o)])
        need |= {ln.split()[-1] for ln in p.stdout.splitlines() if ln.strip()}
        have |= defined_symbols(o)
    return need - have


def section_sizes(obj: Path) -> dict:
    """{'code': text bytes, 'const': rodata bytes, 'data': data+bss bytes} of an object."""
    p = _run([TOOLS["size"], "-A", str(obj)])
    out = {"code": 0, "const": 0, "data": 0}
    for line in p.stdout.splitlines():
        parts = line.split()
        if len(parts) < 2 or not parts[1].isdigit():
            continue
        name, size = parts[0], int(parts[1])
        if name.startswith(".text"):
            out["code"] += size
        elif name.startswith(".rodata"):
            out["const"] += size
        elif name.startswith((".data", ".bss")):
            out["data"] += size
    return out


# ---- minimum floating-point operations ------------------------------------------------

ARITH_OPS = {getattr(ca, n): n[3:].lower() for n in (
    "OP_ADD", "OP_SUB", "OP_MUL", "OP_DIV", "OP_SQRT", "OP_FABS", "OP_SQ", "OP_TWICE",
    "OP_INV", "OP_FMIN", "OP_FMAX", "OP_COPYSIGN")}
NEG_OPS = {ca.OP_NEG: "neg"}
DATA_OPS = {ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST, ca.OP_PARAMETER, ca.OP_ASSIGN}


def function_flops(f: ca.Function) -> dict:
    """The floating-point operations in a CasADi Function's algorithm (what its generated
    C executes): {'flops': arithmetic operations, 'neg': negations (not counted: an exact
    sign flip that folds into the following add/sub), 'by_op': {op: n}, 'loads': input
    elements read, 'stores': output elements written}. loads + stores is the memory
    traffic no load/store machine avoids (every coefficient is used once). Operations not
    classified here raise, so a new kind of operation in the chain cannot go uncounted."""
    by_op, neg, loads, stores = Counter(), 0, 0, 0
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        if op in ARITH_OPS:
            by_op[ARITH_OPS[op]] += 1
        elif op in NEG_OPS:
            neg += 1
        elif op == ca.OP_INPUT:
            loads += 1
        elif op == ca.OP_OUTPUT:
            stores += 1
        elif op not in DATA_OPS:
            raise ValueError(f"operation {op} in {f.name()} is not classified for the flop "
                             f"count; add it to ARITH_OPS or DATA_OPS")
    return {"flops": sum(by_op.values()), "neg": neg, "by_op": dict(sorted(by_op.items())),
            "loads": loads, "stores": stores, "kernel": f.name()}


def per_call_flops(f: ca.Function, n_call_inputs: int) -> dict:
    """The arithmetic operations of f that depend on a per-call input (its first
    n_call_inputs arguments; the others are coefficients): an operation on coefficients
    alone can be done once, when a table is loaded. {'flops', 'by_op', 'coeff_only'}."""
    dep = {}
    by_op, coeff_only = Counter(), 0
    for k in range(f.n_instructions()):
        op, ins, outs = f.instruction_id(k), f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_INPUT:
            dep[outs[0]] = ins[0] < n_call_inputs
        elif op == ca.OP_OUTPUT:
            continue
        elif op in ARITH_OPS or op in NEG_OPS or op in DATA_OPS:
            d = any(dep.get(w, False) for w in ins)
            dep[outs[0]] = d
            if op in ARITH_OPS:
                if d:
                    by_op[ARITH_OPS[op]] += 1
                else:
                    coeff_only += 1
        else:
            raise ValueError(f"operation {op} in {f.name()} is not classified for the flop "
                             f"count; add it to ARITH_OPS or DATA_OPS")
    return {"flops": sum(by_op.values()), "by_op": dict(sorted(by_op.items())),
            "coeff_only": coeff_only}


def folded_kernel(spec: ChainSpec, sensor, set_only=False) -> tuple:
    """The chain of one sensor with every constant folded: the generated kernel itself
    (codegen.build_kernel: chain.folded_sensor_kernel on the prepared coefficients that
    `<unit>_table_prepare` computes once per table, chain.fold_sensor_coeffs). Returns
    (Function, number of prepared coefficients a call reads)."""
    from generator.flight.chain import n_prepared
    from generator.flight.codegen import build_kernel
    s = spec.unit.sensor(sensor) if isinstance(sensor, str) else sensor
    return build_kernel(spec, s, set_only=set_only), n_prepared(spec, s, set_only)


def flop_bound(spec: ChainSpec, sensor, set_only=False) -> dict:
    """The lower bound of one sensor call's floating-point operations: the per-call
    operations of the folded chain (folded_kernel); with, for comparison, the per-call
    operations of the generated kernel itself ('kernel_per_call'; since the kernels read
    prepared coefficients it is the folded chain, so the two are equal: nothing a table
    load could do once is left in a call)."""
    s = spec.unit.sensor(sensor) if isinstance(sensor, str) else sensor
    ins = spec.sensor_inputs(s, set_only)
    f, n_folded = folded_kernel(spec, s, set_only)
    bound = per_call_flops(f, len(ins))
    kind = "correct_set" if set_only else "correct"
    kernel = per_call_flops(Entry(0, kind, s.name, "", "").kernel(spec), len(ins))
    # one load per folded coefficient and per input element, one store per output
    # element: what a machine that moves one value per instruction cannot avoid
    moves = (n_folded + sum(i.size for i in ins)
             + sum(o.size for o in spec.sensor_outputs(s, set_only)))
    return {"flops": bound["flops"], "by_op": bound["by_op"], "moves": moves,
            "kernel_per_call": kernel["flops"], "kernel_coeff_only": kernel["coeff_only"]}


def entry_bound(spec: ChainSpec, entry: Entry) -> dict:
    """flop_bound of an entry point; for select, the per-call operations of the agreement
    kernel (the squared tolerances (agree_i + agree_j)^2 are coefficients only)."""
    if entry.kind == "select":
        f = entry.kernel(spec)
        b = per_call_flops(f, 1)
        moves = sum(f.nnz_in(i) for i in range(f.n_in())) + f.nnz_out(0)
        return {"flops": b["flops"], "by_op": b["by_op"], "kernel_per_call": b["flops"],
                "kernel_coeff_only": b["coeff_only"], "moves": moves}
    return flop_bound(spec, entry.sensor, set_only=entry.kind == "correct_set")


def min_flops(spec: ChainSpec, sensor, set_only=False) -> dict:
    """function_flops of one sensor's kernel."""
    s = spec.unit.sensor(sensor) if isinstance(sensor, str) else sensor
    kind = "correct_set" if set_only else "correct"
    return function_flops(Entry(0, kind, s.name, "", "").kernel(spec))


# ---- instruction counting -------------------------------------------------------------

_TRACE = re.compile(r"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/")
MARKERS = ("mark_call_begin", "mark_call_end", "mark_loop_begin", "mark_loop_end")


def _trace_pcs(text: str):
    for line in text.splitlines():
        m = _TRACE.match(line)
        if m:
            yield int(m.group(1), 16)


def _span(f) -> tuple:
    return f.addr, f.addr + max(f.size, 2)


def trace_regions(text: str, funcs: dict) -> list:
    """[(kind, Counter pc -> executions)] of the regions between the runner's markers
    ('call' or 'loop'), the marker functions' own instructions excluded, in order."""
    marks = {funcs[n].addr: n for n in MARKERS}
    spans = [_span(funcs[n]) for n in MARKERS]
    regions, cur, kind = [], None, None
    for pc in _trace_pcs(text):
        m = marks.get(pc)
        if m is not None:
            if m.endswith("_begin"):
                cur, kind = Counter(), m[5:-6]
            elif cur is not None:
                regions.append((kind, cur))
                cur = None
            continue
        if cur is not None and not any(lo <= pc < hi for lo, hi in spans):
            cur[pc] += 1
    return regions


def _func_of(funcs_sorted, pc):
    for f in funcs_sorted:
        lo, hi = _span(f)
        if lo <= pc < hi:
            return f
    return None


INSN_CLASSES = (
    ("fp arithmetic", re.compile(r"^v(add|sub|mul|div|neg|abs|sqrt|fma|fms|fnm|nm)")),
    ("fp load/store", re.compile(r"^v(ldr|str|ldm|stm|push|pop)")),
    ("fp convert", re.compile(r"^vcvt")),
    ("fp compare", re.compile(r"^v(cmp|mrs)")),
    ("fp move", re.compile(r"^vmov")),
    ("load/store", re.compile(r"^(ldr|str|ldm|stm|push|pop)")),
    ("branch/call/return", re.compile(r"^(b|bl|blx|bx|cbz|cbnz|tbb|tbh)(\.|$|eq|ne|cs|cc|hs|"
                                      r"lo|mi|pl|vs|vc|hi|ls|ge|lt|gt|le)")),
    ("it", re.compile(r"^it")),
)
CLASS_NAMES = tuple(c for c, _ in INSN_CLASSES) + ("other integer",)


def classify(mnem: str, ops: str = "") -> str:
    if re.match(r"^(pop|ldm)", mnem) and "pc" in ops:
        return "branch/call/return"
    for name, rx in INSN_CLASSES:
        if rx.match(mnem):
            return name
    return "other integer"


@dataclass
class EntryMeasure:
    entry: Entry
    paths: dict            # path -> instructions per call (entry point and its callees)
    path_status: dict      # path -> status the call returned (what the path is)
    by_function: dict      # nominal path: function -> instructions executed
    by_class: dict         # nominal path: instruction class -> instructions executed
    by_insn: dict          # nominal path: mnemonic -> instructions executed
    stack_painted: int     # max over paths: bytes written below the caller's SP
    stack_static: int      # -fstack-usage frames summed along the worst call chain
    frames: dict           # function -> frame bytes (.su)
    code_bytes: int        # sizes of the functions reachable from the entry point
    functions: dict        # function -> size
    flops: dict            # function_flops of the entry's kernel
    bound: dict            # entry_bound: per-call flops of the folded chain (the lower bound)
    trace_per_iter: dict   # path -> instructions per iteration of the timing loop (trace)
    icount_per_iter: dict  # path -> the same from -icount virtual time (cross-check)

    @property
    def nominal(self) -> int:
        return self.paths["nominal"]

    @property
    def worst(self) -> int:
        return max(self.paths.values())

    @property
    def ratio(self) -> float:
        return self.nominal / self.flops["flops"]

    @property
    def bound_ratio(self) -> float:
        """Instructions per call (nominal path) / the folded chain's per-call flops."""
        return self.nominal / self.bound["flops"]


def _ref_sensor(cs, sensor, raw, temp, coil, **kw):
    from generator.flight.chain import reference_sensor
    return reference_sensor(cs.spec, cs.unit.sensor(sensor), cs.flat_sensor(sensor),
                            cs.flat_unit(), raw, temp, coil, **kw)


def representative_calls(cs: CoefficientSet, entry: Entry) -> dict:
    """The paths through an entry point that the measurement covers, chosen with the
    Python reference so that each really takes its path: {path: (args, expected status)}.
    'nominal' is a valid sample (status 0): a calibrated vector of plausible magnitude,
    in-range temperature, coil currents given."""
    from generator.flight import chain
    spec = cs.spec
    if entry.kind == "select":
        S = len(spec.unit.sensors)
        c = [float(cs.sensors[s.name]["agree_nT"]) for s in spec.unit.sensors]
        v = np.array([21000.0, -14000.0, 33000.0])
        fields = np.array([v + 0.05 * min(c) * np.array([i, -i, 0.5 * i]) for i in range(S)])
        order = spec.fallback_order()
        ok = np.zeros(S, dtype=np.int64)
        one_bad = ok.copy()
        one_bad[order[0]] = chain.STATUS_SATURATED
        off = fields.copy()
        off[order[0]] += 20 * max(c)
        return {"nominal": ((fields[None], ok[None]), None),
                "first_invalid": ((fields[None], one_bad[None]), None),
                "one_disagrees": ((off[None], ok[None]), None),
                "none_valid": ((fields[None], np.full((1, S), chain.STATUS_SATURATED)), None)}
    s = spec.unit.sensor(entry.sensor)
    c = cs.sensors[s.name]
    t_min, t_max = float(c["t_min_C"]), float(c["t_max_C"])
    t_nom = float(np.clip(float(c["t_ref_C"]) + 3.25, t_min, t_max))
    nc = len(spec.coils)
    coil = np.array([[0.05 * (j + 1) for j in range(nc)]]) if nc else None
    rng = np.random.default_rng(7)
    span = int(60000 / s.lsb_nT)
    for _ in range(1000):   # a raw sample the reference calls valid at t_nom
        k = 6 if s.set_reset else 3
        raw = np.clip(s.zero_count + rng.integers(-span, span + 1, (1, k)),
                      s.count_min + 1, s.count_max - 1)
        if s.set_reset:   # a pair: SET = zero + x + o, RESET = zero - x + o
            x, o = raw[:, :3] - s.zero_count, rng.integers(-300, 301, (1, 3))
            raw = np.concatenate([s.zero_count + x + o, s.zero_count - x + o], axis=1)
        if _ref_sensor(cs, s.name, raw, [t_nom], coil)["status"][0] == 0:
            break
    else:
        raise RuntimeError(f"no valid sample found for {s.name}")
    sat = raw.copy()
    sat[0, 0] = s.count_max
    if entry.kind == "correct_set":
        pair = _ref_sensor(cs, s.name, raw, [t_nom], coil)
        off = pair["offset_counts"]
        setc = raw[:, :3]
        paths = {"nominal": (setc, [t_nom], off, coil),
                 "clamped": (setc, [t_max + 10.0], off, coil),
                 "no_offset": (setc, [t_nom], np.full((1, 3), np.nan), coil),
                 "nonfinite": (setc, [np.nan], off, coil)}
        if nc:
            paths["no_currents"] = (setc, [t_nom], off, None)
        out = {}
        for p, (sc, t, of, cl) in paths.items():
            st = _ref_sensor(cs, s.name, sc, t, cl, set_only=True, offset_counts=of)["status"][0]
            out[p] = ((s.name, sc, np.array(t), of, cl), int(st))
        return out
    paths = {"nominal": (raw, [t_nom], coil), "clamped": (raw, [t_max + 10.0], coil),
             "saturated": (sat, [t_nom], coil), "nonfinite": (raw, [np.nan], coil)}
    if nc:
        paths["no_currents"] = (raw, [t_nom], None)
    return {p: ((s.name, r, np.array(t), cl), int(_ref_sensor(cs, s.name, r, t, cl)["status"][0]))
            for p, (r, t, cl) in paths.items()}


TRACE_REPS = (1, 2)            # calls per timing loop in the trace run
ICOUNT_REPS = (1000, 3000)     # ... in the -icount run
TRACE_CAL_REPS = (10, 20)      # calibration loops, trace run
ICOUNT_CAL_REPS = (10000, 50000)   # ... -icount run (long: the tick scale's precision)


def measure(cs: CoefficientSet, arm: ArmUnit | None = None, timeout=300.0) -> dict:
    """Everything the report shows, measured on the emulated target.

    Per entry point and path: instructions from the entry point's first instruction to
    its return, everything it calls included (exact, from the execution trace); the
    stack (static along the call graph; painted high-water mark); code size. Both
    counting methods are calibrated with the known-length functions cal_nops/cal_empty,
    and the trace's per-iteration counts of every timing loop are checked against
    -icount virtual time. Returns {'entries': [EntryMeasure], 'calibration', 'unit'}."""
    arm = arm or ArmUnit(cs)
    b = arm.build
    funcs = elf_functions(b.elf)
    fsorted = sorted(funcs.values(), key=lambda f: f.addr)
    su = stack_usage(b.dir)
    entries = entry_points(cs)
    calls = {e.id: representative_calls(cs, e) for e in entries}

    def make_job(reps_pair, cal_pair):
        job = Job(cs)
        job.defaults()
        for r in cal_pair:
            job.calibrate(r)
        order = []
        for e in entries:
            for ri, reps in enumerate(reps_pair):
                for pname, (args, _) in calls[e.id].items():
                    job.call(e.kind, *args, reps=reps)
                    order.append((e.id, pname, ri))
        return job, order

    tjob, order = make_job(TRACE_REPS, TRACE_CAL_REPS)
    out, text = run_job(b.elf, tjob.bytes(), trace=True, timeout=timeout)
    tres = tjob.parse(out)
    regions = trace_regions(text, funcs)
    del text
    ijob, _ = make_job(ICOUNT_REPS, ICOUNT_CAL_REPS)
    out_i, _ = run_job(b.elf, ijob.bytes(), icount=True, timeout=timeout)
    ires = ijob.parse(out_i)

    # -- calibration: the trace must count exactly CAL_NOPS + 1 instructions per call of
    # cal_nops and 1 per call of cal_empty; -icount's ticks give instructions per tick
    if [k for k, _ in regions[:4]] != ["loop"] * 4:
        raise ArmRunError("trace: calibration regions not found")
    cal = {"nops": CAL_NOPS, "trace": []}
    for (_, cnt), reps, fname in zip(regions[:4], (TRACE_CAL_REPS[0],) * 2 +
                                     (TRACE_CAL_REPS[1],) * 2, ("cal_nops", "cal_empty") * 2):
        lo, hi = _span(funcs[fname])
        cal["trace"].append({
            "function": fname, "reps": reps,
            "counted": sum(v for pc, v in cnt.items() if lo <= pc < hi),
            "expected": reps * (CAL_NOPS + 1 if fname == "cal_nops" else 1),
            "loop_total": sum(cnt.values())})
    d_nops = ires[1]["ticks_nops"] - ires[0]["ticks_nops"]
    d_empty = ires[1]["ticks_empty"] - ires[0]["ticks_empty"]
    dr_c = ICOUNT_CAL_REPS[1] - ICOUNT_CAL_REPS[0]
    scale = CAL_NOPS * dr_c / (d_nops - d_empty)
    cal["icount_insn_per_tick"] = scale
    cal["icount"] = {"reps": ICOUNT_CAL_REPS,
                     "ticks_nops": [ires[0]["ticks_nops"], ires[1]["ticks_nops"]],
                     "ticks_empty": [ires[0]["ticks_empty"], ires[1]["ticks_empty"]]}
    dr_t = TRACE_CAL_REPS[1] - TRACE_CAL_REPS[0]
    dr_i = ICOUNT_REPS[1] - ICOUNT_REPS[0]
    tr = cal["trace"]
    cal["loop_per_iter"] = {
        "cal_nops": {"trace": (tr[2]["loop_total"] - tr[0]["loop_total"]) / dr_t,
                     "icount": scale * d_nops / dr_c},
        "cal_empty": {"trace": (tr[3]["loop_total"] - tr[1]["loop_total"]) / dr_t,
                      "icount": scale * d_empty / dr_c}}
    # a difference of two tick readings is exact to +-1 tick at each end
    cal["icount_resolution"] = 2 * scale / dr_i

    # -- measurements: per measured record a 'call' region, then a 'loop' region
    rest = regions[4:]
    if len(rest) != 2 * len(order):
        raise ArmRunError(f"trace: {len(rest)} regions for {len(order)} measurements")
    per = {}
    for i, key in enumerate(order):
        (k1, call_cnt), (k2, loop_cnt) = rest[2 * i], rest[2 * i + 1]
        if (k1, k2) != ("call", "loop"):
            raise ArmRunError(f"trace: unexpected regions {k1}, {k2}")
        per[key] = (call_cnt, sum(loop_cnt.values()), tres[2 + i], ires[2 + i])

    results = []
    for e in entries:
        caller = funcs[f"entry_{e.tag}"]
        tree = reachable(funcs, e.fn)
        tree_set = set(tree)
        paths, pstat, tper, iper = {}, {}, {}, {}
        nominal = None
        painted = 0
        for pname, (_, expect) in calls[e.id].items():
            call_cnt, loop1, r1, i1 = per[(e.id, pname, 0)]
            _, loop2, _, i2 = per[(e.id, pname, 1)]
            callee, classes, mnems = Counter(), Counter(), Counter()
            for pc, v in call_cnt.items():
                f = _func_of(fsorted, pc)
                if f is caller:
                    continue      # the call site: argument set-up, result handling
                if f is None or f.name not in tree_set:
                    raise ArmRunError(f"trace: {e.fn} executed code outside its call graph "
                                      f"at 0x{pc:x} ({f.name if f else '?'})")
                callee[f.name] += v
                mnem, ops = f.insns.get(pc, ("?", ""))
                classes[classify(mnem, ops)] += v
                mnems[mnem.split(".")[0]] += v
            paths[pname] = sum(callee.values())
            pstat[pname] = int(r1["status"][0]) if e.kind != "select" else \
                int(r1["reason"][0])
            if e.kind != "select" and expect is not None and pstat[pname] != expect:
                raise ArmRunError(f"{e.fn} path {pname}: status {pstat[pname]} on the "
                                  f"target, {expect} in the reference")
            tper[pname] = (loop2 - loop1) / (TRACE_REPS[1] - TRACE_REPS[0])
            iper[pname] = scale * (i2["ticks"][0] - i1["ticks"][0]) / dr_i
            painted = max(painted, int(r1["stack"][0]))
            if pname == "nominal":
                nominal = (dict(callee), dict(classes), dict(mnems.most_common()))
        results.append(EntryMeasure(
            entry=e, paths=paths, path_status=pstat, by_function=nominal[0],
            by_class=nominal[1], by_insn=nominal[2], stack_painted=painted,
            stack_static=worst_stack(funcs, su, e.fn),
            frames={n: su[_base_name(n)][0] for n in tree if _base_name(n) in su},
            code_bytes=sum(funcs[n].size for n in tree),
            functions={n: funcs[n].size for n in tree},
            flops=function_flops(e.kernel(cs.spec)), bound=entry_bound(cs.spec, e),
            trace_per_iter=tper, icount_per_iter=iper))

    # -- whole unit: the objects as compiled (every function CasADi emits, API helpers
    # included), and the functions the API's entry points reach (what a flight link with
    # -ffunction-sections --gc-sections would keep of them)
    objs = b.unit_objects
    compiled = Counter()
    for o in objs:
        compiled.update(section_sizes(o))
    reach = set()
    for e in entries:
        reach.update(reachable(funcs, e.fn))
    unit_syms = set().union(*(defined_symbols(o) for o in objs))
    linked = {n: funcs[n].size for n in sorted(reach) if n in unit_syms}
    unit = {"compiled": dict(compiled), "linked_code": sum(linked.values()),
            "linked_functions": linked,
            "objects": {o.name: section_sizes(o) for o in objs}}
    return {"entries": results, "calibration": cal, "unit": unit, "build": b}


# ---- static checks (issue 7 item 3) -------------------------------------------------------


def warning_check(cs: CoefficientSet, extra=EXTRA_WARNINGS, workdir: Path | None = None,
                  sources: dict | None = None) -> tuple:
    """Compile each generated .c with the flight flags plus `extra` (-Werror stays on).
    Returns ({file: compiler messages, '' when clean}, work dir with sources and objects)."""
    require_toolchain()
    files = dict(sources) if sources is not None else render(cs)
    work = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="magcal-warn-"))
    work.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (work / name).write_text(text)
    out = {}
    for name in unit_c_files(files):
        cmd = [CC, *ARCH_FLAGS, *FP_FLAGS, *flags_for(name, cs.unit.id, files), *extra,
               "-I", str(work), "-c", str(work / name), "-o", str(work / (name[:-2] + ".o"))]
        p = _run(cmd, cwd=work)
        out[name] = p.stderr.strip() if (p.returncode != 0 or p.stderr.strip()) else ""
        if p.returncode != 0 and not out[name]:
            out[name] = f"exit status {p.returncode}"
    return out, work


def external_symbols(objs) -> dict:
    """What a unit's objects need from outside the unit: {'all': set, 'heap': set,
    'libm_or_runtime': set (neither allowed nor heap)}."""
    ext = undefined_symbols(objs)
    return {"all": ext, "heap": ext & HEAP_SYMBOLS,
            "not_allowed": ext - ALLOWED_EXTERNAL}


def cppcheck_available() -> bool:
    return shutil.which("cppcheck") is not None


def cppcheck(paths, include: Path) -> subprocess.CompletedProcess:
    return _run(["cppcheck", *CPPCHECK_FLAGS, "-I", str(include), *map(str, paths)],
                timeout=600)


def static_checks(cs: CoefficientSet) -> list:
    """The issue-7 checks as Markdown lines (the tests assert the same things)."""
    lines = []
    msgs, work = warning_check(cs)
    bad = {k: v for k, v in msgs.items() if v}
    flags = " ".join(EXTRA_WARNINGS)
    if bad:
        lines.append(f"`{flags}`: **warnings** in " + ", ".join(f"`{k}`" for k in bad))
    else:
        lines.append(f"`{flags}` (with -Werror): clean for every generated file; the one "
                     f"exception is `-Wno-unused-parameter` for `{cs.unit.id}_kernels.c` "
                     "(CasADi's function signature has `iw`, `w`, `mem`, unused here)")
    objs = sorted(work.glob("*.o"))
    ext = external_symbols(objs)
    if ext["not_allowed"] or ext["heap"]:
        lines.append("undefined symbols of the objects: **" +
                     ", ".join(sorted(ext["not_allowed"] | ext["heap"])) + "**")
    else:
        allowed = sorted(ext["all"])
        lines.append("undefined symbols of the objects (`arm-none-eabi-nm -u`, after "
                     "resolving among the unit's objects): " +
                     (", ".join(allowed) if allowed else "none") +
                     " (no heap, no libm function, no soft-float helper)")
    if cppcheck_available():
        p = cppcheck(sorted(work.glob("*.c")), work)
        ver = _run(["cppcheck", "--version"]).stdout.strip()
        if p.returncode == 0:
            lines.append(f"{ver} `{' '.join(CPPCHECK_FLAGS)}`: clean")
        else:
            kinds = Counter(re.findall(r"\[([A-Za-z]\w*)\]\s*$", p.stderr + p.stdout, re.M))
            lines.append(f"{ver} `{' '.join(CPPCHECK_FLAGS)}`: **fails** (" +
                         ", ".join(f"{k} x{n}" for k, n in sorted(kinds.items())) + ")")
            if "uninitvar" in kinds:
                lines.append(
                    "cppcheck cannot follow the kernel's writes through `res[]`, so it "
                    "reports the wrapper's reads of the kernel outputs (`band_margin_nT2`, "
                    "`offset_counts`, `margin_nT2`) as uninitialised. Proposal **P2**: in "
                    "`templates/magcal.c.j2` put `/* cppcheck-suppress uninitvar ; written "
                    "by the kernel through res[] */` on the line before each such read "
                    "(no code change; needs `--inline-suppr`, which the checks pass). "
                    "Zero-initialising the arrays instead also works but costs stores, and "
                    "for `margin_nT2` GCC emits a call to `memset`, which no flight object "
                    "may need.")
    else:
        lines.append("cppcheck: not installed here")
    shutil.rmtree(work, ignore_errors=True)
    return lines


# ---- proposal P1, measured: the kernels in the wrapper's translation unit -----------------


def single_tu_variant(files: dict, unit_id: str, volatile_base: bool = False) -> dict | None:
    """Proposal P1 applied to generated sources: `<unit>_kernels.c` compiled inside
    `<unit>_magcal.c` as static inline functions. volatile_base adds proposal P3: each
    wrapper reads its coefficient block's address through a volatile pointer, so that GCC
    addresses the coefficients from that base (VLDR reaches +-1020 B) instead of folding
    the block's offset in the coefficient struct into every load. None when the sources
    are not laid out as expected (e.g. once the proposals are applied)."""
    k_name, h_name, m_name = (f"{unit_id}_kernels.c", f"{unit_id}_kernels.h",
                              f"{unit_id}_magcal.c")
    inc = f'#include "{h_name}"'
    if k_name not in files or h_name not in files or inc not in files.get(m_name, ""):
        return None
    out = dict(files)
    kernels = out.pop(k_name)
    sizes = "\n".join(ln for ln in out[h_name].splitlines()
                      if ln.startswith("#define") and "_SZ_" in ln)
    out[f"{unit_id}_kernels.inc"] = kernels
    m = out[m_name].replace(inc, "#define CASADI_SYMBOL_EXPORT static inline\n" + sizes +
                            f'\n#include "{unit_id}_kernels.inc"')
    if volatile_base:
        m, n = re.subn(rf"^(\s+)const {unit_id}_real_t \*c = coeffs->(\w+);",
                       rf"\1const {unit_id}_real_t *volatile c_base = coeffs->\2;\n"
                       rf"\1const {unit_id}_real_t *c = c_base;", m, flags=re.M)
        if n == 0:
            return None
    out[m_name] = m
    return out


VARIANTS = (("P1", {}), ("P1+P3", {"volatile_base": True}))


def _measure_variant(cs, files):
    # the wrapper now holds CasADi's code: the same warning exception as the kernels file
    arm = ArmUnit(cs, sources=files)
    mv = measure(cs, arm)
    from generator.flight.chain import reference_sensor
    rng = np.random.default_rng(11)
    calls, refs = [], []
    for s in cs.unit.sensors:
        c = cs.sensors[s.name]
        raw, temp, coil = random_inputs(rng, s, 2000, len(cs.spec.coils),
                                         (float(c["t_min_C"]), float(c["t_max_C"])))
        calls.append(("correct", s.name, raw, temp, coil))
        refs.append(reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw,
                                     temp, coil))
    for (_, name, *_), got, ref in zip(calls, arm.run(calls), refs):
        for key in ref:
            if np.ascontiguousarray(got[key]).tobytes() != \
                    np.ascontiguousarray(ref[key]).tobytes():
                raise ArmRunError(f"variant differs from the reference: {name} {key}")
    return mv, 2000 * len(calls)


def _variant_rows(cs, m):
    """Measure the proposals on this unit; None when they do not apply."""
    base = render(cs)
    done = {}
    for label, kw in VARIANTS:
        files = single_tu_variant(base, cs.unit.id, **kw)
        if files is None:
            return None
        done[label] = _measure_variant(cs, files)
    rows = []
    for e in m["entries"]:
        r = {"fn": e.entry.fn, "kind": e.entry.kind, "base": e}
        for label, (mv, _) in done.items():
            r[label] = next(v for v in mv["entries"] if v.entry.fn == e.entry.fn)
        rows.append(r)
    return {"labels": [lb for lb, _ in VARIANTS], "rows": rows,
            "unit_code": {lb: mv["unit"]["compiled"]["code"] for lb, (mv, _) in done.items()},
            "n_checked": sum(n for _, n in done.values())}


# ---- report ---------------------------------------------------------------------------

TARGET_RATIO = 2.0          # issue 7: instructions <= 2 x the kernel's own flops
TARGET_BOUND_RATIO = 1.5    # issue 20: instructions <= 1.5 x the folded chain's flops
TARGET_UNIT_CODE = 16 * 1024
TARGET_STACK = 512


def flight_report(cs: CoefficientSet, out_md, source: str | None = None,
                  with_variant: bool = True, with_checks: bool = True) -> dict:
    """Measure the unit on the emulated Cortex-M4F and write the Markdown report.
    Returns the measurement (measure()) plus 'variant' and 'checks'."""
    m = measure(cs)
    rows = []
    for e in m["entries"]:
        rows.append({"e": e, "worst_path": max(e.paths, key=e.paths.get),
                     "floor": (e.flops["flops"] + e.flops["loads"] + e.flops["stores"]) /
                     e.flops["flops"]})
    sensor_rows = [r for r in rows if r["e"].entry.kind != "select"]
    select_row = next((r for r in rows if r["e"].entry.kind == "select"), None)
    path_names = []
    for r in rows:
        path_names += [p for p in r["e"].paths if p not in path_names]
    max_dev = max(abs(e.trace_per_iter[p] - e.icount_per_iter[p])
                  for e in m["entries"] for p in e.paths)
    unitsz = dict(m["unit"])
    unitsz["coeff_bytes"] = sum(o["const"] for n, o in unitsz["objects"].items()
                                if n.endswith("_coeffs_default.o"))
    m["variant"] = _variant_rows(cs, m) if with_variant else None
    m["checks"] = static_checks(cs) if with_checks else []
    ctx = {
        "unit": cs.unit.id, "layout_hash": f"0x{cs.spec.layout_hash():08x}",
        "float_type": cs.unit.float_type, "coils": list(cs.spec.coils),
        "source": source or "COEFFS.json", "out_name": str(out_md),
        "tools": tool_versions(), "machine": MACHINE,
        "flags": " ".join(ARCH_FLAGS + FP_FLAGS + STRICT_FLAGS),
        "kernel_flags": " ".join(KERNEL_FLAGS[len(STRICT_FLAGS):]),
        "measure_flags": " ".join(MEASURE_FLAGS),
        "rows": rows, "select_row": select_row, "path_names": path_names,
        "ratio_min": min(r["e"].ratio for r in sensor_rows),
        "ratio_max": max(r["e"].ratio for r in sensor_rows),
        "stack_max": max(max(r["e"].stack_static, r["e"].stack_painted) for r in rows),
        "cal": m["calibration"], "unitsz": unitsz, "max_dev": max_dev,
        "bratio_min": min(r["e"].bound_ratio for r in sensor_rows),
        "bratio_max": max(r["e"].bound_ratio for r in sensor_rows),
        "bfloor_min": min(1 + r["e"].bound["moves"] / r["e"].bound["flops"]
                          for r in sensor_rows),
        "bfloor_max": max(1 + r["e"].bound["moves"] / r["e"].bound["flops"]
                          for r in sensor_rows),
        "targets": {"ratio": TARGET_RATIO, "bound": TARGET_BOUND_RATIO,
                    "code": TARGET_UNIT_CODE, "stack": TARGET_STACK},
        "qemu_trace": " ".join(map(str, qemu_command(Path("runner.elf"),
                                                     Path("trace.log"))[1:])),
        "qemu_icount": " ".join(map(str, qemu_command(Path("runner.elf"), icount=True)[1:])),
        "trace_reps": TRACE_REPS, "icount_reps": ICOUNT_REPS,
        "paint_bytes": 4 * PAINT_WORDS, "date": _dt.date.today().isoformat(),
        "classes": CLASS_NAMES, "variant": m["variant"], "checks": m["checks"],
        "packages": " ".join(DEBIAN_PACKAGES),
    }
    v = m["variant"]
    if v:
        last = v["labels"][-1]
        vr = [r[last].ratio for r in v["rows"] if r["kind"] != "select"]
        head = [2 * r["base"].flops["flops"] - (r["base"].flops["flops"] +
                r["base"].flops["loads"] + r["base"].flops["stores"])
                for r in v["rows"] if r["kind"] != "select"]
        ctx.update(var_ratio_min=min(vr), var_ratio_max=max(vr), headroom_min=min(head),
                   headroom_max=max(head))
    fl = [r["floor"] for r in sensor_rows]
    ctx.update(floor_min=min(fl), floor_max=max(fl))
    text = _arm_env().get_template("flight_report.md.j2").render(**ctx)
    Path(out_md).parent.mkdir(parents=True, exist_ok=True)
    Path(out_md).write_text(text)
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m generator.flight.target",
                                 description="the flight C on the emulated Cortex-M4F")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("report", help="measure size, stack, instructions; write Markdown")
    r.add_argument("coeffs", help="coefficients.json")
    r.add_argument("-o", "--output", required=True, help="report file (.md)")
    args = ap.parse_args(argv)
    if args.cmd == "report":
        try:
            cs = CoefficientSet.load(args.coeffs)
            src = args.coeffs
            cwd = Path.cwd().resolve()
            if Path(src).resolve().is_relative_to(cwd):      # name it as the user did
                src = str(Path(src).resolve().relative_to(cwd))
            m = flight_report(cs, args.output, source=src)
        except ArmToolchainMissing as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        for e in m["entries"]:
            print(f"{e.entry.fn}: {e.nominal} instructions, {e.flops['flops']} flops, "
                  f"ratio {e.ratio:.2f}, bound {e.bound['flops']} flops, ratio to the "
                  f"bound {e.bound_ratio:.2f}, code {e.code_bytes} B, "
                  f"stack {e.stack_static} B")
        print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
