"""Flight C for one unit: CasADi kernels from the chain definition, wrapped by Jinja2.

Backends are data (the list TEMPLATES below, as acados keeps its template list): each
entry names a template in ``templates/`` and the file it renders. The arithmetic comes
from CasADi's CodeGenerator only; the templates add the fixed-size API, the coefficient
layout, the compiled-in defaults and the wrapper logic (clamp, flags), all driven by the
same ChainSpec that drives the Python reference.

Output is deterministic: same coefficients, same bytes.
"""

from __future__ import annotations

import importlib.resources
import re
import tempfile
from pathlib import Path

import casadi as ca
import jinja2
import numpy as np

from generator import __version__
from generator.flight.chain import (SELECT_REASONS, STATUS_BITS, STATUS_INFO_MASK, ChainSpec,
                                    CoeffView, agreement_kernel,
                                    folded_sensor_kernel, input_scale_nT, is_physical,
                                    lag_kernel, n_prepared, prepare_sensor, prepared_leaves,
                                    prepared_view, range_nT, saturation_limit, fold_shape)
from generator.errors import InputError
from generator.flight.c_syntax import c_literal
from generator.flight.coeffs import CoefficientSet
from generator.flight.tables import table_context


def _template_dir() -> Path:
    """The Jinja2 templates: shipped inside the package as package data (a wheel install),
    else the top-level ``templates/`` of a source checkout (an editable install)."""
    shipped = importlib.resources.files("generator") / "templates"
    if shipped.is_dir():
        return Path(str(shipped))
    return Path(__file__).resolve().parents[2] / "templates"


TEMPLATE_DIR = _template_dir()

# (template, output file name pattern); {unit} is the unit id.
TEMPLATES = (
    ("magcal.h.j2", "{unit}_magcal.h"),
    ("magcal.c.j2", "{unit}_magcal.c"),
    ("coeffs_default.c.j2", "{unit}_coeffs_default.c"),
    ("table.h.j2", "{unit}_table.h"),
    ("table.c.j2", "{unit}_table.c"),
)
TABLE_TEMPLATES = tuple(t for t in TEMPLATES if t[0].startswith("table."))


def versions() -> dict:
    return {"magcal": __version__, "casadi": ca.__version__, "jinja2": jinja2.__version__}


def kernel_name(spec: ChainSpec, sensor, set_only=False) -> str:
    return f"{spec.unit.id}_{sensor.name}_{'set_' if set_only else ''}kernel"


def build_kernel(spec: ChainSpec, sensor, set_only=False) -> ca.Function:
    """The CasADi Function of one sensor's chain: `chain.folded_sensor_kernel` on the
    kernel's prepared coefficients (`chain.prepared_view`).

    Arguments: the chain inputs, then the prepared vector (`<unit>_table_prepare`)."""
    ins = spec.sensor_inputs(sensor, set_only)
    sym = {i.name: ca.SX.sym(i.name, i.size) for i in ins}
    p_sym = ca.SX.sym("prepared", n_prepared(spec, sensor, set_only))
    f = prepared_view(spec, sensor, [p_sym[k] for k in range(p_sym.numel())], set_only)

    def elems(name):
        return [sym[name][k] for k in range(sym[name].numel())] if name in sym else []

    temp = sym["temp_C"][0] if "temp_C" in sym else None   # None: a sensor with no temperature
    out = folded_sensor_kernel(spec, sensor, elems("raw_counts"), temp, elems("coil_A"),
                               f, ca.SX(0.5), set_only=set_only, channels=elems("channels"),
                               rate_dps=elems("rate_dps"))
    outs = spec.sensor_outputs(sensor, set_only)
    return ca.Function(kernel_name(spec, sensor, set_only),
                       [sym[i.name] for i in ins] + [p_sym],
                       [ca.vertcat(*out[o.name]) for o in outs],
                       [i.name for i in ins] + ["prepared"], [o.name for o in outs])


