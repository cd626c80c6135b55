"""The flight processor's toolchain, and the build of a unit's flight C with the test runner.

Cortex-M4F, emulated by QEMU's `mps2-an386`: the tools and their flags (the flight build's
-O2 -ffp-contract=off -std=c99, hard float), the runner protocol's constants, the entry
points of the generated API as the runner calls them, the runner's sources
(templates/arm/) and the build itself, cached by content. Running and measuring are in
arm_runner and arm_measure; generator.flight.target gathers all three.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import casadi as ca

from generator.flight import host
from generator.flight.chain import ChainSpec
from generator.flight.codegen import TEMPLATE_DIR, _env, build_kernel, render, template_context
from generator.flight.coeffs import CoefficientSet

# ---- toolchain ------------------------------------------------------------------------

DEBIAN_PACKAGES = ("gcc-arm-none-eabi", "libnewlib-arm-none-eabi", "qemu-system-arm")
CC = os.environ.get("ARM_CC", "arm-none-eabi-gcc")
TOOLS = {"cc": CC, "nm": "arm-none-eabi-nm", "objdump": "arm-none-eabi-objdump",
         "size": "arm-none-eabi-size", "qemu": os.environ.get("QEMU_ARM", "qemu-system-arm")}
MACHINE = "mps2-an386"

ARCH_FLAGS = ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"]
FP_FLAGS = ["-O2", "-ffp-contract=off", "-std=c99"]
STRICT_FLAGS = ["-Wall", "-Wextra", "-Werror"]
# CasADi's file: its boilerplate has unused parameters (iw, w, mem), as on the host.
KERNEL_FLAGS = STRICT_FLAGS + ["-Wno-unused-parameter"]
# Issue 7 item 3: the generated C also builds with these (documented exceptions below).
EXTRA_WARNINGS = ["-Wdouble-promotion", "-Wconversion", "-Wshadow"]
# What the measurement adds to the unit's objects: the .su frame sizes (the objects are
# byte-identical with and without it; -ffunction-sections/-fdata-sections would not be:
# they disable GCC's section anchors, so the unit is built without them).
MEASURE_FLAGS = ["-fstack-usage"]
# The runner only: its memcpy/memset must not become calls to themselves, and its
# marker functions must not be merged; per-function sections for --gc-sections.
RUNNER_FLAGS = STRICT_FLAGS + ["-fno-tree-loop-distribute-patterns", "-fno-ipa-icf",
                               "-ffunction-sections", "-fdata-sections"]
LINK_FLAGS = ["-nostdlib", "-nostartfiles", "-Wl,--gc-sections"]
CPPCHECK_FLAGS = ["--enable=warning,portability", "--error-exitcode=1", "--std=c99",
                  "--inline-suppr", "--quiet"]

# Undefined symbols the generated objects may need from outside the unit: none, or the
# libm functions the chain's operations map to (sqrtf/fabsf, float32).
# The chain may call sqrtf/fabsf; memcpy, memset and memcmp are the four (with memmove)
# that GCC requires of even a freestanding C environment (it emits calls to them itself)
# and that the table code uses for byte-exact copies; no heap, nothing else of libc/libm.
ALLOWED_EXTERNAL = {"sqrtf", "fabsf", "memcpy", "memset", "memcmp", "memmove"}
HEAP_SYMBOLS = {"malloc", "calloc", "realloc", "free", "_sbrk", "sbrk", "_malloc_r",
                "_free_r", "_calloc_r", "_realloc_r"}

# ---- runner protocol (templates/arm/runner.c.j2) ---------------------------------------

MAGIC = 0x4A4C434D         # "MCLJ"
DONE = 0x454E4F44          # "DONE"
PROTOCOL = 1
CMD = {"END": 0xFFFFFFFF, "COEFFS": 1, "DEFAULTS": 2, "CORRECT": 3, "MEASURE": 4,
       "CALIBRATE": 5, "EXT": 6}
JOB_FILE, OUT_FILE = "job.bin", "out.bin"
IO_CHUNK = 8192
EXT_MAX = 16384
PAINT_WORDS = 512            # 2 KiB painted below the stack pointer per measured call
STACK_SIZE = 16384
CAL_NOPS = 100               # the calibration function: CAL_NOPS nops + bx lr
BUILD_VERSION = "arm-2"      # bump when the build recipe changes (cache key)


class ArmToolchainMissing(RuntimeError):
    pass


class ArmBuildError(RuntimeError):
    pass


class ArmRunError(RuntimeError):
    pass


@functools.lru_cache(maxsize=None)
def missing_tools() -> list:
    """The tools of DEBIAN_PACKAGES that are not on PATH (empty when all are)."""
    out = [t for k, t in TOOLS.items() if shutil.which(t) is None]
    if shutil.which(CC) is not None and not _newlib_headers_ok():
        out.append("newlib headers (math.h for arm-none-eabi)")
    return out


def _newlib_headers_ok() -> bool:
    p = subprocess.run([CC, *ARCH_FLAGS, "-E", "-x", "c", "-", "-o", os.devnull],
                       input="#include <math.h>\n#include <stdint.h>\n", capture_output=True,
                       text=True)
    return p.returncode == 0


def require_toolchain():
    miss = missing_tools()
    if miss:
        raise ArmToolchainMissing(
            f"missing {', '.join(miss)}; install the Debian packages "
            f"{' '.join(DEBIAN_PACKAGES)}")


def _run(cmd, cwd=None, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


@functools.lru_cache(maxsize=None)
def tool_versions() -> dict:
    out = {}
    for key in ("cc", "qemu"):
        try:
            out[key] = _run([TOOLS[key], "--version"]).stdout.splitlines()[0].strip()
        except (OSError, IndexError):
            out[key] = "?"
    return out


def qemu_version() -> tuple:
    m = re.search(r"version (\d+)\.(\d+)", tool_versions()["qemu"])
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def cache_dir() -> Path:
    """The per-user build cache of the host build (host.cache_dir: private, owned by this
    user), its folder arm/: the test runner's images are built and run from here too."""
    d = host.cache_dir() / "arm"
    d.mkdir(mode=0o700, exist_ok=True)
    host._check_private(d)
    return d


