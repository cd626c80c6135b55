"""`magcal plan`: the ground-test program of a unit (seed 000 sec. 5, docs/methods.md).

The jig holding the flight computer and the stowed boom board is put in twelve static
positions; in each the climatic chamber steps through the temperature levels, holding each
until the boards have settled and the segment's samples are recorded. This module computes
the program and writes it as a printable document (Markdown and HTML with figures) and a
machine-readable profile (`plan.json`, read back by `magcal check --plan`).

Positions. Position p turns the body so that one body axis points up and another points
to magnetic north: each of +-X, +-Y, +-Z up, at headings 0 and 90 deg of the next body axis
(X up: Y north, then Y east; Y up: Z north / east; Z up: X north / east). R_p maps body axes
to the lab's north-east-down axes; the expected field in body axes is R_p^T B_lab with
B_lab = F (cos I, 0, sin I) (F the lab field magnitude, I the inclination, north along
magnetic north, i.e. declination already removed). generator.campaign.simulate uses the same twelve.

Holds. A board follows the chamber as a first-order lag with time constant tau. After a
step of size S (from the board's last settled temperature to the new set-point), the
board is within the tolerance e of the set-point after tau ln(S / e) (measured from the
moment the chamber reaches the level: a conservative bound, since the board has already
followed part of the way during the ramp). The hold is that settling time plus the
recording time of the segment (samples x sample period), rounded up to whole minutes:

    hold >= tau ln(S / e) + N_samples T_sample

The first level of each position is entered from wherever the board was left: between room
temperature (where the jig is turned) and the last level, so S_1 = max(|L_1 - room|,
|L_1 - L_last|), which holds whatever time the repositioning takes.

Default assumptions (all overridable on the command line):
* board time constant 20 min: the flight computer and boom board sit in the jig inside the
  structure, whose thermal mass dominates; boards of this size in the example campaigns
  show 10-20 min. Measure yours on the first step (the time the reported temperature takes
  to cover 63 % of the step) and re-plan with --board-tau-min;
* settling tolerance 0.5 degC: below the MMC5883MA's 0.7 degC temperature step, and an
  offset drift of a few tens of nT/degC then moves b by well under the reading noise;
* ramp 1 degC/min: gentle on the boards and the connectors, avoids condensation;
* 120 samples per segment at 5 s (10 min): the segment finder of the fit needs 10 min of
  steady temperature (generator.fit.thermal.find_segments), and 120 samples per position
  and level make the per-level calibration's noise negligible against the cubic's;
* levels -20, -5, 10, 25, 40, 55 degC (the example unit's ground test), room 25 degC,
  15 min to turn the jig.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from generator.errors import InputError
from generator.io.json_input import load_json

FORMAT = "magcal-test-plan"
FORMAT_VERSION = 1

DEFAULT_LEVELS_C = (-20.0, -5.0, 10.0, 25.0, 40.0, 55.0)
DEFAULT_INCLINATION_DEG = 70.0
DEFAULT_BOARD_TAU_MIN = 20.0
DEFAULT_SETTLE_TOL_C = 0.5
DEFAULT_RAMP_C_PER_MIN = 1.0
DEFAULT_SAMPLE_PERIOD_S = 5.0
DEFAULT_SAMPLES_PER_SEGMENT = 120
DEFAULT_ROOM_C = 25.0
DEFAULT_REPOSITION_MIN = 15.0

_AX = "XYZ"
_NED_UP = np.array([0.0, 0.0, -1.0])
_NED_NORTH = np.array([1.0, 0.0, 0.0])
_NED_EAST = np.array([0.0, 1.0, 0.0])


# =======================================================================================
# Positions
# =======================================================================================
def twelve_positions() -> list:
    """Body -> lab (north-east-down) rotation matrices of the twelve positions, in order:
    for each body axis X, Y, Z: axis up with the next axis north, then east; axis down with
    the next axis north, then east."""
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            for heading_deg in (0.0, 90.0):
                u = sign * np.eye(3)[axis]                 # body axis that points up
                v = np.eye(3)[(axis + 1) % 3]              # body axis at the heading
                h = math.radians(heading_deg)
                lab_v = np.array([math.cos(h), math.sin(h), 0.0])
                body = np.column_stack([u, v, np.cross(u, v)])
                lab = np.column_stack([_NED_UP, lab_v, np.cross(_NED_UP, lab_v)])
                out.append(lab @ body.T)
    return out


def lab_field_ned(field_nT: float, inclination_deg: float) -> np.ndarray:
    """Lab field in north-east-down axes (magnetic north, so no east component)."""
    inc = math.radians(inclination_deg)
    return float(field_nT) * np.array([math.cos(inc), 0.0, math.sin(inc)])


def _body_axis_name(v) -> str:
    """Name of the signed body axis closest to v, e.g. '+X'."""
    k = int(np.argmax(np.abs(v)))
    return ("+" if v[k] > 0 else "-") + _AX[k]


@dataclass
class Position:
    number: int
    up: str                        # body axis pointing up, e.g. "+X"
    north: str                     # body axis pointing to magnetic north
    east: str
    R_body_to_ned: list            # 3x3
    expected_field_body_nT: list   # (3,)

    @property
    def label(self) -> str:
        return f"{self.up} up, {self.north} north"


def positions(field_nT: float, inclination_deg: float) -> list:
    b_lab = lab_field_ned(field_nT, inclination_deg)
    out = []
    for i, R in enumerate(twelve_positions()):
        out.append(Position(
            number=i + 1, up=_body_axis_name(R.T @ _NED_UP),
            north=_body_axis_name(R.T @ _NED_NORTH), east=_body_axis_name(R.T @ _NED_EAST),
            R_body_to_ned=np.round(R, 12).tolist(),
            expected_field_body_nT=[float(v) for v in R.T @ b_lab]))
    return out


# =======================================================================================
# Temperature profile
# =======================================================================================
@dataclass
class Step:
    level_C: float
    from_C: float                  # set-point the board may still be at (see module doc)
    step_C: float
    ramp_s: float                  # chamber ramp from the previous set-point
    settle_s: float                # tau ln(step / tolerance)
    record_s: float                # samples x period
    hold_s: float                  # settle + record, rounded up to whole minutes


@dataclass
class TestPlan:
    unit_id: str
    lab_field_nT: float
    inclination_deg: float
    positions: list                # of Position
    levels_C: list
    room_C: float
    board_tau_s: float
    settle_tolerance_C: float
    ramp_C_per_min: float
    sample_period_s: float
    samples_per_segment: int
    reposition_s: float
    steps: list                    # of Step, one position's cycle (the same in each)
    return_ramp_s: float
    assumptions: list = field(default_factory=list)

    # ---- derived -----------------------------------------------------------------------
    @property
    def position_duration_s(self) -> float:
        return (self.reposition_s + sum(s.ramp_s + s.hold_s for s in self.steps)
                + self.return_ramp_s)

    @property
    def total_duration_s(self) -> float:
        return len(self.positions) * self.position_duration_s

    @property
    def settle_total_s(self) -> float:
        return len(self.positions) * sum(s.settle_s for s in self.steps)

    @property
    def samples_total(self) -> int:
        """Samples recorded over the whole program at the plan's rate (ramps included)."""
        return int(self.total_duration_s // self.sample_period_s)

    def chamber_program(self) -> list:
        """The whole program as timed items: position, action (reposition / ramp / hold /
        return), start_s, duration_s, set-point at the end, and for holds the recording
        window (record_from_s, record_to_s) in program time."""
        out, t = [], 0.0
        for p in self.positions:
            out.append({"position": p.number, "action": "reposition", "start_s": t,
                        "duration_s": self.reposition_s, "setpoint_C": self.room_C,
                        "note": f"turn the jig: {p.label}"})
            t += self.reposition_s
            for s in self.steps:
                out.append({"position": p.number, "action": "ramp", "start_s": t,
                            "duration_s": s.ramp_s, "setpoint_C": s.level_C})
                t += s.ramp_s
                out.append({"position": p.number, "action": "hold", "start_s": t,
                            "duration_s": s.hold_s, "setpoint_C": s.level_C,
                            "record_from_s": t + s.hold_s - s.record_s,
                            "record_to_s": t + s.hold_s})
                t += s.hold_s
            out.append({"position": p.number, "action": "return", "start_s": t,
                        "duration_s": self.return_ramp_s, "setpoint_C": self.room_C})
            t += self.return_ramp_s
        return out

    def setpoint_profile(self, one_position=True):
        """(time_s, chamber set-point) corner points of one position's cycle (or all)."""
        t, T = [0.0], [self.room_C]
        items = self.chamber_program()
        if one_position:
            items = [i for i in items if i["position"] == self.positions[0].number]
        for it in items:
            t.append(it["start_s"] + it["duration_s"])
            T.append(it["setpoint_C"])
        return np.array(t), np.array(T)

    def to_json_dict(self) -> dict:
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION,
            "unit": self.unit_id,
            "lab_field_nT": self.lab_field_nT, "inclination_deg": self.inclination_deg,
            "heading_reference": "magnetic north (lab axes north-east-down)",
            "positions": [asdict(p) | {"label": p.label} for p in self.positions],
            "levels_C": list(self.levels_C), "room_C": self.room_C,
            "board_tau_s": self.board_tau_s, "settle_tolerance_C": self.settle_tolerance_C,
            "ramp_C_per_min": self.ramp_C_per_min, "sample_period_s": self.sample_period_s,
            "samples_per_segment": self.samples_per_segment,
            "reposition_s": self.reposition_s, "return_ramp_s": self.return_ramp_s,
            "steps": [asdict(s) for s in self.steps],
            "position_duration_s": self.position_duration_s,
            "total_duration_s": self.total_duration_s,
            "samples_total": self.samples_total,
            "chamber_program": self.chamber_program(),
            "assumptions": list(self.assumptions),
        }


