#!/usr/bin/env python3
"""What folding at table-load time saves on the flight processor, measured (issue 20 item 5).

A measurement prototype, not the flight design: it builds a variant of the unit's generated
C in which every sensor kernel runs `chain.folded_sensor_kernel` on prepared coefficients
(`chain.fold_sensor_coeffs`, computed once in float32 by numpy, the way a `prepare` step at
table activation would, and compiled in as constant arrays), and counts instructions per
call on the emulated Cortex-M4F (QEMU mps2-an386) with the same measurement as
docs/flight_target.md (generator/flight/arm_measure.measure), the generated code of the
unchanged unit measured in the same run as the baseline.

Fold subsets (each a variant, measured):
  all       scale and axis signs into b and M, H M for boom sensors, band limits squared;
  no_H      as `all`, but a boom sensor keeps H as a separate stage (H M not formed);
  band      only the band limits squared once (the chain otherwise unchanged);
  all_asis  `all` without forcing the kernels inline (see below);
  +wrap     (suffix; `none+wrap`: no fold) one cut of the wrapper's overhead (item 2), the
            shared inputs a sensor reads (coil currents, body rate) copied once into
            locals that both the finiteness probe and the kernel read, instead of
            loading them from `aux` twice; the arithmetic is unchanged;
  +nn       (suffix) another cut: the kernel writes its vector outputs into locals that the
            wrapper copies to `out`, so that CasADi's `if (res[k] != 0)` tests are on
            pointers the compiler knows to be non-null. Measured 1 to 5 instructions per
            call less, it is now in templates/magcal.c.j2, so on today's sources the cut
            finds nothing to do (reported "not laid out as expected").

The folded kernels of two sensors that differ only in their axis signs (mpu1, mpu2 of the
example unit) become the same code once the signs are data: GCC's identical-code folding
(on at -O2) then merges them into one function called from two wrappers, which it no
longer inlines, and the arguments go through memory (arg[], res[]). The variants other than
all_asis mark CasADi's kernel bodies always_inline, as a generated design would have to.

Before counting, each variant's outputs are compared bit for bit with a float32 Python
reference that runs the same folding and the same folded kernel (chain.reference_sensor
with its kernel replaced), over random samples of every sensor (pair and SET-only calls):
a variant whose C and reference disagree is not reported.

What is not in the variant (so the figures are what folding alone buys): the wrapper is
the generated one; a real design passes a pointer to the prepared struct where this
prototype reads a file-scope array (one literal-pool load either way).

    python3 bench/bench_fold.py [COEFFS.json]

Needs gcc-arm-none-eabi, libnewlib-arm-none-eabi and qemu-system-arm (exit status 2
without them).
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402

from generator.flight import chain  # noqa: E402
from generator.flight import codegen  # noqa: E402
from generator.flight.arm_build import missing_tools  # noqa: E402
from generator.flight.arm_measure import _leaves, measure  # noqa: E402
from generator.flight.arm_runner import ArmUnit, random_inputs  # noqa: E402
from generator.flight.c_syntax import c_literal  # noqa: E402
from generator.flight.coeffs import CoefficientSet  # noqa: E402

EXAMPLE = REPO / "generated" / "samsat_fm1" / "coefficients.json"
VARIANTS = ("all", "no_H", "band", "all_asis", "none+wrap", "all+wrap")


# ---- the folded chain under a fold subset ------------------------------------------------


def _fold(spec, s, c, u, half, set_only, which):
    if which == "band":
        return None
    if which == "no_H" and s.frame == "boom":
        if spec.opts(s).sr_compensation:   # H is kept apart already
            return chain.fold_sensor_coeffs(spec, s, c, u, half, set_only=set_only)
        # the scale/sign fold of M without the H premultiplication (identity: exact)
        H = u.get("H_boom_to_body")
        eye = [[type(half)(1.0) if i == j else type(half)(0.0) for j in range(3)]
               for i in range(3)]
        u_eye = _UnitView(u, eye)
        f = chain.fold_sensor_coeffs(spec, s, c, u_eye, half, set_only=set_only)
        f["H"] = H
        return f
    return chain.fold_sensor_coeffs(spec, s, c, u, half, set_only=set_only)


class _UnitView:
    """A unit CoeffView with H_boom_to_body replaced (the identity: M folded without H)."""

    def __init__(self, u, H):
        self._u, self._H = u, H

    def scalar(self, name):
        return self._u.scalar(name)

    def get(self, name):
        return self._H if name == "H_boom_to_body" else self._u.get(name)


def _band_kernel(spec, s, raw, temp_C, coil_A, c, u, half, set_only, channels, rate_dps,
                 f_min2, f_max2, base=None):
    """sensor_kernel (or `base`, the unreplaced one) with the squared band limits given
    (the 'band' subset)."""
    out = (base or chain.sensor_kernel)(spec, s, raw, temp_C, coil_A, c, u, half, set_only=set_only,
                              channels=channels, rate_dps=rate_dps)
    B = out["field_body_nT"]
    norm2 = B[0] * B[0] + B[1] * B[1] + B[2] * B[2]
    out["band_margin_nT2"] = [norm2 - f_min2, f_max2 - norm2]
    return out


def _folded_out(spec, s, raw, temp, coil, f, half, set_only, channels, rate_dps):
    """folded_sensor_kernel; with H kept apart (no_H) the boom stage runs after it."""
    if "H" in f and not spec.opts(s).sr_compensation:
        g = dict(f)
        H = g.pop("H")
        out = chain.folded_sensor_kernel(spec, s, raw, temp, coil, g, half, set_only=set_only,
                                         channels=channels, rate_dps=rate_dps)
        B = [chain._dot3(H[i], out["field_body_nT"]) for i in range(3)]
        out["field_body_nT"] = B
        norm2 = B[0] * B[0] + B[1] * B[1] + B[2] * B[2]
        out["band_margin_nT2"] = [norm2 - f["field_min2"], f["field_max2"] - norm2]
        return out
    return chain.folded_sensor_kernel(spec, s, raw, temp, coil, f, half, set_only=set_only,
                                      channels=channels, rate_dps=rate_dps)


def _rebuild(template, it):
    if isinstance(template, dict):
        return {k: _rebuild(template[k], it) for k in template}
    if isinstance(template, (list, tuple)):
        return [_rebuild(e, it) for e in template]
    return next(it)


def prepared(cs, s, set_only, which):
    """The prepared coefficients of one kernel, float32 by numpy (the prepare step):
    (structure dict, flat float32 array)."""
    spec = cs.spec
    ft = chain.np_dtype(spec.unit)
    flat = np.asarray(cs.flat_sensor(s.name), dtype=ft)
    fu = np.asarray(cs.flat_unit(), dtype=ft)
    c = chain.CoeffView([flat[k] for k in range(flat.size)], spec.sensor_blocks(s))
    u = chain.CoeffView([fu[k] for k in range(fu.size)], spec.unit_blocks())
    if which == "band":
        lo, hi = u.scalar("field_min_nT"), u.scalar("field_max_nT")
        f = {"field_min2": lo * lo, "field_max2": hi * hi}
    else:
        f = _fold(spec, s, c, u, ft(0.5), set_only, which)
    return f, np.array([ft(x) for x in _leaves(f)], dtype=ft)


def kernel_fn(cs, s, set_only, which):
    """The variant kernel: same name and arguments as codegen.build_kernel's, the sensor
    coefficient argument being the prepared vector ('band': the table's coefficients
    followed by the two squared limits)."""
    spec = cs.spec
    ins = spec.sensor_inputs(s, set_only)
    sym = {i.name: ca.SX.sym(i.name, i.size) for i in ins}
    u_sym = ca.SX.sym("unit_coeffs", spec.n_unit_coeffs())
    u = chain.CoeffView([u_sym[k] for k in range(u_sym.numel())], spec.unit_blocks())

    def elems(name):
        return [sym[name][k] for k in range(sym[name].numel())] if name in sym else []
    temp = sym["temp_C"][0] if "temp_C" in sym else None
    half = ca.SX(0.5)
    f_num, flat = prepared(cs, s, set_only, which)
    if which == "band":
        n = spec.n_sensor_coeffs(s)
        p_sym = ca.SX.sym("prepared", n + 2)
        c = chain.CoeffView([p_sym[k] for k in range(n)], spec.sensor_blocks(s))
        out = _band_kernel(spec, s, elems("raw_counts"), temp, elems("coil_A"), c, u, half,
                           set_only, elems("channels"), elems("rate_dps"), p_sym[n],
                           p_sym[n + 1])
    else:
        p_sym = ca.SX.sym("prepared", flat.size)
        f = _rebuild(f_num, iter([p_sym[k] for k in range(flat.size)]))
        out = _folded_out(spec, s, elems("raw_counts"), temp, elems("coil_A"), f, half,
                          set_only, elems("channels"), elems("rate_dps"))
    outs = spec.sensor_outputs(s, set_only)
    fn = ca.Function(codegen.kernel_name(spec, s, set_only),
                     [sym[i.name] for i in ins] + [p_sym, u_sym],
                     [ca.vertcat(*out[o.name]) for o in outs])
    if which == "band":
        flat = np.concatenate([np.asarray(cs.flat_sensor(s.name), dtype=flat.dtype), flat])
    return fn, flat


def variant_sources(cs, which, force_inline=True):
    """{file: text}: the generated sources with the variant kernels and their prepared
    constants; None when the wrapper is not laid out as expected."""
    spec = cs.spec
    unit = spec.unit.id
    ft = spec.unit.float_type
    files = codegen.render(cs)
    real = "float" if ft == "float32" else "double"
    cg = ca.CodeGenerator(f"{unit}_kernels", {"casadi_real": real, "casadi_int": "int",
                                              "with_header": True, "with_mem": False})
    consts = []
    magcal = files[f"{unit}_magcal.c"]
    _, _, base_funcs = codegen.casadi_sources(spec)
    for s in spec.unit.sensors:
        for set_only in ((False, True) if s.set_reset else (False,)):
            fn, flat = kernel_fn(cs, s, set_only, which)
            cg.add(fn)
            arr = f"{unit}_{s.name}_{'set_' if set_only else ''}prep"
            lits = ", ".join(c_literal(float(v), ft) for v in flat)
            # external linkage and writable, as a prepare step's output is: the compiler
            # cannot fold the values into the code
            consts.append(f"extern {unit}_real_t {arr}[{flat.size}];\n"
                          f"{unit}_real_t {arr}[{flat.size}] = {{ {lits} }};")
            entry = f"{unit}_{s.name}_correct{'_set' if set_only else ''}"
            k_c = len(spec.sensor_inputs(s, set_only))
            magcal, n = re.subn(
                rf"(uint16_t {entry}\(.*?)(    arg\[{k_c}\] = )c;", rf"\1\2{arr};", magcal,
                count=1, flags=re.S)
            if n != 1:
                return None
    for key, f in base_funcs.items():
        if key.split(":")[-1] in ("lag", "chlag", "agree"):   # unchanged kernels
            cg.add(f)
    with tempfile.TemporaryDirectory() as d:
        cg.generate(d + "/")
        text = (Path(d) / f"{unit}_kernels.c").read_text()
    text = codegen._internal_helpers_static(text)
    if force_inline:
        text = re.sub(r"^static int (casadi_f\d+)\(",
                      r"static inline __attribute__((always_inline)) int \1(", text, flags=re.M)
    files[f"{unit}_kernels.inc"] = text
    if force_inline:
        magcal = magcal.replace("#define CASADI_SYMBOL_EXPORT static inline\n",
                                "#define CASADI_SYMBOL_EXPORT static inline "
                                "__attribute__((always_inline))\n", 1)
    marker = f'#include "{unit}_kernels.inc"'
    magcal = magcal.replace(marker, marker + "\n\n/* prepared coefficients (bench_fold) */\n"
                            + "\n".join(consts), 1)
    files[f"{unit}_magcal.c"] = magcal
    return files


# ---- the float32 reference of a variant -----------------------------------------------


@contextmanager
def reference_kernel(cs, which):
    """chain.reference_sensor with its kernel replaced by the variant's arithmetic
    (folding in float32 on the table's values, then the folded kernel)."""
    orig = chain.sensor_kernel
    if which == "none":     # the chain as generated: the reference as it is
        yield
        return

    def kernel(spec, s, raw, temp_C, coil_A, c, u, half, set_only=False, channels=(),
               rate_dps=()):
        if which == "band":
            lo, hi = u.scalar("field_min_nT"), u.scalar("field_max_nT")
            return _band_kernel(spec, s, raw, temp_C, coil_A, c, u, half, set_only,
                                channels, rate_dps, lo * lo, hi * hi, base=orig)
        f = _fold(spec, s, c, u, half, set_only, which)
        return _folded_out(spec, s, raw, temp_C, coil_A, f, half, set_only, channels,
                           rate_dps)
    chain.sensor_kernel = kernel
    try:
        yield
    finally:
        chain.sensor_kernel = orig


def check_bits(cs, arm, which, n=2000, seed=11):
    """Compare the variant on the target with its float32 reference, bit for bit."""
    rng = np.random.default_rng(seed)
    spec = cs.spec
    calls, refs = [], []
    with reference_kernel(cs, which):
        for s in spec.unit.sensors:
            c = cs.sensors[s.name]
            raw, temp, coil = random_inputs(rng, s, n, len(spec.coils),
                                            (float(c["t_min_C"]), float(c["t_max_C"])))
            calls.append(("correct", s.name, raw, temp, coil))
            refs.append(chain.reference_sensor(spec, s, cs.flat_sensor(s.name),
                                               cs.flat_unit(), raw, temp, coil))
            if s.set_reset:
                off = refs[-1]["offset_counts"]
                calls.append(("correct_set", s.name, raw[:, :3], temp, off, coil))
                refs.append(chain.reference_sensor(spec, s, cs.flat_sensor(s.name),
                                                   cs.flat_unit(), raw[:, :3], temp, coil,
                                                   set_only=True, offset_counts=off))
    got = arm.run(calls)
    bad = []
    for call, g, r in zip(calls, got, refs):
        for key in r:
            if key in g and np.ascontiguousarray(g[key]).tobytes() != \
                    np.ascontiguousarray(r[key]).tobytes():
                bad.append(f"{call[0]} {call[1]} {key}")
    return sum(len(c[2]) for c in calls), bad


def wrapper_cut(magcal: str) -> str | None:
    """The +wrap cut applied to `<unit>_magcal.c`: each sensor wrapper copies the aux
    vectors it reads into locals (in the probe's `if (aux != 0)` block) and passes those to
    its kernel. None when the wrapper is not laid out as expected."""
    parts = re.split(r"(?m)^(?=uint\d+_t \w+\()", magcal)
    out, n_done = [], 0
    for part in parts:
        names = sorted(set(re.findall(r"finite_probe \+= aux->(\w+)\[\d+\]", part)))
        for name in names:
            size = 1 + max(int(k) for k in re.findall(rf"aux->{name}\[(\d+)\]", part))
            real = re.search(r"const (\w+_real_t) \*c", part).group(1)
            part = part.replace("    unsigned int status = 0u;\n",
                                f"    unsigned int status = 0u;\n    {real} {name}[{size}];\n",
                                1)
            part = re.sub(rf"finite_probe \+= aux->{name}\[(\d+)\] - aux->{name}\[\d+\];",
                          rf"{name}[\1] = aux->{name}[\1];\n        "
                          rf"finite_probe += {name}[\1] - {name}[\1];", part)
            part, k = re.subn(rf"= \(aux != 0\) \? aux->{name} : 0;",
                              rf"= (aux != 0) ? {name} : 0;", part)
            if k == 0:
                return None
            n_done += 1
        out.append(part)
    return "".join(out) if n_done else None


def nonnull_cut(magcal: str) -> str | None:
    """The +nn cut: res[k] = out->X becomes a local X_out copied to out->X after the
    kernel call. None when the wrapper is not laid out as expected."""
    parts = re.split(r"(?m)^(?=uint\d+_t \w+\()", magcal)
    out, n_done = [], 0
    for part in parts:
        names = re.findall(r"res\[\d+\] = out->(\w+);", part)
        if names:
            real = re.search(r"const (\w+_real_t) \*c", part).group(1)
            decl = "".join(f"    {real} {n}_out[3];\n" for n in names)
            copy = "".join(f"    {n2}\n" for n in names for n2 in
                           (f"out->{n}[{k}] = {n}_out[{k}];" for k in range(3)))
            part = part.replace("    unsigned int status = 0u;\n",
                                "    unsigned int status = 0u;\n" + decl, 1)
            for n in names:
                part = part.replace(f"= out->{n};", f"= {n}_out;")
            part, k = re.subn(r"(    \(void\)\w+_kernel\(arg, res, 0, 0, 0\);\n)",
                              lambda m: m.group(1) + copy, part, count=1)
            if k != 1:
                return None
            n_done += 1
        out.append(part)
    return "".join(out) if n_done else None


CUTS = {"wrap": lambda m: wrapper_cut(m), "nn": lambda m: nonnull_cut(m)}


def build_variant(cs, which):
    """(sources, fold subset) of a variant name '<fold>[+wrap][_asis]'."""
    asis = which.endswith("_asis")
    fold, _, wrap = which.replace("_asis", "").partition("+")
    files = codegen.render(cs) if fold == "none" else \
        variant_sources(cs, fold, force_inline=not asis)
    if files is not None and wrap:
        name = f"{cs.unit.id}_magcal.c"
        cut = CUTS[wrap](files[name])
        files = None if cut is None else {**files, name: cut}
    return files, fold


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("coeffs", nargs="?", default=str(EXAMPLE))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args(argv)
    if missing_tools():
        print("bench_fold: missing " + ", ".join(missing_tools()), file=sys.stderr)
        return 2
    cs = CoefficientSet.load(args.coeffs)
    base = measure(cs)
    rows = {e.entry.fn: {"base": e.nominal, "bound": e.bound["flops"],
                         "per_call": e.bound["kernel_per_call"]}
            for e in base["entries"] if e.entry.kind != "select"}
    for which in args.variants.split(","):
        files, fold = build_variant(cs, which)
        if files is None:
            print(f"{which}: the wrapper is not laid out as expected; not measured")
            continue
        arm = ArmUnit(cs, sources=files)
        n, bad = check_bits(cs, arm, fold)
        if bad:
            print(f"{which}: C and float32 reference differ ({', '.join(bad)}); not reported")
            continue
        print(f"{which}: {n} samples bit-identical to its float32 reference")
        mv = measure(cs, arm)
        for e in mv["entries"]:
            if e.entry.fn in rows:
                rows[e.entry.fn][which] = e.nominal
    done = [w for w in args.variants.split(",") if all(w in r for r in rows.values())]
    head = f"{'entry point':28s} {'bound':>5s} {'per call':>8s} {'base':>5s}" + "".join(
        f" {w:>6s} {'saved':>5s}" for w in done) + "  ratio to bound: base" + "".join(
        f" / {w}" for w in done)
    print(f"unit {cs.unit.id}: instructions per call, nominal path, Cortex-M4F (QEMU)")
    print(head)
    for fn, r in rows.items():
        line = f"{fn:28s} {r['bound']:5d} {r['per_call']:8d} {r['base']:5d}" + "".join(
            f" {r[w]:6d} {r['base'] - r[w]:5d}" for w in done)
        line += f"  {r['base'] / r['bound']:.2f}" + "".join(
            f" / {r[w] / r['bound']:.2f}" for w in done)
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