# ---- sources -------------------------------------------------------------------------


def _arm_env():
    env = _env()
    env.loader.searchpath.append(str(TEMPLATE_DIR / "arm"))
    return env


def runner_context(cs: CoefficientSet) -> dict:
    ctx = dict(template_context(cs))
    ctx.update({
        "job_file": JOB_FILE, "out_file": OUT_FILE, "magic": MAGIC, "done": DONE,
        "version": PROTOCOL, "cmd": CMD, "io_chunk": IO_CHUNK, "ext_max": EXT_MAX,
        "paint_words": PAINT_WORDS, "stack_size": STACK_SIZE, "cal_nops": CAL_NOPS,
        "n_irq": 32, "n_coil_slots": max(1, len(cs.spec.coils)),
    })
    by_name = {s["name"]: s for s in ctx["sensors"]}
    ctx["entries"] = [{"id": e.id, "kind": e.kind, "fn": e.fn, "tag": e.tag,
                       "s": by_name.get(e.sensor)} for e in entry_points(cs)]
    return ctx


def runner_sources(cs: CoefficientSet) -> dict:
    """{file name: text} of the test runner (not flight code)."""
    ctx = runner_context(cs)
    env = _arm_env()
    return {
        "runner.c": env.get_template("runner.c.j2").render(**ctx),
        "startup.S": env.get_template("startup.S.j2").render(**ctx),
        "link.ld": env.get_template("mps2_an386.ld.j2").render(**ctx),
    }


def unit_c_files(cs_or_files) -> list:
    """The .c files of a unit's generated sources ({name: text} or a CoefficientSet)."""
    files = cs_or_files if isinstance(cs_or_files, dict) else render(cs_or_files)
    return sorted(n for n in files if n.endswith(".c"))


CASADI_MARK = "automatically generated by CasADi"


def flags_for(name: str, unit_id: str, files: dict | None = None) -> list:
    """Warning flags of one generated file: the flight flags; CasADi's exception
    (-Wno-unused-parameter) only for CasADi's own text compiled on its own."""
    if name == f"{unit_id}_kernels.c":
        return KERNEL_FLAGS
    if files is not None and name in files and CASADI_MARK in files[name] \
            and "#pragma GCC diagnostic" not in files[name]:
        return KERNEL_FLAGS     # CasADi's own text, not wrapped by our templates
    # the wrapper includes the kernels between "#pragma GCC diagnostic push/pop" that
    # silence CasADi's unused work-array parameters: the wrapper itself gets every flag
    return STRICT_FLAGS


# ---- build ---------------------------------------------------------------------------


@dataclass
class ArmBuild:
    """A linked runner ELF for one unit, with its objects, .su files and analysis."""

    cs: CoefficientSet
    dir: Path
    unit_sources: dict
    extra_sources: dict

    @property
    def elf(self) -> Path:
        return self.dir / "runner.elf"

    @property
    def unit_objects(self) -> list:
        return [self.dir / (n[:-2] + ".o") for n in sorted(self.unit_sources) if n.endswith(".c")]

    @property
    def extra_objects(self) -> list:
        return [self.dir / (n[:-2] + ".o") for n in sorted(self.extra_sources)
                if n.endswith(".c")]


def _compile(cc_flags, src: Path, obj: Path, include: Path):
    cmd = [CC, *ARCH_FLAGS, *FP_FLAGS, *cc_flags, "-I", str(include), "-c", str(src),
           "-o", str(obj)]
    p = _run(cmd, cwd=obj.parent)
    if p.returncode != 0:
        raise ArmBuildError(f"compile failed: {' '.join(map(str, cmd))}\n{p.stderr}")
    return p


