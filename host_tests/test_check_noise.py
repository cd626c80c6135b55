"""`magcal check` predicts the coefficients' sigma from a sensor's noise. A sensor reading
physical units (ICD section 4) has lsb_nT = the unit's size (1000 nT for uT), which is not
a noise: without a stated noise_nT the part's noise is used, as the fit does."""
from types import SimpleNamespace

from generator.campaign.check import predict_sensor
from generator.fit.samples import field_noise_nT
from generator.io import parts
from generator.io.unit import SensorSpec


def test_physical_input_uses_the_parts_noise_not_the_unit_size():
    spec = SensorSpec("lis", "LIS3MDL", "body", ("+x", "+y", "+z"), 1000.0, 0, False, None,
                      input="uT", temperature=True, range_nT=1.6e6)
    out = predict_sensor(SimpleNamespace(n=0), spec, (-20.0, 60.0))
    assert out["noise_nT"] == field_noise_nT(spec) == parts.part("LIS3MDL").noise_nT
    assert out["noise_nT"] != 1000.0


def test_a_stated_noise_wins():
    spec = SensorSpec("lis", "LIS3MDL", "body", ("+x", "+y", "+z"), 1000.0, 0, False, 55.0,
                      input="uT", temperature=True, range_nT=1.6e6)
    assert predict_sensor(SimpleNamespace(n=0), spec, (-20.0, 60.0))["noise_nT"] == 55.0
