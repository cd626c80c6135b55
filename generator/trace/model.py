"""The float64 model of the extended flight chain for one sensor (the order of
generator.flight.chain.sensor_kernel, see generator.trace.effects), batched over
parameter rows, with its Levenberg-Marquardt fit.

Its parameters are deviations from the baseline (the core fit or a supplied
coefficients.json), in scaled internal units: b and M in all rows of the baseline degree
(M symmetric where only magnitudes are known; M fixed and b0 absorbed by B_p where only
positions are), K where the data drive the coils, B_p per static position, and each
effect's own parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from generator.fit.ellipsoid import sym_from6
from generator.flight.coeffs import CoefficientSet
from generator.trace import effects as fx
from generator.trace.samples import NORM, POS, VEC, SensorSamples

M_UNIT = 1e-4             # internal unit of M deviations (~5 nT at 50 uT)
FD_STEP = 1e-3            # finite-difference step, internal units (~1e-3 nT)
BATCH_ELEMENTS = 400_000  # batch x samples per model evaluation (memory)


@dataclass
class BaseFit:
    """The baseline's structure and values for one sensor (physical units)."""
    name: str
    degree: int
    t_ref_C: float
    t_min_C: float
    t_max_C: float
    b_poly: np.ndarray            # (degree+1, 3)
    M_poly: np.ndarray            # (degree+1, 3, 3)
    K: np.ndarray | None          # (3, ncoil)
    H: np.ndarray                 # (3, 3) boom -> body

    @property
    def t_scale_C(self) -> float:
        return max(abs(self.t_min_C - self.t_ref_C), abs(self.t_max_C - self.t_ref_C), 1.0)


def base_from_coefficients(cs: CoefficientSet, name: str, degree: int | None = None) -> BaseFit:
    v = cs.sensors[name]
    b = np.asarray(v["b_poly_nT"], float)
    M = np.asarray(v["M_poly"], float)
    if degree is None:
        degree = declared_degree(cs, name)
    degree = int(min(degree, b.shape[0] - 1))
    K = np.asarray(v["K_nT_per_A"], float) if "K_nT_per_A" in v else None
    H = np.asarray(cs.unit_values.get("H_boom_to_body", np.eye(3)), float)
    # a sensor with no temperature: constant, every temperature clamped to dT = 0
    t_ref, t_lo, t_hi = (float(v["t_ref_C"]), float(v["t_min_C"]), float(v["t_max_C"])) \
        if "t_ref_C" in v else (0.0, 0.0, 0.0)
    return BaseFit(name, degree, t_ref, t_lo, t_hi,
                   b[:degree + 1].copy(), M[:degree + 1].copy(), K, H)


def declared_degree(cs: CoefficientSet, name: str) -> int:
    """The degree a sensor's fit used (fit stats), else its highest non-zero row."""
    st = cs.fit_info.get("sensors", {}).get(name, {}).get("stats", {}) or {}
    if isinstance(st.get("degree"), int):
        return st["degree"]
    v = cs.sensors[name]
    b = np.asarray(v["b_poly_nT"])
    M = np.asarray(v["M_poly"])
    nz = [k for k in range(b.shape[0]) if np.any(b[k] != 0) or np.any(M[k] != 0)]
    return max([0] + [k for k in nz])


def _solve_psd(A, b):
    """Solve A x = b for a symmetric positive (semi-)definite A: Cholesky, else the
    eigen-decomposition with the null space dropped."""
    try:
        L = np.linalg.cholesky(A)
        return np.linalg.solve(L.T, np.linalg.solve(L, b))
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(A)
        keep = w > (w[-1] * 1e-13 if len(w) and w[-1] > 0 else np.inf)
        return V[:, keep] @ ((V[:, keep].T @ b) / w[keep])


def _as_slice(ix):
    """A sorted index array as a slice where it is a contiguous range (a view, no copy)."""
    ix = np.asarray(ix)
    if len(ix) and ix[-1] - ix[0] == len(ix) - 1:
        return slice(int(ix[0]), int(ix[-1]) + 1)
    return ix


