"""Is a written report fit to read? The checks a reader would make at a glance, on the
files: every figure shows something, no section says it could not draw, no table is empty.

problems(html_path) -> list of one-line problems (empty: fit to read):

* a figure file missing, or a PNG that is blank: one colour, or (almost) nothing but its
  background (fewer than MIN_INK of its pixels differ from the most common colour);
* a PNG whose text chunk EMPTY_AXES_KEY (written by generator.report.figures._save) names
  axes with nothing drawn in them;
* a "not drawn" / "not computed" message in the page;
* a numpy repr in the page ('np.float64(1.2)', 'array([...])'): a number formatted by its
  repr, not printed to its precision; and numpy's str() of an array ('[1. 2. 3.]', two or
  more numbers between brackets separated by blanks only, or one ending in a bare point,
  '[1.]'), which a citation '[1]', a list '[1, 2]' or an interval '[-20, 55] degC' is not;
* a non-number printed as a value: a table cell that is nan / inf (any case, signed, with
  a unit or a 1-sigma: 'NaN', '-inf', 'inf nT', '1.2 ± inf'), and in the text a nan / inf
  where a number stands: after '=', ':' or '±', or before a unit or '±' ('H: nan
  deg', 'K = inf nT/A'); the words used in prose ('coefficients that are all quiet NaN',
  'fails on NaN') are not values; nan / inf / None in a range ('-20.0..nan degC'), a list
  or tuple ('[-694.0, nan, -1195.0]', '(nan, nan)'), a bracketed sigma ('1.2 (nan)'),
  None as a value ('None nT', '= None', a cell that is None) and numpy's np.True_;
* a table without a data row.
"""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from generator.report.figures import EMPTY_AXES_KEY

# A figure with a drawn curve or bar marks far more than this share of its pixels (a 1 px
# line across a 900 px wide figure of 400 px height is 0.25 %); axes, ticks and labels
# alone (what an empty figure still has) mark about 2-3 %, so this catches a PNG with no
# frame at all; empty axes are caught by EMPTY_AXES_KEY.
MIN_INK = 0.002
FAILURE_TEXT = re.compile(r"not drawn|not computed", re.IGNORECASE)
NUMPY_REPR = re.compile(r"\bnp\.[a-z_]+\d*\(|\barray\(|\bdtype=|\bnp\.(?:True_|False_)")
# numpy's str() of an array: '[1. 2. 3.]', '[ 0.5 -1.  2. ]', '[1 2 3]', '[1.e-03 2.e+00]',
# '[1. ... 9.]', '[[1. 2.] [3. 4.]]' (inner), '[1.]'; not '[1]', '[1.5]', '[1, 2]'
_NUM = r"[-+]?(?:\d+\.?\d*(?:e[-+]?\d+)?|\.\d+|nan|inf)"
NUMPY_STR = re.compile(rf"\[\s*{_NUM}(?:\s+(?:{_NUM}|\.\.\.))+\s*\]"
                       r"|\[\s*[-+]?\d+\.(?:e[-+]?\d+)?\s*\]", re.IGNORECASE)
_NONNUM = r"[-+]?(?:nan|inf(?:inity)?)"
# a unit after a value (case-sensitive: 'A' is ampere, 'a' is a word)
_UNIT = (r"(?-i:(?:nT|µT|uT|mG|G|degC|deg|°C|°|%|cm|mm|m|ppm|A|mA|s|ms|min|h|Hz|K|dB)"
         r"(?:/[A-Za-z]+)?)(?![\w])")
# a table cell that is a non-number: alone, with a unit, or in a value ± sigma
NONNUMBER_CELL = re.compile(rf"{_NONNUM}(?:\s*{_UNIT})?|{_NONNUM}\s*±.*|.*±\s*{_NONNUM}"
                            rf"(?:\s*{_UNIT})?", re.IGNORECASE)
# nan / inf where a number stands in running text (module docstring)
NONNUMBER_TEXT = re.compile(rf"(?:[=:±]\s*){_NONNUM}(?![\w])"
                            rf"|(?<![\w.\-+]){_NONNUM}\s*(?:±|{_UNIT})", re.IGNORECASE)


