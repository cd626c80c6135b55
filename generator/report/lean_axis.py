"""Axis ticks drawn from one tick object per axis instead of one per location.

matplotlib's Axis builds a Tick for every tick location (two tick marks, a grid line and
two labels: five artists and their transforms, ~0.5 ms each) and draws each of them one
by one: for the report's figures, ~900 tick objects and a third of the drawing time
(bench/bench_figures.py). The ticks of one axis are copies of its first tick moved to
their locations (matplotlib makes every further tick from the first with
Axis._copy_tick_props); here that first tick is moved to each location in turn, as it is
measured and drawn:

* the grid lines of an axis drawn as one path (the lines at the locations, as
  matplotlib's, each a 2-point segment snapped as before), the tick marks of a side as one
  line of markers (a marker at each location: the same marker, snapped to the same
  pixel), the labels one after the other (the same text at the same place);
* the tick labels measured for the axis label and the offset text as matplotlib measures
  them (Axis._get_ticklabel_bboxes, at each location).

The order of drawing within an axis changes (all its grid lines, then the marks, then the
labels, where matplotlib draws tick after tick): grid lines lie inside the axes, marks
and labels outside, so nothing drawn in one axis overlaps another part of it and the
pixels are the same (host_tests/test_figures_lean_axis.py compares them with
matplotlib's own drawing).

Applied only to an axis whose existing ticks are all styled like its first (no single
tick label coloured or sized differently: what the report's figures never do); any other
axis keeps matplotlib's own.

Also here, the figures' other tick choices: few ticks (lean_ticks), explicit ticks
without a tick object per location (fixed_ticks), locators that return only the
locations in view (ticks_in_view, which also puts every axis of a figure on _LeanAxis).
"""

from __future__ import annotations

import numpy as np

_CLASSES: dict = {}
_SUPPORTED: list = []

# the matplotlib whose Axis.draw, Axis._update_ticks and tick-label measuring _LeanAxis
# copies, and the private names it calls; any other matplotlib draws its own axes
MATPLOTLIB_COPIED = (3, 11)
_PRIVATE_AXIS = ("_tick_group_visible", "_get_ticklabel_bboxes", "_update_label_position",
                 "_update_offset_text_position", "_get_tick_boxes_siblings", "_get_axis_name")


def supported() -> bool:
    """True when this matplotlib is the one _LeanAxis copies (MATPLOTLIB_COPIED) and has
    every private name it relies on; otherwise lean() leaves every axis to matplotlib
    (the same figures, drawn more slowly). Checked once per process."""
    if not _SUPPORTED:
        import matplotlib
        from matplotlib import axis as maxis
        from matplotlib import transforms as mtransforms
        try:
            version = tuple(int(v) for v in matplotlib.__version__.split(".")[:2])
        except ValueError:
            version = ()
        ok = (version == MATPLOTLIB_COPIED
              and all(hasattr(maxis.Axis, n) for n in _PRIVATE_AXIS)
              and hasattr(mtransforms, "_interval_contains_close"))
        _SUPPORTED.append(ok)
    return _SUPPORTED[0]


