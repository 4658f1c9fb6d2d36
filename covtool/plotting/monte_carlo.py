"""Monte Carlo validation figures, drawn from a :class:`~covtool.results.MonteCarloResult`."""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import fixed_margins, LENGTH, case_style, legend_outside, shade_stops, log_axis
from covtool.units import ARCMIN

#: compared quantity -> axis label
LABELS = {"horizontal": "horizontal position (radial)", "altitude": "altitude", "azimuth": "azimuth"}


def _scale(result, q):
    return (ARCMIN, "arcmin") if q == "azimuth" else (LENGTH[result.length_unit], result.length_unit)


def case_figure(result, case: str):
    """One case: Monte Carlo RMS, linear σ and its χ² band, per quantity.

    Parameters
    ----------
    result : covtool.results.MonteCarloResult
    case : str

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    t, band, N, conf = result.times, result.bands[case], result.runs, result.confidence
    fig, axs = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    tm = t / 60.0
    for ax, q in zip(axs, LABELS):
        x, sig, lo, hi = band[q]
        f, u = _scale(result, q)
        shade_stops(ax, result.stops)
        ax.fill_between(tm, lo / f, hi / f, color="C0", alpha=0.25, lw=0,
                        label=f"{100 * conf:g} % χ² bounds of σ (N = {N})")
        ax.plot(tm, sig / f, "C0", lw=1.2, label="linear covariance σ")
        ax.plot(tm, x / f, "C3", lw=0.9, ls="--", label="Monte Carlo RMS")
        ax.set_ylabel(f"{LABELS[q]} [{u}]")
        ax.grid(True, which="both", alpha=0.3)
        if q != "azimuth" and np.nanmax(sig) / max(np.nanmin(sig[1:]), 1e-300) > 100:
            log_axis(ax, "y")
    legend_outside(axs[0])
    axs[-1].set_xlabel("time [min]")
    fig.suptitle(f"{case}: Monte Carlo RMS against the linear covariance analysis")
    # known contents: log tick labels and the axis labels on the left, the legend beside the top axes
    fixed_margins(fig, left=0.85, right=2.35, bottom=0.55, top=0.5, hspace=0.08)
    return fig


def ratio_figure(result):
    """Monte Carlo RMS / linear σ of every case, with the χ² bounds.

    Parameters
    ----------
    result : covtool.results.MonteCarloResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    t, N, conf = result.times, result.runs, result.confidence
    fig, axs = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    tm = t / 60.0
    for ax, q in zip(axs, LABELS):
        shade_stops(ax, result.stops)
        for i, c in enumerate(result.cases):
            st = case_style(i)
            x, sig, lo, hi = result.bands[c][q]
            with np.errstate(invalid="ignore", divide="ignore"):
                ax.plot(tm[1:], (x / sig)[1:], color=st["color"], linestyle=st["linestyle"], lw=0.9, label=c)
                if i == 0 or q == "horizontal":
                    col = st["color"] if q == "horizontal" else "k"
                    ax.plot(tm[1:], (lo / sig)[1:], color=col, ls="--", lw=0.6)
                    ax.plot(tm[1:], (hi / sig)[1:], color=col, ls="--", lw=0.6)
        ax.axhline(1.0, color="k", lw=0.5)
        ax.set_ylabel(f"{LABELS[q]}: RMS / σ")
        ax.grid(True, alpha=0.3)
    legend_outside(axs[0])
    axs[-1].set_xlabel("time [min]")
    fig.suptitle(f"Monte Carlo RMS / linear σ, N = {N}; dashed: {100 * conf:g} % χ² bounds")
    fixed_margins(fig, left=0.85, right=1.6, bottom=0.55, top=0.5, hspace=0.08)
    return fig


def nees_figure(result):
    """Average NEES / d of every case against the χ² bounds (log axis).

    Parameters
    ----------
    result : covtool.results.MonteCarloResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    t, N, conf, nees = result.times, result.runs, result.confidence, result.nees
    keys = ("truth", "filter", "filter_nav")
    titles = {"truth": "navigation errors vs the linear truth covariance (eq (15)-(16)); band: χ² bounds of d",
              "filter": "filter states vs the filter's claimed P_f; dotted: linear prediction, dashed: its bounds",
              "filter_nav": "navigation errors vs the filter's claimed P_f; dotted: linear prediction"}
    fig, axs = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    for ax, key in zip(axs, keys):
        for i, c in enumerate(result.cases):
            if (c, key) not in nees:
                continue
            col = case_style(i)["color"]
            spec, mean, lo, hi, _, pred = nees[(c, key)]
            tm = t[spec.steps] / 60.0
            d = spec.dof
            ax.plot(tm, mean / d, color=col, lw=1.0, label=f"{c} (d = {int(np.median(d))})")
            if pred is not None:
                ax.plot(tm, pred[0] / d, color=col, ls=":", lw=1.2)
                ax.plot(tm, pred[1] / d, color=col, ls="--", lw=0.5)
                ax.plot(tm, pred[2] / d, color=col, ls="--", lw=0.5)
            if i == 0 or key != "truth":
                ax.fill_between(tm, lo / d, hi / d, color="0.5", alpha=0.15, lw=0)
        ax.axhline(1.0, color="k", lw=0.5)
        log_axis(ax, "y")
        ax.set_ylabel("mean NEES / d")
        ax.set_title(titles[key], fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        if ax.has_data() and ax.get_legend_handles_labels()[0]:
            legend_outside(ax)
    axs[-1].set_xlabel("time [min]")
    fig.suptitle(f"Average NEES over N = {N} runs; grey: {100 * conf:g} % χ² bounds of a consistent covariance")
    # each axes has a title: room for it between the panels
    fixed_margins(fig, left=1.3, right=1.75, bottom=0.55, top=0.65, hspace=0.25)
    return fig
