"""Catalogue of candidate effects for `magcal trace` (issue 6).

Each entry is one class: what the effect is (`physics`), what it is made of in the data
(`candidates` builds one instance per applicable column or quantity, `explained_by`
names them), its parameters (a few internal, well-scaled numbers, `describe` gives them
in physical units), where it acts in the float64 model of the chain (a *hook*, below) and
its FLIGHT FORM, i.e. how it enters the flight chain's coefficient set (`to_flight`;
`in_chain = False` for effects the flight chain does not carry).

The float64 model of the extended chain (generator.trace.tracer.SensorModel) runs, per sample,
in the order of generator.flight.chain.sensor_kernel:

    field_f                         raw field, frame axes (SET/RESET, axis map)
    T_el   <- hook "temperature"    (ThermalLag: first-order filter of the reported T)
    clamp, dT, b(T), M(T)           base polynomials of the baseline degree
    x = field_f - b(T) - K i_coil
    x -= hook "offset"              (TemperaturePolynomial extra b rows, ChannelBias C ch,
                                     BiasStep)
    x  = hook "transform" (order)   (CubicNonlinearity x_i -= n_i x_i^3, then
                                     SetResetRotation B += c (w_f x B))
    B = M(T) x
    reference <- hook "reference"   (TimeOffset: B_ref + dt r + g c, r the rate)

Hooks are batched: p has shape (Bt, n_params) (a batch of parameter vectors, used for the
finite-difference Jacobian), the samples S are shared, arrays returned are (Bt, n, ...).

Adding an effect: write one subclass (see docs/effects.md) and append it to CATALOGUE.

Size: the catalogue, one class per effect; they share the Effect protocol and are listed
once in CATALOGUE, which trace and the tests import.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from generator.flight.chain import MAX_POLY_DEGREE
from generator.trace.recursion import first_order_loop

FIELD_SCALE_nT = 50000.0          # the cubic's internal parameter: nT at 50 uT on the axis


class Effect:
    """Base class of a catalogue entry. Subclasses set the class attributes and override
    `candidates`, the hook of their stage and `describe` / `to_flight`."""

    name = ""                 # short name, used in trace.json "effect"
    title = ""                # a few words for the report
    physics = ""              # one sentence: the mechanism
    flight_form = ""          # one sentence: how the flight chain carries it
    in_chain = True           # False: no flight-chain form (see flight_form)
    stage = ""     # "temperature" | "offset" | "transform" | "calibrated" | "reference"
    order = 0                 # order among effects of the "transform" stage
    repeatable = False        # more than one instance per sensor (another channel, step)
    n_params = 0              # continuous parameters (internal units, fitted jointly)
    n_hyper = 0               # scanned parameters (a change time, a time constant)
    fd_in_scoring = True      # score with the Jacobian columns of the parameters
    linear_offset = True      # stage "offset": offset(p) is linear in p (no constant), so
    #                           its Jacobian columns are analytic (SensorModel.jacobian)
    prior = 0                 # tie-break between statistically equivalent explanations:
    #                           the higher wins (a mechanism the part is known to have)

    def __init__(self):
        self.hyper = None

    # ---- identity ---------------------------------------------------------------------
    def key(self) -> str:
        return self.name

    def explained_by(self) -> list:
        return []

    @property
    def n_dof(self) -> int:
        """Parameter count used by the significance rule (continuous + scanned)."""
        return self.n_params + self.n_hyper

    # ---- candidates -------------------------------------------------------------------
    @classmethod
    def candidates(cls, ctx) -> tuple:
        """(list of instances applicable to this sensor's data, reason when none)."""
        return [], "not implemented"

    # ---- scanning -----------------------------------------------------------------------
    def scan_grid(self, S) -> list:
        return [None]

    def set_hyper(self, h):
        self.hyper = h

    def init_params(self) -> np.ndarray:
        return np.zeros(self.n_params)

    def refine_grid(self, S, best) -> list:
        """A finer grid around the best coarse value (for the final fit); [] for none."""
        return []

    def hyper_after_fit(self, p):
        """The scanned value that a fit with parameters p amounts to (see ThermalLag)."""
        return self.hyper

    def time_constant_s(self, p):
        """The effect's time constant at parameters p (a lag), None if it has none."""
        return None

    # ---- hooks (override the one of `stage`) -------------------------------------------
    def temperature(self, p, S, T):
        return T

    def offset(self, p, S, st):
        return 0.0

    def transform(self, p, S, x, st):
        return x

    def calibrated(self, p, S, B, st):
        return B

    def reference_shift(self, p, S):
        return 0.0

    def regressor_noise(self, S):
        """None, or (n_params,): the expected share of white noise in the sum over the
        rows of each parameter's squared residual column, where the regressor is a noisy
        measurement (errors in variables, independent of the residual's own noise): the
        fit takes it out (generator.trace.model.SensorModel.fit)."""
        return None

    # ---- output -----------------------------------------------------------------------
    def describe(self, p, model=None) -> dict:
        """Physical parameters (JSON-able, names with units)."""
        return {}

    def to_flight(self, p, values: dict, options: dict, model) -> None:
        """Write the flight form into the sensor's block values / chain options."""

    @classmethod
    def from_flight(cls, sensor_values: dict, options, S, model_info) -> list:
        """Instances (with parameters) for a supplied coefficient set that already carries
        this effect's flight form: [(effect, internal params)]."""
        return []

    def label(self) -> str:
        by = ", ".join(self.explained_by())
        return f"{self.name}({by})" if by else self.name


# ---------------------------------------------------------------------------------------
# Helpers over the sensor samples (S: generator.trace.tracer.SensorSamples)
# ---------------------------------------------------------------------------------------

def first_order(a, x, y0) -> np.ndarray:
    """The recursion y[0] = y0, y[k] = y[k-1] + a[k-1] (x[k] - y[k-1]) for 0 <= a < 1,
    vectorised: y[k] = P[k] (y0 + sum_{j<=k} a[j-1] x[j] / P[j]), P[k] = prod (1 - a),
    in chunks over which P falls by at most e^-LOG_SPAN (no overflow). The error of a
    term is about eps * k * max|a x| (the partial sums are taken relative to the chunk's
    start, where the factor is 1), i.e. round-off of the loop's size; a = 1 (no memory)
    is the input itself."""
    x = np.asarray(x, float)
    n = len(x)
    out = np.empty(n)
    if n == 0:
        return out
    out[0] = y0
    if n == 1:
        return out
    a = np.asarray(a, float)
    with np.errstate(divide="ignore"):
        lq = np.negative(a)
        np.log1p(lq, out=lq)                    # log(1 - a) <= 0, -inf where a = 1
    hard = ~np.isfinite(lq)
    hard |= lq < -LOG_SPAN                      # no memory: y[k] = x[k] (to e^-LOG_SPAN)
    lq[hard] = 0.0
    L = np.cumsum(lq, out=lq)                   # in place (series-long arrays: memory)
    if (np.count_nonzero(hard) - L[-1] / LOG_SPAN) * 100 > n:
        # short memory: many chunks; the plain loop is faster (compiled, the same
        # operations in the same order as on Python floats: trace.recursion)
        first_order_loop(a, x, y0, out)
        return out
    k, y = 0, float(y0)                         # out[k] = y known; next index k + 1
    cut = np.nonzero(hard)[0]
    del hard
    ci = 0
    while k < n - 1:
        # the chunk: indices k+1 .. e (inclusive), up to the next memoryless step and
        # while the factor stays above e^-LOG_SPAN
        while ci < len(cut) and cut[ci] < k:
            ci += 1
        stop = cut[ci] if ci < len(cut) else n - 1        # index into a (sample stop+1)
        if stop == k:                                      # sample k+1 has no memory
            y = x[k + 1]
            out[k + 1] = y
            k += 1
            continue
        Lk = L[k - 1] if k > 0 else 0.0
        e = _span_end(L, k, stop, Lk)
        e = max(e, k + 1)
        rel = L[k:e] - Lk                                   # log factor from sample k
        csum = np.cumsum(a[k:e] * x[k + 1:e + 1] * np.exp(-rel))
        seg = np.exp(rel) * (y + csum)
        out[k + 1:e + 1] = seg
        y = float(seg[-1])
        k = e
    return out


LOG_SPAN = 500.0     # first_order: e^500 stays far inside float64's range
_SPAN_WINDOW = 4096  # _span_end's first window (rows)


def _span_end(L, k, stop, Lk) -> int:
    """k + the number of i in k .. stop-1 with -(L[i] - Lk) <= LOG_SPAN, L the running
    sum of log factors (non-increasing, so the computed -(L[i] - Lk) is non-decreasing
    and that count is where LOG_SPAN sorts in, as np.searchsorted(-(L[k:stop] - Lk),
    LOG_SPAN, "right") over the whole stretch gives it) -- found in windows that double
    from k, so a chunk costs its own length, not the rest of the file's (with many
    chunks the whole stretch made the recursion quadratic in the rows: issue 20 F5)."""
    w = _SPAN_WINDOW
    while True:
        hi = min(k + w, stop)
        d = -(L[k:hi] - Lk)
        if hi == stop or (len(d) and d[-1] > LOG_SPAN):
            return int(np.searchsorted(d, LOG_SPAN, side="right")) + k
        w *= 2


def lag_filter(time_s, temp_C, tau_s) -> np.ndarray:
    """The flight chain's element temperature: T_el[0] = T[0], then
    T_el[k] = T_el[k-1] + dt/(tau + dt) (T[k] - T_el[k-1]) (generator.flight.chain.lag_kernel;
    a step back in time, dt < 0, holds the filter as the chain does)."""
    t = np.asarray(time_s, float)
    T = np.asarray(temp_C, float)
    if len(T) == 0:
        return np.empty_like(T)
    if tau_s <= 0:
        return T.copy()
    return first_order(_lag_factors(t, tau_s), T, T[0])


def _lag_factors(t, tau_s) -> np.ndarray:
    """dt / (tau + dt), dt = max(diff(t), 0): the recursion's factors (in place: two
    series-long arrays, not four)."""
    dt = np.diff(t)
    np.maximum(dt, 0.0, out=dt)
    a = dt + tau_s
    np.divide(dt, a, out=a)
    return a


def lag_filter_dtau(time_s, temp_C, tau_s, filtered=None) -> np.ndarray:
    """d T_el / d tau of lag_filter: differentiating the recursion gives the same filter,
    g[0] = 0, g[k] = g[k-1] + a[k-1] (u[k] - g[k-1]), u[k] = -(T[k] - T_el[k-1]) / (tau + dt),
    since d a / d tau = -a / (tau + dt)."""
    t = np.asarray(time_s, float)
    T = np.asarray(temp_C, float)
    if len(T) < 2 or tau_s <= 0:
        return np.zeros(len(T))
    el = lag_filter(t, T, tau_s) if filtered is None else filtered
    dt = np.diff(t)
    np.maximum(dt, 0.0, out=dt)
    den = dt + tau_s
    u = np.empty(len(T))                # in place: the same operations, fewer arrays
    u[0] = 0.0
    np.subtract(T[1:], el[:-1], out=u[1:])
    np.negative(u[1:], out=u[1:])
    np.divide(u[1:], den, out=u[1:])
    np.divide(dt, den, out=dt)          # the factors dt / (tau + dt)
    del den
    return first_order(dt, u, 0.0)


# The recursions' caches on a file's series hold whole-series arrays (8 B a row each);
# above the trace's cap a series is the whole file (trace.subsample's bridge rows), so
# their size is bounded in bytes too, not only in entries: at most SERIES_CACHE_BYTES a
# cache (values are the same with or without a cache; only the time to recompute).
SERIES_CACHE_BYTES = 64 * 2 ** 20


def _cache_full(cache, n_rows, max_entries) -> bool:
    """The cache holds as many arrays of n_rows floats as it may (then it is cleared)."""
    return len(cache) > min(max_entries, max(4, SERIES_CACHE_BYTES // (8 * max(n_rows, 1))))


def element_temperature(series, tau_s) -> np.ndarray:
    """lag_filter of one file's temperature series, kept on the series (one recursion per
    time constant; the cache lives and dies with the series)."""
    cache = series.__dict__.setdefault("_lag_cache", {})
    key = round(float(tau_s), 12)
    v = cache.get(key)
    if v is None:
        t = series.time_s                   # unpacked once (a PackedSeries unpacks on read)
        if _cache_full(cache, len(t), 64):
            cache.clear()
        v = cache[key] = lag_filter(t, series.temp_C, tau_s)
    return v


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a * a))) if a.size else 0.0


