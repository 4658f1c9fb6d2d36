"""Validated error-state models: named states, initial covariance, processes.

A :class:`Model` is the validated form of a model file.  States carry their
names, symbols and units; every matrix built from a model is indexed by
:attr:`Model.names`.
"""

from __future__ import annotations

import dataclasses
from fractions import Fraction
from dataclasses import dataclass, field

import numpy as np

from covtool.lincov.model.blocks import BLOCK_KINDS
from covtool.nav.strapdown import NAV_STATES
from covtool.nav import attitude as quat
from covtool.units import from_si, si_unit

#: processes a state may follow
PROCESSES = ("constant", "random_walk", "markov", "markov_distance")


@dataclass(frozen=True)
class State:
    """One error state.

    Attributes
    ----------
    name, symbol : str
        Unique name (``acc_bias_x``) and symbol (``B_x``, seed 002 notation).
    block, kind : str
        Block name and block kind (see :data:`covtool.lincov.model.blocks.BLOCK_KINDS`).
    meaning : str
        One-line description.
    dimension : str
        Physical dimension (:data:`covtool.units.DIMENSIONS`).
    unit : str
        Display (datasheet) unit, e.g. ``"ug"``.
    sigma : float
        Initial 1σ. [SI]
    process : str
        ``constant`` (random constant), ``random_walk``, ``markov`` (first-order
        Gauss–Markov in time) or ``markov_distance`` (Gauss–Markov in distance
        travelled).  Navigation states use ``"navigation"``.
    tau : float or None
        Markov correlation time. [s]
    distance : float or None
        Markov correlation distance. [m]
    rw : float
        Random-walk intensity (root-PSD of the driving white noise). [SI/√s]
    source : str
        Where the magnitude comes from.
    """

    name: str
    symbol: str
    block: str
    kind: str
    meaning: str
    dimension: str
    unit: str
    sigma: float
    process: str
    tau: float | None = None
    distance: float | None = None
    rw: float = 0.0
    source: str = ""

    def psd(self, speed=None):
        """Driving-noise PSD of this state's own process [SI²/s].

        Markov: ``2σ²/τ``; Markov in distance: ``2σ²|v|/d`` (needs ``speed``);
        random walk: ``rw²``; random constant: 0.
        """
        if self.process == "markov":
            return 2.0 * self.sigma**2 / self.tau
        if self.process == "markov_distance":
            return 2.0 * self.sigma**2 * np.asarray(speed) / self.distance
        if self.process == "random_walk":
            return self.rw**2
        return 0.0


