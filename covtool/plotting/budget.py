"""Error-budget figures (seed 002, Fig 4), drawn from an :class:`~covtool.results.ErrorBudgetResult`."""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import LENGTH, fixed_margins, log_limits, shade_stops, source_colors, log_axis
from covtool.units import ARCMIN

#: error -> (axis title, unit kind)
ERRORS = {"horizontal": ("horizontal position (σ_N² + σ_E²)", "length"), "altitude": ("altitude (σ_D²)", "length"),
          "azimuth": ("azimuth (σ_ψ²)", "angle")}


def top_sources(v: np.ndarray, top: int) -> list[int]:
    """Indices of the ``top`` sources with the largest peak share.

    Parameters
    ----------
    v : ndarray, shape (B, n_rec)
        Variance contributions over time.
    top : int

    Returns
    -------
    list of int
        Sources ordered by the largest share of the total they reach at
        any record time (times with a zero total are skipped); sources that
        never contribute are left out.
    """
    tot = v.sum(axis=0)
    pos = tot > 0
    if not pos.any():
        return []
    peak = np.max(v[:, pos] / tot[pos], axis=1)
    return [int(i) for i in np.argsort(-peak, kind="stable")[:top] if peak[i] > 0]


def budget_figure(result, case: str):
    """One case's error budget: each source's variance on a log axis, and shares.

    Left column: the variance contribution of each of the ``result.top``
    sources with the largest peak share, the rest summed as "other", and
    the total (black), as lines on a log axis spanning the data -- so the
    state after the first stop is as readable as its peak.  Right column:
    the shares of the variance, stacked (%).  Every source keeps one colour
    in every panel (and in every case's figure); ZUPT stops are shaded; one
    legend beside the axes.

    Parameters
    ----------
    result : covtool.results.ErrorBudgetResult
    case : str
        A key of ``result.variances``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    colors = source_colors(result.source_order)
    tm = np.asarray(result.times) / 60.0
    names = result.sources[case]
    lu = result.length_unit
    fig, axs = plt.subplots(3, 2, figsize=(16, 11), sharex=True, gridspec_kw={"width_ratios": [3, 2]})
    handles = {}
    for row, (e, (title, kind)) in zip(axs, ERRORS.items()):
        si, unit = (LENGTH[lu], lu) if kind == "length" else (ARCMIN, "arcmin")
        v = np.asarray(result.variances[case][e]) / si**2
        idx = top_sources(v, result.top)
        rest = [i for i in range(len(names)) if i not in idx]
        total = v.sum(axis=0)
        lines = [(names[i], v[i], colors[names[i]]) for i in idx]
        if rest:
            lines.append((f"other ({len(rest)} sources)", v[rest].sum(axis=0), "0.55"))
        later = tm > 0
        for lab, y, col in lines:
            (h,) = row[0].plot(tm, np.where(y > 0, y, np.nan), color=col, lw=1.4, label=lab)
            handles.setdefault(lab, h)
        (h,) = row[0].plot(tm, total, color="k", lw=2.0, label="total")
        handles.setdefault("total", h)
        log_axis(row[0], "y")
        lim = log_limits([total[later]] + [y[later] for _, y, _ in lines], pad=2.0)
        if lim:
            # sources below 1e-4 of the largest total are not worth a decade of the axis
            row[0].set_ylim(max(lim[0], lim[1] * 1e-5), lim[1])
        with np.errstate(divide="ignore", invalid="ignore"):
            pct = [np.where(total > 0, 100.0 * np.clip(y, 0, None) / total, 0.0) for _, y, _ in lines]
        row[1].stackplot(tm, *pct, colors=[c for _, _, c in lines])
        row[1].set_ylim(0, 100)
        row[0].set_ylabel(f"variance [{unit}²]")
        row[1].set_ylabel("share of variance [%]")
        row[0].set_title(f"{case}: {title}")
        for ax in row:
            if case != "pure_ins":
                shade_stops(ax, result.stops, label=None)
            ax.grid(True, which="both", alpha=0.3)
    for ax in axs[-1]:
        ax.set_xlabel("time [min]")
        ax.set_xlim(tm[0], tm[-1])
    order = [k for k in result.source_order if k in handles] + [k for k in handles if k not in result.source_order]
    fig.legend([handles[k] for k in order], order, loc="upper left", bbox_to_anchor=(0.80, 0.95), fontsize=8,
               title="source (one colour in every panel)")
    note = "; shaded: stops with ZUPT" if case != "pure_ins" and result.stops else ""
    fig.suptitle(f"Error budget, {case}: variance by source (the {result.top} with the largest peak share){note}")
    # the axes end at 79 % of the width: the legend (anchored at 80 %) sits beside them
    fixed_margins(fig, left=0.9, right=0.21 * 16 + 0.1, bottom=0.6, top=0.8, wspace=0.22, hspace=0.25)
    return fig
