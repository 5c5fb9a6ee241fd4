"""The reproduction's figures draw every value: off-scale paper values are marked with their
value and break the paper's line, and unstable (infinite) values of several methods at one
N stay apart in the ∞ band."""

import math

import matplotlib
import numpy as np
import pytest

from dissil_jax.internal import FIGURES, experiment_figures as figs

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _record(method, segments, median, data="initial", example="linear"):
    return dict(example=example, data=data, method=method, segments=segments,
                mse_median=median, mse_max=median * 3, mse_q1=median / 2, mse_q3=median * 2)


@pytest.fixture
def ax():
    fig, ax = plt.subplots()
    yield ax
    plt.close(fig)


def test_paper_values_off_the_scale_are_marked_not_dropped(ax):
    # The paper's linear GD+NN medians (initial segments) are 7e2 to 3e7; ours are near 0.1.
    paper = dict(FIGURES[("linear", "initial", "median")])["mlp"]
    segs = [s for s, _ in paper]
    rows = [_record("mlp", s, 0.1) for s in segs]
    figs._panel(ax, rows, "linear", "initial", "median")
    top = figs._scale(rows)
    assert top == pytest.approx(10 * 0.3)  # ten times our largest statistic (the max)
    off = [(s, v) for s, v in paper if v >= top]
    assert off, "the premise: some paper values lie above the axis"
    dashed = [ln for ln in ax.get_lines() if ln.get_label() == "GD+NN (paper)"][0]
    ys = np.asarray(dashed.get_ydata(), float)
    # broken (NaN) at every off-scale point, never joined across it
    assert np.isnan(ys[[segs.index(s) for s, _ in off]]).all()
    texts = {t.get_text() for t in ax.texts}
    assert {figs._short(v) for _, v in off} <= texts
    # and each has a triangle inside the axis
    tri = [ln for ln in ax.get_lines() if ln.get_marker() == "^"]
    assert sorted(float(ln.get_xdata()[0]) for ln in tri) == sorted(float(s) for s, _ in off)
    assert all(ln.get_ydata()[0] < top for ln in tri)


def test_infinite_values_of_two_methods_at_one_n_do_not_overlap(ax):
    rows = [_record("ico", 25, 0.05), _record("gd", 25, math.inf), _record("ico_nc", 25, math.inf)]
    figs._panel(ax, rows, "linear", "initial", "median")
    top = figs._scale(rows)
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    assert len(crosses) == 2
    xs = [float(ln.get_xdata()[0]) for ln in crosses]
    assert xs[0] != xs[1] and all(abs(x - 25) < 2 for x in xs)
    # in the band above the finite range, inside the axis
    lo, hi = ax.get_ylim()
    assert all(top < ln.get_ydata()[0] < hi for ln in crosses)
    assert "∞" in {t.get_text() for t in ax.texts}


def test_single_n_and_all_infinite_panels_have_a_readable_range(ax):
    rows = [_record("gd", 2, math.inf)]
    figs._panel(ax, rows, "linear", "initial", "quartiles")
    lo, hi = ax.get_xlim()
    assert lo < 2 < hi and hi - lo >= 2
    ylo, yhi = ax.get_ylim()
    assert ylo <= figs._scale(rows) / 100 and yhi > figs._scale(rows)


def test_plot_figures_writes_one_png_per_statistic(tmp_path):
    rows = [_record("pgd", s, 0.2 + 0.01 * s, data=d) for s in (2, 25) for d in ("initial", "sliding")]
    paths = figs.plot_figures(rows, tmp_path)
    assert sorted(p.name for p in paths) == [f"linear_{k}.png" for k in ("max", "median", "quartiles")]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_tables_state_each_sections_settings_quick_runs_and_certificates():
    from dissil_jax.experiments.report import tables_markdown

    base = dict(segments=25, percent_stable=100.0, percent_change_cost=-99.0, train_time_s=0.5,
                mse_q1=0.02, mse_median=0.03, mse_q3=0.04, mse_max=0.05, seed=3, inits=7,
                dissil_jax_version="9.9", jax_version="0.1", dtype="float64", cpu_count=5,
                date="2026-01-02T00:00:00+00:00")
    recs = [dict(base, example="nonlinear", data="initial", method="pgd", certified=True),
            dict(base, example="nonlinear", data="initial", method="gd", certified=None),
            dict(base, example="linear", data="initial", method="ico", certified=False,
                 quick=True, date="2026-01-05T00:00:00+00:00")]
    md = tables_markdown(recs)
    linear, nonlinear = md.split("## Nonlinear")
    assert ("Settings: seed 3; initialisations 7; dissil_jax 9.9; jax 0.1; dtype float64; "
            "CPU count 5; recorded 2026-01-02.") in nonlinear
    assert "recorded 2026-01-05." in linear
    # the quick banner belongs to the quick section only
    assert "Quick run" in linear and "Quick run" not in nonlinear
    rows = {line.split("|")[1].strip(): line.rstrip(" |").rsplit("|", 1)[-1].strip()
            for line in md.splitlines() if line.startswith("| ") and "| 25 |" in line}
    assert rows == {"PGD": "all", "GD": "–", "ICO": "not all"}
