"""The segment finder on a quantised temperature (review of issue 19, item 3).

The MMC5883's temperature comes in 0.7 degC steps; a hold whose true temperature sits
near a code boundary dithers between two codes. The band of generator/fit/segments.py
accounts for the step (quantisation error uniform over one step, sd q/sqrt(12); 6 sd of it
is 1.73 q, more than the one step a dithering hold spans), so:

* a hold dithering between two codes is one segment, not cut into pieces (the recording
  window of every hold of a simulated campaign lies in one segment);
* two real levels 2 degC apart are not merged (at 0.7 degC steps they can read only two
  codes apart);
* the demo's thermal campaign still gives six levels per sensor, each in all twelve
  positions.

Dithering is made by adding white noise to the true board temperature before the MMC's
quantiser (generator.campaign.simulate.report_temperature): sd 0.1-0.3 degC keeps the
reading on the two codes about the true value most of the time, which is the case here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.campaign.board_thermal import first_order_lag
from generator.fit.segments import (find_segments, group_levels, segment_band_C,
                                    temperature_noise)
from generator.io import parts
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit

MMC_STEP_C = parts.temperature_lsb_C("MMC5883MA")        # the catalogue's 0.7 degC


def mmc(true_C):
    return sim.report_temperature("MMC5883MA", true_C)[0]


def test_band_holds_one_step_of_dither_from_the_part_lsb_or_the_data():
    assert MMC_STEP_C == 0.7 and sim.MMC_TEMP_STEP_C == MMC_STEP_C
    # a reading on one code only: nothing in the data shows the step; the part's LSB does
    T = np.full(500, 20.2)
    assert segment_band_C(T) == 0.5                      # the floor, nothing else known
    assert segment_band_C(T, temp_lsb_C=MMC_STEP_C) == pytest.approx(
        6 * MMC_STEP_C / math.sqrt(12))
    # dithering between two codes: the step is seen in the data as well
    rng = np.random.default_rng(0)
    T = mmc(20.55 + rng.normal(0, 0.1, 5000))
    assert set(np.unique(T)) == {20.2, 20.9}
    band = segment_band_C(T)
    assert band >= 6 * MMC_STEP_C / math.sqrt(12) > MMC_STEP_C


def test_noise_of_white_noise_and_spikes():
    """temperature_noise: the winsorised RMS of second differences is the noise's sd; a
    fraction f of spiked second differences (each clipped at 3 s) raises the fixed point
    s^2 = (1 - f) 0.99488 sigma_d^2 + 9 f s^2 to s = sigma_d sqrt((1 - f) 0.99488 / (1 - 9 f)),
    a bounded bias, where the plain RMS would be dominated by the spikes."""
    rng = np.random.default_rng(1)
    x = rng.normal(0, 0.3, 100000)
    # 1e5 samples: the estimate's sampling sd is ~0.3 %; 2 % is far beyond it
    assert temperature_noise(x) == pytest.approx(0.3, rel=0.02)
    x[rng.choice(len(x), 1000, replace=False)] += 4.0      # 1 % of samples: f = 3 %
    f = 0.03
    expected = 0.3 * math.sqrt((1 - f) * 0.99488 / (1 - 9 * f)) / 0.99744
    assert temperature_noise(x) == pytest.approx(expected, rel=0.03)
    # unclipped, each spike adds 4^2 + 8^2 + 4^2 = 96 to the sum of d2^2: the plain RMS is
    # sqrt(0.3^2 + 0.01 * 96 / 6) = 0.5 degC
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    assert math.sqrt(np.mean(d2 ** 2) / 6) == pytest.approx(0.5, rel=0.03)


@pytest.mark.parametrize("period_s", [1.0, 10.0, 60.0])
@pytest.mark.parametrize("noise_C", [0.1, 0.2, 0.3])
def test_a_dithering_hold_is_one_segment(period_s, noise_C):
    """Two hours at one true temperature near a code boundary (dithering between the two
    codes), with a 0.3 degC drift: one segment holding nearly every sample."""
    rng = np.random.default_rng(int(period_s * 10 + noise_C * 100))
    for boundary_offset_C in (-0.1, 0.0, 0.1):
        t = np.arange(0.0, 7200.0, period_s)
        true_C = -75.0 + MMC_STEP_C * 100.5 + boundary_offset_C + 0.3 * t / 7200.0
        T = mmc(true_C + rng.normal(0, noise_C, len(t)))
        assert len(np.unique(T)) >= 2                     # it does dither
        segs = find_segments(t, T)
        assert len(segs) == 1, [(s.t_start_s, s.t_stop_s, s.temp_C) for s in segs]
        # the 5-sample median filter and the window leave at most a few samples out
        assert len(segs[0].index) >= 0.95 * len(t)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A simulated thermal campaign following the plan (60 s samples, 10 per hold) with
    the body board's true temperature."""
    out = tmp_path_factory.mktemp("th")
    unit = sim.make_example_unit()
    truth = sim.random_truth(unit, np.random.default_rng(1))
    plan = sim.plan_for(unit, truth, sample_period_s=60.0, samples_per_segment=10)
    path, arrays = sim.simulate_campaign("thermal_12pos", unit, truth,
                                         np.random.default_rng(2), out, plan=plan)
    sim.write_unit_toml(unit, out / "unit.toml")
    tel = read_telemetry(path, load_unit(out / "unit.toml"))
    return plan, tel, arrays