def _mv(M, v):
    """Per-sample matrix times vector: (n, 3, 3) x (n, 3) -> (n, 3), as three broadcast
    products (numpy's einsum of this shape does not use BLAS and is slower)."""
    return M[:, :, 0] * v[:, 0, None] + M[:, :, 1] * v[:, 1, None] + M[:, :, 2] * v[:, 2, None]


class SensorModel:
    """B_cal of one sensor from the extended chain, float64, batched over parameters.

    theta: internal parameters, deviations from the baseline: b rows (nT at the edge of
    the temperature range), M rows (M_UNIT), K (nT at the rms current), B_p (nT), then
    each effect's parameters (see generator.trace.effects)."""

    def __init__(self, base: BaseFit, *, free_b, free_M, free_K, groups, Bp0, i_rms=1.0,
                 effects=(), theta=None):
        self.base = base
        self.free_b = list(free_b)            # rows of b that are free
        self.free_M = free_M                  # "full" | "sym" | None
        self.free_K = bool(free_K) and base.K is not None
        self.groups = np.asarray(groups, np.int64)
        self.Bp0 = np.asarray(Bp0, float).reshape(-1, 3)
        self.i_rms = float(i_rms)
        self.effects = list(effects)
        D = base.degree
        sc = base.t_scale_C ** np.arange(D + 1)
        self.b_scaled = base.b_poly * sc[:, None]
        self.M_scaled = base.M_poly * sc[:, None, None]
        sizes = [("b", 3 * len(self.free_b)),
                 ("M", {"full": 9, "sym": 6, None: 0}[free_M] * (D + 1)),
                 ("K", base.K.size if self.free_K else 0),
                 ("Bp", 3 * len(self.groups))]
        sizes += [(f"e{i}", e.n_params) for i, e in enumerate(self.effects)]
        self.sl, k = {}, 0
        for name, size in sizes:
            self.sl[name] = slice(k, k + size)
            k += size
        self.P = k
        self.theta = np.zeros(k) if theta is None else np.asarray(theta, float).copy()
        assert self.theta.shape == (k,), (self.theta.shape, k)

    # ---- structure -------------------------------------------------------------------
    @staticmethod
    def for_samples(base: BaseFit, S: SensorSamples, effects=(), params=()):
        """The model whose free blocks the samples determine, B_p at the group means."""
        kinds = S.kinds_present()
        if VEC in kinds:
            free_b, free_M = list(range(base.degree + 1)), "full"
        elif NORM in kinds:
            free_b, free_M = list(range(base.degree + 1)), "sym"
        else:
            free_b, free_M = list(range(1, base.degree + 1)), None
        free_K = base.K is not None and S.coil is not None and np.any(S.coil != 0)
        i_rms = float(np.sqrt(np.mean(S.coil ** 2))) if free_K else 1.0
        groups = np.unique(S.group[S.kind == POS])
        m = SensorModel(base, free_b=free_b, free_M=free_M, free_K=free_K, groups=groups,
                        Bp0=np.zeros((len(groups), 3)), i_rms=max(i_rms, 1e-9))
        for e, p in zip(effects, params):
            m = m.with_effect(e, p)
        if len(groups):
            B = m.field(S)
            ip = S.kind == POS
            m.Bp0 = np.array([B[ip & (S.group == g)].mean(axis=0) for g in groups])
        return m

    def with_effect(self, effect, p0) -> "SensorModel":
        return SensorModel(self.base, free_b=self.free_b, free_M=self.free_M,
                           free_K=self.free_K, groups=self.groups, Bp0=self.Bp0,
                           i_rms=self.i_rms, effects=self.effects + [effect],
                           theta=np.concatenate([self.theta, np.asarray(p0, float)]))

    def copy(self) -> "SensorModel":
        return SensorModel(self.base, free_b=self.free_b, free_M=self.free_M,
                           free_K=self.free_K, groups=self.groups, Bp0=self.Bp0,
                           i_rms=self.i_rms, effects=list(self.effects), theta=self.theta)

    @property
    def degree(self) -> int:
        extra = [e.degree for e in self.effects if isinstance(e, fx.TemperaturePolynomial)]
        return max([self.base.degree] + extra)

    @property
    def t_scale_C(self) -> float:
        return self.base.t_scale_C

    def effect_params(self, i, theta=None):
        th = self.theta if theta is None else theta
        return th[self.sl[f"e{i}"]]

    # ---- evaluation --------------------------------------------------------------------
    def evaluate(self, th, S: SensorSamples):
        """B_cal (Bt, n, 3) and the reference shift (Bt, n, 3) or None, for parameter
        rows th (Bt, P), in the chain's order."""
        f = self._forward(th, S)
        return f["B_out"], f["shift"]

    def _forward(self, th, S: SensorSamples) -> dict:
        """The chain's intermediates (for one parameter row: powers of the scaled
        temperature, the reading after offsets and transforms x_final (n, 3), Msum =
        sum_k s^k M_k (n, 3, 3), B before a calibrated stage) and its outputs."""
        th = np.atleast_2d(th)
        Bt = th.shape[0]
        base = self.base
        D = base.degree
        T = S.temp_C[None, :]
        for i, e in enumerate(self.effects):
            if e.stage == "temperature":
                T = e.temperature(th[:, self.sl[f"e{i}"]], S, S.temp_C)
        Tc = np.clip(T, base.t_min_C, base.t_max_C)
        s = (Tc - base.t_ref_C) / base.t_scale_C
        st = SimpleNamespace(T=Tc, s=s)
        powers = [np.ones_like(s)]
        for _ in range(D):
            powers.append(powers[-1] * s)
        b_s = np.broadcast_to(self.b_scaled, (Bt, D + 1, 3)).copy()
        if self.free_b:
            b_s[:, self.free_b, :] += th[:, self.sl["b"]].reshape(Bt, len(self.free_b), 3)
        x = S.x[None, :, :] - sum(powers[k][:, :, None] * b_s[:, k, None, :]
                                  for k in range(D + 1))
        if base.K is not None and S.coil is not None:
            K = np.broadcast_to(base.K, (Bt,) + base.K.shape)
            if self.free_K:
                K = K + th[:, self.sl["K"]].reshape((Bt,) + base.K.shape) / self.i_rms
            x = x - np.matmul(S.coil, np.transpose(K, (0, 2, 1)))
        x = np.broadcast_to(x, (Bt, S.n, 3))
        for i, e in enumerate(self.effects):
            if e.stage == "offset":
                x = x - e.offset(th[:, self.sl[f"e{i}"]], S, st)
        for i, e in sorted(enumerate(self.effects), key=lambda ie: ie[1].order):
            if e.stage == "transform":
                x = e.transform(th[:, self.sl[f"e{i}"]], S, x, st)
        M_s = np.broadcast_to(self.M_scaled, (Bt, D + 1, 3, 3))
        if self.free_M == "full":
            M_s = M_s + M_UNIT * th[:, self.sl["M"]].reshape(Bt, D + 1, 3, 3)
        elif self.free_M == "sym":
            M_s = M_s + M_UNIT * sym_from6(th[:, self.sl["M"]].reshape(Bt, D + 1, 6))
        B = sum(powers[k][:, :, None] * np.matmul(x, np.transpose(M_s[:, k], (0, 2, 1)))
                for k in range(D + 1))
        out = {}
        if Bt == 1:
            out = {"powers": [p[0] for p in powers], "x_final": x[0], "B": B[0], "st": st,
                   "M_s": M_s,
                   "Msum": sum(powers[k][0][:, None, None] * M_s[0, k][None]
                               for k in range(D + 1))}
        for i, e in enumerate(self.effects):
            if e.stage == "calibrated":
                B = e.calibrated(th[:, self.sl[f"e{i}"]], S, B, st)
        shift = None
        for i, e in enumerate(self.effects):
            if e.stage == "reference":
                d = e.reference_shift(th[:, self.sl[f"e{i}"]], S)
                shift = d if shift is None else shift + d
        out["B_out"], out["shift"] = B, shift
        return out

    def field(self, S, theta=None) -> np.ndarray:
        """B_cal (n, 3) at theta (default: the fitted parameters)."""
        th = self.theta if theta is None else theta
        return self.evaluate(th[None], S)[0][0]

    def residual(self, th, S: SensorSamples) -> np.ndarray:
        """Residual rows (Bt, R): vector rows, magnitude rows, position rows."""
        th = np.atleast_2d(th)
        f = self._forward(th, S)
        return self._residual_rows(th, S, f["B_out"], f["shift"])

    def _residual_rows(self, th, S, B, shift) -> np.ndarray:
        Bt = th.shape[0]
        iv, im, ip = S.idx
        parts = []
        if len(iv):
            ref = S.ref[iv][None]
            if shift is not None:
                ref = ref + shift[:, iv]
            parts.append((B[:, iv] - ref).reshape(Bt, -1))
        if len(im):
            parts.append(np.linalg.norm(B[:, im], axis=2) - S.norm[im][None])
        if len(ip):
            g = S.group[ip]
            k = np.searchsorted(self.groups, g)
            k = np.minimum(k, max(len(self.groups) - 1, 0))
            known = (self.groups[k] == g) if len(self.groups) else np.zeros(len(g), bool)
            target = np.empty((Bt, len(ip), 3))
            if known.any():
                Bp = th[:, self.sl["Bp"]].reshape(Bt, -1, 3) + self.Bp0[None]
                target[:, known] = Bp[:, k[known]]
            for gg in np.unique(g[~known]):      # an unseen position: its own mean
                sel = g == gg
                target[:, sel] = B[:, ip[sel]].mean(axis=1, keepdims=True)
            parts.append((B[:, ip] - target).reshape(Bt, -1))
        return np.concatenate(parts, axis=1) if parts else np.zeros((Bt, 0))

    def jacobian(self, S, theta=None, cols=None):
        """(r (R,), J (R, len(cols))) at theta: the linear blocks (b, M, K, B_p)
        analytically where the chain allows it (see _analytic_columns), the rest by
        forward differences."""
        th0 = self.theta if theta is None else np.asarray(theta, float)
        cols = np.arange(self.P) if cols is None else np.asarray(cols)
        lin = self._linearisation(th0, S)
        R = len(lin["r0"]) if lin is not None else S.n_rows
        J = np.empty((R, len(cols)), order="F")      # filled column by column
        r0, done = self._analytic_into(th0, S, cols, J, lin)
        fd = [k for k, c in enumerate(cols) if int(c) not in done]
        if fd:
            J[:, fd] = self._fd_columns(th0, S, cols[fd], r0)
        return r0, J

    def _fd_columns(self, th0, S, cols, r0):
        J = np.empty((len(r0), len(cols)))
        chunk = max(1, BATCH_ELEMENTS // max(S.n, 1))
        for a in range(0, len(cols), chunk):
            sub = cols[a:a + chunk]
            th = np.repeat(th0[None], len(sub), axis=0)
            th[np.arange(len(sub)), sub] += FD_STEP
            J[:, a:a + len(sub)] = (self.residual(th, S) - r0[None]).T / FD_STEP
        return J

    def _analytic_into(self, th0, S, cols, J, lin):
        """(r0, {column: dr/dtheta_column}) for the columns that have a closed form.

        B = sum_k s^k M_k x'' with x'' the reading after offsets and transforms, so
        dB/dM_k = s^k x'' exactly; where no transform stage follows the offsets,
        x' = x - sum_k s^k b_k - K i - offsets gives dB/db_k = -s^k Msum,
        dB/dK = -Msum i / i_rms (Msum = sum_k s^k M_k) and, for an effect of the offset
        stage (linear in its parameters), dB/dp_a = -Msum offset(e_a). A thermal lag
        (stage temperature, its parameter log(tau / hyper)): dB/dp = dB/ds ds/dT_el
        dT_el/dp, dT_el/dtau by the recursion of effects.lag_filter_dtau, dB/ds =
        M'(s) x' - Msum (b'(s) + d offsets/ds), zero where the temperature is clamped. A
        `calibrated` stage after M that is linear in B (set_reset_rotation:
        B + c w x B) maps every column through its own derivative and gives its
        parameter's column (calibrated_columns); another calibrated stage, or a static
        position not among the model's groups, leaves everything to finite differences.
        Magnitude rows: d|B| = (B / |B|) . dB."""
        want = set(int(c) for c in cols)
        if lin is None or not want:
            return (lin["r0"] if lin is not None else self.residual(th0[None], S)[0]), set()
        pos = {int(c): k for k, c in enumerate(cols)}
        done = set()

        def add(c, dB, skip=None):
            if c in want:
                lin["rows_into"](J[:, pos[c]], dB, skip)
                done.add(c)

        D = self.base.degree
        s_pow, xpp, Msum = lin["powers"], lin["xpp"], lin["Msum"]
        stages = lin["stages"]
        n = S.n
        sl = self.sl["M"]
        if self.free_M is not None and want & set(range(sl.start, sl.stop)):
            if self.free_M == "full":
                basis = np.eye(9).reshape(9, 3, 3)
            else:
                basis = sym_from6(np.eye(6))
            nb_ = len(basis)
            for k in range(D + 1):
                sx = M_UNIT * s_pow[k][:, None] * xpp                # (n, 3)
                for a_ in range(nb_):
                    c = sl.start + k * nb_ + a_
                    if c in want:
                        add(c, sx @ basis[a_].T)
        if "transform" not in stages:
            sl = self.sl["b"]
            for fi, k in enumerate(self.free_b):
                for j in range(3):
                    if sl.start + 3 * fi + j in want:
                        add(sl.start + 3 * fi + j, -s_pow[k][:, None] * Msum[:, :, j])
            if self.free_K and S.coil is not None and \
                    want & set(range(self.sl["K"].start, self.sl["K"].stop)):
                sl = self.sl["K"]
                nc = self.base.K.shape[1]
                for a_ in range(3):
                    for ci in range(nc):
                        add(sl.start + a_ * nc + ci,
                            -Msum[:, :, a_] * (S.coil[:, ci] / self.i_rms)[:, None])
            for i, e in enumerate(self.effects):
                sl = self.sl[f"e{i}"]
                if not want & set(range(sl.start, sl.stop)):
                    continue
                if e.stage == "offset" and e.linear_offset and e.n_params:
                    dx = np.asarray(e.offset(np.eye(e.n_params), S, lin["st"]), float)
                    dx = np.broadcast_to(dx, (e.n_params, n, 3))
                    for a_ in range(e.n_params):
                        add(sl.start + a_, -_mv(Msum, dx[a_]))
                elif e.stage == "temperature" and hasattr(e, "temperature_jacobian"):
                    dT = e.temperature_jacobian(th0[sl], S)            # (n_params, n)
                    dBds = self._dB_ds(th0, S, lin)
                    for a_ in range(e.n_params):
                        add(sl.start + a_, dBds * (dT[a_] / self.base.t_scale_C)[:, None])
        for i, e in enumerate(self.effects):
            sl = self.sl[f"e{i}"]
            if e.stage == "calibrated" and want & set(range(sl.start, sl.stop)):
                own = e.calibrated_columns(th0[sl][None], S, lin["B"])   # (n_params, n, 3)
                for a_ in range(e.n_params):
                    add(sl.start + a_, own[a_], skip=i)
        sl = self.sl["Bp"]
        iv, im, ip = S.idx
        if len(ip) and want & set(range(sl.start, sl.stop)):
            k_of = np.searchsorted(self.groups, S.group[ip])
            base_row = 3 * len(iv) + len(im)
            for gi in range(len(self.groups)):
                sel = np.nonzero(k_of == gi)[0]
                for j in range(3):
                    c = sl.start + 3 * gi + j
                    if c in want:
                        col = J[:, pos[c]]
                        col[:] = 0.0
                        col[base_row + 3 * sel + j] = -1.0
                        done.add(c)
        return lin["r0"], done

    def _analytic_columns(self, th0, S, cols):
        """(r0, {column: dr/dtheta_column}) of the columns _analytic_into fills (the
        docstring there)."""
        cols = np.asarray(cols)
        lin = self._linearisation(th0, S)
        R = len(lin["r0"]) if lin is not None else S.n_rows
        J = np.empty((R, len(cols)))
        r0, done = self._analytic_into(th0, S, cols, J, lin)
        return r0, {int(c): J[:, k].copy() for k, c in enumerate(cols) if int(c) in done}

    def _linearisation(self, th0, S):
        """The forward pass at th0 and what the analytic columns need (cached for the
        last (S, theta)): None where the chain has a stage without a closed form."""
        key = (id(S), S.n, th0.tobytes(), tuple(repr(getattr(e, "hyper", None))
                                                 for e in self.effects))
        cache = getattr(self, "_lin_cache", None)
        if cache is not None and cache[0] == key:
            return cache[1]
        stages = {e.stage for e in self.effects}
        cal = [(i, e) for i, e in enumerate(self.effects) if e.stage == "calibrated"]
        iv, im, ip = S.idx
        ok = all(hasattr(e, "calibrated_jvp") for _, e in cal)
        if ok and len(ip):
            g = S.group[ip]
            ok = bool(len(self.groups)) and bool(np.isin(g, self.groups).all())
        if not ok:
            return None
        f = self._forward(th0[None], S)
        r0 = self._residual_rows(th0[None], S, f["B_out"], f["shift"])[0]
        B_out = f["B_out"][0]
        u = None
        if len(im):
            nb = np.linalg.norm(B_out[im], axis=1)
            u = B_out[im] / np.where(nb > 0, nb, 1.0)[:, None]
        ps = [(i, th0[self.sl[f"e{i}"]][None]) for i, _ in cal]

        def rows(dB, skip=None):
            """(n, 3, C) field changes before the calibrated stages -> (R, C) rows
            (skip: the calibrated stage whose own column dB already is, after it)."""
            for i, p in ps:
                if skip is not None and i <= skip:
                    continue
                dB = self.effects[i].calibrated_jvp(p, S, dB)
            parts = []
            if len(iv):
                parts.append(dB[iv].reshape(-1, dB.shape[2]))
            if len(im):
                dm = dB[im]
                parts.append(u[:, 0, None] * dm[:, 0] + u[:, 1, None] * dm[:, 1]
                             + u[:, 2, None] * dm[:, 2])
            if len(ip):
                parts.append(dB[ip].reshape(-1, dB.shape[2]))
            return np.concatenate(parts) if parts else np.zeros((0, dB.shape[2]))

        nv, nm = len(iv), len(im)
        sv = _as_slice(iv)
        sm = _as_slice(im)
        sp = _as_slice(ip)

        def rows_into(col, dB, skip=None):
            """One column: the field change dB (n, 3) before the calibrated stages into
            the residual rows col (R,), no intermediate copies."""
            if ps:
                dB = dB[:, :, None]
                for i, p in ps:
                    if skip is None or i > skip:
                        dB = self.effects[i].calibrated_jvp(p, S, dB)
                dB = dB[:, :, 0]
            if nv:
                col[:3 * nv].reshape(nv, 3)[:] = dB[sv]
            if nm:
                dm = dB[sm]
                np.multiply(u[:, 0], dm[:, 0], out=col[3 * nv:3 * nv + nm])
                col[3 * nv:3 * nv + nm] += u[:, 1] * dm[:, 1]
                col[3 * nv:3 * nv + nm] += u[:, 2] * dm[:, 2]
            if len(ip):
                col[3 * nv + nm:].reshape(len(ip), 3)[:] = dB[sp]

        lin = {"r0": r0, "powers": f["powers"], "xpp": f["x_final"], "Msum": f["Msum"],
               "B": f["B"], "st": f["st"], "stages": stages, "rows": rows,
               "rows_into": rows_into,
               "M_s": f.get("M_s"), "x_off": f.get("x_off")}
        self._lin_cache = (key, lin)
        return lin

    def offset_columns(self, S, e):
        """The Jacobian columns (R, n_params) of a candidate effect e of the offset stage
        (linear in its parameters, zero at zero) added to this model at its fit, from this
        model's own linearisation (the candidate's forward pass is this one); None where
        they have no closed form here."""
        if not (e.stage == "offset" and e.linear_offset and e.n_params):
            return None
        lin = self._linearisation(self.theta, S)
        if lin is None or "transform" in lin["stages"]:
            return None
        dx = np.asarray(e.offset(np.eye(e.n_params), S, lin["st"]), float)
        dx = np.broadcast_to(dx, (e.n_params, S.n, 3))
        dB = np.stack([-_mv(lin["Msum"], dx[a]) for a in range(e.n_params)], axis=2)
        return lin["rows"](dB)

    def _dB_ds(self, th0, S, lin):
        """dB/ds (n, 3) at th0 before the calibrated stages, no transform stage: M'(s) x'
        - Msum (b'(s) + d offsets / ds) (offsets that depend on s by central differences,
        exact for their polynomials to round-off), zero where T is clamped."""
        D = self.base.degree
        s_pow, xpp, Msum, st = lin["powers"], lin["xpp"], lin["Msum"], lin["st"]
        Bt1 = th0[None]
        M_s = lin["M_s"][0]                                   # (D+1, 3, 3)
        b_s = self.b_scaled.copy()
        if self.free_b:
            b_s[self.free_b] += th0[self.sl["b"]].reshape(len(self.free_b), 3)
        dB = np.zeros((S.n, 3))
        db = np.zeros((S.n, 3))
        for k in range(1, D + 1):
            dB += k * s_pow[k - 1][:, None] * (xpp @ M_s[k].T)
            db += k * s_pow[k - 1][:, None] * b_s[k][None]
        h = 1e-4
        for i, e in enumerate(self.effects):
            if e.stage != "offset":
                continue
            p = Bt1[:, self.sl[f"e{i}"]]
            s0 = st.s
            up = type(st)(T=st.T, s=s0 + h)
            dn = type(st)(T=st.T, s=s0 - h)
            d = (np.asarray(e.offset(p, S, up), float) - np.asarray(e.offset(p, S, dn), float))
            if np.any(d):
                db += np.broadcast_to(d, (1, S.n, 3))[0] / (2 * h)
        dB -= _mv(Msum, db)
        inside = (st.T[0] > self.base.t_min_C) & (st.T[0] < self.base.t_max_C)
        return dB * inside[:, None]

    def fit(self, S, max_nfev=60) -> "SensorModel":
        """Least squares over all free parameters by Levenberg-Marquardt on the normal
        equations (column-scaled J^T J + lambda I; BLAS products instead of MINPACK's
        unblocked QR of the tall Jacobian: the model is linear or nearly so in every
        block, so a few Gauss-Newton steps converge). More parameters than rows: scipy's
        trust-region solver."""
        if self.P == 0:
            return self
        if S.n_rows <= self.P:
            fun = lambda th: self.residual(th[None], S)[0]          # noqa: E731
            jac = lambda th: self.jacobian(S, th)[1]                 # noqa: E731
            from scipy.optimize import least_squares
            self.theta = least_squares(fun, self.theta, jac=jac, method="trf", xtol=1e-10,
                                       ftol=1e-12, gtol=1e-12, max_nfev=max_nfev).x
            return self
        th = self.theta.copy()
        r, J = self.jacobian(S, th)
        eiv = self._regressor_noise(S)    # (P,) errors in variables taken out (TimeOffset)
        sse = float(r @ r) - float(eiv @ (th * th))
        lam, nfev = 1e-6, 1
        while nfev < max_nfev:
            A, g = J.T @ J, J.T @ r
            if np.any(eiv):   # SSE - sum_k N_k p_k^2: its gradient, and its curvature
                g = g - eiv * th                 # where J^T J stays positive
                A2 = A - np.diag(eiv)
                if np.all(np.diag(A2)[eiv > 0] > 0):
                    A = A2
            d = np.sqrt(np.maximum(np.diag(A), 0.0))
            d[d == 0] = 1.0
            As, gs = A / np.outer(d, d), g / d
            accepted = False
            while nfev < max_nfev:
                step = -_solve_psd(As + lam * np.eye(len(d)), gs) / d
                r_new = self.residual((th + step)[None], S)[0]
                nfev += 1
                sse_new = float(r_new @ r_new) - float(eiv @ ((th + step) ** 2))
                if sse_new <= sse:
                    accepted = True
                    break
                lam *= 10.0
                if lam > 1e12:
                    break
            if not accepted:
                break
            gain = sse - sse_new
            th, sse = th + step, sse_new
            lam = max(lam / 10.0, 1e-12)
            if gain <= 1e-12 * max(sse, 1e-300) or np.max(np.abs(step * d)) <= 1e-10 * (
                    1.0 + np.max(np.abs(th * d))):
                break
            r, J = self.jacobian(S, th)
        self.theta = th
        return self

    def _regressor_noise(self, S) -> np.ndarray:
        """(P,): N_k, the white noise's expected share of sum_rows (dr/dtheta_k)^2 for the
        parameters of effects whose regressor is a noisy measurement
        (Effect.regressor_noise); the fit minimises SSE - sum_k N_k theta_k^2, whose
        expectation is the SSE of a noise-free regressor (no attenuation of theta_k).
        Zeros for the rest."""
        out = np.zeros(self.P)
        for i, e in enumerate(self.effects):
            v = e.regressor_noise(S)
            if v is not None:
                out[self.sl[f"e{i}"]] = v
        return out

    def sse(self, S) -> float:
        r = self.residual(self.theta[None], S)[0]
        return float(r @ r)

    def rms(self, S) -> float:
        r = self.residual(self.theta[None], S)[0]
        return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")

    # ---- physical values ---------------------------------------------------------------
    def values(self) -> dict:
        """b_poly_nT, M_poly (degree of the base), K_nT_per_A (or None): physical."""
        D = self.base.degree
        sc = self.base.t_scale_C ** np.arange(D + 1)
        b = self.b_scaled.copy()
        th = self.theta
        if self.free_b:
            b[self.free_b] += th[self.sl["b"]].reshape(len(self.free_b), 3)
        M = self.M_scaled.copy()
        if self.free_M == "full":
            M = M + M_UNIT * th[self.sl["M"]].reshape(D + 1, 3, 3)
        elif self.free_M == "sym":
            M = M + M_UNIT * sym_from6(th[self.sl["M"]].reshape(D + 1, 6))
        K = self.base.K
        if self.free_K:
            K = K + th[self.sl["K"]].reshape(K.shape) / self.i_rms
        return {"b_poly_nT": b / sc[:, None], "M_poly": M / sc[:, None, None],
                "K_nT_per_A": None if K is None else np.array(K)}
