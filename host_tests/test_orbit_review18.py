"""Review of issue 18 (items #3, #5, #6): a unit with a physical-unit, temperature-less
sensor recalibrated from orbit against a prior; the stated floor of a physical-unit
sensor; an epoch error flagged by fit.floor_check.

Own data: generator.campaign.simulate_orbit with a random truth (seed 1801) of a
two-sensor unit (an MMC5983MA reading counts and an RM3100 reading uT without
temperature), ISS TLE, 3 h at 10 s, positions from SGP4."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from generator.campaign import simulate_orbit as so
from generator.campaign.simulate import random_truth
from generator.cli import main
from generator.fit.floor_check import floor_check
from generator.fit.samples import field_noise_nT
from generator.io.unit import SensorSpec, Unit


def _unit() -> Unit:
    return Unit(id="rev18", lab_field_nT=48500.0, float_type="float32", boom_reference=None,
                sensors=(SensorSpec("mmc", "MMC5983MA", "body", ("+x", "+y", "+z"), 6.25,
                                    131072, False, 40.0),
                         SensorSpec("rmu", "RM3100", "body", ("+x", "+y", "+z"), 1000.0, 0,
                                    False, 15.0, input="uT", temperature=False)))


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    d = tmp_path_factory.mktemp("rev18")
    unit = _unit()
    rng = np.random.default_rng(1801)
    truth = random_truth(unit, rng)
    # the RM3100 states no temperature: its truth has none either (b, W and the chip
    # offset constant), so the constant model it gets can reach the floor
    st = truth.sensors["rmu"]
    st.b_poly_frame_nT[1:] = 0.0
    st.W_poly_frame[1:] = 0.0
    st.chip_offset_poly_sensor_nT[1:] = 0.0
    camp = so.simulate_orbit(unit, truth, rng, d / "orbit", duration_s=3 * 3600.0)
    # the prior: a calibration of this unit in its coefficients.json format (here from
    # the orbit data themselves, no prior): the temperature=false block has no t_ref_C
    assert main(["fit", str(camp["unit"]), str(camp["csv"]), "-o", str(d / "ground"),
                 "-q"]) == 0
    return d, camp, d / "ground" / "coefficients.json"


def test_prior_with_a_temperature_less_sensor(orbit):
    d, camp, ground = orbit
    blk = json.loads(ground.read_text())["sensors"]["rmu"]
    assert "t_ref_C" not in blk                     # the case of review item #3
    assert main(["fit", str(camp["unit"]), str(camp["csv"]), "--prior", str(ground),
                 "-o", str(d / "recal"), "-q"]) == 0
    info = json.loads((d / "recal" / "coefficients.json").read_text())["fit"]
    assert str(ground) in info["prior"]


def test_physical_input_floor_has_no_count_quantisation():
    mmc, rmu = _unit().sensors
    # counts: noise and the quantisation of one count, lsb^2 / 12
    assert field_noise_nT(mmc) == pytest.approx(np.sqrt(40.0 ** 2 + 6.25 ** 2 / 12))
    # uT: real numbers, one uT is not a step of the reading
    assert field_noise_nT(rmu) == pytest.approx(15.0)
    for inp, f in (("G", 1e5), ("mG", 100.0), ("nT", 1.0)):
        s = dataclasses.replace(rmu, input=inp, lsb_nT=f)
        assert field_noise_nT(s) == pytest.approx(15.0)
    # no stated noise: the part's (parts.toml RM3100, 15 nT)
    assert field_noise_nT(dataclasses.replace(rmu, noise_nT=None)) == pytest.approx(15.0)


def test_stated_floor_of_a_uT_sensor(orbit):
    d, camp, ground = orbit
    notes = json.loads(ground.read_text())["fit"]["notes"]
    line = next(n for n in notes if n.startswith("rmu: against the field model"))
    assert "noise 15^2" in line, line


def test_floor_check_statistics():
    # at the floor: S / E = 1 is never flagged; far beyond it always
    ok = floor_check(50.0, 1000, 40.0, 30.0, 3 * 3600.0)
    assert not ok["flagged"] and ok["limit"] > 1.0
    assert floor_check(264.0, 1000, 40.0, 30.0, 3 * 3600.0)["flagged"]
    # nu lies between the model's independent samples (18) and all samples
    assert 18 <= ok["nu"] <= 1000


def test_correct_epoch_no_floor_warning(orbit):
    d, camp, ground = orbit
    notes = json.loads(ground.read_text())["fit"]["notes"]
    assert not any("well beyond the floor" in n for n in notes), notes


def test_epoch_error_is_flagged(orbit, capsys):
    d, camp, ground = orbit
    text = camp["unit"].read_text()
    ep = re.search(r'epoch_utc = "([^"]+)Z"', text).group(1)
    shifted = str(np.datetime64(ep, "us") + np.timedelta64(18, "s"))
    bad = d / "u_18s.toml"
    bad.write_text(text.replace(ep, shifted))
    assert main(["fit", str(bad), str(camp["csv"]), "--prior", str(ground),
                 "-o", str(d / "x18"), "-q"]) == 0
    info = json.loads((d / "x18" / "coefficients.json").read_text())["fit"]
    warned = [n for n in info["notes"] if "well beyond the floor" in n]
    assert warned and "time/epoch" in warned[0]
    report = (d / "x18" / "report.md").read_text()
    assert "well beyond the floor" in report and "Warnings: none" not in report
