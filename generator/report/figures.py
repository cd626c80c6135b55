"""The report's figures (matplotlib, Agg backend, no pyplot state): plain arrays in, PNG out.

Each function writes one PNG and returns its path. The numbers drawn always come from
the caller, who puts the same numbers in a table beside the figure (generator.report.report).
Figures are kept few and cheap: one figure per sensor with a grid of subplots, modest dpi.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generator.report.lean_axis import fixed_ticks as _fixed_ticks
from generator.report.lean_axis import lean_ticks as _lean_ticks
from generator.report.lean_axis import ticks_in_view as _ticks_in_view

DPI = 90
_AXIS_COLORS = ("#d62728", "#2ca02c", "#1f77b4")     # X red, Y green, Z blue
_BEFORE, _AFTER = "#bbbbbb", "#1f77b4"


def _figure(w_in, h_in, constrained=False):
    """A figure on the Agg canvas; constrained=True: constrained layout (titles, labels and
    colour bars never overlap; slower to draw, so only where a figure needs it: a colour
    bar). constrained="fixed": one grid of subplots with margins and gaps fixed in inches
    (room for tick labels, axis labels, an axes title and the suptitle; _fixed_margins),
    set once when the figure is saved -- no layout solver (that was half the drawing time
    of a 5 x 3 grid)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from generator.report.agg_text import canvas_class

    fig = Figure(figsize=(w_in, h_in), dpi=DPI,
                 layout="constrained" if constrained is True else None)
    canvas_class()(fig)     # Agg, its strings rasterised once per process (agg_text)
    fig._magcal_fixed = constrained == "fixed"
    return fig


# _fixed_margins, inches: left (tick and axis labels), right, bottom (tick labels and an
# x label), top (the suptitle over an axes title), gaps between rows (an axes title over
# the tick labels of the row above) and between columns (tick and axis labels)
_MARGIN_IN = {"left": 0.75, "right": 0.2, "bottom": 0.55, "top": 0.65, "hgap": 0.75,
              "wgap": 0.75}


def _fixed_margins(fig):
    """Margins and gaps of fig's subplot grid fixed in inches (_MARGIN_IN)."""
    specs = [a.get_subplotspec() for a in fig.axes]
    if not specs or any(s is None for s in specs):
        return
    nrow, ncol = specs[0].get_gridspec().get_geometry()
    w, h = fig.get_size_inches()
    m = _MARGIN_IN
    left, right = m["left"] / w, 1.0 - m["right"] / w
    bottom, top = m["bottom"] / h, 1.0 - m["top"] / h
    ax_h = max((h * (top - bottom) - (nrow - 1) * m["hgap"]) / nrow, 0.1)
    ax_w = max((w * (right - left) - (ncol - 1) * m["wgap"]) / ncol, 0.1)
    fig.subplots_adjust(left=left, right=right, bottom=bottom, top=top,
                        hspace=m["hgap"] / ax_h, wspace=m["wgap"] / ax_w)
    if fig._suptitle is not None:          # its top 0.12 in below the figure's edge
        fig._suptitle.set_y(1.0 - 0.12 / h)


def _title(ax, text, fontsize=9):
    """Axes title as plain text (set_title re-measures every axis on each draw: slow)."""
    ax.text(0.5, 1.02, text, transform=ax.transAxes, ha="center", va="bottom",
            fontsize=fontsize)


def _axes_title(ax, text, fontsize=9):
    """An axes title (ax.get_title() names the axes for the render check) placed at the top
    of the axes without matplotlib's automatic placement: given y, set_title leaves the
    title where it is, whereas the automatic placement measures the tick labels of the axes
    (and of every axes aligned with it) on each draw, a fifth of the time of a grid of
    scatter panels (cProfile, sphere_projections). That placement only ever moves a title
    up, above x tick labels or an x label at the top of the axes or a y offset text; the
    axes given to this have their x axis at the bottom, and their y offset text is turned
    off here (tick labels then show the full values), so the title lands where the
    automatic placement would put it."""
    from matplotlib.ticker import ScalarFormatter
    fmt = ax.yaxis.get_major_formatter()
    if isinstance(fmt, ScalarFormatter):
        fmt.set_useOffset(False)
    ax.set_title(text, fontsize=fontsize, y=1.0)


# ---- drawing several figures at once -----------------------------------------------------
# Inside `with parallel():` the figure functions decorated with @_deferrable only record
# their call and return the path(s) they will write; leaving the block draws them all, in
# forked worker processes (one per core), since drawing is most of a report's time.
_DEFERRED = None
# a drawer started before the figures were asked for (generator.report.drawer), which
# parallel() hands its calls to; None: parallel() forks its own workers
_EARLY = None


