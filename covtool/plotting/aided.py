"""Figures of the aided studies (issue 15): the truth under each filter, the ensemble ratio, the sweep.

Each maker takes the arrays and tables it draws (not a result object), so
that ``functools.partial`` of it pickles: the command line's figure server
draws it while the study computes the next figure's data
(:mod:`covtool.io.figure_server`).
"""

from __future__ import annotations

import numpy as np

from covtool.plotting.style import plain_log_labels


def aided_history_figure(study: str, grade: str, metrics: dict, tr: np.ndarray, outages):
    """CEP and altitude 1σ of the truth under each filter of one IMU grade.

    Parameters
    ----------
    study : str
        Study name (the title).
    grade : str
        The grade drawn: the keys ``(grade, case)`` of ``metrics`` with it.
    metrics : dict of (str, str) to dict of str to ndarray, shape (n_rec,)
        :func:`covtool.analysis.metrics.nav_metrics` per (grade, case) (SI: m).
    tr : ndarray, shape (n_rec,)
        Record times. [s]
    outages : list of (str, float, float)
        ``(name, start, end)`` of each aiding outage, shaded. [s]

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for (g, case), m in metrics.items():
        if g != grade:
            continue
        axs[0].plot(tr / 60, m["cep"], label=case, lw=1.2)
        axs[1].plot(tr / 60, m["sigma_down"], label=case, lw=1.2)
    for _, a, b in outages:
        for ax in axs:
            ax.axvspan(a / 60, b / 60, color="0.85", lw=0)
    axs[0].set_yscale("log")
    axs[0].set_ylabel("CEP [m]")
    axs[1].set_yscale("log")
    for ax in axs:
        plain_log_labels(ax, "y")
    axs[1].set_ylabel("altitude error 1σ [m]")
    axs[1].set_xlabel("time [min]")
    axs[0].legend(fontsize=8)
    for ax in axs:
        ax.grid(True, alpha=0.3, which="both")
    fig.suptitle(f"{study}: truth under each filter, grade {grade}" + (" (outages shaded)" if outages else ""))
    return fig


def aided_ensemble_figure(study: str, quantities, cases, bands: dict, t: np.ndarray, runs: int, confidence: float):
    """Ensemble RMS over the linear σ per quantity and filter, with its χ² bounds shaded.

    Parameters
    ----------
    study : str
    quantities : list of str
        One panel each.
    cases : list of str
    bands : dict of (str, str) to tuple of 4 ndarray, shape (n_rec,)
        ``(rms, sigma, lo, hi)`` per (case, quantity): the ensemble RMS, the
        linear 1σ and the RMS bounds at ``confidence``.
    t : ndarray, shape (n_rec,)
        Record times. [s]
    runs : int
    confidence : float

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    qs = list(quantities)
    fig, axs = plt.subplots(len(qs), 1, figsize=(9, 2.2 * len(qs)), sharex=True)
    for ax, q in zip(np.atleast_1d(axs), qs):
        for c in cases:
            rms, sig, lo, hi = bands[(c, q)]
            pos = sig > 0
            line, = ax.plot(t[pos] / 60, rms[pos] / sig[pos], lw=1.0, label=f"filter {c}")
            ax.fill_between(t[pos] / 60, lo[pos] / sig[pos], hi[pos] / sig[pos], color=line.get_color(),
                            alpha=0.15, lw=0)
        ax.axhline(1.0, color="0.3", lw=0.8)
        ax.set_ylabel(f"{q}\nRMS/σ")
        ax.grid(True, alpha=0.3)
    axs = np.atleast_1d(axs)
    axs[0].legend(fontsize=8)
    axs[-1].set_xlabel("time [min]")
    fig.suptitle(f"{study}: {runs}-run ensemble RMS / linear σ ({100 * confidence:g} % χ² bounds shaded)")
    return fig


def aided_sweep_figure(study: str, df, sweep: dict):
    """CEP at the last record time against a measurement's scale, per (grade, case).

    Parameters
    ----------
    study : str
    df : DataFrame
        The ``measurement_sweep`` table (columns ``grade``, ``case``,
        ``scale``, ``t [min]``, ``CEP [m]``).
    sweep : dict
        ``measurement`` and ``what`` (the swept quantity), for the labels.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    last = df[df["t [min]"] == df["t [min]"].max()]
    fig, ax = plt.subplots(figsize=(7, 5))
    for (g, case), d in last.groupby(["grade", "case"], sort=False):
        ax.loglog(d["scale"], d["CEP [m]"], "o-", label=f"{g}: {case}" if g != "as declared" else case)
    plain_log_labels(ax, "x")
    plain_log_labels(ax, "y")
    ax.set_xlabel(f"{sweep['measurement']} {sweep['what']} scale [-]")
    ax.set_ylabel(f"CEP at {last['t [min]'].iloc[0]:g} min [m]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"{study}: {sweep['measurement']} {sweep['what']} sweep")
    return fig