def build_lag_kernel(spec: ChainSpec, sensor) -> ca.Function:
    """The element-temperature update of a sensor with thermal lag, from `chain.lag_kernel`."""
    temp, el, dt = ca.SX.sym("temp_C"), ca.SX.sym("temp_el_C"), ca.SX.sym("dt_s")
    c_sym = ca.SX.sym("coeffs", spec.n_sensor_coeffs(sensor))
    c = CoeffView([c_sym[k] for k in range(c_sym.numel())], spec.sensor_blocks(sensor))
    return ca.Function(f"{spec.unit.id}_{sensor.name}_lag_kernel", [temp, el, dt, c_sym],
                       [lag_kernel(temp, el, dt, c.scalar("lag_tau_s"))],
                       ["temp_C", "temp_el_C", "dt_s", "coeffs"], ["temp_el_next_C"])


def build_channel_lag_kernel(spec: ChainSpec, sensor) -> ca.Function:
    """The lagged channels' filter update of a sensor (option lagged_channels), from
    `chain.lag_kernel`, one time constant per channel."""
    nl = len(spec.opts(sensor).lagged_channels)
    ch, el, dt = ca.SX.sym("channel", nl), ca.SX.sym("channel_el", nl), ca.SX.sym("dt_s")
    c_sym = ca.SX.sym("coeffs", spec.n_sensor_coeffs(sensor))
    c = CoeffView([c_sym[k] for k in range(c_sym.numel())], spec.sensor_blocks(sensor))
    tau = c.get("lag_channel_tau_s")
    nxt = [lag_kernel(ch[j], el[j], dt, tau[j]) for j in range(nl)]
    return ca.Function(f"{spec.unit.id}_{sensor.name}_chlag_kernel", [ch, el, dt, c_sym],
                       [ca.vertcat(*nxt)], ["channel", "channel_el", "dt_s", "coeffs"],
                       ["channel_el_next"])


def build_agreement_kernel(spec: ChainSpec) -> ca.Function:
    """Pairwise agreement margins of all sensors, from `chain.agreement_kernel`."""
    S = len(spec.unit.sensors)
    fields = ca.SX.sym("field_body_nT", 3 * S)
    agree = ca.SX.sym("agree_nT", S)
    margins = agreement_kernel([[fields[3 * i + k] for k in range(3)] for i in range(S)],
                               [agree[i] for i in range(S)])
    return ca.Function(f"{spec.unit.id}_agree_kernel", [fields, agree],
                       [ca.vertcat(*margins) if margins else ca.SX(0, 1)],
                       ["field_body_nT", "agree_nT"], ["margin_nT2"])


def casadi_sources(spec: ChainSpec) -> tuple[str, dict, dict]:
    """(kernels text, {kernel: (sz_arg, sz_res)}, {key: Function}) from CasADi's
    CodeGenerator. The text is included by `<unit>_magcal.c` (one translation unit, so
    the compiler sees that no kernel argument is ever null and inlines the kernels);
    every kernel must run in registers and locals only (no iw/w work arrays)."""
    name = f"{spec.unit.id}_kernels"
    real = "float" if spec.unit.float_type == "float32" else "double"
    cg = ca.CodeGenerator(name, {"casadi_real": real, "casadi_int": "int",
                                 "with_header": True, "with_mem": False})
    funcs = {}
    for s in spec.unit.sensors:
        funcs[s.name] = build_kernel(spec, s)
        cg.add(funcs[s.name])
        if s.set_reset:
            funcs[s.name + ":set"] = build_kernel(spec, s, set_only=True)
            cg.add(funcs[s.name + ":set"])
        if spec.opts(s).thermal_lag:
            funcs[s.name + ":lag"] = build_lag_kernel(spec, s)
            cg.add(funcs[s.name + ":lag"])
        if spec.opts(s).lagged_channels:
            funcs[s.name + ":chlag"] = build_channel_lag_kernel(spec, s)
            cg.add(funcs[s.name + ":chlag"])
    funcs[":agree"] = build_agreement_kernel(spec)
    cg.add(funcs[":agree"])
    with tempfile.TemporaryDirectory() as d:
        cg.generate(d + "/")
        c_text = (Path(d) / f"{name}.c").read_text()
        h_text = (Path(d) / f"{name}.h").read_text()
    sizes = {}
    for f in funcs.values():
        k = f.name()
        got = {m: int(re.search(rf"#define {k}_SZ_{m} (\d+)", h_text).group(1))
               for m in ("ARG", "RES", "IW", "W")}
        if got["IW"] or got["W"]:
            raise RuntimeError(f"{k} needs CasADi work arrays {got}: the wrappers pass none")
        sizes[k] = (got["ARG"], got["RES"])
    return c_text, sizes, funcs