def _lean(fn):
    """fn, a figure function, run lean; two costs of matplotlib that are not drawing:

    * rcParams["patch.facecolor"] resolved to the colour it names. matplotlib's default is
      "C0", the first colour of the colour cycle, which every Patch resolves when it is
      made -- the four spines of each axes among them -- by building the cycle's colour
      list anew (Cycler.by_key): 5 % of the report's figure time (py-spy). Resolved once
      per figure here: the same colour.
    * Python's cyclic garbage collector paused while the figure is built and drawn (and
      restored after). A figure makes ~10^5 small objects; each allocation threshold
      crossed runs a collection, which walks everything the process holds (the campaign's
      arrays and the fit besides): ~15 % of the figure time (bench/bench_figures.py). The
      figure's own reference cycles are freed by the next collection after it; a paused
      collector holds at most one figure's garbage."""
    import functools

    @functools.wraps(fn)
    def run(*args, **kwargs):
        import gc

        import matplotlib
        from matplotlib.colors import to_hex, to_rgba
        face = to_hex(to_rgba(matplotlib.rcParams["patch.facecolor"]), keep_alpha=True)
        collecting = gc.isenabled()
        gc.disable()
        try:
            with matplotlib.rc_context({"patch.facecolor": face}):
                return fn(*args, **kwargs)
        finally:
            if collecting:
                gc.enable()
    return run


def _defer(fn, args, kwargs):
    """Record a figure call inside parallel(); with a drawer started early, also send it
    there at once (its workers draw while this process goes on)."""
    _DEFERRED.append((fn, args, kwargs))
    if _EARLY is not None:
        _EARLY.send(len(_DEFERRED) - 1, fn, args, kwargs)


def _deferrable(paths_of):
    def deco(fn):
        fn = _lean(fn)

        def wrapper(*args, **kwargs):
            if _DEFERRED is None:
                return fn(*args, **kwargs)
            _defer(fn, args, kwargs)
            return paths_of(*args, **kwargs)
        wrapper.__name__, wrapper.__doc__ = fn.__name__, fn.__doc__
        wrapper.draw_now = fn
        return wrapper
    return deco


def _warm_up():
    fig = _figure(1.0, 1.0)
    fig.text(0.5, 0.5, "0.5 °C")
    fig.canvas.draw()


def _run_deferred(k):
    fn, args, kwargs = _DEFERRED[k]
    fn(*args, **kwargs)
    return k


def _draw_or_report(k) -> bool:
    """Draw deferred figure k; False if its drawing raised (the parent draws it again and
    raises the error there: parallel.__exit__)."""
    try:
        _run_deferred(k)
    except Exception:
        return False
    return True


class parallel:
    """Draw the figures requested inside the block together, on up to `workers` cores
    (generator.forked: plain forked children; a figure whose child failed is drawn again
    in this process, where its error is raised as usual; an interrupt kills the
    children).

    The figures are handed out as the children ask for them, not dealt in advance
    (forked_map's on_demand), so a child that drew an expensive figure draws fewer of the
    rest. A figure no child reports as drawn (its child failed or died) is drawn here.

    Within generator.report.drawer.early_drawer() the calls go to that drawer instead,
    each as soon as it is recorded (matplotlib already imported there, the figures drawn
    while the block goes on); what it did not draw is drawn as above."""

    def __init__(self, workers=None):
        from generator.forked import default_workers
        self.workers = workers or default_workers()

    def __enter__(self):
        global _DEFERRED
        _DEFERRED = []
        return self

    def __exit__(self, exc_type, exc, tb):
        global _DEFERRED
        calls = _DEFERRED
        try:
            if exc_type is not None or not calls:
                return False
            global _EARLY
            early, _EARLY = _EARLY, None        # used once
            done = early.finish(len(calls)) if early is not None else None
            if done is not None:                # drawn by the drawer, but for its failures
                for k in [k for k, ok in enumerate(done) if not ok]:
                    _run_deferred(k)
                return False
            from contextlib import closing

            from generator.forked import forked_map
            # on demand: each child takes the next figure when it has finished one; a
            # figure whose child died is drawn here by forked_map, one that raised in a
            # child is drawn here again after the others, where its error is raised;
            # _warm_up: matplotlib and its fonts loaded once, before the children fork
            with closing(forked_map(_draw_or_report, range(len(calls)), self.workers,
                                    before_fork=_warm_up, on_demand=True)) as done:
                failed = [k for k, ok in enumerate(done) if not ok]
            for k in failed:
                _run_deferred(k)
        finally:
            _DEFERRED = None
        return False


