"""Figure of the ``magnitude_sweep`` study, drawn from a :class:`~covtool.results.MagnitudeSweepResult`."""

from __future__ import annotations

from covtool.plotting.style import case_style, legend_outside, log_axis


def sweep_figure(result):
    """True CEP / CEP of filter A against each swept magnitude, per reduced filter.

    One panel per group (log x, in the group's datasheet unit), one curve
    per filter with its own colour, line style and marker; the threshold
    and the model's declared magnitude are marked; legend beside the axes.

    Parameters
    ----------
    result : covtool.results.MagnitudeSweepResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    from covtool.units import from_si

    sweep, groups = result.sweep, result.groups
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups) + 1.6, 4.4), squeeze=False, sharey=True)
    for ax, g in zip(axes[0], groups):
        unit = g["unit_text"]
        s = sweep[sweep["group"] == g["name"]]
        for k, f in enumerate(dict.fromkeys(s["filter"])):
            if f == "A":
                continue
            gg = s[s["filter"] == f].sort_values("magnitude, SI value")
            x = [float(from_si(v, unit)) if unit else v for v in gg["magnitude, SI value"]]
            ax.plot(x, gg["CEP / A [-]"], ms=4, label=f, markerfacecolor="none", **case_style(k))
        ax.axhline(result.threshold, color="k", ls="--", lw=1, label=f"{result.threshold:g} x A")
        dsig = result.declared[g["name"]]
        ax.axvline(float(from_si(dsig, unit)) if unit else dsig, color="0.5", ls=":", lw=1, label="declared")
        log_axis(ax, "x")
        ax.set_xlabel(f"{g['name']} 1sigma [{unit}]" if unit else g["name"])
        ax.set_title(g["name"])
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("true CEP / CEP of optimal filter A at the report time")
    legend_outside(axes[0, -1])
    fig.suptitle("Where the reduced filters stop being within the threshold of the optimal filter")
    fig.tight_layout()
    return fig