class _LeanAxis:
    """Mixin put in front of XAxis / YAxis (the instance's class is changed in place:
    lean(axis)). _update_ticks returns (tick, loc, label) for each location in view, where
    tick is the axis's first major (minor) tick; _get_ticklabel_bboxes and draw take that
    form."""

    def _update_ticks(self):
        from matplotlib import transforms as mtransforms
        from matplotlib.ticker import NullLocator
        out = []
        for major, ticker, kw in ((True, self.major, self._major_tick_kw),
                                  (False, self.minor, self._minor_tick_kw)):
            if not self._tick_group_visible(kw) or isinstance(ticker.locator, NullLocator):
                continue
            locs = self.get_majorticklocs() if major else self.get_minorticklocs()
            labels = ticker.formatter.format_ticks(locs)
            if not len(locs):
                continue
            tick = (self.majorTicks if major else self.minorTicks)[0]
            out += [(tick, loc, label) for loc, label in zip(locs, labels)]
        if not out:
            return []
        # in view, as Axis._update_ticks
        lo, hi = sorted(self.get_view_interval())
        tr = self.get_transform()
        interval_t = tr.transform([lo, hi])
        keep = []
        for item in out:
            try:
                loc_t = tr.transform(item[1])
            except AssertionError:      # a masked value of the scale: matplotlib skips it
                continue
            if mtransforms._interval_contains_close(interval_t, loc_t):
                keep.append(item)
        return keep

    def _place(self, tick, loc, label):
        tick.update_position(loc)
        tick.label1.set_text(label)
        tick.label2.set_text(label)

    def _get_ticklabel_bboxes(self, ticks, renderer):
        b1, b2 = [], []
        for tick, loc, label in ticks:
            self._place(tick, loc, label)
            for lab, out in ((tick.label1, b1), (tick.label2, b2)):
                if lab.get_visible() and lab.get_in_layout():
                    out.append(lab.get_window_extent(renderer))
        return b1, b2

    def _draw_ticks(self, ticks, renderer):
        """The grid lines of each tick group as one path, the tick marks of each side as
        one line of markers, then the labels."""
        groups = {}
        for tick, loc, label in ticks:
            groups.setdefault(id(tick), (tick, []))[1].append((loc, label))
        x_axis = self.axis_name == "x"
        for tick, items in groups.values():
            if not tick.get_visible():
                continue
            locs = np.array([loc for loc, _ in items], float)
            n = len(locs)
            saved = [(ln, ln.get_xdata(orig=True), ln.get_ydata(orig=True))
                     for ln in (tick.gridline, tick.tick1line, tick.tick2line)]
            try:
                if tick.gridline.get_visible():
                    along = np.repeat(locs, 3)
                    along[2::3] = np.nan                # one segment per location
                    across = np.tile([0.0, 1.0, np.nan], n)
                    tick.gridline.set_data(*((along, across) if x_axis else (across, along)))
                    tick.gridline.draw(renderer)
                for line, at in ((tick.tick1line, 0.0), (tick.tick2line, 1.0)):
                    if line.get_visible():
                        line.set_data(*((locs, np.full(n, at)) if x_axis
                                        else (np.full(n, at), locs)))
                        line.draw(renderer)
            finally:
                for ln, xd, yd in saved:
                    ln.set_data(xd, yd)
            for loc, label in items:
                self._place(tick, loc, label)
                tick.label1.draw(renderer)
                tick.label2.draw(renderer)
            tick.stale = False

    _drawn_boxes = None

    def _get_tick_boxes_siblings(self, renderer):
        """The tick label boxes the axis label is placed below (beside): while this axis
        is drawn and its label is not aligned with other axes' (Figure.align_labels), the
        boxes just measured, instead of the ticks found and measured again."""
        if self._drawn_boxes is not None:
            groups = self.get_figure(root=False)._align_label_groups
            group = groups.get(self._get_axis_name())
            if group is not None and list(group.get_siblings(self.axes)) == [self.axes]:
                return self._drawn_boxes
        return super()._get_tick_boxes_siblings(renderer)

    def draw(self, renderer):
        # matplotlib's Axis.draw (3.11) with the ticks drawn by _draw_ticks
        if not self.get_visible():
            return
        renderer.open_group(__name__, gid=self.get_gid())
        ticks_to_draw = self._update_ticks()
        tlb1, tlb2 = self._get_ticklabel_bboxes(ticks_to_draw, renderer)
        self._draw_ticks(ticks_to_draw, renderer)
        self._drawn_boxes = (tlb1, tlb2)
        try:
            self._update_label_position(renderer)
        finally:
            self._drawn_boxes = None
        self.label.draw(renderer)
        self._update_offset_text_position(tlb1, tlb2)
        self.offsetText.set_text(self.major.formatter.get_offset())
        self.offsetText.draw(renderer)
        renderer.close_group(__name__)
        self.stale = False


def _style(tick):
    """What a tick's artists look like (not where they are): ticks with equal styles draw
    alike at the same location."""
    def line(ln):
        return (ln.get_visible(), ln.get_marker(), ln.get_markersize(),
                ln.get_markeredgewidth(), str(ln.get_markeredgecolor()), str(ln.get_color()),
                ln.get_linewidth(), ln.get_linestyle(), ln.get_alpha(), ln.get_zorder())

    def text(t):
        return (t.get_visible(), hash(t.get_fontproperties()), str(t.get_color()),
                t.get_rotation(), t.get_horizontalalignment(), t.get_verticalalignment(),
                t.get_alpha(), t.get_rotation_mode())
    return (tick.get_visible(), line(tick.tick1line), line(tick.tick2line),
            line(tick.gridline), text(tick.label1), text(tick.label2))


