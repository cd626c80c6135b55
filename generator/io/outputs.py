"""Outputs written whole or not at all.

A file is written to a temporary file in its own folder, flushed to disk (fsync) and
renamed over the target (os.replace: atomic on POSIX). A folder of outputs is built in a
temporary folder beside the target; on success it is renamed to the target, or (when the
target folder exists) its files are renamed into it one by one; on any error the
temporary folder is removed. An output path that names an existing folder where a file is
needed, an existing file where a folder is needed, or lies under a file, is bad input
(InputError, exit 2) found before anything is computed or written.

The system refusing the writing itself (a full disk, a quota, a read-only or failing
filesystem: an OSError while writing, flushing or renaming) is OutputError: one line naming
the output and the system's reason, exit status 1, after the temporary file or folder has
been removed.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from generator.errors import InputError, OutputError

# the system's reasons for refusing to store what is written, whoever writes it: these are
# about the output's storage, not the command's input (a read of an input that fails is the
# readers' InputError before it gets here)
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


def _reason(e: OSError) -> str:
    """The system's reason of e, in words, with its errno name (e.g. 'No space left on
    device (ENOSPC)')."""
    name = errno.errorcode.get(e.errno) if e.errno is not None else None
    text = e.strerror or str(e) or type(e).__name__
    return f"{text} ({name})" if name else text


def _is_output_fault(e: OSError, tmp) -> bool:
    """Does an OSError raised while an output was being written concern that output: a
    storage errno, or a file name under its temporary file or folder?"""
    if e.errno in STORAGE_ERRNOS:
        return True
    for name in (e.filename, e.filename2):
        if name is not None and str(name).startswith(str(tmp)):
            return True
    return False


def _cannot_create(path, e: OSError, what: str):
    """The error for a temporary file or folder that could not be made beside `path`: the
    storage refusing (OutputError, exit 1), or a place that cannot hold an output (a
    folder without write permission: InputError, exit 2)."""
    if e.errno in STORAGE_ERRNOS:
        return OutputError(path, _reason(e))
    return InputError(path, f"{what}: {e.strerror or e}")


def _first_file_above(path: Path):
    """The first existing ancestor of path that is not a folder, or None."""
    for parent in list(path.parents)[::-1]:
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def check_output_file(path) -> Path:
    """Path of an output file, or InputError when it cannot be one."""
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise InputError(path, "output file: not a file name")
    blocker = _first_file_above(p)
    if blocker is not None:
        raise InputError(path, f"output file: '{blocker}' is a file, not a folder")
    if p.is_dir():
        raise InputError(path, "output file: is an existing folder")
    if p.is_symlink() and not p.exists():
        raise InputError(path, "output file: a symbolic link to nothing: refused")
    if p.exists() and not p.is_file():
        # a device, a pipe, a socket: renaming over it would replace it (/dev/null!)
        raise InputError(path, "output file: exists and is not a regular file: refused")
    return p


def refuse_inputs(output, inputs) -> None:
    """InputError when the output would overwrite one of the command's own inputs."""
    out = Path(output)
    if not out.exists():
        return
    for i in inputs:
        if i is not None and Path(i).exists() and os.path.samefile(out, i):
            raise InputError(output, f"output file: is the input {i}: refused (it would be "
                                     "overwritten)")


def check_output_folder(path) -> Path:
    """Path of an output folder, or InputError when it cannot be one."""
    p = Path(path)
    if str(path) == "":
        raise InputError(path, "output folder: empty name")
    blocker = _first_file_above(p)
    if blocker is not None:
        raise InputError(path, f"output folder: '{blocker}' is a file, not a folder")
    if p.is_symlink() and not p.exists():
        raise InputError(path, "output folder: a symbolic link to nothing: refused")
    if p.exists() and not p.is_dir():
        raise InputError(path, "output folder: is an existing file")
    return p


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _makedirs(folder: Path) -> list:
    """mkdir -p; returns the folders it created (outermost first) so they can be removed."""
    made = []
    for parent in [*list(folder.parents)[::-1], folder]:
        if not parent.exists():
            try:
                parent.mkdir()
            except FileExistsError:
                continue
            except OSError as e:
                raise _cannot_create(parent, e, "cannot create the output folder") from None
            made.append(parent)
    return made


def _remove_made(made) -> None:
    for d in reversed(made):
        try:
            d.rmdir()
        except OSError:
            pass


