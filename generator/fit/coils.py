"""Magnetorquer coupling K (seed 000, section "coils and the boom magnetometer").

The coil field at a sensor is linear in the coil currents. In the chain it is subtracted
in raw frame-axis units, before the calibration matrix:

    B = M(T) (B~ - b(T) - K i)            K: 3 x ncoil, nT/A, the sensor's frame axes

so K is what the coil adds to the *uncalibrated* frame-axis reading per ampere (the
truth's K_coil_frame_nT_per_A). It is fitted from a coil campaign (coils.csv: the unit
static in the jig, each magnetorquer stepped through +-25..100 mA) with no calibration at
all: per sensor, per frame axis, ordinary least squares of B~ on the currents plus one
constant per static position (the constant absorbs the field, the offsets and anything
else that does not change while the unit sits still). M never enters, so K comes out in
the chain's units. The temperature must hold still within a position (it does in the jig:
the constant does not follow an offset drifting with temperature).

Uncertainty: the OLS covariance with each axis' residual variance.

Reports:
* `interference_table`: |K column| x current (default 0.1 A) per sensor and coil, in nT and
  as % of the lab field, carried to the seed's points (5, 15, 30 cm) by the distance law
  of a coil study when one is given (else an assumed distance and 1/r^3, said so per
  row), beside the seed's 30 cm figures (167.87 nT without the solar panel, 307.57 nT
  with it, 0.1 A); also the distance at which the seed's coil would give the measured
  interference.
* The coil study (`fit_coil_study`, docs/coil_study.md): K per distance and panel state
  measured at known distances, and the distance law |K| = K30 (30 cm / r)^n fitted to
  them with its uncertainty.
* `correction_table`: |B| (and vector, where reference vectors exist) RMS error of the
  calibrated readings with and without subtracting K i, per sensor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from generator.errors import InputError
from generator.io.coil_study import (DISTANCE_COLUMN, PANEL_COLUMN, TEST_SENSOR_KEY,  # noqa: F401
                                     check_study, coil_columns, is_coil_study, panel_flags,
                                     static_rows, study_sensors)

# Seed 000: coil at 30 cm (point 6, the boom length) driven at 0.1 A, mean absolute error
SEED_CURRENT_A = 0.1
SEED_POINTS_CM = (5.0, 15.0, 30.0)            # points 1, 3 and 6
SEED_30CM_NO_PANEL_NT = 167.87               # 0.33 %
SEED_30CM_PANEL_NT = 307.57                  # 0.61 %

# Assumed distance from a sensor to the magnetorquers when the caller gives none.
#   boom: the boom length, 30 cm (seed 000: point 6 "the length of the boom");
#   body: 10 cm -- an assumption: the flight computer inside a ~10 cm CubeSat body, about
#         one body width from the torquer coils. Pass distance_cm to override.
DEFAULT_DISTANCE_CM = {"boom": 30.0, "body": 10.0}

# A distance law is flagged when its chi2 exceeds this quantile of the chi2 distribution at
# its degrees of freedom: with points that scatter only by their stated 1-sigma that
# happens to one law in a hundred; beyond it the errors or the power law are off.
CHI2_QUANTILE = 0.99


@dataclass
class SensorCoilFit:
    name: str
    coils: tuple                       # current column names, column order of K
    K_nT_per_A: np.ndarray             # (3, ncoil) frame axes
    K_sigma_nT_per_A: np.ndarray       # (3, ncoil) 1-sigma
    residual_sigma_nT: np.ndarray      # (3,) per frame axis
    n_samples: int
    n_positions: int
    constants_nT: np.ndarray           # (n_positions, 3) per-position constant

    def column_norm_nT_per_A(self) -> np.ndarray:
        """|K[:, j]| per coil."""
        return np.linalg.norm(self.K_nT_per_A, axis=0)

    def column_norm_sigma_nT_per_A(self) -> np.ndarray:
        """1-sigma of |K[:, j]| (first order, axes independent)."""
        n = self.column_norm_nT_per_A()
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.sqrt(np.sum((self.K_nT_per_A * self.K_sigma_nT_per_A) ** 2, axis=0)) / n
        return np.where(n > 0, s, np.linalg.norm(self.K_sigma_nT_per_A, axis=0))

    def to_dict(self) -> dict:
        return {"coils": list(self.coils), "K_nT_per_A": self.K_nT_per_A.tolist(),
                "K_sigma_nT_per_A": self.K_sigma_nT_per_A.tolist(),
                "residual_sigma_nT": self.residual_sigma_nT.tolist(),
                "n_samples": self.n_samples, "n_positions": self.n_positions}


@dataclass
class CoilFit:
    coils: tuple
    sensors: dict                      # name -> SensorCoilFit
    notes: list = field(default_factory=list)

    def K(self) -> dict:
        """{sensor: K (3, ncoil)} for the chain / calibrated_fields."""
        return {n: f.K_nT_per_A for n, f in self.sensors.items()}

    def to_dict(self) -> dict:
        return {"coils": list(self.coils),
                "sensors": {n: f.to_dict() for n, f in self.sensors.items()},
                "notes": list(self.notes)}


def fit_coupling(field_frame_nT, coil_A, group, *, coils=None, name="", source=None
                 ) -> SensorCoilFit:
    """OLS of the raw frame-axis field on the currents plus a constant per group.

    field_frame_nT (N, 3), coil_A (N, ncoil), group (N,) integer labels of static
    positions; all rows must be finite (select them first).
    """
    y = np.asarray(field_frame_nT, float)
    I = np.asarray(coil_A, float)
    g = np.asarray(group)
    n, nc = I.shape
    coils = tuple(coils) if coils is not None else tuple(f"coil{j}" for j in range(nc))
    labels, gi = np.unique(g, return_inverse=True)
    ng = len(labels)
    p = nc + ng
    if n <= p:
        raise InputError(source, f"coils: {name}: {n} usable samples for {p} unknowns "
                                 f"({nc} couplings + {ng} position constants)")
    # currents relative to their position mean: the constants separate exactly
    Ic = I.copy()
    for k in range(ng):
        sel = gi == k
        Ic[sel] -= I[sel].mean(axis=0)
    span = np.sqrt(np.sum(Ic ** 2, axis=0))
    for j in range(nc):
        if span[j] == 0.0:
            raise InputError(source, f"coils: {name}: current {coils[j]!r} never changes "
                                     "within a static position: its coupling is undetermined")
    G = Ic.T @ Ic
    if np.linalg.cond(G) > 1e10:
        raise InputError(source, f"coils: {name}: the coil currents always move together "
                                 "(design matrix singular): step them separately")
    Ginv = np.linalg.inv(G)
    yc = y.copy()
    const = np.zeros((ng, 3))
    for k in range(ng):
        sel = gi == k
        const[k] = y[sel].mean(axis=0)
        yc[sel] -= const[k]
    K_T = Ginv @ (Ic.T @ yc)                       # (nc, 3)
    r = yc - Ic @ K_T
    s2 = np.sum(r ** 2, axis=0) / (n - p)           # per frame axis
    K_sig = np.sqrt(np.outer(np.diag(Ginv), s2)).T  # (3, nc)
    # constants at zero current
    for k in range(ng):
        sel = gi == k
        const[k] -= I[sel].mean(axis=0) @ K_T
    return SensorCoilFit(name=name, coils=coils, K_nT_per_A=K_T.T.copy(),
                         K_sigma_nT_per_A=K_sig, residual_sigma_nT=np.sqrt(s2),
                         n_samples=int(n), n_positions=int(ng), constants_nT=const)


def fit_coils(unit, telemetries, *, coils=None, sensors=None) -> CoilFit:
    """K per sensor from one or more coil-campaign files (Telemetry objects).

    coils: current column names (default: every coil_*_A column of the first file, sorted;
    all files must carry them). Static positions: (file, position) for position > 0;
    samples with position 0 (moving) are left out; a file without a position column is
    taken as one static position (noted). Rows with a missing current or an unusable
    reading are left out.
    """
    from generator.io import telemetry_csv as _telemetry
    if not telemetries:
        raise InputError(unit.path, "coils: no telemetry files given")
    if coils is None:
        coils = coil_columns(telemetries[0])
    coils = tuple(coils)
    if not coils:
        raise InputError(telemetries[0].path, "coils: no coil_*_A current columns")
    names = [s.name for s in unit.sensors] if sensors is None else list(sensors)
    notes = []
    per_sensor = {n: ([], [], []) for n in names}
    for fi, tel in enumerate(telemetries):
        missing = [c for c in coils if c not in tel.columns]
        if missing:
            raise InputError(tel.path, f"coils: missing current column(s) {missing}")
        I = np.column_stack([tel.columns[c] for c in coils])
        if "position" in tel.columns:
            pos = tel.columns["position"]
            static = np.isfinite(pos) & (pos > 0)
            group = np.where(static, fi * 100000 + np.nan_to_num(pos), -1).astype(np.int64)
            if (~static).any():
                notes.append(f"{tel.path}: {int((~static).sum())} samples not in a static "
                             "position, left out")
        else:
            static = np.ones(tel.n, dtype=bool)
            group = np.full(tel.n, fi * 100000, dtype=np.int64)
            notes.append(f"{tel.path}: no position column; the file is taken as one static "
                         "position")
        ok_I = np.isfinite(I).all(axis=1)
        data = _telemetry.preprocess(tel, unit)
        for n in names:
            sd = data[n]
            sel = static & ok_I & sd.usable & np.isfinite(sd.field_frame_nT).all(axis=1)
            per_sensor[n][0].append(sd.field_frame_nT[sel])
            per_sensor[n][1].append(I[sel])
            per_sensor[n][2].append(group[sel])
    out = {}
    src = ", ".join(str(t.path) for t in telemetries)
    for n in names:
        y = np.concatenate(per_sensor[n][0])
        I = np.concatenate(per_sensor[n][1])
        g = np.concatenate(per_sensor[n][2])
        out[n] = fit_coupling(y, I, g, coils=coils, name=n, source=src)
    return CoilFit(coils=coils, sensors=out, notes=notes)


# =======================================================================================
# Reports
# =======================================================================================
def default_distance_cm(spec) -> float:
    return DEFAULT_DISTANCE_CM.get(spec.frame, DEFAULT_DISTANCE_CM["body"])


def scale_power(value_at_r0, r0_cm, r_cm, exponent):
    """Power-law fall-off: value(r) = value(r0) (r0 / r)^exponent."""
    return np.asarray(value_at_r0, float) * (float(r0_cm) / np.asarray(r_cm, float)) ** exponent


def scale_inverse_cube(value_at_r0, r0_cm, r_cm):
    """Dipole fall-off: value(r) = value(r0) (r0 / r)^3."""
    return scale_power(value_at_r0, r0_cm, r_cm, 3.0)


def equivalent_distance_cm(interference_nT, ref_nT=SEED_30CM_NO_PANEL_NT, ref_r_cm=30.0,
                           exponent=3.0):
    """Distance at which a coil giving ref_nT at ref_r_cm would give interference_nT."""
    return float(ref_r_cm * (ref_nT / float(interference_nT)) ** (1.0 / exponent))


def interference_table(unit, coil_fit: CoilFit, *, current_A: float = SEED_CURRENT_A,
                       lab_field_nT: float | None = None, distance_cm: dict | None = None,
                       points_cm=SEED_POINTS_CM, study: "CoilStudy | None" = None) -> list:
    """Rows {sensor, coil, K_col_nT_per_A, sigma, interference_nT, pct_of_lab_field,
    distance_cm, distance_source, law (DistanceLaw or None), law_is_own, exponent,
    at_cm {r: nT}, seed_no_panel_at_cm {r: nT} (the seed's 30 cm figure scaled by
    r^-exponent; only 30 cm is measured in the seed), seed_panel_at_cm (each panel state
    scaled by its own law: seed_no_panel_law, seed_panel_law, the row's law where the study
    did not measure that state, None: 1/r^3), equivalent_distance_cm, flags [str]}.

    With a coil study (fit_coil_study) each row takes the law measured for its own sensor
    and coil (law_is_own), else the law the study measured for that coil on another sensor,
    carried to this sensor (law_is_own False, said so in distance_source); the fall-off is
    that law's (its exponent, not 3) and the sensor's distance is where the law gives the
    interference measured on that sensor. A coil the study never measured gets no distance
    and no values by distance (distance_source 'not measured ...', distance_cm None,
    at_cm {}). flags: the law's misfit and its extrapolation beyond the measured distances
    (DistanceLaw.flags) at the row's distance and at points_cm. distance_cm {sensor: cm}
    given here wins over the study's distance. Without a study nothing is measured about
    distance: the distance is the assumption DEFAULT_DISTANCE_CM by frame and the
    fall-off a dipole's (distance_source 'assumed').
    """
    lab = lab_field_nT if lab_field_nT is not None else unit.lab_field_nT
    rows = []
    for name, f in coil_fit.sensors.items():
        spec = unit.sensor(name)
        norms = f.column_norm_nT_per_A()
        sig = f.column_norm_sigma_nT_per_A()
        for j, coil in enumerate(f.coils):
            x = float(norms[j] * current_A)
            law, own = _study_law(study, name, coil)
            n = 3.0 if law is None else law.exponent
            flags = []
            r0_sigma = None
            if (distance_cm or {}).get(name) is not None:
                r0, source = float(distance_cm[name]), "given"
            elif study is not None and law is None:
                r0, source = None, (f"not measured: the coil study has no {coil}")
            elif law is not None and norms[j] > 0:
                r0, r0_sigma = law.distance_cm(norms[j], sig[j])
                source = (f"coil study, this sensor's law ({PANEL_STATE[law.panel]})" if own
                          else f"coil study, the law of {law.sensor} {law.coil} "
                               f"({PANEL_STATE[law.panel]}) carried to this sensor")
            else:
                r0, source = default_distance_cm(spec), "assumed"
            if law is not None:
                flags = law.flags(r0, *points_cm)
            # the seed's figures carried to points_cm: each panel state by its own law
            # (the study's law of this row's sensor and coil in that state), else by the
            # row's law (the other state's: said so by seed_*_law's panel), else 1/r^3
            law_np = _panel_law(study, law, 0)
            law_p = _panel_law(study, law, 1)
            n_np = 3.0 if law_np is None else law_np.exponent
            n_p = 3.0 if law_p is None else law_p.exponent
            rows.append({
                "sensor": name, "coil": coil, "frame": spec.frame,
                "K_col_nT_per_A": float(norms[j]), "K_col_sigma_nT_per_A": float(sig[j]),
                "current_A": current_A, "interference_nT": x,
                "interference_sigma_nT": float(sig[j] * current_A),
                "pct_of_lab_field": (100.0 * x / lab) if lab else None,
                "distance_cm": r0, "distance_sigma_cm": r0_sigma, "distance_source": source,
                "law": law, "law_is_own": bool(own), "exponent": n if r0 is not None else None,
                "at_cm": ({} if r0 is None else
                          {float(r): float(scale_power(x, r0, r, n)) for r in points_cm}),
                "at_cm_sigma": ({} if r0 is None else
                                {float(r): _at_sigma(x, float(sig[j] * current_A), r0, r, law,
                                                     source, current_A)
                                 for r in points_cm}),
                "seed_no_panel_at_cm": {float(r): float(scale_power(
                    SEED_30CM_NO_PANEL_NT * current_A / SEED_CURRENT_A, 30.0, r, n_np))
                    for r in points_cm},
                "seed_panel_at_cm": {float(r): float(scale_power(
                    SEED_30CM_PANEL_NT * current_A / SEED_CURRENT_A, 30.0, r, n_p))
                    for r in points_cm},
                "seed_no_panel_law": law_np, "seed_panel_law": law_p,
                "equivalent_distance_cm": (equivalent_distance_cm(
                    x, SEED_30CM_NO_PANEL_NT * current_A / SEED_CURRENT_A, exponent=n_np)
                    if x > 0 else None),
                "flags": flags,
            })
    return rows


PANEL_STATE = {0: "without panel", 1: "with panel"}


def _at_sigma(x, x_sigma, r0, r, law, source, current_A):
    """1-sigma of the interference x (at r0) carried to r. On a law's distance (source
    not 'given'/'assumed') the value is the law's own, so is its 1-sigma; at a given or
    assumed distance: x's 1-sigma and the law's exponent's, the distance itself carries
    none (it is not measured)."""
    if law is not None and source not in ("given", "assumed"):
        sig = law.sigma_at(r, current_A)
        return None if sig is None else float(sig)
    rel2 = (x_sigma / x) ** 2 if x > 0 else 0.0
    if law is not None and law.exponent_sigma is not None:
        rel2 += (np.log(r0 / r) * law.exponent_sigma) ** 2
    n = 3.0 if law is None else law.exponent
    return float(scale_power(x, r0, r, n) * np.sqrt(rel2))


def _panel_law(study, law, panel):
    """The study's law of law's sensor and coil in the given panel state; law itself when
    the study did not measure that state (its panel then says which state it is); None
    without a law."""
    if law is None or law.panel == panel or study is None:
        return law
    return study.law(law.sensor, law.coil, panel) or law


def _study_law(study, sensor, coil) -> tuple:
    """(law, own) a sensor and coil take from a coil study: the study's law of that sensor
    and coil (own True), else of that coil on another sensor (own False), else (None,
    False); without the panel (the flight configuration's torquer field) where measured,
    then the one with the most points."""
    if study is None:
        return None, False
    laws = [w for w in study.laws if w.coil == coil]
    for own in (True, False):
        ws = [w for w in laws if (w.sensor == sensor) == own]
        if ws:
            return min(ws, key=lambda w: (w.panel, -w.n_points)), own
    return None, False


def format_interference_table(rows) -> str:
    if not rows:
        return ""
    pts = list(rows[0]["seed_no_panel_at_cm"])
    head = ("| sensor | coil | K col nT/A | at {I} A nT | % lab | assumed r cm | "
            + " | ".join(f"@{r:g} cm" for r in pts)
            + " | seed no panel " + "/".join(f"{r:g}" for r in pts)
            + " cm | seed panel " + "/".join(f"{r:g}" for r in pts) + " cm | seed-coil r_eq cm |")
    head = head.replace("{I}", f"{rows[0]['current_A']:g}")
    lines = [head, "|" + "---|" * (9 + len(pts))]
    for r in rows:
        seed_np = "/".join(f"{r['seed_no_panel_at_cm'][p]:.0f}" for p in pts)
        seed_p = "/".join(f"{r['seed_panel_at_cm'][p]:.0f}" for p in pts)
        pct = f"{r['pct_of_lab_field']:.3f}" if r["pct_of_lab_field"] is not None else "-"
        lines.append(
            f"| {r['sensor']} | {r['coil']} | {r['K_col_nT_per_A']:.0f} +- "
            f"{r['K_col_sigma_nT_per_A']:.0f} | {r['interference_nT']:.1f} | {pct} | "
            + ("not measured | " if r["distance_cm"] is None else f"{r['distance_cm']:g} | ")
            + " | ".join(f"{r['at_cm'][p]:.1f}" if p in r["at_cm"] else "-" for p in pts)
            + f" | {seed_np} | {seed_p} | "
            + (f"{r['equivalent_distance_cm']:.1f} |" if r["equivalent_distance_cm"] else "- |"))
    lines.append("seed 000 measured only the 30 cm point (167.87 nT without the solar panel, "
                 "307.57 nT with it, 0.1 A); its 5 and 15 cm columns are that figure scaled by "
                 "1/r^3. r_eq: distance at which the seed's coil (no panel) would give the "
                 "fitted interference.")
    return "\n".join(lines)


def correction_table(unit, tel, calibrations, coil_fit: CoilFit, *, H_boom_to_body=None
                     ) -> dict:
    """Per sensor, RMS errors of the calibrated field on a file without and with the
    K i correction: {sensor: {"rms_norm_nT": {"without", "with"}, "rms_vector_nT":
    {...} or None, "rms_norm_on_nT": {...} (samples with current only), "n", "n_on"}}.
    |B| reference: ref_norm_nT, else the unit's lab_field_nT; vector reference: ref_x/y/z_nT
    (body frame = the boom board's frame in the jig) when present. H_boom_to_body: give it
    when the file was taken with the boom deployed; the boom sensors' reference vectors are
    then H^T ref."""
    from generator.io import telemetry_csv as _telemetry
    data = _telemetry.preprocess(tel, unit)
    I = np.column_stack([tel.columns[c] for c in coil_fit.coils])
    if tel.has("ref_norm_nT"):
        ref_norm = tel.columns["ref_norm_nT"]
    elif unit.lab_field_nT:
        ref_norm = np.full(tel.n, float(unit.lab_field_nT))
    else:
        raise InputError(tel.path, "coils: no ref_norm_nT column and no lab_field_nT")
    ref_vec = (np.column_stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"])
               if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT") else None)
    on = np.any(np.nan_to_num(I) != 0.0, axis=1)
    out = {}
    for name, f in coil_fit.sensors.items():
        if name not in calibrations:
            continue
        sd = data[name]
        ok = sd.usable & np.isfinite(I).all(axis=1) & np.isfinite(ref_norm)
        cal = calibrations[name]
        res = {"n": int(ok.sum()), "n_on": int((ok & on).sum())}
        for key in ("rms_norm_nT", "rms_norm_on_nT", "rms_vector_nT"):
            res[key] = {}
        for label, x in (("without", sd.field_frame_nT),
                         ("with", sd.field_frame_nT - np.nan_to_num(I) @ f.K_nT_per_A.T)):
            B = cal.apply64(x, sd.temp_C)
            e = np.linalg.norm(B, axis=1) - ref_norm
            res["rms_norm_nT"][label] = float(np.sqrt(np.mean(e[ok] ** 2)))
            res["rms_norm_on_nT"][label] = (float(np.sqrt(np.mean(e[ok & on] ** 2)))
                                            if (ok & on).any() else None)
            if ref_vec is not None and cal.body_frame:
                rv = ref_vec
                if H_boom_to_body is not None and unit.sensor(name).frame == "boom":
                    rv = ref_vec @ np.asarray(H_boom_to_body, float)
                ev = B - rv
                res["rms_vector_nT"][label] = float(np.sqrt(np.mean(ev[ok] ** 2)))
        if not res["rms_vector_nT"]:
            res["rms_vector_nT"] = None
        out[name] = res
    return out


def format_correction_table(table: dict) -> str:
    lines = ["| sensor | |B| RMS without K nT | with K nT | |B| RMS, current on: without | "
             "with | vector RMS without | with |", "|---|---:|---:|---:|---:|---:|---:|"]
    for n, r in table.items():
        v = r["rms_vector_nT"] or {}
        lines.append(
            f"| {n} | {r['rms_norm_nT']['without']:.1f} | {r['rms_norm_nT']['with']:.1f} | "
            f"{_f(r['rms_norm_on_nT']['without'])} | {_f(r['rms_norm_on_nT']['with'])} | "
            f"{_f(v.get('without'))} | {_f(v.get('with'))} |")
    return "\n".join(lines)


def _f(x):
    return "-" if x is None else f"{x:.1f}"


def has_coil_steps(tel) -> bool:
    """A coil campaign: magnetorquer currents that step while the unit stands in static
    positions (a `position` column > 0). Orbit telemetry with B-dot currents is not one:
    its field turns with the satellite, which a per-position constant cannot absorb.
    Neither is a coil study (a `coil_distance_cm` column): its test coil is not where the
    flight magnetorquers are (fit_coil_study)."""
    cols = [c for c in tel.columns if c.startswith("coil_") and c.endswith("_A")]
    if is_coil_study(tel):
        return False
    if not cols or "position" not in tel.columns:
        return False
    static = tel.columns["position"] > 0
    return bool(static.any()) and any(np.nanmax(np.abs(tel.columns[c][static])) > 0
                                      for c in cols)


# =======================================================================================
# The coil study: interference at known distances (docs/coil_study.md). Its format and
# input rules (distances > 0, panel 0/1, known test sensors, two or more distances per
# panel state, a current that steps) are generator/io/coil_study.py, checked when the
# file is read.
# =======================================================================================
@dataclass
class StudyPoint:
    sensor: str
    coil: str
    panel: int                          # 0 without, 1 with the solar panel
    distance_cm: float
    K_nT_per_A: np.ndarray              # (3,) frame axes
    K_sigma_nT_per_A: np.ndarray        # (3,)
    K_norm_nT_per_A: float              # |K|
    K_norm_sigma_nT_per_A: float
    n_samples: int

    def to_dict(self) -> dict:
        return {"sensor": self.sensor, "coil": self.coil, "panel": self.panel,
                "distance_cm": self.distance_cm, "K_nT_per_A": self.K_nT_per_A.tolist(),
                "K_sigma_nT_per_A": self.K_sigma_nT_per_A.tolist(),
                "K_norm_nT_per_A": self.K_norm_nT_per_A,
                "K_norm_sigma_nT_per_A": self.K_norm_sigma_nT_per_A,
                "n_samples": self.n_samples}


@dataclass
class DistanceLaw:
    """|K|(r) = K_30 (30 cm / r)^n, fitted to the points of one sensor, coil and panel
    state by weighted least squares in log-log (weights from the points' 1-sigma); the
    uncertainties from the covariance, scaled by sqrt(chi2/dof) where the scatter exceeds
    the points' own errors (Birge ratio). Two points leave no degree of freedom: the law
    goes through both, its uncertainty is the points' 1-sigma propagated plainly (nothing
    can tell whether they scatter more than their errors: flagged `unchecked`)."""
    sensor: str
    coil: str
    panel: int
    n_points: int
    exponent: float
    exponent_sigma: float | None        # None: not known (a law built without its fit)
    K_30cm_nT_per_A: float
    K_30cm_sigma_nT_per_A: float | None
    chi2_per_dof: float | None          # None: two points, no degree of freedom left
    r_min_cm: float | None = None       # the measured distances' span (None: not recorded)
    r_max_cm: float | None = None
    # covariance of (ln K30, n), 2 x 2 nested list; None: the two 1-sigma taken independent
    cov_lnK30_n: list | None = None

    def at(self, r_cm, current_A=1.0):
        return self.K_30cm_nT_per_A * (30.0 / np.asarray(r_cm, float)) ** self.exponent \
            * current_A

    def _cov(self) -> np.ndarray | None:
        if self.cov_lnK30_n is not None:
            return np.asarray(self.cov_lnK30_n, float)
        if self.exponent_sigma is None or self.K_30cm_sigma_nT_per_A is None:
            return None
        return np.diag([(self.K_30cm_sigma_nT_per_A / self.K_30cm_nT_per_A) ** 2,
                        self.exponent_sigma ** 2])

    def sigma_at(self, r_cm, current_A=1.0):
        """1-sigma of at(r_cm, current_A), first order in (ln K30, n) with their
        covariance: ln at = ln K30 - n ln(r / 30 cm). None where the law has no
        uncertainty."""
        C = self._cov()
        if C is None:
            return None
        g = -np.log(np.asarray(r_cm, float) / 30.0)
        var_ln = C[0, 0] + 2 * g * C[0, 1] + g * g * C[1, 1]
        return self.at(r_cm, current_A) * np.sqrt(np.maximum(var_ln, 0.0))

    def distance_cm(self, K_norm_nT_per_A, K_norm_sigma_nT_per_A=None) -> tuple:
        """(r, 1-sigma of r or None): where the law gives |K| = K_norm. First order in
        (ln K30, n) with their covariance and in ln K_norm, taken independent of the law's
        points (a separate measurement)."""
        K = float(K_norm_nT_per_A)
        n = self.exponent
        d = np.log(self.K_30cm_nT_per_A) - np.log(K)
        r = float(30.0 * np.exp(d / n))
        C = self._cov()
        if C is None:
            return r, None
        g = np.array([1.0 / n, -d / n ** 2])           # d ln r / d (ln K30, n)
        var_ln = float(g @ C @ g)
        if K_norm_sigma_nT_per_A is not None:
            var_ln += (float(K_norm_sigma_nT_per_A) / K / n) ** 2
        return r, r * float(np.sqrt(max(var_ln, 0.0)))

    @property
    def dof(self) -> int:
        return self.n_points - 2

    # Not determined (review #19 D), a statistical rule, not a threshold read off a run:
    # * the exponent, when its 1-sigma is at least its magnitude (relative sigma >= 1):
    #   the 1-sigma interval of n then includes 0, so the points cannot tell the law's
    #   fall-off from no fall-off at all;
    # * a value of the law at r, when the 1-sigma of ln |K(r)| is at least 1: its 1-sigma
    #   interval spans more than a factor e either way (e^-1 .. e^+1 of the value), so not
    #   even its order of magnitude is known. Away from the measured span this is n's
    #   1-sigma carried by ln(30 cm / r): distances close together (29.5 and 30 cm) leave
    #   n so loose that the law's values at 5 cm are any number.
    # Both are printed "undetermined (...)" instead of numbers and flagged.
    def undetermined(self) -> str | None:
        """The flag when the points do not determine the exponent (its 1-sigma at least
        its magnitude, see above); else None (also when n has no 1-sigma)."""
        if self.exponent_sigma is None or self.exponent_sigma < abs(self.exponent):
            return None
        return (f"undetermined: n = {self.exponent:.3g} with 1-sigma "
                f"{self.exponent_sigma:.2g} (distances {self.span_text()} too close for "
                "the points' 1-sigma)")

    def undetermined_at(self, r_cm) -> bool:
        """The law's value at r_cm is not determined: its ln 1-sigma at least 1 (the
        1-sigma interval spans more than a factor e either way; see above)."""
        sig = self.sigma_at(r_cm)
        return sig is not None and float(sig) >= float(self.at(r_cm))

    def span_text(self) -> str:
        """The measured distances, '29.5-30 cm' (without unit when not recorded: '?')."""
        if self.r_min_cm is None or self.r_max_cm is None:
            return "?"
        return f"{self.r_min_cm:g}-{self.r_max_cm:g} cm"

    def unchecked(self) -> str | None:
        """The flag when nothing tests the law against its points (two points: it goes
        through both, no degree of freedom for a misfit test); else None."""
        if self.dof > 0:
            return None
        return f"unchecked: {self.n_points} points, no misfit test"

    def chi2_limit_per_dof(self) -> float | None:
        """CHI2_QUANTILE quantile of chi2 at the law's dof, per dof (None: no dof)."""
        if self.dof <= 0:
            return None
        from generator.fit.special import chi2_quantile
        return chi2_quantile(CHI2_QUANTILE, self.dof) / self.dof

    def misfit(self) -> str | None:
        """The flag when the points scatter about the law more than their 1-sigma allows:
        chi2 beyond its CHI2_QUANTILE quantile at the law's dof; else None."""
        lim = self.chi2_limit_per_dof()
        if lim is None or self.chi2_per_dof is None or self.chi2_per_dof <= lim:
            return None
        return (f"chi2/dof {self.chi2_per_dof:.2f} above {lim:.2f} (its "
                f"{100 * CHI2_QUANTILE:g} % quantile at {self.dof} dof): the points scatter "
                "more than their errors, the law or the errors are off")

    def extrapolated(self, r_cm) -> str | None:
        """The flag when the law is used at r_cm outside the measured distances; else None
        (also when the span was not recorded)."""
        if self.r_min_cm is None or self.r_max_cm is None or r_cm is None:
            return None
        r = float(r_cm)
        # the span's own ends are measured: a relative 1e-9 only absorbs float rounding
        if self.r_min_cm * (1 - 1e-9) <= r <= self.r_max_cm * (1 + 1e-9):
            return None
        return (f"extrapolated to {r:.3g} cm, outside the measured "
                f"{self.r_min_cm:g}..{self.r_max_cm:g} cm")

    def flags(self, *r_cm) -> list:
        """Every flag of the law used at the distances r_cm (undetermined exponent, misfit
        or unchecked, extrapolation, a value not determined at one of r_cm)."""
        loose = [r for r in dict.fromkeys(r_cm) if r is not None and self.undetermined_at(r)]
        out = [self.undetermined(), self.misfit(), self.unchecked()] \
            + [self.extrapolated(r) for r in r_cm] \
            + ([f"undetermined at {', '.join(f'{float(r):.3g}' for r in loose)} cm: the "
                "value's 1-sigma spans more than a factor e (distances "
                f"{self.span_text()} too close for the points' 1-sigma)"] if loose else [])
        return [f for f in out if f]

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("sensor", "coil", "panel", "n_points",
                                              "exponent", "exponent_sigma", "K_30cm_nT_per_A",
                                              "K_30cm_sigma_nT_per_A", "chi2_per_dof",
                                              "r_min_cm", "r_max_cm", "cov_lnK30_n")}


