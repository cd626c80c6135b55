"""Issue 17, item 5: a user-declared regressor in the unit file,

    [[trace.regressor]]
    name = "heater_w"
    formula = "v_heater * i_heater"

parsed by a small parser (generator.io.formula: numbers, channel names, + - * / **,
parentheses; never Python's eval), refused with exit 2 and the key on anything else, and
taken by trace as a candidate channel (its flight form: a channel computed before the
chain, docs/effects.md).

The trace case: a heater whose field follows its power v * i, with v and i switched
independently (square waves of different periods), 12 x the per-axis noise on one sensor
(above the detection floor of 5 x, test_trace_intermittent.py); neither channel alone
carries the product.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.errors import InputError
from generator.io import formula as fm
from generator.io.unitfile import load_unit
from generator.trace import tracer as tr

from test_trace import _direction, run, sigma_field, small_unit

SHARED_UNIT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "samsat_fm1" \
    / "unit.toml"


@pytest.mark.parametrize("text, cols, want", [
    ("v_heater * i_heater", {"v_heater": [2.0, 3.0], "i_heater": [0.5, -1.0]}, [1.0, -3.0]),
    ("-x**2", {"x": [3.0, -2.0]}, [-9.0, -4.0]),
    ("(a + b) / 2 - 3e-1", {"a": [1.0, 2.0], "b": [3.0, 5.0]}, [1.7, 3.2]),
    ("2 ** x ** 2", {"x": [1.0, 2.0]}, [2.0, 16.0]),        # right-associative
    ("a / b", {"a": [1.0, 1.0], "b": [0.0, 4.0]}, [np.nan, 0.25]),   # not finite: missing
    ("+a - -b", {"a": [1.0], "b": [2.0]}, [3.0]),
])
def test_formulas_evaluate(text, cols, want):
    tree = fm.parse(text)
    got = fm.evaluate(tree, {k: np.asarray(v) for k, v in cols.items()})
    np.testing.assert_allclose(got, want, rtol=1e-15, equal_nan=True)
    assert fm.names(tree) == list(cols)


BAD = ["__import__('os').system('x')", "abs(x)", "x.real", "x; y", "x if y else z",
       "lambda: 1", "'a'", "x[0]", "x @ y", "x % 2", "x // 2", "1e999", "(x", "x +", "",
       "x y", "(" * 60 + "x" + ")" * 60, "x == 1", "x" * 501]


@pytest.mark.parametrize("text", BAD)
def test_anything_else_is_refused(text):
    with pytest.raises(fm.FormulaError):
        fm.parse(text)


def _unit_file(tmp_path, regressor_toml):
    p = tmp_path / "unit.toml"
    p.write_text(SHARED_UNIT.read_text() + "\n" + regressor_toml)
    return p


def test_the_unit_file_carries_the_regressor(tmp_path):
    if not SHARED_UNIT.is_file():
        pytest.skip("shared data not found")
    u = load_unit(_unit_file(tmp_path, '[[trace.regressor]]\nname = "heater_w"\n'
                                       'formula = "v_heater * i_heater"\n'))
    assert u.extra["trace_regressors"] == [{"name": "heater_w",
                                            "formula": "v_heater * i_heater",
                                            "inputs": ["v_heater", "i_heater"]}]


@pytest.mark.parametrize("body, key", [
    ('name = "p"\nformula = "open(x)"', "trace.regressor[1].formula"),
    ('name = "p"\nformula = "x ; y"', "trace.regressor[1].formula"),
    ('name = "p"\nformula = 3', "trace.regressor[1].formula"),
    ('name = "p"\nformula = "2 * 3"', "trace.regressor[1].formula"),
    ('name = "p"\nformula = "p * 2"', "trace.regressor[1].formula"),
    ('name = "1p"\nformula = "x"', "trace.regressor[1].name"),
    ('name = "p"\nformula = "x"\nweight = 2', "trace.regressor[1].weight"),
])
def test_a_bad_regressor_is_bad_input_naming_the_key(tmp_path, body, key, capsys):
    if not SHARED_UNIT.is_file():
        pytest.skip("shared data not found")
    p = _unit_file(tmp_path, "[[trace.regressor]]\n" + body + "\n")
    with pytest.raises(InputError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_unit(p)
    from generator.cli import main
    assert main(["plan", str(p), "-o", str(tmp_path / "plan")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0], err


@dataclass
class HeaterPower(sim.Effect):
    """Test-only: a heater's field follows its power v * i (v, i switched independently)."""
    sensor: str
    nT_per_W: tuple
    name = "heater_power"
    v = sim.SquareWave(500.0, 0.5, 8.0, 4.0, 60.0, 2)
    i = sim.SquareWave(700.0, 0.5, 0.6, 0.1, 0.0, 3)

    def channels(self, time_s):
        return {"v_heater": (self.v.values(time_s), self.v.decimals),
                "i_heater": (self.i.values(time_s), self.i.decimals)}

    def frame_nT(self, ctx):
        p = ctx.channels["v_heater"] * ctx.channels["i_heater"]
        return p[:, None] * np.asarray(self.nT_per_W, float)


def test_trace_takes_the_declared_regressor(tmp_path):
    rng = np.random.default_rng(81_001)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = "mpu1"
    p_span = 8.0 * 0.6 - 4.0 * 0.1                  # the power's swing, W
    eff = HeaterPower(s, tuple(_direction(rng) * 12.0 * sigma_field(unit.sensor(s)) / p_span))
    tel, _ = run("thermal", unit, truth, 9, tmp_path, [eff])
    regs = fm.read_regressors("unit.toml", {"regressor": [
        {"name": "heater_w", "formula": "v_heater * i_heater"}]})
    unit_r = replace(unit, extra={"trace_regressors": [
        {k: r[k] for k in ("name", "formula", "inputs")} for r in regs]})
    res = tr.trace(unit_r, [tel])
    found = [(n, st.effect.label()) for n, st in res.effects]
    assert found and found[0] == (s, "channel_bias(heater_w)"), found
    js = res.to_json()
    e = js["effects"][0]
    assert e["regressors"] and e["regressors"][0]["formula"] == "v_heater * i_heater"
    assert any("heater_w = v_heater * i_heater" in n for n in js["notes"])
    assert res.coefficients.spec.opts(s).channels[0] == "heater_w"
    # a file that already has a column of the regressor's name is bad input
    cols = dict(tel.columns, heater_w=np.zeros(tel.n))
    from generator.io.telemetry import Telemetry
    with pytest.raises(InputError, match="heater_w"):
        tr.trace(unit_r, [Telemetry(tel.path, cols, tel.line_numbers, dict(tel.meta))])
