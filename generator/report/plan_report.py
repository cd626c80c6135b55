"""The ground-test program as a report: positions, temperature profile, sampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.campaign.plan import TestPlan, _hms, window_check
from generator.report import figures
from generator.report.document import Report, Section, Table


def plan_report(plan: TestPlan, out_dir):
    """Report (title, sections, figures written into out_dir) of a test plan."""
    out_dir = Path(out_dir)
    rep = Report(f"Ground test program: unit {plan.unit_id}")
    rep.add(Section("Summary", [
        f"Twelve static positions of the jig; in each the chamber steps through "
        f"{len(plan.levels_C)} temperature levels ({', '.join(f'{v:g}' for v in plan.levels_C)}"
        f" degC) and holds each until the boards have settled to within "
        f"{plan.settle_tolerance_C:g} degC, then {plan.samples_per_segment} samples are "
        f"recorded every {plan.sample_period_s:g} s. Total {_hms(plan.total_duration_s)} "
        f"({plan.total_duration_s / 86400:.1f} days), of which settling "
        f"{_hms(plan.settle_total_s)}. Record continuously (ramps too: the joint fit uses "
        f"them), with the position number in the `position` column (0 while moving) and the "
        f"reference field vector in `ref_x/y/z_nT` where the lab knows it (ICD section 2)."],
        [Table(["item", "value"], [
            ["unit", plan.unit_id], ["lab field |B| nT", plan.lab_field_nT],
            ["inclination deg", plan.inclination_deg],
            ["positions", len(plan.positions)], ["temperature levels", len(plan.levels_C)],
            ["board time constant min", plan.board_tau_s / 60.0],
            ["settling tolerance degC", plan.settle_tolerance_C],
            ["ramp degC/min", plan.ramp_C_per_min],
            ["sample period s", plan.sample_period_s],
            ["samples per segment", plan.samples_per_segment],
            ["one position", _hms(plan.position_duration_s)],
            ["whole program", _hms(plan.total_duration_s)],
            ["samples over the program", plan.samples_total]], "Program at a glance")]))

    # positions: sheet + table
    fig_pos = figures.positions_sheet(out_dir / "plan_positions.png", plan)
    rows = []
    for p in plan.positions:
        b = p.expected_field_body_nT
        rows.append([p.number, p.up, p.north, p.east, f"{b[0]:.1f}", f"{b[1]:.1f}",
                     f"{b[2]:.1f}", f"{np.linalg.norm(b):.1f}"])
    rep.add(Section("The twelve positions", [
        "Each drawing shows the body (the jig) in the lab: which body axis points up, which "
        "to magnetic north, and the lab field B. Axes: X red, Y green, Z blue; the grey arrow "
        "on the floor is magnetic north. The table gives the field each position should "
        "read in body axes (ICD ref_x/y/z_nT)."],
        [Table(["position", "up", "north", "east", "B_x nT", "B_y nT", "B_z nT", "|B| nT"],
               rows, "Positions and expected field in body axes")],
        [(fig_pos.name, "The twelve positions: body axes in the lab, up, north and the "
                        "expected field")]))

    # temperature profile: figure + step table
    fig_prof = figures.profile_figure(out_dir / "plan_profile.png", plan)
    rows = [[f"{s.level_C:g}", f"{s.from_C:g}", f"{s.step_C:g}", f"{s.ramp_s / 60:.1f}",
             f"{s.settle_s / 60:.1f}", f"{s.record_s / 60:.1f}", f"{s.hold_s / 60:.0f}"]
            for s in plan.steps]
    chk = window_check(plan)
    rows_chk = [[f"{L:g}", f"{v['from_min']:.0f}", f"{v['to_min']:.0f}",
                 f"{v['max_dev_C']:.3f}", v["worst_position"],
                 "yes" if v["max_dev_C"] <= plan.settle_tolerance_C else "NO"]
                for L, v in chk.items()]
    rep.add(Section("Temperature profile (the same in every position)", [
        f"hold = tau ln(step / {plan.settle_tolerance_C:g} degC) + recording, tau = "
        f"{plan.board_tau_s / 60:g} min, rounded up to whole minutes; the hold starts when the "
        f"chamber reaches the level. After the last level the chamber returns to "
        f"{plan.room_C:g} degC ({plan.return_ramp_s / 60:.0f} min) and the jig is turned to the "
        f"next position ({plan.reposition_s / 60:g} min). The second table is the board "
        f"temperature predicted by the same first-order model: its largest distance from "
        f"the level during each recording window."],
        [Table(["level degC", "from degC", "step degC", "ramp min", "settle min",
                "record min", "hold min"], rows, "One position's cycle"),
         Table(["level degC", "record from min", "record to min",
                "max |board - level| degC", "worst position", "settled"], rows_chk,
               "Predicted board temperature in the recording windows (record times in a "
               "position's cycle)")],
        [(fig_prof.name, "Chamber set-point and predicted board temperature over one "
                         "position's cycle; recording windows shaded")]))

    rep.add(Section("Sampling and recording", [
        f"Sample every {plan.sample_period_s:g} s throughout ({plan.samples_total} rows in "
        f"all). Per position and level {plan.samples_per_segment} samples fall in the "
        f"recording window. Check the recording with `magcal check UNIT.toml DATA.csv --plan "
        f"plan.json` before the jig leaves the chamber: it lists the positions and levels "
        f"that are missing or not settled and the coefficients the data would leave poorly "
        f"determined."]))
    rep.add(Section("Assumptions", [a[0].upper() + a[1:] + "." for a in plan.assumptions]))
    return rep