def _internal_helpers_static(c_text: str) -> str:
    """CasADi defines its small helpers (casadi_sq, casadi_fabs, ...) with external linkage;
    in the wrapper's translation unit they must be static like everything else of it."""
    c_text = re.sub(r"^(casadi_real casadi_\w+\()", r"static \1", c_text, flags=re.M)
    # every kernel body is inlined into its one caller (CASADI_KERNEL_INLINE, magcal.c):
    # once the axis signs are data, kernels of sensors that differ only in their signs are
    # the same code, and GCC's identical-code folding would merge them into one function
    # called with its arguments in memory (measured: 40+ instructions more per call)
    return re.sub(r"^static int (casadi_f\d+)\(", r"static CASADI_KERNEL_INLINE int \1(",
                  c_text, flags=re.M)


def _macro(name: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in name).upper()


# C expression of each kernel input, by chain input name (the wrapper's locals and aux).
_ARG_EXPR = {
    "raw_counts": "counts",
    "temp_C": "&temp_C",
    "coil_A": "(aux != 0) ? aux->coil_A : 0",
    "channels": "chan",
    "rate_dps": "(aux != 0) ? aux->rate_dps : 0",
}


def _kernel_args(spec: ChainSpec, sensor, set_only) -> list:
    """The wrapper's argument expressions of a kernel, in the kernel's input order."""
    return [_ARG_EXPR[i.name] for i in spec.sensor_inputs(sensor, set_only)] + ["p"]


def _raw_fields(sensor) -> dict:
    """Names of the raw struct's reading fields: {'plain'|'set'|'reset': name}."""
    base = f"field_{sensor.input}" if is_physical(sensor) else "counts"
    if sensor.set_reset:
        return {"set": f"set_{base}", "reset": f"reset_{base}"}
    return {"plain": base}


def boom_alignment_note(cs: CoefficientSet) -> str | None:
    """Why H is the identity, when it was not fitted (a boom sensor with no body-frame
    reference): the generated header and the report say so."""
    note = cs.fit_info.get("boom_alignment")
    return note if isinstance(note, str) else None


def _literals(values, float_type, where, unit) -> list:
    """C literals of coefficient values; a value with no literal in the flight type (NaN,
    inf, beyond float32) is bad input naming the coefficient (exit 2), not a crash."""
    try:
        return [c_literal(v, float_type) for v in values]
    except ValueError as e:
        raise InputError(unit.path, f"{where}: {e}: it cannot be written into the flight "
                                    "C") from None


def _prepared_block(cs: CoefficientSet, sensor, set_only) -> dict:
    """The compiled-in defaults' prepared vector of one kernel (chain.prepare_sensor, the
    values `<unit>_table_prepare` computes from `<unit>_coeffs_default`): size and
    initializer rows. A default that folds to a non-finite value (a broken default that
    `<unit>_table_init` refuses) is written as NAN / INFINITY (math.h)."""
    spec = cs.spec
    vals = prepare_sensor(spec, sensor, cs.flat_sensor(sensor.name), cs.flat_unit(),
                          set_only=set_only)
    lits = [c_literal(float(v), spec.unit.float_type) if np.isfinite(v) else
            "NAN" if np.isnan(v) else ("INFINITY" if v > 0 else "-INFINITY") for v in vals]
    return {"size": len(lits), "lines": _lines(lits), **_fold_layout(spec, sensor, set_only)}


def _fold_layout(spec: ChainSpec, sensor, set_only) -> dict:
    """What `<unit>_table_prepare` (templates/magcal.c.j2) needs to compute one kernel's
    prepared vector in chain.fold_sensor_coeffs' order: the offset of each of its entries
    ('at'), the number of polynomial terms, the axis scale (a literal for physical inputs,
    else lsb [x 0.5 for a SET/RESET pair]) and signs, the plain count's zero, H."""
    shape = fold_shape(spec, sensor, set_only)
    at, k = {}, 0
    for key, v in shape.items():
        at[key] = k
        k += len(prepared_leaves(v))
    _, sign = sensor.axis_map()
    pair = sensor.set_reset and not set_only
    ft = spec.unit.float_type
    scale = (c_literal(input_scale_nT(sensor) * (0.5 if pair else 1.0), ft)
             if is_physical(sensor) else None)
    return {"at": at, "n_terms": spec.degree(sensor) + 1, "sign": list(sign),
            "scale_literal": scale, "pair": pair,
            "offset_literal": c_literal(input_scale_nT(sensor), ft)
            if is_physical(sensor) and pair else None,
            "fold_H": sensor.frame == "boom" and not spec.opts(sensor).sr_compensation,
            "n_coils": len(spec.coils), "n_chan": len(spec.opts(sensor).channels),
            "n_chlag": len(spec.opts(sensor).lagged_channels)}


