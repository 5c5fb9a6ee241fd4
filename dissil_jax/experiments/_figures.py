"""Figures 1-6 of the paper from configuration records: ours solid, the paper's dashed.

The y-axis is logarithmic and spans our finite values (up to ten times the largest). Two
kinds of value fall outside it, and both are drawn, never dropped:

- **ours, infinite** (an unstable closed loop counts as $\\infty$): a cross in a grey band
  above the axis labelled "∞", each method's crosses shifted sideways so that methods at
  the same $N$ do not hide each other; an infinite upper quartile is a triangle at the top
  of its band;
- **the paper's, off the scale** (its GD medians reach $10^{11}$): an open triangle at the
  top of the axis with the value written beside it, and the dashed line is broken there
  rather than drawn across the missing points.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ._paper import FIGURES
from .protocol import METHOD_LABELS, METHODS

_COLORS = {"ico": "#0047ab", "ico_nc": "#00bfff", "pgd": "#ff4000", "gd": "#ffa600",
           "mlp": "#c05fa8", "direct": "#2e8b57", "ren": "#8b4513"}
DATA_TITLES = {"initial": "Initial segments", "sliding": "Sliding window"}
_STATS = (("median", "Median"), ("max", "Worst"), ("quartiles", "Quartiles (q1, median, q3)"))
_BAND = 4.0  # the height (a factor) of the ∞ band above the axis's finite range


def _scale(rows: list[dict]) -> float:
    """The top of the finite range: ten times our largest finite statistic (1 if none)."""
    finite = [r[f"mse_{k}"] for r in rows for k in ("median", "max", "q1", "q3")
              if np.isfinite(r[f"mse_{k}"])]
    return 10.0 * max(finite) if finite else 1.0


def _x_limits(ax, xs, shifts: float) -> None:
    """Room on both sides for the sideways shifts and the value labels."""
    lo, hi = min(xs), max(xs)
    pad = max(1.0, 0.05 * (hi - lo)) + shifts
    ax.set_xlim(lo - pad, hi + pad + 0.04 * (hi - lo))


def _ours(ax, rows, m, stat, top, shift):
    """Our statistic for method `m` against N: finite points joined, infinite ones as
    crosses in the ∞ band (shifted by `shift` along N)."""
    x = np.array([r["segments"] for r in rows], float)
    col = _COLORS[m]
    y = np.array([r["mse_max" if stat == "max" else "mse_median"] for r in rows], float)
    inf = ~np.isfinite(y)
    label = METHOD_LABELS[m] if "(ours)" in METHOD_LABELS[m] else f"{METHOD_LABELS[m]} (ours)"
    ax.plot(x, np.where(inf, np.nan, y), "-o", color=col, label=label if (~inf).any() else None)
    if inf.any():
        ax.plot(x[inf] + shift, np.full(inf.sum(), top * np.sqrt(_BAND)), "x", color=col,
                ms=9, mew=2, label=None if (~inf).any() else label)
    if stat == "quartiles":
        lo = np.array([r["mse_q1"] for r in rows], float)
        hi = np.array([r["mse_q3"] for r in rows], float)
        ok = np.isfinite(lo)
        both = ok & np.isfinite(hi)  # the band only between finite quartiles
        ax.fill_between(x, np.where(both, lo, np.nan), np.where(both, hi, np.nan), color=col,
                        alpha=0.12)
        if len(x) == 1:  # a band of one N has no width: a bar instead
            ax.vlines(x[ok] + shift, lo[ok], np.minimum(hi[ok], top), color=col, lw=3,
                      alpha=0.5)
        up = ok & ~np.isfinite(hi)
        ax.plot(x[up] + shift, np.full(up.sum(), top), "^", color=col, ms=7)


def _short(value: float) -> str:
    """A value for a label in two characters or so: 730 -> '7e2', 4.3e11 -> '4e11'."""
    return f"{value:.0e}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def _paper(ax, points, m, stat, top, level):
    """The paper's values for `m`: dashed, broken at values above `top`, which are marked
    at the top of the axis with their value (on row `level`, so that several methods' marks
    at one N stay apart). Returns whether any was."""
    px = np.array([p[0] for p in points], float)
    quart = stat == "quartiles"
    py = np.array([p[1][1] if quart else p[1] for p in points], float)
    col = _COLORS[m]
    off = ~(py < top)
    ax.plot(px, np.where(off, np.nan, py), "--", marker="s", ms=3, mfc="none", color=col,
            alpha=0.7, lw=1.2, label=f"{METHOD_LABELS[m]} (paper)")
    at = top / 1.3 / 1.9 ** level
    for xi, yi in zip(px[off], py[off]):
        ax.plot([xi], [at], "^", mfc="none", color=col, ms=7)
        ax.annotate(_short(yi), (xi, at), textcoords="offset points", xytext=(5, -3),
                    fontsize=8, color=col)
    if quart:  # the paper's quartiles, as thin bars beside ours
        lo = np.array([p[1][0] for p in points], float)
        hi = np.array([p[1][2] for p in points], float)
        ok = ~off & (hi < top)
        ax.vlines(px[ok], lo[ok], hi[ok], color=col, lw=1, alpha=0.6, linestyles="dashed")
    return bool(off.any())


def _panel(ax, rows, example, data, stat):
    top = _scale(rows)
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    xs = [r["segments"] for r in rows]
    span = max(xs) - min(xs)
    step = 0.02 * (span if span else 2.0)
    level = 0
    for i, m in enumerate(methods):
        mr = sorted((r for r in rows if r["method"] == m), key=lambda r: r["segments"])
        _ours(ax, mr, m, stat, top, (i - (len(methods) - 1) / 2) * step)
        ref = dict(FIGURES.get((example, data, stat), {})).get(m)
        if ref:
            level += _paper(ax, ref, m, stat, top, level)
            xs += [p[0] for p in ref]
    ax.set_yscale("log")
    ax.axhspan(top, top * _BAND, color="0.92", zorder=0)
    # "∞" where a tick label would be, level with the crosses
    ax.text(-0.012, top * np.sqrt(_BAND), "∞", transform=ax.get_yaxis_transform(),
            ha="right", va="center", fontsize=12)
    finite = any(np.isfinite(r[f"mse_{k}"]) for r in rows for k in ("median", "max"))
    ax.set_ylim(top=top * _BAND, **({} if finite else {"bottom": top / 100}))
    # no tick labels in the band: its only value is ∞
    plain = ax.yaxis.get_major_formatter()
    ax.yaxis.set_major_formatter(lambda v, pos: "" if v > top * 1.0001 else plain(v, pos))
    ax.yaxis.set_minor_formatter("")
    _x_limits(ax, xs, len(methods) * step)
    ax.set_xlabel("number of training segments N")
    ax.set_ylabel("test MSE of plant states vs expert")
    ax.set_title(DATA_TITLES[data])
    ax.grid(True, which="both", alpha=0.3)


def _legend(fig, axes, quartiles: bool) -> None:
    """One legend for the figure, outside the panels (it covered data inside them)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    seen = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    extra = {"unstable (∞, shifted per method)":
             Line2D([], [], ls="none", marker="x", color="0.3", ms=8, mew=2),
             "paper's value off the scale":
             Line2D([], [], ls="none", marker="^", mfc="none", color="0.3", ms=7)}
    if quartiles:
        extra["q1 to q3 (ours)"] = Patch(color="0.3", alpha=0.2)
        extra["q3 = ∞ (ours)"] = Line2D([], [], ls="none", marker="^", color="0.3", ms=7)
    seen.update(extra)
    fig.legend(list(seen.values()), list(seen), loc="outside lower center", ncol=4,
               fontsize=9, frameon=False)


