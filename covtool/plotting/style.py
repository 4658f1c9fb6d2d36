"""Shared figure conventions: per-case styles, adaptive log limits, stop bands, legends outside.

Every figure of :mod:`covtool.plotting` uses these so that

* each case has its own colour, line style *and* marker (curves that lie on
  one another stay distinguishable), and cases whose curves coincide are
  named together in the legend;
* a log axis spans the data (no fixed floor clipping a curve);
* ZUPT stops are shaded bands;
* legends sit beside the axes, never over a curve.
"""

from __future__ import annotations

import numpy as np

from covtool.units import OUTPUT_LENGTHS

#: SI per unit of the length units a study may choose (``[output] units``; one home: covtool.units)
LENGTH = OUTPUT_LENGTHS

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
           "#7f7f7f", "#bcbd22")
_LINES = ("-", "--", "-.", ":", (0, (5, 1, 1, 1, 1, 1)), (0, (8, 2)))
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">")


def case_style(k: int) -> dict:
    """Colour, line style and marker of the ``k``-th case (all three differ between neighbours)."""
    return {"color": _COLORS[k % len(_COLORS)], "linestyle": _LINES[k % len(_LINES)],
            "marker": _MARKERS[k % len(_MARKERS)]}


def source_colors(names) -> dict:
    """One distinct colour per source name, the same in every panel and figure.

    Parameters
    ----------
    names : sequence of str
        Every source of the study, in one fixed order.

    Returns
    -------
    dict of str to colour
        Up to 18 sources from matplotlib's ``tab20`` without its greys
        (kept for "other"), the strong hues first; more from
        ``tab20b``/``tab20c``.
    """
    import matplotlib.pyplot as plt

    # grey (tab20's 14, 15) is kept for "other"
    strong = [plt.get_cmap("tab20")(i) for i in range(0, 20, 2) if i != 14]
    light = [plt.get_cmap("tab20")(i) for i in range(1, 20, 2) if i != 15]
    more = [plt.get_cmap(nm)(i) for nm in ("tab20b", "tab20c") for i in range(20)]
    pal = strong + light + more
    return {n: pal[i % len(pal)] for i, n in enumerate(names)}


def log_limits(curves, pad: float = 1.5) -> tuple[float, float] | None:
    """Limits of a log axis that show every positive finite value of ``curves``.

    Parameters
    ----------
    curves : iterable of array_like
    pad : float
        Factor of room below the smallest and above the largest value.

    Returns
    -------
    (float, float) or None
        ``None`` when no value is positive.
    """
    vals = np.concatenate([np.asarray(c, float).ravel() for c in curves]) if curves else np.zeros(0)
    vals = vals[np.isfinite(vals) & (vals > 0)]
    if not vals.size:
        return None
    return float(vals.min() / pad), float(vals.max() * pad)


def coincident_groups(curves: dict, rtol: float = 0.01) -> list[list[str]]:
    """Cases whose curves coincide within ``rtol`` everywhere, grouped.

    Parameters
    ----------
    curves : dict of str to ndarray, shape (K,)
    rtol : float
        Largest relative difference (to the larger value) counted as the same.

    Returns
    -------
    list of list of str
        Groups in first-appearance order; a case alone is a group of one.
    """
    names = list(curves)
    groups: list[list[str]] = []
    for n in names:
        y = np.asarray(curves[n], float)
        for g in groups:
            y0 = np.asarray(curves[g[0]], float)
            den = np.maximum(np.abs(y), np.abs(y0))
            ok = np.isfinite(y) & np.isfinite(y0) & (den > 0)
            if y.shape == y0.shape and ok.any() and np.all(np.abs(y - y0)[ok] <= rtol * den[ok]) \
                    and np.array_equal(np.isfinite(y), np.isfinite(y0)):
                g.append(n)
                break
        else:
            groups.append([n])
    return groups


def shade_stops(ax, stops, *, label: str | None = "stop with ZUPT") -> None:
    """Shade each ``(start, end)`` stop [s] on a time axis in minutes."""
    for i, (a, b) in enumerate(stops):
        ax.axvspan(a / 60.0, max(b, a + 1.0) / 60.0, color="#9ecae1", alpha=0.35, lw=0,
                   label=label if i == 0 else None, zorder=0)


def log_axis(ax, which: str = "y") -> None:
    """Put ``ax``'s ``which`` axis on a log scale with minor ticks at 2 and 5 of each decade.

    Its labels are plain text (:func:`plain_log_labels`).

    Matplotlib's default places a minor tick (and, with ``grid(which="both")``, a grid line) at
    every multiple 2…9 of each decade.  Each tick is an artist of several lines and texts: on a
    figure spanning five decades they took a quarter of its drawing time.  Ticks at 2 and 5 keep
    a readable grid and label short spans.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    which : {"x", "y"}

    Raises
    ------
    ValueError
        ``which`` is neither ``"x"`` nor ``"y"``.
    """
    from matplotlib.ticker import LogLocator

    axis = _axis(ax, which)
    (ax.set_xscale if which == "x" else ax.set_yscale)("log")
    axis.set_minor_locator(LogLocator(base=10.0, subs=(2.0, 5.0)))
    plain_log_labels(ax, which)


def plain_log_labels(ax, which: str = "y") -> None:
    """Label ``ax``'s ``which`` log axis in plain text (:class:`covtool.plotting.ticks.PlainLogFormatter`).

    The same labels on the same ticks as matplotlib's default (in the
    scale's base), without a mathtext parse per label in each process that
    draws.  Call it after the axis is put on its log scale.

    Raises
    ------
    ValueError
        ``which`` is neither ``"x"`` nor ``"y"``.
    """
    from covtool.plotting.ticks import PlainLogFormatter

    axis = _axis(ax, which)
    base = float(getattr(axis.get_transform(), "base", 10.0))     # the scale's own base (10 unless set)
    axis.set_major_formatter(PlainLogFormatter(base=base))
    axis.set_minor_formatter(PlainLogFormatter(base=base, labelOnlyBase=False))


def _axis(ax, which: str):
    """``ax.xaxis`` or ``ax.yaxis``; ``ValueError`` for any other ``which``."""
    if which not in ("x", "y"):
        raise ValueError(f"which must be 'x' or 'y', got {which!r}")
    return getattr(ax, f"{which}axis")


def legend_outside(ax, **kw):
    """Legend to the right of ``ax``: it never covers a curve."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8, **kw)


def fixed_margins(fig, *, left: float = 0.9, right: float = 0.25, bottom: float = 0.6, top: float = 0.45,
                  wspace: float | None = None, hspace: float | None = None) -> None:
    """Place the axes with margins given in inches (no layout pass).

    ``tight_layout`` and the constrained layout measure every tick label
    of every axes, a second draw of the figure; the figures of
    :mod:`covtool.plotting` have known contents (tick labels of a few
    characters, a legend of known width beside the axes), so their margins
    are declared instead, in inches so that they hold at any figure size.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    left, right, bottom, top : float
        Margins between the figure's edges and the axes grid. [in]
    wspace, hspace : float, optional
        Space between axes as a fraction of the average axes width/height
        (matplotlib's ``subplots_adjust``).
    """
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    w, h = fig.get_size_inches()
    fig.set_layout_engine(None)
    fig.subplots_adjust(left=left / w, right=1.0 - right / w, bottom=bottom / h, top=1.0 - top / h,
                        wspace=wspace, hspace=hspace)
    # a placeholder engine: the layout is done, and no writer may impose another
    fig.set_layout_engine(PlaceHolderLayoutEngine(adjust_compatible=True, colorbar_gridspec=True))
