"""Review #20d F1: coefficients the flight code's table checks refuse (here det M below
1/27) are written by `magcal generate` and used by `magcal apply`, but flagged: one
warning line on stderr, -q or not, naming the check. (`magcal table` exits 2 on them; as
the compiled-in default, <unit>_table_init replaces them by NaN.)"""

from __future__ import annotations

import json
from pathlib import Path

from generator.cli import main

EXAMPLE = Path(__file__).resolve().parents[1] / "generated" / "samsat_fm1" / "coefficients.json"


def test_generate_flags_coefficients_the_table_checks_refuse(tmp_path, capsys):
    d = json.loads(EXAMPLE.read_text())
    d["sensors"]["mpu1"]["M_poly"][0][1] = [0.03 * v for v in d["sensors"]["mpu1"]["M_poly"][0][1]]
    bad = tmp_path / "lowdet.json"
    bad.write_text(json.dumps(d))
    assert main(["generate", str(bad), "-o", str(tmp_path / "g"), "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "BAD_DETERMINANT" in err[0], err
    assert main(["table", str(bad), "-o", str(tmp_path / "t.bin"), "-q"]) == 2
    capsys.readouterr()
    # the example's own coefficients pass the checks: no warning
    assert main(["generate", str(EXAMPLE), "-o", str(tmp_path / "g2"), "-q"]) == 0
    assert capsys.readouterr().err.strip() == ""
