"""Many constant (degree 0) reference-vector fits at once: their Gauss-Newton runs stacked.

The held-out comparison fits every temperature level of every fold on its own (fit.levels
_level_fits: 120 constant fits of ~2,500 samples on the shared thermal campaign), and
each fit's Gauss-Newton iterates are a dozen small numpy operations on 12-vectors and
12 x 12 matrices: ~40 % of such a fit's time is their fixed cost, not the samples.
reference_fits runs the fits side by side (each one fit.reference.reference_fit_steps, the
one definition of the fit: its passes over the samples, its noise bounds, splits and
weights are per fit, unchanged) and does the Gauss-Newton runs they ask for together,
one stacked iterate for all of them (stacked_gauss_newton).

stacked_gauss_newton is fit.reference._gauss_newton for a constant model (K = 1) with
every parameter free and the split given (how reference_fit calls it), on L runs at once:
the same iterates, the same projection of the start onto the fitted directions, the same
line search (halving from 1 while the step exceeds 1e-4, accepted where the cost does not
rise by more than 1e-12 of it) and stopping rule (the step moves chi^2 by < 1e-10, or the
line search fails, or GN_MAX_ITER iterates), each run stopping on its own (a run that
has stopped is no longer updated). The iterate's cost, gradient and J^T W J are those of
ResidualStats.cost_grad and normal_matrix written out for K = 1 with a leading axis over
the runs, and the fitted directions are handled as masks over the whole eigenbasis (a
direction held contributes exact zeros) instead of the columns picked out: the same
arithmetic in another order, so the coefficients agree with the run-by-run fit to
float64 rounding, not bit for bit (host_tests/test_reference_batch.py measures it on the
recorded calls of the shared campaign and on random problems). Each run's result (cost,
residuals and J^T W J at its last iterate) is the scalar one's
(reference.gauss_newton_result).

Used only where the coefficients feed a comparison and are not reported: the held-out
folds' per-level fits (fit.levels._level_fits with uncertainty=False). The fits that are
written (the final fits) stay run by run.
"""

from __future__ import annotations

import numpy as np

from generator.errors import InputError
from generator.fit.reference import (GN_MAX_ITER, ResidualStats, _gauss_newton,
                                     gauss_newton_result, reference_fit_steps)


def reference_fits(calls) -> list:
    """[reference_fit(*args, **kwargs) for (args, kwargs) in calls], each item the result
    or the InputError that call raised; the constant fits' Gauss-Newton runs stacked
    (stacked_gauss_newton), any other run done on its own (_gauss_newton)."""
    out = [None] * len(calls)
    runs = {}

    def advance(i, steps, result):
        try:
            runs[i] = (steps, next(steps) if result is None else steps.send(result))
        except StopIteration as done:
            out[i] = done.value
        except InputError as e:
            out[i] = e

    for i, (args, kwargs) in enumerate(calls):
        advance(i, reference_fit_steps(*args, **kwargs), None)
    while runs:
        todo, runs = runs, {}
        stack = [i for i, (_, run) in todo.items() if _stackable(run)]
        results = dict(zip(stack, stacked_gauss_newton([todo[i][1] for i in stack])))
        for i, (steps, run) in todo.items():
            advance(i, steps, results[i] if i in results else _gauss_newton(*run))
    return out


def _stackable(run) -> bool:
    P, free, split, stats = run[0], run[8], run[10], run[11]
    return P.shape[1] == 1 and bool(np.all(free)) and split is not None and stats is not None


def _theta(th0, S, z):
    return th0 + S * z


def _bM(theta):
    return theta[:, :3], theta[:, 3:].reshape(-1, 3, 3)


