"""Issue 7: the generated flight C on the flight processor (Cortex-M4F, QEMU mps2-an386).

The unit's sources are built with arm-none-eabi-gcc and the flight flags, linked with our
own test runner (templates/arm/) and run under qemu-system-arm with semihosting; outputs
come back as bit patterns and are compared with chain.reference_sensor / reference_select
bit for bit, as the host suite does. Also: the instruction counter's calibration, stack
and code size against the targets, and the static checks of the generated C (extra
warnings, cppcheck, undefined symbols).

Skips when the toolchain is missing, naming the Debian packages; fails instead when the
environment variable CI is set (the CI script installs them).
"""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from chain_fixtures import (EXAMPLE_COEFFS, REPO, assert_bit_identical, bits, random_coeffs,
                            random_inputs, samsat_unit, with_float)
from generator.flight import chain
from generator.flight import target as ta
from generator.flight.chain import reference_select, reference_sensor
from generator.flight.coeffs import CoefficientSet

pytestmark = pytest.mark.arm

COILS = ("coil_x_A", "coil_y_A", "coil_z_A")
N_RANDOM = 4000          # per sensor and entry point (the host suite runs 100,000)
from ci import in_ci

IN_CI = in_ci()


def _require(what_missing: list):
    if what_missing:
        msg = (f"missing {', '.join(what_missing)}: install the Debian packages "
               f"{' '.join(ta.DEBIAN_PACKAGES)}")
        if IN_CI:
            pytest.fail(f"CI is set: {msg}")
        pytest.skip(msg)


@pytest.fixture(scope="session")
def toolchain():
    _require(ta.missing_tools())


def _cases():
    rng = np.random.default_rng(20261207)
    cases = []
    if EXAMPLE_COEFFS.exists():
        cases.append(("example", lambda: CoefficientSet.load(EXAMPLE_COEFFS)))
    a = random_coeffs(rng, samsat_unit("arm32"))
    b = random_coeffs(rng, samsat_unit("armcoil"), coils=COILS)
    c = with_float(random_coeffs(rng, samsat_unit("arm64"), coils=COILS), "float64")
    cases += [("random", lambda: a), ("random_coils", lambda: b),
              ("random_f64_softfloat", lambda: c)]
    return cases


CASES = _cases()


@pytest.fixture(scope="module", params=CASES, ids=[c[0] for c in CASES])
def unit(request, toolchain):
    label, make = request.param
    cs = make()
    return label, cs, ta.ArmUnit(cs)


def _t_range(cs, s):
    return float(cs.sensors[s.name]["t_min_C"]), float(cs.sensors[s.name]["t_max_C"])


def _ref(cs, s, raw, temp, coil, **kw):
    return reference_sensor(cs.spec, s, cs.flat_sensor(s.name), cs.flat_unit(), raw, temp,
                            coil, **kw)


def _has(cs, kind):
    return any(e.kind == kind for e in ta.entry_points(cs))


def _sensor_calls(cs, raw_by_sensor):
    """The calls for every sensor entry point and the reference's answers."""
    calls, refs = [], []
    for s in cs.unit.sensors:
        raw, temp, coil = raw_by_sensor[s.name]
        calls.append(("correct", s.name, raw, temp, coil))
        refs.append((f"{s.name} correct", _ref(cs, s, raw, temp, coil)))
        if s.set_reset and _has(cs, "correct_set"):
            # stored offsets as the pair calls leave them, some missing
            off = refs[-1][1]["offset_counts"].copy()
            off[::9] = np.nan
            calls.append(("correct_set", s.name, raw[:, :3], temp, off, coil))
            refs.append((f"{s.name} correct_set",
                         _ref(cs, s, raw[:, :3], temp, coil, set_only=True, offset_counts=off)))
    return calls, refs