# ---------------------------------------------------------------------------------------
# The catalogue
# ---------------------------------------------------------------------------------------

class ChannelBias(Effect):
    """A bias linear in a telemetry channel: a heater current, a solar-array or bus
    current, a voltage, a flag, a magnetorquer current the model does not carry, a body
    rate. Every numeric column that is not a sensor, reference, time or position column
    is a candidate; one instance per column. Parameter: C (3, nT per unit of the column,
    frame axes). Flight form: the `channels` option, block C_nT_per_unit, x -= C ch."""

    name = "channel_bias"
    title = "bias linear in a telemetry channel"
    physics = ("a current or a switched load near the sensor adds a field proportional to "
               "a telemetry channel")
    flight_form = "channels option: block C_nT_per_unit (3 x nch), x -= C ch after the coils"
    stage = "offset"
    repeatable = True
    n_params = 3

    def __init__(self, channel, scale, present=None):
        super().__init__()
        self.channel = channel
        self.scale = float(scale)        # internal parameter = nT per `scale` units
        # a channel that only some files carry: an offset of its own for those files, so
        # that only its variation counts (its mean would otherwise stand for "this file")
        self.partial = present is not None
        self.n_params = 6 if self.partial else 3

    def key(self):
        return f"{self.name}:{self.channel}"

    def explained_by(self):
        return [self.channel]

    @classmethod
    def candidates(cls, ctx):
        S = ctx.samples
        have = {e.channel for e in ctx.effects if isinstance(e, ChannelBias)}
        out = []
        for name, v in S.channels.items():
            if name in have:
                continue
            present = S.channel_present.get(name)
            partial = present is not None and not present.all()
            v = np.asarray(v, float)
            vv = v[present] if partial else v
            sd = float(np.std(vv)) if len(vv) else 0.0
            if not np.isfinite(sd) or sd <= 1e-12 * max(1.0, float(np.max(np.abs(vv)))):
                continue
            out.append(cls(name, sd, present if partial else None))
        return out, ("" if out else "no varying telemetry channel besides the modelled ones")

    def offset(self, p, S, st):
        ch = S.channels[self.channel] / self.scale
        out = p[:, None, :3] * ch[None, :, None]
        if self.partial:
            has = S.channel_present[self.channel].astype(float)
            out = out + p[:, None, 3:6] * has[None, :, None]
        return out

    def C_nT_per_unit(self, p):
        return np.asarray(p, float)[:3] / self.scale

    def describe(self, p, model=None):
        out = {"C_nT_per_unit": self.C_nT_per_unit(p).tolist(), "channel_std": self.scale}
        if self.partial:
            out["offset_where_present_nT"] = np.asarray(p, float)[3:6].tolist()
        return out

    def to_flight(self, p, values, options, model):
        chans = options.setdefault("channels", [])
        C = values.get("C_nT_per_unit")
        col = self.C_nT_per_unit(p).reshape(3, 1)
        if self.channel in chans:   # already there (a channel scale wrote a zero column):
            j = chans.index(self.channel)          # one channel, its C and its g column
            C = np.array(C, float)
            C[:, j:j + 1] = C[:, j:j + 1] + col
            values["C_nT_per_unit"] = C
        else:
            chans.append(self.channel)
            values["C_nT_per_unit"] = col if C is None else np.hstack([C, col])
        if self.partial:   # the files that carry the channel are the operating condition
            values["b_poly_nT"][0] = values["b_poly_nT"][0] + np.asarray(p, float)[3:6]

    @classmethod
    def from_flight(cls, sv, options, S, info):
        out = []
        C = np.asarray(sv.get("C_nT_per_unit", np.zeros((3, 0))), float)
        g = np.asarray(sv["g_per_unit"], float).reshape(3, -1) \
            if getattr(options, "channel_scale", False) else None
        for j, ch in enumerate(options.channels):
            if g is not None and not np.any(C[:, j]) and np.any(g[:, j]):
                continue          # a channel that only scales (ChannelScale.from_flight)
            v = S.channels.get(ch)
            sd = float(np.std(v)) if v is not None and len(v) else 1.0
            sd = sd if sd > 0 else 1.0
            e = cls(ch, sd)
            out.append((e, C[:, j] * sd))
        return out