class _Stack:
    """The runs' fixed sums for K = 1 (ResidualStats and reading_moments), stacked."""

    def __init__(self, runs):
        self.n = len(runs)
        self.th0 = np.stack([r[5] for r in runs])
        self.S = np.stack([r[6] for r in runs])
        self.eiv = np.array([float(r[9]) for r in runs])
        ev = [r[10] for r in runs]
        self.EV = np.stack([e[1] for e in ev])
        self.fit = np.stack([e[2] for e in ev]).astype(float)        # 1 fitted, 0 held
        z, a, Gpp, Gpr, M0, E0, W, X, XX, self.mom = [], [], [], [], [], [], [], [], [], []
        for P, x, B, w, theta, th0, S, unpack, free, eiv, split, stats in runs:
            mom = stats.weighted(w)
            th = theta.copy()
            th[~free] = th0[~free]
            z.append((th - th0) / S)
            rs = ResidualStats(P, x, B, w, *unpack(_theta(th0, S, z[-1])), mom)
            a.append(rs.a)
            Gpp.append(rs.Gpp)
            Gpr.append(rs.Gpr)
            M0.append(rs.Mp0[0])
            E0.append(rs.E0[0])
            W.append(mom["W"][0])
            X.append(mom["X"][0])
            XX.append(mom["XX"][0])
            self.mom.append(mom)
        self.z0 = np.stack(z)
        self.a, self.W = np.array(a), np.array(W)
        self.Gpp, self.Gpr = np.stack(Gpp), np.stack(Gpr)
        self.M0, self.E0 = np.stack(M0), np.stack(E0)
        self.X, self.XX = np.stack(X), np.stack(XX)

    def cost_grad(self, k, z, jac=True):
        """ResidualStats.cost_grad for K = 1 of runs k (index array) at z (len(k), 12);
        with jac also normal_matrix (J^T W J)."""
        b, M = _bM(_theta(self.th0[k], self.S[k], z))
        eiv, W = self.eiv[k], self.W[k]
        L = np.concatenate([M - self.M0[k],
                            -(np.einsum("rac,rc->ra", M, b) - self.E0[k])[:, :, None]],
                           axis=2)                                            # (r, 3, 4)
        LG = L @ self.Gpp[k]
        cost = (self.a[k] + 2.0 * np.sum(L * self.Gpr[k].transpose(0, 2, 1), axis=(1, 2))
                + np.sum(LG * L, axis=(1, 2)))
        cost = cost - eiv * W * np.sum(M * M, axis=(1, 2))
        if not jac:
            return cost, None, None
        Gr = self.Gpr[k].transpose(0, 2, 1) + LG                          # (r, 3, 4)
        Ge = Gr[:, :, 3]                                                   # [r, a]
        gM = Gr[:, :, :3] - Ge[:, :, None] * b[:, None, :] - (eiv * W)[:, None, None] * M
        gb = -np.einsum("ra,ral->rl", Ge, M)
        g = np.concatenate([gb, gM.reshape(-1, 9)], axis=1)
        return cost, g, self._normal(k, b, M)

    def _normal(self, k, b, M):
        """normal_matrix for K = 1, stacked."""
        r = len(k)
        W, X, XX, eiv = self.W[k], self.X[k], self.XX[k], self.eiv[k]
        Xb = X[:, :, None] * b[:, None, :]
        A = XX - Xb - Xb.transpose(0, 2, 1) + W[:, None, None] * (b[:, :, None] * b[:, None, :])
        Y = X - W[:, None] * b
        out = np.zeros((r, 12, 12))
        out[:, :3, :3] = W[:, None, None] * np.einsum("ril,rip->rlp", M, M)
        Mb = -(M[:, :, None, :] * Y[:, None, :, None]).reshape(r, 9, 3)    # [a c, l]
        out[:, 3:, :3] = Mb
        out[:, :3, 3:] = Mb.transpose(0, 2, 1)
        MM = out[:, 3:, 3:].reshape(r, 3, 3, 3, 3)
        for i in range(3):
            MM[:, i, :, i, :] = A
        d = np.arange(3, 12)
        out[:, d, d] -= (eiv * W)[:, None]
        return out


def stacked_gauss_newton(runs) -> list:
    """_gauss_newton(*run) for each run (K = 1, all free, split given: _stackable), the
    iterates of all runs stacked (module docstring). Returns [(theta, JTJ, cost, r)]."""
    if not runs:
        return []
    st = _Stack(runs)
    try:
        z = _iterate(st)
    except np.linalg.LinAlgError:       # a singular step: each run on its own, as serially
        return [_gauss_newton(*run) for run in runs]
    out = []
    for i, (P, x, B, w, theta, th0, S, unpack, free, eiv, split, stats) in enumerate(runs):
        out.append(gauss_newton_result(P, x, B, w, _theta(th0, S, z[i]), unpack, eiv,
                                       st.mom[i]))
    return out


def _project(EV, m, v):
    """Vf (Vf^T v) with Vf the columns of EV where m is 1 (stacked)."""
    return np.einsum("rpi,ri->rp", EV, m * np.einsum("rpi,rp->ri", EV, v))


def _iterate(st: _Stack) -> np.ndarray:
    """The stacked iterates (fit.reference._gauss_newton's loop); the runs' last z."""
    L = st.n
    z = st.z0.copy()
    EV, m, S = st.EV, st.fit, st.S
    SS = S[:, :, None] * S[:, None, :]
    active = np.arange(L)
    first = True
    for _ in range(GN_MAX_ITER):
        if not len(active):
            break
        k = active
        cost, g, JTJ = st.cost_grad(k, z[k])
        Ek, mk = EV[k], m[k]
        Jw = JTJ * SS[k]
        evj = np.einsum("rpi,rpq,rqi->ri", Ek, Jw, Ek) * mk
        if first:       # the start's component where the data say nothing: the prior
            z[k] = _project(Ek, mk, z[k])
            cost, g, JTJ = st.cost_grad(k, z[k])
            first = False
            Jw = JTJ * SS[k]
        F = np.einsum("rpi,rpq,rqj->rij", Ek, Jw, Ek)
        F = F * mk[:, :, None] * mk[:, None, :] + np.eye(12) * (1.0 - mk)[:, None, :]
        rhs = mk * np.einsum("rpi,rp->ri", Ek, S[k] * g)
        dz = -np.einsum("rpi,ri->rp", Ek, mk * np.linalg.solve(F, rhs[:, :, None])[:, :, 0])
        # the line search, every pending run at the same step
        z_new = z[k].copy()
        accepted = np.zeros(len(k), bool)
        step = 1.0
        while step > 1e-4 and not accepted.all():
            p = np.nonzero(~accepted)[0]
            zt = z[k[p]] + step * dz[p]
            c_new = st.cost_grad(k[p], zt, jac=False)[0]
            ok = c_new <= cost[p] + 1e-12 * np.abs(cost[p])
            z_new[p[ok]] = zt[ok]
            accepted[p[ok]] = True
            step *= 0.5
        d = mk * np.einsum("rpi,rp->ri", Ek, z_new - z[k])
        done = np.sum(evj * d * d, axis=1) < 1e-10
        z[k[accepted]] = z_new[accepted]
        # a failed line search stops the run where it is; a small step after being taken
        active = k[accepted & ~done]
    return z