def test_random_inputs_bit_identical(unit):
    """Thousands of random samples per sensor through every entry point, compiled-in
    default coefficients: the target's bits are the reference's bits."""
    label, cs, arm = unit
    rng = np.random.default_rng(1)
    nc = len(cs.spec.coils)
    inputs = {s.name: random_inputs(rng, s, N_RANDOM, nc, _t_range(cs, s))
              for s in cs.unit.sensors}
    calls, refs = _sensor_calls(cs, inputs)
    outs = arm.run(calls)                      # default coefficients (flash)
    for (name, ref), got in zip(refs, outs):
        assert_bit_identical(got, ref, f"{label}/{name}")
        # not vacuous: outputs vary, many samples valid
        assert np.unique(bits(got["field_body_nT"][:, 0])).size > N_RANDOM // 3
        st = got["status"] & ~np.uint16(chain.STATUS_IMPLAUSIBLE)
        assert np.mean(st == 0) > 0.3


def test_edge_cases_bit_identical(unit):
    """Counts at and next to the rails, zero field, temperatures at and beyond the range
    ends and one ulp either side, +-inf, nan; currents with nan and inf. Uploaded table."""
    label, cs, arm = unit
    ft = chain.np_dtype(cs.unit)
    data = {}
    for s in cs.unit.sensors:
        t_min, t_max = _t_range(cs, s)
        f32 = np.float32
        temps = [t_min, t_max, np.nextafter(f32(t_min), f32(-np.inf)),
                 np.nextafter(f32(t_min), f32(np.inf)), np.nextafter(f32(t_max), f32(np.inf)),
                 np.nextafter(f32(t_max), f32(-np.inf)), -273.15, 1e30, -1e30, 0.0, -0.0,
                 25.0, np.inf, -np.inf, np.nan]
        k = 6 if s.set_reset else 3
        counts = [s.count_min, s.count_min + 1, s.zero_count, s.count_max - 1, s.count_max]
        raws = [np.full(k, c) for c in counts]
        raws.append(np.resize([s.count_min, s.count_max], k))
        raws.append(np.resize([s.count_min + 1, s.count_max - 1], k))
        if s.set_reset:   # zero field with a bridge offset: SET == RESET
            raws.append(np.array([40000, 30000, 20000, 40000, 30000, 20000]))
        rows = [(r, t) for r in raws for t in temps]
        raw = np.array([r for r, _ in rows])
        temp = np.array([t for _, t in rows], dtype=np.float32)
        coil = None
        if cs.spec.coils:
            coil = np.zeros((raw.shape[0], len(cs.spec.coils)))
            coil[::7] = 0.1
            coil[3::11, 0] = np.nan
            coil[5::13, 1] = np.inf
            coil[6::17, 2] = -np.inf
        data[s.name] = (raw, temp, coil)
    calls, refs = _sensor_calls(cs, data)
    outs = arm.run(calls, coeffs_flat=arm.flat_coeffs())   # the uploaded-table path
    for (name, ref), got in zip(refs, outs):
        assert_bit_identical(got, ref, f"{label}/{name} edges")
    # the paths are really taken
    st = np.concatenate([o["status"] for o in outs])
    for bit in (chain.STATUS_NONFINITE, chain.STATUS_SATURATED, chain.STATUS_TEMP_CLAMPED):
        assert np.any(st & bit), bit
    assert outs[0]["field_body_nT"].dtype == ft


def test_select_bit_identical(unit):
    label, cs, arm = unit
    if not _has(cs, "select"):
        pytest.skip("this chain has no select entry point")
    rng = np.random.default_rng(2)
    S, n = len(cs.unit.sensors), 3000
    ft = chain.np_dtype(cs.unit)
    agree = [float(cs.sensors[s.name]["agree_nT"]) for s in cs.unit.sensors]
    fields = np.repeat(rng.normal(0, 30000, (n, 1, 3)), S, axis=1) + \
        rng.normal(0, 1, (n, S, 3)) * np.array(agree)[None, :, None] * rng.uniform(0, 2, (n, S, 1))
    fields[::5, rng.integers(0, S)] += 10 * max(agree)
    fields[7::50] = np.nan
    fields = fields.astype(ft)
    statuses = np.where(rng.random((n, S)) < 0.25, chain.STATUS_SATURATED, 0).astype(np.uint16)
    got = arm.select(fields, statuses)
    ref = reference_select(cs.spec, {s.name: cs.flat_sensor(s.name) for s in cs.unit.sensors},
                           fields, statuses)
    assert_bit_identical({k: got[k] for k in ("status", "field_body_nT")},
                         {k: ref[k] for k in ("status", "field_body_nT")}, f"{label}/select")
    for k in ("sensor", "rank", "reason"):
        np.testing.assert_array_equal(got[k], ref[k], err_msg=f"{label}/select {k}")
    assert len(np.unique(got["reason"])) >= 3   # several outcomes exercised


