"""Dropped-state impact figure of the ``zupt_filter_order`` study, drawn from its result."""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import LENGTH


def impact_figure(result):
    """Per filter, CEP and altitude PE with each dropped block's noise alone / put back.

    Each panel has two bars per dropped block -- (a) the block's eq (11)-(13)
    noise alone, (b) the block put back into the filter -- and the filter's
    nominal and no-equivalent-noise values as vertical lines.  A bar value
    that is not a finite non-negative length (a covariance the guard did
    not pass) has no bar but an "n/a" at the axis, never a bar of zero; a
    reference line that is not has no line and an "n/a" in its panel's
    title.

    Parameters
    ----------
    result : covtool.results.ZuptFilterOrderResult
        Its ``impact`` table (lengths in ft), last report time and
        ``length_unit`` (``[output] units``, in which the lengths are drawn).

    Returns
    -------
    matplotlib.figure.Figure
    """
    table, t_report = result.tables["impact"], result.report_times[-1]
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    tab = table[np.isclose(table["t [min]"], t_report / 60.0)]
    names = list(dict.fromkeys(tab["filter"]))
    cols = ("CEP [ft]", "alt PE [ft]")
    unit = getattr(result, "length_unit", "ft")
    scale = LENGTH["ft"] / LENGTH[unit]
    # one pass over the table: (filter, block, variant) -> the two values (the first row of each, as .iloc[0]),
    # in the study's length unit
    value = {}
    for key, v in zip(zip(tab["filter"], tab["block"], tab["variant"]), zip(*(tab[c] for c in cols))):
        value.setdefault(key, tuple(x * scale for x in v))
    bars = (("noise from block only", -0.2, "(a) eq (11)-(13) noise of this block only"),
            ("block put back", 0.2, "(b) this block put back into the filter"))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.2 + 2.6 * len(names)), squeeze=False)
    for r, name in enumerate(names):
        blocks = list(dict.fromkeys(b for (f, b, _v) in value if f == name and b != ""))
        nom = next(v for (f, _b, var), v in value.items() if f == name and var == "nominal")
        none = next(v for (f, _b, var), v in value.items() if f == name and var == "no equivalent noise")
        y = np.arange(len(blocks))
        for c, col in enumerate(cols):
            ax = axes[r, c]
            ref = [x if np.isfinite(x) and x >= 0 else np.nan for x in (nom[c], none[c])]
            top = [x for x in ref if np.isfinite(x)]
            # the reference lines first (a line of NaN draws nothing but keeps its legend entry): the legend
            # reads nominal, no noise, (a), (b)
            ax.axvline(ref[0], color="k", lw=1.2, label="nominal (all dropped blocks as noise)")
            ax.axvline(ref[1], color="0.5", lw=1.0, ls="--", label="no equivalent noise")
            # each variant's bars as one collection of rectangles (0, y ± 0.2) – (w, y ± 0.2): one artist,
            # not one patch per bar (the same rectangles, drawn in a fraction of the time)
            for j, (variant, off, label) in enumerate(bars):
                w = np.array([value[(name, b, variant)][c] for b in blocks], float)
                ok = np.isfinite(w) & (w >= 0)
                y0, y1, z = y[ok] + off - 0.2, y[ok] + off + 0.2, np.zeros(int(ok.sum()))
                verts = np.stack([np.c_[z, y0], np.c_[z, y1], np.c_[w[ok], y1], np.c_[w[ok], y0]], axis=1)
                ax.add_collection(PolyCollection(verts, facecolors=colors[j], edgecolors="none", label=label))
                for yb in y[~ok] + off:
                    ax.text(0.0, yb, " n/a", va="center", ha="left", fontsize=7, color="0.3")
                top.extend(w[ok])
            hi = max(top, default=0.0)
            ax.set_xlim(0.0, 1.05 * hi if hi > 0 else 1.0)
            # the bars span y − 0.4 … y + 0.4; 5 % of that span beyond, the first block on top
            pad = 0.05 * max(len(blocks) - 0.2, 1.0)
            ax.set_ylim(len(blocks) - 0.6 + pad, -0.4 - pad)
            # the blocks are named once, on the left panel; the right one has the same rows, unlabelled
            ax.set_yticks(y, blocks, fontsize=8) if c == 0 else ax.set_yticks([])
            quantity = col.split(" [")[0]
            ax.set_xlabel(f"true {quantity} [{unit}] at {t_report / 60:g} min")
            missing = [lab for lab, x in zip(("nominal", "no equivalent noise"), ref) if not np.isfinite(x)]
            ax.set_title(f"filter {name}: {quantity}" + "".join(f" ({lab} n/a)" for lab in missing))
            ax.grid(True, axis="x", alpha=0.3)
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", ncol=4, fontsize=8)
    fig.suptitle("Dropped-state impact (D'Appolito state deletion, seed 002 ref [13])")
    from covtool.plotting.style import fixed_margins

    # block names of up to ~14 characters at 8 pt on the left; the legend row at the bottom
    fixed_margins(fig, left=1.0, right=0.3, bottom=1.05, top=0.9, wspace=0.22, hspace=0.55)
    return fig
