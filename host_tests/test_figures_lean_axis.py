"""The figures' shortcuts draw what matplotlib draws: the lean axes
(generator/report/lean_axis.py: every tick drawn from one tick object) give the same
PNG bytes as matplotlib's own axes, and a coefficient grid drawn on the artists of the
previous sensor (figures._coefficient_grids) gives the same bytes as one drawn anew."""

from __future__ import annotations

import numpy as np
import pytest

from generator.report import figures, lean_axis


def _demo_figure(path):
    """Axes of the kinds the report draws: linear with a grid and an axis label, log y with
    fixed x tick labels (rotated), an image with fixed ticks on both axes, tick labels
    hidden on an upper row."""
    fig = figures._figure(8.0, 6.0)
    axes = fig.subplots(2, 2)
    x = np.linspace(-20.0, 55.0, 40)
    ax = axes[0, 0]
    ax.plot(x, 0.97 + 1e-4 * x, "-", lw=1.2)
    ax.errorbar(x[::8], 0.97 + 1e-4 * x[::8], yerr=2e-4, fmt="o", ms=3, capsize=2)
    lean_axis.lean_ticks(ax)
    ax.tick_params(axis="x", labelbottom=False)
    ax.grid(alpha=0.3, lw=0.5)
    ax.set_ylabel("m_xx", fontsize=8)
    ax = axes[0, 1]
    k = np.arange(12)
    ax.bar(k, 10.0 ** (1 + k / 4), 0.4, bottom=0)
    ax.set_yscale("log")
    lean_axis.lean_ticks(ax, log_y=True)
    lean_axis.fixed_ticks(ax.xaxis, k, [f"pos {v}" for v in k], fontsize=7, rotation=60)
    ax.grid(axis="y", alpha=0.3, lw=0.5)
    ax = axes[1, 0]
    ax.imshow(np.outer(np.arange(6), np.arange(9)), origin="lower", aspect="auto")
    lean_axis.fixed_ticks(ax.xaxis, range(9), [f"{15 * v:g}" for v in range(9)], fontsize=6)
    lean_axis.fixed_ticks(ax.yaxis, range(6), [f"{v:g}" for v in range(6)], fontsize=6)
    ax.set_xlabel("angle, deg", fontsize=7)
    ax = axes[1, 1]
    ax.plot(x, 3000.0 * np.sin(x / 9.0), ".", ms=2)
    lean_axis.lean_ticks(ax, ny=5)
    ax.set_xlabel("time, h", fontsize=8)
    ax.grid(alpha=0.3, lw=0.5)
    fig.suptitle("lean axes", fontsize=10)
    return figures._save(fig, path)


needs_copied_matplotlib = pytest.mark.skipif(
    not lean_axis.supported(),
    reason=f"lean axes copy matplotlib {lean_axis.MATPLOTLIB_COPIED}; this one draws its own")


def test_another_matplotlib_draws_its_own_axes(tmp_path, monkeypatch):
    """On a matplotlib other than the one _LeanAxis copies (wheel check: Python 3.10 gets
    matplotlib 3.10, which lacks Axis._tick_group_visible), lean() leaves every axis to
    matplotlib and the figures still draw."""
    monkeypatch.setattr(lean_axis, "_SUPPORTED", [False])
    fig = figures._figure(3.0, 2.0)
    ax = fig.subplots()
    ax.plot([0, 1, 2], [0, 1, 2])
    assert not lean_axis.lean(ax.xaxis)
    assert type(ax.xaxis).__name__ == "XAxis"
    assert _demo_figure(tmp_path / "stock.png").stat().st_size > 0


@needs_copied_matplotlib
def test_lean_axes_draw_the_same_bytes_as_matplotlibs(tmp_path, monkeypatch):
    lean_png = _demo_figure(tmp_path / "lean.png").read_bytes()
    monkeypatch.setattr(lean_axis, "lean", lambda axis: False)     # matplotlib's own axes
    stock_png = _demo_figure(tmp_path / "stock.png").read_bytes()
    assert lean_png == stock_png


@needs_copied_matplotlib
def test_lean_is_refused_for_an_axis_whose_ticks_differ():
    fig = figures._figure(3.0, 2.0)
    ax = fig.subplots()
    ax.plot([0, 1, 2], [0, 1, 2])
    ticks = ax.xaxis.get_major_ticks(3)
    ticks[1].label1.set_color("red")            # one tick label styled on its own
    assert not lean_axis.lean(ax.xaxis)
    assert lean_axis.lean(ax.yaxis)


def _job(path, k):
    rng = np.random.default_rng(k)
    level_T = np.array([-19.0, -4.0, 10.0, 25.0, 40.0, 55.0])
    curve_T = np.linspace(-19.0, 55.0, 50)
    base = rng.normal(size=12) * [1000, 1000, 1000, 1, 0.01, 0.01, 0.01, 1, 0.01, 0.01,
                                  0.01, 1]
    slope = rng.normal(size=12) * 1e-3 * np.abs(base)
    return dict(path=path, title=f"sensor {k}", names=[f"c{i}" for i in range(12)],
                units=["nT"] * 3 + [""] * 9, level_T=level_T,
                level_val=base + np.outer(level_T, slope),
                level_sig=np.full((6, 12), 0.05) * np.abs(slope) * 10,
                curve_T=curve_T, curve_val=base + np.outer(curve_T, slope),
                curve_band=np.full((50, 12), 0.02) * np.abs(slope) * 10,
                t_range=(-19.0, 55.0) if k % 2 else None)


@pytest.mark.parametrize("second", [1, 2])
def test_a_coefficient_grid_on_reused_artists_equals_one_drawn_anew(tmp_path, second):
    """second = 1: the same data shape (artists given new data); 2: no calibrated-range
    span for the second sensor (the span removed)."""
    figures._coefficient_grids([_job(tmp_path / "a0.png", 0),
                                _job(tmp_path / "a1.png", second)])
    figures._coefficient_grids([_job(tmp_path / "b1.png", second)])
    assert (tmp_path / "a1.png").read_bytes() == (tmp_path / "b1.png").read_bytes()
