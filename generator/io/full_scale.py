"""A sensor whose every sample is beyond its full scale: most often a wrong declared unit.

preprocess (telemetry_csv) marks a sample unusable where any axis reaches the part's full
scale (physical input: |value| x nT per input unit >= SensorSpec.full_scale_nT; counts: at
the rails). A handful of such samples is a saturation and is counted. When EVERY sample of
a sensor that has readings is beyond full scale, in every file given, the fit has nothing
of that sensor and used to stop at "no usable sample with a field reference", although the
files carry references. The likely cause is the unit file: nT data declared input = "mG"
(x100), "uT" (x1000) or "G" (x1e5) put the Earth's field far beyond any part's range. This
check runs before the fit (pipeline.fit) and names the cause: the file, the sensor, the
count, the full scale and the unit file's key.
"""

from __future__ import annotations

from generator.errors import InputError
from generator.io.telemetry_csv import preprocess


def check_full_scale(unit, tels, data=None) -> None:
    """InputError when a sensor has readings but every one, in all files `tels`, is beyond
    the part's full scale (module doc). data: optional [preprocess(tel, unit) per tel]
    already computed. Silent otherwise (a sensor without readings at all is the fit's to
    report, a partial saturation is counted by preprocess)."""
    if data is None:
        data = [preprocess(tel, unit) for tel in tels]
    for s in unit.sensors:
        n_sat = n_usable = 0
        first = None
        for tel, d in zip(tels, data):
            sd = d.get(s.name)
            if sd is None:
                continue
            n_usable += int(sd.usable.sum())
            n_sat += sd.n_saturated
            if sd.n_saturated and first is None:
                first = tel
        if n_usable or not n_sat:
            continue
        where = f" in the {len(tels)} files" if len(tels) > 1 else ""
        if s.counts:
            why = (f"all {n_sat} samples of sensor '{s.name}'{where} at the rails of its counts "
                   f"({s.count_min}..{s.count_max}, full scale {s.full_scale_nT:g} nT): "
                   f"are part = \"{s.part}\", lsb_nT = {s.lsb_nT:g} and zero_count = "
                   f"{s.zero_count} right?")
        else:
            why = (f"all {n_sat} samples of sensor '{s.name}'{where} beyond the part's full scale "
                   f"({s.full_scale_nT:g} nT, {s.part}): is the input unit "
                   f"(input = \"{s.input}\") right?")
        raise InputError(first.path, why)