def _lines(literals, per_line=6) -> list:
    """Initializer rows of at most per_line literals, each ending in a comma."""
    return [", ".join(literals[i:i + per_line]) + "," for i in range(0, len(literals), per_line)]


def _env() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
        autoescape=False,
    )


def template_context(cs: CoefficientSet) -> dict:
    spec = cs.spec
    unit = spec.unit
    ft = unit.float_type
    sensors = []
    for s in unit.sensors:
        blocks, k = [], 0
        flat = cs.flat_sensor(s.name)
        for b in spec.sensor_blocks(s):
            vals = flat[k:k + b.size]
            blocks.append({"name": b.name, "macro": b.name.upper(), "offset": k,
                           "shape": b.shape, "size": b.size, "unit": b.unit, "doc": b.doc,
                           "lines": _lines(_literals(vals, ft, f"sensors.{s.name}.{b.name}",
                                                     unit))})
            k += b.size
        sensors.append({
            "index": len(sensors),
            "name": s.name, "NAME": s.name.upper(), "part": s.part, "frame": s.frame,
            "axes": list(s.axes), "set_reset": s.set_reset, "n_coeffs": k, "blocks": blocks,
            "count_min": s.count_min if not is_physical(s) else None,
            "count_max": s.count_max if not is_physical(s) else None,
            "physical": is_physical(s), "input": s.input, "temperature": s.temperature,
            # the raw struct's fields (physical inputs: real numbers, the unit in the name)
            "raw_fields": _raw_fields(s),
            "sat_limit": c_literal(saturation_limit(s), ft) if is_physical(s) else None,
            "full_scale": (f"{saturation_limit(s):.9g} {s.input} ({range_nT(s):.9g} nT)"
                           if is_physical(s) else None),
            # real-valued inputs of the raw struct that the finiteness probe tests: the
            # temperature, then (physical inputs) the readings; a prefix of it for SET-only
            "probe": (["temp_C"] if s.temperature else []) +
                     ([f"counts[{k}]" for k in range(6 if s.set_reset else 3)]
                      if is_physical(s) else []),
            "has_probe": s.temperature or is_physical(s) or bool(
                spec.coils or spec.opts(s).kernel_channels or spec.opts(s).sr_compensation
                or spec.opts(s).thermal_lag),
            "n_raw": 6 if s.set_reset else 3,
            "kernel": kernel_name(spec, s),
            "set_kernel": kernel_name(spec, s, set_only=True),
            "lag_kernel": f"{unit.id}_{s.name}_lag_kernel",
            "kargs": _kernel_args(spec, s, False),
            "set_kargs": _kernel_args(spec, s, True) if s.set_reset else [],
            "has_state": spec.has_state(s),
            "lag": spec.opts(s).thermal_lag,
            "uses_dt": spec.opts(s).thermal_lag or bool(spec.opts(s).lagged_channels),
            "chlag": bool(spec.opts(s).lagged_channels),
            "chlag_kernel": f"{unit.id}_{s.name}_chlag_kernel",
            "n_chan": len(spec.opts(s).channels),
            "n_chlag": len(spec.opts(s).lagged_channels),
            "sr_comp": spec.opts(s).sr_compensation,
            "channel_idx": [spec.aux_channels.index(ch)
                            for ch in spec.opts(s).kernel_channels],
            "outputs": [o.name for o in spec.sensor_outputs(s)],
            # the kernels' prepared coefficients: their layout for <unit>_table_prepare
            # and the defaults' values (chain.prepare_sensor)
            "folded": _prepared_block(cs, s, False),
            "set_folded": _prepared_block(cs, s, True) if s.set_reset else None,
        })
    # An array that ends more than 1020 bytes into its struct is read through its own base
    # pointer (Cortex-M VLDR offsets reach +-1020 bytes). The prepared struct holds each
    # sensor's table coefficients (clamp limits, time constants, agreement tolerance) and
    # then its kernels' prepared vectors.
    real_size = 4 if ft == "float32" else 8
    start = 0
    for s_ctx in sensors:
        start += s_ctx["n_coeffs"] + s_ctx["folded"]["size"] + (
            s_ctx["set_folded"]["size"] if s_ctx["set_folded"] else 0)
        s_ctx["own_base"] = start * real_size > 1020
    ublocks, k = [], 0
    flat_u = cs.flat_unit()
    for b in spec.unit_blocks():
        ublocks.append({"name": b.name, "macro": b.name.upper(), "offset": k, "shape": b.shape,
                        "size": b.size, "unit": b.unit, "doc": b.doc,
                        "lines": _lines(_literals(flat_u[k:k + b.size], ft,
                                                  f"unit_coefficients.{b.name}", unit))})
        k += b.size
    kernels_text, sizes, _ = casadi_sources(spec)
    ctx = {
        "kernels_text": kernels_text,
        "sz": sizes,
        "unit": unit.id,
        "UNIT": unit.id.upper(),
        "real": "float" if ft == "float32" else "double",
        "float_type": ft,
        "versions": versions(),
        "layout_hash": f"0x{spec.layout_hash():08x}",
        "poly_degree": spec.poly_degree,
        "coils": list(spec.coils),
        "n_coils": len(spec.coils),
        "has_aux": spec.has_aux,
        "channels": [{"name": ch, "macro": _macro(ch), "index": k}
                     for k, ch in enumerate(spec.aux_channels)],
        "needs_rate": spec.needs_rate,
        "needs_dt": spec.needs_dt,
        "sensors": sensors,
        "unit_blocks": ublocks,
        "n_unit_coeffs": k,
        "status_bits": sorted(STATUS_BITS.items(), key=lambda kv: kv[1]),
        "status_info_mask": STATUS_INFO_MASK,
        "select_reasons": sorted(SELECT_REASONS.items(), key=lambda kv: kv[1]),
        "fallback_order": list(spec.fallback_order()),
        "boom_note": boom_alignment_note(cs) if spec.has_boom else None,
        "has_boom": spec.has_boom,
        # whether some sensor folds a coupling (coils, channels) in the prepare step
        "prepare_rows": bool(spec.coils) or any(
            spec.opts(s).channels or spec.opts(s).lagged_channels for s in unit.sensors),
        "pairs": [(i, j) for i in range(len(sensors)) for j in range(i + 1, len(sensors))],
    }
    return ctx


