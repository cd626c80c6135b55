"""A fitted M far from unit scale is flagged (fit/sanity.py): readings in another unit than
the unit file says by a factor below scale_check's refusal (20), e.g. counts declared at
a sixth of their LSB, give M ~ 6; the warning names the key. Units in the right units get
no such warning."""

from pathlib import Path

import pytest

from generator.fit.thermal import fit_unit
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "samsat_fm1"


def _fit(unit_path):
    unit = load_unit(unit_path)
    return fit_unit(unit, [read_telemetry(SHARED / "rotation.csv", unit)])


def _scale_warnings(cal):
    return [w for w in cal.stats["sanity"]["warnings"] if "scales the readings" in w]


@pytest.mark.skipif(not (SHARED / "unit.toml").exists(), reason="shared data not present")
@pytest.mark.parametrize("factor", [6.0, 0.125])
def test_wrong_lsb_flagged_right_ones_not(tmp_path, factor):
    text = (SHARED / "unit.toml").read_text()
    lines = text.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip() == 'name = "mpu1"')
    k = next(i for i in range(at, len(lines)) if lines[i].strip().startswith("lsb_nT"))
    lines[k] = f"lsb_nT = {150.0 / factor!r}"        # readings now `factor` x too small
    (tmp_path / "unit.toml").write_text("\n".join(lines) + "\n")
    cals = _fit(tmp_path / "unit.toml")
    got = _scale_warnings(cals["mpu1"])
    assert len(got) == 1 and "lsb_nT" in got[0], got
    sc = cals["mpu1"].stats["sanity"]
    assert sc["scale_M_max"] == pytest.approx(factor, rel=0.1)
    for name, cal in cals.items():
        if name != "mpu1":
            assert not _scale_warnings(cal), (name, _scale_warnings(cal))
