"""The human report of a run: Markdown and the same in HTML, figures as PNG beside them.

Sections are plain data (title, paragraphs, tables, figures) so every verb adds its own
and every number shown in a figure is also in a table.
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__


@dataclass
class Table:
    header: list
    rows: list
    caption: str = ""


@dataclass
class Section:
    title: str
    paragraphs: list = field(default_factory=list)
    tables: list = field(default_factory=list)
    figures: list = field(default_factory=list)   # (relative png path, caption)


@dataclass
class Report:
    title: str
    sections: list = field(default_factory=list)

    def add(self, section: Section) -> Section:
        self.sections.append(section)
        return section

    # ---- writers -----------------------------------------------------------------------
    def markdown(self) -> str:
        out = [f"# {self.title}", "", f"_magcal {__version__}_", ""]
        for s in self.sections:
            out += [f"## {s.title}", ""]
            for p in s.paragraphs:
                out += [p, ""]
            for t in s.tables:
                if t.caption:
                    out += [f"**{t.caption}**", ""]
                out.append("| " + " | ".join(map(str, t.header)) + " |")
                out.append("|" + "---|" * len(t.header))
                for r in t.rows:
                    out.append("| " + " | ".join(_cell(v) for v in r) + " |")
                out.append("")
            for path, caption in s.figures:
                out += [f"![{caption}]({path})", "", f"_{caption}_", ""]
        return "\n".join(out) + "\n"

    def html(self) -> str:
        e = html.escape
        out = ["<!DOCTYPE html>", "<html lang=\"en\"><head><meta charset=\"utf-8\">",
               f"<title>{e(self.title)}</title>",
               "<style>body{font-family:sans-serif;max-width:70em;margin:2em auto;padding:0 1em}"
               "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;"
               "padding:2px 8px;text-align:right}th{background:#eee}caption{font-weight:bold;"
               "text-align:left}img{max-width:100%}figure{margin:1em 0}</style></head><body>",
               f"<h1>{e(self.title)}</h1><p><em>magcal {e(__version__)}</em></p>"]
        for s in self.sections:
            out.append(f"<h2>{e(s.title)}</h2>")
            for p in s.paragraphs:
                out.append(f"<p>{e(p)}</p>")
            for t in s.tables:
                out.append("<table>")
                if t.caption:
                    out.append(f"<caption>{e(t.caption)}</caption>")
                out.append("<tr>" + "".join(f"<th>{e(str(h))}</th>" for h in t.header) + "</tr>")
                for r in t.rows:
                    out.append("<tr>" + "".join(f"<td>{e(_cell(v))}</td>" for v in r) + "</tr>")
                out.append("</table>")
            for path, caption in s.figures:
                out.append(f"<figure><img src=\"{e(path)}\" alt=\"{e(caption)}\">"
                           f"<figcaption>{e(caption)}</figcaption></figure>")
        out.append("</body></html>")
        return "\n".join(out) + "\n"

    def write(self, out_dir, stem="report") -> Path:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / f"{stem}.md").write_text(self.markdown())
        path = out_dir / f"{stem}.html"
        path.write_text(self.html())
        return path


def _cell(v) -> str:
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return "-"
        a = abs(float(v))
        if a != 0 and (a < 1e-3 or a >= 1e6):
            return f"{float(v):.4g}"
        return f"{float(v):.4g}" if a < 10 else f"{float(v):.1f}"
    return str(v)


# ---- the fit report ------------------------------------------------------------------------


def fit_sections(cs) -> list:
    """Per-sensor summary of a fit: method, range, residuals, coefficients at t_ref."""
    rows = []
    info = cs.fit_info.get("sensors", {})
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        st = info.get(s.name, {}).get("stats", {}) or {}
        rows.append([
            s.name, s.part, s.frame, info.get(s.name, {}).get("method", ""),
            f"{float(v['t_min_C']):.1f} .. {float(v['t_max_C']):.1f}",
            st.get("n_samples", st.get("samples", "")),
            _first(st, "rms_norm_nT", "rms_nT", "fit_rms_nT"),
            _first(st, "heldout_rms_nT", "holdout_rms_nT"),
        ])
    summary = Section("Fit summary", [
        "Calibration B = M(T)(B~ - b(T)) per sensor, cubic in temperature (seed 000, eq. 5-7). "
        "Temperatures outside the calibrated range are clamped and flagged by the flight code."],
        [Table(["sensor", "part", "frame", "method", "calibrated range degC", "samples",
                "residual RMS nT", "held-out RMS nT"], rows)])
    coef = Section("Coefficients at the reference temperature")
    for s in cs.unit.sensors:
        v = cs.sensors[s.name]
        u = cs.uncertainty.get(s.name, {})
        b0 = np.asarray(v["b_poly_nT"])[0]
        M0 = np.asarray(v["M_poly"])[0]
        bs = np.asarray(u["b_poly_nT"])[0] if "b_poly_nT" in u else np.full(3, np.nan)
        Ms = np.asarray(u["M_poly"])[0] if "M_poly" in u else np.full((3, 3), np.nan)
        rows = [[ax, f"{b0[i]:.1f} ± {bs[i]:.1f}"] + [f"{M0[i, j]:.5f} ± {Ms[i, j]:.5f}"
                                                      for j in range(3)]
                for i, ax in enumerate("xyz")]
        coef.tables.append(Table(["axis", "b nT", "M x", "M y", "M z"], rows,
                                 f"{s.name} at {float(v['t_ref_C']):.1f} degC (1-sigma)"))
    return [summary, coef]


def _first(d, *keys):
    for k in keys:
        if k in d and d[k] is not None:
            return d[k]
    return ""


def write_fit_report(cs, out_dir, data_paths=(), progress=None) -> Path:
    rep = Report(f"magcal fit: unit {cs.unit.id}")
    rep.add(Section("Inputs", [f"Telemetry: {', '.join(str(p) for p in data_paths)}."]))
    for s in fit_sections(cs):
        rep.add(s)
    return rep.write(out_dir)
