"""`magcal import` on a full disk (out14 left it: its Staging wrote outside io.outputs):
one line naming the output folder and the system's reason, exit 1, no folder it made and
no staging file left behind, as every other verb's outputs."""

from __future__ import annotations

import errno
import os

import pytest

from generator.cli import main
from generator.io import icd_write


def test_a_full_disk_during_an_import(tmp_path, capsys, monkeypatch):
    px4 = [os.path.join(r, f) for r, _, fs in os.walk("/work/shared/realdata")
           for f in fs if f.endswith(".ulg")]
    if not px4:
        pytest.skip("no PX4 log under /work/shared/realdata")

    def full(path, text):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    monkeypatch.setattr(icd_write, "_atomic_write", full)
    out = tmp_path / "new" / "imp"
    rc = main(["import", "px4", px4[0], "-o", str(out), "-q"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 1 and len(err) == 1, err
    assert err[0] == (f"magcal import: {out}: cannot write the output: No space left on "
                      "device (ENOSPC)"), err
    assert not (tmp_path / "new").exists()