class ThermalLag(Effect):
    """The sensing element lags the reported (board) temperature: the polynomials b(T),
    M(T) see T_el, the reported T through the chain's first-order filter
    T_el += dt/(tau + dt) (T - T_el). Parameter: tau_s (scanned on a log grid, then
    fitted with everything else). Flight form: the `thermal_lag` option, block lag_tau_s."""

    name = "thermal_lag"
    title = "thermal lag of the sensing element"
    physics = ("the sensing element follows the reported board temperature with a time "
               "constant, so the temperature model is wrong while the temperature changes")
    flight_form = "thermal_lag option: block lag_tau_s; the polynomials use T_el"
    stage = "temperature"
    n_params = 1
    n_hyper = 0
    fd_in_scoring = True      # each grid value refined by the tau column (log tau)
    relinearise = True        # scored again from a nonlinear fit (see trace._rescore_refitted)
    GRID = 14

    def __init__(self):
        super().__init__()
        self.hyper = 1.0

    def explained_by(self):
        return ["temperature rate (reported temperature through a first-order lag)"]

    @classmethod
    def candidates(cls, ctx):
        if any(isinstance(e, ThermalLag) for e in ctx.effects):
            return [], "already in the model"
        if ctx.degree < 1:
            return [], "the model has no temperature dependence for the element to lag"
        S = ctx.samples
        if np.ptp(S.temp_C) < max(0.5, 3 * ctx.temp_quantum):
            return [], "the temperature hardly changes"
        return [cls()], ""

    def scan_grid(self, S):
        dts = [np.median(np.diff(f.time_s)) for f in S.files if len(f.time_s) > 1]
        spans = [np.ptp(f.time_s) for f in S.files if len(f.time_s) > 1]
        lo = max(0.5 * float(np.min(dts)) if dts else 1.0, 0.05)
        hi = max(0.5 * float(np.max(spans)) if spans else 10 * lo, 4 * lo)
        return list(np.exp(np.linspace(math.log(lo), math.log(hi), self.GRID)))

    def refine_grid(self, S, best):
        return list(best * np.exp(np.linspace(-0.3, 0.3, 7)))

    LOG_LIMIT = 20.0    # |log(tau / hyper)| at most 20: tau within e^+-20 of the scanned
    #                     value (beyond, the element is a constant or the board itself
    #                     for any data; a fit that runs off there stays finite)

    def tau_s(self, p):
        lp = float(np.clip(float(np.asarray(p).reshape(-1)[0]), -self.LOG_LIMIT, self.LOG_LIMIT))
        return float(self.hyper * math.exp(lp))

    def hyper_after_fit(self, p):
        return self.tau_s(p)

    def time_constant_s(self, p):
        return self.tau_s(p)

    def temperature(self, p, S, T):
        taus = self.hyper * np.exp(np.clip(np.asarray(p)[:, 0], -self.LOG_LIMIT,
                                           self.LOG_LIMIT))
        out = np.empty((len(taus), S.n))
        uniq, inv = np.unique(np.round(taus, 12), return_inverse=True)
        for u_i, tau in enumerate(uniq):
            T_el = np.empty(S.n)
            for fi, series in enumerate(S.files):
                sel = S.file_index == fi
                if sel.any():
                    T_el[sel] = element_temperature(series, tau)[S.file_row[sel]]
            out[inv == u_i] = T_el
        return out

    def temperature_jacobian(self, p, S):
        """d T_el / d p (1, n) at the parameter p (log(tau / hyper)): tau dT_el/dtau, by
        the derivative's own recursion (lag_filter_dtau) per file."""
        tau = self.tau_s(p)
        out = np.zeros((1, S.n))
        if abs(float(np.asarray(p).reshape(-1)[0])) >= self.LOG_LIMIT:
            return out                            # clipped: tau does not move
        for fi, series in enumerate(S.files):
            sel = S.file_index == fi
            if sel.any():
                g = lag_filter_dtau(series.time_s, series.temp_C, tau,
                                    element_temperature(series, tau))
                out[0, sel] = tau * g[S.file_row[sel]]
        return out

    def describe(self, p, model=None):
        return {"lag_tau_s": self.tau_s(p)}

    def to_flight(self, p, values, options, model):
        options["thermal_lag"] = True
        values["lag_tau_s"] = np.array(self.tau_s(p))

    @classmethod
    def from_flight(cls, sv, options, S, info):
        if not options.thermal_lag:
            return []
        e = cls()
        e.hyper = max(float(sv["lag_tau_s"]), 1e-6)
        return [(e, np.zeros(1))]


