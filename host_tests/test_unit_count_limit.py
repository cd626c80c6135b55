"""A raw count range the flight chain cannot hold exactly is refused in the unit file
(review 20e F1: a 32-bit offset-binary part passed every check, then its C did not compile:
`raw >= 3147483648` on an int32_t). Counts are int32_t in the flight C and converted to the
chain's float type: exact up to 2^24 in float32 (the folded chain's count - zero_count
rests on that), up to int32's range in float64 (io.unitfile.EXACT_COUNT_LIMIT)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from generator.cli import main
from generator.errors import InputError
from generator.io.unitfile import EXACT_COUNT_LIMIT, load_unit


def _unit(tmp_path, zero, range_nT, lsb_nT, float_type=None):
    text = ('[unit]\nid = "z"\nlab_field_nT = 48000.0\n'
            + (f'float = "{float_type}"\n' if float_type else "")
            + '\n[[sensor]]\nname = "g"\npart = "generic"\nframe = "body"\n'
              'axes = ["+x", "+y", "+z"]\ninput = "counts"\n'
              f"range_nT = {range_nT!r}\nlsb_nT = {lsb_nT!r}\nzero_count = {zero}\n"
              "temperature = false\n")
    p = tmp_path / "unit.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("float_type", [None, "float32", "float64"])
def test_a_32_bit_offset_binary_part_is_refused_naming_the_key(tmp_path, float_type):
    p = _unit(tmp_path, 2 ** 31, 1e6, 0.001, float_type)
    with pytest.raises(InputError) as e:
        load_unit(p)
    msg = str(e.value)
    assert "zero_count" in msg and "(1147483648, 3147483648)" in msg
    line = p.read_text().splitlines().index(f"zero_count = {2 ** 31}") + 1
    assert msg.startswith(f"{p}:{line}:")                   # the zero_count line
    assert ('use float = "float64"' in msg) == (float_type != "float64")  # the way out


def test_the_limit_is_exact_integers_of_the_chain(tmp_path):
    # a 24-bit offset-binary part: counts 0 .. 2^24, every one exact in float32
    u = load_unit(_unit(tmp_path, 2 ** 23, 2 ** 23 * 0.1, 0.1))
    assert u.sensors[0].zero_count == 2 ** 23
    # one lsb of range more reaches 2^24 + 1: not exact in float32
    with pytest.raises(InputError, match="range_nT: the raw range"):
        load_unit(_unit(tmp_path, 2 ** 23, (2 ** 23 + 1) * 0.1, 0.1))
    # float64 holds it, up to int32's range
    load_unit(_unit(tmp_path, 2 ** 23, (2 ** 23 + 1) * 0.1, 0.1, "float64"))
    # (range_nT is at most 1e7 nT: a fine lsb reaches the int32 counts)
    load_unit(_unit(tmp_path, 2 ** 30, 1e6, 0.001, "float64"))      # up to 2,073,741,824
    with pytest.raises(InputError, match=r"\+-2,147,483,647"):
        load_unit(_unit(tmp_path, 2 ** 30, 1e6, 0.0009, "float64"))  # 2,184,852,935
    assert EXACT_COUNT_LIMIT == {"float32": 2 ** 24, "float64": 2 ** 31 - 1}


def test_cli_exit_2_one_line(tmp_path, capsys):
    p = _unit(tmp_path, 2 ** 31, 1e6, 0.001)
    rc = main(["plan", str(p), "-o", str(tmp_path / "plan"), "-q"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and "zero_count" in err[0]


@pytest.mark.slow
def test_a_float64_unit_at_the_int32_limit_compiles_and_applies(tmp_path):
    """A float64 unit with counts near the int32 limit (up to 2,073,741,824): simulate, fit, generate
    --compile and apply run (the C's saturation limits fit int32_t)."""
    p = _unit(tmp_path, 2 ** 30, 1e6, 0.001, "float64")
    run = [sys.executable, "-m", "generator.cli"]
    for argv in (["simulate", str(p), "--seed", "3", "-o", "sim", "--campaigns",
                  "thermal_12pos", "rotation", "-q"],
                 ["fit", str(p), "sim/thermal_12pos.csv", "sim/rotation.csv", "-o", "fit",
                  "--no-report", "-q"],
                 ["generate", "fit/coefficients.json", "-o", "gen", "--compile", "-q"],
                 ["apply", "fit/coefficients.json", "sim/rotation.csv", "-o", "out.csv",
                  "-q"]):
        r = subprocess.run(run + argv, cwd=tmp_path, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, (argv[0], r.stderr[-2000:])