EMPTY_AXES_KEY = "magcal-empty-axes"   # PNG text chunk: visible axes with nothing drawn


def empty_axes(fig) -> list:
    """Titles (or indices) of the visible axes of fig with no data drawn in them."""
    return [a.get_title() or str(k) for k, a in enumerate(fig.axes)
            if a.get_visible() and not a.has_data()]


def _save(fig, path) -> Path:
    """Write the PNG; the titles of axes left empty go into its text chunk EMPTY_AXES_KEY
    (read by the render check, host_tests/test_report_render.py)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if getattr(fig, "_magcal_fixed", False):
        _fixed_margins(fig)
    _ticks_in_view(fig)
    import matplotlib

    # Drawn on the figure's Agg canvas at DPI (the figure's own dpi: _figure), as savefig
    # would, and written as an RGB PNG when every pixel is opaque (the figures' white
    # background): the same pixels as savefig's RGBA PNG, with a quarter less to compress.
    # Text chunks: matplotlib's "Software", EMPTY_AXES_KEY. The encoding: _png_bytes.
    fig.set_dpi(DPI)
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    pixels = rgba[..., :3] if (rgba[..., 3] == 255).all() else rgba
    texts = {"Software": f"Matplotlib version{matplotlib.__version__}, https://matplotlib.org/",
             EMPTY_AXES_KEY: "; ".join(empty_axes(fig))}
    path.write_bytes(_png_bytes(pixels, texts, DPI))
    return path


PNG_ZLIB_LEVEL = 3


def _png_bytes(pixels, texts, dpi) -> bytes:
    """A PNG (8 bits per channel, RGB or RGBA by pixels' last axis) of pixels (H, W, 3|4
    uint8), lossless: every row with PNG filter 0 (none) and zlib level PNG_ZLIB_LEVEL.
    PIL's encoder tries the five filters on each row (adaptive): on the report's figures
    (large flat areas, thin lines) that took 2.5-3x the time of compressing the rows as
    they are (three of the thermal campaign's PNGs: 15-33 ms against 5-13 ms each), for
    files from 20 % smaller to 21 % larger (bench/bench_figures.py). texts: tEXt chunks (iTXt,
    UTF-8, when a value is not Latin-1), as PIL writes and reads them; dpi: the pHYs chunk
    as PIL writes it."""
    import struct
    import zlib

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind))))

    h, w, c = pixels.shape
    rows = np.zeros((h, 1 + w * c), np.uint8)       # column 0: filter type 0 per row
    rows[:, 1:] = pixels.reshape(h, w * c)
    ppm = int(dpi / 0.0254 + 0.5)
    out = [b"\x89PNG\r\n\x1a\n",
           chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2 if c == 3 else 6, 0, 0, 0))]
    for key, value in texts.items():
        try:
            out.append(chunk(b"tEXt", key.encode("latin-1") + b"\0" + value.encode("latin-1")))
        except UnicodeEncodeError:
            out.append(chunk(b"iTXt", key.encode("latin-1") + b"\0\0\0\0\0"
                             + value.encode("utf-8")))
    out += [chunk(b"pHYs", struct.pack(">IIB", ppm, ppm, 1)),
            chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_ZLIB_LEVEL)),
            chunk(b"IEND", b"")]
    return b"".join(out)


# =======================================================================================
# Calibration report
# =======================================================================================
def coefficient_grid(path, title, names, units, level_T, level_val, level_sig, curve_T,
                     curve_val, curve_band, t_range=None) -> Path:
    """Temperature dependence of the 12 calibration coefficients (seed 000 fig. 24-25).

    names/units: 12 labels (b_x, b_y, b_z, m_xx .. m_zz); level_T (L,), level_val and
    level_sig (L, 12): per-level estimates with 1-sigma (points with error bars);
    curve_T (G,), curve_val (G, 12): the fitted polynomial; curve_band (G, 12) its 1-sigma
    (shaded; inf/NaN: not drawn). Layout: column 1 the offsets, columns 2-4 the matrix.
    """
    return coefficient_grids([dict(path=path, title=title, names=names, units=units,
                                   level_T=level_T, level_val=level_val, level_sig=level_sig,
                                   curve_T=curve_T, curve_val=curve_val, curve_band=curve_band,
                                   t_range=t_range)])[0]


def coefficient_grids(jobs) -> list:
    """Several coefficient_grid figures, all on one reused figure (_coefficient_grids);
    inside `parallel()` one deferred call, not split over the workers: each part would
    build the figure again (~0.25 s CPU more for the thermal campaign's five sensors,
    bench/bench_figures.py), and parallel() hands the other figures to the other worker
    meanwhile."""
    if _DEFERRED is None:
        return _coefficient_grids(jobs)
    _defer(_coefficient_grids, (jobs,), {})
    return [Path(j["path"]) for j in jobs]


@_lean
def _coefficient_grids(jobs) -> list:
    """Several coefficient_grid figures (one per sensor) drawn on one reused figure: the
    axes and their ticks are built once, which halves the cost of every further sensor.
    jobs: list of dicts with coefficient_grid's arguments. Returns the paths."""
    fig = _figure(13.0, 7.2)
    # the same x limits set on every axes (below) instead of shared x axes: matplotlib
    # walks the share group on every look at a shared axes' limits; tick labels on the
    # bottom row only, as sharex=True puts them
    axes = fig.subplots(3, 4)
    for ax in axes[:-1].ravel():
        ax.tick_params(axis="x", labelbottom=False)
    order = [axes[c, 0] for c in range(3)] + [axes[i, j + 1] for i in range(3) for j in range(3)]
    titles = []
    for ax in order:
        titles.append(ax.text(0.5, 1.02, "", transform=ax.transAxes, ha="center",
                              va="bottom", fontsize=9))
        _lean_ticks(ax)
        ax.tick_params(labelsize=7)
        ax.yaxis.get_major_formatter().set_useOffset(False)
        ax.grid(alpha=0.3, lw=0.5)
    for ax in axes[-1]:
        ax.set_xlabel("sensor temperature, °C", fontsize=8)
    sup = fig.suptitle("", fontsize=11)
    fig.subplots_adjust(left=0.06, right=0.99, top=0.91, bottom=0.08, wspace=0.32, hspace=0.32)
    paths = []
    made = [None] * len(order)      # per axes: its artists and the data shape they show
    for job in jobs:
        new_legend = False
        level_T = np.asarray(job["level_T"], float).reshape(-1)
        level_val = np.asarray(job["level_val"], float).reshape(len(level_T), 12)
        level_sig = np.asarray(job["level_sig"], float).reshape(len(level_T), 12)
        curve_T = np.asarray(job["curve_T"], float)
        curve_val = np.asarray(job["curve_val"], float).reshape(len(curve_T), 12)
        curve_band = np.asarray(job["curve_band"], float).reshape(len(curve_T), 12)
        t_range = job.get("t_range")
        for c, ax in enumerate(order):
            band = curve_band[:, c]
            ok = np.isfinite(band)
            sig = np.where(np.isfinite(level_sig[:, c]), level_sig[:, c], 0.0)
            lo_hi = [curve_val[:, c]]
            if ok.any():
                lo_hi += [curve_val[ok, c] - band[ok], curve_val[ok, c] + band[ok]]
            if len(level_T):
                lo_hi += [level_val[:, c] - sig, level_val[:, c] + sig]
            shape = (bool(ok.any()), bool(len(level_T)))
            if made[c] is not None and made[c]["shape"] == shape:
                # the artists of the previous sensor given this sensor's data (making
                # them anew was half this figure's time): the same artists as new ones
                a = made[c]
                if ok.any():
                    a["fill"].set_data(curve_T[ok], curve_val[ok, c] - band[ok],
                                       curve_val[ok, c] + band[ok])
                a["line"].set_data(curve_T, curve_val[:, c])
                if len(level_T):
                    # as Axes.errorbar: the marker line, the two cap lines at y -/+ sigma
                    # and the bars from one to the other (vlines)
                    data_line, (cap_lo, cap_hi), (bars,) = a["errorbar"]
                    low, high = level_val[:, c] - sig, level_val[:, c] + sig
                    data_line.set_data(level_T, level_val[:, c])
                    cap_lo.set_data(level_T, low)
                    cap_hi.set_data(level_T, high)
                    bars.set_segments(np.stack([np.stack([level_T, low], -1),
                                                np.stack([level_T, high], -1)], 1))
                for p in list(ax.patches):       # the span: drawn last, as before
                    p.remove()
            else:
                for a in list(ax.lines) + list(ax.collections) + list(ax.patches):
                    a.remove()
                ax.containers.clear()
                made[c] = {"shape": shape}
                if c == 0:
                    new_legend = True
                if ok.any():
                    made[c]["fill"] = ax.fill_between(
                        curve_T[ok], curve_val[ok, c] - band[ok], curve_val[ok, c] + band[ok],
                        color="#1f77b4", alpha=0.25, lw=0, label="polynomial ±1σ")
                made[c]["line"], = ax.plot(curve_T, curve_val[:, c], "-", color="#1f77b4",
                                           lw=1.3, label="fitted polynomial")
                if len(level_T):
                    made[c]["errorbar"] = ax.errorbar(
                        level_T, level_val[:, c], yerr=sig, fmt="o", ms=3.5,
                        color="#d62728", ecolor="#d62728", capsize=2, lw=1,
                        label="per-level estimate ±1σ")
            if t_range is not None:
                ax.axvspan(*t_range, color="#2ca02c", alpha=0.04, lw=0)
            y = np.concatenate([np.ravel(v) for v in lo_hi])
            y = y[np.isfinite(y)]
            if y.size:
                lo, hi = float(y.min()), float(y.max())
                pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi) * 1e-3, 1e-9)
                ax.set_ylim(lo - pad, hi + pad)
            xs = np.concatenate([curve_T, level_T])
            if xs.size:
                span = float(xs.max() - xs.min()) or 1.0
                ax.set_xlim(float(xs.min()) - 0.04 * span, float(xs.max()) + 0.04 * span)
            names, units = job["names"], job["units"]
            titles[c].set_text(f"{names[c]} ({units[c]})" if units[c] else names[c])
        if new_legend:          # its handles made anew (else: the same, given new data)
            leg = order[0].get_legend()
            if leg is not None:
                leg.remove()
            order[0].legend(fontsize=6, loc="best")
        sup.set_text(job["title"])
        paths.append(_save(fig, job["path"]))
    return paths


