"""Navigation-error figures: seed 002 Figs 6-7 and the pure INS errors, drawn from results."""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import (log_axis, LENGTH, case_style, coincident_groups, legend_outside, log_limits,
                                    shade_stops)
from covtool.units import ARCMIN

#: quantity -> (metric key, axis label, figure title)
QUANTITIES = {"horizontal": ("cep", "horizontal CEP", "Fig 6: horizontal position error (CEP)"),
              "altitude": ("alt_pe", "altitude PE", "Fig 7: altitude error (PE)")}


def error_history_figure(result, quantity: str = "horizontal"):
    """Seed 002 Fig 6 (``"horizontal"``) or Fig 7 (``"altitude"``) from a filter-order result.

    One curve per case, each with its own colour, line style and markers
    (staggered so that coinciding curves all show); cases whose curves
    coincide within 1 % are named in a note.  The log axis spans every
    value from the first update on (the start-up ramp from σ = 0 is not
    allowed to stretch it); ZUPT stops are shaded; the legend sits beside
    the axes.

    Parameters
    ----------
    result : covtool.results.ZuptFilterOrderResult
        Its ``metrics`` (per case), ``times``, ``stops`` and ``length_unit``.
    quantity : {"horizontal", "altitude"}

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    KeyError
        Unknown ``quantity``.
    """
    import matplotlib.pyplot as plt

    key, ylabel, title = QUANTITIES[quantity]
    unit = result.length_unit
    t = np.asarray(result.times)
    tm = t / 60.0
    curves = {c: np.asarray(m[key]) / LENGTH[unit] for c, m in result.metrics.items()}
    later = t > 0
    groups = coincident_groups({c: y[later] for c, y in curves.items()})
    fig, ax = plt.subplots(figsize=(10, 5.2))
    shade_stops(ax, result.stops)
    n = len(curves)
    every = max(1, t.size // 12)
    for k, (c, y) in enumerate(curves.items()):
        st = case_style(k)
        ax.plot(tm, y, lw=1.4, label=c, markevery=(int(k * every / max(n, 1)), every), ms=5,
                markerfacecolor="none", **st)
    # the axis spans every value from the first update on: the start-up ramp from σ = 0 would
    # otherwise stretch it over decades the filters never visit (it is drawn, and clipped, below)
    tu = np.asarray(result.update_times)
    span = t >= tu[0] if tu.size else later
    lim = log_limits([y[span] for y in curves.values()])
    log_axis(ax, "y")
    if lim:
        ax.set_ylim(*lim)
    ax.set_xlim(tm[0], tm[-1])
    ax.set_xlabel("time [min]")
    ax.set_ylabel(f"{ylabel} [{unit}]")
    ax.set_title(f"{title} by filter model")
    ax.grid(True, which="both", alpha=0.3)
    legend_outside(ax, title="case")
    same = [g for g in groups if len(g) > 1]
    if same:
        note = "; ".join(", ".join(g) + " coincide (within 1 %)" for g in same)
        fig.text(0.01, 0.01, f"Note: {note}. Their markers are staggered so that each shows.", fontsize=8,
                 ha="left", va="bottom")
    from covtool.plotting.style import fixed_margins

    # known contents: log tick labels and the axis label on the left, the legend beside the axes (its longest
    # entry "stop with ZUPT"), the title on top, the note (if any) below the x label
    fixed_margins(fig, left=0.8, right=1.75, bottom=0.85 if same else 0.65, top=0.4)
    return fig


def pure_ins_figure(result):
    """Pure INS position, altitude and attitude 1σ from a pure-INS result.

    Parameters
    ----------
    result : covtool.results.PureInsResult
        Its ``metrics``, ``times`` and ``length_unit``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    m, unit = result.metrics, result.length_unit
    f = LENGTH[unit]
    t = np.asarray(result.times)
    tm, later = t / 60.0, t > 0
    panels = [
        ([("CEP", m["cep"] / f), ("σ north", m["sigma_north"] / f), ("σ east", m["sigma_east"] / f)],
         f"horizontal position [{unit}]"),
        ([("σ altitude", m["sigma_down"] / f)], f"altitude error 1σ [{unit}]"),
        ([("azimuth", m["sigma_azimuth"] / ARCMIN), ("north tilt", m["sigma_tilt_n"] / ARCMIN),
          ("east tilt", m["sigma_tilt_e"] / ARCMIN)], "attitude error 1σ [arcmin]"),
    ]
    fig, axs = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    for ax, (lines, ylabel) in zip(axs, panels):
        for k, (lab, y) in enumerate(lines):
            st = case_style(k)
            ax.plot(tm, y, label=lab, color=st["color"], linestyle=st["linestyle"], lw=1.3)
        lim = log_limits([y[later] for _, y in lines])
        log_axis(ax, "y")
        if lim:
            ax.set_ylim(*lim)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        legend_outside(ax)
    axs[-1].set_xlabel("time [min]")
    axs[-1].set_xlim(tm[0], tm[-1])
    fig.suptitle(f"{result.name}: pure INS errors (1σ)")
    fig.tight_layout()
    return fig
