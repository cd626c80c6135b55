"""Review 17 #8 (#11-#13): bad input to `magcal trace` is refused naming what is wrong.
- a regressor named like a column the ICD reserves (coil_x_A, rate_x_dps, ...);
- the nesting limit of a formula is the documented one (40 levels of parentheses);
- --holdout that is one of the data files (the same path or the same bytes);
- a regressor's non-finite rows are missing (left out), not 0."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.errors import InputError
from generator.io import formula as fm
from generator.io.telemetry import Telemetry
from generator.trace import tracer as tr
from generator.trace.samples import gather_samples

from test_trace import run, small_unit


@pytest.mark.parametrize("name", ["coil_x_A", "rate_x_dps", "ref_norm_nT", "time_s"])
def test_a_regressor_named_like_a_reserved_column_is_refused(name):
    with pytest.raises(InputError, match=r"trace\.regressor\[1\]\.name"):
        fm.read_regressors("unit.toml", {"regressor": [{"name": name,
                                                        "formula": "heater_w * 2"}]})


def test_the_nesting_limit_is_forty_parentheses():
    assert fm.parse("(" * 40 + "x" + ")" * 40) == ("name", "x")
    with pytest.raises(fm.FormulaError, match="40"):
        fm.parse("(" * 41 + "x" + ")" * 41)


@pytest.fixture(scope="module")
def thermal(tmp_path_factory):
    out = tmp_path_factory.mktemp("thermal")
    unit = small_unit()
    truth = sim.random_truth(unit, np.random.default_rng(7))
    tel, _ = run("thermal", unit, truth, 7, out)
    return unit, tel


def test_holdout_that_is_a_data_file_is_refused(thermal, tmp_path):
    unit, tel = thermal
    with pytest.raises(InputError, match="--holdout: the same file"):
        tr.trace(unit, [tel.path], holdout=[tel.path])
    copy = tmp_path / "copy.csv"
    shutil.copyfile(tel.path, copy)
    with pytest.raises(InputError, match="--holdout: the same content"):
        tr.trace(unit, [tel.path], holdout=[copy])


def test_regressor_rows_that_are_not_finite_are_missing(thermal):
    unit, tel = thermal
    r = np.linspace(1.0, 2.0, tel.n)
    r[::10] = np.nan                              # a division by zero every tenth row
    cols = dict(tel.columns)
    cols["p_W"] = r
    t2 = Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))
    notes = []
    loose = gather_samples(unit, [t2], [0], channels=["p_W"])
    strict = gather_samples(unit, [t2], [0], channels=["p_W"], strict={"p_W"}, notes=notes)
    for s in loose:
        assert strict[s].n < loose[s].n
        assert np.all(np.isin(strict[s].order, np.nonzero(np.isfinite(r))[0]))
    assert any("missing" in n for n in notes)