@dataclass
class CoilStudy:
    points: list                        # of StudyPoint
    laws: list                          # of DistanceLaw
    sources: list
    notes: list = field(default_factory=list)

    def law(self, sensor, coil, panel):
        return next((w for w in self.laws if (w.sensor, w.coil, w.panel) ==
                     (sensor, coil, panel)), None)

    def seed_comparison(self, current_A=SEED_CURRENT_A) -> list:
        """Per law at 30 cm and current_A: interference and its 1-sigma beside the seed's
        figure for the same panel state, and their ratio."""
        out = []
        for w in self.laws:
            seed = (SEED_30CM_PANEL_NT if w.panel else SEED_30CM_NO_PANEL_NT) \
                * current_A / SEED_CURRENT_A
            x = float(w.at(30.0, current_A))
            sig = (None if w.K_30cm_sigma_nT_per_A is None
                   else float(w.K_30cm_sigma_nT_per_A * current_A))
            out.append({"sensor": w.sensor, "coil": w.coil, "panel": w.panel,
                        "current_A": current_A, "at_30cm_nT": x, "sigma_nT": sig,
                        "seed_nT": seed, "ratio_to_seed": x / seed})
        return out

    def to_dict(self) -> dict:
        return {"sources": [str(s) for s in self.sources],
                "points": [p.to_dict() for p in self.points],
                "laws": [w.to_dict() for w in self.laws],
                "seed_comparison": self.seed_comparison(), "notes": list(self.notes)}


