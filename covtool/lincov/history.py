"""Labelled covariance histories: times, state names, P, update times.

A :class:`CovarianceHistory` is what a covariance run leaves behind for a
reader: the covariance of the stored states at the stored times, with the
states' names and the measurement-update times, so that a σ is asked for by
name (``h.sigma("dh")``), never by a raw index.  Runs may store only the
navigation block (seed 002, eq (14)) at the history spacing; the class
holds exactly what it is given.

Named slices of the navigation block:

* :data:`NAV_STATES` -- the 10 error states of seed 002, eq (14):
  δL, δl, δh, δV_N, δV_E, δV_D, δq0..δq3;
* :data:`POSITION`, :data:`VELOCITY`, :data:`QUATERNION` -- its parts;
* :data:`PHYSICAL_NAV` -- the physical 9-vector (north, east, down
  position, velocity, north/east tilt, azimuth) of
  :func:`covtool.lincov.dynamics.physical_nav`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from covtool.nav.strapdown import NAV_STATES

#: position errors δL, δl, δh (seed 002, eq (14))
POSITION = NAV_STATES[0:3]
#: velocity errors δV_N, δV_E, δV_D
VELOCITY = NAV_STATES[3:6]
#: attitude errors as quaternion errors δq0..δq3
QUATERNION = NAV_STATES[6:10]
#: the physical navigation 9-vector of :func:`covtool.lincov.dynamics.physical_nav`
PHYSICAL_NAV = ("north", "east", "down", "vN", "vE", "vD", "tilt_n", "tilt_e", "azimuth")

__all__ = ["CovarianceHistory", "NAV_STATES", "POSITION", "VELOCITY", "QUATERNION", "PHYSICAL_NAV"]


@dataclass(frozen=True, eq=False)
class CovarianceHistory:
    """Covariance of named states at given times.

    Attributes
    ----------
    times : ndarray, shape (K,)
        Times of the stored covariances, increasing. [s]
    names : tuple of str, length n
        State names, in the order of ``P``'s rows.
    P : ndarray, shape (K, n, n)
        Covariance at each time (posterior at an update time), SI.
    update_times : ndarray, shape (U,)
        Times of the measurement updates (may fall between stored times). [s]
    prior : ndarray, shape (U, n, n) or None
        Covariance just before each update, when the run kept it.
    label : str
        What the history is (``"filter B1: truth"``), for legends and messages.

    Raises
    ------
    ValueError
        Shapes that do not agree, duplicate names, times not increasing.
    """

    times: np.ndarray
    names: tuple
    P: np.ndarray
    update_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior: np.ndarray | None = None
    label: str = ""

    def __post_init__(self):
        t = np.asarray(self.times, float).reshape(-1)
        P = np.asarray(self.P, float)
        names = tuple(str(n) for n in self.names)
        u = np.asarray(self.update_times, float).reshape(-1)
        what = self.label or "covariance history"
        if P.ndim != 3 or P.shape[0] != t.size or P.shape[1] != P.shape[2] or P.shape[1] != len(names):
            raise ValueError(f"{what}: P has shape {P.shape}; expected ({t.size}, {len(names)}, {len(names)}) "
                             "for its times and state names")
        if len(set(names)) != len(names):
            raise ValueError(f"{what}: duplicate state names")
        if t.size > 1 and not np.all(np.diff(t) > 0):
            raise ValueError(f"{what}: times are not increasing")
        if self.prior is not None and np.shape(self.prior) != (u.size,) + P.shape[1:]:
            raise ValueError(f"{what}: prior has shape {np.shape(self.prior)}; expected "
                             f"({u.size}, {len(names)}, {len(names)}), one per update time")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "update_times", u)

    # ---- access by name --------------------------------------------------
    @property
    def n(self) -> int:
        """Number of stored states."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Row of state ``name`` in ``P``.

        Raises
        ------
        KeyError
            ``name`` is not a stored state (the message lists them).
        """
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"{self.label or 'history'}: no state {name!r} (stored: {', '.join(self.names)})") \
                from None

    def variance(self, name: str) -> np.ndarray:
        """Variance of state ``name`` over time, shape (K,), SI²."""
        i = self.index(name)
        return self.P[:, i, i].copy()

    def sigma(self, name: str) -> np.ndarray:
        """1σ of state ``name`` over time, shape (K,), SI.

        A negative variance (which the kernel's guard refuses upstream)
        gives NaN, never a σ.
        """
        v = self.variance(name)
        with np.errstate(invalid="ignore"):
            return np.where(v >= 0, np.sqrt(np.abs(v)), np.nan)

    def select(self, names) -> "CovarianceHistory":
        """The sub-history of the states ``names`` (in that order)."""
        idx = [self.index(n) for n in names]
        ix = np.ix_(idx, idx)
        prior = None if self.prior is None else self.prior[(slice(None),) + ix]
        return CovarianceHistory(self.times, tuple(names), self.P[(slice(None),) + ix], self.update_times,
                                 prior, self.label)

    def nav(self) -> "CovarianceHistory":
        """The 10-state navigation block of seed 002, eq (14)."""
        return self.select(NAV_STATES)

    def at(self, t: float) -> np.ndarray:
        """Covariance at the stored time nearest ``t``, shape (n, n)."""
        return self.P[int(np.argmin(np.abs(self.times - t)))]

    # ---- export ------------------------------------------------------------
    def to_pandas(self, names=None) -> pd.DataFrame:
        """1σ of each state over time.

        Parameters
        ----------
        names : sequence of str, optional
            States to include (default: all).

        Returns
        -------
        DataFrame
            Index ``t [s]``; one column per state, its 1σ in SI.
        """
        names = self.names if names is None else tuple(names)
        df = pd.DataFrame({n: self.sigma(n) for n in names}, index=pd.Index(self.times, name="t [s]"))
        df.columns.name = "1sigma (SI)"
        return df

    def plot(self, names=None, *, ax=None, scale: dict | None = None, log: bool = True):
        """Draw the 1σ of ``names`` against time in minutes.

        Parameters
        ----------
        names : sequence of str, optional
            States to draw (default: the first three).
        ax : matplotlib Axes, optional
        scale : dict of str to (float, str), optional
            Per state ``(SI per display unit, unit text)``, e.g.
            ``{"dh": (0.3048, "ft")}``; default SI.
        log : bool
            Logarithmic y axis.

        Returns
        -------
        matplotlib.figure.Figure
        """
        import matplotlib.pyplot as plt

        names = self.names[:3] if names is None else tuple(names)
        if ax is None:
            fig, ax = plt.subplots(figsize=(8, 4.5))
        else:
            fig = ax.figure
        tm = self.times / 60.0
        for n in names:
            f, unit = (scale or {}).get(n, (1.0, "SI"))
            ax.plot(tm, self.sigma(n) / f, label=f"{n} [{unit}]")
        for tu in self.update_times:
            ax.axvline(tu / 60.0, color="0.6", lw=0.5, alpha=0.5)
        if log:
            ax.set_yscale("log")
        ax.set_xlabel("time [min]")
        ax.set_ylabel("1σ")
        ax.set_title(self.label or "covariance history")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        return fig


class AtSteps:
    """Covariances kept at some grid steps only, read as ``obj[k]`` by grid index ``k``.

    What a recorded run keeps (:func:`covtool.lincov.reference.propagate`,
    :func:`~covtool.lincov.reference.propagate_with_filter` with ``record``):
    the consumers that read a history at its steps only
    (:func:`covtool.analysis.consistency.nees_whitening`, ``expected_nees``)
    take it in place of the ``(N+1, n, n)`` history.

    Parameters
    ----------
    steps : array_like of int, shape (J,)
        Grid indices, increasing.
    P : ndarray, shape (J, n, n)
        The covariance at each.

    Raises
    ------
    ValueError
        Steps not increasing, or not one per covariance.
    KeyError
        On reading a step that was not kept.
    """

    def __init__(self, steps, P):
        self.steps = np.asarray(steps, int)
        self.P = np.asarray(P)
        if self.P.shape[0] != self.steps.size:
            raise ValueError(f"{self.steps.size} steps for {self.P.shape[0]} covariances")
        if np.any(np.diff(self.steps) <= 0):
            raise ValueError("the steps of the kept covariances must increase")
        self._slot = {int(k): i for i, k in enumerate(self.steps)}

    def __getitem__(self, k):
        try:
            return self.P[self._slot[int(k)]]
        except KeyError:
            raise KeyError(f"grid step {int(k)} was not kept (kept: {self.steps.size} steps)") from None

