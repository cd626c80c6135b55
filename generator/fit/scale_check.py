"""Are the readings in the unit the unit file says? Checked before any fit.

A wrong `lsb_nT` (0.3 for 300) or a wrong `input` (gauss declared as uT) gives readings a
factor 10^2..10^3 away from the field they measure, and every fit then "succeeds" with a
meaningless calibration. The check compares, per sensor, the median magnitude of the
raw readings (in nT, as the unit file converts them) with the median magnitude of the
reference the files carry (ref_x/y/z_nT, ref_norm_nT, else the unit's lab_field_nT).

The bound is physical: a magnetometer's scale error is tens of percent, and hard iron
(a magnet at 1 cm, a nearby motor) raises the raw magnitude at most to the part's range,
a few mT, while the Earth's field is 25..65 uT. A ratio outside [1/RATIO, RATIO] with
RATIO = 20 is therefore a unit error, not a calibration to fit: it catches 0.3 for 300
(10^-3) and gauss read as uT (10^-2), not a factor 10 (mG for uT), which a fit's scale
check and the report's residual show.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.io.telemetry_csv import preprocess

RATIO = 20.0


def reference_magnitude_nT(tel, unit) -> np.ndarray:
    """Per sample, the magnitude of the field reference the file carries (NaN where none)."""
    n = tel.n
    if tel.has("ref_x_nT", "ref_y_nT", "ref_z_nT"):
        ref = np.stack([tel.columns[f"ref_{a}_nT"] for a in "xyz"], axis=1)
        return np.linalg.norm(ref, axis=1)
    if tel.has("ref_norm_nT"):
        return np.asarray(tel.columns["ref_norm_nT"], float)
    if unit.lab_field_nT:
        return np.full(n, float(unit.lab_field_nT))
    return np.full(n, np.nan)


def check_reading_scale(unit, tels) -> None:
    """InputError naming the file and sensor whose readings are RATIO or more away from
    the field reference in magnitude (see the module doc); silent where no reference."""
    for tel in tels:
        ref = reference_magnitude_nT(tel, unit)
        if not np.any(np.isfinite(ref) & (ref > 0)):
            continue
        data = preprocess(tel, unit)
        for s in unit.sensors:
            d = data.get(s.name)
            if d is None:
                continue
            mag = np.linalg.norm(d.field_frame_nT, axis=1)
            ok = d.usable & np.isfinite(mag) & np.isfinite(ref) & (ref > 0)
            if ok.sum() < 3:
                continue
            ratio = float(np.median(mag[ok]) / np.median(ref[ok]))
            if not 1.0 / RATIO <= ratio <= RATIO:
                how = (f"lsb_nT = {s.lsb_nT:g}" if s.input == "counts"
                       else f"input = \"{s.input}\"")
                raise InputError(tel.path, f"sensor '{s.name}': its readings are "
                                           f"{ratio:.3g} x the reference field in magnitude "
                                           f"(median {np.median(mag[ok]):.4g} nT against "
                                           f"{np.median(ref[ok]):.4g} nT): the unit file's "
                                           f"{how} does not match the data (a unit error, "
                                           "not a calibration to fit)")