def fit_distance_law(r_cm, K_norm, K_sigma, *, sensor="", coil="", panel=0, source=None
                     ) -> DistanceLaw:
    """log|K| = log K_30 - n log(r / 30 cm), weighted by the points' relative errors."""
    r = np.asarray(r_cm, float)
    y = np.log(np.asarray(K_norm, float))
    s = np.asarray(K_sigma, float) / np.asarray(K_norm, float)      # sigma of log|K|
    if len(np.unique(r)) < 2:
        raise InputError(source, f"coil study: {sensor} {coil} panel {panel}: one distance "
                                 "only; the distance law needs two or more")
    s = np.where(s > 0, s, np.min(s[s > 0]) if np.any(s > 0) else 1.0)
    A = np.column_stack([np.ones_like(r), -np.log(r / 30.0)])
    w = 1.0 / s
    cov = np.linalg.inv((A * w[:, None] ** 2).T @ A)
    beta = cov @ (A.T @ (w ** 2 * y))
    dof = len(r) - 2
    chi2 = float(np.sum(((y - A @ beta) * w) ** 2))
    if dof > 0:      # Birge: scatter beyond the errors widens them; two points cannot tell
        cov = cov * max(1.0, chi2 / dof)
    K30 = float(np.exp(beta[0]))
    return DistanceLaw(sensor=sensor, coil=coil, panel=int(panel), n_points=int(len(r)),
                       exponent=float(beta[1]),
                       exponent_sigma=float(np.sqrt(cov[1, 1])),
                       K_30cm_nT_per_A=K30,
                       K_30cm_sigma_nT_per_A=float(K30 * np.sqrt(cov[0, 0])),
                       chi2_per_dof=chi2 / dof if dof > 0 else None,
                       r_min_cm=float(r.min()), r_max_cm=float(r.max()),
                       cov_lnK30_n=cov.tolist())


