"""Figures of the studies, drawn from result objects (matplotlib, imported only when a figure is drawn).

Each function takes a :mod:`covtool.results` object (and a case or
quantity) and returns a :class:`matplotlib.figure.Figure`; runners put
``functools.partial(function, result, ...)`` into ``result.figures``.
Conventions shared by every figure are in :mod:`covtool.plotting.style`:
per-case colour, line style and marker, log axes spanning the data, shaded
ZUPT stops, legends beside the axes, one colour per error source.

Modules: :mod:`~covtool.plotting.navigation` (seed 002 Figs 6-7, pure INS),
:mod:`~covtool.plotting.budget` (error budget), :mod:`~covtool.plotting.sensitivity`
(Fig 8), :mod:`~covtool.plotting.zupt_filter_order` (dropped-state impact),
:mod:`~covtool.plotting.magnitude_sweep`, :mod:`~covtool.plotting.monte_carlo`,
:mod:`~covtool.plotting.dual_imu`, :mod:`~covtool.plotting.trade_grid`,
:mod:`~covtool.plotting.ad_reset` (seed 000).
"""
