"""Issue 17, items 3 and 4, and the empty-column crash: the trace keeps nothing the data
refute and accepts no degenerate solution.

* Magnitude-only data (`ref_norm_nT`) with a supplied baseline (`--coeffs`), over a small
  range of field directions (a cone of 20 degrees: the true field varies by about 11 uT):
  refitting b and a symmetric M to |B| alone can contract the calibration toward a
  constant vector of the reference's length, which fits |B| with less than the noise. The
  trace must refuse such a refit (the calibrated field's variation may not fall more than
  residual.MAX_SHRINK below the reference's own, here the baseline calibration's) and say
  so in trace.json (`final.<sensor>.refused`).
* A refitted model whose error on the evaluation data rose beyond chance is refused.
* An empty (not missing) temperature column: that sensor is skipped with the reason; if
  no sensor is left, one InputError naming the file.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.errors import InputError
from generator.io.telemetry import Telemetry
from generator.io.telemetry_csv import read_telemetry
from generator.trace import residual as rv
from generator.trace import tracer as tr

from test_trace import run, small_unit

CONE_DEG = 20.0


def cone_case(seed, out):
    rng = np.random.default_rng(31_000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    ground, _ = run("thermal", unit, truth, seed, out)
    p, arr = sim.simulate_campaign("rotation", unit, truth, np.random.default_rng(seed + 1), out,
                                   fast=True, set_reset_delay_s=0.0, name="rot")
    rot = read_telemetry(p, unit)
    assert "ref_norm_nT" in rot.columns and "ref_x_nT" not in rot.columns
    b = arr["b_body_nT"]
    u = b / np.linalg.norm(b, axis=1)[:, None]
    c = np.cos(np.radians(CONE_DEG))
    centre = u[np.argmax((u @ u.T > c).sum(axis=1))]
    keep = u @ centre > c
    cols = {k: np.asarray(v)[keep] for k, v in rot.columns.items()}
    rot = Telemetry(rot.path, cols, np.asarray(rot.line_numbers)[keep], dict(rot.meta))
    return unit, ground, rot


@pytest.mark.parametrize("seed", [1, 2])
def test_magnitude_only_refit_may_not_collapse_the_field(seed, tmp_path):
    unit, ground, rot = cone_case(seed, tmp_path)
    cs = tr.baseline_coefficients(unit, [ground])[0]
    res = tr.trace(unit, [rot], coeffs=cs)
    out = json.loads(json.dumps(res.to_json(), default=tr._json_default))
    refused_any = False
    for n, t in res.traces.items():
        S = t.S_fit
        ref_var, _ = rv.reference_variation_nT(S, t.base_model.field(S))
        m = t.steps[-1].model_after if t.steps else t.final_model
        assert rv.field_variation_nT(m.field(S)) >= (1 - rv.MAX_SHRINK) * ref_var, n
        # an unguarded refit of the same structure: where it collapses, the trace said so
        free = t.base_model.copy().fit(S)
        if rv.shrinks(free.field(S), S, ref_var):
            refused = out["final"][n]["refused"]
            assert refused and "degenerate" in refused[0]["why"], (n, refused)
            refused_any = True
    # the case is built so that the unguarded refit does collapse (else it tests nothing)
    assert refused_any


def test_a_refit_that_raises_the_evaluation_error_is_refused(tmp_path):
    rng = np.random.default_rng(33_000)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    tel, _ = run("thermal", unit, truth, 3, tmp_path)
    res = tr.trace(unit, [tel])
    t = res.traces["mmc1"]
    good = t.final_model if not t.steps else t.steps[-1].model_after
    bad = good.copy()
    bad.theta = bad.theta + 5.0 * rng.normal(size=bad.P)      # 5 nT-ish in every parameter
    ref_var, what = rv.reference_variation_nT(t.S_fit, good.field(t.S_fit))
    why = tr._refusal(good, bad, t.S_fit, t.S_eval, ref_var, what)
    assert "raised the evaluation RMS" in why
    assert tr._refusal(good, good.copy(), t.S_fit, t.S_eval, ref_var, what) == ""


def _blank(path, columns, out):
    lines = open(path).read().splitlines()
    h = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    hdr = lines[h].split(",")
    ks = [hdr.index(c) for c in columns]
    rows = []
    for ln in lines[h + 1:]:
        f = ln.split(",")
        for k in ks:
            f[k] = ""
        rows.append(",".join(f))
    out.write_text("\n".join(lines[:h + 1] + rows) + "\n")
    return out


def test_an_empty_temperature_column_is_a_clear_skip_or_error(tmp_path):
    rng = np.random.default_rng(35_000)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    tel, _ = run("thermal", unit, truth, 4, tmp_path)
    cs = tr.baseline_coefficients(unit, [tel])[0]
    one = _blank(tel.path, ["mpu1_temp_C"], tmp_path / "one_empty.csv")
    res = tr.trace(unit, [str(one)], coeffs=cs)
    assert "mpu1" not in res.traces and "mpu1_temp_C is empty" in res.skipped["mpu1"]
    allc = _blank(tel.path, [f"{s.name}_temp_C" for s in unit.sensors], tmp_path / "empty.csv")
    with pytest.raises(InputError) as err:
        tr.trace(unit, [str(allc)], coeffs=cs)
    assert "empty.csv" in str(err.value) and "is empty" in str(err.value)