@contextlib.contextmanager
def atomic_file(path, mode: str = "w", **open_kw):
    """Open a temporary file beside `path`; on normal exit it becomes `path` (fsync +
    os.replace), on an exception it is removed and `path` is untouched. An OSError of
    the writing (the caller's writes into the file: a storage errno; the flush, fsync and
    rename here: any) is OutputError naming `path`."""
    p = check_output_file(path)
    made = _makedirs(p.parent) if str(p.parent) not in ("", ".") else []
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as e:
        _remove_made(made)
        raise _cannot_create(path, e, "cannot write") from None
    try:
        if "encoding" not in open_kw and "b" not in mode:
            open_kw["encoding"] = "utf-8"
        written = False              # the caller's part done: any OSError after is ours
        try:
            with os.fdopen(fd, mode, **open_kw) as f:
                yield f
                written = True
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, p)
        except OSError as e:
            if written or _is_output_fault(e, tmp):
                raise OutputError(path, _reason(e)) from e
            raise
        _fsync_dir(p.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        _remove_made(made)
        raise


def write_bytes(path, data: bytes) -> Path:
    with atomic_file(path, "wb") as f:
        f.write(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    with atomic_file(path, "w", newline="") as f:
        f.write(text)
    return Path(path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class OutputFolder:
    """A folder being built: `.tmp` is where to write; `final(p)` maps a path under
    `.tmp` to where it will be once committed."""

    def __init__(self, target: Path, tmp: Path):
        self.target, self.tmp = target, tmp
        # after the commit: the files the target folder already held that this run did
        # not write (outputs of an earlier run, e.g. a figure this report no longer has);
        # kept, never deleted, and named by stale_note
        self.earlier: list = []

    def stale_note(self) -> str:
        """'' or one line naming the files of an earlier run the folder still holds."""
        if not self.earlier:
            return ""
        names = [str(p.relative_to(self.target)) for p in self.earlier]
        shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        return (f"note: {self.target} also holds {len(names)} file(s) this run did not write "
                f"(from an earlier run, kept): {shown}")

    def final(self, p) -> Path:
        p = Path(p)
        try:
            return self.target / p.relative_to(self.tmp)
        except ValueError:
            return p


@contextlib.contextmanager
def output_folder(path):
    """Build a folder of outputs in a temporary folder beside `path` (yields an
    OutputFolder); commit it on normal exit, remove it on an exception. An OSError of the
    writing (the caller's writes under the folder: a storage errno or a file name under
    it; the commit here: any) is OutputError naming `path`."""
    target = check_output_folder(path)
    parent = target.parent
    made = _makedirs(parent) if str(parent) not in ("", ".") else []
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent))
    except OSError as e:
        _remove_made(made)
        raise _cannot_create(path, e, "cannot create the output folder") from None
    try:
        folder = OutputFolder(target, tmp)
        built = False                # the caller's part done: any OSError after is ours
        try:
            yield folder
            built = True
            folder.earlier = _commit(tmp, target)
        except OSError as e:
            if built or _is_output_fault(e, tmp):
                raise OutputError(path, _reason(e)) from e
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_made(made)
        raise


def _commit(tmp: Path, target: Path) -> list:
    """Move the built folder into place; the target's files this run did not write."""
    os.chmod(tmp, 0o777 & ~_umask())
    for f in tmp.rglob("*"):
        if f.is_file():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
    if not target.exists():
        try:
            os.rename(tmp, target)
            _fsync_dir(target.parent)
            return []
        except OSError:
            pass           # created meanwhile: merge below
    written = {f.relative_to(tmp) for f in tmp.rglob("*") if f.is_file()}
    _merge(tmp, target)
    shutil.rmtree(tmp, ignore_errors=True)
    return sorted(f for f in target.rglob("*")
                  if f.is_file() and f.relative_to(target) not in written
                  and not f.name.startswith("."))


def _merge(src: Path, dst: Path) -> None:
    """Rename every file of src into dst (folders merged); an existing file is replaced,
    a folder where a file goes (or the reverse) is an error found before any rename."""
    moves = []
    for f in sorted(src.rglob("*")):
        rel = f.relative_to(src)
        d = dst / rel
        if f.is_dir():
            if d.exists() and not d.is_dir():
                raise InputError(d, "output: is an existing file where a folder goes")
        else:
            if d.is_dir():
                raise InputError(d, "output: is an existing folder where a file goes")
            moves.append((f, d))
    for f, d in moves:
        d.parent.mkdir(parents=True, exist_ok=True)
        os.replace(f, d)
    _fsync_dir(dst)


# ---- CSV cells, vectorised -------------------------------------------------------------
# Output CSVs write every float as Python's repr(float(v)) would: the shortest text that
# reads back as the same float64 (a float32 value widened to float64 exactly, so it reads
# back as the same float32), in fixed notation for 1e-4 <= |v| < 1e16 and 0, else
# scientific ("1e-05"). pyarrow's C formatter finds the same shortest digits (both are
# shortest round-trip with the nearest-value tie-break); where its layout differs from
# repr's ("1" for 1.0, "1e+15", "0.00001") the cell is fixed or written by repr itself.
# host_tests/test_stream_io.py compares the two on a million values of every magnitude.


def float_cells(values, present=None):
    """pyarrow string array: repr(float(v)) of each value, null (an empty cell) where the
    value is NaN or infinite or present is False."""
    import pyarrow as pa
    import pyarrow.compute as pc

    from generator.io.arrow_np import bool_array, float64_array, string_array

    with np.errstate(invalid="ignore"):             # a signalling NaN stays a NaN
        x = np.asarray(values, dtype=np.float64)    # float32 widened exactly
    ok = np.isfinite(x)
    if present is not None:
        ok &= np.asarray(present, dtype=bool)
    numbers = float64_array(x, ok)                # offset 0, validity: ok
    s = pc.cast(numbers, "string")
    n = len(s)
    if n == 0 or not ok.any():
        return s
    # per cell, from the text buffer: does it hold a '.' or an 'e'?
    offsets = np.frombuffer(s.buffers()[1], dtype=np.int32)[s.offset:s.offset + n + 1]
    data = np.frombuffer(s.buffers()[2], dtype=np.uint8)[:offsets[-1]]
    lens = np.diff(offsets)
    starts = np.minimum(offsets[:-1], max(data.shape[0] - 1, 0))
    filled = lens > 0                    # only null cells are empty (their flags unused)
    has_dot = np.logical_or.reduceat(data == ord("."), starts) & filled
    has_e = np.logical_or.reduceat(data == ord("e"), starts) & filled
    ax = np.abs(x)
    with np.errstate(invalid="ignore"):
        fixed = (ax == 0) | ((ax >= 1e-4) & (ax < 1e16))     # repr's fixed notation
    slow = ok & (has_e | ~fixed)
    need_dot = ok & ~slow & ~has_dot                          # "1" -> "1.0"
    n_dot = int(need_dot.sum())
    if 0 < n_dot <= n // 16:           # a few whole numbers among fractions: cell by cell
        at = np.flatnonzero(need_dot)
        s = pc.replace_with_mask(s, bool_array(need_dot), string_array(
            [data[offsets[i]:offsets[i + 1]].tobytes().decode() + ".0" for i in at.tolist()]))
    elif n_dot:                        # many (time stamps, counts): shift the text buffer
        new_offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(lens + 2 * need_dot, out=new_offsets[1:])
        shift = np.repeat(new_offsets[:-1] - offsets[:-1], lens)
        out = np.empty(int(new_offsets[-1]), dtype=np.uint8)
        out[np.arange(offsets[0], offsets[-1]) - offsets[0] + shift] = data[offsets[0]:]
        ends = new_offsets[1:][need_dot]
        out[ends - 2] = ord(".")
        out[ends - 1] = ord("0")
        s = pa.Array.from_buffers(pa.string(), n, [
            numbers.buffers()[0], pa.py_buffer(new_offsets.astype(np.int32)),
            pa.py_buffer(out)])
    if slow.any():
        s = pc.replace_with_mask(s, bool_array(slow),
                                 string_array([repr(v) for v in x[slow].tolist()]))
    return s


def int_cells(values):
    """pyarrow string array: str(int(v)) of each integer value."""
    import pyarrow.compute as pc

    from generator.io.arrow_np import int64_array

    return pc.cast(int64_array(values), "string")


def csv_lines(columns) -> memoryview:
    """The rows of equal-length pyarrow string arrays as CSV text (UTF-8 bytes), each row
    ended by a newline; a null is an empty cell. Cells are written as they are: the
    callers' cells never hold a comma, quote or newline (numbers and identifiers)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    from generator.io.arrow_np import repeated_string

    n = len(columns[0])
    if n == 0:
        return memoryview(b"")
    rows = pc.binary_join_element_wise(*columns, repeated_string(",", n),
                                       null_handling="replace", null_replacement="")
    rows = pc.binary_join_element_wise(rows, repeated_string("", n),
                                       repeated_string("\n", n))      # "row" -> "row\n"
    if isinstance(rows, pa.ChunkedArray):
        rows = rows.combine_chunks()
    offsets = np.frombuffer(rows.buffers()[1], dtype=np.int32)
    start, end = int(offsets[rows.offset]), int(offsets[rows.offset + len(rows)])
    return memoryview(rows.buffers()[2])[start:end]
