"""`magcal trace` on orbit telemetry with no ref_* column (the reference from the field
model along the TLE's track): the post-launch new current (a payload's supply switching
on and off, simulate_orbit.new_current) is traced to its channel on the sensor it
couples into, and nothing is invented on the others.

Seeds: development used unit seed 11 and orbit seed 111; this test's draws (unit seed
31, SeedSequence(31) children) were first run when the file was complete. The coupling,
(300, -200, 150) nT per A at 0.5 A, is ~ 190 nT at the sensor, several times the MMC's
noise, so a tracer that misses it fails here.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.campaign import simulate_orbit as so
from generator.campaign.simulate import load_truth, make_example, make_example_unit
from generator.cli import main


@pytest.fixture(scope="module")
def traced(tmp_path_factory):
    d = tmp_path_factory.mktemp("orbit_trace")
    paths = make_example(d, seed=31, size="example")
    assert main(["fit", str(paths["unit"]), str(paths["thermal_12pos"]),
                 str(paths["rotation"]), str(paths["coils"]), "-o", str(d / "ground"),
                 "-q"]) == 0
    unit = make_example_unit()
    ss_change, ss_orbit = np.random.SeedSequence(31).spawn(2)
    changed, _ = so.post_launch(load_truth(d / "truth.json", unit),
                                rng=np.random.default_rng(ss_change))
    orb = so.simulate_orbit(unit, changed, np.random.default_rng(ss_orbit), d / "orbit",
                            effects=[so.new_current("mmc2", (300.0, -200.0, 150.0))],
                            duration_s=6 * 3600.0)
    assert main(["fit", str(orb["unit"]), str(orb["csv"]), "--prior",
                 str(d / "ground" / "coefficients.json"), "-o", str(d / "recal"), "-q"]) == 0
    assert main(["trace", str(orb["unit"]), str(orb["csv"]), "--coeffs",
                 str(d / "recal" / "coefficients.json"), "-o", str(d / "trace"), "-q"]) == 0
    return json.loads((d / "trace" / "trace.json").read_text())


def test_the_new_current_is_traced_to_its_channel(traced):
    found = [(e["sensor"], e["explained_by"]) for e in traced["effects"]]
    assert ("mmc2", ["payload_A"]) in found
    assert all(s == "mmc2" for s, _ in found), found


def test_the_trace_removes_it(traced):
    (e,) = [e for e in traced["effects"] if e["sensor"] == "mmc2"]
    assert e["rms_after_nT"] < 0.8 * e["rms_before_nT"]