def test_compiled_in_defaults_equal_the_uploaded_table(unit):
    label, cs, arm = unit
    rng = np.random.default_rng(4)
    s = cs.unit.sensors[-1]
    raw, temp, coil = random_inputs(rng, s, 2000, len(cs.spec.coils), _t_range(cs, s))
    flash = arm.correct(s.name, raw, temp, coil)
    ram = arm.correct(s.name, raw, temp, coil, coeffs_flat=arm.flat_coeffs())
    assert_bit_identical(flash, ram, f"{label}/{s.name} defaults vs table")


def test_the_comparison_catches_a_perturbed_coefficient(unit):
    """The smallest change of one matrix coefficient of the table the target runs that
    reaches its kernel (the kernel reads M folded with the count scale, rounded once when
    the table is prepared: one ulp of M can fold to the same value, so it is stepped until
    the prepared value changes): the bit comparison must notice; and the unperturbed table
    must pass on the same samples."""
    label, cs, arm = unit
    rng = np.random.default_rng(7)
    s = cs.unit.sensors[0]
    raw, temp, coil = random_inputs(rng, s, 3000, len(cs.spec.coils), _t_range(cs, s))
    flat = arm.flat_coeffs()
    k = cs.spec.offsets(cs.spec.sensor_blocks(s))["M_poly"]   # m0_00 of the first sensor
    n_s = cs.spec.n_sensor_coeffs(s)   # the first sensor's block leads the flat set
    unit_flat = flat[-cs.spec.n_unit_coeffs():]
    before = chain.prepare_sensor(cs.spec, s, flat[:n_s], unit_flat)
    bad = flat.copy()
    for _ in range(4):
        bad[k] = np.nextafter(bad[k], arm.dtype(np.inf))
        if not np.array_equal(chain.prepare_sensor(cs.spec, s, bad[:n_s], unit_flat), before):
            break
    else:
        raise AssertionError("four ulps of M did not reach the prepared coefficients")
    good_out, bad_out = arm.run([("correct", s.name, raw, temp, coil)], coeffs_flat=flat)[0], \
        arm.run([("correct", s.name, raw, temp, coil)], coeffs_flat=bad)[0]
    ref = _ref(cs, s, raw, temp, coil)
    assert_bit_identical(good_out, ref, f"{label}/{s.name}")
    with pytest.raises(AssertionError, match="samples differ"):
        assert_bit_identical(bad_out, ref)


def test_the_runner_fails_loudly(unit):
    """A job for another chain layout, a truncated job: non-zero exit, no silent result."""
    label, cs, arm = unit
    job = ta.Job(cs)
    job.defaults()
    data = bytearray(job.bytes())
    struct.pack_into("<I", data, 8, cs.spec.layout_hash() ^ 1)
    with pytest.raises(ta.ArmRunError, match="exit status"):
        ta.run_job(arm.build.elf, bytes(data), timeout=60)
    job = ta.Job(cs)
    s = cs.unit.sensors[0]
    job.correct(s.name, np.full((4, 6 if s.set_reset else 3), s.zero_count), [20.0] * 4)
    with pytest.raises(ta.ArmRunError, match="exit status"):
        ta.run_job(arm.build.elf, job.bytes()[:-20], timeout=60)