def _ceil_minute(seconds: float) -> float:
    return 60.0 * math.ceil(seconds / 60.0 - 1e-9)


def settle_time_s(step_C: float, board_tau_s: float, tolerance_C: float) -> float:
    """Time for a first-order lag to come within tolerance of a step: tau ln(step/tol)."""
    step = abs(float(step_C))
    if step <= tolerance_C:
        return 0.0
    return float(board_tau_s) * math.log(step / tolerance_C)


MAX_RECORD_S = 86400.0
MAX_GRID_POINTS = 200_000
MAX_CYCLE_ROWS = 2e6


def make_plan(unit, *, lab_field_nT=None, inclination_deg=DEFAULT_INCLINATION_DEG,
              levels_C=DEFAULT_LEVELS_C, board_tau_min=DEFAULT_BOARD_TAU_MIN,
              settle_tol_C=DEFAULT_SETTLE_TOL_C, ramp_C_per_min=DEFAULT_RAMP_C_PER_MIN,
              sample_period_s=DEFAULT_SAMPLE_PERIOD_S,
              samples_per_segment=DEFAULT_SAMPLES_PER_SEGMENT, room_C=DEFAULT_ROOM_C,
              reposition_min=DEFAULT_REPOSITION_MIN) -> TestPlan:
    """The twelve-position thermal program for a unit (see the module docstring)."""
    src = getattr(unit, "path", None)
    F = lab_field_nT if lab_field_nT is not None else unit.lab_field_nT
    if F is None:
        raise InputError(src, "plan: the unit file has no lab_field_nT; give --lab-field-nT")
    checks = [("lab field", F, 1000.0, 1e6), ("inclination", inclination_deg, -90.0, 90.0),
              ("board time constant (min)", board_tau_min, 1e-3, 1e4),
              ("settling tolerance (degC)", settle_tol_C, 1e-3, 50.0),
              ("ramp rate (degC/min)", ramp_C_per_min, 1e-3, 100.0),
              ("sample period (s)", sample_period_s, 1e-3, 3600.0),
              ("samples per segment", samples_per_segment, 1, 1e6),
              ("repositioning time (min)", reposition_min, 0.0, 1e4),
              ("room temperature (degC)", room_C, -60.0, 60.0)]
    for name, v, lo, hi in checks:
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise InputError(src, f"plan: {name} {v!r} is outside [{lo:g}, {hi:g}]")
    levels = [float(v) for v in levels_C]
    if not levels:
        raise InputError(src, "plan: no temperature levels")
    if any(not math.isfinite(v) or not -150.0 <= v <= 200.0 for v in levels):
        raise InputError(src, f"plan: temperature levels must be in -150..200 degC: {levels}")
    if len(set(levels)) != len(levels):
        raise InputError(src, f"plan: repeated temperature level in {levels}")
    tau_s = 60.0 * float(board_tau_min)
    record_s = int(samples_per_segment) * float(sample_period_s)
    # each parameter may be in range and their product still absurd: a position held more
    # than a day at one level is no ground test (the program would run for years)
    if record_s > MAX_RECORD_S:
        raise InputError(src, f"plan: {int(samples_per_segment)} samples x "
                              f"{float(sample_period_s):g} s = {record_s:g} s of recording "
                              f"per position and level; at most {MAX_RECORD_S:g} s (one day)")
    rate = float(ramp_C_per_min) / 60.0
    steps = []
    prev = room_C
    for i, L in enumerate(levels):
        if i == 0:
            frm = max((room_C, levels[-1]), key=lambda v: abs(L - v))
            ramp = abs(L - room_C) / rate
        else:
            frm = prev
            ramp = abs(L - prev) / rate
        step = abs(L - frm)
        settle = settle_time_s(step, tau_s, settle_tol_C)
        steps.append(Step(level_C=L, from_C=float(frm), step_C=float(step), ramp_s=float(ramp),
                          settle_s=float(settle), record_s=float(record_s),
                          hold_s=_ceil_minute(settle + record_s)))
        prev = L
    assumptions = [
        f"board thermal time constant {board_tau_min:g} min"
        + (" (default: the boards sit in the jig inside the structure; the example "
           "campaigns show 10-20 min; measure yours on the first step and re-plan)"
           if board_tau_min == DEFAULT_BOARD_TAU_MIN else ""),
        f"settled: within {settle_tol_C:g} degC of the set-point; hold = tau ln(step / "
        f"{settle_tol_C:g} degC) + {int(samples_per_segment)} samples x {sample_period_s:g} s, "
        "counted from the end of the ramp (conservative: the boards follow part of the way "
        "during the ramp)",
        "the first level of each position is entered from between room temperature and the "
        "last level: its step is the larger of the two",
        f"chamber ramp {ramp_C_per_min:g} degC/min; the jig is turned at room temperature "
        f"({room_C:g} degC) in {reposition_min:g} min",
        f"lab field {F:.1f} nT, inclination {inclination_deg:g} deg, headings magnetic; the "
        "jig's reference edge is aligned with magnetic north to within a few degrees",
    ]
    plan = TestPlan(unit_id=unit.id, lab_field_nT=float(F), inclination_deg=float(inclination_deg),
                    positions=positions(F, inclination_deg), levels_C=levels, room_C=float(room_C),
                    board_tau_s=tau_s, settle_tolerance_C=float(settle_tol_C),
                    ramp_C_per_min=float(ramp_C_per_min), sample_period_s=float(sample_period_s),
                    samples_per_segment=int(samples_per_segment),
                    reposition_s=60.0 * float(reposition_min), steps=steps,
                    return_ramp_s=abs(levels[-1] - room_C) / rate, assumptions=assumptions)
    # the campaign file the program describes: one row per sample period over a position's
    # cycle (the profile figure's grid) must stay a file a lab can record and a tool read
    rows = plan.position_duration_s / float(sample_period_s)
    if rows > MAX_CYCLE_ROWS:
        raise InputError(src, f"plan: one position's cycle ({_hms(plan.position_duration_s)}) "
                              f"at {float(sample_period_s):g} s per sample is {rows:.3g} rows; "
                              f"at most {MAX_CYCLE_ROWS:g} (a longer sample period, faster "
                              "ramps or a shorter time constant)")
    return plan


