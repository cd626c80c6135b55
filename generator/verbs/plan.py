"""`magcal plan`: the ground-test program of a unit, written as plan.md/.html/.json."""

from __future__ import annotations

import json
from pathlib import Path

from generator.campaign.plan import TestPlan, _hms, make_plan
from generator.io.outputs import check_output_folder, output_folder
from generator.io.unitfile import load_unit
from generator.report.plan_report import plan_report


def write_plan(plan: TestPlan, out_dir) -> dict:
    """plan.md, plan.html (with the figures) and plan.json in out_dir; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rep = plan_report(plan, out_dir)
    html = rep.write(out_dir, stem="plan")
    js = out_dir / "plan.json"
    js.write_text(json.dumps(plan.to_json_dict(), indent=1) + "\n", encoding="utf-8")
    return {"html": html, "markdown": out_dir / "plan.md", "json": js,
            "figures": [out_dir / "plan_positions.png", out_dir / "plan_profile.png"]}


def run_plan(args, progress) -> tuple:
    """`magcal plan`: exit status and the JSON result (the profile and the paths)."""
    check_output_folder(args.output)
    unit = load_unit(args.unit)
    plan = make_plan(unit, lab_field_nT=args.lab_field_nT, inclination_deg=args.inclination_deg,
                     levels_C=args.levels, board_tau_min=args.board_tau_min,
                     settle_tol_C=args.settle_tol_C, ramp_C_per_min=args.ramp_C_per_min,
                     sample_period_s=args.sample_period_s,
                     samples_per_segment=args.samples_per_segment, room_C=args.room_C,
                     reposition_min=args.reposition_min)
    progress(f"unit {unit.id}: {len(plan.positions)} positions x {len(plan.levels_C)} levels, "
             f"{_hms(plan.total_duration_s)} in all")
    with output_folder(args.output) as folder:
        paths = write_plan(plan, folder.tmp)
    paths = {k: ([folder.final(p) for p in v] if isinstance(v, list) else folder.final(v))
             for k, v in paths.items()}
    progress(f"wrote {paths['html']}, {paths['markdown']} and {paths['json']}")
    if folder.stale_note():
        progress(folder.stale_note())
    result = plan.to_json_dict()
    result["files"] = {k: ([str(p) for p in v] if isinstance(v, list) else str(v))
                       for k, v in paths.items()}
    return 0, result
