"""Adapter: `circuitpython-mag-cal` from PyPI, its `Sensor` ellipsoid fit.

API (mag_cal/sensor.py, 1.4.1): Sensor(axes="+X+Y+Z").fit_ellipsoid(data (N, 3)) solves
the 9-term quadric = 1 by least squares, sets `centre` and the symmetric `transform`,
and `apply` computes (reading - centre) @ transform (row vectors), unit radius. As a
column-vector matrix that is transform^T.
"""

from _protocol import run


def fit(x):
    from mag_cal import Sensor
    sensor = Sensor("+X+Y+Z")
    sensor.fit_ellipsoid(x.copy())
    return sensor.centre, sensor.transform.T


if __name__ == "__main__":
    raise SystemExit(run("circuitpython-mag-cal", "circuitpython-mag-cal", fit))
