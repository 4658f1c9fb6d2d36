"""Accelerometer-board figures (seed 000), drawn from an :class:`~covtool.results.AdResetResult`."""

from __future__ import annotations

from covtool.plotting.style import case_style, legend_outside, plain_log_labels


def ratio_label(r: float) -> str:
    """``0.5`` -> ``"50%"`` (the N_e / N_t ratio as the tables name it)."""
    return f"{100 * r:g}%"


def ad_reset_figure(result, name: str):
    """One figure of an ``ad_reset`` result, from its table ``name``.

    Parameters
    ----------
    result : covtool.results.AdResetResult
        ``figure_specs[name]`` says what to draw: ``"extrema"`` (Figs 2, 4,
        5: max/min against the input, one colour per N_e ratio), ``"fig3"``
        (zero and extremum points) or ``"bode"`` (magnitude and phase).
    name : str

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    KeyError
        ``name`` is not one of the result's figures.
    """
    spec = result.figure_specs[name]
    df = result.tables[name]
    draw = {"extrema": _extrema, "fig3": _fig3, "bode": _bode}[spec["kind"]]
    return draw(df, name, spec)


def _fig3(df, name, spec):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 4.5))
    for k, (c, ls) in enumerate(zip(df.columns[1:], ("-", "-", "--", "--", ":"))):
        ax.plot(df["N_a [samples]"], df[c], ls, color=case_style(k)["color"], label=c.replace(" [samples]", ""))
    for nm, v in spec["thresholds"].items():
        ax.axvline(v, color="grey", lw=0.6)
        ax.text(v, ax.get_ylim()[1], f" {nm}", va="top", fontsize=8)
    ax.set_xlabel("pulse period $N_a$ [samples]")
    ax.set_ylabel("n [samples]")
    ax.set_title("Fig 3: zero and extremum points of e[n] (eq 17-18)")
    legend_outside(ax)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _bode(df, name, spec):
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8.5, 5.5), sharex=True)
    for col in df.columns[1:]:
        (a1 if "magnitude" in col else a2).semilogx(df["frequency [Hz]"], df[col],
                                                     label=col.split(" magnitude")[0].split(" phase")[0])
    plain_log_labels(a1, "x")                           # a2 shares the x axis, its scale and its tickers
    a1.set_ylabel("magnitude [dB]")
    a2.set_ylabel("phase [deg]")
    a2.set_xlabel("frequency [Hz]")
    a1.set_title(name.replace("_", " "))
    legend_outside(a1)
    for a in (a1, a2):
        a.grid(which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def _extrema(df, name, spec):
    import matplotlib.pyplot as plt

    xcol, unit = spec["xcol"], spec["unit"]
    fig, ax = plt.subplots(figsize=(8.5, 4.5))
    for k, r in enumerate(spec["ratios"]):
        col = case_style(k)["color"]
        lab = ratio_label(r)
        for kind in ("max", "min"):
            ax.plot(df[xcol], df[f"{kind} {lab} [{unit}]"], "-", color=col,
                    label=f"N_e = {lab} N_t" if kind == "max" else None)
            if spec["nav"]:
                ax.plot(df[xcol], df[f"{kind} {lab} nav [{unit}]"], ":", color=col)
            if spec["tag"]:
                ax.plot(df[xcol], df[f"{kind} {lab}{spec['tag']} [{unit}]"], ":", color=col)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel(xcol.replace("m/s^2", "m/s$^2$"))
    ax.set_ylabel(f"{spec['ylabel']} [{unit}]".replace("m/s^2", "m/s$^2$"))
    ax.set_title(spec["title"], fontsize=10)
    legend_outside(ax)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig
