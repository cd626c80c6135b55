"""Review of issue 18, input faults of the in-flight path (items #8, #9, #10, #12, #13):
an unreadable cache entry, a time outside the field model's span, kp_index beside a
file's own ref_norm_nT, every sample disturbed, TLE lines of two objects.

Own data: generator.campaign.simulate_orbit, example unit mounting reduced to its body
MMC5883MA, random truth (seed 1802), ISS TLE, 1 h at 10 s."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from generator.campaign import simulate_orbit as so
from generator.campaign.simulate import make_example_unit, random_truth
from generator.cli import main
from generator.io import orbit
from generator.io.telemetry_csv import read_telemetry
from generator.io.unitfile import _tle_checksum, load_unit


@pytest.fixture(scope="module")
def camp(tmp_path_factory):
    d = tmp_path_factory.mktemp("inp18")
    ex = make_example_unit()
    unit = dataclasses.replace(ex, sensors=ex.sensors[:1], boom_reference=None)
    rng = np.random.default_rng(1802)
    return so.simulate_orbit(unit, random_truth(unit, rng), rng, d, duration_s=3600.0)


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGCAL_CACHE", str(tmp_path / "cache"))


def _rewrite(src, dst, columns: dict):
    """The CSV src with columns replaced or added (name -> per-row values)."""
    lines = src.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    head = lines[k].split(",")
    rows = [ln.split(",") for ln in lines[k + 1:]]
    for name, vals in columns.items():
        if name not in head:
            head.append(name)
            for r in rows:
                r.append("")
        j = head.index(name)
        for r, v in zip(rows, vals):
            r[j] = f"{v:.6g}"
    dst.write_text("\n".join(lines[:k] + [",".join(head)] + [",".join(r) for r in rows])
                   + "\n")
    return dst


def test_unreadable_cache_entry_is_recomputed(camp, tmp_path):
    unit = load_unit(camp["unit"])
    track = orbit.track_of(read_telemetry(camp["csv"], unit), unit)
    field, prov = orbit.field_along(track)     # read_telemetry computed and cached it
    assert prov["cache"] == "hit"
    entry = next((tmp_path / "cache" / "geomag").glob("*.npz"))
    good = entry.read_bytes()
    for damage in (good[: len(good) // 3], b"garbage, not a zip file\n", b""):
        entry.write_bytes(damage)
        again, p = orbit.field_along(track)
        assert p["cache"] == "miss"
        np.testing.assert_array_equal(again, field)
        assert orbit.field_along(track)[1]["cache"] == "hit"    # replaced by a good entry


def test_time_outside_the_model_names_the_input(camp, tmp_path, capsys):
    # IGRF-14 ends 2030-01-01: an epoch half an hour before, one hour of samples
    text = camp["unit"].read_text()
    ep = re.search(r'epoch_utc = "([^"]+)"', text).group(1)
    u = tmp_path / "u2030.toml"
    u.write_text(text.replace(ep, "2029-12-31T23:30:00Z"))
    assert main(["fit", str(u), str(camp["csv"]), "-o", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert str(camp["csv"]) in err[0] and "[orbit] epoch_utc" in err[0]
    assert "cache" not in err[0] and "time_s" in err[0]
    # the line of the first sample past 2030-01-01 (1800 s after the epoch, 10 s steps)
    tel = read_telemetry(camp["csv"], load_unit(camp["unit"]))
    first = int(np.flatnonzero(tel.time_s > 1800.0)[0])
    assert f":{int(tel.line_numbers[first])}:" in err[0], err[0]


def test_every_sample_disturbed_is_said(camp, tmp_path, capsys):
    n = camp["arrays"]["time_s"].shape[0]
    csv = _rewrite(camp["csv"], tmp_path / "storm.csv", {"kp_index": np.full(n, 5.0)})
    assert main(["fit", str(camp["unit"]), str(csv), "-o", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "kp_index" in err and "every one" in err and "disturbed" in err


def test_kp_honoured_beside_own_ref_norm(camp, tmp_path):
    A = camp["arrays"]
    n = A["time_s"].shape[0]
    kp = np.where(np.arange(n) % 4 == 0, 6.0, 1.0)
    csv = _rewrite(camp["csv"], tmp_path / "ref.csv",
                   {"kp_index": kp, "ref_norm_nT": A["model_norm_nT"]})
    unit = load_unit(camp["unit"])
    tel = read_telemetry(csv, unit)
    assert "field_reference" not in tel.meta            # its own reference is used
    assert tel.meta["kp_left_out"]["samples"] == int((kp >= 4).sum())
    assert np.all(np.isnan(tel.columns["ref_norm_nT"][kp >= 4]))
    assert np.all(np.isfinite(tel.columns["ref_norm_nT"][kp < 4]))


def test_tle_lines_of_two_objects(camp, tmp_path, capsys):
    text = camp["unit"].read_text()
    l2 = so.ISS_TLE[1]
    other = l2[:2] + "25545" + l2[7:68]
    other += _tle_checksum(other + "0")
    u = tmp_path / "mismatch.toml"
    u.write_text(text.replace(l2, other))
    assert main(["fit", str(u), str(camp["csv"]), "-o", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # refused when the unit file is read, whatever the position source: file, line, key
    assert len(err) == 1 and "[orbit]" in err[0] and "tle" in err[0] and str(u) in err[0]
    assert "catalogue number" in err[0]
