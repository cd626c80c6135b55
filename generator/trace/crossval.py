"""Blocked cross-validation in time of a linearised model: least squares of
r0 (+ d0) + J d + G beta per training fold from the full normal equations minus the
held-out rows' (no copies of the training rows), and the held-out residual of each block.
"""

from __future__ import annotations

import numpy as np

from generator.trace.samples import SensorSamples


class LinearSolver:
    """Least squares min |y + J d + G beta| over d (J: the current model's Jacobian on
    some rows) and beta (G: a candidate's columns), by normal equations with column
    scaling (only products of tall matrices and eigen-decompositions of small ones)."""

    def __init__(self, J):
        self.J = J
        P = J.shape[1]
        if P == 0:
            self.Ginv = np.zeros((0, 0))
            return
        self.Ginv = _pinv_gram(J.T @ J)

    def fit(self, y, G=None):
        """(residual, beta or None, d): the least-squares residual on these rows."""
        J = self.J
        d_y = -self.Ginv @ (J.T @ y) if J.shape[1] else np.zeros(0)
        ry = y + J @ d_y if J.shape[1] else y.copy()
        if G is None or G.shape[1] == 0:
            return ry, None, d_y
        if J.shape[1]:
            d_G = -self.Ginv @ (J.T @ G)
            rG = G + J @ d_G
        else:
            d_G = np.zeros((0, G.shape[1]))
            rG = G
        beta = -_pinv_gram(rG.T @ rG) @ (rG.T @ ry)
        return ry + rG @ beta, beta, d_y + d_G @ beta


def _pinv_gram(A, rcond=1e-13):
    """Pseudo-inverse of a symmetric positive semi-definite Gram matrix (scaled eigh)."""
    d = np.sqrt(np.maximum(np.diag(A), 0))
    d[d == 0] = 1.0
    As = A / np.outer(d, d)
    try:   # the common, well-conditioned case: Cholesky (fast), checked
        L = np.linalg.cholesky(As)
        dg = np.diag(L)
        if dg.min() > 0 and (dg.max() / dg.min()) ** 2 < 1e8:
            Li = np.linalg.inv(L)
            return (Li.T @ Li) / np.outer(d, d)
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(As)
    keep = w > (w[-1] * rcond if len(w) and w[-1] > 0 else np.inf)
    inv = (V[:, keep] / w[keep]) @ V[:, keep].T
    return inv / np.outer(d, d)


