"""The one reading of the CI environment variable, and what a missing resource means.

`.ci/run` exports CI=true. Under CI a test that needs a promised resource (the shared
example unit, the real recordings, gcc, the ARM toolchain, chromium, the committed example
unit) FAILS when the resource is missing: CI cannot pass by skipping. Outside CI the test
skips with a message naming what to install.
"""

from __future__ import annotations

import os

import pytest

_TRUE = ("1", "true", "yes", "on")


def in_ci(environ=None) -> bool:
    """True when CI is set to true/1/yes/on (any case); unset, empty, 0, false, no: False."""
    value = (os.environ if environ is None else environ).get("CI", "")
    return value.strip().lower() in _TRUE


def require(ok: bool, what: str):
    """Skip (outside CI) or fail (under CI) when a promised resource is missing."""
    if ok:
        return
    if in_ci():
        pytest.fail(f"CI is set and a promised resource is missing: {what}")
    pytest.skip(what)


def require_gcc():
    import shutil
    require(shutil.which("gcc") is not None, "gcc not found (apt-get install gcc libc6-dev)")