def _with_options(cs, rng):
    """cs with the optional stages of chain.SensorOptions on two sensors (coefficients of
    the added blocks small and random; time constants 30 s)."""
    from dataclasses import replace

    opts = (("mmc1", chain.SensorOptions(channels=("heater_A",), thermal_lag=True,
                                         sr_compensation=True, lagged_channels=("bus_V",))),
            ("mpu1", chain.SensorOptions(channels=("heater_A", "bus_V"), nonlinear=True,
                                         channel_scale=True)))
    spec = replace(cs.spec, sensor_options=opts)
    sensors = {}
    for s in spec.unit.sensors:
        v = dict(cs.sensors[s.name])
        for b in spec.sensor_blocks(s):
            if b.name not in v:
                v[b.name] = np.array(30.0) if "tau" in b.name else \
                    rng.normal(0, 1e-4 if "cubic" in b.name else
                               1e-3 if b.name == "g_per_unit" else 20.0, b.shape or ())
        sensors[s.name] = v
    return CoefficientSet(spec, sensors, cs.unit_values, {}, {})


def test_optional_stages_bit_identical(toolchain):
    """Channels, thermal lag (a recursion over the calls), a lagged channel (its own
    recursion), SET/RESET rotation compensation, the channel scale and the cubic: the
    target's bits are the reference's bits."""
    if not hasattr(chain, "SensorOptions"):
        pytest.skip("this chain has no optional stages")
    rng = np.random.default_rng(12)
    cs = _with_options(random_coeffs(rng, samsat_unit("armopt"), coils=COILS), rng)
    arm = ta.ArmUnit(cs)
    n = 3000
    calls, refs = [], []
    for s in cs.unit.sensors[:2]:
        raw, temp, coil = random_inputs(rng, s, n, len(COILS), _t_range(cs, s))
        temp = np.cumsum(rng.normal(0, 0.5, n)).astype(np.float32) + 20   # a slow drift
        temp[::97] = np.nan
        ch = {"heater_A": rng.uniform(0, 0.5, n), "bus_V": rng.uniform(7.0, 8.4, n)}
        rate, dt = rng.normal(0, 2, (n, 3)), rng.uniform(0.5, 2.0, n)
        aux = {"channels": ch, "rate_dps": rate, "dt_s": dt}
        calls.append(("correct", s.name, raw, temp, coil, {"aux": aux}))
        refs.append((s.name, _ref(cs, s, raw, temp, coil, channels=ch, rate_dps=rate,
                                  dt_s=dt)))
    for (name, ref), got in zip(refs, arm.run(calls)):
        assert_bit_identical(got, ref, f"options/{name}")


EXT_SOURCE = """\
/* a stand-in for a table validator linked into the runner: sums the payload bytes */
#include <stdint.h>
int magcal_runner_ext(const uint8_t *payload, uint32_t len, uint8_t *out, uint32_t *out_len);
int magcal_runner_ext(const uint8_t *payload, uint32_t len, uint8_t *out, uint32_t *out_len)
{
    uint32_t i, sum = 0u;
    for (i = 0u; i < len; ++i) {
        sum += payload[i];
    }
    for (i = 0u; i < 4u; ++i) {
        out[i] = (uint8_t)(sum >> (8u * i));
    }
    *out_len = 4u;
    return 7;
}
"""


def test_extra_sources_hook(toolchain):
    """Extra sources (e.g. a table validator) are compiled with the strict flight flags,
    linked into the runner, and reached through the EXT command; without them the weak
    default answers -1."""
    cs = random_coeffs(np.random.default_rng(9), samsat_unit("ext"))
    payload = bytes(range(1, 200))
    results = []
    for extra in (None, {"validator.c": EXT_SOURCE}):
        arm = ta.ArmUnit(cs, extra_sources=extra)
        job = ta.Job(cs)
        job.ext(payload)
        out, _ = ta.run_job(arm.build.elf, job.bytes(), timeout=60)
        results.append(job.parse(out)[0])
    assert results[0] == {"rc": -1, "data": b""}
    assert results[1]["rc"] == 7
    assert int.from_bytes(results[1]["data"], "little") == sum(payload)
    with pytest.raises(ta.ArmBuildError, match="Werror|error"):
        ta.ArmUnit(cs, extra_sources={"bad.c": "static int unused_fn(void) { return 1; }\n"})