# nan / inf / None inside the forms a report prints numbers in: a range 'a..b', a list or
# tuple element '[1.0, nan, 2.0]' / '(nan, nan)', a bracketed sigma '1.2 (nan)'; and None
# printed as a value ('None nT', '= None', a cell that is None)
_NONVAL = rf"(?:{_NONNUM}|None)"
NONNUMBER_FORMS = re.compile(
    rf"(?:(?<![\w.]){_NONVAL}\s*\.\.(?!\.)|(?<!\.)\.\.\s*{_NONVAL}(?![\w]))"
    rf"|[\[(,]\s*{_NONVAL}\s*(?=[,\])])"
    rf"|(?-i:None)\s*{_UNIT}|[=:±]\s*(?-i:None)\b", re.IGNORECASE)
NONE_CELL = re.compile(rf"None(?:\s*{_UNIT})?")


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.tables, self.text = [], [], []
        self.cells, self.prose = [], []        # table cells' text; the text outside them
        self._in_table = None
        self._cell = False
        self._caption = False
        self._td = None                        # the text of the open td / th

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src"))
        elif tag == "table":
            self._in_table = {"id": a.get("id"), "rows": 0, "caption": ""}
            self.tables.append(self._in_table)
        elif tag == "td" and self._in_table is not None and not self._cell:
            self._cell = True
        if tag in ("td", "th"):
            self._td = []
        elif tag == "caption":
            self._caption = True

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._td is not None:
            self.cells.append("".join(self._td).strip())
            self._td = None
        if tag == "tr" and self._in_table is not None and self._cell:
            self._in_table["rows"] += 1
            self._cell = False
        elif tag == "table":
            self._in_table = None
        elif tag == "caption":
            self._caption = False

    def handle_data(self, data):
        self.text.append(data)
        (self._td if self._td is not None else self.prose).append(data)
        if self._in_table is not None and self._caption:
            self._in_table["caption"] += data


def png_problems(path) -> list:
    """A PNG's problems: missing, blank, or axes left empty (module docstring)."""
    from PIL import Image

    p = Path(path)
    if not p.is_file() or p.stat().st_size == 0:
        return [f"{p.name}: missing or empty file"]
    with Image.open(p) as im:
        empty = (getattr(im, "text", {}) or {}).get(EMPTY_AXES_KEY, "")
        rgb = np.asarray(im.convert("RGB"))
    out = []
    flat = rgb.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    ink = 1.0 - counts.max() / len(flat)
    if len(colours) == 1:
        out.append(f"{p.name}: blank (one colour)")
    elif ink < MIN_INK:
        out.append(f"{p.name}: nearly blank ({100 * ink:.2f} % of pixels drawn)")
    if empty:
        out.append(f"{p.name}: axes with nothing drawn: {empty}")
    return out


def problems(html_path) -> list:
    """Every problem of the report at html_path (module docstring)."""
    html_path = Path(html_path)
    page = _Page()
    page.feed(html_path.read_text(encoding="utf-8"))
    out = []
    for src in page.images:
        out += png_problems(html_path.parent / src)
    for t in page.tables:
        if t["rows"] == 0:
            out.append(f"{t['id'] or 'a table'}: no data row ({t['caption'].strip()[:60]})")
    text = " ".join(page.text)
    for m in FAILURE_TEXT.finditer(text):
        out.append("page says: " + text[max(0, m.start() - 40):m.end() + 60].strip())
    for m in NUMPY_REPR.finditer(text):
        out.append("numpy repr in the page: " + text[max(0, m.start() - 40):m.end() + 40].strip())
    for m in NUMPY_STR.finditer(text):
        out.append("numpy array printed in the page: "
                   + text[max(0, m.start() - 40):m.end() + 40].strip())
    return out + nonnumber_problems(page.cells, page.prose)


def nonnumber_problems(cells, prose) -> list:
    """nan / inf printed as a value: in table cells (the cell itself, or where a number
    stands in a longer cell) and in the text outside tables (module docstring)."""
    out = []
    for c in cells:
        if (NONNUMBER_CELL.fullmatch(c) or NONE_CELL.fullmatch(c.strip())
                or NONNUMBER_TEXT.search(c) or NONNUMBER_FORMS.search(c)):
            out.append(f"non-number in a table cell: {c[:80]!r}")
    text = " ".join(prose)
    for pattern in (NONNUMBER_TEXT, NONNUMBER_FORMS):
        for m in pattern.finditer(text):
            out.append("non-number in the page: "
                       + text[max(0, m.start() - 40):m.end() + 40].strip())
    return out
