"""Shared fixtures: paths to the repository, the shared data and the example unit."""

from __future__ import annotations

import os
import sys
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")   # before numpy loads: see generator/__init__.py

import pytest

from ci import require

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# ../shared beside the checkout (ICD); MAGCAL_SHARED points elsewhere (a git worktree
# whose parent folder has no shared/).
SHARED = Path(os.environ.get("MAGCAL_SHARED") or REPO.parent / "shared")
FM1 = SHARED / "data" / "samsat_fm1"
REALDATA = SHARED / "realdata"


@pytest.fixture(scope="session")
def fm1_dir() -> Path:
    require(FM1.is_dir(), f"shared example unit not found at {FM1} "
                          "(CI must have ../shared beside the checkout)")
    return FM1


@pytest.fixture(scope="session")
def realdata_dir() -> Path:
    require(REALDATA.is_dir(), f"shared real recordings not found at {REALDATA}")
    return REALDATA
