"""The first-order recursion's plain loop at C speed, for the trace's lag filters.

    y[0] = y0,  y[k] = y[k-1] + a[k-1] (x[k] - y[k-1])      (k = 1 .. n-1)

is the loop trace.effects.first_order runs where the memory is short (many chunks of
its vectorised form). In Python it costs ~0.3 us a row, and the thermal-lag scan runs it
over every row of every file for each time constant at each refit (issue 20, review 20e
F5: 10^6 rows, 571 s a round). Here the same loop is compiled through the project's cffi
host build (generator.flight.host.cffi_module: -std=c99 -O2 -ffp-contract=off, no
fast-math, cached by a hash of the source), so every step is the same two IEEE-754 double
operations in the same order (a subtraction, a product, a sum; no fused multiply-add):
the results are the Python loop's bit for bit (host_tests/test_trace_recursion.py holds
them to it).

Where no compiler or no build cache is at hand the Python loop runs instead (same
numbers, only slower); `compiled()` says which one is used.
"""

from __future__ import annotations

import numpy as np

_C = r"""
#include "first_order.h"

void magcal_first_order(const double *a, const double *x, double y0, double *out, long n)
{
    double y = y0;
    long k;
    if (n <= 0) {
        return;
    }
    out[0] = y0;
    for (k = 1; k < n; ++k) {
        y = y + a[k - 1] * (x[k] - y);
        out[k] = y;
    }
}
"""

_H = ("#ifndef MAGCAL_FIRST_ORDER_H\n#define MAGCAL_FIRST_ORDER_H\n"
      "void magcal_first_order(const double *a, const double *x, double y0, double *out,"
      " long n);\n#endif\n")

_CDEF = "void magcal_first_order(const double *a, const double *x, double y0, double *out, long n);\n"

_lib = None          # (lib, ffi) once built, False when it cannot be built


def _load():
    global _lib
    if _lib is None:
        from generator.errors import InputError
        from generator.flight import host
        try:
            _lib = host.cffi_module("_magcal_first_order",
                                    {"first_order.c": _C, "first_order.h": _H,
                                     "first_order.cdef": _CDEF},
                                    "first_order.cdef", '#include "first_order.h"')
        except (host.HostBuildError, RuntimeError, InputError, OSError):
            _lib = False           # no compiler / no private cache: the Python loop
    return _lib


def compiled() -> bool:
    """The compiled loop is used (else the Python loop, same numbers)."""
    return bool(_load())


def python_loop(a, x, y0, out) -> None:
    """The loop in Python floats (the reference, and the fallback)."""
    y = float(y0)
    al, xl = np.asarray(a, float).tolist(), np.asarray(x, float).tolist()
    out[0] = y
    for k in range(1, len(xl)):
        y = y + al[k - 1] * (xl[k] - y)
        out[k] = y


def first_order_loop(a, x, y0, out) -> None:
    """out[:] = the recursion over a (n-1 factors) and x (n inputs) from y0, n = len(x),
    in the loop's own order (above); out is a float64 array of n."""
    n = len(x)
    if n == 0:
        return
    lib = _load()
    if not lib:
        python_loop(a, x, y0, out)
        return
    lib, ffi = lib
    a = np.ascontiguousarray(a, dtype=np.float64)
    x = np.ascontiguousarray(x, dtype=np.float64)
    if len(a) < n - 1:
        raise ValueError(f"first_order_loop: {len(a)} factors for {n} inputs")
    assert out.dtype == np.float64 and out.flags.c_contiguous and len(out) >= n
    lib.magcal_first_order(ffi.cast("const double *", a.ctypes.data),
                           ffi.cast("const double *", x.ctypes.data), float(y0),
                           ffi.cast("double *", out.ctypes.data), n)
