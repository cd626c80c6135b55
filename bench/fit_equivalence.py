#!/usr/bin/env python3
"""Does a faster fit decide the same? coefficients.json of today's tree against the tree at
--baseline-commit, on the same inputs, fitted in the same run.

    python3 bench/fit_equivalence.py [--baseline-commit c6ef128] [--keep DIR]
                                     [--cases fm1_thermal,demo]

Cases (each fitted by generator.pipeline.fit in a fresh subprocess per tree, BLAS pinned
to one thread, MAGCAL_WORKERS=1, run outside any checkout and checked to import the tree's
own generator/):

* fm1_thermal, fm1_all: the shared unit samsat_fm1 (thermal_12pos; and thermal_12pos,
  rotation, coils, flight_6h: the coil coupling and the boom alignment too);
* fm1_orbit_on_prior: its flight_6h alone on the prior of its ground campaigns (fitted
  by the baseline tree): the in-flight recalibration (magnitudes on a prior);
* demo: the demo's simulated unit (generator.campaign.simulate.make_example, seed 1) and
  its four ground campaigns, as `magcal demo` fits them;
* u_lis (LIS3MDL + QMC5883L), u_phys (a physical-input generic part with SET/RESET, float64,
  and an RM3100 on the boom without temperature), u_mmc (MMC5883MA without SET/RESET +
  MPU-9255): units of other parts, simulated by `magcal simulate --seed 7` (thermal_12pos,
  rotation), made with the BASELINE tree's simulator so both trees fit the same bytes.

Compared: the whole coefficients.json (values, uncertainties, the fit's stats: chosen
degrees, held-out scores, flags, warnings, notes). Strings, booleans, integers, shapes and
keys must be identical (a decision or a text that changed is listed); floats are reported
as the largest relative difference |a - b| / max(|a|, |b|) per case and top-level key,
with the path where it occurs. Exit 1 if anything but floats differs. No threshold on the
floats: the reader judges whether the largest difference is float64 round-off (~1e-16
relative per operation, amplified by the conditioning of the normal equations).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "bench"))
from bench_fit import _env, extract  # noqa: E402
from bench_io import FM1  # noqa: E402

UNITS = {
    "u_lis": """[unit]
id = "u_lis"
lab_field_nT = 48000.0
float = "float32"

[[sensor]]
name = "lis1"
part = "LIS3MDL"
frame = "body"
axes = ["+x", "-y", "-z"]
lsb_nT = 14.62
zero_count = 0
set_reset = false
noise_nT = 320.0

[[sensor]]
name = "qmc1"
part = "QMC5883L"
frame = "body"
axes = ["+y", "+x", "-z"]
lsb_nT = 8.333
zero_count = 0
set_reset = false
noise_nT = 200.0
""",
    "u_phys": """[unit]
id = "u_phys"
lab_field_nT = 50000.0
float = "float64"

[boom]
reference = "gen1"

[[sensor]]
name = "gen1"
part = "generic"
frame = "body"
axes = ["+x", "+y", "+z"]
lsb_nT = 1.0
zero_count = 0
set_reset = true
noise_nT = 100.0
input = "uT"
range_nT = 1600000.0

[[sensor]]
name = "rm1"
part = "RM3100"
frame = "boom"
axes = ["-z", "+x", "-y"]
lsb_nT = 13.33
zero_count = 0
set_reset = false
noise_nT = 15.0
temperature = false
""",
    "u_mmc": """[unit]
id = "u_mmc"
lab_field_nT = 52000.0
float = "float32"

[[sensor]]
name = "mmc1"
part = "MMC5883MA"
frame = "body"
axes = ["-x", "+z", "+y"]
lsb_nT = 25.0
zero_count = 32768
set_reset = false
noise_nT = 40.0

[[sensor]]
name = "mpu1"
part = "MPU-9255"
frame = "body"
axes = ["+y", "-x", "+z"]
lsb_nT = 150.0
zero_count = 0
set_reset = false
noise_nT = 250.0
""",
}

FIT = r"""
import json, sys
from generator import pipeline
cases = json.loads(sys.argv[1])
for name, (unit, files, out, prior) in cases.items():
    pipeline.fit(unit, files, prior=prior).save(out)
"""

# the fits ran the generator/ of the tree asked for (not another one on sys.path)
CHECK_TREE = r"""
import generator, pathlib, sys
assert pathlib.Path(generator.__file__).resolve().parent.parent == \
    pathlib.Path(sys.argv[2]).resolve(), (generator.__file__, sys.argv[2])
