"""Compile a unit's generated flight C on the host with cffi and call it.

The flight sources are compiled exactly as the standards require
(-std=c99 -O2 -ffp-contract=off, no fast-math); the template-written wrappers also with
-Wall -Wextra -Werror -pedantic. A host-only batch shim (templates/host_shim.*.j2) loops
over samples so that `magcal apply` and the tests run the flight code itself.

Builds are cached in a private per-user folder (cache_dir) by a hash of their inputs
(input_key: coefficients, package and template sources, tool versions, flags, compiler),
so a cached build starts without rendering the C; a cached module is loaded only when its
sha256 matches the sidecar written after its build.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from generator.flight.chain import ChainSpec, is_physical, np_dtype
from generator.flight.codegen import _env, render, template_context
from generator.flight.coeffs import CoefficientSet, json_default
from generator.errors import InputError

CC = os.environ.get("CC", "gcc")
FP_FLAGS = ["-std=c99", "-O2", "-ffp-contract=off", "-fno-fast-math"]
STRICT_FLAGS = ["-Wall", "-Wextra", "-Werror", "-pedantic"]


def cache_dir() -> Path:
    """The per-user build cache: $MAGCAL_CACHE, else $XDG_CACHE_HOME/magcal or
    ~/.cache/magcal, else <tempdir>/magcal-<uid>; created with mode 0700.

    Compiled modules are loaded (run) from here, so a folder that another user owns or
    can write to is refused (InputError naming it), never used."""
    env = os.environ.get("MAGCAL_CACHE")
    if env:
        candidates = [Path(env).absolute()]   # the build runs in other folders
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
        candidates = [base / "magcal",
                      Path(tempfile.gettempdir()) / f"magcal-{os.getuid()}"]
    last = None
    for d in candidates:
        try:
            d.parent.mkdir(parents=True, exist_ok=True)
            d.mkdir(mode=0o700, exist_ok=True)
        except OSError as e:
            last = e
            continue
        _check_private(d)
        return d
    raise InputError(candidates[-1], f"build cache: cannot create: {last}")


def _check_private(path: Path) -> None:
    """InputError unless path is a real folder (no symlink) owned by this user and not
    writable by group or others."""
    try:
        st = os.lstat(path)
    except OSError as e:
        raise InputError(path, f"build cache: {e.strerror or e}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise InputError(path, "build cache: not a folder (a symlink or a file): refused")
    if st.st_uid != os.getuid():
        raise InputError(path, f"build cache: owned by uid {st.st_uid}, not by this user "
                               f"(uid {os.getuid()}): refused (set MAGCAL_CACHE to a private "
                               "folder)")
    if st.st_mode & 0o022:
        raise InputError(path, f"build cache: writable by group or others (mode "
                               f"{stat.S_IMODE(st.st_mode):03o}): refused (chmod 700, or set "
                               "MAGCAL_CACHE to a private folder)")


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _verified_module(build_dir: Path, module_name: str):
    """The module file of a cached build when its sha256 matches the sidecar written
    after the build (and folder and file are private), else None."""
    if not build_dir.is_dir():
        return None
    mods = sorted(build_dir.glob(f"{module_name}*.so"))
    if len(mods) != 1:
        return None
    mod = mods[0]
    side = mod.with_name(mod.name + ".sha256")
    try:
        _check_private(build_dir)
        st = os.lstat(mod)
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
            return None
        want = side.read_text().strip()
    except (OSError, InputError):
        return None
    return mod if want == _sha256_file(mod) else None


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


def cffi_module(prefix: str, files, cdef_file: str, source: str, input_key: str | None = None):
    """(lib, ffi) of a cffi module built from `files` (name -> text): every .c file compiled
    with FP_FLAGS + STRICT_FLAGS, the module's own C is `source`, its declarations are
    files[cdef_file]. Cached under cache_dir() by the hash of sources, flags, compiler and
    Python; concurrent builders race safely (the first rename wins).

    input_key: the caller's hash of everything the sources are made from (input_key());
    then the cache is keyed by it, and `files` may be a callable that renders the sources,
    called only when there is no verified build to load."""
    if input_key is None:
        key = hashlib.sha256()
        for name in sorted(files):
            key.update(name.encode() + b"\0" + files[name].encode() + b"\0")
        key.update(cdef_file.encode() + b"\0" + source.encode() + b"\0")
        key.update(" ".join(FP_FLAGS + STRICT_FLAGS).encode())
        key.update(compiler_id().encode())
        key.update(sys.version.encode())
        input_key = key.hexdigest()
    module_name = f"{prefix}_{input_key[:16]}"
    build_dir = cache_dir() / module_name
    mod_path = _verified_module(build_dir, module_name)
    if mod_path is None:
        if build_dir.exists() or build_dir.is_symlink():
            # a build without a matching sidecar (interrupted, or tampered with): set aside
            stale = build_dir.with_name(f"{module_name}.stale-{os.getpid()}")
            try:
                os.rename(build_dir, stale)
                shutil.rmtree(stale, ignore_errors=True)
            except OSError:
                pass
        _build_cffi(module_name, files() if callable(files) else files, cdef_file, source)
        mod_path = _verified_module(build_dir, module_name)
        if mod_path is None:
            raise HostBuildError(f"the build of {module_name} in {build_dir} does not match "
                                 "its recorded sha256 after building: refusing to load it")
    spec = importlib.util.spec_from_file_location(module_name, mod_path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.lib, mod.ffi


def _build_cffi(module_name, files, cdef_file, source):
    import cffi

    tmp = Path(tempfile.mkdtemp(prefix=module_name + "-", dir=cache_dir()))
    try:
        src = tmp / "src"
        src.mkdir()
        for name, text in files.items():
            (src / name).write_text(text)
        objs = [str(_compile(src / n, tmp / (n[:-2] + ".o"), STRICT_FLAGS, src))
                for n in sorted(files) if n.endswith(".c")]
        ffi = cffi.FFI()
        ffi.cdef(files[cdef_file])
        ffi.set_source(module_name, source, include_dirs=[str(src)], extra_objects=objs,
                       extra_compile_args=["-std=c99", "-O2", "-ffp-contract=off"])
        ffi.compile(tmpdir=str(tmp), verbose=False)
        built = next(tmp.glob(f"{module_name}*.so"))
        final = tmp.parent / module_name
        if not final.exists():
            (tmp / "final").mkdir(mode=0o700)
            shutil.move(str(built), tmp / "final" / built.name)
            # the sidecar: what a later load verifies before running the module
            (tmp / "final" / (built.name + ".sha256")).write_text(
                _sha256_file(tmp / "final" / built.name) + "\n")
            try:
                os.rename(tmp / "final", final)
            except OSError:
                pass          # another process won the race; use theirs
    finally:           # on every path: no half-built folder is left in the cache
        shutil.rmtree(tmp, ignore_errors=True)


# what the host build's sources are made from, besides the coefficients: the package's own
# code (chain, codegen, literals, unit model: any of it can change the C) and the templates
_SOURCE_SUFFIXES = (".py", ".toml", ".j2", ".c", ".h", ".inc")


def input_key(cs: CoefficientSet, roots=None) -> str:
    """sha256 (hex) of everything the host build of `cs` is made from, without rendering
    it: the coefficient set as coefficients.json would hold it, every source file of the
    generator package and of the templates (`roots`, default both), the versions of
    magcal, CasADi, Jinja2, cffi and numpy, the compiler flags and compiler, and Python.
    Any change to an input changes the key, so a stale build is never loaded."""
    import cffi
    import casadi
    import jinja2

    import generator
    from generator.flight.codegen import TEMPLATE_DIR

    h = hashlib.sha256(b"magcal host build inputs v1\0")
    h.update(json.dumps(cs.to_json_dict(), sort_keys=True, default=json_default).encode())
    if roots is None:
        roots = (Path(generator.__file__).resolve().parent, TEMPLATE_DIR)
    for k, root in enumerate(roots):
        root = Path(root)
        for p in sorted(root.rglob("*")):
            if p.suffix in _SOURCE_SUFFIXES and "__pycache__" not in p.parts and p.is_file():
                h.update(f"\0{k}:{p.relative_to(root).as_posix()}\0".encode())
                h.update(p.read_bytes())
    for part in (generator.__version__, casadi.__version__, jinja2.__version__,
                 cffi.__version__, np.__version__, " ".join(FP_FLAGS + STRICT_FLAGS), CC,
                 compiler_id(), sys.version):
        h.update(b"\0" + str(part).encode())
    return h.hexdigest()


class HostUnit:
    """The compiled flight C of one unit, callable from Python.

    The build is cached by input_key(cs) (hashes of the inputs, not the rendered C): a
    cached, sha256-verified build is loaded without rendering anything; the C is rendered
    (CasADi + Jinja2) and compiled only when there is none. `sources` given: the build of
    exactly those sources (keyed by their text)."""

    def __init__(self, cs: CoefficientSet, sources: dict | None = None, quiet=True):
        self.cs = cs
        self.spec: ChainSpec = cs.spec
        self.dtype = np_dtype(self.spec.unit)

        def files():
            out = dict(sources) if sources is not None else render(cs)
            ctx = template_context(cs)
            env = _env()
            out["host_shim.c"] = env.get_template("host_shim.c.j2").render(**ctx)
            out["host_shim.h"] = env.get_template("host_shim.h.j2").render(**ctx)
            return out

        key = input_key(cs) if sources is None else None
        self._lib, self._ffi = cffi_module(
            "_magcal_host", files if key else files(), "host_shim.h",
            '#include <stdint.h>\n#include "host_shim.h"\n', input_key=key)

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

    def _ptr(self, a, ctype=None):
        return self._ffi.cast(f"{ctype or self._ctype} *", a.ctypes.data)

    def _aux(self, n, coil_A, channels, rate_dps, dt_s):
        """Aux arrays (kept alive by the caller) and their pointers; NULL where not given."""
        spec, keep = self.spec, []

        def arr(values, width):
            if values is None:
                return self._ffi.NULL
            a = np.ascontiguousarray(np.asarray(values, dtype=np.float64)
                                     .astype(self.dtype).reshape(n, width))
            keep.append(a)
            return self._ptr(a)

        chans = None
        if channels is not None and spec.aux_channels:
            chans = np.stack([np.asarray(channels.get(c, np.zeros(n)), dtype=np.float64)
                              for c in spec.aux_channels], axis=1)
        ptrs = (arr(coil_A if spec.coils else None, len(spec.coils)),
                arr(chans, len(spec.aux_channels)),
                arr(rate_dps if spec.needs_rate else None, 3),
                arr(dt_s if spec.needs_dt else None, 1))
        return keep, ptrs

    def _coeffs(self, coeffs_flat):
        return np.ascontiguousarray(self.flat_coeffs() if coeffs_flat is None else
                                    np.asarray(coeffs_flat, dtype=self.dtype))

    def _raw(self, sensor, raw_counts):
        """The readings as the sensor's C API takes them, with the pointer type: counts as
        int32; a physical-input sensor's real numbers in the float type (float64 first,
        then one rounding, as chain.reference_sensor converts them)."""
        if is_physical(sensor):
            raw = np.asarray(raw_counts, dtype=np.float64).astype(self.dtype)
            return np.ascontiguousarray(raw), self._ctype
        return np.ascontiguousarray(raw_counts, dtype=np.int32), "int32_t"

    def new_state(self, sensor: str) -> np.ndarray:
        """A zeroed state of the sensor's chain (its C state struct as bytes), for
        correct(..., state=): consecutive calls on it are one sequence of calls."""
        return np.zeros(int(getattr(self._lib, f"host_{sensor}_state_size")()), np.uint8)

    def correct(self, sensor: str, raw_counts, temp_C, coil_A=None, coeffs_flat=None,
                channels=None, rate_dps=None, dt_s=None, state=None) -> dict:
        """Run `<unit>_<sensor>_correct` over a sequence of samples on one state; same
        outputs as chain.reference_sensor (offset_counts: the state's stored offset after
        each call, NaN until the first unsaturated pair). raw_counts: counts, or for a
        physical-input sensor its readings in its input unit. channels: {column: (N,)}.
        state: None, a fresh zeroed state; else a buffer from new_state(sensor), read at
        the start and updated in place at the end (streaming in chunks)."""
        s = self.spec.unit.sensor(sensor)
        raw, raw_t = self._raw(s, raw_counts)
        n = raw.shape[0]
        assert raw.shape == (n, 6 if s.set_reset else 3), raw.shape
        temp = np.ascontiguousarray(np.asarray(temp_C, dtype=np.float64).astype(self.dtype))
        co = self._coeffs(coeffs_flat)
        field = np.zeros((n, 3), dtype=self.dtype)
        chip = np.zeros((n, 3), dtype=self.dtype)
        offs = np.zeros((n, 3), dtype=self.dtype)
        status = np.zeros(n, dtype=np.uint16)
        keep, aux = self._aux(n, coil_A, channels, rate_dps, dt_s)
        getattr(self._lib, f"host_{sensor}_batch")(
            self._ptr(co), n, self._ptr(raw, raw_t), self._ptr(temp), *aux,
            self._ptr(field), self._ptr(chip), self._ptr(offs), self._ptr(status, "uint16_t"),
            self._state_ptr(sensor, state))
        out = {"field_body_nT": field, "status": status}
        if s.set_reset:
            out["chip_offset_nT"] = chip
            out["offset_counts"] = offs
        return out

    def _state_ptr(self, sensor, state):
        if state is None or state.size == 0:
            return self._ffi.NULL
        want = int(getattr(self._lib, f"host_{sensor}_state_size")())
        if state.dtype != np.uint8 or state.size != want or not state.flags.c_contiguous:
            raise ValueError(f"state of {sensor}: not a buffer from new_state()")
        return self._ffi.cast("unsigned char *", state.ctypes.data)

    def correct_set(self, sensor: str, set_counts, temp_C, offset_counts, coil_A=None,
                    coeffs_flat=None, channels=None, rate_dps=None, dt_s=None) -> dict:
        """Run `<unit>_<sensor>_correct_set` with a stored offset per sample (NaN: none)."""
        raw, raw_t = self._raw(self.spec.unit.sensor(sensor), set_counts)
        n = raw.shape[0]
        temp = np.ascontiguousarray(np.asarray(temp_C, dtype=np.float64).astype(self.dtype))
        off = np.ascontiguousarray(np.asarray(offset_counts, dtype=self.dtype))
        co = self._coeffs(coeffs_flat)
        field = np.zeros((n, 3), dtype=self.dtype)
        status = np.zeros(n, dtype=np.uint16)
        keep, aux = self._aux(n, coil_A, channels, rate_dps, dt_s)
        getattr(self._lib, f"host_{sensor}_set_batch")(
            self._ptr(co), n, self._ptr(raw, raw_t), self._ptr(temp), *aux,
            self._ptr(off), self._ptr(field), self._ptr(status, "uint16_t"))
        return {"field_body_nT": field, "status": status}

    def correct_mixed(self, sensor: str, raw_counts, temp_C, mode, coil_A=None,
                      coeffs_flat=None, channels=None, rate_dps=None, dt_s=None) -> dict:
        """Calls of every kind on one state: mode bit 0 = SET-only (raw_counts' RESET half
        unused), bit 1 = state NULL. Sensors that keep a state only."""
        raw, raw_t = self._raw(self.spec.unit.sensor(sensor), raw_counts)
        n = raw.shape[0]
        temp = np.ascontiguousarray(np.asarray(temp_C, dtype=np.float64).astype(self.dtype))
        md = np.ascontiguousarray(mode, dtype=np.uint8)
        co = self._coeffs(coeffs_flat)
        field = np.zeros((n, 3), dtype=self.dtype)
        status = np.zeros(n, dtype=np.uint16)
        keep, aux = self._aux(n, coil_A, channels, rate_dps, dt_s)
        getattr(self._lib, f"host_{sensor}_mixed_batch")(
            self._ptr(co), n, self._ptr(raw, raw_t), self._ptr(temp), *aux,
            self._ptr(md, "uint8_t"), self._ptr(field), self._ptr(status, "uint16_t"))
        return {"field_body_nT": field, "status": status}

    def select(self, fields, statuses, coeffs_flat=None) -> dict:
        """Run `<unit>_select` over samples: fields (N, S, 3), statuses (N, S)."""
        f = np.ascontiguousarray(np.asarray(fields, dtype=self.dtype))
        st = np.ascontiguousarray(np.array(statuses, dtype=np.uint16))
        n = st.shape[0]
        co = self._coeffs(coeffs_flat)
        sel = np.zeros((n, 3), dtype=self.dtype)
        sensor = np.zeros(n, dtype=np.int8)
        rank = np.zeros(n, dtype=np.int8)
        reason = np.zeros(n, dtype=np.uint8)
        self._lib.host_select_batch(self._ptr(co), n, self._ptr(f), self._ptr(st, "uint16_t"),
                                    self._ptr(sel), self._ptr(sensor, "int8_t"),
                                    self._ptr(rank, "int8_t"), self._ptr(reason, "uint8_t"))
        return {"status": st, "field_body_nT": sel, "sensor": sensor.astype(np.int64),
                "rank": rank.astype(np.int64), "reason": reason.astype(np.int64)}
