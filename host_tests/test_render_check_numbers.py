"""The render check catches a non-number printed as a value and numpy's str() of an array
(review of issue 19, 19b F7; generator/report/render_check.py), and passes the text a
report legitimately carries: citations '[1]', lists and intervals '[-20, 55] degC', the
word NaN in prose.

The reviewer's case: in a copy of a report, one summary cell replaced by 'nan', 'NaN',
'inf nT' or '[1. 2. 3.]' passed the check.
"""

from __future__ import annotations

import html as _html

import pytest

from generator.report import render_check
from generator.report.document import Report, Section, Table

GOOD_CELL = "12.3 ± 0.4"
PROSE = ("The offset b (seed 000 eq. 5 [1]) over the calibrated range [-20, 55] degC; the "
         "table's fallback coefficients are all quiet NaN: every correction then fails on "
         "NaN and is flagged. A CSV cell nan or inf is refused when read; NaN/inf cells "
         "name their line. Points [5, 15, 30] cm, seed figure 12 [a]. The offset was "
         "[-694.0, 1288.0, -1195.0] nT. Info: the inflight check runs at 10 Hz.")


def _report(tmp_path, cell=GOOD_CELL, paragraph=PROSE):
    rep = Report("t", [Section("Summary", [paragraph], [
        Table(["sensor", "|B| error nT", "note"],
              [["mmc1", cell, "3 NaN cells left out (empty in the file)"],
               ["mmc2", "0.52 ± 0.05", "range [-20, 55] degC"]], "Verdict")])])
    return rep.write(tmp_path)


def _with_cell(tmp_path, text):
    """The written report with the summary cell replaced by text (as the reviewer did on
    a copy of a report: the HTML edited, not the code that writes it)."""
    path = _report(tmp_path)
    page = path.read_text(encoding="utf-8")
    old = f"<td>{_html.escape(GOOD_CELL)}</td>"
    assert page.count(old) == 1
    path.write_text(page.replace(old, f"<td>{_html.escape(text)}</td>"), encoding="utf-8")
    return path


def test_legitimate_text_passes(tmp_path):
    assert render_check.problems(_report(tmp_path)) == []


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-inf", "+inf", "Infinity", "inf nT",
                                  "nan %", "-inf nT/A", "nan ± 0.3", "12.3 ± inf",
                                  "12.3 ± nan nT"])
def test_a_non_number_cell_is_caught(tmp_path, text):
    probs = render_check.problems(_with_cell(tmp_path, text))
    assert len(probs) == 1 and "non-number in a table cell" in probs[0], probs
    assert repr(text) in probs[0]


@pytest.mark.parametrize("text", ["[1. 2. 3.]", "[ 0.5 -1.   2. ]", "[1 2 3]",
                                  "[1.e-03 2.e+00]", "[1. ... 9.]", "[[1. 2.] [3. 4.]]",
                                  "[1.]", "[nan  1.]"])
def test_numpy_array_str_is_caught_in_a_cell_and_in_the_text(tmp_path, text):
    probs = render_check.problems(_with_cell(tmp_path, text))
    assert probs and all("numpy array printed" in p or "non-number" in p for p in probs)
    assert any("numpy array printed" in p for p in probs), probs
    probs = render_check.problems(_report(tmp_path / "p", paragraph=f"b = {text} nT"))
    assert any("numpy array printed" in p for p in probs), probs


@pytest.mark.parametrize("text", ["[1]", "[12]", "[1.5]", "[1, 2, 3]", "[-20, 55]",
                                  "[requirements]", "1.0", "-", "0.33"])
def test_what_is_not_an_array_or_a_non_number_passes_in_a_cell(tmp_path, text):
    assert render_check.problems(_with_cell(tmp_path, text)) == []


@pytest.mark.parametrize("sentence", ["H (boom -> body): nan deg (1-sigma).",
                                      "K = inf nT/A at 30 cm.", "the angle error is nan deg",
                                      "offset 120 ± nan nT", "a ratio -inf % of the seed's"])
def test_a_non_number_in_the_text_is_caught(tmp_path, sentence):
    probs = render_check.problems(_report(tmp_path, paragraph=PROSE + " " + sentence))
    assert len(probs) == 1 and "non-number in the page" in probs[0], probs


@pytest.mark.parametrize("text", ["None", "None nT", "nan..nan degC", "-20.0..nan degC",
                                  "[-694.0, nan, -1195.0]", "[-694.0, None, -1195.0]",
                                  "(nan, nan, nan)", "1.2 (nan)", "[nan]"])
def test_non_numbers_in_the_reports_own_forms_are_caught(tmp_path, text):
    """Ranges, lists, tuples and bracketed sigmas as the report prints them (review #19c)."""
    probs = render_check.problems(_with_cell(tmp_path, text))
    assert any("non-number in a table cell" in p for p in probs), probs
    if text != "None":        # a bare None in prose is a word ("None of the sensors")
        probs = render_check.problems(_report(tmp_path / "p", paragraph=f"{PROSE} x {text}."))
        assert any("non-number in the page" in p for p in probs), probs


@pytest.mark.parametrize("sentence", ["None of the sensors was held.", "-19.0..55.9 degC",
                                      "tables 1..3", "x ... y", "Nothing left. None."])
def test_words_and_true_ranges_pass(tmp_path, sentence):
    assert render_check.problems(_report(tmp_path, paragraph=PROSE + " " + sentence)) == []


def test_numpy_bool_repr_is_caught(tmp_path):
    probs = render_check.problems(_report(tmp_path, paragraph=PROSE + " flagged: np.True_"))
    assert any("numpy" in p for p in probs), probs
