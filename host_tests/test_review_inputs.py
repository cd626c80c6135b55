"""Regression tests of faults a hostile-input review found after the hardening work."""

from __future__ import annotations

import json
import os
import stat

import pytest

from generator.cli import main
from generator.io import names

from conftest import REPO  # noqa: F401  (the test environment)


def run(argv, capsys):
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


@pytest.fixture(scope="module")
def coeffs(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "-o", str(out / "d"), "-q"]) == 0
    return out / "d" / "fit" / "coefficients.json"


def test_output_over_a_device_or_pipe_is_refused(tmp_path, coeffs, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    rc, err = run(["table", coeffs, "-o", fifo, "-q"], capsys)
    assert rc == 2 and len(err) == 1 and "not a regular file" in err[0]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not (tmp_path / "pipe.txt").exists()


def test_output_over_an_input_is_refused(tmp_path, coeffs, capsys):
    c = tmp_path / "c.json"
    c.write_bytes(coeffs.read_bytes())
    before = c.read_bytes()
    rc, err = run(["table", c, "-o", c, "-q"], capsys)
    assert rc == 2 and len(err) == 1 and "is the input" in err[0]
    assert c.read_bytes() == before


def test_dangling_symlink_output_is_refused_before_work(tmp_path, coeffs, capsys):
    link = tmp_path / "gl"
    link.symlink_to(tmp_path / "nowhere")
    rc, err = run(["generate", coeffs, "-o", link, "-q"], capsys)
    assert rc == 2 and len(err) == 1 and "symbolic link" in err[0]


def test_serial_zero_is_refused(tmp_path, coeffs, capsys):
    rc, err = run(["table", coeffs, "-o", tmp_path / "t.bin", "--serial", "0", "-q"], capsys)
    assert rc == 2 and len(err) == 1 and "--serial" in err[0]
    assert not (tmp_path / "t.bin").exists()


def test_integers_beyond_python_s_digit_limit_are_bad_input(tmp_path, coeffs, capsys):
    d = json.loads(coeffs.read_text())
    text = json.dumps(d).replace('"lsb_nT": 25.0', '"lsb_nT": 1' + "0" * 5000, 1)
    assert "0" * 5000 in text
    bad = tmp_path / "big.json"
    bad.write_text(text)
    rc, err = run(["generate", bad, "-o", tmp_path / "g", "-q"], capsys)
    assert rc == 2 and len(err) == 1


def test_negative_demo_seed_is_bad_usage(tmp_path, capsys):
    rc = main(["demo", "-o", str(tmp_path / "d"), "--seed", "-1", "-q"])
    assert rc == 2 and not (tmp_path / "d").exists()


@pytest.mark.parametrize("name", ["casadi_real", "math_errhandling", "unix", "linux", "errno",
                                  "ref", "coil_x", "rate"])
def test_names_that_break_the_c_or_the_columns_are_refused(name):
    assert names.name_fault(name) is not None


def test_numbers_written_as_text_are_refused(tmp_path, coeffs, capsys):
    text = coeffs.read_text()
    import re
    m = re.search(r'"agree_nT": ([0-9.e+-]+)', text)
    assert m
    bad = tmp_path / "s.json"
    bad.write_text(text.replace(m.group(0), f'"agree_nT": "{m.group(1)}"', 1))
    rc, err = run(["generate", bad, "-o", tmp_path / "g", "-q"], capsys)
    assert rc == 2 and len(err) == 1 and "text where numbers go" in err[0]
