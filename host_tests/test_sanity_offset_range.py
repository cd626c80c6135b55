"""The offset sanity limit does not scale with the input unit (issue 16 review item 2).

With physical input (nT, uT, G) lsb_nT is a placeholder (1.0) and the count range says
nothing about the field: the limit is the sensor's full scale in nT (the part's widest
range or the unit file's range_nT), the same whatever unit the columns hold.
"""

import pytest

from generator.fit.sanity import offset_cause, offset_range_nT
from generator.io import parts
from generator.io.unit import SensorSpec


def _spec(input_unit, **kw):
    return SensorSpec(name="mag", part="LIS3MDL", frame="body", axes=("+x", "+y", "+z"),
                      lsb_nT=1.0, zero_count=0, set_reset=False, input=input_unit, **kw)


@pytest.mark.parametrize("unit", ["nT", "uT", "G"])
def test_physical_input_limit_is_part_full_scale(unit):
    widest = parts.part("LIS3MDL").range_nT
    assert widest > 1e5          # LIS3MDL: +-16 G = 1.6e6 nT at its widest setting
    assert offset_range_nT(_spec(unit)) == pytest.approx(widest)
    assert "wrong input unit" in offset_cause(_spec(unit))
    assert "lsb_nT" not in offset_cause(_spec(unit))


def test_physical_input_unit_range_overrides_part():
    assert offset_range_nT(_spec("uT", range_nT=4e5)) == 4e5


def test_counts_input_keeps_count_range_and_cause():
    s = SensorSpec(name="mag", part="LIS3MDL", frame="body", axes=("+x", "+y", "+z"),
                   lsb_nT=14.62, zero_count=0, set_reset=False)
    assert offset_range_nT(s) == pytest.approx(32768 * 14.62)
    assert "lsb_nT" in offset_cause(s)
