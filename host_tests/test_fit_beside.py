"""fit_unit(beside=): a job independent of the fits (pipeline.fit's settling analysis) run
as one more item of the sensors' forked hand-out. Its result, the calibrations and their
failures must be what running it after fit_unit gives, serially or forked."""

from __future__ import annotations

import numpy as np
import pytest

from generator.errors import InputError
from generator.fit.thermal import fit_unit
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit


@pytest.fixture(scope="module")
def rotation(fm1_dir):
    unit = load_unit(fm1_dir / "unit.toml")
    return unit, [read_telemetry(fm1_dir / "rotation.csv", unit)]


@pytest.mark.parametrize("workers", ["1", "2"])
def test_beside_result_and_calibrations_as_without_it(rotation, monkeypatch, workers):
    import os

    unit, tels = rotation
    monkeypatch.setenv("MAGCAL_WORKERS", workers)
    plain = fit_unit(unit, tels)
    cals, side = fit_unit(unit, tels, beside=lambda: {"pid": os.getpid(), "n": 7})
    assert side["n"] == 7
    assert list(cals) == list(plain)
    for name in plain:
        assert np.array_equal(cals[name].M_poly, plain[name].M_poly)
        assert np.array_equal(cals[name].b_poly_nT, plain[name].b_poly_nT)
        assert cals[name].stats == plain[name].stats


@pytest.mark.parametrize("workers", ["1", "2"])
def test_beside_input_error_comes_after_the_sensors(rotation, monkeypatch, workers):
    unit, tels = rotation
    monkeypatch.setenv("MAGCAL_WORKERS", workers)

    def bad():
        raise InputError("side.csv", "the side job's fault")

    with pytest.raises(InputError, match="the side job's fault"):
        fit_unit(unit, tels, beside=bad)
    # a sensor that cannot be fitted is named first, as when the job ran after fit_unit
    from generator.fit import thermal

    real = thermal.fit_sensor
    second = unit.sensors[1].name

    def failing(name, *a, **k):
        if name == second:
            raise InputError("sensor.csv", f"{name}: the sensor's fault")
        return real(name, *a, **k)

    monkeypatch.setattr(thermal, "fit_sensor", failing)
    with pytest.raises(InputError, match="the sensor's fault"):
        fit_unit(unit, tels, beside=bad)
