"""Trade-grid figure, drawn from a :class:`~covtool.results.TradeGridResult`."""

from __future__ import annotations

from covtool.plotting.style import case_style, legend_outside, log_limits, log_axis


def trade_figure(result):
    """CEP and altitude PE against ZUPT interval, a panel per IMU grade (nominal tuning).

    Parameters
    ----------
    result : covtool.results.TradeGridResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    nom, grades = result.nominal, result.grades
    u = result.length_unit
    ng = len(grades)
    fig, axes = plt.subplots(2, ng, figsize=(3.6 * ng + 2.2, 7), squeeze=False, sharex=True, sharey="row")
    for j, g in enumerate(grades):
        d = nom[nom["grade"] == g["name"]]
        for k, f in enumerate(result.filters):
            df = d[d["filter"] == f].sort_values("ZUPT interval [min]")
            st = case_style(k)
            axes[0, j].plot(df["ZUPT interval [min]"], df[f"CEP [{u}]"], ms=4, label=f, markerfacecolor="none", **st)
            axes[1, j].plot(df["ZUPT interval [min]"], df[f"alt PE [{u}]"], ms=4, label=f, markerfacecolor="none",
                            **st)
        axes[0, j].set_title(f"{g['name']} (sensor errors ×{g['scale']:g})")
        axes[1, j].set_xlabel("ZUPT interval [min]")
    for r, col in enumerate((f"CEP [{u}]", f"alt PE [{u}]")):
        lim = log_limits([nom[col].to_numpy()], pad=1.3)
        for ax in axes[r]:
            log_axis(ax, "y")
            if lim:
                ax.set_ylim(*lim)
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel(f"horizontal CEP [{u}]")
    axes[1, 0].set_ylabel(f"altitude PE [{u}]")
    legend_outside(axes[0, -1], title="filter")
    tm = nom["t [min]"].max() if len(nom) else result.duration / 60
    fig.suptitle(f"Trade grid at {tm:g} min: filter × ZUPT interval × IMU grade (nominal tuning)")
    fig.tight_layout()
    return fig