def build(cs: CoefficientSet, sources: dict | None = None,
          extra_sources: dict | None = None, casadi_files: tuple = ()) -> ArmBuild:
    """Compile the unit's flight C (or `sources`, e.g. a perturbed variant) with the flight
    flags, plus `extra_sources` ({name: text}; .c files compiled with the strict flags
    and linked, .h files available to all; e.g. a table validator defining
    magcal_runner_ext), and link the runner. casadi_files: further files that contain
    CasADi's code and get its warning exception. Cached by content."""
    require_toolchain()
    unit_src = dict(sources) if sources is not None else render(cs)
    extra = dict(extra_sources or {})
    runner = runner_sources(cs)
    key = hashlib.sha256()
    for group in (unit_src, extra, runner):
        for name in sorted(group):
            key.update(name.encode() + b"\0" + group[name].encode() + b"\0")
        key.update(b"\1")
    key.update(" ".join(ARCH_FLAGS + FP_FLAGS + STRICT_FLAGS + KERNEL_FLAGS + MEASURE_FLAGS
                        + RUNNER_FLAGS + LINK_FLAGS).encode())
    key.update(tool_versions()["cc"].encode() + BUILD_VERSION.encode())
    key.update(repr(sorted(casadi_files)).encode())
    final = cache_dir() / f"{cs.unit.id}-{key.hexdigest()[:16]}"
    b = ArmBuild(cs, final, unit_src, extra)
    if (final / "runner.elf").exists():
        return b
    tmp = Path(tempfile.mkdtemp(prefix=final.name + "-", dir=cache_dir()))
    try:
        for group in (unit_src, extra, runner):
            for name, text in group.items():
                (tmp / name).write_text(text)
        objs = []
        uid = cs.unit.id
        for name in sorted(unit_src):
            if name.endswith(".c"):
                obj = tmp / (name[:-2] + ".o")
                flags = KERNEL_FLAGS if name in casadi_files else flags_for(name, uid, unit_src)
                _compile(flags + MEASURE_FLAGS, tmp / name, obj, tmp)
                objs.append(obj)
        for name in sorted(extra):
            if name.endswith(".c"):
                obj = tmp / (name[:-2] + ".o")
                _compile(STRICT_FLAGS + MEASURE_FLAGS, tmp / name, obj, tmp)
                objs.append(obj)
        _compile(RUNNER_FLAGS, tmp / "runner.c", tmp / "runner.o", tmp)
        _compile([], tmp / "startup.S", tmp / "startup.o", tmp)
        objs += [tmp / "runner.o", tmp / "startup.o"]
        cmd = [CC, *ARCH_FLAGS, *LINK_FLAGS, "-T", str(tmp / "link.ld"),
               f"-Wl,-Map={tmp / 'runner.map'}", "-o", str(tmp / "runner.elf"),
               *map(str, objs), "-lgcc"]
        p = _run(cmd, cwd=tmp)
        if p.returncode != 0:
            raise ArmBuildError(f"link failed: {' '.join(cmd)}\n{p.stderr}")
        try:
            os.rename(tmp, final)
        except OSError:      # another process built the same thing first
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return b


@dataclass(frozen=True)
class Entry:
    """One entry point of the flight API, as the runner calls it."""

    id: int
    kind: str            # "correct", "correct_set" or "select"
    sensor: str | None   # None for select
    fn: str              # the C function
    tag: str             # runner-internal name

    def kernel(self, spec: ChainSpec) -> ca.Function:
        """The CasADi Function whose arithmetic this entry point runs."""
        from generator.flight import codegen
        if self.kind == "select":
            return codegen.build_agreement_kernel(spec)
        s = spec.unit.sensor(self.sensor)
        if self.kind == "correct_set":
            return build_kernel(spec, s, set_only=True)
        return build_kernel(spec, s)


def entry_points(cs: CoefficientSet) -> list:
    """The flight API of the unit's generated C, in runner order: per sensor
    `<unit>_<sensor>_correct` (and `_correct_set` for SET/RESET sensors), then
    `<unit>_select`."""
    ctx = template_context(cs)
    unit = ctx["unit"]
    out = []
    for s in ctx["sensors"]:
        out.append(Entry(len(out), "correct", s["name"], f"{unit}_{s['name']}_correct",
                         f"{s['name']}_correct"))
        if s["set_reset"] and "set_kernel" in s:
            out.append(Entry(len(out), "correct_set", s["name"],
                             f"{unit}_{s['name']}_correct_set", f"{s['name']}_correct_set"))
    if "fallback_order" in ctx:
        out.append(Entry(len(out), "select", None, f"{unit}_select", "select"))
    return out


def chain_features(cs: CoefficientSet) -> dict:
    """The optional parts of the generated API (older chains lack the keys: defaults)."""
    ctx = template_context(cs)
    coils = ctx.get("coils", [])
    return {
        "n_coils": len(coils), "n_channels": len(ctx.get("channels", [])),
        "needs_rate": bool(ctx.get("needs_rate", False)),
        "needs_dt": bool(ctx.get("needs_dt", False)),
        "has_aux": bool(ctx.get("has_aux", bool(coils))),
        "state": {s["name"]: bool(s.get("has_state", s["set_reset"])) for s in ctx["sensors"]},
        "lag": {s["name"]: bool(s.get("lag", False)) for s in ctx["sensors"]},
    }
