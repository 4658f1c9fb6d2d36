"""Result objects returned by every study runner.

Runners compute; they never open files.  Each study kind returns its own
typed result (a :class:`StudyResult` subclass) whose histories know their
times and state names (:class:`covtool.lincov.history.CovarianceHistory`);
figures are drawn from the result by :mod:`covtool.plotting`, and
:mod:`covtool.io.writers` turns it into files.

Common to every result: ``tables`` (pandas DataFrames whose headers carry
their units), ``figures`` (name -> figure maker), ``provenance``,
``to_pandas()`` (the summary table) and ``plot()`` (the main figure).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from covtool.lincov.history import CovarianceHistory

__all__ = ["StudyResult", "PureInsResult", "ZuptFilterOrderResult", "ErrorBudgetResult", "ZuptSensitivityResult",
           "MagnitudeSweepResult", "AdResetResult", "MonteCarloResult", "DualImuResult", "TradeGridResult",
           "RESULT_CLASSES"]


@dataclass
class StudyResult:
    """Everything a study produced.

    Attributes
    ----------
    name : str
        Study name (used for file names).
    kind : str
        Study kind (``pure_ins``, ``zupt_filter_order``, ``ad_reset``, ...).
    tables : dict of str to DataFrame
        Output tables.  ``"summary"`` is always present and is written to
        ``summary.csv``; every table becomes a workbook sheet and a CSV file.
        Column headers carry their unit in brackets, e.g. ``"cep [ft]"``.
    figures : dict of str to callable
        ``name -> f()`` returning a :class:`matplotlib.figure.Figure`, drawn
        from this result by :mod:`covtool.plotting`; each is saved as
        ``<name>.png``.  Built lazily so the numeric API never imports
        matplotlib.
    resolved : dict
        The fully resolved study declaration (defaults filled in), for provenance.
    provenance : dict
        Extra provenance rows (model hashes, tool version, timings).
    charts : list of dict
        Native Excel chart specifications for the workbook writer
        (see :func:`covtool.io.workbook.add_line_chart`).

    Each subclass adds the named, typed fields of its study kind.
    """

    name: str
    kind: str
    tables: dict[str, pd.DataFrame]
    figures: dict[str, Callable[[], Any]] = field(default_factory=dict)
    resolved: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    charts: list = field(default_factory=list)

    #: the figure :meth:`plot` draws (default: the first of ``figures``)
    main_figure: ClassVar[str | None] = None
    #: the only fields its figures read, besides ``name`` and ``kind`` (None: every field); the others
    #: are left out of :meth:`figure_view`: the study's systems and histories (up to hundreds of MB), and
    #: objects whose unpickling imports what no figure needs (a trajectory and its generating profile,
    #: covtool.nav.trajectory; a board's parameters, python-control)
    drawn_from: ClassVar[tuple[str, ...] | None] = None

    def figure_view(self) -> "StudyResult":
        """A shallow copy for drawing the figures in another process.

        Every field but ``name``, ``kind`` and those of :attr:`drawn_from`
        is None, and ``figures`` is empty, so that the copy pickles small
        and unpickles fast (the figure makers reference this result, not
        the copy).  Used by :class:`covtool.io.figure_server.FigureServer`.

        Returns
        -------
        StudyResult
            Of this result's class.
        """
        import copy
        import dataclasses

        view = copy.copy(self)
        view.figures = {}
        if self.drawn_from is not None:
            keep = {"name", "kind", *self.drawn_from}
            for f in dataclasses.fields(self):
                if f.name not in keep and f.name != "figures":
                    setattr(view, f.name, None)
        return view

    @property
    def summary(self) -> pd.DataFrame:
        """The summary table."""
        return self.tables["summary"]

    def to_pandas(self) -> pd.DataFrame:
        """The summary table (a copy)."""
        return self.summary.copy()

    def plot(self, name: str | None = None):
        """Draw one of the result's figures (default: its main figure).

        Parameters
        ----------
        name : str, optional
            A key of ``figures``.

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        KeyError
            No figure of that name (the message lists them), or the study
            draws none.
        """
        if not self.figures:
            raise KeyError(f"study {self.name!r} ({self.kind}) draws no figure")
        name = name or (self.main_figure if self.main_figure in self.figures else next(iter(self.figures)))
        if name not in self.figures:
            raise KeyError(f"no figure {name!r} (figures: {', '.join(self.figures)})")
        return self.figures[name]()


@dataclass
class _Navigation:
    """Fields shared by the navigation studies (lengths drawn in ``length_unit``)."""

    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    metrics: dict = field(default_factory=dict)
    length_unit: str = "ft"
    update_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stops: tuple = ()


@dataclass
class PureInsResult(_Navigation, StudyResult):
    """``pure_ins``: the truth model propagated without aiding.

    Attributes
    ----------
    history : CovarianceHistory
        Navigation block (seed 002, eq (14)) over the whole run.
    times : ndarray, shape (N+1,)
        Time grid. [s]
    metrics : dict of str to ndarray, shape (N+1,)
        :func:`covtool.analysis.metrics.nav_metrics` (SI).
    length_unit : {"ft", "m"}
        Unit of lengths in the figures (``[output] units``).
    history : CovarianceHistory
        The 10 navigation states (seed 002 eq (14)) at every step of ``times``.
    truth_history : CovarianceHistory
        Every truth state (the full model) at the record steps: every
        ``[output] history_every``, the report times, the start and the
        end (every step without ``history_every``), so that its memory
        grows with the records, not with duration × n².
    """

    history: "CovarianceHistory | None" = None
    truth_history: "CovarianceHistory | None" = None
    main_figure: ClassVar[str] = "pure_ins_errors"
    drawn_from: ClassVar[tuple[str, ...]] = ("times", "metrics", "length_unit")


@dataclass
class ZuptFilterOrderResult(_Navigation, StudyResult):
    """``zupt_filter_order``: reduced filters run against the truth (seed 002, §3.1).

    Attributes
    ----------
    histories : dict of str to CovarianceHistory
        Per case (``"pure_ins"``, filter names), the truth navigation
        block (eq (14)) under that filter's gains, eq (15)-(16).
    claimed : dict of str to CovarianceHistory
        Per filter, the navigation block of the filter's own covariance.
    metrics, claimed_metrics : dict of str to dict of ndarray
        Per case, :func:`covtool.analysis.metrics.nav_metrics` of the truth
        (over ``times``) and of the filter's claim (at ``report_times``
        only: the exact CEP is costly), SI.
    times : ndarray, shape (N+1,)
        Time grid. [s]
    update_times : ndarray
        ZUPT update times. [s]
    stops : tuple of (float, float)
        Stationary intervals holding a ZUPT. [s]
    report_times : list of float
        Times of the summary rows. [s]
    length_unit : {"ft", "m"}
    runs : dict of str to BatchResult
        Per filter, the batched eq (15)-(16) run
        (:class:`covtool.lincov.batch.BatchResult`: navigation blocks of the
        truth and filter covariances at ``record_steps``).
    filter_models : dict of str to FilterModel
        Per filter, its model (spec, state names, ``D``, ``F_f``, ``Q_f``,
        ``P_f(0)``).
    trajectory : object
        The reference trajectory at the grid nodes (``q_nb`` etc.).
    record_steps : ndarray of int
        Grid steps at which the navigation blocks are recorded (the history
        spacing, the report times and the last step); ``times`` are these steps' times.
    """

    histories: dict = field(default_factory=dict)
    claimed: dict = field(default_factory=dict)
    claimed_metrics: dict = field(default_factory=dict)
    report_times: list = field(default_factory=list)
    runs: dict = field(default_factory=dict)
    filter_models: dict = field(default_factory=dict)
    trajectory: Any = None
    record_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    main_figure: ClassVar[str] = "fig6_horizontal_cep"
    drawn_from: ClassVar[tuple[str, ...]] = ("tables", "report_times", "length_unit", "metrics", "stops", "times",
                                             "update_times")


@dataclass
class ErrorBudgetResult(_Navigation, StudyResult):
    """``error_budget``: the truth covariance split into its sources (seed 002, Fig 4).

    Attributes
    ----------
    times : ndarray, shape (K,)
        Record times. [s]
    variances : dict of str to dict of str to ndarray, shape (B, K)
        Per case and error (``horizontal``, ``altitude``, ``azimuth``),
        each source's variance contribution (SI²).
    sources : dict of str to list of str
        Per case, the source names (rows of ``variances``).
    source_order : list of str
        Every source of the study, in one order (one colour each in every
        figure).
    top : int
        Sources drawn per panel.
    runs : dict of str to BudgetRun
        Per case, the batched run of its sources
        (:mod:`covtool.analysis.budget`).
    residuals : dict of str to dict of str to float
        Per case, ``"same"`` (sum of contributions against the total run
        with the same Q_d) and ``"nominal"`` (against the nominal run):
        largest relative residual.
    record_steps : ndarray of int
        Grid steps of ``times``.
    setup : ZuptSetup
        The study's truth, filters and ZUPT schedule
        (:mod:`covtool.studies.zupt_setup`).
    truth_system : System
        The truth Φ, Q_d composed on the event grid
        (:class:`covtool.lincov.batch.System`).
    noise : ndarray, shape (n_sources, K, n, n)
        Per-source truth Q_d of each event interval.
    """

    variances: dict = field(default_factory=dict)
    sources: dict = field(default_factory=dict)
    source_order: list = field(default_factory=list)
    top: int = 8
    runs: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    record_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    setup: Any = None
    truth_system: Any = None
    noise: Any = None
    drawn_from: ClassVar[tuple[str, ...]] = ("length_unit", "source_order", "sources", "stops", "times", "top",
                                             "variances")


@dataclass
class ZuptSensitivityResult(StudyResult):
    """``zupt_sensitivity``: errors against scaled P_f(0), Q_f, R_f (seed 002, Fig 8).

    Attributes
    ----------
    scales : ndarray
        Swept scale factors. [-]
    parameters : list of str
        Swept parameters (``P0``, ``Q``, ``R``).
    curves : dict of (str, str, str) to ndarray
        ``(filter, parameter, metric) -> error [m]`` at the swept scales,
        metric ``"horizontal"`` (CEP) or ``"altitude"`` (PE), last report time.
    fits : dict of (str, str, str) to callable
        The least-squares fits, ``scale -> error`` in ``length_unit``.
    report_time : float
        [s]
    length_unit : {"ft", "m"}
        Unit of the fits and figures (``[output] units``).
    filter_models : dict of str to FilterModel
        Per swept filter, its model (nominal P_f(0), F_f, Q_f).
    setup : ZuptSetup
        The study's truth, filters and ZUPT schedule.
    """

    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))
    parameters: list = field(default_factory=list)
    filters: list = field(default_factory=list)
    curves: dict = field(default_factory=dict)
    fits: dict = field(default_factory=dict)
    report_time: float = 0.0
    labels: dict = field(default_factory=dict)
    length_unit: str = "ft"
    filter_models: dict = field(default_factory=dict)
    setup: Any = None
    main_figure: ClassVar[str] = "fig8_1_horizontal"
    drawn_from: ClassVar[tuple[str, ...]] = ("curves", "filters", "fits", "labels", "length_unit", "parameters",
                                             "report_time", "scales")


@dataclass
class MagnitudeSweepResult(StudyResult):
    """``magnitude_sweep``: where the reduced filters stop being near the optimum.

    Attributes
    ----------
    sweep : DataFrame
        The ``sweep`` table (one row per group, filter and magnitude).
    groups : list of dict
        The swept groups (name, states, unit text).
    threshold : float
        CEP / CEP_A threshold. [-]
    declared : dict of str to float
        Per group, the model's declared 1σ of its first state (SI).
    """

    sweep: pd.DataFrame | None = None
    groups: list = field(default_factory=list)
    threshold: float = 0.0
    declared: dict = field(default_factory=dict)
    drawn_from: ClassVar[tuple[str, ...]] = ("declared", "groups", "sweep", "threshold")


@dataclass
class AdResetResult(StudyResult):
    """``ad_reset``: the accelerometer-board study (seed 000).

    Attributes
    ----------
    figure_specs : dict of str to dict
        Per figure (named as its table), what :func:`covtool.plotting.ad_reset.ad_reset_figure` draws.
    params : dict
        The resolved board parameters (SI).
    derived : dict
        Derived board quantities (scale factor ``sf``, bandwidths, ...; SI).
    """

    figure_specs: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    derived: dict = field(default_factory=dict)
    main_figure: ClassVar[str] = "fig2"
    drawn_from: ClassVar[tuple[str, ...]] = ("tables", "figure_specs")


@dataclass
class MonteCarloResult(_Navigation, StudyResult):
    """``monte_carlo``: the linear covariance against nonlinear Monte Carlo runs.

    Attributes
    ----------
    cases : list of str
    bands : dict of str to dict of str to tuple of ndarray
        Per case and quantity (``horizontal``, ``altitude``, ``azimuth``):
        Monte Carlo RMS, linear σ, lower and upper χ² bound of the RMS,
        each shape (N+1,), SI.
    nees : dict of (str, str) to tuple
        Per case and NEES kind: ``(spec, mean, lower, upper, inside, prediction)``.
    runs : int
        Monte Carlo runs N.
    confidence : float
        Probability of the χ² bounds.
    sums : dict of str to EnsembleSums
        Per case, the Monte Carlo sums of the error moments.
    linear, linear_conditional, linear_driven : dict of str to dict
        Per case, the linear covariance's σ and degrees of freedom: of the
        full run, conditional on the sampled initial errors, and of the
        noise-driven part alone.
    bands_conditional : dict of str to dict of str to tuple of ndarray
        As ``bands``, against the conditional linear σ.
    filter_check : dict of str to float
        Per filter, largest absolute difference of the Monte Carlo feedback
        filter's covariance from the linear run's (SI).
    stats : dict
        Run statistics (backend, chunks computed and reused, seconds).
    acceptance_tests : dict of (str, str) to dict
        Per (case, quantity), the test against the linear-Monte-Carlo null
        (:func:`covtool.analysis.consistency.null_test`: in-bounds share, its
        null 5th percentile, T, its null spread, p-values, verdict).
    null_mean_squares : dict of str to ndarray, optional
        Per case, the linear Monte Carlo's mean squares, shape
        (replicas, times, quantities) (:mod:`covtool.validation.linear_mc`);
        None when ``null_replicas = 0``.
    """

    cases: list = field(default_factory=list)
    bands: dict = field(default_factory=dict)
    nees: dict = field(default_factory=dict)
    runs: int = 0
    confidence: float = 0.95
    sums: dict = field(default_factory=dict)
    linear: dict = field(default_factory=dict)
    linear_conditional: dict = field(default_factory=dict)
    linear_driven: dict = field(default_factory=dict)
    bands_conditional: dict = field(default_factory=dict)
    filter_check: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    acceptance_tests: dict = field(default_factory=dict)
    null_mean_squares: Any = None
    main_figure: ClassVar[str] = "mc_ratio"
    drawn_from: ClassVar[tuple[str, ...]] = ("bands", "cases", "confidence", "length_unit", "nees", "runs", "stops",
                                             "times")


@dataclass
class DualImuResult(StudyResult):
    """``dual_imu``: the dual-IMU comparison (seed 001), also ``covtool dualnav`` on logs.

    Attributes
    ----------
    config : object
        The typed study configuration.
    fault_free, fault : list
        Per flight, the comparison run (innovations, window statistics,
        g-sensitivity estimates) without and with the injected fault.
    labels : tuple of str
        Legend names of the two groups of flights.
    estimates : bool
        Whether the g-sensitivity estimate figure applies.
    bridged : object
        ``covtool dualnav`` only: the logs with their gaps bridged
        (:class:`covtool.dualnav.gaps.BridgedLog` pair).
    """

    config: Any = None
    fault_free: list = field(default_factory=list)
    fault: list = field(default_factory=list)
    labels: tuple = ("fault-free", "g-sensitivity injected")
    estimates: bool = True
    bridged: Any = None
    main_figure: ClassVar[str] = "difference_envelope"
    drawn_from: ClassVar[tuple[str, ...]] = ("config", "fault_free", "fault", "labels", "estimates")

    def figure_view(self) -> "DualImuResult":
        """:meth:`StudyResult.figure_view` whose runs hold only what the figures draw.

        Each run becomes a namespace of its epochs, differences, predicted
        envelope, window statistics and g-sensitivity estimates (arrays), and
        the configuration one of the name, fault, false-alarm rate and window
        the figures print, so that the view unpickles without the dual-IMU
        kernels and the typed configuration (0.3 s in the figure server).
        """
        from types import SimpleNamespace

        def drawn(r):
            return SimpleNamespace(t=r.t, z=r.z, envelope=r.envelope, window_stat=r.window_stat,
                                   window_threshold=r.window_threshold,
                                   model=SimpleNamespace(components=tuple(r.model.components)),
                                   gsens=SimpleNamespace(candidates=r.gsens.candidates, estimate=r.gsens.estimate))

        view = super().figure_view()
        cfg = self.config
        view.config = SimpleNamespace(name=cfg.name, fault=cfg.fault, false_alarm=cfg.false_alarm, window=cfg.window)
        view.fault_free = [drawn(r) for r in self.fault_free]
        view.fault = [drawn(r) for r in self.fault]
        return view


@dataclass
class TradeGridResult(StudyResult):
    """``trade_grid``: the filter trade over a grid of settings.

    Attributes
    ----------
    nominal : DataFrame
        Summary rows at nominal tuning (P0, Q, R scales 1).
    grades : list of dict
        IMU grades (``name``, ``scale``).
    filters : list of str
    duration : float
        [s]
    length_unit : {"ft", "m"}
        Unit of the pivot tables' lengths and the figure (``[output] units``).
    """

    nominal: pd.DataFrame | None = None
    grades: list = field(default_factory=list)
    filters: list = field(default_factory=list)
    duration: float = 0.0
    length_unit: str = "ft"
    drawn_from: ClassVar[tuple[str, ...]] = ("duration", "filters", "grades", "length_unit", "nominal")


#: study kind -> its result class
RESULT_CLASSES = {"pure_ins": PureInsResult, "zupt_filter_order": ZuptFilterOrderResult,
                  "error_budget": ErrorBudgetResult, "zupt_sensitivity": ZuptSensitivityResult,
                  "magnitude_sweep": MagnitudeSweepResult, "ad_reset": AdResetResult,
                  "monte_carlo": MonteCarloResult, "dual_imu": DualImuResult, "trade_grid": TradeGridResult}
