"""The human report of `magcal trace`: protocol, summary, each effect with its figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.document import Report, Section, Table
from generator.trace.residual import per_sample, quantities
from generator.trace.tracer import (NORM, SensorSamples, SensorTrace, Step, TraceResult,
                                     evidence_sentence, protocol_text, runner_up_text,
                                     unexplained_plot_name)


def _per_sample(S: SensorSamples, r, direction=None):
    """(sample index, value) from residual rows: 3-row kinds projected on `direction`."""
    iv, im, ip = S.idx
    nv, nm = 3 * len(iv), len(im)
    vals = np.empty(S.n)
    if direction is None:
        direction = np.array([1.0, 0.0, 0.0])
    if len(iv):
        vals[iv] = r[:nv].reshape(-1, 3) @ direction
    if len(im):
        vals[im] = r[nv:nv + nm]
    if len(ip):
        vals[ip] = r[nv + nm:].reshape(-1, 3) @ direction
    return vals


def _direction(S, explained):
    iv, im, ip = S.idx
    nv, nm = 3 * len(iv), len(im)
    three = np.concatenate([explained[:nv].reshape(-1, 3), explained[nv + nm:].reshape(-1, 3)])
    if len(three) == 0:
        return np.array([1.0, 0.0, 0.0])
    _, _, Vt = np.linalg.svd(three, full_matrices=False)
    d = Vt[0]
    return d if three.mean(axis=0) @ d >= 0 else -d


def plot_step(name, tr: SensorTrace, st: Step, path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    S = tr.S_eval
    rb = st.model_before.residual(st.model_before.theta[None], S)[0]
    ra = st.model_after.residual(st.model_after.theta[None], S)[0]
    expl = rb - ra
    d = _direction(S, expl)
    vb, va, ve = (_per_sample(S, r, d) for r in (rb, ra, expl))
    o = np.argsort(S.order, kind="stable")
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    k = np.asarray(S.time_s, float)[o]      # the data are in time: a time axis
    ax[0].plot(k, vb[o], ".", ms=2, color="0.6", label=f"before ({st.rms_before_nT:.1f} nT rms)")
    ax[0].plot(k, va[o], ".", ms=2, color="tab:blue", label=f"after ({st.rms_after_nT:.1f} nT rms)")
    ax[0].plot(k, ve[o], "-", lw=1, color="tab:red", label=f"explained by {st.effect.name}")
    ax[0].set_xlabel("time in its file, s (held-out samples)")
    axis_txt = "" if not any(S.kind != NORM) else \
        f" along [{d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f}]"
    ax[0].set_ylabel(f"residual{axis_txt}, nT")
    ax[0].legend(fontsize=7, loc="best")
    ax[0].set_title(f"{name}: {st.effect.label()}", fontsize=9)
    lim = [float(np.min(ve)), float(np.max(ve))]
    ax[1].plot(ve, vb, ".", ms=2, color="0.6", label="before")
    ax[1].plot(ve, va, ".", ms=2, color="tab:blue", label="after")
    ax[1].plot(lim, lim, "-", color="tab:red", lw=1, label="slope 1")
    ax[1].set_xlabel(f"explained by {st.effect.name}, nT")
    ax[1].set_ylabel("residual, nT")
    ax[1].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return str(path)


def plot_unexplained(name, tr: SensorTrace, path) -> str:
    """The residual left above the noise: against time, and against what it follows most."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    S = tr.S_eval
    # the model the residual was judged with (fitted on the fit data only)
    m = tr.steps[-1].model_after if tr.steps else tr.final_model
    r = m.residual(m.theta[None], S)[0]
    v = per_sample(S, r)
    B = m.field(S)
    q = quantities(S, B)
    top = tr.unexplained["correlates"][0]["quantity"] if tr.unexplained["correlates"] else \
        "time_s"
    o = np.argsort(S.order, kind="stable")
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    for k, c in enumerate(("tab:red", "tab:green", "tab:blue")):
        if np.isfinite(v[:, k]).any():
            ax[0].plot(S.time_s[o], v[o, k], ".", ms=2, color=c, label="xyz"[k] if
                       np.isfinite(v[:, 1]).any() else "|B| residual")
            ax[1].plot(q[top], v[:, k], ".", ms=2, color=c)
    fl = tr.noise.get("floor_nT") or 0.0
    for a in ax:
        a.axhline(fl, color="0.5", lw=0.8, ls="--")
        a.axhline(-fl, color="0.5", lw=0.8, ls="--")
        a.set_ylabel("residual, nT")
    ax[0].set_xlabel("time, s (evaluation samples)")
    ax[0].set_title(f"{name}: unexplained, {tr.noise['residual_rms_nT']:.1f} nT rms against "
                    f"a noise floor of {fl:.1f} nT (dashed)", fontsize=9)
    ax[0].legend(fontsize=7, loc="best")
    ax[1].set_xlabel(top)
    ax[1].set_title(f"against what it follows most ({top})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return str(path)


def write_report(res: TraceResult, out: Path) -> Path:
    rep = Report(f"magcal trace: unit {res.unit.id}")
    src = res.sources
    rep.add(Section("Inputs and protocol", [
        f"Data: {', '.join(src['data'])}." + (f" Holdout: {', '.join(src['holdout'])}."
                                              if src["holdout"] else ""),
        f"Baseline: {src['baseline']}. Figures evaluated on: {res.evaluated_on}.",
        *[f"{k.capitalize()}: {v}." for k, v in protocol_text(res.evaluated_on).items()],
        *[f"Note: {n}" for n in res.notes[:20]]]))
    rows = []
    for n, tr in res.traces.items():
        rows.append([n, tr.metric, tr.baseline_rms_nT,
                     ", ".join(st.effect.label() for st in tr.steps) or "none",
                     tr.final_rms_nT])
    for n, why in res.skipped.items():
        rows.append([n, "-", float("nan"), f"skipped: {why}", float("nan")])
    rep.add(Section("Summary", [
        "Held-out RMS of the residual per sensor, before (the baseline structure refitted) "
        "and after the traced effects."],
        [Table(["sensor", "residual", "baseline RMS nT", "effects found", "final RMS nT"],
               rows)]))
    k = 0
    for n, tr in res.traces.items():
        for i, st in enumerate(tr.steps):
            k += 1
            fig = f"trace_{n}_{i + 1}_{st.effect.name}.png"
            plot_step(n, tr, st, out / fig)
            e = st.effect
            cand = [[s.effect.label(), s.dof, 100 * s.rel_rms_gain,
                     f"{s.blocks_improved}/{len(s.block_gain)}", s.z, s.lr,
                     "yes" if s.significant else "; ".join(s.reasons)]
                    for s in st.scores[:8]]
            params = e.describe(st.params, st.model_after)
            paras = [evidence_sentence(n, st),
                     f"Physics: {e.physics}.",
                     "Parameters: " + ", ".join(f"{k_}={_fmt(v)}"
                                                for k_, v in params.items()) + ".",
                     f"Flight form: {e.flight_form}."]
            if st.runner_up is not None:
                paras.append("Runner-up: " + runner_up_text(st) + ".")
            rep.add(Section(f"{n}: {e.label()}", paras, [Table(
                ["candidate", "parameters", "CV RMS gain %", "blocks improved", "z",
                 "likelihood ratio", "significant"], cand,
                f"round {i + 1}: candidates by held-out error")],
                [(fig, f"{n}: held-out residual before and after {e.label()}, and the part "
                       "it explains")]))
    quiet = []
    for n, tr in res.traces.items():
        best = tr.last_scores[0] if tr.last_scores else None
        quiet.append([n, best.effect.label() if best else "-",
                      100 * best.rel_rms_gain if best else float("nan"),
                      tr.stop])
    rep.add(Section("What is left", [
        "The best remaining candidate per sensor and why it was not added."],
        [Table(["sensor", "best remaining candidate", "CV RMS gain %", "stop"], quiet)]))
    for n, tr in res.traces.items():
        if not tr.unexplained:
            continue
        fig = unexplained_plot_name(n)
        plot_unexplained(n, tr, out / fig)
        u = tr.unexplained
        rep.add(Section(f"{n}: unexplained residual", [
            f"{u['residual_rms_nT']:.2f} nT rms is left, {u['rms_above_noise_nT']:.2f} nT "
            f"above the noise floor of {u['noise_floor_nT']:.2f} nT, and no effect of the "
            "catalogue explains it. What it follows most (share of its variance explained "
            "by its mean in quantile bins of the quantity): " +
            ", ".join(f"{c['quantity']} {c['eta2']:.2f}" for c in u["correlates"]) + "."],
            [Table(["quantity", "eta^2"], [[c["quantity"], c["eta2"]] for c in u["correlates"]],
                   "what the residual follows, strongest first")],
            [(fig, f"{n}: the residual left, against time and against "
                       f"{u['correlates'][0]['quantity'] if u['correlates'] else 'time'}")]))
    na = [[n, name, why] for n, tr in res.traces.items() for name, why in tr.not_applicable.items()]
    if na:
        rep.add(Section("Candidates that did not apply", [],
                        [Table(["sensor", "effect", "why"], na)]))
    return rep.write(out, stem="trace_report")


def _fmt(v):
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


