"""Issue 6 on measured data: `magcal trace` on a PX4 log it was not built for.

Data: ../shared/realdata/px4_ecl_office (Toothsmile/ecl @ d2997b1, BSD-3-Clause): a
hexacopter armed indoors and almost still for 329 s, four magnetometers already
calibrated by PX4, their chip temperatures warming by 5-7 degC, six motor PWM outputs,
the armed flag. Nothing is known about the true field except that it is constant while
the vehicle stands still, so the residual is each sensor's deviation from a constant
(ICD section 2, "position" rows), the baseline is the identity (the data as PX4
calibrated them), and every candidate of the catalogue competes: temperature, a drift in
time, a step, every motor channel, the armed flag. The test does not say which one wins;
it asserts that a cause is named with the significance rule passed, that the held-out
error falls, and it prints what was found (run with -s).

The samples carry vibration noise of 200-4600 nT (per axis, 40-100 Hz); the default run
traces 1 s means (`px4_log_telemetry(average_s=1.0)`: the field is constant, averaging
keeps everything slower than a second), the raw samples run in the slow set.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.trace import tracer as tr
from generator.io.px4_csv import px4_log_telemetry
from generator.report.trace_report import write_report
from generator.flight.coeffs import CoefficientSet

from conftest import REALDATA
from ci import require

PX4 = REALDATA / "px4_ecl_office"


@pytest.fixture(scope="module")
def px4_dir():
    require((PX4 / "sensor_mag_0.csv").exists(), f"PX4 log not found at {PX4}")
    return PX4


def _table(res) -> str:
    lines = ["", f"PX4 office log: held-out RMS per sensor ({res.evaluated_on}), deviation "
                 "from a constant"]
    for n, t in res.traces.items():
        lines.append(f"  {n}: {t.baseline_rms_nT:7.1f} nT -> {t.final_rms_nT:7.1f} nT"
                     f"   ({t.S_fit.n} samples fitted, {t.S_eval.n} held out)")
        for st in t.steps:
            e = st.effect
            params = e.describe(st.params, st.model_after)
            lines.append(f"     + {e.label()}: {st.rms_before_nT:.1f} -> {st.rms_after_nT:.1f} nT"
                         f", CV gain {100 * st.score.rel_rms_gain:.1f} %, z = {st.score.z:.1f}"
                         f"; {json.dumps(params, default=float)[:160]}")
            if st.runner_up is not None:
                lines.append(f"       runner-up: {tr.runner_up_text(st)}")
        if not t.steps:
            lines.append(f"     nothing added: {t.stop}")
    return "\n".join(lines)


def _check(res, tmp_path):
    found = res.effects
    assert found, "no cause named:\n" + _table(res)
    for n, st in found:
        assert st.score.significant
        assert st.rms_after_nT < st.rms_before_nT, (n, st.effect.label())
    paths = res.write(tmp_path)
    paths["report"] = write_report(res, tmp_path)
    j = json.loads(paths["trace"].read_text())
    assert set(j["baseline"]) == set(j["final"]) == {"mag0", "mag1", "mag2", "mag3"}
    assert len(j["effects"]) == len(found)
    for e in j["effects"]:
        assert e["rms_after_nT"] < e["rms_before_nT"] and e["evidence"]
    cs = CoefficientSet.load(paths["coefficients"])
    assert cs.unit.sensor_names == ("mag0", "mag1", "mag2", "mag3")
    assert paths["report"].exists()


def test_px4_adapter_reads_the_log(px4_dir):
    unit, tel = px4_log_telemetry(px4_dir, average_s=1.0)
    assert unit.sensor_names == ("mag0", "mag1", "mag2", "mag3")
    assert 320 < tel.time_s[-1] - tel.time_s[0] < 335
    from generator.io.telemetry_csv import preprocess
    pre = preprocess(tel, unit)
    for s in unit.sensors:
        d = pre[s.name]
        B = np.linalg.norm(d.field_frame_nT[d.usable], axis=1)
        assert 25000 < np.median(B) < 45000, s.name            # an indoor Earth field
        T = d.temp_C[d.usable]
        assert 2.0 < T[-20:].mean() - T[:20].mean() < 8.0, s.name  # the chips warm up
    motors = [c for c in tel.columns if c.startswith("motor") and c.endswith("_pwm_us")]
    assert len(motors) >= 6 and "armed" in tel.columns
    raw_unit, raw = px4_log_telemetry(px4_dir)
    assert raw.n > 100_000 and raw_unit == unit


def test_px4_trace_names_a_cause_of_the_drift(px4_dir, tmp_path):
    unit, tel = px4_log_telemetry(px4_dir, average_s=1.0)
    res = tr.trace(unit, [tel])
    print(_table(res))
    _check(res, tmp_path)


@pytest.mark.slow
def test_px4_trace_on_the_raw_samples(px4_dir, tmp_path):
    unit, tel = px4_log_telemetry(px4_dir)
    res = tr.trace(unit, [tel])
    print(_table(res))
    _check(res, tmp_path)
