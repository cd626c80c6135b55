"""magcal: magnetometer calibration toolchain for SamSat-ION-class satellites.

Python fits the calibration, CasADi and Jinja2 emit fixed-size flight C, cffi
compiles that C on the host so tests check bit-level agreement with the Python
reference (see README.md for a tour).
"""

import os

# The fits solve many small problems; a multi-threaded BLAS only adds overhead to them on
# a 2-core machine (seen: the per-level analytic fit 25 ms single-threaded, 0.3-0.7 s
# threaded). Set before numpy loads; a caller's own setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
