"""A wrong declared input unit names its cause (review #19 F8).

nT data declared input = "mG" (x100), "uT" (x1000) or "G" (x1e5): every sample is then
beyond the part's full scale and unusable; the fit used to stop at "no usable sample with a
field reference" although the files carry references. generator/io/full_scale.py,
called from pipeline.fit, says instead: all N samples of the sensor beyond the full scale,
is the input unit right -- exit 2, one line naming the file, the sensor and the key.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.cli import main
from generator.errors import InputError
from generator.io.full_scale import check_full_scale
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit

UNIT = """[unit]
id = "onent"
lab_field_nT = 47000.0

[[sensor]]
name = "ist"
part = "IST8310"
frame = "body"
axes = ["+x", "+y", "+z"]
input = "{input}"
temperature = false
"""


@pytest.fixture(scope="module")
def nT_campaign(tmp_path_factory):
    """A rotation campaign (4000 samples, ~47000 nT, ICD physical input in nT)."""
    d = tmp_path_factory.mktemp("hint")
    (d / "unit.toml").write_text(UNIT.format(input="nT"))
    assert main(["simulate", str(d / "unit.toml"), "-o", str(d / "sim"), "-q", "--seed", "3",
                 "--campaigns", "rotation"]) == 0
    return d, d / "sim" / "rotation.csv"


@pytest.mark.parametrize("declared", ["mG", "uT", "G"])
def test_nT_data_declared_in_a_larger_unit(nT_campaign, tmp_path, capsys, declared):
    d, csv = nT_campaign
    (tmp_path / "unit.toml").write_text(UNIT.format(input=declared))
    capsys.readouterr()
    rc = main(["fit", str(tmp_path / "unit.toml"), str(csv), "-o", str(tmp_path / "fit"),
               "--no-report", "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    assert "rotation.csv" in err and "sensor 'ist'" in err
    assert f'input = "{declared}"' in err and "full scale" in err
    n = read_telemetry(csv, load_unit(d / "unit.toml")).n
    assert f"all {n} samples" in err
    assert "no usable sample" not in err
    assert not (tmp_path / "fit").exists()


def test_right_unit_and_partial_saturation_pass(nT_campaign, tmp_path):
    """The declared unit right: silent. Some samples beyond full scale (a magnet passing by):
    counted by preprocess, not this error."""
    d, csv = nT_campaign
    unit = load_unit(d / "unit.toml")
    tel = read_telemetry(csv, unit)
    check_full_scale(unit, [tel])
    fs = unit.sensor("ist").full_scale_nT
    tel.columns["ist_x"] = np.array(tel.columns["ist_x"], dtype=float)
    tel.columns["ist_x"][: tel.n // 2] = 2.0 * fs
    check_full_scale(unit, [tel])
    tel.columns["ist_x"][:] = 2.0 * fs                 # now every sample
    with pytest.raises(InputError, match=r"all \d+ samples of sensor 'ist' beyond"):
        check_full_scale(unit, [tel])