# ---- measurement: counters, stack, size --------------------------------------------------


@pytest.fixture(scope="module")
def measured(toolchain):
    cs = random_coeffs(np.random.default_rng(5), samsat_unit("armm"), coils=COILS)
    return cs, ta.measure(cs)


def test_instruction_counter_is_calibrated(measured):
    """The trace counts a known instruction sequence exactly; -icount time agrees with the
    trace's counts of every timing loop to within the tick resolution."""
    cs, m = measured
    cal = m["calibration"]
    for t in cal["trace"]:
        assert t["counted"] == t["expected"], t
    # whole nanoseconds per tick: 1 ns per instruction, SysTick on the 25 MHz processor
    # clock gives 40 (QEMU 7.2); the scale must at least be a whole number
    scale = cal["icount_insn_per_tick"]
    assert round(scale) >= 1 and abs(scale - round(scale)) < 0.01, scale
    tol = 3 * cal["icount_resolution"]
    for name, v in cal["loop_per_iter"].items():
        assert abs(v["trace"] - v["icount"]) <= tol, (name, v)
    for e in m["entries"]:
        for p in e.paths:
            assert abs(e.trace_per_iter[p] - e.icount_per_iter[p]) <= tol, (e.entry.fn, p)
            # the loop iteration contains the call: the call count is a part of it
            assert 0 < e.paths[p] < e.trace_per_iter[p]


def test_measurement_sees_the_paths(measured):
    """Different paths cost different instruction counts, and the early exit is cheap."""
    cs, m = measured
    for e in m["entries"]:
        if e.entry.kind == "select":
            continue
        assert e.path_status["nominal"] == 0
        assert e.paths["nonfinite"] < e.paths["nominal"] / 2
        # the clamp path is taken (GCC may make it branch-free, so it can cost the same)
        assert e.path_status["clamped"] & 0x04
        # every kernel flop is executed as an FPU arithmetic instruction
        assert e.by_class["fp arithmetic"] >= e.flops["flops"]


def test_stack_and_code_size_targets(measured):
    cs, m = measured
    for e in m["entries"]:
        assert 0 < e.stack_painted <= e.stack_static < ta.TARGET_STACK, e.entry.fn
        assert e.code_bytes > 0
    assert m["unit"]["linked_code"] < ta.TARGET_UNIT_CODE


@pytest.mark.xfail(strict=True, reason="issue 7 target not met yet: instructions per call "
                   "are 2.04-2.34 x the kernel's own flops on this unit (measured "
                   "2026-11-24, with the prepare step: the kernels are the folded chain, so "
                   "their flops are the flop bound); measurements and proposals in "
                   "docs/flight_target.md")
def test_instructions_within_twice_the_minimum_flops(measured):
    cs, m = measured
    for e in m["entries"]:
        if e.entry.kind != "select":
            assert e.ratio <= ta.TARGET_RATIO, (e.entry.fn, e.nominal, e.flops["flops"])


@pytest.mark.xfail(strict=True, reason="issue 20 goal not met: instructions per call are "
                   "2.04-2.34 x the flop bound on this unit (measured 2026-11-24, with the "
                   "prepare step: the generated kernels run the folded chain, bench_fold.py "
                   "measures 7-38 instructions per call saved against the unfolded code); "
                   "the rest is loads, stores and the wrapper's checks: the folded chain's "
                   "own loads and stores put the floor at 1.54-1.62 x the bound without "
                   "multi-register loads; docs/flight_target.md, 'The flop bound'")
def test_instructions_within_the_flop_bound_goal(measured):
    cs, m = measured
    for e in m["entries"]:
        if e.entry.kind != "select":
            assert e.bound_ratio <= ta.TARGET_BOUND_RATIO, (e.entry.fn, e.nominal, e.bound)


def test_flop_bound_is_below_every_measured_call(measured):
    """The bound is a lower bound of what runs: every sensor call executes at least as many
    FPU arithmetic instructions as the folded chain's per-call operations."""
    cs, m = measured
    for e in m["entries"]:
        assert 0 < e.bound["flops"] <= e.by_class["fp arithmetic"], (e.entry.fn, e.bound)


