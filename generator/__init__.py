"""magcal: magnetometer calibration toolchain for SamSat-ION-class satellites.

Python fits the calibration, CasADi and Jinja2 emit fixed-size flight C, cffi
compiles that C on the host so tests check bit-level agreement with the Python
reference (see README.md for a tour).
"""

__version__ = "0.1.0"
