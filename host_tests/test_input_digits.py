"""A cell in another script's digits ('１２', full-width) is not a number of the ICD's CSV:
exit 2 naming line and column, never read as 12 (numpy's and Python's float() take it)."""
import pytest

from generator.errors import InputError
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import load_unit


@pytest.mark.parametrize("cell", ["１２", "١٢", "1２"])
def test_non_ascii_digits_are_refused(tmp_path, fm1_dir, cell):
    unit = load_unit(fm1_dir / "unit.toml")
    lines = (fm1_dir / "rotation.csv").read_text(encoding="utf-8").splitlines()
    header_at = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    names = lines[header_at].split(",")
    row = header_at + 6
    cells = lines[row].split(",")
    j = names.index("mpu1_x")
    cells[j] = cell
    lines[row] = ",".join(cells)
    p = tmp_path / "digits.csv"
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(InputError) as e:
        read_telemetry(p, unit)
    msg = str(e.value)
    assert "not a number" in msg and "mpu1_x" in msg and f":{row + 1}" in msg, msg