"""

DEMO = r"""
import sys
from generator.campaign import simulate
simulate.make_example(sys.argv[1], seed=1)
"""


def make_cases(tree: Path, data: Path) -> dict:
    """{case: (unit.toml, [files][, prior])}, the simulated ones written by `tree`'s
    simulator, the prior fitted by `tree`."""
    env = _env(tree)
    data.mkdir(parents=True, exist_ok=True)
    cases = {"fm1_thermal": (FM1 / "unit.toml", [FM1 / "thermal_12pos.csv"]),
             "fm1_all": (FM1 / "unit.toml", [FM1 / f for f in (
                 "thermal_12pos.csv", "rotation.csv", "coils.csv", "flight_6h.csv")])}
    # the in-flight recalibration: the orbit file's magnitudes on a ground calibration
    # (the prior, fitted by `tree` from the ground files)
    prior = data / "fm1_ground.json"
    subprocess.run([sys.executable, "-c", FIT, json.dumps({"ground": (
        str(FM1 / "unit.toml"), [str(FM1 / f) for f in ("thermal_12pos.csv", "rotation.csv",
                                                         "coils.csv")], str(prior), None)})],
                   env=env, check=True, cwd=data)
    cases["fm1_orbit_on_prior"] = (FM1 / "unit.toml", [FM1 / "flight_6h.csv"], prior)
    subprocess.run([sys.executable, "-c", DEMO, str(data / "demo")], env=env, check=True,
                   cwd=data)
    cases["demo"] = (data / "demo" / "unit.toml", [data / "demo" / f"{k}.csv" for k in (
        "thermal_12pos", "rotation", "coils", "coil_study")])
    for name, text in UNITS.items():
        (data / f"{name}.toml").write_text(text, encoding="utf-8")
        subprocess.run([sys.executable, "-m", "generator.cli", "simulate",
                        str(data / f"{name}.toml"), "-o", str(data / name), "--seed", "7",
                        "-q", "--campaigns", "thermal_12pos", "rotation"], env=env,
                       check=True, cwd=data)
        cases[name] = (data / name / "unit.toml",
                       [data / name / f"{k}.csv" for k in ("thermal_12pos", "rotation")])
    return cases


def fit_all(tree: Path, cases: dict, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    arg = {k: (str(c[0]), [str(f) for f in c[1]], str(out / f"{k}.json"),
               str(c[2]) if len(c) > 2 else None) for k, c in cases.items()}
    # cwd: not a checkout (python -c puts the working directory first on sys.path, which
    # would import the generator/ found there instead of `tree`'s)
    p = subprocess.run([sys.executable, "-c", CHECK_TREE + FIT, json.dumps(arg), str(tree)],
                       env=_env(tree, MAGCAL_WORKERS="1"), capture_output=True, text=True,
                       cwd=out)
    if p.returncode:
        raise SystemExit(f"{tree}: {p.stderr.strip()[-2000:]}")
    return {k: json.loads(Path(v[2]).read_text()) for k, v in arg.items()}


def compare(a, b, path, floats: dict, other: list):
    """Walk two JSON values: float differences into floats[top key] = (rel, path, a, b),
    anything else that differs into other."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            other.append(f"{path}: keys {sorted(set(a) ^ set(b))}")
        for k in a.keys() & b.keys():
            compare(a[k], b[k], f"{path}/{k}", floats, other)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            other.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b)):
            compare(x, y, f"{path}[{i}]", floats, other)
    elif isinstance(a, float) and isinstance(b, float):
        if a == b or (math.isnan(a) and math.isnan(b)):
            rel = 0.0
        else:
            rel = abs(a - b) / max(abs(a), abs(b))
        top = "/".join(path.split("/")[:2])
        if rel > floats.get(top, (-1.0,))[0]:
            floats[top] = (rel, path, a, b)
    elif type(a) is not type(b) or a != b:
        other.append(f"{path}: {str(a)[:200]!r} != {str(b)[:200]!r}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-commit", default="c6ef128")
    ap.add_argument("--keep", help="keep the inputs and coefficients.json files here")
    ap.add_argument("--cases", help="comma-separated: only these cases (default: all seven)")
    a = ap.parse_args()
    td = tempfile.mkdtemp(prefix="fit_equivalence_")
    tmp = Path(td)
    try:
        base = extract(a.baseline_commit, tmp / "baseline")
        cases = make_cases(base, tmp / "data")
        if a.cases:
            want = a.cases.split(",")
            unknown = sorted(set(want) - set(cases))
            if unknown:
                raise SystemExit(f"--cases: unknown {unknown} (the cases: {sorted(cases)})")
            cases = {k: v for k, v in cases.items() if k in want}
        res_b = fit_all(base, cases, tmp / "out_baseline")
        res_t = fit_all(REPO, cases, tmp / "out_today")
        failed = False
        for k in cases:
            floats, other = {}, []
            compare(res_b[k], res_t[k], "", floats, other)
            worst = max(floats.values(), default=(0.0, "", 0, 0))
            if worst[0] == 0 and not other:
                print(f"{k}: IDENTICAL (every value bit for bit)")
                continue
            print(f"{k}: {'IDENTICAL apart from floats' if not other else 'DIFFERENT'}; "
                  f"largest relative float difference {worst[0]:.3g} at {worst[1]} "
                  f"({worst[2]!r} vs {worst[3]!r})")
            for top, (rel, p, x, y) in sorted(floats.items()):
                if rel > 0:
                    print(f"    {top}: {rel:.3g} at {p}")
            for o in other[:20]:
                print(f"    DIFFERS {o}")
            if len(other) > 20:
                print(f"    ... and {len(other) - 20} more")
            failed |= bool(other)
    finally:
        if a.keep:
            shutil.copytree(tmp, a.keep, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("baseline"))
        shutil.rmtree(tmp, ignore_errors=True)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    main()
