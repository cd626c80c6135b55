"""Issue 17, speed: the analytic Jacobian columns of the linear blocks (b, M, K, B_p) of
generator.trace.model.SensorModel equal the finite differences they replace, for vector,
magnitude and static-position rows, with and without effects in the chain (the thermal
lag's tau column, by its own recursion, against central differences).

Tolerance: forward differences of step FD_STEP (1e-3 internal units, ~1e-3 nT) on a model
that is linear in these blocks (b, K, B_p) or bilinear (M with magnitude rows: |B| is
curved with radius |B| ~ 5e4 nT) differ from the derivative by round-off, about
1e-16 * |r| / FD_STEP ~ 1e-8 relative, and by the curvature term FD_STEP * |dB|^2 / |B|;
1e-5 of the column's largest entry bounds both with margin.
"""

from __future__ import annotations

import numpy as np
import pytest

from generator.campaign import simulate as sim
from generator.trace import effects as fx
from generator.trace import tracer as tr
from generator.io.telemetry_csv import read_telemetry
from generator.trace.samples import NORM, POS

from test_trace import run, small_unit

REL_TOL = 1e-5


def samples(tmp_path, kind):
    rng = np.random.default_rng(51_000)
    unit = small_unit()
    truth = sim.random_truth(unit, rng)
    truth.H_boom_to_body = np.eye(3)
    tel, _ = run("thermal", unit, truth, 7, tmp_path)
    tels = [tel]
    if kind == "coils":       # the coil campaign: K fitted and free in the model
        p, _ = sim.simulate_campaign("coils", unit, truth, np.random.default_rng(8), tmp_path,
                                     fast=True, set_reset_delay_s=0.0, name="coils")
        tels.append(read_telemetry(p, unit))
    cs = tr.baseline_coefficients(unit, tels)[0]
    S = tr.gather_samples(unit, tels, [0] * len(tels), channels=[],
                          coils=cs.spec.coils)["mmc1"]
    if kind == "norm":          # magnitude rows only
        S.kind = np.full(S.n, NORM)
        S.ref = np.full_like(S.ref, np.nan)
        S._rows = None
    elif kind == "pos":         # static positions only
        S.kind = np.full(S.n, POS)
        S.group = np.asarray(S.file_index * 1_000_000 + 1 + (S.time_s // 400), np.int64)
        S._rows = None
    return cs, S


@pytest.mark.parametrize("with_effect", [False, True, "offset"])
@pytest.mark.parametrize("kind", ["vec", "norm", "pos", "coils"])
def test_analytic_columns_equal_finite_differences(kind, with_effect, tmp_path):
    cs, S = samples(tmp_path, kind)
    base = tr.base_from_coefficients(cs, "mmc1", 2)
    m = tr.SensorModel.for_samples(base, S)
    if with_effect is True:
        e = fx.ThermalLag()
        e.set_hyper(60.0)
        m = m.with_effect(e, e.init_params())
    elif with_effect == "offset":     # offset-stage effects: analytic columns too
        ch = np.sin(S.time_s / 300.0)
        S.channels["heater_A"] = ch
        S.channel_present["heater_A"] = S.time_s > np.median(S.time_s)
        for e in (fx.ChannelBias("heater_A", 0.5, S.channel_present["heater_A"]),
                  fx.TimeDrift(1000.0), fx.TemperaturePolynomial(3)):
            m = m.with_effect(e, e.init_params())
    rng = np.random.default_rng(3)
    th = m.theta + rng.normal(scale=2.0, size=m.P)
    r0, done = m._analytic_columns(th, S, np.arange(m.P))
    assert done, "no analytic column"
    blocks = [b for b in ("b", "M", "K", "Bp") if m.sl[b].stop > m.sl[b].start]
    if with_effect == "offset":
        blocks += [f"e{i}" for i in range(len(m.effects))]
    if kind == "coils":
        assert m.free_K
    for b in blocks:                           # every free linear block is analytic here
        assert set(range(m.sl[b].start, m.sl[b].stop)) <= set(done), b
    if with_effect is True:                     # the thermal lag's column is analytic too
        assert m.sl["e0"].start in done
    cols = np.array(sorted(done))
    J_fd = m._fd_columns(th, S, cols, r0)
    if with_effect is True:
        # log(tau) is not a linear parameter: its forward difference is off by the
        # curvature, FD_STEP / 2 relative; central differences of the same step are off
        # by FD_STEP^2 / 6 ~ 2e-7 of the column's third-derivative scale, inside REL_TOL
        c = m.sl["e0"].start
        k = int(np.searchsorted(cols, c))
        h = tr.FD_STEP
        up, dn = th.copy(), th.copy()
        up[c] += h
        dn[c] -= h
        J_fd[:, k] = (m.residual(up[None], S)[0] - m.residual(dn[None], S)[0]) / (2 * h)
    for k, c in enumerate(cols):
        scale = max(np.max(np.abs(J_fd[:, k])), 1e-12)
        assert np.max(np.abs(done[c] - J_fd[:, k])) <= REL_TOL * scale + 1e-9, (kind, c)
