"""`magcal demo`: the whole chain on a simulated example unit, with no arguments.

The project's own simulator (generator/simulate.py) makes a unit and its campaigns; then
fit -> generate -> compile -> bit-exact check of the flight C against the Python
reference on every sample -> accuracy against the simulator's truth -> report.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .chain import reference_sensor
from .coeffs import CoefficientSet


def run_demo(out: Path, seed: int = 1, progress=None) -> int:
    from . import codegen, pipeline, simulate
    from . import truth as truth_mod
    from .host import HostUnit
    from .report import Report, Section, Table, fit_report
    from .telemetry import preprocess, read_telemetry

    progress = progress or pipeline.Progress()
    out = Path(out)
    data_dir = out / "data"
    progress(f"simulating the example unit (seed {seed}) into {data_dir}")
    paths = simulate.make_example(data_dir, seed=seed)
    campaign = Path(paths["thermal_12pos"])

    progress("fitting the thermal twelve-position campaign")
    cs = pipeline.fit(paths["unit"], [campaign], progress=progress)
    fit_dir = out / "fit"
    fit_dir.mkdir(parents=True, exist_ok=True)
    cs.save(fit_dir / "coefficients.json")
    cs = CoefficientSet.load(fit_dir / "coefficients.json")   # what a user would ship

    c_dir = out / "flight_c"
    files = codegen.generate(cs, c_dir)
    progress(f"generated {len(files)} C files in {c_dir}")
    host = HostUnit(cs)
    progress("compiled on the host: -std=c99 -O2 -ffp-contract=off -Wall -Wextra -Werror")

    tel = read_telemetry(campaign, cs.unit)
    data = preprocess(tel, cs.unit)
    truth = truth_mod.load_truth(paths["truth"])
    b_true = np.load(paths["thermal_12pos_truth"])["b_body_nT"]
    rows = []
    all_identical = True
    for s in cs.unit.sensors:
        inp = pipeline.chain_inputs(tel, cs.spec, s.name)
        aux = dict(channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        c_out = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"], **aux)
        py_out = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                  inp["raw_counts"], inp["temp_C"], inp["coil_A"], **aux)
        same = all(np.array_equal(np.ascontiguousarray(c_out[k]).view(np.uint8),
                                  np.ascontiguousarray(py_out[k]).view(np.uint8))
                   for k in c_out)
        all_identical &= same
        ok = inp["present"] & (c_out["status"] == 0)
        raw_B = data[s.name].field_frame_nT
        ours = truth_mod.rms_norm_error(c_out["field_body_nT"][ok], b_true[ok])
        raw = truth_mod.rms_norm_error(raw_B[ok], b_true[ok])
        true_cal = truth_mod.true_calibrated_frame(truth, s.name, raw_B, data[s.name].temp_C)
        best = truth_mod.rms_norm_error(true_cal[ok], b_true[ok])
        rows.append([s.name, int(ok.sum()), "identical" if same else "DIFFERENT",
                     raw, ours, best, ours / best])

    progress("writing the report (figures)")
    fit_rep = fit_report(cs, out, data_paths=[campaign], progress=progress)
    rep = Report(f"magcal demo: simulated unit {cs.unit.id} (seed {seed})")
    rep.add(Section("What ran", [
        "The project's simulator made the unit, its truth and its campaigns; magcal fitted the "
        "thermal twelve-position campaign, generated and compiled the flight C, and ran every "
        "sample through it and through the Python reference."]))
    rep.add(Section("Result on the thermal campaign", [], [Table(
        ["sensor", "valid samples", "C vs Python", "|B| RMS raw nT", "|B| RMS calibrated nT",
         "|B| RMS true parameters nT", "ratio to truth"], rows)]))
    rep.extend(fit_rep.sections)      # inputs, fit, |B| RMS, temperature dependence
    report = rep.write(out)

    print(f"\nmagcal demo: unit {cs.unit.id}, {tel.n} samples of {campaign.name}")
    print(f"{'sensor':8s} {'C == Python':>12s} {'raw nT':>10s} {'calibrated':>11s} "
          f"{'truth':>8s} {'ratio':>6s}")
    for r in rows:
        print(f"{r[0]:8s} {r[2]:>12s} {r[3]:10.1f} {r[4]:11.1f} {r[5]:8.1f} {r[6]:6.3f}")
    print(f"coefficients: {fit_dir / 'coefficients.json'}")
    print(f"flight C:     {c_dir}")
    print(f"report:       {report}")
    return 0 if all_identical else 1
