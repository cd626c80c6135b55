"""Scoring a candidate effect by blocked cross-validation, linearised about the current
fit, and the significance rule that decides whether it is added.

Significance rule (all three; m = candidates in the round, Bonferroni; ALPHA = 1e-3):
  1. beyond chance, with the parameter count: the held-out likelihood ratio
     n_eff ln(SSE0_cv / SSE1_cv) (SSE of the blocks' held-out residuals without and with
     the candidate) against chi^2 with the effect's parameter count (scanned parameters
     counted), p * m < ALPHA; n_eff = rows (1 - rho) / (1 + rho), rho the lag-1
     autocorrelation of the candidate's residual (correlated noise counts less). A
     useless parameter raises the held-out error on average, so chance alone rarely
     gives a large positive ratio;
  2. beyond the noise where it acts: a held-out score test with each block's own noise.
     Per held-out row, u = (residual without) - (residual with the candidate), the
     candidate's prediction from the training folds, independent of the row's noise;
     the held-out SSE gain sum(r0^2 - r1^2) = sum(2 r0 u - u^2) has, for a useless
     candidate, mean -sum(u^2) <= 0 and variance 4 sum_b s_b^2 k sum_{rows of b} u^2
     (s_b^2: block b's held-out noise with the candidate, k = (1 + rho) / (1 - rho) the
     AR(1) inflation of correlated noise). z = gain / sqrt(variance), one-sided normal,
     p * m < ALPHA. A block with a noise burst (unmodelled structure a regressor may
     match by chance) has a large s_b and counts little; an effect confined to a few
     blocks (a ramp, a heater switched a few times, one coil run, a switch that happens
     once) counts in full where it acts, and nothing is diluted by the blocks where its
     regressor is quiet (there u = 0). This replaced a t-test over the blocks' gains, which
     treats 49 quiet blocks as evidence against an effect seen in one;
  3. large enough to matter: the held-out RMS falls by at least MIN_REL_GAIN (1 %) in
     the blocks where the candidate acts (those that carry ACT_SHARE of its held-out
     prediction sum(u^2), largest first): an effect confined to a few blocks (a switch on
     3 % of the samples) is not diluted by the blocks where it is quiet, and an effect
     spread over all blocks is judged on all of them as before.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from generator.trace import effects as fx
from generator.trace.crossval import CVEngine, _lag1
from generator.trace.model import SensorModel
from generator.trace.samples import SensorSamples

ALPHA = 1e-3              # family-wise level per sensor and round (Bonferroni over candidates)
MIN_REL_GAIN = 0.01       # least held-out RMS reduction of an accepted effect
N_FOLDS = 5               # cross-validation folds (blocks dealt in turn)
ACT_SHARE = 0.9           # rule 3: the blocks carrying this share of sum(u^2) (largest
#                           first) are where a candidate acts


@dataclass
class Score:
    effect: object
    hyper: object
    dof: int
    sse0_cv: float
    sse1_cv: float
    block_gain: np.ndarray
    z: float                  # held-out score test with per-block noise (rule 2)
    p_z: float
    sse0_full: float
    sse1_full: float
    n_eff: float
    lr: float                 # held-out likelihood ratio n_eff ln(SSE0_cv / SSE1_cv)
    p_lr: float
    lr_fit: float             # the same on the fit data (information)
    file_z: dict = field(default_factory=dict)  # file name -> held-out z on its rows
    m: int = 1
    act_gain: float | None = None    # rule 3: held-out RMS gain in the blocks where it acts
    act_blocks: int | None = None
    significant: bool = False
    reasons: list = field(default_factory=list)
    explained: np.ndarray | None = None      # r0 - full-data residual (rows of the fit set)
    null: "Score | None" = None     # against the candidate's noise-matched null (_null_score)

    @property
    def rel_rms_gain(self) -> float:
        return 1.0 - math.sqrt(self.sse1_cv / self.sse0_cv) if self.sse0_cv > 0 else 0.0

    def carried_by(self) -> list:
        """The files whose held-out rows show the effect on their own: held-out z above
        the one-sided ALPHA point of the normal (the family-wise level of the rule)."""
        from scipy import stats as sps
        zc = float(sps.norm.isf(ALPHA))
        return [f for f, z in self.file_z.items() if z > zc]

    @property
    def blocks_improved(self) -> int:
        return int(np.sum(self.block_gain > 0))

    def judge(self, m, alpha, min_gain):
        self.m = m
        self.reasons = []
        if not self.p_lr * m < alpha:
            self.reasons.append(f"held-out likelihood ratio {self.lr:.1f} for {self.dof} "
                                f"parameters is within chance (p x {m} = "
                                f"{min(self.p_lr * m, 1):.2g})")
        if not self.p_z * m < alpha:
            self.reasons.append(f"held-out gain within the noise of the blocks where it acts "
                                f"(z = {self.z:.2f}, p x {m} = {min(self.p_z * m, 1):.2g})")
        gain = self.rel_rms_gain if self.act_gain is None else self.act_gain
        if not gain >= min_gain:
            where = "" if self.act_blocks is None else \
                f" in the {self.act_blocks} blocks where it acts"
            self.reasons.append(f"held-out RMS gain {100 * gain:.2f} %{where} "
                                f"< {100 * min_gain:g} %")
        if self.null is not None and not self.null.judge(m, alpha, min_gain):
            self.reasons.append("not beyond its noise-matched null (the reference's slope "
                                "change alone, which averages the reference's noise as the "
                                "interpolation does): " + "; ".join(self.null.reasons))
        self.significant = not self.reasons
        return self.significant

    def summary(self) -> dict:
        return {"effect": self.effect.name, "explained_by": self.effect.explained_by(),
                "parameters": self.dof, "cv_rms_gain_pct": 100 * self.rel_rms_gain,
                "blocks_improved": self.blocks_improved,
                "blocks": int(len(self.block_gain)), "z": _f(self.z), "p_z": _f(self.p_z),
                "heldout_likelihood_ratio": _f(self.lr), "p_lr": _f(self.p_lr),
                "fit_likelihood_ratio": _f(self.lr_fit),
                "n_eff": _f(self.n_eff), "candidates_in_round": self.m,
                "heldout_z_per_file": {k: _f(v) for k, v in self.file_z.items()},
                "cv_rms_gain_where_it_acts_pct": None if self.act_gain is None else
                _f(100 * self.act_gain), "blocks_where_it_acts": self.act_blocks,
                "significant": self.significant, "why_not": list(self.reasons),
                **({} if self.null is None else {"against_noise_matched_null": {
                    "cv_rms_gain_pct": 100 * self.null.rel_rms_gain, "z": _f(self.null.z),
                    "heldout_likelihood_ratio": _f(self.null.lr),
                    "significant": self.null.significant}})}


PROGRESS_EVERY_S = 10.0    # a progress line inside a round at most this often (wall time)


class RoundProgress:
    """Where a scoring round is (candidate i of n, its scan's value j of m), said through
    the trace's progress callback at most every `every_s` of wall time: a long round
    (every row of long files through each candidate's recursions) is not silent for
    minutes, a short one says nothing more."""

    def __init__(self, say=None, prefix="", every_s=None, clock=time.perf_counter):
        from generator.progress import Every

        self.say, self.prefix = say, prefix
        self.every_s = PROGRESS_EVERY_S if every_s is None else every_s
        self.due = Every(self.every_s, clock)
        self.where = ""

    def candidate(self, i, n, e) -> None:
        self.where = f"scoring candidate {i} of {n} ({e.label()})"
        self.tick()

    def tick(self, detail="") -> None:
        if self.say is not None and self.due():
            self.say(self.prefix + self.where + (f": {detail}" if detail else ""))


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else (1e300 if v > 0 else -1e300)


def score_candidate(model: SensorModel, S: SensorSamples, cv: CVEngine, e, base_train,
                    base_test, progress: RoundProgress | None = None):
    """Held-out score of candidate effect e added to the model (hyper-parameters chosen
    inside each training fold on its own training error); progress: told at each scanned
    value."""
    tick = progress.tick if progress is not None else (lambda detail="": None)
    grid = e.scan_grid(S)
    H = len(grid)
    best_train = np.full(len(cv.folds), np.inf)
    test1 = np.empty(len(cv.r0))
    fulls = np.empty(H)
    masked = hasattr(e, "mask") and e.fd_in_scoring
    if masked:   # a linear effect switched on by a row mask: columns once, masked per value
        e.set_hyper(None)
        d0_all, G_all = candidate_columns(model, S, e, cv.r0)
    directed = hasattr(e, "score_directions")
    if directed:  # scored along directions in its parameters: columns once, mapped per value
        d0_p, G_p = candidate_columns(model, S, e, cv.r0)

    def columns():
        if masked:
            return None, G_all * e.mask(S)[S.row_sample][:, None]
        if directed:
            return d0_p, None if G_p is None else G_p @ e.score_directions()
        return candidate_columns(model, S, e, cv.r0)

    def keep(j, train, _block, full, test):
        # per fold: the grid value with the least training error (the first of equals);
        # the held-out rows only of the folds it improves
        fulls[j] = full
        for f, (te, _, _, _) in enumerate(cv.folds):
            if train[f] < best_train[f]:
                best_train[f] = train[f]
                test1[te] = test[te]
        return best_train

    stepped = masked and d0_all is None and G_all is not None and hasattr(e, "step_key") \
        and list(grid) == sorted(grid)
    if stepped:   # a step at each grid value: one pass of sufficient statistics
        cv.step_scan(G_all, e.step_key(S)[S.row_sample], grid, keep)
    for j, h in enumerate([] if stepped else grid):
        tick(f"scan value {j + 1} of {H}")
        e.set_hyper(h)
        d0, G = columns()
        keep(j, *cv.evaluate(d0, G, bound=best_train))
    jbest = int(np.argmin(fulls))
    if getattr(e, "relinearise", False) and test1 @ test1 < base_test @ base_test:
        return _rescore_refitted(model, S, cv, e, [grid[j] for j in np.argsort(fulls)[:2]],
                                 base_test, tick)
    h = grid[jbest]
    e.set_hyper(h)
    d0, G = columns()
    res_full = cv.full_residual(d0, G)
    sc = _make_score(e, h, S, cv, base_test, test1, res_full, float(fulls[jbest]))
    if getattr(e, "null_params", ()) and directed and G_p is not None:
        sc.null = _null_score(S, cv, e, h, d0_p, G_p)
    return sc


def _null_score(S, cv: CVEngine, e, h, d0, G) -> "Score":
    """The candidate with all its parameters free (columns G) against its NOISE-MATCHED
    NULL, the model with only e.null_params free (TimeOffset: the reference's slope
    change g, whose fit averages the reference's white noise as well as any
    interpolation can): the held-out score of what the rest (the offset) adds beyond
    that, judged by the same rule (Score.judge)."""
    null = list(e.null_params)
    _, _, _, test0 = cv.evaluate(d0, G[:, null])
    _, _, full1, test1 = cv.evaluate(d0, G)
    ns = _make_score(e, h, S, cv, test0, test1, cv.full_residual(d0, G), full1)
    ns.dof = e.n_params - len(null)
    ns.p_lr = _chi2_sf(ns.lr, ns.dof)
    return ns


def _chi2_sf(lr, dof) -> float:
    from scipy import stats as sps
    return float(sps.chi2.sf(max(lr, 0.0), dof))


def heldout_z(test0, test1, row_block, n_blocks, kappa) -> float:
    """The held-out score statistic of rule 2 (module docstring): the held-out SSE gain
    over its standard deviation for a useless candidate, with each block's own noise."""
    u = test0 - test1
    gain = float(test0 @ test0 - test1 @ test1)
    cnt = np.bincount(row_block, minlength=n_blocks)
    s2 = np.bincount(row_block, weights=test1 * test1, minlength=n_blocks) / np.maximum(cnt, 1)
    uu = np.bincount(row_block, weights=u * u, minlength=n_blocks)
    var = 4.0 * kappa * float(s2 @ uu)
    if var <= 0:
        return 0.0 if gain <= 0 else math.inf
    return gain / math.sqrt(var)


def _make_score(e, h, S, cv: CVEngine, test0, test1, res_full, sse1_full) -> Score:
    """The statistics of the significance rule from the held-out residuals without
    (test0) and with (test1) the candidate, and its fit-data residual."""
    from scipy import stats as sps
    r0 = cv.r0
    rb, nb = cv.row_block, cv.n_blocks
    base_block = np.bincount(rb, weights=test0 * test0, minlength=nb)
    block1 = np.bincount(rb, weights=test1 * test1, minlength=nb)
    gain = base_block - block1
    sse0_full = float(r0 @ r0)
    rho = min(max(_lag1(res_full, S), 0.0), 0.99)
    n_eff = len(r0) * (1 - rho) / (1 + rho)
    kappa = (1 + rho) / (1 - rho)
    z = heldout_z(test0, test1, rb, nb, kappa)
    p_z = float(sps.norm.sf(z))
    file_z = {}
    row_file = S.file_index[S.row_sample]
    for fi in np.unique(row_file):
        sel = row_file == fi
        file_z[S.file_names[fi]] = heldout_z(test0[sel], test1[sel], rb[sel], nb, kappa)
    lr_fit = n_eff * math.log(sse0_full / sse1_full) if sse1_full > 0 and sse0_full > 0 \
        else 0.0
    sse0_cv, sse1_cv = float(base_block.sum()), float(block1.sum())
    lr = n_eff * math.log(sse0_cv / sse1_cv) if sse1_cv > 0 and sse0_cv > 0 else 0.0
    dof = e.n_dof
    p_lr = _chi2_sf(lr, dof)
    act_gain, act_blocks = _gain_where_it_acts(test0 - test1, rb, nb, base_block, block1)
    return Score(e, h, dof, sse0_cv, sse1_cv, gain, z, p_z, sse0_full, sse1_full, n_eff, lr,
                 p_lr, lr_fit, file_z=file_z, explained=r0 - res_full, act_gain=act_gain,
                 act_blocks=act_blocks)


def _gain_where_it_acts(u, row_block, n_blocks, sse0_block, sse1_block):
    """(held-out RMS gain, block count) over the blocks that carry ACT_SHARE of the
    candidate's held-out prediction sum(u^2), largest first (rule 3)."""
    uu = np.bincount(row_block, weights=u * u, minlength=n_blocks)
    tot = float(uu.sum())
    if tot <= 0:
        return 0.0, 0
    o = np.argsort(-uu)
    k = int(np.searchsorted(np.cumsum(uu[o]), ACT_SHARE * tot)) + 1
    act = o[:k]
    s0, s1 = float(sse0_block[act].sum()), float(sse1_block[act].sum())
    return (1.0 - math.sqrt(s1 / s0) if s0 > 0 else 0.0), k


def _rescore_refitted(model, S, cv: CVEngine, e, starts, base_test,
                      tick=lambda detail="": None) -> Score:
    """Second stage for an effect whose linearisation about the current model is poor
    (a thermal lag moves the temperature the polynomials see by degrees): fit the model
    with the effect from the best scanned values (nonlinear, all parameters), keep the
    best, and cross-validate linearised about that fit (the effect's own parameter in the
    Jacobian, so each training fold refits it)."""
    best = None
    for i, h in enumerate(starts):
        tick(f"refit {i + 1} of {len(starts)} from the best scanned values")
        e.set_hyper(h)
        m1 = model.with_effect(e, e.init_params()).fit(S, max_nfev=20)
        sse = m1.sse(S)
        if best is None or sse < best[0]:
            best = (sse, h, m1)
    _, h, m1 = best
    e.set_hyper(h)
    r1, J1 = m1.jacobian(S)
    cv1 = CVEngine(r1, J1, cv.row_block, cv.fold_of_block, cv.n_blocks)
    _, _, _, test1 = cv1.evaluate()
    hyper = e.hyper_after_fit(m1.effect_params(len(m1.effects) - 1))
    e.set_hyper(hyper)
    return _make_score(e, hyper, S, cv, base_test, test1, r1, float(r1 @ r1))


def candidate_columns(model: SensorModel, S, e, r0):
    """(d0, G): the residual change of the model with e at its initial parameters, and
    the Jacobian columns of e's parameters there (None for scan-only effects)."""
    if e.fd_in_scoring and not np.any(e.init_params()):
        G = model.offset_columns(S, e)      # linear offset: from the model's own forward
        if G is not None:
            return None, G
    m1 = model.with_effect(e, e.init_params())
    cols = np.arange(model.P, m1.P) if (e.fd_in_scoring and e.n_params) else np.arange(0)
    r1, G = m1.jacobian(S, cols=cols)
    d0 = r1 - r0
    if not np.any(d0):
        d0 = None
    return d0, (G if G.shape[1] else None)


def _context(model: SensorModel, S: SensorSamples):
    from generator.fit.thermal import temperature_quantum
    return SimpleNamespace(samples=S, effects=model.effects, degree=model.degree,
                           temp_quantum=temperature_quantum(S.temp_C))


def candidate_list(model, S):
    ctx = _context(model, S)
    cands, why = [], {}
    for cls in fx.CATALOGUE:
        inst, reason = cls.candidates(ctx)
        if inst:
            cands.extend(inst)
        else:
            why[cls.name] = reason
    return cands, why


def score_round(model: SensorModel, S_fit, fold_of_block, n_blocks, alpha, min_gain,
                progress: RoundProgress | None = None):
    cands, why = candidate_list(model, S_fit)
    if not cands:
        return [], why
    r0, J = model.jacobian(S_fit)
    cv = CVEngine(r0, J, S_fit.block[S_fit.row_sample], fold_of_block, n_blocks)
    base_train, _, _, base_test = cv.evaluate()
    scores = []
    for i, e in enumerate(cands):
        if progress is not None:
            progress.candidate(i + 1, len(cands), e)
        scores.append(score_candidate(model, S_fit, cv, e, base_train, base_test, progress))
    for s in scores:
        s.judge(len(scores), alpha, min_gain)
    scores.sort(key=lambda s: s.sse1_cv)
    return scores, why


EQUIVALENT_CORR = 0.95


def equivalent(a: Score, b: Score) -> bool:
    """Two candidates explain the same thing: their fitted contributions are correlated
    above EQUIVALENT_CORR and their held-out errors differ by no more than chance
    (n_eff ln(SSE_a / SSE_b) within the 95 % point of chi^2 with 1 degree of freedom)."""
    c = _corr(a.explained, b.explained)
    if c is None or c < EQUIVALENT_CORR:
        return False
    from scipy import stats as sps
    n_eff = min(a.n_eff, b.n_eff)
    return abs(n_eff * math.log(a.sse1_cv / b.sse1_cv)) < sps.chi2.ppf(0.95, 1)


def choose(sig: list) -> Score:
    """The significant candidate with the least held-out error, unless an equivalent one
    (see `equivalent`) is simpler (fewer parameters, scanned ones counted) or, as simple,
    has a higher prior (generator.trace.effects.Effect.prior)."""
    best = sig[0]
    for s in sig[1:]:
        simpler = (s.dof, -s.effect.prior) < (best.dof, -best.effect.prior)
        if simpler and equivalent(best, s):
            best = s
    return best


def _corr(a, b):
    if a is None or b is None:
        return None
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else None
