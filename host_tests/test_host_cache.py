"""Issue 20: HostUnit's build cache is keyed by hashes of its inputs, not by rendering.

A cached build starts without rendering the C (no CasADi, no Jinja2 call); any change of
an input (a template byte, a generator source byte, a coefficient) changes the key, so a
stale build is never loaded; the sha256 sidecar check of the cached module stays.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import generator
from generator.flight import host as host_mod
from generator.flight.codegen import TEMPLATE_DIR
from generator.flight.coeffs import CoefficientSet, json_default
from generator.flight.host import HostUnit, input_key

from conftest import REPO

COEFFS = REPO / "generated" / "samsat_fm1" / "coefficients.json"


def _cs():
    return CoefficientSet.load(COEFFS)


def _changed_coefficient(cs, delta=1e-3):
    d = json.loads(json.dumps(cs.to_json_dict(), default=json_default))
    name = cs.unit.sensors[0].name
    d["sensors"][name]["b_poly_nT"][0][0] += delta
    return CoefficientSet.from_json_dict(d, None)


@pytest.fixture()
def roots(tmp_path):
    pkg = tmp_path / "generator"
    shutil.copytree(Path(generator.__file__).resolve().parent, pkg,
                    ignore=shutil.ignore_patterns("__pycache__"))
    tpl = tmp_path / "templates"
    shutil.copytree(TEMPLATE_DIR, tpl)
    return pkg, tpl


def _flip_one_byte(path: Path):
    data = bytearray(path.read_bytes())
    k = len(data) // 2
    data[k] = ord("x") if data[k] != ord("x") else ord("y")
    path.write_bytes(bytes(data))


def test_key_is_stable_and_follows_every_input(roots):
    cs = _cs()
    pkg, tpl = roots
    base = input_key(cs, roots=(pkg, tpl))
    assert input_key(_cs(), roots=(pkg, tpl)) == base          # same inputs, same key
    assert input_key(_changed_coefficient(cs), roots=(pkg, tpl)) != base
    assert input_key(_changed_coefficient(cs, 1e-9), roots=(pkg, tpl)) != base
    assert input_key(cs.with_boom_stowed(), roots=(pkg, tpl)) != base
    _flip_one_byte(tpl / "host_shim.c.j2")
    k_tpl = input_key(cs, roots=(pkg, tpl))
    assert k_tpl != base
    _flip_one_byte(pkg / "flight" / "chain.py")
    assert input_key(cs, roots=(pkg, tpl)) not in (base, k_tpl)


def test_a_new_template_file_changes_the_key(roots):
    cs = _cs()
    pkg, tpl = roots
    base = input_key(cs, roots=(pkg, tpl))
    (tpl / "extra.h.j2").write_text("/* */\n")
    assert input_key(cs, roots=(pkg, tpl)) != base


def test_cached_build_starts_without_rendering(monkeypatch):
    cs = _cs()
    first = HostUnit(cs)                        # builds, or loads an earlier build

    def no_render(*a, **k):
        raise AssertionError("rendered the C although a verified build is cached")

    monkeypatch.setattr(host_mod, "render", no_render)
    again = HostUnit(cs)
    n = 50
    raw = np.full((n, 6), 32768, dtype=np.int64)
    raw[:, :3] += 400
    raw[:, 3:] -= 400
    name = next(s.name for s in cs.unit.sensors if s.set_reset)
    a = first.correct(name, raw, np.full(n, 25.0))
    b = again.correct(name, raw, np.full(n, 25.0))
    assert a["field_body_nT"].tobytes() == b["field_body_nT"].tobytes()

    # a changed coefficient is another key: the old build is not used, the C is rendered
    class Rendered(Exception):
        pass

    def render_called(*a, **k):
        raise Rendered

    monkeypatch.setattr(host_mod, "render", render_called)
    with pytest.raises(Rendered):
        HostUnit(_changed_coefficient(cs, 0.125))


def test_tampered_cached_build_is_not_loaded(tmp_path, monkeypatch):
    """The sha256 sidecar check still guards a cached build found by the input key."""
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))
    cs = _cs()
    HostUnit(cs)
    key = input_key(cs)
    build = tmp_path / "cache" / f"_magcal_host_{key[:16]}"
    mod = next(build.glob("_magcal_host_*.so"))
    side = mod.with_name(mod.name + ".sha256")
    side.write_text("0" * 64 + "\n")
    assert host_mod._verified_module(build, f"_magcal_host_{key[:16]}") is None
