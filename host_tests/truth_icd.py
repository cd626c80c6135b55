"""The truth baseline of a simulated unit, computed independently of the project.

Tests that compare a fit with "what the TRUE parameters give on the same raw data" must
not take the raw data through the project's own preprocessing: a wrong counts -> nT or
axis mapping there would be shared by the fit and the baseline, and the comparison would
pass. Here everything comes from the CSV and the unit file with a few lines of numpy,
written from the shared documents only:

* ICD section 1-2: frame axis k is the sensor axis named axes[k] ("+z", "-y", ...) with
  that sign; counts -> nT: (count - zero_count) x lsb_nT, or for a SET/RESET sensor
  (set - reset) / 2 x lsb_nT (docs/methods.md section 3: field = (Out1 - Out2) / 2);
* shared/data/<unit>/README.md: m = W(T) B_frame + b(T) + K i_coil in the sensor's frame,
  dT = T - t_ref, so the best any calibration can do is W(T)^-1 (m - b(T) - K i) at the
  reported temperature.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
from scipy.stats import norm

try:
    import tomllib
except ModuleNotFoundError:   # Python 3.10
    import tomli as tomllib


def read_csv(path) -> dict:
    """Column name -> float array ('#' lines are comments, the first other is the header;
    an empty field is NaN)."""
    with open(path) as f:
        lines = [ln for ln in f if not ln.startswith("#")]
    header = next(csv.reader([lines[0]]))
    data = np.genfromtxt(lines[1:], delimiter=",", dtype=float)
    return {name: data[:, j] for j, name in enumerate(header)}


def unit_sensors(unit_toml) -> dict:
    """Sensor name -> its [[sensor]] table of the unit file (plain TOML, no project code)."""
    with open(unit_toml, "rb") as f:
        doc = tomllib.load(f)
    return {s["name"]: s for s in doc["sensor"]}


def load_truth_json(path) -> dict:
    with open(path) as f:
        return json.load(f)


def icd_frame_field(cols: dict, sensor: dict) -> np.ndarray:
    """ICD section 1-2: counts -> nT (SET/RESET: (set - reset) / 2 x lsb; else
    (count - zero) x lsb), then frame axis k = sign x sensor axis named axes[k]."""
    name, lsb = sensor["name"], sensor["lsb_nT"]
    if sensor.get("set_reset", False):
        f = {a: (cols[f"{name}_set_{a}"] - cols[f"{name}_reset_{a}"]) / 2 * lsb for a in "xyz"}
    else:
        f = {a: (cols[f"{name}_{a}"] - sensor["zero_count"]) * lsb for a in "xyz"}
    return np.stack([(1.0 if ax[0] == "+" else -1.0) * f[ax[1]] for ax in sensor["axes"]],
                    axis=1)


def poly_at(poly, dT):
    """sum_k poly[k] dT^k for poly (K, ...) and dT (N,) -> (N, ...)."""
    poly = np.asarray(poly, float)
    dT = np.asarray(dT, float).reshape(-1)
    return sum(poly[k][None] * dT.reshape((-1,) + (1,) * (poly.ndim - 1)) ** k
               for k in range(poly.shape[0]))


def true_parameters_field(truth: dict, sensor: str, m, temp_C, coil_A=None) -> np.ndarray:
    """W(T)^-1 (m - b(T) - K i) with truth.json's parameters, T as reported; m (N, 3) in
    the sensor's frame; coil_A (N, 3) in the order x, y, z or None."""
    t = truth["sensors"][sensor]
    dT = np.asarray(temp_C, float) - float(truth["t_ref_C"])
    y = np.asarray(m, float) - poly_at(t["b_poly_frame_nT"], dT)
    if coil_A is not None and "K_coil_frame_nT_per_A" in t:
        y = y - np.nan_to_num(np.asarray(coil_A, float)) @ np.asarray(
            t["K_coil_frame_nT_per_A"], float).T
    return np.linalg.solve(poly_at(t["W_poly_frame"], dT), y[..., None])[..., 0]


def rms_norm_error(B, B_true) -> float:
    """RMS over samples of |B| - |B_true| (nT)."""
    return float(np.sqrt(np.mean((np.linalg.norm(B, axis=1)
                                  - np.linalg.norm(B_true, axis=1)) ** 2)))


def rms_vector_error(B, B_true) -> float:
    """RMS over samples and axes of B - B_true (nT per axis)."""
    return float(np.sqrt(np.mean(np.sum((np.asarray(B) - B_true) ** 2, axis=1) / 3)))


def ratio_bound(n: int, n_ratios: int, alpha: float = 1e-3) -> float:
    """Upper bound of RMS error (fitted calibration) / RMS error (true parameters) on the
    same n samples, for a fit that reaches the noise floor.

    The RMS of n samples of noise estimates the noise's RMS with a relative spread of
    1/sqrt(2n) (per axis; chi-square with n degrees of freedom). The two errors are the
    SAME noise plus, for the fit, its parameter error, which adds only ~p/(3n) in variance
    (p parameters: 48 for cubic M(T), b(T); ratio ~1 + p/(6n) = 1.0002 at n = 36000): the
    spread of one RMS on its own, 1/sqrt(2n), is a generous bound for the spread of their
    ratio. z: the normal's one-sided point at alpha over the n_ratios ratio assertions of
    a test file (Bonferroni). n = 36000 (chamber), 15 ratios: 1.014; n = 4000 (hand
    rotation): 1.043. An offset biased by 0.3 x the noise per axis gives
    sqrt(1 + 0.09) = 1.044, 3 x the chamber's margin.
    """
    return 1.0 + float(norm.isf(alpha / n_ratios)) / math.sqrt(2 * n)
