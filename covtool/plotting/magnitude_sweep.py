"""Figures of the ``magnitude_sweep`` study (moved from its runner, unchanged)."""

from __future__ import annotations

import pandas as pd


def sweep_figure(sweep: pd.DataFrame, opts: dict, truth):
    def make():
        import matplotlib.pyplot as plt
        from covtool.units import from_si
        groups = opts["groups"]
        fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 4.2), squeeze=False, sharey=True)
        for ax, g in zip(axes[0], groups):
            unit = g["unit_text"]
            s = sweep[sweep["group"] == g["name"]]
            for f in dict.fromkeys(s["filter"]):
                if f == "A":
                    continue
                gg = s[s["filter"] == f].sort_values("magnitude, SI value")
                x = [float(from_si(v, unit)) if unit else v for v in gg["magnitude, SI value"]]
                ax.plot(x, gg["CEP / A [-]"], marker="o", ms=3, label=f)
            ax.axhline(opts["threshold"], color="k", ls="--", lw=1, label=f"{opts['threshold']:g} x A")
            dsig = truth.states[truth.index[g["states"][0]]].sigma
            ax.axvline(float(from_si(dsig, unit)) if unit else dsig, color="0.5", ls=":", lw=1,
                       label="declared")
            ax.set_xscale("log")
            ax.set_xlabel(f"{g['name']} 1sigma [{unit}]" if unit else g["name"])
            ax.set_title(g["name"])
            ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].set_ylabel("true CEP / CEP of optimal filter A at the report time")
        axes[0, -1].legend(fontsize=8)
        fig.suptitle("Where the reduced filters stop being within the threshold of the optimal filter")
        fig.tight_layout()
        return fig
    return make
