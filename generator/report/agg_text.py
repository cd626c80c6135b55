"""Text on the figures' Agg canvas from a per-process cache of rasterised strings.

Drawing a string costs matplotlib ~0.6 ms (a HarfBuzz layout, then each glyph set up and
rasterised by FreeType at its sub-pixel position): a third of the thermal campaign's
figure time, for ~1,250 strings of which only ~370 differ (tick labels repeat across
panels and figures; bench/bench_figures.py). Here each distinct string is laid out and
rasterised once, relative to an anchor on a whole pixel, and every later occurrence
composites the kept glyph bitmaps (draw_text_image) at its own anchor.

The anchor, matplotlib's (x, y) of the text, is rounded to the nearest whole pixel (a
shift of at most half a pixel, unseen at the figures' 90 dpi): FreeType's rendering of a
glyph moved by a whole pixel is the same bitmap moved by that pixel (the outline is
translated in 26.6 fixed point), so every occurrence of a string draws the same pixels.
The result is deterministic: the same figure gives the same file, whatever was drawn
before it in the process.

Everything else is matplotlib's: mathtext, text with OpenType features or a language
set, and a matplotlib without the glyph-level API (before 3.11: FT2Font._layout,
_set_transform, _render_glyph) take the stock RendererAgg.draw_text.
"""

from __future__ import annotations

import math

import numpy as np

MAX_ENTRIES = 20000     # distinct strings kept per process (a report draws a few hundred)

_CANVAS = None
_CACHE: dict = {}
# set when a private matplotlib function this module uses fails (a matplotlib whose
# internals changed): from then on every string is drawn by matplotlib's own renderer
_STOCK_ONLY = [False]


def canvas_class():
    """The FigureCanvasAgg subclass whose renderer draws text from the cache (stock
    FigureCanvasAgg when this matplotlib lacks the glyph-level API)."""
    global _CANVAS
    if _CANVAS is None:
        _CANVAS = _build()
    return _CANVAS


