"""True parameters of a simulated unit (truth.json) and what they give on raw data.

Truth convention (shared/data/<unit>/README.md), per sensor in its frame after the axis
mapping, dT = T - t_ref:

    m = W(T) B_frame + b(T) + K i_coil,   W(T) = sum_k W_k dT^k,   b(T) = sum_k b_k dT^k

with B_frame = H^T B_body for boom sensors with the boom deployed, B_frame = B_body
otherwise. m is the SET/RESET'd, axis-mapped reading (preprocess(...).field_frame_nT).
The best any calibration can do on raw data is therefore W(T)^-1 (m - b(T) - K i),
evaluated at the REPORTED temperature (what a flight unit sees); tests compare fits
against that.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from generator.errors import InputError


def load_truth(path) -> dict:
    """truth.json -> dict with numpy arrays: {"t_ref_C", "H_boom_to_body", "sensors":
    {name: {"W_poly" (k,3,3), "b_poly_nT" (k,3), "K_nT_per_A" (3,n_coils) or None,
    "chip_offset_poly_sensor_nT" or None}}}."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read truth file: {e}") from None
    except RecursionError:
        raise InputError(path, "truth file: nested too deeply") from None
    try:
        sensors = {}
        for name, s in raw["sensors"].items():
            sensors[name] = {
                "W_poly": np.asarray(s["W_poly_frame"], float),
                "b_poly_nT": np.asarray(s["b_poly_frame_nT"], float),
                "K_nT_per_A": (np.asarray(s["K_coil_frame_nT_per_A"], float)
                               if "K_coil_frame_nT_per_A" in s else None),
                "chip_offset_poly_sensor_nT": (np.asarray(s["chip_offset_poly_sensor_nT"], float)
                                               if "chip_offset_poly_sensor_nT" in s else None),
            }
        return {"t_ref_C": float(raw.get("t_ref_C", 25.0)),
                "H_boom_to_body": (np.asarray(raw["H_boom_to_body"], float)
                                   if "H_boom_to_body" in raw else None),
                "sensors": sensors}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"truth file: missing or malformed entry ({e})") from None


def _as_truth(truth) -> dict:
    return load_truth(truth) if isinstance(truth, (str, Path)) else truth


def _poly(coefs, dT):
    """sum_k coefs[k] dT^k for coefs (K, ...) and dT (N,) -> (N, ...)."""
    d = dT.reshape((-1,) + (1,) * (coefs.ndim - 1))
    return sum(coefs[k] * d ** k for k in range(coefs.shape[0]))


def true_W(truth, sensor_name, temp_C) -> np.ndarray:
    t = _as_truth(truth)
    s = t["sensors"][sensor_name]
    return _poly(s["W_poly"], np.asarray(temp_C, float).reshape(-1) - t["t_ref_C"])


def true_b(truth, sensor_name, temp_C) -> np.ndarray:
    t = _as_truth(truth)
    s = t["sensors"][sensor_name]
    return _poly(s["b_poly_nT"], np.asarray(temp_C, float).reshape(-1) - t["t_ref_C"])


def true_calibrated_frame(truth, sensor_name, field_frame_nT, temp_C, coil_A=None):
    """W(T)^-1 (m - b(T) - K i): the sensor's field in its frame with the TRUE parameters,
    T the reported temperature. field_frame_nT (N, 3); temp_C (N,); coil_A (N, n_coils)
    in the truth's coil order (x, y, z) or None (no current)."""
    t = _as_truth(truth)
    s = t["sensors"][sensor_name]
    m = np.asarray(field_frame_nT, float)
    T = np.broadcast_to(np.asarray(temp_C, float), (m.shape[0],))
    y = m - true_b(t, sensor_name, T)
    if coil_A is not None and s["K_nT_per_A"] is not None:
        i = np.nan_to_num(np.asarray(coil_A, float))
        y = y - i @ s["K_nT_per_A"].T
    return np.linalg.solve(true_W(t, sensor_name, T), y[..., None])[..., 0]


def true_frame_field(truth, frame, b_body_nT, boom_deployed) -> np.ndarray:
    """True field in a sensor's frame: H^T B_body for boom sensors with the boom deployed,
    B_body otherwise (the jig keeps the boom board aligned with the body)."""
    b = np.asarray(b_body_nT, float)
    if frame == "boom" and boom_deployed:
        H = _as_truth(truth)["H_boom_to_body"]
        return b @ H          # rows: (H^T B)^T = B^T H
    return b


def rms_norm_error(B_cal, B_true) -> float:
    """RMS over samples of |B_cal| - |B_true| (nT); rows with non-finite values skipped."""
    a = np.linalg.norm(np.asarray(B_cal, float), axis=-1)
    b = np.linalg.norm(np.asarray(B_true, float), axis=-1)
    e = a - b
    e = e[np.isfinite(e)]
    if e.size == 0:
        raise ValueError("rms_norm_error: no finite samples")
    return float(np.sqrt(np.mean(e ** 2)))


def rms_vector_error(B_cal, B_true) -> float:
    """RMS over samples and axes of B_cal - B_true (nT)."""
    e = np.asarray(B_cal, float) - np.asarray(B_true, float)
    e = e[np.isfinite(e).all(axis=-1)]
    return float(np.sqrt(np.mean(e ** 2)))
