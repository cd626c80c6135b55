"""Review fault 5 of issue 16: a prior (--prior coefficients.json) from another unit, or
of another part, axis mapping or input, is refused (exit 2, one line naming the key),
unless it is sensor-compatible (a sister unit with the same sensors: accepted, said so)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.calibration import SensorCalibration
from generator.fit.prior_unit import check_prior_unit
from generator.flight.coeffs import CoefficientSet
from generator.io.icd_write import write_unit_toml
from generator.io.unitfile import load_unit

MPU = {"name": "mpu", "part": "MPU-9255", "frame": "body", "axes": ["+x", "+y", "+z"],
       "lsb_nT": 150.0, "zero_count": 0, "set_reset": False, "noise_nT": 300.0}


def _unit(tmp_path, uid="framecheck", **change):
    d = tmp_path / f"{uid}_{'_'.join(f'{k}' for k in change)}"
    d.mkdir(exist_ok=True)
    return load_unit(write_unit_toml(d / "unit.toml", uid, [{**MPU, **change}],
                                     unit_keys={"lab_field_nT": 49000.0}))


def _prior(tmp_path, unit):
    cal = SensorCalibration.constant("mpu", np.array([100.0, -200.0, 50.0]), np.eye(3),
                                     b_poly_sigma_nT=np.full((4, 3), 30.0),
                                     M_poly_sigma=np.full((4, 3, 3), 0.003))
    cs = CoefficientSet.from_calibrations(unit, {"mpu": cal})
    path = tmp_path / f"prior_{unit.id}.json"
    cs.save(path)
    return path


def test_same_unit_is_accepted(tmp_path):
    u = _unit(tmp_path)
    assert check_prior_unit(u, u, "p.json") == []


def test_sister_unit_with_the_same_sensors_is_accepted_and_said(tmp_path):
    notes = check_prior_unit(_unit(tmp_path, "sister"), _unit(tmp_path), "p.json")
    assert len(notes) == 1 and "sister" in notes[0]


def test_part_alias_is_the_same_part(tmp_path):
    assert check_prior_unit(_unit(tmp_path, part="MPU-9250"), _unit(tmp_path), "p") == []


@pytest.mark.parametrize("change,key", [({"part": "HMC5883L", "lsb_nT": 92.0}, "part"),
                                        ({"axes": ["+y", "+x", "-z"]}, "axes"),
                                        ({"frame": "boom"}, "frame")])
def test_another_sensor_is_refused_naming_the_key(tmp_path, change, key):
    with pytest.raises(InputError, match=rf"key 'sensor\.mpu\.{key}'"):
        check_prior_unit(_unit(tmp_path, "other", **change), _unit(tmp_path), "p.json")


def test_other_unit_without_our_sensor_is_refused(tmp_path):
    other = _unit(tmp_path, "other")
    other = dataclasses.replace(other, sensors=(dataclasses.replace(other.sensors[0],
                                                                     name="mag"),))
    with pytest.raises(InputError, match="key 'sensor'"):
        check_prior_unit(other, _unit(tmp_path), "p.json")


def test_fit_with_a_prior_of_another_part_exits_2(tmp_path, capsys):
    from test_fit_frame_mismatch import _data
    from generator.cli import main
    unit = _unit(tmp_path)
    other = _unit(tmp_path, "other", part="HMC5883L", lsb_nT=92.0)
    prior = _prior(tmp_path, other)
    data = _data(tmp_path / "d.csv", np.random.default_rng(4))
    rc = main(["fit", str(unit.path), str(data), "-o", str(tmp_path / "o"), "-q",
               "--prior", str(prior)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert str(prior) in err[0] and "sensor.mpu.part" in err[0]
    # the same prior written for a sister unit with the same sensor is taken
    ok = _prior(tmp_path, _unit(tmp_path, "sister"))
    assert main(["fit", str(unit.path), str(data), "-o", str(tmp_path / "o2"), "-q",
                 "--prior", str(ok)]) == 0
