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
"""

from __future__ import annotations

import numpy as np

_CLASSES: dict = {}


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