@_deferrable(lambda path, *a, **k: Path(path))
def rms_bars(path, title, rows) -> Path:
    """|B| RMS before and after calibration (seed 000 fig. 27-29), log scale.

    rows: list of (row title, [panel, ...]) with panel = {"title", "labels", "before",
    "after", optional "xlabel"} (before/after: RMS in nT per label). One row of panels
    per sensor.
    """
    ncol = max(len(p) for _, p in rows)
    fig = _figure(5.2 * ncol, 2.3 * len(rows) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(rows), ncol, squeeze=False))
    for r, (rt, panels) in enumerate(rows):
        for c in range(ncol):
            ax = axes[r, c]
            if c >= len(panels):
                ax.set_visible(False)
                continue
            p = panels[c]
            x = np.arange(len(p["labels"]))
            before = np.asarray(p["before"], float)
            after = np.asarray(p["after"], float)
            ok = np.concatenate([before, after])
            ok = ok[np.isfinite(ok) & (ok > 0)]
            lo = float(ok.min()) / 2 if ok.size else 0.1
            hi = float(ok.max()) * 2 if ok.size else 1.0
            ax.bar(x - 0.2, before, 0.4, color=_BEFORE, label="before", bottom=0)
            ax.bar(x + 0.2, after, 0.4, color=_AFTER, label="after", bottom=0)
            ax.set_yscale("log")
            ax.set_ylim(lo, hi)
            _lean_ticks(ax, log_y=True)
            _fixed_ticks(ax.xaxis, x, p["labels"], fontsize=7,
                         rotation=0 if len(x) <= 14 else 60)
            if p.get("xlabel"):
                ax.set_xlabel(p["xlabel"], fontsize=7, labelpad=1)
            ax.tick_params(axis="y", labelsize=7)
            _title(ax, f"{rt}: {p['title']}")
            ax.set_ylabel("nT", fontsize=7)
            ax.grid(axis="y", alpha=0.3, lw=0.5)
    hnd, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(hnd, lab, loc="upper right", ncol=2, fontsize=7, frameon=False)
    h = 2.3 * len(rows) + 0.6
    fig.suptitle(title, fontsize=11, y=1 - 0.12 / h)
    fig.subplots_adjust(left=0.07, right=0.99, top=1 - 0.75 / h, bottom=0.45 / h,
                        wspace=0.15, hspace=0.55)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def angle_before_after(path, title, before_deg, after_deg, x=None, xlabel="sample") -> Path:
    """Angle between two magnetometers' vectors before and after the alignment H
    (seed 000 fig. 10): against time (or sample), and as histograms."""
    before = np.asarray(before_deg, float)
    after = np.asarray(after_deg, float)
    x = np.arange(len(before)) if x is None else np.asarray(x, float)
    fig = _figure(11.0, 3.6)
    a1, a2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2, 1]})
    a1.plot(x, before, ".", ms=1.5, color="#888888", label="before (H = I)")
    a1.plot(x, after, ".", ms=1.5, color=_AFTER, label="after H")
    a1.set_yscale("log")
    a1.set_xlabel(xlabel, fontsize=8)
    a1.set_ylabel("angle between vectors, deg", fontsize=8)
    a1.legend(fontsize=7, markerscale=5)
    a1.grid(alpha=0.3, lw=0.5)
    hi = max(float(np.nanmax(before)) if before.size else 1.0, 1e-3)
    bins = np.linspace(0, hi, 41)
    a2.hist(before, bins=bins, color="#888888", alpha=0.7, label="before")
    a2.hist(after, bins=bins, color=_AFTER, alpha=0.8, label="after")
    a2.set_xlabel("angle, deg", fontsize=8)
    a2.set_ylabel("samples", fontsize=8)
    a2.legend(fontsize=7)
    for a in (a1, a2):
        a.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.99, top=0.88, bottom=0.15, wspace=0.25)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def error_maps(path, title, rate_dps, theta_deg, maps, map_titles, unit="nT",
               contour=None) -> Path:
    """SET/RESET offset error maps (seed 000 fig. 12-13): one heatmap per measurement
    time, rate (rows) x angle between field and axis (columns). contour: (value, label)
    drawn as a white line where the map crosses value (e.g. the seed's bound)."""
    maps = [np.asarray(m, float) for m in maps]
    n = len(maps)
    ncol = min(n, 2)
    nrow = (n + ncol - 1) // ncol
    w_in, h_in = 6.0 * ncol, 3.2 * nrow + 0.4
    # margins fixed in inches (_MARGIN_IN: titles clear the labels) with room on the right
    # for the colour bar: no constrained-layout solver (a third of this figure's time)
    fig = _figure(w_in, h_in)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    m, cbar_in = _MARGIN_IN, 1.1            # colour bar 0.15 in wide, its ticks and label
    left, right = m["left"] / w_in, 1.0 - (m["right"] + cbar_in) / w_in
    bottom, top = m["bottom"] / h_in, 1.0 - m["top"] / h_in
    ax_h = max((h_in * (top - bottom) - (nrow - 1) * m["hgap"]) / nrow, 0.1)
    ax_w = max((w_in * (right - left) - (ncol - 1) * m["wgap"]) / ncol, 0.1)
    fig.subplots_adjust(left=left, right=right, bottom=bottom, top=top,
                        hspace=m["hgap"] / ax_h, wspace=m["wgap"] / ax_w)
    cax = fig.add_axes([right + 0.25 / w_in, bottom, 0.15 / w_in, top - bottom])
    vmax = max(float(np.nanmax(m)) for m in maps) or 1.0
    im = None
    for k, ax in enumerate(axes):
        if k >= n:
            ax.set_visible(False)
            continue
        im = ax.imshow(maps[k], origin="lower", aspect="auto", cmap="viridis", vmin=0,
                       vmax=vmax)
        _fixed_ticks(ax.xaxis, range(len(theta_deg)), [f"{t:g}" for t in theta_deg],
                     fontsize=6)
        _fixed_ticks(ax.yaxis, range(len(rate_dps)), [f"{r:g}" for r in rate_dps],
                     fontsize=6)
        ax.set_xlabel("angle between field and axis, deg", fontsize=7)
        ax.set_ylabel("rate, deg/s", fontsize=7)
        _axes_title(ax, map_titles[k], fontsize=8)
        if contour is not None and np.nanmin(maps[k]) < contour[0] < np.nanmax(maps[k]):
            cs = ax.contour(maps[k], levels=[contour[0]], colors="white", linewidths=1.2)
            ax.clabel(cs, fmt={contour[0]: contour[1]}, fontsize=6)
    if im is not None:
        fig.colorbar(im, cax=cax, label=unit)
    else:
        cax.set_visible(False)
    fig.suptitle(title, fontsize=10, y=1.0 - 0.12 / h_in)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def coil_distance(path, title, distance_cm, series, current_A=None) -> Path:
    """Coil interference against distance (seed 000 fig. 5-6), log-log; series:
    {label: values in nT at distance_cm} (NaN: not measured)."""
    d = np.asarray(distance_cm, float)
    fig = _figure(6.5, 4.2)
    ax = fig.subplots()
    for k, (label, v) in enumerate(series.items()):
        v = np.asarray(v, float)
        ok = np.isfinite(v) & (v > 0)
        ax.loglog(d[ok], v[ok], "o-", ms=4, lw=1, label=label, color=f"C{k}")
    from matplotlib.ticker import NullFormatter
    ax.set_xticks(d)
    ax.set_xticklabels([f"{x:g}" for x in d])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("distance coil - magnetometer, cm", fontsize=8)
    ax.set_ylabel("interference |dB|, nT" + (f" at {current_A:g} A" if current_A else ""),
                  fontsize=8)
    ax.grid(alpha=0.3, lw=0.5, which="both")
    ax.legend(fontsize=6)
    ax.tick_params(labelsize=7)
    _axes_title(ax, title, fontsize=10)
    fig.subplots_adjust(left=0.13, right=0.98, top=0.9, bottom=0.13)
    return _save(fig, path)


