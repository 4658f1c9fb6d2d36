"""Dual-IMU figures (seed 001), drawn from a :class:`~covtool.results.DualImuResult`."""

from __future__ import annotations

import numpy as np

from covtool.dualnav.difference import DIFF_NAMES
from covtool.plotting.style import legend_outside, log_axis
from covtool.units import PPM_G

#: component kind -> (unit, SI to unit)
DIFF_UNITS = {"pos": ("m", 1.0), "vel": ("m/s", 1.0), "att": ("mrad", 1e3)}


def dual_imu_figures(result) -> dict:
    """Figure makers of a dual-IMU result: difference envelope, window test, g-sensitivity estimates.

    Parameters
    ----------
    result : covtool.results.DualImuResult

    Returns
    -------
    dict of str to functools.partial
        ``name -> f()`` returning a matplotlib Figure (partials over
        ``result``: they pickle with its figure view, for the figure server).
    """
    from functools import partial

    figs = {"difference_envelope": partial(difference_figure, result), "window_test": partial(window_figure, result)}
    if result.config.fault and result.estimates:
        figs["gsens_estimates"] = partial(gsens_figure, result)
    return figs


def difference_figure(result):
    """Each compared component's difference in the first flights against the ±3σ predicted envelope.

    Parameters
    ----------
    result : covtool.results.DualImuResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    cfg, free, fault = result.config, result.fault_free, result.fault
    labels = result.labels
    import matplotlib.pyplot as plt

    comps = free[0].model.components if free else fault[0].model.components
    fig, axs = plt.subplots(2, 3, figsize=(13, 7), sharex=True)
    for k, c in enumerate(comps[-6:]):
        ax = axs.flat[k]
        name = DIFF_NAMES[c]
        unit, scale = DIFF_UNITS[name[:3]]
        ref = free[0] if free else fault[0]
        ci = list(ref.model.components).index(c)
        ax.fill_between(ref.t, -3 * scale * ref.envelope[:, ci], 3 * scale * ref.envelope[:, ci], color="0.85",
                        label="±3σ predicted")
        for runs, color, lab in ((free, "C0", labels[0]), (fault, "C3", labels[1])):
            for r in runs[:1]:
                for i in range(min(3, r.z.shape[0])):
                    ax.plot(r.t, scale * r.z[i, :, c], color=color, lw=0.8, label=lab if i == 0 else None)
        ax.set_title(f"{name} (main − KIMU)")
        ax.set_ylabel(f"[{unit}]")
        ax.grid(True, alpha=0.3)
    legend_outside(axs.flat[2])
    for ax in axs[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{cfg.name}: navigation difference after mounting compensation vs predicted envelope")
    fig.tight_layout()
    return fig


def window_figure(result):
    """The windowed NIS statistic of every flight against its threshold.

    Parameters
    ----------
    result : covtool.results.DualImuResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    cfg, free, fault = result.config, result.fault_free, result.fault
    labels = result.labels
    import matplotlib.pyplot as plt

    from matplotlib.collections import LineCollection

    fig, ax = plt.subplots(figsize=(9, 4.5))
    thr = None
    for runs, color, lab in ((free, "0.6", labels[0]), (fault, "C3", labels[1])):
        # one collection per group: a Line2D per flight (1100 of them) took seconds to draw
        segs = []
        for r in runs:
            W = r.window_stat.shape[1]
            tt = r.t[r.t.size - W:]
            segs += [np.column_stack([tt, s]) for s in r.window_stat]
            thr = r.window_threshold
        if segs:
            ax.add_collection(LineCollection(segs, colors=color, linewidths=0.5, alpha=0.6, label=lab))
    if thr is not None:
        ax.axhline(thr, color="k", ls="--", label=f"threshold (α = {cfg.false_alarm:g} per flight)")
    log_axis(ax, "y")
    ax.autoscale_view()
    ax.set_xlabel("end of window [s]")
    ax.set_ylabel(f"Σ NIS over {cfg.window:g} s")
    legend_outside(ax)
    fig.tight_layout()
    ax.grid(True, alpha=0.3)
    return fig


def gsens_figure(result):
    """The g-sensitivity estimates of the fault-free and the faulted flights.

    Parameters
    ----------
    result : covtool.results.DualImuResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    cfg, free, fault = result.config, result.fault_free, result.fault
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    if fault:
        c = fault[0].gsens.candidates.index((cfg.fault[0], cfg.fault[1]))
        e = np.concatenate([r.gsens.estimate[:, c] for r in fault]) / PPM_G
        k = cfg.fault[2] / PPM_G
        ax.hist(e, bins=20, color="C3", alpha=0.7, label="fault runs")
        ax.axvline(k, color="k", label="injected")
        ax.axvspan(0.8 * k, 1.2 * k, color="C2", alpha=0.15, label="±20 %")
    if free:
        c = free[0].gsens.candidates.index((cfg.fault[0], cfg.fault[1])) if cfg.fault else 0
        e = np.concatenate([r.gsens.estimate[:, c] for r in free]) / PPM_G
        ax.hist(e, bins=20, color="0.5", alpha=0.7, label="fault-free runs")
    ax.set_xlabel("estimated g-sensitive scale factor [ppm/g]")
    ax.set_ylabel("flights")
    legend_outside(ax)
    fig.tight_layout()
    return fig
