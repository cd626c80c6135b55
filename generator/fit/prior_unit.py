"""Is a prior (a coefficients.json given with --prior) a calibration of THIS unit's sensors?

A ground calibration from another unit, or of other parts, would be taken as the truth
for every coefficient the data do not determine. The prior is accepted when every sensor
it is used for is the same sensor: the same part (catalogue name, aliases resolved),
frame, axis mapping, SET/RESET, input and temperature reporting (the keys that decide
what b and M mean). A prior with another unit id is accepted only when it is
sensor-compatible for every sensor of this unit (a sister unit with the same sensors);
otherwise it is refused (InputError, exit 2) naming the key that differs.
"""

from __future__ import annotations

from generator.errors import InputError

# the sensor keys that decide what a calibration's b and M mean
COMPATIBLE_KEYS = ("part", "frame", "axes", "set_reset", "input", "temperature")


def _canon(part):
    from generator.io import parts as catalogue
    p = catalogue.find(part)
    return p.name if p is not None else str(part)


def _value(spec, key):
    v = getattr(spec, key)
    if key == "part":
        return _canon(v)
    if key == "axes":
        return tuple(v)
    return v


def check_prior_unit(prior_unit, unit, path) -> list:
    """InputError when the prior's unit (a generator.io.unit.Unit) does not fit `unit`
    (module docstring); else the notes to report (list of str)."""
    here = {s.name: s for s in unit.sensors}
    there = {s.name: s for s in prior_unit.sensors}
    common = [n for n in here if n in there]
    if not common:
        raise InputError(path, f"--prior: key 'sensor': none of this unit's sensors "
                               f"({', '.join(here)}) is in the prior (unit "
                               f"'{prior_unit.id}': {', '.join(there)}): not a calibration "
                               "of this unit")
    for n in common:
        for k in COMPATIBLE_KEYS:
            a, b = _value(there[n], k), _value(here[n], k)
            if a != b:
                raise InputError(path, f"--prior: key 'sensor.{n}.{k}': {a!r} in the prior "
                                       f"(unit '{prior_unit.id}'), {b!r} in unit "
                                       f"'{unit.id}': not a calibration of this sensor")
    notes = []
    if prior_unit.id != unit.id:
        missing = [n for n in here if n not in there]
        if missing:
            raise InputError(path, f"--prior: key 'unit.id': the prior is of unit "
                                   f"'{prior_unit.id}', not '{unit.id}', and lacks sensor(s) "
                                   f"{', '.join(missing)}: not a sensor-compatible prior")
        notes.append(f"the prior is of unit '{prior_unit.id}' (this unit: '{unit.id}'); "
                     "accepted: every sensor is the same part, frame, axes and input")
    return notes