@_deferrable(lambda path, *a, **k: Path(path))
def residual_causes(path, title, panels) -> Path:
    """Residual against its traced cause: one panel per effect, residual before (grey)
    and after (blue) the model gained the effect, against the explaining quantity.
    panels: [{"title", "xlabel", "x", "before", "after"}]."""
    n = len(panels)
    ncol = min(n, 3)
    nrow = (n + ncol - 1) // ncol
    fig = _figure(4.6 * ncol, 3.1 * nrow + 0.4)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for k, ax in enumerate(axes):
        if k >= n:
            ax.set_visible(False)
            continue
        p = panels[k]
        x = np.asarray(p["x"], float)
        step = max(1, len(x) // 4000)             # thin very long series for speed
        ax.plot(x[::step], np.asarray(p["before"], float)[::step], ".", ms=1.5,
                color="#999999", label="before")
        if p.get("after") is not None:
            ax.plot(x[::step], np.asarray(p["after"], float)[::step], ".", ms=1.5,
                    color=_AFTER, label="after")
        ax.set_xlabel(p.get("xlabel", ""), fontsize=7)
        ax.set_ylabel("residual, nT", fontsize=7)
        _axes_title(ax, p["title"], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3, lw=0.5)
        ax.legend(fontsize=6, markerscale=4)
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.08, right=0.99, top=1 - 0.5 / (3.1 * nrow + 0.4),
                        bottom=0.12 / nrow + 0.04, wspace=0.3, hspace=0.55)
    return _save(fig, path)


