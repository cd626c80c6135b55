"""CI cannot pass by skipping: one reading of CI, the CI script sets it, the suite collects
on every Python the package declares, and the markers in pyproject.toml select something."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from ci import in_ci, require
from conftest import REALDATA, REPO


@pytest.mark.parametrize("value,expected", [
    ("true", True), ("TRUE", True), ("True", True), ("1", True), ("yes", True), ("YES", True),
    (" true ", True), ("on", True),
    ("", False), ("0", False), ("false", False), ("False", False), ("no", False), ("off", False),
])
def test_in_ci_parses_the_usual_spellings(value, expected):
    assert in_ci({"CI": value}) is expected


def test_in_ci_unset_is_false():
    assert in_ci({}) is False


def test_require_fails_under_ci_and_skips_outside(monkeypatch):
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="promised resource"):
        require(False, "a thing")
    monkeypatch.setenv("CI", "0")
    with pytest.raises(pytest.skip.Exception):
        require(False, "a thing")
    require(True, "present: nothing happens")


def test_ci_script_exports_ci_and_keeps_the_wheel_check():
    text = (REPO / ".ci" / "run").read_text()
    assert re.search(r"^export CI=true$", text, re.M)
    assert "bash .ci/wheel_check" in text
    assert text.index("export CI=true") < text.index("python3 -m pytest")


def _py_files():
    return sorted((REPO / "host_tests").glob("*.py")) + sorted((REPO / "bench").rglob("*.py"))


def test_only_ci_py_reads_the_ci_variable():
    """Every other file goes through ci.in_ci / ci.require, so CI means one thing."""
    pat = re.compile(r"""environ(\.get)?\s*[\[(]\s*["']CI["']|getenv\(\s*["']CI["']""")
    offenders = [p.name for p in _py_files() if p.name != "ci.py" and pat.search(p.read_text())]
    assert offenders == []


# Standard-library modules added after Python 3.10 (the package declares >= 3.10).
NEW_MODULES = {"tomllib": "3.11", "wsgiref.types": "3.11"}


def _unguarded_new_imports(path: Path) -> list:
    """Imports of NEW_MODULES that are not inside a try whose handler catches the
    ImportError (the fallback pattern: try: import tomllib / except ...: import tomli)."""
    tree = ast.parse(path.read_text())
    guarded = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and node.handlers:
            for sub in node.body:
                for n in ast.walk(sub):
                    guarded.add(id(n))
        # the other fallback pattern: if sys.version_info >= (3, 11): import tomllib
        # else: import tomli as tomllib
        if isinstance(node, ast.If) and "version_info" in ast.unparse(node.test) \
                and node.orelse:
            for sub in node.body:
                for n in ast.walk(sub):
                    guarded.add(id(n))
    bad = []
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        for name in names:
            if name in NEW_MODULES and id(node) not in guarded:
                bad.append(f"{path.relative_to(REPO)}:{node.lineno} imports {name}")
    return bad


def test_tests_collect_on_python_310():
    bad = [b for p in _py_files() for b in _unguarded_new_imports(p)]
    assert bad == []


def test_package_imports_on_python_310():
    bad = [b for p in sorted((REPO / "generator").rglob("*.py"))
           for b in _unguarded_new_imports(p)]
    assert bad == []


def test_every_marker_used_selects_something():
    """A marker declared in pyproject.toml is used by some test (else it deselects nothing)."""
    text = (REPO / "pyproject.toml").read_text()
    block = text[text.index("[tool.pytest.ini_options]"):]
    markers = block[block.index("markers"):]
    declared = re.findall(r'^\s*"(\w+):', markers[:markers.index("]")], re.M)
    used = set()
    for p in (REPO / "host_tests").glob("test_*.py"):
        used |= set(re.findall(r"pytest\.mark\.(\w+)", p.read_text()))
    assert declared and set(declared) <= used, (declared, used)


def test_real_recordings_present_under_ci(realdata_dir):
    """The real-data tests need ../shared/realdata; in CI its absence is a failure."""
    require((realdata_dir / "px4_ecl_office" / "sensor_mag_0.csv").exists(),
            f"PX4 log missing under {realdata_dir}")
    assert REALDATA == realdata_dir


def test_example_unit_committed_under_ci():
    """test_bitexact.py leaves the example unit out of its cases when the file is missing;
    here that absence is a failure under CI."""
    from chain_fixtures import EXAMPLE_COEFFS
    require(EXAMPLE_COEFFS.exists(), f"no committed example unit at {EXAMPLE_COEFFS}")


def test_gcc_present_under_ci():
    from ci import require_gcc
    require_gcc()