def test_flop_count_is_the_casadi_algorithm():
    """min flops counts what CasADi generates: it grows by exactly the added operations."""
    cs0 = random_coeffs(np.random.default_rng(6), samsat_unit("fa"))
    cs1 = random_coeffs(np.random.default_rng(6), samsat_unit("fb"), coils=COILS)
    s = cs0.unit.sensors[1]      # plain sensor
    f0 = ta.min_flops(cs0.spec, s)["flops"]
    f1 = ta.min_flops(cs1.spec, s)["flops"]
    # coils: per axis 3 products, 2 sums and 1 subtraction
    assert f1 - f0 == 3 * (len(COILS) + (len(COILS) - 1) + 1)


def test_report_command(tmp_path, toolchain):
    """`python -m generator.flight.target report` writes the report with measured numbers."""
    cs = random_coeffs(np.random.default_rng(8), samsat_unit("rep"))
    src = tmp_path / "coefficients.json"
    cs.save(src)
    out = tmp_path / "flight_target.md"
    p = subprocess.run([sys.executable, "-m", "generator.flight.target", "report", str(src), "-o",
                        str(out)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert p.returncode == 0, p.stderr
    text = out.read_text()
    m = ta.measure(cs)
    for e in m["entries"]:
        assert f"| `{e.entry.fn}` | `{e.flops['kernel']}` | {e.code_bytes} |" in text
        assert f"| {e.nominal} |" in text
    assert "instructions per tick" in text and "Static checks" in text


# ---- issue 7 item 3: static checks of the generated C ------------------------------------


@pytest.fixture(scope="module", params=[c for c in CASES if "f64" not in c[0]],
                ids=[c[0] for c in CASES if "f64" not in c[0]])
def warned(request, toolchain, tmp_path_factory):
    label, make = request.param
    cs = make()
    msgs, work = ta.warning_check(cs, workdir=tmp_path_factory.mktemp(label))
    return label, cs, msgs, work


def test_extra_warnings_clean(warned):
    """-Wdouble-promotion -Wconversion -Wshadow on top of the flight flags (-Werror): every
    generated file compiles clean; the only exception, -Wno-unused-parameter for the
    CasADi file, is the host build's too."""
    label, cs, msgs, work = warned
    assert msgs and all(m == "" for m in msgs.values()), msgs
    assert ta.flags_for(f"{cs.unit.id}_kernels.c", cs.unit.id)[-1] == "-Wno-unused-parameter"
    assert "-Wno-unused-parameter" not in ta.flags_for(f"{cs.unit.id}_magcal.c", cs.unit.id)


def test_warnings_are_checked(warned, tmp_path):
    """The check is not vacuous: a double promotion in a copy of the wrapper is caught."""
    label, cs, msgs, work = warned
    files = {p.name: p.read_text() for p in work.iterdir() if p.suffix in (".c", ".h", ".inc")}
    name = f"{cs.unit.id}_magcal.c"
    files[name] += "\ndouble magcal_promote(float x);\ndouble magcal_promote(float x) " \
                   "{ return x * 2.0; }\n"
    bad, _ = ta.warning_check(cs, workdir=tmp_path, sources=files)
    assert "double-promotion" in bad[name]


def test_no_heap_no_libm(warned):
    """Nothing in the unit's objects needs the heap, libm (except sqrtf/fabsf) or a
    soft-float helper: their undefined symbols, after resolving among themselves."""
    label, cs, msgs, work = warned
    objs = sorted(work.glob("*.o"))
    assert len(objs) == len(ta.unit_c_files(ta.render(cs)))
    ext = ta.external_symbols(objs)
    assert not ext["heap"], ext
    assert not ext["not_allowed"], ext


def test_cppcheck_clean(warned):
    label, cs, msgs, work = warned
    if not ta.cppcheck_available():
        _require(["cppcheck (Debian package cppcheck)"])
    p = ta.cppcheck(sorted(work.glob("*.c")), work)
    assert p.returncode == 0, p.stdout + p.stderr