class TemperaturePolynomial(Effect):
    """One more degree of the offset polynomial b(T) (a quartic or quintic term): the
    offset's temperature curve bends more than the baseline degree allows. Parameter:
    b_{d+1} (3, nT/degC^(d+1)). Flight form: poly_degree d+1 (unit-wide), the new row of
    b_poly_nT; M_poly's new row is zero (the scale's curve keeps its degree)."""

    name = "temperature_polynomial"
    title = "higher polynomial degree of b(T)"
    physics = ("the offset's temperature curve has a higher-order term than the "
               "calibration polynomial")
    flight_form = ("poly_degree raised (unit-wide): one more row of b_poly_nT, the new "
                   "row of M_poly zero")
    stage = "offset"
    repeatable = True
    n_params = 3

    def __init__(self, degree):
        super().__init__()
        self.degree = int(degree)

    def key(self):
        return f"{self.name}:{self.degree}"

    def explained_by(self):
        return [f"temperature^{self.degree}"]

    @classmethod
    def candidates(cls, ctx):
        d = ctx.degree
        if d >= MAX_POLY_DEGREE:
            return [], f"degree {d} is the chain's highest"
        S = ctx.samples
        n_levels = len(np.unique(np.round(S.temp_C / max(ctx.temp_quantum, 1e-3))))
        if n_levels < d + 3 or np.ptp(S.temp_C) < max(0.5, 3 * ctx.temp_quantum):
            return [], "too few distinct temperatures for another degree"
        return [cls(d + 1)], ""

    def offset(self, p, S, st):
        return p[:, None, :] * (st.s ** self.degree)[:, :, None]

    def b_row(self, p, model):
        return np.asarray(p, float) / model.t_scale_C ** self.degree

    def describe(self, p, model=None):
        out = {"degree": self.degree}
        if model is not None:
            out[f"b{self.degree}_nT_per_C{self.degree}"] = self.b_row(p, model).tolist()
        return out

    def to_flight(self, p, values, options, model):
        b = values["b_poly_nT"]
        if b.shape[0] < self.degree + 1:
            b = np.vstack([b, np.zeros((self.degree + 1 - b.shape[0], 3))])
            M = values["M_poly"]
            values["M_poly"] = np.concatenate(
                [M, np.zeros((self.degree + 1 - M.shape[0], 3, 3))])
        b[self.degree] = b[self.degree] + self.b_row(p, model)
        values["b_poly_nT"] = b


class CubicNonlinearity(Effect):
    """A per-axis cubic of the reading (the bridge's transfer curve bends at high field):
    after the offsets, x_i -= n_i x_i^3. Needs readings in several field directions (the
    cubic of one constant reading is only noise). Parameter: n (3, 1/nT^2). Flight form:
    the `nonlinear` option, block cubic_per_nT2."""

    name = "cubic_nonlinearity"
    title = "per-axis cubic of the reading"
    physics = "the sensor's transfer curve bends: each axis reads a cubic of its field"
    flight_form = "nonlinear option: block cubic_per_nT2, x_i -= n_i x_i^3 after the offsets"
    stage = "transform"
    order = 1
    n_params = 3

    def explained_by(self):
        return ["reading^3 per axis"]

    @classmethod
    def candidates(cls, ctx):
        if any(isinstance(e, CubicNonlinearity) for e in ctx.effects):
            return [], "already in the model"
        S = ctx.samples
        absolute = S.kind != 2
        if not absolute.any():
            # without an absolute reference any contraction of the readings toward the
            # position constants shrinks the noise: the scale, and a cubic, are not defined
            return [], "no field reference (positions only): the scale of the reading is free"
        v = np.where((S.kind == 0)[:, None], S.ref, S.x)[absolute]
        u = v / np.maximum(np.linalg.norm(v, axis=1), 1e-9)[:, None]
        from generator.fit.ellipsoid import distinct_rows
        if distinct_rows(u, 0.1, at_most=6) < 6:
            return [], ("the field takes fewer than 6 directions: a cubic is not separable "
                        "from noise")
        return [cls()], ""

    def transform(self, p, S, x, st):
        n = p / FIELD_SCALE_nT ** 3
        return x - n[:, None, :] * x ** 3

    def describe(self, p, model=None):
        return {"cubic_per_nT2": (np.asarray(p, float) / FIELD_SCALE_nT ** 3).tolist(),
                "nT_at_50uT": np.asarray(p, float).tolist()}

    def to_flight(self, p, values, options, model):
        options["nonlinear"] = True
        values["cubic_per_nT2"] = np.asarray(p, float) / FIELD_SCALE_nT ** 3

    @classmethod
    def from_flight(cls, sv, options, S, info):
        if not options.nonlinear:
            return []
        return [(cls(), np.asarray(sv["cubic_per_nT2"], float) * FIELD_SCALE_nT ** 3)]


