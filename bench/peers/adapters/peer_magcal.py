"""Adapter: `magcal` from PyPI (MagnetometerCalibrator; unrelated to this project).

Its API (magcal/core.py, 1.0.1): readings go into `raw_data` (normally collected over a
serial port), `calibrate(method="ellipsoid")` needs >= 500 samples and returns
calibration_params with 'center' and 'transform_matrix'; it applies
transform_matrix @ (reading - center). Its ellipsoid fit takes the CENTRE AS THE MEAN of
the readings and fits only the quadratic form about it (unit radius). calibrate() prints a
quality summary, which is discarded here.
"""

import contextlib
import io

from _protocol import run


def fit(x):
    from magcal import MagnetometerCalibrator
    cal = MagnetometerCalibrator()
    cal.raw_data = x.tolist()
    with contextlib.redirect_stdout(io.StringIO()):
        params = cal.calibrate(method="ellipsoid")
    return params["center"], params["transform_matrix"]


if __name__ == "__main__":
    raise SystemExit(run("magcal", "magcal", fit))
