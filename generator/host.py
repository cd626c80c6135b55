"""Compile a unit's generated flight C on the host with cffi and call it.

The flight sources are compiled exactly as the standards require
(-std=c99 -O2 -ffp-contract=off, no fast-math); the template-written wrappers also with
-Wall -Wextra -Werror -pedantic. A host-only batch shim (templates/host_shim.*.j2) loops
over samples so that `magcal apply` and the tests run the flight code itself.

Builds are cached by the hash of their sources, flags and compiler.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .chain import ChainSpec, np_dtype
from .codegen import _env, render, template_context
from .coeffs import CoefficientSet

CC = os.environ.get("CC", "gcc")
FP_FLAGS = ["-std=c99", "-O2", "-ffp-contract=off", "-fno-fast-math"]
STRICT_FLAGS = ["-Wall", "-Wextra", "-Werror", "-pedantic"]
# CasADi's generated file: its boilerplate has unused parameters (iw, w, mem); everything
# else of -Wall -Wextra -pedantic applies.
KERNEL_FLAGS = ["-Wall", "-Wextra", "-Werror", "-pedantic", "-Wno-unused-parameter"]


def cache_dir() -> Path:
    d = Path(os.environ.get("MAGCAL_CACHE", Path(tempfile.gettempdir()) / "magcal-build"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def compiler_id() -> str:
    try:
        return subprocess.run([CC, "--version"], capture_output=True, text=True,
                              check=True).stdout.splitlines()[0]
    except (OSError, subprocess.CalledProcessError) as e:
        raise RuntimeError(f"no C compiler '{CC}' ({e}); install gcc") from None


class HostBuildError(RuntimeError):
    pass


def _compile(src: Path, obj: Path, flags, include: Path):
    cmd = [CC, *FP_FLAGS, *flags, "-fPIC", "-I", str(include), "-c", str(src), "-o", str(obj)]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise HostBuildError(f"compile failed: {' '.join(cmd)}\n{p.stderr}")
    return obj


class HostUnit:
    """The compiled flight C of one unit, callable from Python."""

    def __init__(self, cs: CoefficientSet, sources: dict | None = None, quiet=True):
        self.cs = cs
        self.spec: ChainSpec = cs.spec
        self.dtype = np_dtype(self.spec.unit)
        files = dict(sources) if sources is not None else render(cs)
        ctx = template_context(cs)
        env = _env()
        files["host_shim.c"] = env.get_template("host_shim.c.j2").render(**ctx)
        files["host_shim.h"] = env.get_template("host_shim.h.j2").render(**ctx)
        key = hashlib.sha256()
        for name in sorted(files):
            key.update(name.encode() + b"\0" + files[name].encode() + b"\0")
        key.update(" ".join(FP_FLAGS + STRICT_FLAGS + KERNEL_FLAGS).encode())
        key.update(compiler_id().encode())
        key.update(sys.version.encode())
        self.key = key.hexdigest()[:16]
        self.module_name = f"_magcal_host_{self.key}"
        self.build_dir = cache_dir() / self.module_name
        self._lib, self._ffi = self._load_or_build(files)

    def _load_or_build(self, files):
        mod_path = next(self.build_dir.glob(f"{self.module_name}*.so"), None) \
            if self.build_dir.is_dir() else None
        if mod_path is None:
            self._build(files)
            mod_path = next(self.build_dir.glob(f"{self.module_name}*.so"))
        spec = importlib.util.spec_from_file_location(self.module_name, mod_path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod.lib, mod.ffi

    def _build(self, files):
        import cffi

        tmp = Path(tempfile.mkdtemp(prefix=self.module_name + "-", dir=cache_dir()))
        src = tmp / "src"
        src.mkdir()
        for name, text in files.items():
            (src / name).write_text(text)
        unit = self.spec.unit.id
        objs = []
        for name in sorted(files):
            if not name.endswith(".c"):
                continue
            flags = KERNEL_FLAGS if name == f"{unit}_kernels.c" else STRICT_FLAGS
            objs.append(str(_compile(src / name, tmp / (name[:-2] + ".o"), flags, src)))
        ffi = cffi.FFI()
        ffi.cdef(files["host_shim.h"])
        ffi.set_source(self.module_name, '#include <stdint.h>\n#include "host_shim.h"\n',
                       include_dirs=[str(src)], extra_objects=objs,
                       extra_compile_args=["-std=c99", "-O2", "-ffp-contract=off"])
        ffi.compile(tmpdir=str(tmp), verbose=False)
        built = next(tmp.glob(f"{self.module_name}*.so"))
        final = tmp.parent / self.module_name
        if final.exists():  # another process won the race; use theirs
            shutil.rmtree(tmp, ignore_errors=True)
            return
        (tmp / "final").mkdir()
        shutil.move(str(built), tmp / "final" / built.name)
        try:
            os.rename(tmp / "final", final)
        except OSError:
            pass
        shutil.rmtree(tmp, ignore_errors=True)

    # ---- calls -------------------------------------------------------------------------
    def flat_coeffs(self, cs: CoefficientSet | None = None) -> np.ndarray:
        cs = cs or self.cs
        parts = [cs.flat_sensor(s.name) for s in self.spec.unit.sensors] + [cs.flat_unit()]
        return np.concatenate(parts).astype(self.dtype)

    def default_coeffs(self) -> np.ndarray:
        n = sum(self.spec.n_sensor_coeffs(s) for s in self.spec.unit.sensors) \
            + self.spec.n_unit_coeffs()
        out = np.zeros(n, dtype=self.dtype)
        self._lib.host_default_coeffs(self._ffi.cast(f"{self._ctype} *", out.ctypes.data))
        return out

    @property
    def _ctype(self):
        return "float" if self.dtype == np.float32 else "double"

    def correct(self, sensor: str, raw_counts, temp_C, coil_A=None, coeffs_flat=None) -> dict:
        """Run `<unit>_<sensor>_correct` over samples; same outputs as chain.reference_sensor."""
        s = self.spec.unit.sensor(sensor)
        ffi, ct = self._ffi, self._ctype
        raw = np.ascontiguousarray(raw_counts, dtype=np.int32)
        n = raw.shape[0]
        assert raw.shape == (n, 6 if s.set_reset else 3), raw.shape
        temp = np.ascontiguousarray(np.asarray(temp_C, dtype=np.float64).astype(self.dtype))
        co = np.ascontiguousarray(self.flat_coeffs() if coeffs_flat is None else
                                  np.asarray(coeffs_flat, dtype=self.dtype))
        field = np.zeros((n, 3), dtype=self.dtype)
        offset = np.zeros((n, 3), dtype=self.dtype)
        status = np.zeros(n, dtype=np.uint16)
        coil_ptr = ffi.NULL
        if self.spec.coils and coil_A is not None:
            coil = np.ascontiguousarray(np.asarray(coil_A, dtype=np.float64).astype(self.dtype))
            assert coil.shape == (n, len(self.spec.coils))
            coil_ptr = ffi.cast(f"{ct} *", coil.ctypes.data)
        getattr(self._lib, f"host_{sensor}_batch")(
            ffi.cast(f"{ct} *", co.ctypes.data), n, ffi.cast("int32_t *", raw.ctypes.data),
            ffi.cast(f"{ct} *", temp.ctypes.data), coil_ptr,
            ffi.cast(f"{ct} *", field.ctypes.data), ffi.cast(f"{ct} *", offset.ctypes.data),
            ffi.cast("uint16_t *", status.ctypes.data))
        out = {"field_body_nT": field, "status": status}
        if s.set_reset:
            out["chip_offset_nT"] = offset
        return out
