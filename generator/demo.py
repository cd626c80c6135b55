"""`magcal demo`: the whole chain on a simulated example unit, with no arguments.

The project's own simulator (generator/campaign/simulate.py) makes a unit, its truth and its
ground and orbit campaigns; then fit (temperature model, coil coupling, boom alignment)
-> generate -> compile -> every sample through the flight C and the Python reference,
bit for bit -> accuracy against the simulator's truth on the ground and in orbit ->
uplink table through the flight validator -> report.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.flight.chain import is_valid, reference_sensor
from generator.flight.coeffs import CoefficientSet


def _same_bits(a: dict, b: dict) -> bool:
    return all(np.array_equal(np.ascontiguousarray(a[k]).view(np.uint8),
                              np.ascontiguousarray(b[k]).view(np.uint8)) for k in a)


def _campaign_rows(cs, host, csv_path, truth_npz, truth, deployed, static=False):
    """Per sensor: valid samples, C == Python, |B| RMS raw / calibrated / true parameters,
    and the angle to the true field (calibrated and true parameters). static: the chamber
    campaign, simulated standing still with the magnetorquers off (its file has no coil
    or body-rate columns: they are 0, as the simulator made them)."""
    from generator import pipeline
    from generator.io import truth as truth_mod
    from generator.io.telemetry_csv import preprocess, read_telemetry

    tel = read_telemetry(csv_path, cs.unit)
    data = preprocess(tel, cs.unit)
    b_true = np.load(truth_npz)["b_body_nT"]
    H_true = np.asarray(truth["H_boom_to_body"], float)
    coil = np.stack([tel.columns.get(c, np.zeros(tel.n)) for c in
                     ("coil_x_A", "coil_y_A", "coil_z_A")], axis=1)
    rows, identical = [], True
    for s in cs.unit.sensors:
        inp = pipeline.chain_inputs(tel, cs.spec, s.name, coils_off=static, aux_off=static)
        aux = dict(channels=inp["channels"], rate_dps=inp["rate_dps"], dt_s=inp["dt_s"])
        c_out = host.correct(s.name, inp["raw_counts"], inp["temp_C"], inp["coil_A"], **aux)
        py_out = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                  inp["raw_counts"], inp["temp_C"], inp["coil_A"], **aux)
        same = _same_bits(c_out, py_out)
        identical &= same
        ok = inp["present"] & is_valid(c_out["status"])
        raw_B = data[s.name].field_frame_nT
        B_tp = truth_mod.true_calibrated_frame(truth, s.name, raw_B, data[s.name].temp_C,
                                               coil_A=coil)
        if s.frame == "boom" and deployed:
            B_tp = B_tp @ H_true.T
        ours = truth_mod.rms_norm_error(c_out["field_body_nT"][ok], b_true[ok])
        best = truth_mod.rms_norm_error(B_tp[ok], b_true[ok])
        rows.append([s.name, int(ok.sum()), "identical" if same else "DIFFERENT",
                     truth_mod.rms_norm_error(raw_B[ok], b_true[ok]), ours, best, ours / best,
                     _rms_angle_deg(c_out["field_body_nT"][ok], b_true[ok]),
                     _rms_angle_deg(B_tp[ok], b_true[ok])])
    return tel, rows, identical


def _rms_angle_deg(B, B_true) -> float:
    cos = np.sum(B * B_true, axis=1) / np.linalg.norm(B, axis=1) / np.linalg.norm(B_true, axis=1)
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))


# ---- in-flight recalibration (issue 18; generator/campaign/simulate_orbit.py) -------------


def orbit_recalibration(out: Path, paths: dict, ground_json: Path, seed: int, progress):
    """The unit after launch (every offset shifted when panels and boom deploy), six hours
    of ISS-orbit telemetry with only the TLE in the unit file (no ref_*), recalibrated by
    `fit --prior` against IGRF-14 along the SGP4 track; the uplink of what changed; the
    |B| error before and after on another three hours of the same orbit (held out).
    Returns (report Section, printed lines, ok)."""
    from generator.campaign import simulate, simulate_orbit as so
    from generator import pipeline
    from generator.fit.samples import field_noise_nT
    from generator.io.telemetry_csv import read_telemetry
    from generator.io.unitfile import load_unit
    from generator.report.document import Section, Table
    from generator.verbs.uplink import make_uplink, write_uplink

    d = out / "orbit"
    unit = simulate.make_example_unit()
    truth = simulate.load_truth(paths["truth"], unit)
    ss_change, ss_fit, ss_held = np.random.SeedSequence([seed, 18]).spawn(3)
    changed, shifts = so.post_launch(truth, rng=np.random.default_rng(ss_change))
    progress("in flight: six hours of ISS-orbit telemetry (TLE only) after the deployment "
             "shifted every offset")
    orb = so.simulate_orbit(unit, changed, np.random.default_rng(ss_fit), d, name="orbit")
    held = so.simulate_orbit(unit, changed, np.random.default_rng(ss_held), d, name="held",
                             duration_s=3 * 3600.0)
    new = pipeline.fit(orb["unit"], [orb["csv"]], prior=ground_json, progress=progress)
    (d / "fit").mkdir(parents=True, exist_ok=True)
    new.save(d / "fit" / "coefficients.json")
    ground = CoefficientSet.load(ground_json)
    up = make_uplink(ground, new, onboard_serial=1)
    (d / "uplink").mkdir(parents=True, exist_ok=True)
    write_uplink(up, d / "uplink")
    prov = next(iter(new.fit_info["field_reference"].values()))

    u = load_unit(held["unit"])
    tel = read_telemetry(held["csv"], u)
    A = held["arrays"]
    model_rms = float(np.sqrt(np.mean((A["true_norm_nT"] - A["model_norm_nT"]) ** 2)))
    rows = []
    for s in u.sensors:
        row = [s.name]
        for cs in (ground, new):
            inp = pipeline.chain_inputs(tel, cs.spec, s.name)
            o = reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(),
                                 inp["raw_counts"], inp["temp_C"], inp["coil_A"],
                                 channels=inp["channels"], rate_dps=inp["rate_dps"],
                                 dt_s=inp["dt_s"])
            ok = inp["present"] & is_valid(o["status"])
            n = np.linalg.norm(np.asarray(o["field_body_nT"], float), axis=1)
            row.append(float(np.sqrt(np.mean((n[ok] - A["model_norm_nT"][ok]) ** 2))))
        floor = float(np.hypot(field_noise_nT(s), model_rms))
        rows.append(row + [floor, row[2] / floor])
    ok = all(r[4] <= 1.2 for r in rows)
    s = up["summary"]
    changed_blocks = sorted({c.block for c in up["changes"] if c.block})
    text = [
        f"After launch every sensor's offset shifted (deployment; simulate_orbit.post_launch, "
        f"e.g. mmc2 {np.round(shifts['mmc2'], 0).tolist()} nT). The orbit file has no ref_* "
        f"column: magcal computed |B| from {prov['model']} ({prov['package']} "
        f"{prov['package_version']}) at positions from {prov['position_source']}.",
        "`fit --prior` with the ground calibration; the table below is the |B| error against "
        "the field model on three held-out hours, through the Python reference of the flight "
        "chain, before (ground calibration) and after; the floor is sqrt(noise^2 + model^2) "
        f"with the model's error {model_rms:.0f} nT rms in this simulation.",
        f"Uplink (orbit/uplink/): serial {s['onboard_serial']} -> {s['new_serial']}, "
        f"{s['values_changed']} values changed ({', '.join(changed_blocks)}), "
        f"{s['table_bytes']} bytes in {s['parts']} parts of at most {s['chunk_bytes']} bytes; "
        "the diff is orbit/uplink/diff.txt."]
    table = Table(["sensor", "|B| error before nT", "|B| error after nT", "floor nT",
                   "after / floor"], rows, "In-flight recalibration: held-out |B| error "
                  "against the field model, before and after")
    lines = ["", "in-flight recalibration (ISS TLE, IGRF-14, ground calibration as prior), "
                 "held-out |B| error against the field model",
             f"{'sensor':8s} {'before':>8s} {'after':>8s} {'floor':>8s} {'ratio':>6s}"]
    lines += [f"{r[0]:8s} {r[1]:8.1f} {r[2]:8.1f} {r[3]:8.1f} {r[4]:6.2f}" for r in rows]
    lines += [f"uplink: serial {s['onboard_serial']} -> {s['new_serial']}, "
              f"{s['values_changed']} values changed, {s['parts']} parts "
              f"({d / 'uplink' / 'diff.txt'})"]
    lines += ["  " + str(c) for c in up["changes"] if c.block == "b_poly_nT"][:3]
    return Section("In-flight recalibration against the field model", text, [table]), lines, ok


def run_demo_atomic(out: Path, seed: int = 1, progress=None) -> int:
    """run_demo built in a temporary folder beside `out` and renamed into place (nothing is
    left on an error); its text outputs and printed lines name `out`, not the temporary
    folder."""
    import contextlib
    import io
    import sys

    from generator.io.outputs import output_folder
    from generator.progress import Progress

    progress = progress or Progress()
    buf = io.StringIO()
    with output_folder(out) as folder:
        with contextlib.redirect_stdout(buf):
            rc = run_demo(folder.tmp, seed=seed, progress=progress)
        tmp, target = str(folder.tmp), str(folder.target)
        for f in folder.tmp.rglob("*"):
            if f.suffix in (".md", ".html", ".json") and f.is_file():
                text = f.read_text(encoding="utf-8")
                if tmp in text:
                    f.write_text(text.replace(tmp, target), encoding="utf-8")
    sys.stdout.write(buf.getvalue().replace(tmp, target))
    if folder.stale_note():
        progress(folder.stale_note())
    return rc


def run_demo(out: Path, seed: int = 1, progress=None) -> int:
    from generator.flight import codegen
    from generator import pipeline
    from generator.campaign import simulate
    from generator.flight import tables
    from generator.flight import table_host
    from generator.io import truth as truth_mod
    from generator.flight.host import HostUnit
    from generator.report.document import Report, Section, Table
    from generator.report.report import fit_report

    from generator.progress import Progress

    progress = progress or Progress()
    out = Path(out)
    data_dir = out / "data"
    progress(f"simulating the example unit (seed {seed}) into {data_dir}")
    paths = simulate.make_example(data_dir, seed=seed)
    with open(paths["unit"], "a", encoding="utf-8") as f:   # the ICD's example needs
        f.write("\n[requirements]\nfield_error_nT = 150.0\nangle_deg = 0.5\n")
    ground = [Path(paths[k]) for k in ("thermal_12pos", "rotation", "coils", "coil_study")]

    progress("fitting the ground campaigns: thermal twelve positions, rotation, coils, "
             "coil study")
    cs = pipeline.fit(paths["unit"], ground, progress=progress)
    fit_dir = out / "fit"
    fit_dir.mkdir(parents=True, exist_ok=True)
    cs.save(fit_dir / "coefficients.json")
    cs = CoefficientSet.load(fit_dir / "coefficients.json")   # what a user would ship

    c_dir = out / "flight_c"
    files = codegen.generate(cs, c_dir)
    progress(f"generated {len(files)} C files in {c_dir}")
    host = HostUnit(cs)
    progress("compiled on the host: -std=c99 -O2 -ffp-contract=off -Wall -Wextra -Werror")

    truth = truth_mod.load_truth(paths["truth"])
    stowed = cs.with_boom_stowed()      # the jig campaign: H not applied
    thermal_tel, thermal_rows, ok_thermal = _campaign_rows(
        stowed, HostUnit(stowed), paths["thermal_12pos"],
        paths["thermal_12pos_truth"], truth, deployed=False, static=True)
    flight_tel, flight_rows, ok_flight = _campaign_rows(
        cs, host, paths["flight"], paths["flight_truth"], truth, deployed=True)
    all_identical = ok_thermal and ok_flight

    progress("uplink table: encode, flight validator, one flipped bit")
    table = tables.encode_table(cs, serial=1, created_s=0)
    (out / "table.bin").write_bytes(table)
    th = table_host.TableHost(cs)
    accepted = th.validate(table)
    flipped = bytearray(table)
    flipped[len(flipped) // 2] ^= 0x10
    rejected = th.validate(bytes(flipped))
    table_ok = accepted == 0 and rejected != 0

    orbit_section, orbit_lines, orbit_ok = orbit_recalibration(
        out, paths, fit_dir / "coefficients.json", seed, progress)

    progress("writing the report (figures)")
    # every fitted file (the coil study's section: K against distance)
    fit_rep = fit_report(cs, out, data_paths=ground, progress=progress)
    rep = Report(f"magcal demo: simulated unit {cs.unit.id} (seed {seed})")
    rep.add(fit_rep.sections.pop(0))  # the summary and verdict first
    rep.add(Section("What ran", [
        "The project's simulator made the unit, its truth and its campaigns. magcal fitted the "
        "ground campaigns (temperature model from the thermal twelve positions, coil coupling "
        "from the coil steps, boom alignment H from the rotation, the interference against "
        "distance from the coil study), generated and compiled the "
        "flight C, and ran every sample of the thermal and the orbit campaign through it and "
        "through the Python reference; the table below compares them bit for bit and against "
        "the simulator's truth. The unit file states the ICD's example [requirements] "
        "(150 nT, 0.5 deg) for the verdict at the top."]))
    header = ["sensor", "valid samples", "C vs Python", "|B| RMS raw nT",
              "|B| RMS calibrated nT", "|B| RMS true parameters nT", "ratio to truth",
              "angle calibrated deg", "angle true parameters deg"]
    rep.add(Section("Result on the thermal campaign", [
        "Jig data, boom stowed (H not applied)."],
        [Table(header, thermal_rows, "Thermal campaign: the flight C against the Python "
               "reference and the simulator's truth")]))
    rep.add(Section("Result in orbit (flight campaign)", [
        "Orbit telemetry with the boom deployed and the magnetorquers switching: the chain "
        "applies the coil coupling and H."],
        [Table(header, flight_rows, "Orbit campaign: the flight C against the Python "
               "reference and the simulator's truth")]))
    rep.add(Section("Uplink table", [
        f"table.bin: {len(table)} bytes; the flight validator accepts it (code {accepted}) "
        f"and rejects it with one bit flipped (code {int(rejected)}: {th.strerror(rejected)})."]))
    rep.add(orbit_section)
    rep.extend(fit_rep.sections)      # inputs, fit, |B| RMS, temperature dependence, H, K
    report = rep.write(out)

    print(f"\nmagcal demo: unit {cs.unit.id} (seed {seed})")
    for title, tel, rows in (("thermal campaign", thermal_tel, thermal_rows),
                             ("orbit campaign", flight_tel, flight_rows)):
        print(f"\n{title}, {tel.n} samples")
        print(f"{'sensor':8s} {'C == Python':>12s} {'raw nT':>10s} {'calibrated':>11s} "
              f"{'truth':>8s} {'ratio':>6s} {'angle deg':>10s}")
        for r in rows:
            print(f"{r[0]:8s} {r[2]:>12s} {r[3]:10.1f} {r[4]:11.1f} {r[5]:8.1f} {r[6]:6.3f} "
                  f"{r[7]:10.3f}")
    print(f"\nuplink table: {len(table)} bytes, accepted by the flight validator; "
          f"one flipped bit rejected ({th.strerror(rejected)})")
    print("\n".join(orbit_lines))
    print(f"coefficients: {fit_dir / 'coefficients.json'}")
    print(f"flight C:     {c_dir}")
    print(f"report:       {report}")
    return 0 if all_identical and table_ok and orbit_ok else 1
