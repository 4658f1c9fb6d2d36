"""Dropped-state impact figure of the ``zupt_filter_order`` study, drawn from its result."""

from __future__ import annotations

import numpy as np


def impact_figure(result):
    """Per filter, CEP and altitude PE with each dropped block's noise alone / put back.

    Parameters
    ----------
    result : covtool.results.ZuptFilterOrderResult
        Its ``impact`` table and last report time.

    Returns
    -------
    matplotlib.figure.Figure
    """
    table, t_report = result.tables["impact"], result.report_times[-1]
    import matplotlib.pyplot as plt
    tab = table[np.isclose(table["t [min]"], t_report / 60.0)]
    names = list(dict.fromkeys(tab["filter"]))
    cols = ("CEP [ft]", "alt PE [ft]")
    # one pass over the table: (filter, block, variant) -> the two values (the first row of each, as .iloc[0])
    value = {}
    for key, v in zip(zip(tab["filter"], tab["block"], tab["variant"]), zip(*(tab[c] for c in cols))):
        value.setdefault(key, v)
    # the two panels of a filter share its blocks' axis: the names are written once, on the left
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.2 + 2.6 * len(names)), squeeze=False, sharey="row")
    for r, name in enumerate(names):
        blocks = list(dict.fromkeys(b for (f, b, _v) in value if f == name and b != ""))
        nom = next(v for (f, _b, var), v in value.items() if f == name and var == "nominal")
        none = next(v for (f, _b, var), v in value.items() if f == name and var == "no equivalent noise")
        y = np.arange(len(blocks))
        for c, col in enumerate(cols):
            ax = axes[r, c]
            only = [value[(name, b, "noise from block only")][c] for b in blocks]
            back = [value[(name, b, "block put back")][c] for b in blocks]
            ax.barh(y - 0.2, only, 0.4, label="(a) eq (11)-(13) noise of this block only")
            ax.barh(y + 0.2, back, 0.4, label="(b) this block put back into the filter")
            ax.axvline(nom[c], color="k", lw=1.2, label="nominal (all dropped blocks as noise)")
            ax.axvline(none[c], color="0.5", lw=1.0, ls="--", label="no equivalent noise")
            if c == 0:
                ax.set_yticks(y, blocks, fontsize=8)
                ax.invert_yaxis()
            ax.set_xlabel(f"true {col} at {t_report / 60:g} min")
            ax.set_title(f"filter {name}: {col.split(' [')[0]}")
            ax.grid(True, axis="x", alpha=0.3)
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", ncol=4, fontsize=8)
    fig.suptitle("Dropped-state impact (D'Appolito state deletion, seed 002 ref [13])")
    from covtool.plotting.style import fixed_margins

    # block names of up to ~14 characters at 8 pt on the left; the legend row at the bottom
    fixed_margins(fig, left=1.0, right=0.3, bottom=1.05, top=0.9, wspace=0.22, hspace=0.55)
    return fig