PREAMBLE = ("/* DO NOT EDIT: generated by magcal {magcal} (casadi {casadi}, jinja2 {jinja2}).\n"
            " * Regenerate with `magcal generate COEFFS.json -o DIR`; the chain is defined in\n"
            " * generator/flight/chain.py. Unit {unit}, chain layout {layout_hash}. */\n")


def render(cs: CoefficientSet, tables: bool = True) -> dict:
    """{file name: text} of the unit's flight C sources; tables=False: without the uplink
    table's validator (`<unit>_table.h/.c`), which nothing else of the flight C needs."""
    ctx = template_context(cs)
    env = _env()
    files = {}
    for tpl, pattern in TEMPLATES:
        if (tpl, pattern) in TABLE_TEMPLATES:
            if not tables:
                continue
            ctx.setdefault("table", table_context(cs))   # only the table templates read it
        files[pattern.format(unit=ctx["unit"])] = env.get_template(tpl).render(**ctx)
    pre = PREAMBLE.format(unit=ctx["unit"], layout_hash=ctx["layout_hash"], **ctx["versions"])
    files[f"{ctx['unit']}_kernels.inc"] = pre + _internal_helpers_static(ctx["kernels_text"])
    return dict(sorted(files.items()))


def generate(cs: CoefficientSet, out_dir) -> list:
    """Write the unit's flight C into out_dir; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, text in render(cs).items():
        p = out / name
        p.write_text(text)
        paths.append(p)
    return paths
