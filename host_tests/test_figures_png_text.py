"""The figures' own PNG writer (figures._png_bytes) and text cache (report/agg_text.py)."""

import io

import numpy as np
import pytest
from PIL import Image

from generator.report import agg_text
from generator.report.figures import EMPTY_AXES_KEY, _png_bytes


@pytest.mark.parametrize("channels", [3, 4])
def test_png_round_trip(channels):
    rng = np.random.default_rng(channels)
    px = rng.integers(0, 256, (37, 53, channels), dtype=np.uint8)
    texts = {"Software": "magcal", EMPTY_AXES_KEY: "Bx µT, 5 °C; τ = 3 min"}   # τ: not Latin-1
    im = Image.open(io.BytesIO(_png_bytes(px, texts, 90)))
    im.load()
    assert im.mode == ("RGB" if channels == 3 else "RGBA")
    assert np.array_equal(np.asarray(im), px)          # lossless, every pixel
    assert im.text == texts
    assert im.info["dpi"] == pytest.approx((90, 90), abs=0.01)   # pHYs in whole px per m


def _renderer(canvas_cls):
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    fig = Figure(figsize=(3.0, 1.0), dpi=90)
    return canvas_cls(fig).get_renderer()


def _draw(r, x, y, s, size=7, angle=0):
    from matplotlib.font_manager import FontProperties
    r.clear()
    gc = r.new_gc()
    gc.set_foreground("k")
    r.draw_text(gc, x, y, s, FontProperties(size=size), angle)
    return np.asarray(r.buffer_rgba()).copy()


def test_cached_text_is_stock_text_on_whole_pixels():
    """At a whole-pixel anchor the cached glyphs are matplotlib's own pixels, first and
    later draws alike; elsewhere the string moves to the nearest whole pixel."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    cls = agg_text.canvas_class()
    if cls is FigureCanvasAgg:
        pytest.skip("this matplotlib has no glyph-level API: stock text drawing")
    stock, cached = _renderer(FigureCanvasAgg), _renderer(cls)
    for s, angle in [("-0.00128", 0), ("sensor temperature, °C", 0), ("nT", 90)]:
        for x, y in [(20.0, 50.0), (31.0, 60.0)]:            # a second anchor: a cache hit
            a, b = _draw(stock, x, y, s, angle=angle), _draw(cached, x, y, s, angle=angle)
            assert (a[..., 3] > 0).any()
            assert np.array_equal(a, b), (s, x, y)
    # off the pixel grid: the whole-pixel anchor's pixels (x 20.4 -> 20, y 49.6 -> 50)
    assert np.array_equal(_draw(cached, 20.4, 49.6, "-0.00128"), _draw(stock, 20.0, 50.0,
                                                                       "-0.00128"))


def test_cached_font_height_metrics_lay_out_text_as_matplotlib():
    """Text._get_layout takes the font's ascent, descent and line gap from the renderer's
    _get_font_height_metrics when there is one (agg_text caches them): the same extents
    as matplotlib's own reading of the font tables, one line or several."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    cls = agg_text.canvas_class()
    if cls is FigureCanvasAgg:
        pytest.skip("this matplotlib has no glyph-level API: stock text drawing")
    extents = []
    for canvas_cls in (FigureCanvasAgg, cls):
        fig = Figure(figsize=(3.0, 2.0), dpi=90)
        r = canvas_cls(fig).get_renderer()
        texts = [fig.text(0.1, 0.5, "B/|B| 0.00128", fontsize=7),
                 fig.text(0.3, 0.2, "first line\nsecond, °C", fontsize=9.5, rotation=90),
                 fig.text(0.6, 0.6, "bold title", fontsize=11, fontweight="bold")]
        extents.append([t.get_window_extent(r).bounds for t in texts])
    assert hasattr(cls(Figure()).get_renderer(), "_get_font_height_metrics")
    assert extents[0] == extents[1]


def test_a_changed_private_api_falls_back_to_stock_text(monkeypatch):
    """agg_text leans on private matplotlib functions (FT2Font._layout, ...): when one of
    them fails (a matplotlib whose internals changed), the string is drawn by matplotlib's
    own renderer -- the same pixels as stock text -- and so is every later one, never an
    error in the report."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    cls = agg_text.canvas_class()
    if cls is FigureCanvasAgg:
        pytest.skip("this matplotlib has no glyph-level API: stock text drawing")
    monkeypatch.setattr(agg_text, "_CACHE", {})
    monkeypatch.setattr(agg_text, "_STOCK_ONLY", [False])
    stock, cached = _renderer(FigureCanvasAgg), _renderer(cls)

    def changed(*a, **k):
        raise TypeError("changed signature")
    monkeypatch.setattr(type(cached), "_rasterise", changed)
    # off the pixel grid, so that only matplotlib's own drawing gives the stock pixels
    a, b = _draw(stock, 20.4, 49.6, "-0.00128"), _draw(cached, 20.4, 49.6, "-0.00128")
    assert (a[..., 3] > 0).any() and np.array_equal(a, b)
    assert agg_text._STOCK_ONLY[0]
    assert cached._get_font_height_metrics(__import__("matplotlib").font_manager
                                           .FontProperties(size=7)) == (None, None, None)
