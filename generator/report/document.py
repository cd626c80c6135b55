"""The human report as a document: Markdown and the same in HTML, figures as PNG beside them.

Sections are plain data (title, paragraphs, tables, figures) so every verb adds its own.
The rule: every number drawn in a figure is also in a table of the same section. A
figure names the tables that carry its numbers (by default all the section's tables);
the writers number tables and figures and print the link ("Numbers: Table 4"), the HTML
carries it as data-tables on the <figure>, and Report.problems() lists any figure
without a table or whose file is missing.
"""

from __future__ import annotations

import html
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from generator import __version__


COLLAPSE_ROWS = 30     # a longer table is collapsed (<details>): the page stays readable


@dataclass
class Table:
    header: list
    rows: list
    caption: str = ""

    @property
    def collapsed(self) -> bool:
        return len(self.rows) > COLLAPSE_ROWS


@dataclass
class Section:
    title: str
    paragraphs: list = field(default_factory=list)
    tables: list = field(default_factory=list)
    # (relative png path, caption) or (path, caption, [indices into this section's tables])
    figures: list = field(default_factory=list)


def _fig_parts(fig, section):
    path, caption = fig[0], fig[1]
    refs = list(fig[2]) if len(fig) > 2 and fig[2] is not None else list(
        range(len(section.tables)))
    return str(path), caption, refs


@dataclass
class Report:
    title: str
    sections: list = field(default_factory=list)

    def add(self, section: Section) -> Section:
        self.sections.append(section)
        return section

    def extend(self, sections) -> None:
        for s in sections:
            self.add(s)

    # ---- numbering ---------------------------------------------------------------------
    def _numbers(self):
        """[(section, [table numbers], [(figure number, path, caption, [table numbers])])]."""
        out, nt, nf = [], 0, 0
        for s in self.sections:
            tnums = []
            for _ in s.tables:
                nt += 1
                tnums.append(nt)
            figs = []
            for f in s.figures:
                nf += 1
                path, caption, refs = _fig_parts(f, s)
                figs.append((nf, path, caption, [tnums[i] for i in refs if 0 <= i < len(tnums)]))
            out.append((s, tnums, figs))
        return out

    def problems(self, out_dir=None) -> list:
        """Figures without a table of their numbers, and (given out_dir) missing files."""
        probs = []
        for s, tnums, figs in self._numbers():
            for nf, path, caption, refs in figs:
                if not refs:
                    probs.append(f"section '{s.title}': figure {nf} ({path}) has no table "
                                 "with its numbers")
                if out_dir is not None:
                    p = Path(out_dir) / path
                    if not p.is_file() or p.stat().st_size == 0:
                        probs.append(f"section '{s.title}': figure file {p} missing or empty")
        return probs

    # ---- writers -----------------------------------------------------------------------
    def markdown(self) -> str:
        out = [f"# {self.title}", "", f"_magcal {__version__}_", ""]
        for s, tnums, figs in self._numbers():
            out += [f"## {s.title}", ""]
            for p in s.paragraphs:
                out += [p, ""]
            for nf, path, caption, refs in figs:
                link = _refs_text(refs, caption)
                out += [f"![Figure {nf}]({path})", "", f"_Figure {nf}. {caption}{link}_", ""]
            for t, n in zip(s.tables, tnums):
                cap = f"Table {n}.{(' ' + t.caption) if t.caption else ''}"
                if t.collapsed:
                    out += [f"<details><summary>{cap} ({len(t.rows)} rows)</summary>", ""]
                else:
                    out += [f"**{cap}**", ""]
                out.append("| " + " | ".join(_md(h) for h in t.header) + " |")
                out.append("|" + "---|" * len(t.header))
                for r in t.rows:
                    out.append("| " + " | ".join(_md(_cell(v)) for v in r) + " |")
                out.append("")
                if t.collapsed:
                    out += ["</details>", ""]
        return "\n".join(out) + "\n"

    def html(self) -> str:
        e = html.escape
        out = ["<!DOCTYPE html>", "<html lang=\"en\"><head><meta charset=\"utf-8\">",
               f"<title>{e(self.title)}</title>",
               "<style>body{font-family:sans-serif;max-width:78em;margin:2em auto;padding:0 1em;"
               "color:#222}table{border-collapse:collapse;margin:0.6em 0 1.4em 0;font-size:90%}"
               "td,th{border:1px solid #bbb;padding:2px 7px;text-align:right}"
               "th{background:#eee}td:first-child,th:first-child,td.t{text-align:left}"
               # a number and its sigma stay on one line ('9803 ± 48', not broken at ±)
               "td:not(.t){white-space:nowrap}"
               "details{margin:0.4em 0 1.2em 0}.tw{overflow-x:auto;max-width:100%}caption{font-weight:bold;text-align:left;padding:2px 0}"
               "img{max-width:100%;border:1px solid #ddd}figure{margin:1em 0}"
               "figcaption{font-style:italic;font-size:90%}h2{border-bottom:1px solid #ccc;"
               "margin-top:2em}nav li{margin:0.1em 0}</style></head><body>",
               f"<h1>{e(self.title)}</h1><p><em>magcal {e(__version__)}</em></p>"]
        numbered = self._numbers()
        if len(numbered) > 3:
            out.append("<nav><ul>" + "".join(
                f"<li><a href=\"#sec-{k + 1}\">{e(s.title)}</a></li>"
                for k, (s, _, _) in enumerate(numbered)) + "</ul></nav>")
        for k, (s, tnums, figs) in enumerate(numbered):
            out.append(f"<h2 id=\"sec-{k + 1}\">{e(s.title)}</h2>")
            for p in s.paragraphs:
                out.append(f"<p>{_inline_html(p)}</p>")
            for nf, path, caption, refs in figs:
                data = " ".join(f"table-{n}" for n in refs)
                out.append(f"<figure id=\"figure-{nf}\" data-tables=\"{data}\">"
                           f"<a href=\"{e(path)}\"><img src=\"{e(path)}\" "
                           f"alt=\"Figure {nf}: {e(caption)}\"></a><figcaption>Figure {nf}. "
                           f"{e(caption)}{e(_refs_text(refs, caption))}</figcaption></figure>")
            for t, n in zip(s.tables, tnums):
                if t.collapsed:
                    out.append(f"<details><summary>Table {n}.{(' ' + e(t.caption)) if t.caption else ''}"
                               f" ({len(t.rows)} rows: click to open)</summary>")
                out.append(f"<div class=\"tw\"><table id=\"table-{n}\">")
                out.append(f"<caption>Table {n}.{(' ' + e(t.caption)) if t.caption else ''}"
                           "</caption>")
                out.append("<tr>" + "".join(f"<th>{e(str(h))}</th>" for h in t.header) + "</tr>")
                for r in t.rows:
                    out.append("<tr>" + "".join(_td(_cell(v)) for v in r) + "</tr>")
                out.append("</table></div>")
                if t.collapsed:
                    out.append("</details>")
        out.append("</body></html>")
        return "\n".join(out) + "\n"

    def write(self, out_dir, stem="report") -> Path:
        """Write <stem>.md and <stem>.html into out_dir (figures must already be there);
        returns the HTML path. Warns about figures without tables or files."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        for p in self.problems(out_dir):
            warnings.warn(f"report {self.title!r}: {p}", stacklevel=2)
        (out_dir / f"{stem}.md").write_text(self.markdown(), encoding="utf-8")
        path = out_dir / f"{stem}.html"
        path.write_text(self.html(), encoding="utf-8")
        return path


_NUMBER = re.compile(r"^[-+]?(\d[\d.]*|\.\d+)(e[-+]?\d+)?( ± [\d.e+-]+)?( ?%)?$")


def _td(text) -> str:
    """A cell: numbers right-aligned (the default), text left-aligned and wrapping."""
    if text == "-" or _NUMBER.match(text):
        return f"<td>{html.escape(text)}</td>"
    return f"<td class=\"t\">{html.escape(text)}</td>"


def _refs_text(refs, caption="") -> str:
    if not refs:
        return ""
    lead = " " if caption.rstrip().endswith((".", "!", "?")) else ". "
    return lead + ("Numbers: Table " if len(refs) == 1 else "Numbers: Tables ") + \
        ", ".join(str(n) for n in refs) + "."


def _md(s) -> str:
    return str(s).replace("|", "\\|")


def _inline_html(p) -> str:
    """Escape, then `code` -> <code>."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(p))


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return "-"
        a = abs(float(v))
        if a != 0 and (a < 1e-3 or a >= 1e6):
            return f"{float(v):.4g}"
        return f"{float(v):.4g}" if a < 10 else f"{float(v):.1f}"
    if isinstance(v, (np.integer,)):
        return str(int(v))
    return str(v)