class BiasStep(Effect):
    """A step of the offset at an unknown time (a magnetisation event: a current surge,
    a magnet nearby, a SET pulse that failed). The change point is scanned over the data
    in time order (files in the order given, holdout files after them). Parameters: the
    step (3, nT, frame axes) and its time. Flight form: none in the chain; the offset
    after the event is the new b0 (uplink a new table after the event)."""

    name = "bias_step"
    title = "offset step at an unknown time"
    physics = "a magnetisation event shifted the sensor's offset from one moment on"
    flight_form = ("no chain stage: the offset after the event is written into b_poly_nT[0] "
                   "(a new uplink table after the event)")
    in_chain = False
    stage = "offset"
    repeatable = True
    n_params = 3
    n_hyper = 1
    GRID = 48

    def __init__(self):
        super().__init__()
        self.where = None          # (file, time_s) of the first sample after the step

    def explained_by(self):
        if self.where is None:
            return ["time (change point)"]
        f, after, before = self.where
        span = f"{before:.6g}..{after:.6g} s" if before is not None else f"<= {after:.6g} s"
        return [f"time (change at {span} in {Path(f).name})"]

    @classmethod
    def candidates(cls, ctx):
        if ctx.samples.n < 20:
            return [], "too few samples"
        return [cls()], ""

    def scan_grid(self, S):
        q = np.unique(np.quantile(S.order, np.linspace(0.03, 0.97, self.GRID)).round())
        return [int(v) for v in q]

    def refine_grid(self, S, best):
        o = np.unique(S.order)
        i = int(np.searchsorted(o, best))
        step = max(1, len(o) // self.GRID)
        lo, hi = max(0, i - step), min(len(o) - 1, i + step)
        cand = o[lo:hi + 1]
        if len(cand) > 40:
            cand = cand[np.linspace(0, len(cand) - 1, 40).round().astype(int)]
        return [int(v) for v in cand]

    def settle(self, S):
        """Put the change point half way between the last sample before it and the first
        after it (the samples of S say nothing about where in between it happened)."""
        before = S.order[S.order < self.hyper]
        if len(before):
            prev = int(before.max())
            self.hyper = prev + 1 + (int(self.hyper) - prev - 1) // 2

    def step_key(self, S):
        """The quantity the step is taken in: mask = step_key >= hyper."""
        return S.order

    def mask(self, S):
        """1 from the change point on (hyper None: everywhere)."""
        if self.hyper is None:
            return np.ones(S.n)
        return (S.order >= self.hyper).astype(float)

    def offset(self, p, S, st):
        return p[:, None, :] * self.mask(S)[None, :, None]

    def locate(self, S):
        """Where the change point lies: (file, time of the first sample after it, time
        of the last sample before it or None)."""
        i = np.nonzero(S.order >= self.hyper)[0]
        j = np.nonzero(S.order < self.hyper)[0]
        if len(i):
            k = i[np.argmin(S.order[i])]
            before = None
            if len(j):
                kb = j[np.argmax(S.order[j])]
                if S.file_index[kb] == S.file_index[k]:
                    before = float(S.time_s[kb])
            self.where = (S.file_names[S.file_index[k]], float(S.time_s[k]), before)

    def describe(self, p, model=None):
        out = {"step_nT": np.asarray(p, float).tolist()}
        if self.where is not None:
            out.update({"file": self.where[0], "first_sample_after_s": self.where[1],
                        "last_sample_before_s": self.where[2]})
        return out

    def to_flight(self, p, values, options, model):
        b = values["b_poly_nT"]
        b[0] = b[0] + np.asarray(p, float)
        values["b_poly_nT"] = b


class TimeDrift(Effect):
    """A bias drifting linearly in time within each file (creep, ageing, a slow warm-up
    that no telemetry channel follows). The competitor of every slow explanation: where
    temperature rises monotonically, a temperature term and a time drift look alike, and
    only the shape of the curve tells them apart. Parameter: the drift (3, nT/s, frame
    axes). Flight form: none; a drift in time is not predictable in flight (re-estimate
    the offset, or find the channel that drives it)."""

    name = "time_drift"
    title = "bias drifting linearly in time"
    physics = "the offset creeps with time itself, not with any telemetry channel"
    flight_form = "no chain stage: the offset drifts in time; re-estimate it in flight"
    in_chain = False
    stage = "offset"
    n_params = 3

    def __init__(self, scale):
        super().__init__()
        self.scale = float(scale)      # internal parameter = nT at `scale` seconds

    def explained_by(self):
        return ["time since the start of the file"]

    @staticmethod
    def elapsed(S):
        t0 = np.array([f.time_s[0] if len(f.time_s) else 0.0 for f in S.files])
        return S.time_s - t0[S.file_index]

    @classmethod
    def candidates(cls, ctx):
        if any(isinstance(e, TimeDrift) for e in ctx.effects):
            return [], "already in the model"
        S = ctx.samples
        el = cls.elapsed(S)
        sd = float(np.std(el))
        if sd <= 0:
            return [], "no time span"
        return [cls(sd)], ""

    def offset(self, p, S, st):
        return p[:, None, :] * (self.elapsed(S) / self.scale)[None, :, None]

    def describe(self, p, model=None):
        return {"drift_nT_per_s": (np.asarray(p, float) / self.scale).tolist()}


class SetResetRotation(Effect):
    """SET/RESET rotation error: the RESET reading is taken a few ms after the SET one;
    if the body turns meanwhile, (SET - RESET)/2 is the field turned by half that angle,
    an error W (w x B) (delay/2) in the reading, i.e. exactly -c (w x B) after M. Regressor:
    w_f x B from the gyro (rate_*_dps; the boom sensor's rate is H^T w). Parameter:
    c = delay/2 * pi/180 (s rad/deg). Flight form: the `sr_compensation` option, block
    sr_comp_s_per_deg, B += c (w_f x B) after M."""

    name = "set_reset_rotation"
    title = "SET/RESET rotation error (rate x field)"
    physics = ("the RESET reading comes a few ms after the SET one, so a turning body "
               "rotates the SET/RESET field by half the turn in that time")
    flight_form = "sr_compensation option: block sr_comp_s_per_deg, B += c (w_f x B) after M"
    stage = "calibrated"
    order = 2
    n_params = 1
    prior = 1       # every SET/RESET part has a delay; a time offset is only a hypothesis

    def __init__(self, scale):
        super().__init__()
        self.scale = float(scale)      # internal parameter = nT at rms rate and field

    def explained_by(self):
        return ["rate_x_dps, rate_y_dps, rate_z_dps x field"]

    @classmethod
    def candidates(cls, ctx):
        S = ctx.samples
        if any(isinstance(e, SetResetRotation) for e in ctx.effects):
            return [], "already in the model"
        if not S.spec.set_reset:
            return [], "not a SET/RESET sensor"
        if S.rate_frame_dps is None:
            return [], "no rate_x/y/z_dps columns"
        w_rms = _rms(np.linalg.norm(S.rate_frame_dps, axis=1))
        if w_rms < 0.05:
            return [], "the body hardly turns"
        x_rms = _rms(np.linalg.norm(S.x, axis=1))
        return [cls(1.0 / max(w_rms * x_rms, 1e-9))], ""

    def calibrated(self, p, S, B, st):
        if S.rate_frame_dps is None:      # no gyro in the file: the chain takes w = 0
            return B
        c = p[:, 0] * self.scale
        w = S.rate_frame_dps[None, :, :]
        return B + c[:, None, None] * np.cross(w, B)

    def calibrated_jvp(self, p, S, dB):
        """The derivative of `calibrated` along field changes dB (n, 3, C): the stage is
        linear in B, dB + c (w x dB)."""
        if S.rate_frame_dps is None:
            return dB
        c = float(np.asarray(p).reshape(-1)[0]) * self.scale
        w = S.rate_frame_dps[:, :, None]
        wx = np.stack([w[:, 1] * dB[:, 2] - w[:, 2] * dB[:, 1],
                       w[:, 2] * dB[:, 0] - w[:, 0] * dB[:, 2],
                       w[:, 0] * dB[:, 1] - w[:, 1] * dB[:, 0]], axis=1)
        return dB + c * wx

    def calibrated_columns(self, p, S, B):
        """d calibrated / d p (n_params, n, 3) at the field B before the stage."""
        if S.rate_frame_dps is None:
            return np.zeros((1,) + B.shape)
        return (self.scale * np.cross(S.rate_frame_dps, B))[None]

    def c_s_per_deg(self, p):
        return float(np.asarray(p).reshape(-1)[0] * self.scale)

    def describe(self, p, model=None):
        c = self.c_s_per_deg(p)
        return {"sr_comp_s_per_deg": c, "set_reset_delay_ms": 2 * c * 180 / math.pi * 1e3}

    def to_flight(self, p, values, options, model):
        options["sr_compensation"] = True
        values["sr_comp_s_per_deg"] = np.array(self.c_s_per_deg(p))

    @classmethod
    def from_flight(cls, sv, options, S, info):
        if not options.sr_compensation:
            return []
        w = S.rate_frame_dps
        w_rms = _rms(np.linalg.norm(w, axis=1)) if w is not None else 1.0
        x_rms = _rms(np.linalg.norm(S.x, axis=1))
        scale = 1.0 / max(w_rms * x_rms, 1e-9)
        return [(cls(scale), np.array([float(sv["sr_comp_s_per_deg"]) / scale]))]


class TimeOffset(Effect):
    """A time offset between the magnetometer and the reference: the sensor samples the
    field dt after its time stamp, so B_cal is compared with the reference dt later
    (per file, where the field moves; static positions give nothing). Flight form: none;
    it is an alignment of the ground data (shift the time stamps). With an inertially
    fixed field it looks like the SET/RESET rotation error (both are w x B); that one is
    preferred where both fit equally.

    The reference between its samples, from the slopes to the next (s_f) and from the
    previous sample (s_b): ref + dt r + g c, r = (s_f + s_b) / 2 (the central rate) and
    c = (s_f - s_b) / 2 (the slope's change at the sample; at the end of a run, one slope
    alone: r = that slope, c = 0). Parameters dt and g (internal units: nT at the rms
    field rate). Scored (the significance rule, the choice among candidates) in the form
    of the reference LINEARLY INTERPOLATED dt later, ref + dt s_f (dt > 0) or
    ref + dt s_b (dt < 0), i.e. g = |dt| (score_directions; the sign scanned): the
    simulator's rotations (attitude slerped between samples) are exactly that. Once
    accepted, the model fits dt and g freely (the interpolation is one point of that).

    On a NOISY reference (review #20b F6) the interpolation (1 - a) ref_k + a ref_k+1,
    a = dt / step, averages two samples' white noise (variance (1 - a)^2 + a^2 < 1 of
    one): any dt between samples lowered the residual, on training and held-out rows
    alike (60 nT of reference noise at 1 Hz gave an "offset" of 0.24 s with none in the
    data). That averaging is all in the g c part: c's noise shares the sample's own n_k
    with the residual, r's noise, (n_k+1 - n_k-1) / 2 h, shares nothing with either. So
    the candidate must also beat its NOISE-MATCHED NULL (null_params: g alone, which
    averages the noise as well as any interpolation can, the same averaging applied
    symmetrically): dt and g free against g alone, by the same significance rule
    (generator.trace.scoring.Score.judge). The dt reported is the fitted central-rate
    coefficient, which the noise averaging does not pull; its one bias, the errors in
    variables of r's own noise (a factor rate^2 / (rate^2 + sigma_ref^2 / 2 h^2): a 0.3 s
    offset read 0.246 s on a 60 nT reference at 1 Hz), the fit takes out
    (regressor_noise; generator.trace.reference_noise)."""

    name = "time_offset"
    title = "time offset between magnetometer and reference"
    physics = ("the magnetometer's time stamps are off against the reference's, so a "
               "moving field is compared with the reference of another moment")
    flight_form = ("no chain stage: a ground-data alignment (shift the magnetometer or "
                   "reference time stamps by dt)")
    in_chain = False
    stage = "reference"
    n_params = 2                # dt, g
    null_params = (1,)          # g: what the noise-matched null fits

    def __init__(self, scale):
        super().__init__()
        self.scale = float(scale)      # internal parameter = nT at the rms field rate
        self.hyper = 1.0

    @property
    def n_dof(self) -> int:
        return 1                # the scored form: dt (its sign scanned)

    def explained_by(self):
        return ["reference field rate (reference interpolated dt later)"]

    @classmethod
    def candidates(cls, ctx):
        S = ctx.samples
        if any(isinstance(e, TimeOffset) for e in ctx.effects):
            return [], "already in the model"
        vec = S.kind == 0
        if vec.sum() < 10:
            return [], "no reference vectors"
        r = _rms(np.linalg.norm(S.ref_rate[vec, 0], axis=1))
        if r <= 0:
            return [], "the reference field does not move"
        return [cls(1.0 / r)], ""

    def scan_grid(self, S):
        return [1.0, -1.0]        # dt > 0 (forward slopes) or dt < 0 (backward slopes)

    def score_directions(self) -> np.ndarray:
        """(n_params, 1): the scored form in the parameters: dt (1, |1|) x dt, the
        reference interpolated dt later on the scanned side."""
        return np.array([[1.0], [1.0 if (self.hyper or 1.0) >= 0 else -1.0]])

    @staticmethod
    def rate_and_change(S):
        """(r, c) (n, 3) nT/s: the central rate and the slope's change (class docstring)."""
        sf, sb = S.ref_rate[:, 0, :], S.ref_rate[:, 1, :]
        hf, hb = np.any(sf != 0, axis=1)[:, None], np.any(sb != 0, axis=1)[:, None]
        both = hf & hb
        r = np.where(both, 0.5 * (sf + sb), np.where(hf, sf, sb))
        c = np.where(both, 0.5 * (sf - sb), 0.0)
        return r, c

    def reference_shift(self, p, S):
        r, c = self.rate_and_change(S)
        dt, g = p[:, 0] * self.scale, p[:, 1] * self.scale
        return dt[:, None, None] * r[None] + g[:, None, None] * c[None]

    def regressor_noise(self, S):
        """The reference's white noise in r (errors in variables, the class docstring):
        per vector sample with both slopes and axis, sigma_ref^2 (1 / h_f^2 + 1 / h_b^2)
        / 4 in (nT/s)^2 (sigma_ref^2 / 2 h^2 for equal steps), times scale^2; uncorrelated
        with the residual's noise and with c's for equal steps (so g has none to take
        out: its noise is the averaging the null matches). At the ends of runs (one
        slope) none is counted."""
        from generator.trace.reference_noise import reference_noise_var, reference_steps
        var = reference_noise_var(S)
        iv = S.idx[0]
        if len(iv) == 0:
            return np.zeros(self.n_params)
        both = np.all(np.any(S.ref_rate[iv] != 0, axis=2), axis=1)
        h = reference_steps(S)[iv]
        sig2 = np.zeros((len(iv), 3))
        for fi, v in var.items():
            sig2[S.file_index[iv] == fi] = v
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(both & np.all(np.isfinite(h) & (h > 0), axis=1),
                         0.25 * (1.0 / h[:, 0] ** 2 + 1.0 / h[:, 1] ** 2), 0.0)
        return np.array([float(np.sum(sig2.sum(axis=1) * w)) * self.scale ** 2, 0.0])

    def dt_s(self, p):
        return float(np.asarray(p).reshape(-1)[0] * self.scale)

    def describe(self, p, model=None):
        return {"time_offset_s": self.dt_s(p)}


class LaggedChannelBias(ChannelBias):
    """A bias that follows a telemetry channel through a first-order lag: a heater warming
    a board (the offset follows the heater's temperature, not its current), a load whose
    field builds up as a part warms or magnetises. Regressor: the channel through the
    chain's first-order recursion ch_f += dt/(tau + dt) (ch - ch_f), run over each file's
    whole series; tau scanned on a log grid (chosen inside each training fold), then
    refined on all the data. Parameters: C (3, nT per unit), and an offset where only
    some files carry the channel, as ChannelBias. A pure delay of a few samples is a lag
    of about that time constant to this regressor. Flight form: none yet (a new chain
    stage, a filter state per channel, see flight_form)."""

    name = "lagged_channel_bias"
    title = "bias following a telemetry channel through a first-order lag"
    physics = ("a heater or a load warms a board or a part: the offset follows the channel "
               "with a time constant, not at once")
    flight_form = ("lagged_channels option: blocks C_lag_nT_per_unit (3 x the lagged "
                   "channels) and lag_channel_tau_s; a first-order filter state per channel "
                   "in the sensor's state, ch_f += dt/(tau + dt) (ch - ch_f) (the thermal "
                   "lag's recursion), then x -= C_lag ch_f")
    in_chain = True
    n_hyper = 1
    GRID = 10

    def __init__(self, channel, scale, present=None):
        super().__init__(channel, scale, present)
        self.hyper = None

    def explained_by(self):
        return [f"{self.channel} through a first-order lag"]

    def time_constant_s(self, p):
        return float(self.hyper) if self.hyper is not None else None

    @classmethod
    def candidates(cls, ctx):
        have = {e.channel for e in ctx.effects if isinstance(e, ChannelBias)}
        base, why = ChannelBias.candidates(ctx)
        out = [cls(e.channel, e.scale, ctx.samples.channel_present.get(e.channel)
                   if e.partial else None) for e in base if e.channel not in have]
        return out, ("" if out else why or "every varying channel is in the model")

    def scan_grid(self, S):
        dts = [np.median(np.diff(f.time_s)) for f in S.files if len(f.time_s) > 1]
        spans = [np.ptp(f.time_s) for f in S.files if len(f.time_s) > 1]
        lo = max(2.0 * float(np.min(dts)) if dts else 1.0, 0.05)
        hi = max(0.25 * float(np.max(spans)) if spans else 10 * lo, 4 * lo)
        return list(np.exp(np.linspace(math.log(lo), math.log(hi), self.GRID)))

    def refine_grid(self, S, best):
        return list(best * np.exp(np.linspace(-0.3, 0.3, 7)))

    def lagged(self, S):
        out = np.zeros(S.n)
        for fi, series in enumerate(S.files):
            sel = S.file_index == fi
            v = series.channels.get(self.channel)
            if not sel.any() or v is None:
                continue
            cache = series.__dict__.setdefault("_chlag_cache", {})
            key = (self.channel, round(float(self.hyper), 12))
            f = cache.get(key)
            if f is None:
                t = series.time_s
                if _cache_full(cache, len(t), 256):
                    cache.clear()
                f = cache[key] = lag_filter(t, v, self.hyper)
            out[sel] = f[S.file_row[sel]]
        return out

    def offset(self, p, S, st):
        ch = self.lagged(S) / self.scale
        out = p[:, None, :3] * ch[None, :, None]
        if self.partial:
            has = S.channel_present[self.channel].astype(float)
            out = out + p[:, None, 3:6] * has[None, :, None]
        return out

    def describe(self, p, model=None):
        return {**super().describe(p, model), "tau_s": float(self.hyper)}

    def to_flight(self, p, values, options, model):
        options.setdefault("lagged_channels", []).append(self.channel)
        C = values.get("C_lag_nT_per_unit")
        col = self.C_nT_per_unit(p).reshape(3, 1)
        values["C_lag_nT_per_unit"] = col if C is None else np.hstack([C, col])
        tau = values.get("lag_channel_tau_s")
        values["lag_channel_tau_s"] = np.append(np.zeros(0) if tau is None else tau,
                                                float(self.hyper))
        if self.partial:   # the files that carry the channel are the operating condition
            values["b_poly_nT"][0] = values["b_poly_nT"][0] + np.asarray(p, float)[3:6]

    @classmethod
    def from_flight(cls, sv, options, S, info):
        out = []
        lagged = getattr(options, "lagged_channels", ())
        if not lagged:
            return out
        C = np.asarray(sv["C_lag_nT_per_unit"], float).reshape(3, -1)
        taus = np.asarray(sv["lag_channel_tau_s"], float).reshape(-1)
        for j, ch in enumerate(lagged):
            v = S.channels.get(ch)
            sd = float(np.std(v)) if v is not None and len(v) else 1.0
            sd = sd if sd > 0 else 1.0
            e = cls(ch, sd)
            e.hyper = float(taus[j])
            out.append((e, C[:, j] * sd))
        return out


class ChannelScale(Effect):
    """A scale factor that follows a telemetry channel (a supply voltage feeding the
    bridge, a board's temperature seen through a heater current): after the offsets,
    x_i -= g_i ch x_i, per axis. Needs an absolute reference (as the cubic: without one,
    a contraction of the readings shrinks the noise). Parameters: g (3, per unit of the
    channel), internal unit ~1 nT at the field scale and the channel's spread. Flight
    form: none yet (a new chain stage, see flight_form)."""

    name = "channel_scale"
    title = "scale factor following a telemetry channel"
    physics = ("the sensitivity depends on a telemetry quantity (a supply voltage, a "
               "current warming the part): each axis reads (1 + g ch) of its field")
    flight_form = ("channel_scale option: block g_per_unit (3 x the channels), "
                   "x_i -= g_ij ch_j x_i after the channels' offsets, before the cubic (the "
                   "channel joins the sensor's channels, with a zero C column if it only "
                   "scales)")
    in_chain = True
    stage = "transform"
    order = 0
    repeatable = True
    n_params = 3
    prior = -1      # where the data cannot tell it from a bias in the same channel (the
    #                 field held in one direction while the channel moves), the bias, the
    #                 commoner mechanism, is named

    def __init__(self, channel, scale, present=None):
        super().__init__()
        self.channel = channel
        self.scale = float(scale)      # the channel's spread
        # a channel that only some files carry (0 elsewhere): a scale offset h of its own
        # for the files that carry it, so that only its variation counts (as ChannelBias)
        self.partial = present is not None
        self.n_params = 6 if self.partial else 3

    def key(self):
        return f"{self.name}:{self.channel}"

    def explained_by(self):
        return [f"{self.channel} x reading"]

    def scale_offset(self, p):
        """h (3,): the files that carry the channel read (1 - h - g ch) of x (partial)."""
        return np.asarray(p, float)[3:6] / FIELD_SCALE_nT if self.partial else np.zeros(3)

    @classmethod
    def candidates(cls, ctx):
        S = ctx.samples
        if not (S.kind != 2).any():
            return [], "no field reference (positions only): the scale of the reading is free"
        have = {e.channel for e in ctx.effects if isinstance(e, ChannelScale)}
        absolute = S.kind != 2
        f = np.where((S.kind == 0)[:, None], S.ref, S.x)
        u = f / np.maximum(np.linalg.norm(f, axis=1), 1e-9)[:, None]
        from generator.fit.ellipsoid import distinct_rows
        out, why = [], "no varying telemetry channel besides the modelled ones"
        for name, v in S.channels.items():
            if name in have:
                continue
            v = np.asarray(v, float)
            present = S.channel_present.get(name)
            partial = present is not None and not present.all()
            where = present if partial else np.ones(len(v), bool)
            vv = v[where]
            sd = float(np.std(vv)) if len(vv) else 0.0
            if not np.isfinite(sd) or sd <= 1e-12 * max(1.0, float(np.max(np.abs(vv)))):
                continue
            # a scale is told from a bias in the same channel only where the channel
            # moves while the field takes several directions (as the cubic, 6); else
            # g ch x is a bias, plus a contraction of the reading's own noise
            vals, cnt = np.unique(v[absolute & where], return_counts=True)
            moved = absolute & where & (v != vals[np.argmax(cnt)]) if len(vals) else \
                absolute & where
            if distinct_rows(u[moved], 0.1, at_most=6) < 6:
                why = (f"{name}: the field takes fewer than 6 directions while it moves: a "
                       "scale is not separable from a bias")
                continue
            out.append(cls(name, sd, present if partial else None))
        return out, ("" if out else why)

    def g_per_unit(self, p):
        return np.asarray(p, float)[:3] / (FIELD_SCALE_nT * self.scale)

    def transform(self, p, S, x, st):
        p = np.asarray(p, float)
        g = p[:, :3] / (FIELD_SCALE_nT * self.scale)                        # (batch, 3)
        ch = S.channels[self.channel]
        f = g[:, None, :] * ch[None, :, None]
        if self.partial:
            has = S.channel_present[self.channel].astype(float)
            f = f + (p[:, 3:6] / FIELD_SCALE_nT)[:, None, :] * has[None, :, None]
        return x - f * x

    def describe(self, p, model=None):
        out = {"g_per_unit": self.g_per_unit(p).tolist(), "channel_std": self.scale,
               "ppm_per_channel_std": (1e6 * self.g_per_unit(p) * self.scale).tolist()}
        if self.partial:
            out["scale_offset_where_present"] = self.scale_offset(p).tolist()
        return out

    def to_flight(self, p, values, options, model):
        """The channel among the sensor's channels (a zero C column if new), its g by
        channel name (generator.trace.coefficients aligns g_per_unit with the channels
        once every effect is written)."""
        chans = options.setdefault("channels", [])
        if self.channel not in chans:
            chans.append(self.channel)
            C = values.get("C_nT_per_unit")
            values["C_nT_per_unit"] = np.zeros((3, 1)) if C is None else \
                np.hstack([C, np.zeros((3, 1))])
        options["channel_scale"] = True
        # partial: the files that carry the channel read (1 - h - g ch) x = (1 - h)
        # (1 - g / (1 - h) ch) x exactly; the factor (1 - h) per axis is folded into M's
        # columns and the cubic once every effect is written (generator.trace.coefficients)
        h = self.scale_offset(p)
        values.setdefault("_g_by_channel", {})[self.channel] = self.g_per_unit(p) / (1 - h)
        if self.partial:
            values["_axis_factor"] = values.get("_axis_factor", np.ones(3)) * (1 - h)

    @classmethod
    def from_flight(cls, sv, options, S, info):
        if not getattr(options, "channel_scale", False):
            return []
        g = np.asarray(sv["g_per_unit"], float).reshape(3, -1)
        out = []
        for j, ch in enumerate(options.channels):
            if not np.any(g[:, j]):
                continue
            v = S.channels.get(ch)
            sd = float(np.std(v)) if v is not None and len(v) else 1.0
            sd = sd if sd > 0 else 1.0
            out.append((cls(ch, sd), g[:, j] * FIELD_SCALE_nT * sd))
        return out


CATALOGUE = [ChannelBias, ThermalLag, TemperaturePolynomial, CubicNonlinearity, BiasStep,
             TimeDrift, SetResetRotation, TimeOffset, LaggedChannelBias, ChannelScale]


def catalogue_table() -> list:
    """(name, physics, flight form) of every catalogue entry, for docs and reports."""
    return [(c.name, c.physics, c.flight_form) for c in CATALOGUE]