@pytest.mark.parametrize("noise_C", [0.0, 0.1, 0.2])
def test_every_hold_of_a_campaign_is_one_segment(campaign, noise_C):
    plan, tel, arrays = campaign
    t, pos = tel.time_s, tel.columns["position"]
    rng = np.random.default_rng(int(noise_C * 10) + 7)
    T = mmc(arrays["temp_body_C"] + rng.normal(0, noise_C, len(t)))
    segs = find_segments(t, T, pos)
    where = np.full(len(t), -1)
    for k, s in enumerate(segs):
        where[s.index] = k
    holds = [it for it in plan.chamber_program() if it["action"] == "hold"]
    for it in holds:
        w = (t >= it["record_from_s"]) & (t < it["record_to_s"])
        found = set(where[w].tolist())
        assert found != {-1} and len(found) == 1, (it["position"], it["setpoint_C"], found)
    levels = group_levels(segs, 3 * MMC_STEP_C)
    assert len(levels) == len(plan.levels_C)
    assert all(len({s.position for s in lv}) == len(plan.positions) for lv in levels)


@pytest.mark.parametrize("tau_s", [300.0, 900.0])
@pytest.mark.parametrize("period_s", [10.0, 60.0])
@pytest.mark.parametrize("noise_C", [0.0, 0.1, 0.2])
def test_two_levels_2C_apart_are_not_merged(tau_s, period_s, noise_C):
    """Two hours at a level, two hours 2 degC higher, the board lagging by tau_s: each
    hold's settled last half hour lies in a segment of its own, near its own level."""
    rng = np.random.default_rng(int(tau_s + period_s + noise_C * 10))
    for offset_C in np.linspace(-0.35, 0.35, 5):         # where the codes fall
        t = np.arange(0.0, 4 * 3600.0, period_s)
        level = np.where(t < 7200.0, 20.0, 22.0) + offset_C
        board = first_order_lag(t, level, tau_s, level[0])
        T = mmc(board + rng.normal(0, noise_C, len(t)))
        segs = find_segments(t, T)
        where = np.full(len(t), -1)
        for k, s in enumerate(segs):
            where[s.index] = k
        a = set(where[(t >= 5400.0) & (t < 7200.0)].tolist()) - {-1}
        b = set(where[t >= 4 * 3600.0 - 1800.0].tolist()) - {-1}
        assert a and b and not (a & b), (offset_C, a, b)
        # each hold's segment reads its own level: within one step of it (quantisation)
        for ks, true_C in ((a, 20.0 + offset_C), (b, 22.0 + offset_C)):
            for k in ks:
                assert abs(segs[k].temp_C - true_C) < MMC_STEP_C, (offset_C, segs[k])


def test_demo_campaign_has_six_levels_per_sensor_in_every_position(tmp_path):
    """The demo's thermal campaign (make_example, seed 1): six levels per sensor, each in
    all twelve positions, with the level tolerance the fit uses (fit/levels.py)."""
    from generator.fit.joint import DEGREE_STEP_C
    from generator.fit.segments import temperature_quantum

    paths = sim.make_example(tmp_path, seed=1)
    unit = load_unit(paths["unit"])
    tel = read_telemetry(paths["thermal_12pos"], unit)
    pre = preprocess(tel, unit)
    for s in unit.sensors:
        d = pre[s.name]
        segs = find_segments(tel.time_s, d.temp_C, tel.get("position"), d.usable)
        tol = max(2.0, 3.0 * temperature_quantum(d.temp_C), DEGREE_STEP_C / 2)
        levels = group_levels(segs, tol)
        assert len(levels) == 6, s.name
        assert all(len({g.position for g in lv}) == 12 for lv in levels), s.name