def lean(axis) -> bool:
    """Draw axis (an XAxis or YAxis of a 2D axes) with _LeanAxis when its existing ticks
    are styled alike (_style); True when it is (or already was)."""
    if isinstance(axis, _LeanAxis):
        return True
    if not supported():
        return False
    for ticks in (axis.__dict__.get("majorTicks"), axis.__dict__.get("minorTicks")):
        # ticks not made yet (the lazy list): the first is made when asked for
        if ticks and len(ticks) > 1:
            first = _style(ticks[0])
            if any(_style(t) != first for t in ticks[1:]):
                return False
    cls = type(axis)
    if cls not in _CLASSES:
        _CLASSES[cls] = type(f"Lean{cls.__name__}", (_LeanAxis, cls), {})
    axis.__class__ = _CLASSES[cls]
    return True


# ---- the figures' tick choices -------------------------------------------------------
def lean_ticks(ax, nx=5, ny=4, log_y=False):
    """Few ticks: tick objects are most of the drawing time."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullLocator
    ax.xaxis.set_major_locator(MaxNLocator(nx))
    if log_y:
        ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=12))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    else:
        ax.yaxis.set_major_locator(MaxNLocator(ny))
    ax.xaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_minor_locator(NullLocator())


def fixed_ticks(axis, locs, labels, **text_kw):
    """axis.set_ticks(locs, labels, **text_kw) without a tick object per location: the
    same locator (FixedLocator), labels by location (the formatter set_ticklabels makes),
    the view widened to the locations, and text_kw set on the labels of the ticks made so
    far (the first; lean_axis draws every location from it, and matplotlib copies it into
    any tick it makes later)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter
    locs = [float(v) for v in locs]
    labels = [str(v) for v in labels]
    if len(locs):
        axis.set_view_interval(min(locs), max(locs))      # as Axis._set_tick_locations
    axis.set_major_locator(FixedLocator(locs))
    by_loc = dict(zip(locs, labels))
    axis.set_major_formatter(FuncFormatter(lambda v, pos=None: by_loc.get(v, "")))
    if text_kw:
        for tick in axis.majorTicks:
            tick.label1.set(**text_kw)
            tick.label2.set(**text_kw)


class _InViewTicks:
    """Mixin for a tick locator: only the locations inside the axis's view interval (by the
    test matplotlib's Axis._update_ticks applies before drawing, in the scale's space).
    A locator returns a margin of locations outside the view (a log locator a decade or
    more on each side); matplotlib builds a tick object and formats a label for every
    location it gets, then draws only those in view. Dropping them beforehand draws the
    same ticks, labels and grid lines, with fewer tick objects: those are most of the
    drawing time (two lines, a grid line and two labels each)."""

    def __call__(self):
        from matplotlib.transforms import _interval_contains_close
        locs = np.asarray(super().__call__())
        if self.axis is None or not locs.size:
            return locs
        lo, hi = sorted(self.axis.get_view_interval())
        tr = self.axis.get_transform()
        interval = tr.transform([lo, hi])
        keep = []
        for v in locs:
            try:
                keep.append(bool(_interval_contains_close(interval, tr.transform(v))))
            except AssertionError:      # a masked value of the scale: matplotlib skips it
                keep.append(False)
        return locs[np.asarray(keep, bool)]


_IN_VIEW_CLASSES = {}


def ticks_in_view(fig):
    """Every plain 2D axes of fig (not colour bars): an axis without a label text gets a
    fixed label position (set_label_coords: not measured, not drawn either way), and
    _InViewTicks goes on its major and minor locators of the kinds that return locations
    outside the view (MaxNLocator and AutoLocator, LogLocator, AutoMinorLocator); fixed
    and null locators are left as they are. The locator object's class is changed in
    place, so shared axes (one locator) follow; calling this again is harmless."""
    from matplotlib.ticker import AutoMinorLocator, LogLocator, MaxNLocator
    if not supported():        # another matplotlib: its own ticks, as they are
        return
    for ax in fig.axes:
        if ax.name != "rectilinear" or hasattr(ax, "_colorbar"):
            continue
        for axis in (ax.xaxis, ax.yaxis):
            lean(axis)          # its ticks drawn from one tick object (lean_axis)
            if not axis.label.get_text() and getattr(axis, "_autolabelpos", False):
                # no axis label: nothing to place below (beside) the tick labels, whose
                # boxes matplotlib would otherwise measure a second time on each draw
                axis.set_label_coords(0.5, 0.5)
            for ticker in (axis.major, axis.minor):
                loc = ticker.locator
                cls = type(loc)
                if isinstance(loc, _InViewTicks) or \
                        not isinstance(loc, (MaxNLocator, LogLocator, AutoMinorLocator)):
                    continue
                if cls not in _IN_VIEW_CLASSES:
                    _IN_VIEW_CLASSES[cls] = type(f"InView{cls.__name__}", (_InViewTicks, cls),
                                                 {})
                loc.__class__ = _IN_VIEW_CLASSES[cls]