def resolved(value, resolution) -> str:
    """value printed to its resolution: '0' below it (a numerical zero such as -4.5e-15
    is not a measured value), else with the resolution's decimals."""
    v, r = float(value), float(resolution)
    if not np.isfinite(v):
        return "-"
    if abs(v) < r:
        return "0"
    return f"{v:.{max(0, -int(np.floor(np.log10(r))))}f}"


def significant(value, n=3) -> str:
    """value to n significant digits, in plain notation (28077.5 -> '28100', 0.32571 ->
    '0.326'): for a value without a 1-sigma, printed to no more digits than it can carry;
    the caller says why it has no 1-sigma."""
    v = float(value)
    if not np.isfinite(v):
        return "-"
    if v == 0:
        return "0"
    place = n - 1 - int(np.floor(np.log10(abs(v))))
    if place > 0:
        return f"{round(v, place) + 0.0:.{place}f}"
    q = 10.0 ** (-place)
    return f"{round(v / q) * q + 0.0:.0f}"


def pm(value, sigma, digits=None, sign=False) -> str:
    """'value ± sigma' to the sigma's precision: sigma to 2 significant digits, the value
    rounded to the same decimal place (1234.5678 ± 45.6 -> '1235 ± 46', 2696 ± 107 ->
    '2700 ± 110'). digits: a fixed number of decimals instead. Very large or small values
    share one power of ten: '1.234e-06 ± 0.032e-06'. sign: always print the value's sign.
    The one helper for every value with a 1-sigma in the report."""
    v = float(value)
    s = float(sigma) if sigma is not None else float("nan")
    plus = "+" if sign else ""
    if not np.isfinite(v):
        return "-"
    if not np.isfinite(s) or s <= 0:
        return f"{v:{plus}.6g}" + (" ± inf" if s == np.inf else "")
    big = max(abs(v), s)
    if digits is None and (big >= 1e7 or big < 1e-4):
        e = int(np.floor(np.log10(big)))
        mv, ms = pm(v / 10.0 ** e, s / 10.0 ** e, sign=sign).split(" ± ")
        return f"{mv}e{e:+03d} ± {ms}e{e:+03d}"
    place = digits if digits is not None else 1 - int(np.floor(np.log10(s)))
    if place >= 0:
        v = round(v, place) + 0.0        # + 0.0: a value rounded to zero prints '0', not '-0'
        return f"{v:{plus}.{place}f} ± {s:.{place}f}"
    q = 10.0 ** (-place)            # sigma >= 100: round both to its second digit
    return f"{round(v / q) * q + 0.0:{plus}.0f} ± {round(s / q) * q:.0f}"
