"""Issue 15 item 2: the catalogue of parts (generator/io/parts.toml) and its use by the unit
file reader."""

from __future__ import annotations

import pytest

from generator.errors import InputError
from generator.io import parts as P
from generator.io.unit import PARTS
from generator.io.unitfile import load_unit

REQUIRED = ["MMC5883MA", "MMC5983MA", "MPU-9255", "MPU-9250", "AK8963", "ICM-20948",
            "AK09916", "HMC5883L", "QMC5883L", "LIS3MDL", "RM3100", "IST8310", "BMM150",
            "generic"]


def test_the_issue_lists_parts_are_in_the_catalogue():
    for name in REQUIRED:
        assert P.find(name) is not None, name
    assert P.part("MPU-9250") is P.part("MPU-9255") is P.part("AK8963")
    assert P.part("AK09916") is P.part("ICM-20948")


def test_every_entry_is_complete_and_self_consistent():
    for name in P.names():
        p = P.part(name)
        assert p.maker and p.datasheet, name
        assert isinstance(p.set_reset, bool) and isinstance(p.temperature, bool), name
        if p.generic:
            continue
        assert p.count_min < p.zero_count < p.count_max, name
        assert p.noise_nT and p.noise_nT > 0, name
        assert p.resolutions, name
        for r in p.resolutions:
            lo = r.count_min if r.count_min is not None else p.count_min
            hi = r.count_max if r.count_max is not None else p.count_max
            zero = r.zero_count if r.zero_count is not None else p.zero_count
            half_span = min(zero - lo, hi - zero)
            # the setting's full scale fits in its raw range at its resolution (1 % slack for
            # datasheet rounding: e.g. 1370 LSB/G quoted as 0.73 mG/LSB)
            assert r.range_nT <= 1.01 * (half_span + 1) * r.lsb_nT, (name, r.setting)
            assert r.range_nT <= p.range_nT, (name, r.setting)


def test_existing_parts_keep_their_count_ranges():
    """The two parts of version 1 are unchanged (simulator, tables and generated/ rely on them)."""
    assert (PARTS["MMC5883MA"]["count_min"], PARTS["MMC5883MA"]["count_max"]) == (0, 65535)
    assert (PARTS["MPU-9255"]["count_min"], PARTS["MPU-9255"]["count_max"]) == (-32760, 32760)
    assert PARTS["MMC5883MA"]["set_reset_capable"] and not PARTS["MPU-9255"]["set_reset_capable"]


def test_count_range_follows_the_resolution_setting_and_generic_range():
    assert P.count_range(P.part("MMC5983MA"), 6.25, 131072) == (0, 262143)     # 18 bit
    assert P.count_range(P.part("MMC5983MA"), 25.0, 32768) == (0, 65535)       # 16 bit
    assert P.count_range(P.part("generic"), 10.0, 0, 100000.0) == (-10000, 10000)
    with pytest.raises(ValueError):
        P.count_range(P.part("generic"), 10.0, 0, None)


def _unit(tmp_path, sensor_lines):
    p = tmp_path / "unit.toml"
    p.write_text('[unit]\nid = "u"\n\n[[sensor]]\nname = "m"\nframe = "body"\n'
                 'axes = ["+x", "+y", "+z"]\n' + sensor_lines)
    return p


def test_unknown_part_lists_the_catalogue(tmp_path):
    p = _unit(tmp_path, 'part = "HMC5884"\nlsb_nT = 1.0\nzero_count = 0\n')
    with pytest.raises(InputError) as e:
        load_unit(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:8: ") and "'HMC5884' is not a known part" in msg
    for name in P.names():
        assert name in msg


@pytest.mark.parametrize("name", [n for n in P.names() if n != "generic"])
def test_every_part_loads_in_counts_and_physical_units(tmp_path, name):
    p = P.part(name)
    r = p.resolutions[-1]
    zero = r.zero_count if r.zero_count is not None else p.zero_count
    u = load_unit(_unit(tmp_path, f'part = "{name}"\nlsb_nT = {r.lsb_nT!r}\n'
                                  f'zero_count = {zero}\n'))
    s = u.sensor("m")
    assert (s.count_min, s.count_max) == P.count_range(p, r.lsb_nT, zero)
    assert s.full_scale_nT == r.range_nT
    u = load_unit(_unit(tmp_path, f'part = "{name}"\ninput = "uT"\ntemperature = false\n'))
    s = u.sensor("m")
    assert (s.input, s.temperature, s.nT_per_input, s.zero_count) == ("uT", False, 1000.0, 0)
    assert s.full_scale_nT == p.range_nT


def test_set_reset_only_where_the_part_can(tmp_path):
    with pytest.raises(InputError, match="the IST8310 has no SET/RESET"):
        load_unit(_unit(tmp_path, 'part = "IST8310"\ninput = "G"\nset_reset = true\n'))
    u = load_unit(_unit(tmp_path, 'part = "MMC5983MA"\nlsb_nT = 6.25\nzero_count = 131072\n'
                                  'set_reset = true\n'))
    assert u.sensor("m").set_reset
