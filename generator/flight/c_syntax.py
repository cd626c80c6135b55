"""What the generator itself writes into C: numeric literals it formats from numbers.

No text that came from a user's file reaches the generated C except through this module
(literals) or as a validated identifier (generator.io.names).
"""

from __future__ import annotations

import math

import numpy as np


def c_literal(value: float, float_type: str) -> str:
    """Shortest literal that round-trips to the exact value in the flight float type.

    A value that is not finite in that type (NaN, inf, or a float64 beyond float32's
    range) has no C literal: ValueError.
    """
    if float_type == "float32":
        with np.errstate(over="ignore"):
            v32 = np.float32(value)
        if not np.isfinite(v32):
            raise ValueError(f"{value!r} is not a finite float32")
        text = str(v32)
        suffix = "f"
    else:
        if not math.isfinite(float(value)):
            raise ValueError(f"{value!r} is not a finite float64")
        text = repr(float(value))
        suffix = ""
    if "." not in text and "e" not in text:
        text += ".0"
    return text + suffix