class CVEngine:
    """The linearised fit of r0 (+ d0) + J d + G beta per training fold, and the held-out
    residual of each block. Training-fold normal equations come from the full ones minus
    the held-out rows' (no copies of the training rows), solved by block elimination with
    the pseudo-inverse of the training J^T J."""

    FREEZE_RATIO = 10.0   # a parameter whose variance grows more than this when a fold
    #                       is held out is held at its fit in every fold

    def __init__(self, r0, J, row_block, fold_of_block, n_blocks):
        self.r0 = r0
        self.row_block = row_block
        self.fold_of_block = fold_of_block
        self.n_blocks = n_blocks
        fold_of_row = fold_of_block[row_block]
        tests = [np.nonzero(fold_of_row == f)[0] for f in range(int(fold_of_block.max()) + 1)]
        tests = [te for te in tests if len(te)]
        # Parameters that one fold alone determines (the coupling of a coil whose steps
        # all lie in one block, say) would be refitted to noise when that fold is held
        # out, and their held-out error would swamp every comparison: keep them at the
        # fit of all the data in every fold (the candidate's own columns always refit).
        self.frozen = np.zeros(J.shape[1], bool)
        if J.shape[1]:
            JJ = J.T @ J
            var_full = np.diag(_pinv_gram(JJ))
            for te in tests:
                var_f = np.diag(_pinv_gram(JJ - J[te].T @ J[te]))
                with np.errstate(divide="ignore", invalid="ignore"):
                    self.frozen |= ~(var_f <= self.FREEZE_RATIO * var_full)
            self.frozen &= var_full > 0
        J = J[:, ~self.frozen]
        self.J = J
        self.JJ = J.T @ J
        self.Ainv_full = _pinv_gram(self.JJ) if J.shape[1] else np.zeros((0, 0))
        # the rows fold after fold, contiguous: each fold's rows are a slice (a view)
        self.perm = np.concatenate(tests) if tests else np.zeros(0, int)
        self.Jp = J[self.perm]
        self.folds, self.slices = [], []
        a = 0
        for te in tests:
            sl = slice(a, a + len(te))
            a += len(te)
            Jte = self.Jp[sl]
            Ainv = _pinv_gram(self.JJ - Jte.T @ Jte) if J.shape[1] else np.zeros((0, 0))
            self.folds.append((te, Jte, row_block[te], Ainv))
            self.slices.append(sl)

    @staticmethod
    def _solve(Ainv, yy, Jy, G_parts):
        """min |y + J d + G beta|^2 from normal-equation pieces: (SSE, d, beta)."""
        d_y = -Ainv @ Jy
        if G_parts is None:
            return yy + d_y @ Jy, d_y, None
        JG, GG, Gy = G_parts
        AJG = Ainv @ JG
        S = GG - JG.T @ AJG                        # Schur complement (k x k)
        rhs = Gy - JG.T @ (Ainv @ Jy)
        beta = -_pinv_gram(S) @ rhs
        d = d_y - AJG @ beta
        sse = yy + d @ Jy + beta @ Gy
        return max(sse, 0.0), d, beta

    def _y_pieces(self, y):
        """(y permuted fold after fold, per-fold [y.y, J^T y]); those of r0 are kept (most
        candidates leave the residual where it is: d0 = None)."""
        if y is self.r0 and getattr(self, "_r0_pieces", None) is not None:
            return self._r0_pieces
        yp = y[self.perm]
        pieces = [[float(yp[sl] @ yp[sl]), Jte.T @ yp[sl]]
                  for sl, (_, Jte, _, _) in zip(self.slices, self.folds)]
        if y is self.r0:
            self._r0_pieces = (yp, pieces)
        return yp, pieces

    def evaluate(self, d0=None, G=None, bound=None):
        """Train SSE per fold (K,), held-out SSE per block (B,), full-data SSE and the
        held-out residual of every row (R,: each row is held out in exactly one fold),
        for the model with offset d0 (R,) and columns G (R, k). The normal-equation
        pieces are formed once per fold (on the fold's contiguous rows) and summed for
        the whole; a training fold's are the whole's minus its own. bound (K,): the
        held-out rows (and their blocks) only of the folds whose train SSE falls below
        it (a scan keeps the best per fold; the other rows are left NaN)."""
        y = self.r0 if d0 is None else self.r0 + d0
        yp, ypieces = self._y_pieces(y)
        Gp = None if G is None else np.ascontiguousarray(G[self.perm])
        pieces = []
        for sl, (_, Jte, _, _), yc in zip(self.slices, self.folds, ypieces):
            pc = list(yc)
            if Gp is not None:
                Gf = Gp[sl]
                pc += [Jte.T @ Gf, Gf.T @ Gf, Gf.T @ yp[sl]]
            pieces.append(pc)
        return self._finish(y, yp, pieces, (lambda sl: Gp[sl]) if Gp is not None else None,
                            G, bound)

    def step_scan(self, G, key, thresholds, bound_update):
        """evaluate(None, G * (key >= t)) for every t of the ascending thresholds, from
        sufficient statistics: each fold's rows are cut into the intervals between the
        thresholds, the products J^T G, G^T G, G^T y are formed once per interval and
        summed from the top (a row counts for every threshold at or below its key), so
        the scan costs about one evaluation instead of one per threshold. Per threshold
        j, bound_update(j, train, full, heldout) gets the evaluate() results and
        returns the bound for the next (the held-out rows are formed only for the folds
        whose train SSE falls below it, as evaluate's bound)."""
        thr = np.asarray(thresholds)
        H = len(thr)
        yp, ypieces = self._y_pieces(self.r0)
        Gp = np.ascontiguousarray(G[self.perm])
        qp = np.searchsorted(thr, np.asarray(key)[self.perm], side="right")   # rows count
        per_fold = []                                                          # for j < q
        for sl, (_, Jte, _, _) in zip(self.slices, self.folds):
            q = qp[sl]
            Gf, yf = Gp[sl], yp[sl]
            k = G.shape[1]
            JG = np.zeros((H + 1, Jte.shape[1], k))
            GG = np.zeros((H + 1, k, k))
            Gy = np.zeros((H + 1, k))
            order = np.argsort(q, kind="stable")
            cuts = np.searchsorted(q[order], np.arange(H + 2))
            for g in range(1, H + 1):
                rows = order[cuts[g]:cuts[g + 1]]
                if len(rows):
                    Jr, Gr = Jte[rows], Gf[rows]
                    JG[g], GG[g], Gy[g] = Jr.T @ Gr, Gr.T @ Gr, Gr.T @ yf[rows]
            # threshold j takes the intervals g > j: sums from the top
            per_fold.append((np.cumsum(JG[::-1], axis=0)[::-1], np.cumsum(GG[::-1], axis=0)[::-1],
                             np.cumsum(Gy[::-1], axis=0)[::-1], q))
        bound = None
        for j in range(H):
            pieces = [list(yc) + [JG[j + 1], GG[j + 1], Gy[j + 1]]
                      for yc, (JG, GG, Gy, _) in zip(ypieces, per_fold)]

            def cols(sl, j=j):
                return Gp[sl] * (qp[sl] > j)[:, None]

            out = self._finish(self.r0, yp, pieces, cols, None, bound)
            bound = bound_update(j, *out)

    def _finish(self, y, yp, pieces, cols, G, bound):
        """evaluate() from the per-fold pieces [y.y, J^T y(, J^T G, G^T G, G^T y)];
        cols(slice): the candidate's columns of those permuted rows (None: none)."""
        tot = [sum(pc[i] for pc in pieces) for i in range(len(pieces[0]))] if pieces else \
            [float(y @ y), self.J.T @ y] + ([] if G is None else
                                            [self.J.T @ G, G.T @ G, G.T @ y])
        train = np.empty(len(self.folds))
        block = np.zeros(self.n_blocks)
        heldout = np.zeros(len(y)) if bound is None else np.full(len(y), np.nan)
        for f, (sl, (te, Jte, bte, Ainv)) in enumerate(zip(self.slices, self.folds)):
            pc = pieces[f]
            parts = None
            if cols is not None:
                parts = (tot[2] - pc[2], tot[3] - pc[3], tot[4] - pc[4])
            sse, d, beta = self._solve(Ainv, tot[0] - pc[0], tot[1] - pc[1], parts)
            train[f] = sse
            if bound is not None and not sse < bound[f]:
                continue
            test = yp[sl] + Jte @ d
            if beta is not None:
                test = test + cols(sl) @ beta
            heldout[te] = test
            block += np.bincount(bte, weights=test * test, minlength=self.n_blocks)
        full_G = None if cols is None else (tot[2], tot[3], tot[4])
        sse_full, _, _ = self._solve(self.Ainv_full, tot[0], tot[1], full_G)
        return train, block, float(sse_full), heldout

    def full_residual(self, d0=None, G=None):
        y = self.r0 if d0 is None else self.r0 + d0
        J = self.J
        Jy = J.T @ y
        parts = None if G is None else (J.T @ G, G.T @ G, G.T @ y)
        _, d, beta = self._solve(self.Ainv_full, float(y @ y), Jy, parts)
        res = y + J @ d
        if beta is not None:
            res = res + G @ beta
        return res


def lag1_parts(res, S: SensorSamples) -> tuple:
    """(sum of products of successive residual rows, sum of squares) along time per axis /
    kind: the pieces of _lag1, to pool it over pieces of a file."""
    rs, ax = S.row_sample, S.row_axis
    num = den = 0.0
    for a in range(4):
        sel = np.nonzero(ax == a)[0]
        if len(sel) < 3:
            continue
        o = sel[np.argsort(S.order[rs[sel]], kind="stable")]
        v = res[o]
        num += float(v[1:] @ v[:-1])
        den += float(v @ v)
    return num, den


def _lag1(res, S: SensorSamples) -> float:
    """Pooled lag-1 autocorrelation of residual rows along time (per axis / kind)."""
    num, den = lag1_parts(res, S)
    return num / den if den > 0 else 0.0