def _build():
    from matplotlib.backends.backend_agg import FigureCanvasAgg, RendererAgg, get_hinting_flag
    try:
        from matplotlib.ft2font import FT2Font, RenderMode
    except ImportError:
        return FigureCanvasAgg
    if not all(hasattr(FT2Font, a) for a in ("_layout", "_set_transform", "_render_glyph")):
        return FigureCanvasAgg

    class CachedTextRenderer(RendererAgg):
        def draw_text(self, gc, x, y, s, prop, angle, ismath=False, mtext=None):
            if _STOCK_ONLY[0] or ismath or (mtext is not None and (mtext.get_fontfeatures() is not None
                                                  or mtext.get_language() is not None)):
                return super().draw_text(gc, x, y, s, prop, angle, ismath, mtext)
            aa = bool(gc.get_antialiased())
            flags = get_hinting_flag()
            key = (s, hash(prop), prop.get_size_in_points(), self.dpi, float(angle), aa,
                   flags)
            glyphs = _CACHE.get(key)
            if glyphs is None:
                if len(_CACHE) >= MAX_ENTRIES:
                    _CACHE.clear()
                try:
                    glyphs = self._rasterise(s, prop, angle, aa, flags)
                except Exception:       # noqa: BLE001 -- a private API that changed
                    _STOCK_ONLY[0] = True
                    return super().draw_text(gc, x, y, s, prop, angle, ismath, mtext)
                _CACHE[key] = glyphs
            # the anchor on a whole pixel: x right, y_up up from the canvas's bottom edge
            x0, y0_up = round(x), round(self.height - y)
            h = int(self.height)
            for buf, left, top in glyphs:
                # as RendererAgg: draw_text_image's y is downwards, to the bitmap's bottom
                self._renderer.draw_text_image(buf, x0 + left, h - (y0_up + top) + buf.shape[0],
                                               0, gc)

        def get_text_width_height_descent(self, s, prop, ismath):
            """RendererAgg's (width, height, descent) of s, kept per process: matplotlib
            keeps them per renderer (text._get_text_metrics_with_cache), and every figure
            has its own, so each figure laid the same tick labels out again (~450 layouts
            a report, ~6 % of the figure time, py-spy). Same arguments, same numbers: the
            key holds everything the result depends on (the string, the font properties,
            the size, dpi, the math mode and the hinting flags)."""
            if _STOCK_ONLY[0] or ismath == "TeX":
                return super().get_text_width_height_descent(s, prop, ismath)
            key = ("extent", s, hash(prop), prop.get_size_in_points(), self.dpi, ismath,
                   get_hinting_flag())
            out = _CACHE.get(key)
            if out is None:
                if len(_CACHE) >= MAX_ENTRIES:
                    _CACHE.clear()
                out = _CACHE[key] = super().get_text_width_height_descent(s, prop, ismath)
            return out

        def _get_font_height_metrics(self, prop):
            """(ascent, descent, line gap) of prop's font in pixels, which Text._get_layout
            asks its renderer for when it has this method (else it finds the font file and
            reads its tables on each call: ~3,000 times a report): the same arithmetic as
            Text._get_layout's own, once per font and size."""
            key = ("height metrics", hash(prop), prop.get_size_in_points(), self.dpi)
            if _STOCK_ONLY[0]:
                return (None, None, None)       # Text._get_layout then finds them itself
            if key not in _CACHE:
                from matplotlib.font_manager import fontManager, get_font
                out = (None, None, None)
                try:
                    font = get_font(fontManager._find_fonts_by_props(prop))
                    for table_name, gap_key, ascent_key, descent_key in (
                            ('OS/2', 'sTypoLineGap', 'sTypoAscender', 'sTypoDescender'),
                            ('hhea', 'lineGap', 'ascent', 'descent')):
                        table = font.get_sfnt_table(table_name)
                        if table is None:
                            continue
                        units_per_em = font.get_sfnt_table('head')['unitsPerEm']
                        scale = 1 / units_per_em * prop.get_size_in_points() * self.dpi / 72
                        out = (table[ascent_key] * scale, -table[descent_key] * scale,
                               table[gap_key] * scale)
                        break
                except Exception:       # noqa: BLE001 -- a private API that changed
                    _STOCK_ONLY[0] = True
                    return (None, None, None)
                _CACHE[key] = out
            return _CACHE[key]

        def _rasterise(self, s, prop, angle, aa, flags):
            """((bitmap, left, top), ...) of the glyphs of s with its anchor at (0, 0) (the
            arithmetic of RendererAgg._draw_text_glyphs_and_boxes at x = 0, y_up = 0).

            Each glyph is rendered once per process for each sub-pixel offset (its 26.6
            offset modulo one pixel) and kept: a glyph at offset 64 a + f is the glyph at
            f moved by a whole pixels (as the anchors above: FreeType translates the
            outline in 26.6 fixed point), so its bitmap is the kept one with left / top
            moved by a. The report's figures render ~3,300 glyphs, ~540 of them
            distinct (bench/bench_figures.py)."""
            import matplotlib as mpl
            font = self._prepare_font(prop)
            size = prop.get_size_in_points()
            cos, sin = math.cos(math.radians(angle)), math.sin(math.radians(angle))
            matrix = (0x10000 * np.array([[cos, -sin], [sin, cos]])
                      @ [[1, 0], [0, 1]]).round().astype(int)
            mode = RenderMode.NORMAL if aa else RenderMode.MONO
            font_key = (size, self.dpi, flags, aa, tuple(matrix.ravel().tolist()),
                        mpl.rcParams["text.hinting_factor"])
            out = []
            for item in font._layout(s, flags=flags):
                ft, dx, dy = item.ft_object, item.x, item.y       # dy is upwards
                ox = round(0x40 * (dx * cos - dy * sin))
                oy = round(0x40 * (dx * sin + dy * cos))
                key = ("glyph", ft.fname, ft.postscript_name, item.glyph_index, ox & 0x3f,
                       oy & 0x3f) + font_key
                glyph = _CACHE.get(key)
                if glyph is None:
                    ft.set_size(size, self.dpi)
                    ft._set_transform(matrix, [ox & 0x3f, oy & 0x3f])
                    bitmap = ft._render_glyph(item.glyph_index, flags, mode)
                    buf = np.array(bitmap.buffer, dtype=np.uint8, copy=True)
                    if not aa:
                        buf *= 0xff
                    glyph = _CACHE[key] = (buf, int(bitmap.left), int(bitmap.top))
                buf, left, top = glyph
                out.append((buf, left + (ox >> 6), top + (oy >> 6)))
            return tuple(out)

    class CachedTextCanvas(FigureCanvasAgg):
        def get_renderer(self):
            r = super().get_renderer()
            if type(r) is RendererAgg:
                r.__class__ = CachedTextRenderer
            return r

    return CachedTextCanvas
