"""Seed 002 Fig 8 (sensitivity to P_f(0), Q_f, R_f), drawn from a :class:`~covtool.results.ZuptSensitivityResult`."""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import case_style, coincident_groups, LENGTH, legend_outside, log_limits, log_axis, plain_log_labels


def fig8_figure(result, metric: str = "horizontal"):
    """Fig 8.1 (``"horizontal"``) or 8.2 (``"altitude"``): error against each scaled parameter.

    One panel per swept parameter, log-log; per filter its own colour, line
    style and marker (points: covariance analysis, line: least-squares
    fit); filters whose points coincide within 1 % are named in a note;
    the legend sits beside the panels, never over a curve.

    Parameters
    ----------
    result : covtool.results.ZuptSensitivityResult
    metric : {"horizontal", "altitude"}

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    label = result.labels["metrics"][metric]
    params = result.parameters
    fine = np.geomspace(result.scales[0], result.scales[-1], 8 * len(result.scales))
    fig, axes = plt.subplots(1, len(params), figsize=(4.6 * len(params) + 1.6, 4.6), sharey=True, squeeze=False)
    ys = []
    for ax, p in zip(axes[0], params):
        for k, c in enumerate(result.filters):
            st = case_style(k)
            y = result.curves[(c, p, metric)] / LENGTH[result.length_unit]
            ys.append(y)
            ax.plot(result.scales, y, st["marker"], color=st["color"], ms=5, markerfacecolor="none")
            ax.plot(fine, result.fits[(c, p, metric)](fine), color=st["color"], linestyle=st["linestyle"], lw=1.3,
                    marker=st["marker"], markevery=[], label=c)
        log_axis(ax, "x")
        ax.set_yscale("log")            # often under two decades: every minor tick labelled, as matplotlib does
        plain_log_labels(ax, "y")
        ax.set_xlabel(f"{result.labels['params'][p]} scale [-]")
        ax.set_title(f"{result.labels['params'][p]} scaled")
        ax.grid(True, which="both", alpha=0.3)
    lim = log_limits(ys, pad=1.2)
    if lim:
        axes[0][0].set_ylim(*lim)
    axes[0][0].set_ylabel(f"{label} at {result.report_time / 60:g} min [{result.length_unit}]")
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], color=case_style(k)["color"], linestyle=case_style(k)["linestyle"],
                      marker=case_style(k)["marker"], markerfacecolor="none", label=c)
               for k, c in enumerate(result.filters)]
    legend_outside(axes[0][-1], handles=handles, title="filter")
    same = [g for g in coincident_groups({c: np.concatenate([result.curves[(c, p, metric)] for p in params])
                                          for c in result.filters}) if len(g) > 1]
    if same:
        note = "; ".join(", ".join(g) + " coincide (within 1 %)" for g in same)
        fig.text(0.01, 0.01, f"Note: {note}: their markers lie on one another.", fontsize=8, ha="left")
    num = 1 if metric == "horizontal" else 2
    fig.suptitle(f"Fig 8.{num}: sensitivity of the {label.split()[0]} error to the filter's "
                 "P_f(0), Q_f, R_f (points: covariance analysis, lines: least-squares fit)")
    from covtool.plotting.style import fixed_margins

    # known contents: log tick labels and an axis label on the left, the legend of short filter names on the
    # right, the suptitle and panel titles on top, the note (if any) below the x labels
    fixed_margins(fig, left=0.95, right=0.8, bottom=0.85 if same else 0.6, top=0.75, wspace=0.06)
    return fig
