"""Review 17 #1: a scale factor following a channel that only some files carry (a supply
voltage logged in the chamber test, absent from the rotation) is found: the files
without the channel read 0 there, and the files with it get a scale offset of their own
(as a channel bias does), so only the channel's variation counts. The extended
coefficients describe the files that carry the channel: their flight chain reproduces
the traced model there.

Data: the project's simulator; the twelve-position chamber test with the channel and
the effect (size 5-20 x the per-axis noise, as test_trace_channel_scale.py), plus a
hand rotation without it.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import tracer as tr

from test_trace import run, sigma_field, small_unit
from test_trace_channel_scale import ScaledBySupply


@pytest.mark.parametrize("seed", [1, 2])
def test_a_scale_in_a_channel_of_some_files_is_found(seed, tmp_path):
    rng = np.random.default_rng(73_000 + seed)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    s = "mmc1"
    k = float(rng.uniform(8.0, 20.0))
    # a supply around 5 V: 4.6 or 5.4 V (its mean is far from 0, where the files
    # without it sit)
    src = sim.SquareWave(float(rng.uniform(200, 600)), 0.5, 0.8, 4.6,
                         float(rng.uniform(0, 300)), 3)
    g = rng.uniform(0.3, 1.0, 3) * rng.choice([-1.0, 1.0], 3)
    g *= k * sigma_field(unit.sensor(s)) / (0.4 * (unit.lab_field_nT or 50_000.0)) \
        / np.max(np.abs(g))
    eff = ScaledBySupply(s, "supply_V", tuple(g), src)
    thermal, _ = run("thermal", unit, truth, int(rng.integers(1 << 30)), tmp_path, [eff])
    rotation, _ = run("rotation", unit, truth, int(rng.integers(1 << 30)), tmp_path)
    assert "supply_V" in thermal.columns and "supply_V" not in rotation.columns
    res = tr.trace(unit, [thermal, rotation])
    found = [(n, st.effect.name) for n, st in res.effects]
    assert (s, "channel_scale") in found, f"{k:.1f} x noise: {found}"
    st = [st for n, st in res.effects if n == s and st.effect.name == "channel_scale"][0]
    assert st.effect.partial
    # the flight form of the files with the channel is the traced model there
    t = res.traces[s]
    rows, B = tr.calibrated_field64(res.coefficients, thermal, s)
    m = t.final_model
    sel = t.S_fit.channel_present["supply_V"]
    assert sel.any()
    from generator.trace.samples import gather_samples
    Sx = gather_samples(unit, [tr._with_any_reference(thermal)], [0],
                        coils=res.coefficients.spec.coils,
                        H=res.coefficients.unit_values.get("H_boom_to_body"),
                        channels=list(t.S_fit.channels))[s]
    Sx.channel_present = {c: np.ones(Sx.n, bool) for c in Sx.channels}
    Bm = m.field(Sx)
    # float64 both: agreement to rounding of the folded factors (1e-9 of the field)
    assert np.max(np.abs(B - Bm)) < 1e-6 * np.max(np.abs(Bm)), np.max(np.abs(B - Bm))
