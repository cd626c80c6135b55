"""numpy <-> pyarrow arrays through their buffers.

pyarrow imports pandas (about 0.5 s and 50 MB) the first time it converts a Python or
numpy object (pa.array, pa.scalar, Array.to_numpy). The readers and writers of long
telemetry never need pandas, so they build arrays from buffers and read them back the
same way: start-up costs only the imports magcal needs.
"""

from __future__ import annotations

import numpy as np


def _pa():
    import pyarrow as pa

    return pa


def _validity(valid, n):
    """Arrow's validity bitmap (LSB first) of a boolean mask, or None when all valid."""
    if valid is None:
        return None
    valid = np.asarray(valid, dtype=bool)
    if valid.all():
        return None
    return _pa().py_buffer(np.packbits(valid, bitorder="little"))


def float64_array(x, valid=None):
    """pa.Array of float64 from a numpy array (null where valid is False)."""
    pa = _pa()
    x = np.ascontiguousarray(x, dtype=np.float64)
    return pa.Array.from_buffers(pa.float64(), x.shape[0],
                                 [_validity(valid, x.shape[0]), pa.py_buffer(x)])


def int64_array(x, valid=None):
    pa = _pa()
    x = np.ascontiguousarray(x, dtype=np.int64)
    return pa.Array.from_buffers(pa.int64(), x.shape[0],
                                 [_validity(valid, x.shape[0]), pa.py_buffer(x)])


def bool_array(mask):
    pa = _pa()
    mask = np.asarray(mask, dtype=bool)
    return pa.Array.from_buffers(pa.bool_(), mask.shape[0],
                                 [None, pa.py_buffer(np.packbits(mask, bitorder="little"))])


def string_array(items):
    """pa.Array of strings from a list of str (None: null)."""
    pa = _pa()
    enc = [b"" if s is None else s.encode("utf-8") for s in items]
    offsets = np.zeros(len(enc) + 1, dtype=np.int32)
    np.cumsum([len(b) for b in enc], out=offsets[1:])
    valid = None if all(s is not None for s in items) else [s is not None for s in items]
    return pa.Array.from_buffers(pa.string(), len(enc),
                                 [_validity(valid, len(enc)), pa.py_buffer(offsets),
                                  pa.py_buffer(b"".join(enc))])


def repeated_string(text: str, n: int):
    """pa.Array of n copies of text (a constant column for element-wise kernels)."""
    pa = _pa()
    b = text.encode("utf-8")
    offsets = np.arange(n + 1, dtype=np.int32) * len(b)
    return pa.Array.from_buffers(pa.string(), n, [None, pa.py_buffer(offsets),
                                                  pa.py_buffer(b * n)])


def _bits(buf, offset, n):
    return np.unpackbits(np.frombuffer(buf, dtype=np.uint8), bitorder="little")[
        offset:offset + n].astype(bool)


def _chunks(arr):
    return arr.chunks if hasattr(arr, "chunks") else [arr]


def to_float64(arr, copy=True) -> np.ndarray:
    """numpy float64 of a pyarrow numeric Array or ChunkedArray; null -> NaN. copy=False:
    maybe a read-only view of the arrow buffer."""
    pa = _pa()
    import pyarrow.compute as pc

    parts = []
    for c in _chunks(arr):
        if c.type != pa.float64():
            c = pc.cast(c, pa.float64())
        v = np.frombuffer(c.buffers()[1], dtype=np.float64)[c.offset:c.offset + len(c)]
        if c.null_count:
            v = np.where(_bits(c.buffers()[0], c.offset, len(c)), v, np.nan)
        parts.append(v)
    if not parts:
        return np.empty(0)
    if len(parts) == 1:
        return parts[0].copy() if copy else parts[0]
    return np.concatenate(parts)


def integers(arr) -> np.ndarray:
    """numpy integers (the arrow type's width and sign) of a pyarrow integer Array: a
    read-only view of its buffer; the values under nulls are undefined (see nulls)."""
    pa = _pa()
    t = arr.type
    kind = "i" if pa.types.is_signed_integer(t) else "u"
    dtype = np.dtype(f"{kind}{t.bit_width // 8}")
    return np.frombuffer(arr.buffers()[1], dtype=dtype)[arr.offset:arr.offset + len(arr)]


def nulls(arr) -> np.ndarray:
    """numpy bool: True where the Array or ChunkedArray holds a null."""
    parts = []
    for c in _chunks(arr):
        if c.null_count and c.buffers()[0] is not None:
            parts.append(~_bits(c.buffers()[0], c.offset, len(c)))
        else:
            parts.append(np.zeros(len(c), dtype=bool))
    return np.concatenate(parts) if parts else np.zeros(0, dtype=bool)


def to_bool(arr) -> np.ndarray:
    """numpy bool of a pyarrow boolean Array or ChunkedArray; null -> False."""
    parts = []
    for c in _chunks(arr):
        v = _bits(c.buffers()[1], c.offset, len(c))
        if c.null_count:
            v &= _bits(c.buffers()[0], c.offset, len(c))
        parts.append(v)
    return np.concatenate(parts) if parts else np.zeros(0, dtype=bool)