def plot_figures(records: list[dict], out_dir: pathlib.Path) -> list[pathlib.Path]:
    """Figures 1-6 of the paper: median, worst and quartile test MSE against N.

    One PNG per (example, statistic), one panel per data regime; solid lines are ours,
    dashed lines the paper's (read from its figure data). Infinite values of ours and the
    paper's values above the axis are marked, not dropped (module docstring).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = pathlib.Path(out_dir)
    paths = []
    for example in sorted({r["example"] for r in records}):
        datas = [d for d in DATA_TITLES
                 if any(r["example"] == example and r["data"] == d for r in records)]
        for stat, title in _STATS:
            # sized for a page about 700 px wide: 9-10 pt text stays legible there
            fig, axes = plt.subplots(1, len(datas), squeeze=False, layout="constrained",
                                     figsize=(4.7 * len(datas) + 0.6, 6.0))
            for ax, data in zip(axes[0], datas):
                _panel(ax, [r for r in records if r["example"] == example and r["data"] == data],
                       example, data, stat)
            fig.suptitle(f"{example.capitalize()} example: {title} test MSE over controllers")
            _legend(fig, axes[0], stat == "quartiles")
            path = out_dir / f"{example}_{stat}.png"
            fig.savefig(path, dpi=150)
            plt.close(fig)
            paths.append(path)
    return paths