@dataclass(frozen=True)
class Model:
    """A validated error-state model (truth model or the base of a filter).

    Attributes
    ----------
    name : str
    description : str
    path : str
        File the model was read from (``"<dict>"`` if built from a dict).
    states : tuple of State
    correlations : tuple of (str, str, float)
        Initial correlation coefficients between named states.
    arw : float
        Gyro angle random walk, root-PSD of the white rate noise. [rad/√s]
    vrw : float
        Accelerometer velocity random walk, root-PSD. [m/s/√s]
    decl : dict
        The declaration as written (datasheet units); dumping it reproduces the model.
    sha256 : str
        Hash of the declaration, for provenance.
    """

    name: str
    description: str
    path: str
    states: tuple
    correlations: tuple = ()
    arw: float = 0.0
    vrw: float = 0.0
    decl: dict = field(default_factory=dict, compare=False)
    sha256: str = ""

    # ---- names -------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of states."""
        return len(self.states)

    @property
    def names(self) -> list[str]:
        """State names in order."""
        return [s.name for s in self.states]

    @property
    def index(self) -> dict[str, int]:
        """Map from state name to index."""
        return {s.name: i for i, s in enumerate(self.states)}

    def idx(self, names) -> np.ndarray:
        """Indices of the named states (KeyError names the missing one)."""
        ix = self.index
        out = []
        for nm in names:
            if nm not in ix:
                raise KeyError(f"model {self.name!r} has no state {nm!r}")
            out.append(ix[nm])
        return np.array(out, dtype=int)

    def block_names(self) -> list[str]:
        """Block names in order of first appearance."""
        seen = []
        for s in self.states:
            if s.block not in seen:
                seen.append(s.block)
        return seen

    def states_of(self, selector) -> list[str]:
        """Expand block names and state names into state names (order kept)."""
        if isinstance(selector, str):
            selector = [selector]
        out = []
        blocks = set(self.block_names())
        names = set(self.names)
        for sel in selector:
            if sel in names:
                out.append(sel)
            elif sel in blocks:
                out.extend(s.name for s in self.states if s.block == sel)
            else:
                raise KeyError(sel)
        return out

    # ---- covariance --------------------------------------------------------
    def initial_covariance(self, q0=None) -> np.ndarray:
        """Initial covariance P0, shape ``(n, n)``. [SI]

        Parameters
        ----------
        q0 : array_like, shape (4,), optional
            Initial attitude quaternion.  The quaternion-error σ of the model
            file are declared for the body aligned with NED (as in seed 002,
            Table 2: δq0 = 0); for another attitude the error quaternion
            ``δq_ref`` is carried to ``δq = δq_ref ⊗ q0``, which keeps the
            physical tilt and azimuth errors unchanged.
        """
        sig = np.array([s.sigma for s in self.states])
        with np.errstate(over="ignore"):    # a σ whose square overflows gives inf, which the guard refuses by name
            P = np.diag(sig**2)
        ix = self.index
        for a, b, rho in self.correlations:
            i, j = ix[a], ix[b]
            P[i, j] = P[j, i] = rho * sig[i] * sig[j]
        if q0 is not None and "dq0" in ix:
            qi = self.idx(["dq0", "dq1", "dq2", "dq3"])
            T = quat.mul(np.eye(4), np.asarray(q0, float)).T  # columns: e_k ⊗ q0
            T = np.asarray(T)
            P[np.ix_(qi, range(self.n))] = T @ P[qi, :]
            P[np.ix_(range(self.n), qi)] = P[:, qi] @ T.T
        return P

    # ---- transformations ---------------------------------------------------
    def replace_states(self, states, **changes) -> "Model":
        """Copy with a new state tuple (and other fields changed)."""
        names = {s.name for s in states}
        corr = tuple(c for c in self.correlations if c[0] in names and c[1] in names)
        return dataclasses.replace(self, states=tuple(states), correlations=corr, **changes)

    def only(self, sources) -> "Model":
        """Keep only the listed error sources; every other source is zeroed.

        Parameters
        ----------
        sources : list of str
            State names, block names, ``"arw"`` and ``"vrw"``.  A navigation
            state listed keeps its initial σ; all other initial σ and driving
            noises are set to zero.  States stay in the model (they are still
            propagated), so dimensions never change.
        """
        sources = list(sources)
        keep_noise = {"arw", "vrw"} & set(sources)
        keep = set(self.states_of([s for s in sources if s not in ("arw", "vrw")]))
        states = []
        for s in self.states:
            if s.name in keep:
                states.append(s)
            else:
                states.append(dataclasses.replace(s, sigma=0.0, rw=0.0))
        return self.replace_states(states, arw=self.arw if "arw" in keep_noise else 0.0,
                                   vrw=self.vrw if "vrw" in keep_noise else 0.0)

    # ---- tables ------------------------------------------------------------
    def state_table(self) -> pd.DataFrame:
        """One row per state: name, symbol, meaning, unit, σ, process, τ, source."""
        rows = []
        for s in self.states:
            rows.append({
                "state": s.name,
                "symbol": s.symbol,
                "block": s.block,
                "meaning": s.meaning,
                "unit": s.unit,
                "sigma": float(from_si(s.sigma, s.unit)) if s.unit else s.sigma,
                "sigma, SI value": s.sigma,
                "SI unit": si_unit(s.unit),
                "process": s.process,
                "tau [s]": s.tau if s.tau is not None else np.nan,
                "corr. distance [m]": s.distance if s.distance is not None else np.nan,
                "random walk, SI value": s.rw,
                "random walk SI unit": si_unit(s.unit, seconds=Fraction(-1, 2)),
                "source": s.source,
            })
        import pandas as pd          # here: reading a model (covtool show) needs no pandas

        return pd.DataFrame(rows)


def nav_slice(model: Model) -> np.ndarray:
    """Indices of the 10 navigation states of seed 002, eq (14)."""
    return model.idx(NAV_STATES)


__all__ = ["State", "Model", "PROCESSES", "BLOCK_KINDS", "nav_slice"]