def fit_coil_study(unit, telemetries) -> CoilStudy:
    """K per distance and panel state, and the distance law, from coil-study files
    (Telemetry objects with a coil_distance_cm column; docs/coil_study.md).

    Per file: the sensors under test are those named by '# coil_test_sensor:' (every
    sensor when absent); the coils are its coil_*_A columns; samples with position 0
    (moving), a missing distance or current, or an unusable reading are left out. Each
    (distance, panel) group is fitted like a coil campaign (fit_coupling: K plus a constant
    per static position), so the field, the offsets and anything steady drop out."""
    from generator.io import telemetry_csv as _telemetry
    study = [t for t in telemetries if is_coil_study(t)]
    if not study:
        raise InputError(unit.path, "coil study: no file with a coil_distance_cm column")
    groups = {}                                        # (sensor, coil, panel, r) -> data
    notes = []
    for tel in study:
        check_study(tel, unit)          # the input rules, also for a Telemetry made in memory
        coils = coil_columns(tel)
        names = study_sensors(tel.path, tel.meta, unit)
        dist = np.asarray(tel.columns[DISTANCE_COLUMN], float)
        panel = panel_flags(tel)
        I = np.column_stack([tel.columns[c] for c in coils])
        pos = (np.asarray(tel.columns["position"], float) if "position" in tel.columns
               else np.ones(tel.n))
        ok = static_rows(tel) & np.isfinite(I).all(axis=1)
        data = _telemetry.preprocess(tel, unit)
        for n in names:
            sd = data[n]
            use = ok & sd.usable & np.isfinite(sd.field_frame_nT).all(axis=1)
            for r in np.unique(dist[use]):
                for pn in np.unique(panel[use & (dist == r)]):
                    sel = use & (dist == r) & (panel == pn)
                    g = groups.setdefault((n, int(pn), float(r)), ([], [], [], coils))
                    g[0].append(sd.field_frame_nT[sel])
                    g[1].append(I[sel])
                    g[2].append(pos[sel])
    points = []
    src = ", ".join(str(t.path) for t in study)
    for (n, pn, r), (ys, Is, gs, coils) in sorted(groups.items()):
        f = fit_coupling(np.concatenate(ys), np.concatenate(Is), np.concatenate(gs),
                         coils=coils, name=f"{n} at {r:g} cm, panel {pn}", source=src)
        norms, sig = f.column_norm_nT_per_A(), f.column_norm_sigma_nT_per_A()
        for j, c in enumerate(coils):
            points.append(StudyPoint(n, c, pn, r, f.K_nT_per_A[:, j].copy(),
                                     f.K_sigma_nT_per_A[:, j].copy(), float(norms[j]),
                                     float(sig[j]), f.n_samples))
    laws = []
    for key in sorted({(p.sensor, p.coil, p.panel) for p in points}):
        pts = [p for p in points if (p.sensor, p.coil, p.panel) == key]
        if len({p.distance_cm for p in pts}) < 2:
            notes.append(f"{key[0]} {key[1]} panel {key[2]}: one distance only, no law")
            continue
        laws.append(fit_distance_law([p.distance_cm for p in pts],
                                     [p.K_norm_nT_per_A for p in pts],
                                     [p.K_norm_sigma_nT_per_A for p in pts],
                                     sensor=key[0], coil=key[1], panel=key[2], source=src))
    return CoilStudy(points=points, laws=laws, sources=[t.path for t in study], notes=notes)