# =======================================================================================
# Reading a whole program back (magcal simulate --plan)
# =======================================================================================
def plan_from_json_dict(d: dict, source=None) -> TestPlan:
    """The TestPlan of a plan.json written by `magcal plan` (InputError naming the key on
    anything malformed, missing or contradicting the steps).

    A plan is a contract between the lab and the tools: `magcal check` reads its levels and
    positions, `magcal simulate` its steps, and the lab runs its chamber program. A plan
    edited by hand whose summary fields (levels_C, board_tau_s, settle_tolerance_C,
    samples_per_segment, sample_period_s, ramp_C_per_min, room_C, return_ramp_s,
    lab_field_nT, inclination_deg) contradict its steps or positions would make each tool
    follow a different program, so it is refused (InputError naming the key; see
    _check_consistent). The derived items (position_duration_s, total_duration_s,
    samples_total, chamber_program) may be left out of a hand-edited plan and are then
    recomputed from the steps; given, they must agree with them too."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise InputError(source, f"not a {FORMAT} file (missing 'format': '{FORMAT}')")
    if d.get("format_version") != FORMAT_VERSION:
        raise InputError(source, f"format_version {d.get('format_version')!r} is not "
                                 f"supported (this is {FORMAT_VERSION})")

    def num(obj, key, where, lo=-math.inf, hi=math.inf):
        if isinstance(obj, dict) and key not in obj:
            raise InputError(source, f"key {where}{key}: missing (a number in "
                                     f"[{lo:g}, {hi:g}])")
        v = obj.get(key) if isinstance(obj, dict) else None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or not lo <= v <= hi:
            raise InputError(source, f"key {where}{key}: {v!r} is not a number in "
                                     f"[{lo:g}, {hi:g}]")
        return float(v)

    pos_fields = ("number", "up", "north", "east", "R_body_to_ned", "expected_field_body_nT")
    positions_ = []
    for i, p in enumerate(d.get("positions") or []):
        where = f"positions[{i}]."
        if not isinstance(p, dict) or any(k not in p for k in pos_fields):
            raise InputError(source, f"key positions[{i}]: needs {', '.join(pos_fields)}")
        R = np.asarray(p["R_body_to_ned"], dtype=float) if _is_matrix(p["R_body_to_ned"]) \
            else None
        if R is None or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) \
                or abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise InputError(source, f"key {where}R_body_to_ned: not a 3x3 rotation matrix")
        try:
            field_ = np.asarray(p["expected_field_body_nT"], dtype=float)
        except (TypeError, ValueError):
            field_ = np.zeros(0)
        if field_.shape != (3,) or not np.isfinite(field_).all():
            raise InputError(source, f"key {where}expected_field_body_nT: not 3 numbers")
        positions_.append(Position(number=int(num(p, "number", where, 1, 10**6)),
                                   up=str(p["up"]), north=str(p["north"]),
                                   east=str(p["east"]), R_body_to_ned=R.tolist(),
                                   expected_field_body_nT=[float(x) for x in field_]))
    if not positions_:
        raise InputError(source, "key positions: no positions")
    steps = []
    for i, s in enumerate(d.get("steps") or []):
        where = f"steps[{i}]."
        vals = {k: num(s, k, where, lo, hi) for k, lo, hi in (
            ("level_C", -150.0, 200.0), ("from_C", -150.0, 200.0), ("step_C", 0.0, 400.0),
            ("ramp_s", 0.0, 1e7), ("settle_s", 0.0, 1e7), ("record_s", 0.0, MAX_RECORD_S),
            ("hold_s", 0.0, 1e7))}
        if vals["hold_s"] < vals["record_s"]:
            raise InputError(source, f"key {where}hold_s: {vals['hold_s']:g} s is shorter "
                                     f"than its recording ({vals['record_s']:g} s)")
        steps.append(Step(**vals))
    if not steps:
        raise InputError(source, "key steps: no temperature steps")
    plan = TestPlan(
        unit_id=str(d.get("unit", "")), lab_field_nT=num(d, "lab_field_nT", "", 1000.0, 1e6),
        inclination_deg=num(d, "inclination_deg", "", -90.0, 90.0), positions=positions_,
        levels_C=[s.level_C for s in steps], room_C=num(d, "room_C", "", -60.0, 60.0),
        board_tau_s=num(d, "board_tau_s", "", 0.0, 1e7),
        settle_tolerance_C=num(d, "settle_tolerance_C", "", 1e-3, 50.0),
        ramp_C_per_min=num(d, "ramp_C_per_min", "", 1e-3, 100.0),
        sample_period_s=num(d, "sample_period_s", "", 1e-3, 3600.0),
        samples_per_segment=int(num(d, "samples_per_segment", "", 1, 1e6)),
        reposition_s=num(d, "reposition_s", "", 0.0, 1e7), steps=steps,
        return_ramp_s=num(d, "return_ramp_s", "", 0.0, 1e7),
        assumptions=[str(a) for a in d.get("assumptions", [])])
    _check_consistent(d, plan, source)
    rows = plan.total_duration_s / plan.sample_period_s
    if rows > len(plan.positions) * MAX_CYCLE_ROWS:
        raise InputError(source, f"plan: {rows:.3g} samples in all; at most "
                                 f"{len(plan.positions) * MAX_CYCLE_ROWS:g}")
    return plan


def _agree(a, b) -> bool:
    """Two values of the same quantity computed by the same formula agree: a plan written
    by `magcal plan` round-trips through JSON exactly (repr of a float), so the tolerance
    only has to absorb the 12-digit rounding of R_body_to_ned (relative 1e-12) and
    recomputing sums in another order; 1e-9 relative (plus 1e-6 absolute for zeros) is far
    above that and far below any edit that means something (a microsecond of a hold)."""
    return abs(float(a) - float(b)) <= 1e-9 * max(abs(float(a)), abs(float(b))) + 1e-6


def _check_consistent(d: dict, plan: TestPlan, source) -> None:
    """InputError naming the first key of plan.json `d` that contradicts the steps and
    positions `plan` was read from (see plan_from_json_dict)."""
    def bad(key, msg, hint="a plan is one program: make it again with magcal plan, or edit "
                           "both"):
        raise InputError(source, f"key {key}: {msg}; {hint}")

    # levels: check reads levels_C, simulate follows the steps
    if "levels_C" not in d:
        bad("levels_C", "missing (the plan's temperature levels, those of its steps)")
    levels = d["levels_C"]
    if not isinstance(levels, list) or len(levels) != len(plan.steps) or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not _agree(v, s.level_C)
            for v, s in zip(levels, plan.steps)):
        bad("levels_C", f"{levels!r} contradicts the steps' levels "
                        f"{[s.level_C for s in plan.steps]}")
    rate = plan.ramp_C_per_min / 60.0
    record_s = plan.samples_per_segment * plan.sample_period_s
    for i, s in enumerate(plan.steps):
        w = f"steps[{i}]."
        if i == 0:
            # entered from the farther of room temperature and the last level (make_plan)
            far = max(abs(s.level_C - plan.room_C), abs(s.level_C - plan.steps[-1].level_C))
            if not (_agree(s.from_C, plan.room_C) or _agree(s.from_C, plan.steps[-1].level_C)) \
                    or not _agree(abs(s.level_C - s.from_C), far):
                bad(w + "from_C", f"{s.from_C:g} degC: the first level is entered from the "
                                  f"farther of room_C ({plan.room_C:g}) and the last level "
                                  f"({plan.steps[-1].level_C:g})")
        elif not _agree(s.from_C, plan.steps[i - 1].level_C):
            bad(w + "from_C", f"{s.from_C:g} degC is not the previous level "
                              f"({plan.steps[i - 1].level_C:g} degC)")
        if not _agree(s.step_C, abs(s.level_C - s.from_C)):
            bad(w + "step_C", f"{s.step_C:g} degC is not |level_C - from_C| = "
                              f"{abs(s.level_C - s.from_C):g} degC")
        settle = settle_time_s(s.step_C, plan.board_tau_s, plan.settle_tolerance_C)
        if not _agree(s.settle_s, settle):
            implied = ""
            if s.step_C > plan.settle_tolerance_C:
                tau = s.settle_s / math.log(s.step_C / plan.settle_tolerance_C)
                implied = f", which needs board_tau_s {tau:g} s"
            bad("board_tau_s", f"{plan.board_tau_s:g} s (settle_tolerance_C "
                               f"{plan.settle_tolerance_C:g}) contradicts {w}settle_s "
                               f"{s.settle_s:g} s (tau ln(step_C / tolerance) = {settle:g} s"
                               f"{implied})")
        if not _agree(s.record_s, record_s):
            bad("samples_per_segment", f"{plan.samples_per_segment} x sample_period_s "
                                       f"{plan.sample_period_s:g} s = {record_s:g} s contradicts "
                                       f"{w}record_s {s.record_s:g} s")
        prev = plan.room_C if i == 0 else plan.steps[i - 1].level_C
        if not _agree(s.ramp_s, abs(s.level_C - prev) / rate):
            bad("ramp_C_per_min", f"{plan.ramp_C_per_min:g} degC/min contradicts {w}ramp_s "
                                  f"{s.ramp_s:g} s ({abs(s.level_C - prev):g} degC from "
                                  f"{prev:g} degC takes {abs(s.level_C - prev) / rate:g} s)")
        # a hold may be lengthened by hand, not shortened below its settling + recording:
        # the recording would start before the boards settle
        if s.hold_s < s.settle_s + s.record_s - 1e-6:
            bad(w + "hold_s", f"{s.hold_s:g} s is shorter than settle_s + record_s = "
                              f"{s.settle_s + s.record_s:g} s")
    ret = abs(plan.steps[-1].level_C - plan.room_C) / rate
    if not _agree(plan.return_ramp_s, ret):
        bad("return_ramp_s", f"{plan.return_ramp_s:g} s contradicts the return from the last "
                             f"level to room_C at ramp_C_per_min ({ret:g} s)")
    # positions: the field each expects is R^T B_lab(lab_field_nT, inclination_deg)
    b_lab = lab_field_ned(plan.lab_field_nT, plan.inclination_deg)
    for i, p in enumerate(plan.positions):
        R = np.asarray(p.R_body_to_ned, float)
        got = np.asarray(p.expected_field_body_nT, float)
        want = R.T @ b_lab
        if abs(np.linalg.norm(got) - plan.lab_field_nT) > 1e-6 * plan.lab_field_nT:
            bad("lab_field_nT", f"{plan.lab_field_nT:g} nT contradicts "
                                f"positions[{i}].expected_field_body_nT (magnitude "
                                f"{np.linalg.norm(got):.6g} nT)")
        if np.max(np.abs(got - want)) > 1e-6 * plan.lab_field_nT:
            bad(f"positions[{i}].expected_field_body_nT",
                f"{np.round(got, 3).tolist()} nT is not R_body_to_ned^T of the lab field "
                f"({plan.lab_field_nT:g} nT at inclination_deg {plan.inclination_deg:g}): "
                f"{np.round(want, 3).tolist()} nT")
        for key, lab in (("up", _NED_UP), ("north", _NED_NORTH), ("east", _NED_EAST)):
            if getattr(p, key) != _body_axis_name(R.T @ lab):
                bad(f"positions[{i}].{key}", f"{getattr(p, key)!r} contradicts R_body_to_ned "
                                             f"({_body_axis_name(R.T @ lab)})")
    # derived items: optional, else as recomputed from the steps
    for key in ("position_duration_s", "total_duration_s", "samples_total"):
        if key in d and (isinstance(d[key], bool) or not isinstance(d[key], (int, float))
                         or not _agree(d[key], getattr(plan, key))):
            bad(key, f"{d[key]!r} contradicts the steps ({getattr(plan, key):g})",
                "leave the derived keys out to have them recomputed")
    if "chamber_program" in d:
        prog, want = d["chamber_program"], plan.chamber_program()
        if not isinstance(prog, list) or len(prog) != len(want):
            bad("chamber_program", f"{len(prog) if isinstance(prog, list) else prog!r} "
                                   f"items, the steps make {len(want)}",
                "leave it out to have it recomputed")
        for i, (g, w) in enumerate(zip(prog, want)):
            for k, v in w.items():
                gv = g.get(k) if isinstance(g, dict) else None
                same = (gv == v) if isinstance(v, (str, int)) and not isinstance(v, float) \
                    else (isinstance(gv, (int, float)) and not isinstance(gv, bool)
                          and _agree(gv, v))
                if not same:
                    bad(f"chamber_program[{i}].{k}", f"{gv!r} contradicts the steps ({v!r})",
                        "leave chamber_program out to have it recomputed")


def _is_matrix(v) -> bool:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.shape == (3, 3) and bool(np.isfinite(a).all())


def load_plan(path) -> TestPlan:
    """Read a whole plan.json written by `magcal plan` (InputError on anything malformed)."""
    path = Path(path)
    return plan_from_json_dict(load_json(path, "test plan"), path)


# =======================================================================================
# Reading a profile back (magcal check --plan)
# =======================================================================================
@dataclass
class PlanProfile:
    """What `check` needs from a plan: positions with expected field, levels, samples."""
    source: str
    positions: list                # [{"number": int, "expected_field_body_nT": [3], "label"}]
    levels_C: list
    samples_per_segment: int
    sample_period_s: float
    settle_tolerance_C: float

    @staticmethod
    def from_plan(plan: TestPlan, source="default test program (magcal plan defaults)"):
        return PlanProfile(source=source,
                           positions=[{"number": p.number, "label": p.label, "up": p.up,
                                       "expected_field_body_nT": p.expected_field_body_nT}
                                      for p in plan.positions],
                           levels_C=list(plan.levels_C),
                           samples_per_segment=plan.samples_per_segment,
                           sample_period_s=plan.sample_period_s,
                           settle_tolerance_C=plan.settle_tolerance_C)


def load_profile(path) -> PlanProfile:
    """Read a plan.json written by `magcal plan` (InputError on anything malformed)."""
    # the whole plan, checked as `magcal simulate` checks it: a plan whose levels_C
    # contradict its steps would have check and simulate follow different programs
    path = Path(path)
    return PlanProfile.from_plan(load_plan(path), source=str(path))


# =======================================================================================
# The document
# =======================================================================================
def _hms(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60:02d} min" if m >= 60 else f"{m} min"


def predicted_board_temperature(plan: TestPlan, time_s, one_position=True):
    """Board temperature (first-order lag of the chamber set-point, ramps linear) on a time
    grid, starting settled at room temperature."""
    from generator.campaign.board_thermal import first_order_lag
    tc, Tc = plan.setpoint_profile(one_position)
    setpoint = np.interp(time_s, tc, Tc)
    return setpoint, first_order_lag(np.asarray(time_s, float), setpoint, plan.board_tau_s,
                                     initial=plan.room_C)


def window_check(plan: TestPlan, step_s=10.0) -> dict:
    """Board temperature predicted over the whole program (first-order lag of the chamber
    set-point, starting settled at room temperature): per level, the largest distance from
    the level inside any position's recording window, and the window in a cycle (min)."""
    # at most MAX_GRID_POINTS points, however long the program (memory stays bounded)
    step_s = max(step_s, plan.total_duration_s / MAX_GRID_POINTS)
    t = np.arange(0.0, plan.total_duration_s + step_s, step_s)
    _, board = predicted_board_temperature(plan, t, one_position=False)
    out = {}
    t0 = {p.number: None for p in plan.positions}
    for it in plan.chamber_program():
        if it["action"] == "reposition":
            t0[it["position"]] = it["start_s"]
        if it["action"] != "hold":
            continue
        w = (t >= it["record_from_s"]) & (t <= it["record_to_s"])
        dev = float(np.max(np.abs(board[w] - it["setpoint_C"]))) if w.any() else float("nan")
        L = it["setpoint_C"]
        cur = out.get(L)
        if cur is None or dev > cur["max_dev_C"]:
            out[L] = {"max_dev_C": dev, "worst_position": it["position"],
                      "from_min": (it["record_from_s"] - t0[it["position"]]) / 60.0,
                      "to_min": (it["record_to_s"] - t0[it["position"]]) / 60.0}
    return out