# =======================================================================================
# Test plan
# =======================================================================================
def _to_plot(v_ned):
    """North-east-down -> plot axes (east, north, up), so that up is up on the page."""
    v = np.asarray(v_ned, float)
    return np.array([v[..., 1], v[..., 0], -v[..., 2]]).T if v.ndim > 1 else \
        np.array([v[1], v[0], -v[2]])


def positions_sheet(path, plan) -> Path:
    """One sheet, a drawing per position: the body cube in the lab with its axes, which is
    up, magnetic north on the floor, and the field vector; the expected body-axis field in
    the caption of each drawing."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from generator.campaign.plan import lab_field_ned

    fig = _figure(12.5, 10.5)
    b_lab = _to_plot(lab_field_ned(1.0, plan.inclination_deg))
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5)
                        for z in (-0.5, 0.5)]) * 0.9
    faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4),
             (1, 3, 7, 5)]
    # which body axis each face is normal to (+ side), for colouring
    face_axis = [(0, -1), (0, +1), (1, -1), (1, +1), (2, -1), (2, +1)]
    for k, p in enumerate(plan.positions):
        ax = fig.add_subplot(3, 4, k + 1, projection="3d")
        R = np.asarray(p.R_body_to_ned, float)
        pc = _to_plot((R @ corners.T).T)
        polys, cols = [], []
        for f, (axis, sign) in zip(faces, face_axis):
            polys.append(pc[list(f)])
            base = np.array(matplotlib_color(_AXIS_COLORS[axis]))
            cols.append(tuple(base * 0.55 + 0.45) + ((0.55,) if sign > 0 else (0.12,)))
        ax.add_collection3d(Poly3DCollection(polys, facecolors=cols, edgecolors="#555555",
                                             linewidths=0.4))
        for a in range(3):
            v = _to_plot(R[:, a]) * 1.05
            ax.quiver(0, 0, 0, *v, color=_AXIS_COLORS[a], lw=2, arrow_length_ratio=0.15)
            ax.text(*(v * 1.18), "+" + "XYZ"[a], color=_AXIS_COLORS[a], fontsize=9,
                    fontweight="bold", ha="center", va="center")
        # magnetic north on the floor, up arrow, field
        ax.quiver(-0.9, -1.2, -1.1, 0, 0.9, 0, color="#777777", lw=1.5, arrow_length_ratio=0.2)
        ax.text(-0.9, -0.15, -1.1, "N", color="#555555", fontsize=8)
        ax.quiver(0, 0, 0, *(b_lab * 1.35), color="#9467bd", lw=1.6, linestyle="--",
                  arrow_length_ratio=0.1)
        ax.text(*(b_lab * 1.5), "B", color="#9467bd", fontsize=9, fontweight="bold")
        ax.set_xlim(-1.2, 1.2)
        ax.set_ylim(-1.2, 1.2)
        ax.set_zlim(-1.2, 1.2)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=22, azim=-60)
        ax.set_axis_off()
        b = p.expected_field_body_nT
        ax.set_title(f"{p.number}: {p.up} up, {p.north} north\n"
                     f"B = ({b[0]:.0f}, {b[1]:.0f}, {b[2]:.0f}) nT", fontsize=8.5, pad=0)
    fig.suptitle(f"Unit {plan.unit_id}: twelve positions (lab field {plan.lab_field_nT:.0f} nT, "
                 f"inclination {plan.inclination_deg:g}°)\nUp is up on the page; N: magnetic north on the "
                 "floor; B: the lab field; body axes X red, Y green, Z blue, positive faces "
                 "shaded darker", fontsize=10)
    fig.subplots_adjust(left=0.0, right=1.0, top=0.91, bottom=0.0, wspace=0.0, hspace=0.12)
    return _save(fig, path)


def matplotlib_color(c):
    from matplotlib.colors import to_rgb
    return to_rgb(c)


def profile_figure(path, plan) -> Path:
    """Chamber set-point and predicted board temperature over one position's cycle, with
    the recording windows shaded and the tolerance band; below, the whole program."""
    from generator.campaign.plan import predicted_board_temperature

    t = np.arange(0.0, plan.position_duration_s + plan.sample_period_s, plan.sample_period_s)
    setpoint, board = predicted_board_temperature(plan, t)
    fig = _figure(11.0, 6.0)
    a1, a2 = fig.subplots(2, 1, gridspec_kw={"height_ratios": [3, 1]})
    h = t / 3600.0
    a1.plot(h, setpoint, "-", color="#444444", lw=1.2, label="chamber set-point")
    a1.plot(h, board, "-", color="#d62728", lw=1.2,
            label=f"board (first-order lag, τ = {plan.board_tau_s / 60:g} min)")
    first = plan.positions[0].number
    for it in plan.chamber_program():
        if it["position"] != first or it["action"] != "hold":
            continue
        a1.axvspan(it["record_from_s"] / 3600, it["record_to_s"] / 3600, color="#2ca02c",
                   alpha=0.18, lw=0)
        a1.text((it["record_from_s"] + it["record_to_s"]) / 7200, it["setpoint_C"] + 2.5,
                f"{it['setpoint_C']:g}°C\nhold {it['duration_s'] / 60:.0f} min",
                ha="center", fontsize=6.5)
    a1.plot([], [], color="#2ca02c", alpha=0.4, lw=6, label="recording window")
    a1.set_ylabel("temperature, °C", fontsize=8)
    a1.set_xlabel("time in one position's cycle, h", fontsize=8)
    a1.legend(fontsize=7, loc="lower right")
    a1.grid(alpha=0.3, lw=0.5)
    lo, hi = min(plan.levels_C + [plan.room_C]), max(plan.levels_C + [plan.room_C])
    a1.set_ylim(lo - 8, hi + 10)
    # whole program: one bar per position
    per = plan.position_duration_s / 3600
    for k, p in enumerate(plan.positions):
        a2.barh(0, per, left=k * per, color=f"C{k % 10}", alpha=0.6, edgecolor="white")
        a2.text((k + 0.5) * per, 0, str(p.number), ha="center", va="center", fontsize=7)
    a2.set_yticks([])
    a2.set_xlim(0, len(plan.positions) * per)
    a2.set_xlabel(f"whole program, h (positions 1-{len(plan.positions)}; total "
                  f"{plan.total_duration_s / 3600:.1f} h)", fontsize=8)
    for a in (a1, a2):
        a.tick_params(labelsize=7)
    fig.suptitle(f"Unit {plan.unit_id}: temperature profile", fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.99, top=0.93, bottom=0.09, hspace=0.45)
    return _save(fig, path)
