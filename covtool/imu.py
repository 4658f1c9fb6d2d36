"""IMU simulator and IMU grade presets (the input side of the nonlinear reference).

Three layers, data flowing one way:

* **Grades** (``models/imu/*.toml``, :func:`load_imu_grade`): spec-sheet
  values in datasheet units (seed 001, Table 2; seed 002 magnitudes).
  :meth:`ImuGrade.to_model` turns a grade into a covtool error-state
  :class:`~covtool.model.spec.Model`, so the linear analysis and the
  simulator share one declaration.
* **Sensor errors** (:class:`SensorErrors`): one realisation per run of the
  error states of a model, ``x`` of shape ``(M, n_states)`` (e.g. drawn by
  :func:`sample_states` from the model's P0), propagated with the model's
  own processes and injected with the sensitivities of
  :mod:`covtool.model.blocks` — the very functions that define the linear
  model's sensor error equations (seed 002, eq (3) and (5)).
* **Simulator** (:class:`ImuSimulator`): exact increments of a trajectory
  (:func:`ideal_increments`), optionally with mounting rotation and
  vibration (a real motion, so coning and sculling are physical), plus the
  sensor errors and the extras that lie outside the linear model
  (quantisation, range saturation).  It streams :class:`ImuRecord` chunks of
  shape ``(M, k, 3)`` that :func:`covtool.strapdown.run` consumes.

Increments
----------
An integrating gyro outputs ``Δθ_k = ∫_{t_k}^{t_{k+1}} ω_ib^b dt`` and an
integrating accelerometer ``Δv_k = ∫ f^b dt``, both in the *instantaneous*
body frame; turning them into a rotation vector and a velocity increment in
the start-of-interval frame is the strapdown algorithm's job (coning and
sculling, seed 001 eq (1)–(4)).  The increments are therefore the
integrals of the trajectory's exact ω_ib^b(t) and f^b(t)
(:meth:`covtool.trajectory.Trajectory.sample`), by Gauss–Legendre
quadrature with enough nodes per sample for the highest frequency present.

Sensor-error increments
-----------------------
With ``ω̄ = Δθ/h`` and ``f̄ = Δv/h`` the sample means and ``x̄`` the mean
error state over the sample::

    δΔθ = h S_g(f̄, ω̄) x̄ + ARW noise,   δΔv = h S_a(f̄, ω̄) x̄ + VRW noise

with ``S`` the block sensitivities (exact for the terms linear in ``f`` and
``ω``: biases, scale factors, misalignments, g-sensitivity).  The
gravity-disturbance block enters as the specific-force error
``C_n^b diag(g, g, −1) x`` the accelerometers would sense, and the AD-reset
block (seed 000) as the velocity increment ``Δe`` of its state.  White
noises: ``N(0, arw² h)`` and ``N(0, vrw² h)`` per sample and axis
(root-PSDs of :attr:`Model.arw`, :attr:`Model.vrw`).
"""

from __future__ import annotations

import copy
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from . import quaternion as quat
from .errors import ModelFileError
from .io.config import LIMITS, as_list, check_keys, is_library_name, load_toml, quantity, resolve_input, string
from .io.config import table as as_table
from .io.names import check_name
from .model.blocks import BLOCK_KINDS, gravity_sensitivity
from .model.loader import model_from_dict
from .model.spec import Model

__all__ = [
    "ImuRecord", "ideal_increments", "ImuGrade", "load_imu_grade", "imu_grade_from_dict", "dump_imu_grade",
    "list_imu_grades", "imu_grade_dir", "sample_states", "SensorErrors", "Tone", "RandomVibration",
    "Vibration", "VibrationRealization", "ImuSimulator", "GYRO_KEYS", "ACCEL_KEYS",
]


# --------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuRecord:
    """IMU increments on a uniform sample grid.

    Attributes
    ----------
    t0 : float
        Start of the first sample period. [s]
    dt : float
        Sample period h. [s]
    dtheta : ndarray, shape (K, 3) or (M, K, 3)
        Angle increments of the sample periods ``[t0 + k h, t0 + (k+1) h]``.
        [rad]
    dv : ndarray, same shape
        Velocity increments. [m/s]
    """

    t0: float
    dt: float
    dtheta: np.ndarray
    dv: np.ndarray

    @property
    def n_samples(self) -> int:
        """Number of samples K."""
        return self.dtheta.shape[-2]

    @property
    def t(self) -> np.ndarray:
        """End time of every sample period, shape (K,). [s]"""
        return self.t0 + self.dt * np.arange(1, self.n_samples + 1)

    @property
    def rate(self) -> float:
        """Sample rate. [Hz]"""
        return 1.0 / self.dt

    def slice(self, a: int, b: int) -> "ImuRecord":
        """Samples ``a … b−1`` as a record."""
        return ImuRecord(self.t0 + a * self.dt, self.dt, self.dtheta[..., a:b, :], self.dv[..., a:b, :])


def _gl_nodes(nodes: int):
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (1.0 + x), 0.5 * w


def _auto_nodes(max_freq: float, h: float, minimum: int = 3) -> int:
    """Gauss–Legendre nodes integrating ``max_freq`` to ~1e-13."""
    lam = 2.0 * math.pi * max_freq * h
    n = minimum
    while n < 24 and (0.5 * lam) ** (2 * n) / math.factorial(2 * n) > 1e-13:
        n += 1
    return n


def _span(traj, rate, t0, duration):
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"IMU rate must be positive, got {rate!r} Hz")
    h = 1.0 / float(rate)
    t0 = float(traj.t[0]) if t0 is None else float(t0)
    end = float(traj.t[-1]) if duration is None else t0 + float(duration)
    K = int(math.floor((end - t0) / h + 1e-9))
    if K < 1:
        raise ValueError(f"the span [{t0:g}, {end:g}] s holds no whole sample at {rate:g} Hz")
    if end > float(traj.t[-1]) + 1e-9 * max(1.0, end) or t0 < float(traj.t[0]) - 1e-9:
        raise ValueError(f"the span [{t0:g}, {end:g}] s exceeds the trajectory "
                         f"[{traj.t[0]:g}, {traj.t[-1]:g}] s")
    return t0, h, K


def ideal_increments(traj, rate: float, *, t0: float | None = None, duration: float | None = None,
                     nodes: int = 3, mounting=None, chunk: int = 20000) -> ImuRecord:
    """Error-free increments of a trajectory.

    Parameters
    ----------
    traj : covtool.trajectory.Trajectory
        True motion; :meth:`~covtool.trajectory.Trajectory.sample` is exact
        for declared profiles.
    rate : float
        Sample rate. [Hz]
    t0 : float, optional
        Start (default: trajectory start). [s]
    duration : float, optional
        Length (default: to the trajectory end, whole samples). [s]
    nodes : int
        Gauss–Legendre nodes per sample.
    mounting : array_like, shape (4,), optional
        Quaternion ``q_bs`` of the IMU frame in the body frame: the output
        is ``C_b^s Δθ^b``, ``C_b^s Δv^b``.
    chunk : int
        Samples evaluated at once (bounds memory).

    Returns
    -------
    ImuRecord
        ``dtheta``, ``dv`` of shape (K, 3).
    """
    t0, h, K = _span(traj, rate, t0, duration)
    u, w = _gl_nodes(nodes)
    dth = np.empty((K, 3))
    dv = np.empty((K, 3))
    R = None if mounting is None else quat.dcm(np.asarray(mounting, float))
    for a in range(0, K, chunk):
        b = min(K, a + chunk)
        ts = t0 + (np.arange(a, b)[:, None] + u[None, :]) * h
        s = traj.sample(ts.ravel())
        wb = s.w_ib_b.reshape(b - a, nodes, 3)
        fb = s.f_b.reshape(b - a, nodes, 3)
        dth[a:b] = h * np.einsum("j,kjc->kc", w, wb)
        dv[a:b] = h * np.einsum("j,kjc->kc", w, fb)
    if R is not None:
        dth = dth @ R
        dv = dv @ R
    return ImuRecord(t0, h, dth, dv)


# --------------------------------------------------------------------------
# grades
# --------------------------------------------------------------------------

#: gyro keys of a grade file: (dimension, number of values)
GYRO_KEYS = {
    "bias": ("angular_rate", 3),
    "bias_instability": ("angular_rate", 3),
    "bias_instability_tau": ("time", 3),
    "scale_factor": ("dimensionless", 3),
    "misalignment": ("angle", 6),
    "g_sensitivity": ("g_sensitivity", 6),
    "anisoelastic": ("g2_sensitivity", 3),
    "angle_random_walk": ("angle_random_walk", 1),
    "quantization": ("angle", 1),
    "range": ("angular_rate", 1),
}
#: accelerometer keys of a grade file: (dimension, number of values)
ACCEL_KEYS = {
    "bias": ("acceleration", 3),
    "bias_instability": ("acceleration", 3),
    "bias_instability_tau": ("time", 3),
    "scale_factor": ("dimensionless", 3),
    "asymmetric_scale_factor": ("dimensionless", 3),
    "misalignment": ("angle", 6),
    "velocity_random_walk": ("velocity_random_walk", 1),
    "quantization": ("velocity", 1),
    "range": ("acceleration", 1),
}
# grade key -> model block kind (the Markov key handled with its tau)
_GYRO_BLOCKS = {"bias": "gyro_bias", "bias_instability": "gyro_markov_drift",
                "scale_factor": "gyro_scale_factor", "misalignment": "gyro_misalignment",
                "g_sensitivity": "gyro_g_sensitivity", "anisoelastic": "gyro_anisoelastic"}
_ACCEL_BLOCKS = {"bias": "accel_bias", "bias_instability": "accel_markov_bias",
                 "scale_factor": "accel_scale_factor", "asymmetric_scale_factor": "accel_asymmetric_scale_factor",
                 "misalignment": "accel_misalignment"}
_POSITIVE = {"bias_instability_tau", "quantization", "range"}
_TOP_KEYS = {"imu", "gyro", "accel"}
_IMU_KEYS = {"name", "description", "rate", "source"}


@dataclass(frozen=True)
class ImuGrade:
    """IMU error specification (one grade), SI values.

    Attributes
    ----------
    name, description : str
    path : str
        File it was read from (``"<dict>"`` otherwise).
    rate : float or None
        Nominal output rate. [Hz]
    gyro, accel : dict
        Parameter name → tuple of SI values (3 per axis, 6 for
        misalignment and g-sensitivity, 1 for random walk, quantisation and
        range); see :data:`GYRO_KEYS`, :data:`ACCEL_KEYS`.  Absent keys are
        effects switched off.
    sources : dict
        ``"gyro.bias"`` → where the value comes from.
    decl : dict
        The declaration as written (datasheet units).
    """

    name: str
    description: str
    path: str
    rate: float | None
    gyro: dict
    accel: dict
    sources: dict = field(default_factory=dict)
    decl: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def quantization(self) -> tuple:
        """``(angle LSB [rad], velocity LSB [m/s])``, None where not given."""
        g = self.gyro.get("quantization")
        a = self.accel.get("quantization")
        return (None if g is None else g[0], None if a is None else a[0])

    @property
    def range(self) -> tuple:
        """``(rate range [rad/s], specific-force range [m/s²])``, None where not given."""
        g = self.gyro.get("range")
        a = self.accel.get("range")
        return (None if g is None else g[0], None if a is None else a[0])

    def to_model(self, name: str | None = None) -> Model:
        """The grade as a covtool error-state model.

        Parameters
        ----------
        name : str, optional
            Model name (default ``imu_<grade name>``).

        Returns
        -------
        Model
            A navigation block with zero initial σ (alignment is the
            caller's), the grade's ARW and VRW, and one block per given
            sensor parameter: turn-on biases, scale factors, misalignments,
            g-sensitivity and anisoelasticity as random constants, in-run
            bias instability as first-order Markov processes (σ = the
            instability, τ = ``bias_instability_tau``).
        """
        d = self.decl
        nav = {"kind": "navigation", "source": f"IMU grade {self.name!r} ({self.path})"}
        if "angle_random_walk" in d.get("gyro", {}):
            nav["angle_random_walk"] = d["gyro"]["angle_random_walk"]
        if "velocity_random_walk" in d.get("accel", {}):
            nav["velocity_random_walk"] = d["accel"]["velocity_random_walk"]
        blocks = [nav]
        for sensor, table in (("gyro", _GYRO_BLOCKS), ("accel", _ACCEL_BLOCKS)):
            sd = d.get(sensor, {})
            src = sd.get("source", {})
            for key, kind in table.items():
                if key not in sd:
                    continue
                b = {"kind": kind, "sigma": copy.deepcopy(sd[key]),
                     "source": src.get(key, f"IMU grade {self.name!r}: {sensor}.{key}")}
                if key == "bias_instability":
                    b["process"] = "markov"
                    b["tau"] = copy.deepcopy(sd["bias_instability_tau"])
                blocks.append(b)
        decl = {"model": {"name": name or f"imu_{self.name}",
                          "description": f"sensor errors of IMU grade {self.name!r}: {self.description}"},
                "block": blocks}
        return model_from_dict(decl, path=self.path)


def imu_grade_dir(directory=None) -> Path:
    """The grade library, ``<models>/imu``.

    ``<models>`` is :func:`covtool.model.library.default_model_dir`.
    """
    if directory is not None:
        return Path(directory)
    from .model.library import default_model_dir

    return default_model_dir() / "imu"


def list_imu_grades(directory=None) -> list[str]:
    """Names of the grade files in the library."""
    return sorted(p.stem for p in imu_grade_dir(directory).glob("*.toml"))


def imu_grade_from_dict(decl: dict, *, path: str = "<dict>") -> ImuGrade:
    """Validate a grade declaration.

    Parameters
    ----------
    decl : dict
        ``[imu]`` (``name``, ``description``, ``rate``, ``source``),
        ``[gyro]`` and ``[accel]`` tables of :data:`GYRO_KEYS` /
        :data:`ACCEL_KEYS` in datasheet units (one value = all axes), each
        with an optional ``[gyro.source]``/``[accel.source]`` table naming
        the origin of every value.
    path : str
        File name used in messages.

    Returns
    -------
    ImuGrade

    Raises
    ------
    ModelFileError
        Naming the file, the field and the problem: unknown table or key,
        missing name, wrong unit or count, negative value, non-positive
        τ/quantisation/range/rate, instability without τ (or τ without
        instability), a source for an undeclared key.
    """
    file = str(path)
    check_keys(decl, _TOP_KEYS, file, ModelFileError)
    meta = decl.get("imu")
    if not isinstance(meta, dict):
        raise ModelFileError(file, "missing the [imu] table")
    check_keys(meta, _IMU_KEYS, f"{file}: [imu]", ModelFileError)
    name = meta.get("name")
    if not isinstance(name, str) or not name:
        raise ModelFileError(f"{file}: [imu] name", "missing or not a non-empty string")
    check_name(name, f"{file}: [imu] name", ModelFileError, what="IMU grade name")
    for key in ("description", "source"):
        if key in meta:
            string(meta[key], f"{file}: [imu] {key}", ModelFileError)
    rate = None
    if "rate" in meta:
        lim = LIMITS["imu_rate"]
        rate = quantity(meta["rate"], "frequency", f"{file}: [imu] rate", ModelFileError, positive=True,
                        hi=lim.hi, why=lim.reason)
    sources = {}
    parsed = {}
    for sensor, keys in (("gyro", GYRO_KEYS), ("accel", ACCEL_KEYS)):
        where = f"{file}: [{sensor}]"
        table = as_table(decl.get(sensor, {}), where, ModelFileError)
        check_keys(table, set(keys) | {"source"}, where, ModelFileError)
        out = {}
        for key, (dim, count) in keys.items():
            if key not in table:
                continue
            w = f"{file}: {sensor}.{key}"
            if count == 1:
                if isinstance(table[key], (list, tuple)):
                    raise ModelFileError(w, "expected one value, got a list")
                vals = [table[key]]
            else:
                vals = as_list(table[key], count, w, ModelFileError)
            si = tuple(quantity(v, dim, w, ModelFileError, nonnegative=True, positive=key in _POSITIVE)
                       for v in vals)
            out[key] = si
        if ("bias_instability" in out) != ("bias_instability_tau" in out):
            raise ModelFileError(f"{file}: [{sensor}]", "give 'bias_instability' together with "
                                 "'bias_instability_tau' (its correlation time)")
        src = table.get("source", {})
        check_keys(src, set(out), f"{file}: [{sensor}.source]", ModelFileError)
        for key, text in src.items():
            if not isinstance(text, str):
                raise ModelFileError(f"{file}: {sensor}.source.{key}", f"{text!r} is not a string")
            sources[f"{sensor}.{key}"] = text
        parsed[sensor] = out
    return ImuGrade(name, str(meta.get("description", "")), file, rate, parsed["gyro"], parsed["accel"],
                    sources, copy.deepcopy(decl))


def load_imu_grade(name_or_path, directory=None, *, base_dir=None) -> ImuGrade:
    """Load a grade by library name (``"kimu"``) or by path.

    A bare name (no suffix, no separator) is looked up in the grade library
    (:func:`imu_grade_dir`); anything else is a path, relative to
    ``base_dir`` (the directory of the file that names it; the current
    directory when none does).

    Raises
    ------
    ModelFileError
        No such grade (naming where it looked), or an invalid file.
    """
    if isinstance(name_or_path, Path):
        name_or_path = str(name_or_path)
    if isinstance(name_or_path, str) and is_library_name(name_or_path):
        path = imu_grade_dir(directory) / f"{name_or_path}.toml"
        if not path.is_file():
            known = ", ".join(list_imu_grades(directory)) or "none"
            raise ModelFileError(str(name_or_path), f"no such IMU grade (looked in {path.parent}; "
                                 f"known: {known})")
        path = Path(os.path.abspath(path))
    else:
        path = resolve_input(name_or_path, base_dir, str(name_or_path), ModelFileError, what="IMU grade file")
    return imu_grade_from_dict(load_toml(path, ModelFileError), path=str(path))


def dump_imu_grade(grade: ImuGrade) -> str:
    """The grade's declaration as TOML (datasheet units kept)."""
    return tomli_w.dumps(grade.decl)


# --------------------------------------------------------------------------
# error states
# --------------------------------------------------------------------------


def sample_states(model: Model, n_runs: int, rng=None, *, q0=None) -> np.ndarray:
    """Draw initial error-state vectors from a model's P0.

    Parameters
    ----------
    model : Model
    n_runs : int
        Number of runs M.
    rng : numpy.random.Generator or int, optional
    q0 : array_like, shape (4,), optional
        Initial attitude (see :meth:`Model.initial_covariance`).

    Returns
    -------
    ndarray, shape (M, n_states)
        Zero-mean Gaussian samples with covariance P0 (P0 may be singular).
    """
    rng = np.random.default_rng(rng)
    P = model.initial_covariance(q0)
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    return rng.standard_normal((int(n_runs), model.n)) @ L.T


@dataclass
class _Group:
    """A block of sensor states and its sensitivity."""

    kind: str
    sensor: str
    cols: np.ndarray          # indices into the model state vector
    sensitivity: object


class SensorErrors:
    """One realisation per run of a model's sensor-error states.

    Parameters
    ----------
    model : Model
        Error-state model (a truth model, or :meth:`ImuGrade.to_model`).
    x0 : ndarray, shape (M, n_states)
        Initial error states (only the sensor and environment states are
        used here; the first ten, the navigation errors, belong to the
        initial :class:`~covtool.strapdown.NavState`).
    rng : numpy.random.Generator or int, optional
        Source of the driving and white noises.
    noise : bool
        False: no driving noise, no ARW/VRW — every state then follows its
        deterministic mean (constants stay, Markov states decay), which is
        what ``ẋ = F x`` of the linear model describes.
    process_dt : float
        Step of the exact discretisation of the state processes; the states
        are interpolated linearly between steps. [s]

    Notes
    -----
    Processes (exactly discretised over ``Δ``): random constant;
    random walk ``x += rw √Δ w``; Markov ``x = e^{−Δ/τ} x +
    σ √(1 − e^{−2Δ/τ}) w``; Markov in distance the same with the horizontal
    distance travelled over ``Δ`` in place of ``Δ/τ·d``.  These are the
    processes behind the model's F and Q_c (:func:`covtool.dynamics.error_dynamics`).
    """

    def __init__(self, model: Model, x0, rng=None, *, noise: bool = True, process_dt: float = 0.1):
        x0 = np.atleast_2d(np.asarray(x0, dtype=float))
        if x0.ndim != 2 or x0.shape[1] != model.n:
            raise ValueError(f"x0 must have shape (M, {model.n}) for model {model.name!r}, got {x0.shape}")
        if not process_dt > 0:
            raise ValueError(f"process_dt must be positive, got {process_dt!r}")
        self.model = model
        self.x0 = x0
        self.n_runs = x0.shape[0]
        self.rng = np.random.default_rng(rng)
        self.noise = bool(noise)
        self.process_dt = float(process_dt)
        self.arw = model.arw if noise else 0.0
        self.vrw = model.vrw if noise else 0.0
        self.groups: list[_Group] = []
        for block in model.block_names():
            idx = [i for i, s in enumerate(model.states) if s.block == block]
            kind = model.states[idx[0]].kind
            if kind == "navigation":
                continue
            bk = BLOCK_KINDS[kind]
            self.groups.append(_Group(kind, bk.sensor, np.array(idx), bk.sensitivity))
        sensor_cols = [i for g in self.groups for i in g.cols]
        self.dynamic = np.array([i for i in sensor_cols if model.states[i].process != "constant"], dtype=int)
        self.needs_speed = any(model.states[i].process == "markov_distance" for i in self.dynamic)
        self.needs_attitude = any(g.sensor == "gravity" for g in self.groups)
        # process state: values at the last process node
        self._x_dyn = x0[:, self.dynamic].copy()
        self._node_t = None
        self._node_x = None

    @classmethod
    def from_grade(cls, grade: ImuGrade, n_runs: int, rng=None, **kw) -> "SensorErrors":
        """Draw M realisations of a grade's errors (:meth:`ImuGrade.to_model`)."""
        rng = np.random.default_rng(rng)
        model = grade.to_model()
        return cls(model, sample_states(model, n_runs, rng), rng, **kw)

    # ---- processes -------------------------------------------------------
    def _coefficients(self, dt, dist):
        """Transition ``a`` and noise scale ``b`` of every dynamic state.

        ``dist`` (horizontal distance of each step, shape (J,)) may be None
        when no state is Markov in distance.  Returns arrays of shape
        (J, n_dyn).
        """
        J = 1 if dist is None else dist.size
        a = np.ones((J, self.dynamic.size))
        b = np.zeros((J, self.dynamic.size))
        for j, i in enumerate(self.dynamic):
            s = self.model.states[i]
            if s.process == "markov":
                a[:, j] = math.exp(-dt / s.tau)
                b[:, j] = s.sigma * math.sqrt(max(0.0, 1.0 - a[0, j] ** 2))
            elif s.process == "markov_distance":
                a[:, j] = np.exp(-dist / s.distance)
                b[:, j] = s.sigma * np.sqrt(np.clip(1.0 - a[:, j] ** 2, 0.0, None))
            else:  # random walk
                b[:, j] = s.rw * math.sqrt(dt)
        if not self.noise:
            b[:] = 0.0
        return a, b

    def _dynamic_path(self, t_edges, speed_fn):
        """Dynamic states at the sample edges, shape (M, K+1, n_dyn)."""
        nd = self.dynamic.size
        if nd == 0:
            return np.zeros((self.n_runs, t_edges.size, 0))
        if self._node_t is None:
            self._node_t = np.array([float(t_edges[0])])
            self._node_x = self._x_dyn[:, None, :]
        # new process nodes up to the end of the chunk, exactly discretised
        last = self._node_t[-1]
        J = max(0, int(math.ceil((t_edges[-1] - last) / self.process_dt - 1e-9)))
        if J:
            tn = last + self.process_dt * np.arange(1, J + 1)
            dist = None
            if self.needs_speed:
                if speed_fn is None:
                    raise ValueError("Markov-in-distance states need the horizontal speed (speed_fn)")
                dist = np.asarray(speed_fn(tn - 0.5 * self.process_dt), float) * self.process_dt
            a, b = self._coefficients(self.process_dt, dist)
            a = np.broadcast_to(a, (J, nd))
            b = np.broadcast_to(b, (J, nd))
            w = self.rng.standard_normal((J, self.n_runs, nd)) if self.noise else np.zeros((J, 1, nd))
            xs = np.empty((self.n_runs, J, nd))
            x = self._node_x[:, -1, :]
            for j in range(J):
                x = a[j] * x + b[j] * w[j]
                xs[:, j] = x
            self._node_t = np.concatenate([self._node_t, tn])
            self._node_x = np.concatenate([self._node_x, xs], axis=1)
        # keep the nodes from the one at or before the chunk start
        keep = max(0, int(np.searchsorted(self._node_t, t_edges[0] + 1e-12, side="right")) - 1)
        self._node_t = self._node_t[keep:]
        self._node_x = self._node_x[:, keep:]
        nt, nx = self._node_t, self._node_x
        if nt.size == 1:
            return np.repeat(nx, t_edges.size, axis=1)
        j = np.clip(np.searchsorted(nt, t_edges, side="right") - 1, 0, nt.size - 2)
        u = ((t_edges - nt[j]) / (nt[j + 1] - nt[j]))[None, :, None]
        return nx[:, j] + u * (nx[:, j + 1] - nx[:, j])

    # ---- injection ---------------------------------------------------------
    def increment_errors(self, t0, h, dtheta, dv, *, speed_fn=None, attitude=None, gravity=None):
        """Errors of one chunk of samples (advances the processes).

        Parameters
        ----------
        t0 : float
            Start of the chunk. [s]
        h : float
            Sample period. [s]
        dtheta, dv : ndarray, shape (Mv, k, 3)
            True increments (``Mv`` = 1 or M).
        speed_fn : callable, optional
            Horizontal speed at an array of times [m/s] (Markov-in-distance
            states).
        attitude : ndarray, shape (k, 4), optional
            True ``q_ns`` at the sample mid-points (gravity block).
        gravity : ndarray, shape (k,), optional
            Normal gravity at the sample mid-points. [m/s²]

        Returns
        -------
        ddtheta, ddv : ndarray, shape (M, k, 3)
            Errors to add to the increments. [rad], [m/s]
        """
        M = self.n_runs
        k = dtheta.shape[-2]
        t_edges = t0 + h * np.arange(k + 1)
        path = self._dynamic_path(t_edges, speed_fn)                   # (M, k+1, nd)
        xbar_dyn = 0.5 * (path[:, 1:] + path[:, :-1])                  # (M, k, nd)
        dyn_pos = {int(i): j for j, i in enumerate(self.dynamic)}
        Mv = dtheta.shape[0]
        fbar = (dv / h).reshape(Mv * k, 3)
        wbar = (dtheta / h).reshape(Mv * k, 3)
        # collect the sensitivities per sensor, constant and dynamic states apart
        parts = {(t, d): ([], []) for t in ("gyro", "accel") for d in (False, True)}
        for g in self.groups:
            if g.sensor == "ad_reset":
                continue
            if g.sensor == "gravity":
                if attitude is None or gravity is None:
                    raise ValueError("the gravity-disturbance block needs the true attitude and gravity")
                S = np.einsum("kji,kjl->kil", quat.dcm(attitude), gravity_sensitivity(gravity))[None]
                target = "accel"
            else:
                S = g.sensitivity(fbar, wbar).reshape(Mv, k, 3, g.cols.size)
                target = g.sensor
            for j, i in enumerate(g.cols):
                dyn = int(i) in dyn_pos
                Ss, cols = parts[(target, dyn)]
                Ss.append(np.broadcast_to(S[..., j], (Mv, k, 3)))
                cols.append(dyn_pos[int(i)] if dyn else int(i))
        out = {}
        for target in ("gyro", "accel"):
            acc = np.zeros((M, k, 3))
            Ss, cols = parts[(target, False)]
            if cols:
                S = np.stack(Ss, axis=-1)                                  # (Mv, k, 3, nc)
                xc = self.x0[:, cols]                                      # (M, nc)
                if Mv == 1:   # one matrix product for all runs
                    acc += (S[0].reshape(k * 3, -1) @ xc.T).T.reshape(M, k, 3)
                else:
                    acc += np.einsum("mkij,mj->mki", S, xc)
            Ss, cols = parts[(target, True)]
            if cols:
                S = np.stack(Ss, axis=-1)                                  # (Mv, k, 3, nd)
                acc += np.einsum("vkij,mkj->mki", S, xbar_dyn[:, :, cols]) if Mv == 1 else \
                    np.einsum("mkij,mkj->mki", S, xbar_dyn[:, :, cols])
            out[target] = acc
        ddth = out["gyro"] * h
        ddv = out["accel"] * h
        for g in self.groups:
            if g.sensor == "ad_reset":
                # δf^b = ė: the velocity-increment error is the change of e
                cols = [dyn_pos[int(i)] for i in g.cols]
                ddv += path[:, 1:, cols] - path[:, :-1, cols]
        if self.arw > 0:
            ddth += self.arw * math.sqrt(h) * self.rng.standard_normal((M, k, 3))
        if self.vrw > 0:
            ddv += self.vrw * math.sqrt(h) * self.rng.standard_normal((M, k, 3))
        return ddth, ddv


# --------------------------------------------------------------------------
# vibration
# --------------------------------------------------------------------------

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def _axis(axis):
    if isinstance(axis, str):
        if axis not in _AXES:
            raise ValueError(f"axis {axis!r} is not 'x', 'y', 'z' or a 3-vector")
        return np.array(_AXES[axis])
    a = np.asarray(axis, dtype=float)
    if a.shape != (3,) or not np.linalg.norm(a) > 0:
        raise ValueError(f"axis {axis!r} is not 'x', 'y', 'z' or a non-zero 3-vector")
    return a / np.linalg.norm(a)


@dataclass(frozen=True)
class Tone:
    """A sinusoidal vibration of the IMU (sensor frame).

    Attributes
    ----------
    kind : str
        ``"angular"``: rotation ``θ(t) = amplitude sin(2πft + phase)`` about
        ``axis`` [rad]; ``"linear"``: acceleration ``a(t) = amplitude
        sin(2πft + phase)`` along ``axis`` [m/s²].
    axis : str or array_like
        ``"x"``, ``"y"``, ``"z"`` or a vector (normalised).
    amplitude : float
    frequency : float
        [Hz]
    phase : float
        [rad]
    """

    kind: str
    axis: object
    amplitude: float
    frequency: float
    phase: float = 0.0


@dataclass(frozen=True)
class RandomVibration:
    """Band-limited random vibration (a sum of tones per run).

    Attributes
    ----------
    kind : str
        ``"angular"`` (``asd`` of the angular *rate*, [rad/s/√Hz]) or
        ``"linear"`` (``asd`` of the acceleration, [m/s²/√Hz]).
    asd : float
        Flat one-sided amplitude spectral density (√PSD) over the band.
    band : tuple of float
        ``(f1, f2)``. [Hz]
    axes : str
        Axes excited, independently (e.g. ``"xyz"``).
    tones : int
        Tones per axis; frequencies ``f1 + (j + ½)Δf`` with random phases
        (uniform, drawn per run), amplitude ``√(2 PSD Δf)``.
    """

    kind: str
    asd: float
    band: tuple
    axes: str = "xyz"
    tones: int = 64


@dataclass(frozen=True)
class Vibration:
    """Vibration environment: tones and random components."""

    components: tuple = ()

    def realize(self, n_runs: int = 1, rng=None) -> "VibrationRealization":
        """Draw the random phases for M runs.

        Returns
        -------
        VibrationRealization
            Run axis of length 1 when every component is deterministic.
        """
        rng = np.random.default_rng(rng)
        random = any(isinstance(c, RandomVibration) for c in self.components)
        Mv = int(n_runs) if random else 1
        parts = {"angular": ([], [], []), "linear": ([], [], [])}
        for c in self.components:
            if c.kind not in parts:
                raise ValueError(f"vibration kind {c.kind!r} is not 'angular' or 'linear'")
            amps, freqs, phases = parts[c.kind]
            if isinstance(c, Tone):
                if not c.frequency > 0:
                    raise ValueError(f"tone frequency must be positive, got {c.frequency!r}")
                amps.append(np.broadcast_to(c.amplitude * _axis(c.axis), (Mv, 3)))
                freqs.append(float(c.frequency))
                phases.append(np.full(Mv, float(c.phase)))
            else:
                f1, f2 = (float(x) for x in c.band)
                if not 0 < f1 < f2:
                    raise ValueError(f"random vibration band {c.band!r} must satisfy 0 < f1 < f2")
                df = (f2 - f1) / c.tones
                for ax in c.axes:
                    for j in range(c.tones):
                        f = f1 + (j + 0.5) * df
                        a = math.sqrt(2.0 * c.asd**2 * df)
                        if c.kind == "angular":
                            a /= 2.0 * math.pi * f   # rate amplitude -> angle amplitude
                        amps.append(np.broadcast_to(a * _axis(ax), (Mv, 3)))
                        freqs.append(f)
                        phases.append(rng.uniform(0.0, 2.0 * math.pi, Mv))
        def pack(p):
            if not p[1]:
                return np.zeros((Mv, 0, 3)), np.zeros(0), np.zeros((Mv, 0))
            return np.stack(p[0], axis=1), np.array(p[1]), np.stack(p[2], axis=1)
        return VibrationRealization(*pack(parts["angular"]), *pack(parts["linear"]))


@dataclass(frozen=True)
class VibrationRealization:
    """Vibration of M (or 1) runs as explicit tones.

    Angular: ``θ(t) = Σ A_j sin(2π f_j t + φ_j)`` (rotation vector of the
    vibrating IMU frame relative to its nominal frame); linear:
    ``a(t) = Σ B_j sin(2π g_j t + ψ_j)`` (acceleration in the nominal IMU
    frame).  Arrays ``A`` (Mv, J, 3), ``f`` (J,), ``phi`` (Mv, J).
    """

    A: np.ndarray
    f: np.ndarray
    phi: np.ndarray
    B: np.ndarray
    g: np.ndarray
    psi: np.ndarray

    @property
    def n_runs(self) -> int:
        return self.A.shape[0]

    @property
    def max_frequency(self) -> float:
        fs = np.concatenate([self.f, self.g])
        return float(fs.max()) if fs.size else 0.0

    def _sum(self, amp, freq, ph, t, deriv):
        if freq.size == 0:
            return np.zeros((amp.shape[0], np.size(t), 3))
        w = 2.0 * math.pi * freq
        arg = w[None, None, :] * np.asarray(t)[None, :, None] + ph[:, None, :]   # (Mv, N, J)
        if deriv == 0:
            c = np.sin(arg)
        elif deriv == 1:
            c = w * np.cos(arg)
        elif deriv == -1:
            c = -np.cos(arg) / w
        else:  # -2
            c = -np.sin(arg) / w**2
        return np.einsum("mnj,mjc->mnc", c, amp)

    def angle(self, t):
        """Rotation vector θ(t), shape (Mv, N, 3). [rad]"""
        return self._sum(self.A, self.f, self.phi, t, 0)

    def angle_rate(self, t):
        """θ̇(t), shape (Mv, N, 3). [rad/s]"""
        return self._sum(self.A, self.f, self.phi, t, 1)

    def accel(self, t):
        """Linear acceleration a(t), shape (Mv, N, 3). [m/s²]"""
        return self._sum(self.B, self.g, self.psi, t, 0)

    def velocity(self, t):
        """Zero-mean velocity ∫a, shape (Mv, N, 3). [m/s]"""
        return self._sum(self.B, self.g, self.psi, t, -1)

    def displacement(self, t):
        """Zero-mean displacement ∫∫a, shape (Mv, N, 3). [m]"""
        return self._sum(self.B, self.g, self.psi, t, -2)


def _right_jacobian_apply(theta, dtheta):
    """Body rate ``J_r(θ) θ̇`` of the rotation ``exp(θ)``.

    ``J_r = I − (1 − cos a)/a² [θ×] + (a − sin a)/a³ [θ×]²``, ``a = |θ|``.
    """
    a2 = np.sum(theta * theta, axis=-1, keepdims=True)
    a = np.sqrt(a2)
    small = a2 < 1e-8
    sa = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(a)) / sa**2)
    c2 = np.where(small, 1.0 / 6.0 - a2 / 120.0, (a - np.sin(a)) / sa**3)
    tx = np.cross(theta, dtheta)
    return dtheta - c1 * tx + c2 * np.cross(theta, tx)


# --------------------------------------------------------------------------
# simulator
# --------------------------------------------------------------------------


class ImuSimulator:
    """Stream of IMU increments of M runs along a trajectory.

    Parameters
    ----------
    traj : covtool.trajectory.Trajectory
        True motion of the vehicle body.
    rate : float
        Sample rate. [Hz]
    t0, duration : float, optional
        Span (default: the whole trajectory, whole samples). [s]
    errors : SensorErrors, optional
        Sensor errors (sets the number of runs M); None: error-free.
    n_runs : int
        Number of runs when neither ``errors`` nor ``vibration`` sets it.
    quantization : tuple of (float or None), optional
        ``(angle LSB [rad], velocity LSB [m/s])``: the outputs are whole
        multiples of the LSB with the remainder carried to the next sample
        (pulse counting), so the quantisation error never accumulates.
    saturation : tuple of (float or None), optional
        ``(rate range [rad/s], specific-force range [m/s²])``: the sample
        means are clipped per axis.
    vibration : Vibration or VibrationRealization, optional
        Vibration of the IMU as a real motion (see Notes).
    mounting : array_like, shape (4,), optional
        ``q_bs``, the IMU (sensor) frame in the body frame.
    nodes : int, optional
        Gauss–Legendre nodes per sample (default: 3, more when vibration
        frequencies require it).
    chunk : int
        Samples per streamed record (1200 is a multiple of 1 … 6).
    rng : numpy.random.Generator or int, optional
        For the vibration phases (the errors carry their own generator).

    Notes
    -----
    Vibration: the IMU frame is the nominal frame rotated by ``exp(θ(t))``
    and accelerated by ``a(t)`` (nominal frame) relative to it, so::

        ω^s = Cᵀ ω_nom^s + J_r(θ) θ̇,   f^s = Cᵀ (f_nom^s + a),   C = C(exp θ)

    and the truth (:meth:`truth`) is ``q_nb ⊗ q_bs ⊗ exp(θ)``, velocity
    ``v + C_s^n ∫a`` and position offset ``C_s^n ∫∫a``.  The increments are
    the quadrature of these exact rates, so coning and sculling are those of
    the real motion.  (The Coriolis and frame-rotation effects of the
    vibration velocity, µm/s for typical levels, are neglected.)
    """

    def __init__(self, traj, rate: float, *, t0=None, duration=None, errors: SensorErrors | None = None,
                 n_runs: int = 1, quantization=None, saturation=None, vibration=None, mounting=None,
                 nodes: int | None = None, chunk: int = 1200, rng=None):
        self.traj = traj
        self.t0, self.dt, self.n_samples = _span(traj, rate, t0, duration)
        self.rate = 1.0 / self.dt
        self.errors = errors
        if isinstance(vibration, Vibration):
            M = errors.n_runs if errors is not None else int(n_runs)
            vibration = vibration.realize(M, rng)
        self.vibration = vibration
        runs = {int(n_runs)} if errors is None and vibration is None else set()
        if errors is not None:
            runs.add(errors.n_runs)
        if vibration is not None and vibration.n_runs > 1:
            runs.add(vibration.n_runs)
        if len(runs) > 1:
            raise ValueError(f"inconsistent numbers of runs: {sorted(runs)}")
        self.n_runs = runs.pop() if runs else 1
        self.quantization = (None, None) if quantization is None else tuple(quantization)
        self.saturation = (None, None) if saturation is None else tuple(saturation)
        self.mounting = None if mounting is None else np.asarray(mounting, dtype=float)
        self._R = None if mounting is None else quat.dcm(self.mounting)   # C_s^b
        fmax = vibration.max_frequency if vibration is not None else 0.0
        self.nodes = int(nodes) if nodes is not None else _auto_nodes(fmax, self.dt)
        if chunk < 1:
            raise ValueError(f"chunk must be a positive number of samples, got {chunk!r}")
        self.chunk = int(chunk)

    @classmethod
    def from_grade(cls, traj, grade: ImuGrade, n_runs: int, rng=None, *, extras: bool = True,
                   rate=None, noise: bool = True, **kw) -> "ImuSimulator":
        """Simulator of M runs of a grade (errors drawn from its model).

        Parameters
        ----------
        extras : bool
            Apply the grade's quantisation and range saturation.
        rate : float, optional
            Sample rate (default: the grade's). [Hz]
        noise : bool
            See :class:`SensorErrors`.
        **kw
            Passed to :class:`ImuSimulator` (``t0``, ``duration``,
            ``vibration``, ``mounting`` …).
        """
        rng = np.random.default_rng(rng)
        rate = grade.rate if rate is None else rate
        if rate is None:
            raise ValueError(f"IMU grade {grade.name!r} has no rate; pass rate=")
        errors = SensorErrors.from_grade(grade, n_runs, rng, noise=noise)
        if extras:
            kw.setdefault("quantization", grade.quantization)
            kw.setdefault("saturation", grade.range)
        return cls(traj, rate, errors=errors, rng=rng, **kw)

    # ---- truth -----------------------------------------------------------
    def truth(self, t):
        """True state of the IMU frame at times ``t``.

        Returns
        -------
        covtool.strapdown.NavState
            Arrays of leading length S, or (S, M) with per-run vibration.
        """
        from .strapdown import NavState, truth_state

        t = np.atleast_1d(np.asarray(t, dtype=float))
        tr = truth_state(self.traj, t, mounting=self.mounting)
        vib = self.vibration
        if vib is None:
            return tr
        rel = quat.from_rotvec(vib.angle(t))                       # (Mv, S, 4)
        q = quat.mul(tr.q[None], rel)
        C = quat.dcm(tr.q)                                         # (S, 3, 3) nominal C_s^n
        v = tr.v_n[None] + np.einsum("sij,msj->msi", C, vib.velocity(t))
        d = np.einsum("sij,msj->msi", C, vib.displacement(t))
        from . import earth
        rm, rn = earth.radii(tr.lat)
        lat = tr.lat[None] + d[..., 0] / (rm + tr.h)
        lon = tr.lon[None] + d[..., 1] / ((rn + tr.h) * np.cos(tr.lat))
        h = tr.h[None] - d[..., 2]
        tp = lambda a: np.swapaxes(a, 0, 1)   # (Mv, S, …) -> (S, Mv, …)
        if vib.n_runs == 1:
            return NavState(tr.t, lat[0], lon[0], h[0], v[0], q[0], tr.dtheta_prev, tr.dv_prev)
        S = t.size
        return NavState(tr.t, tp(lat), tp(lon), tp(h), tp(v), tp(q), np.zeros((S, 3)), np.zeros((S, 3)))

    def initial_state(self, errors=None, *, previous: bool = True):
        """Initial navigation state of the IMU frame for the M runs.

        Parameters
        ----------
        errors : ndarray, shape (M, 10), optional
            Initial navigation errors (e.g. ``x0[:, :10]``).
        previous : bool
            Seed the "previous sample" with the exact increment of the
            sample period before ``t0`` when the trajectory allows it.
        """
        from .strapdown import NavState

        tr = self.truth([self.t0])
        M = self.n_runs
        x = np.zeros((M, 10)) if errors is None else np.broadcast_to(np.asarray(errors, float), (M, 10))
        if tr.lat.ndim == 2:
            lat, lon, h, v, q = tr.lat[0], tr.lon[0], tr.h[0], tr.v_n[0], tr.q[0]
        else:
            lat, lon, h = (np.repeat(a, M) for a in (tr.lat, tr.lon, tr.h))
            v, q = np.repeat(tr.v_n, M, axis=0), np.repeat(tr.q, M, axis=0)
        q = q + x[:, 6:10]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        dth_p = np.zeros((M, 3))
        dv_p = np.zeros((M, 3))
        if previous and self.t0 - self.dt >= float(self.traj.t[0]) - 1e-12:
            a, b = self._true_increments(self.t0 - self.dt, 1)
            dth_p[:] = a[:, 0]
            dv_p[:] = b[:, 0]
        return NavState(self.t0, lat + x[:, 0], lon + x[:, 1], h + x[:, 2], v + x[:, 3:6], q, dth_p, dv_p)

    # ---- increments --------------------------------------------------------
    def _true_increments(self, t_start, k):
        """Exact increments of k samples, shape (Mv, k, 3)."""
        h = self.dt
        u, w = _gl_nodes(self.nodes)
        ts = (t_start + (np.arange(k)[:, None] + u[None, :]) * h).ravel()
        s = self.traj.sample(ts)
        wb, fb = s.w_ib_b, s.f_b
        if self._R is not None:
            wb = wb @ self._R
            fb = fb @ self._R
        vib = self.vibration
        if vib is None:
            wb, fb = wb[None], fb[None]
        else:
            th = vib.angle(ts)
            Ct = np.swapaxes(quat.dcm(quat.from_rotvec(th)), -1, -2)   # C(exp θ)ᵀ
            wb = np.einsum("mnij,nj->mni", Ct, wb) + _right_jacobian_apply(th, vib.angle_rate(ts))
            fb = np.einsum("mnij,mnj->mni", Ct, fb[None] + vib.accel(ts))
        Mv = wb.shape[0]
        dth = h * np.einsum("j,mkjc->mkc", w, wb.reshape(Mv, k, self.nodes, 3))
        dv = h * np.einsum("j,mkjc->mkc", w, fb.reshape(Mv, k, self.nodes, 3))
        return dth, dv

    def _context(self, t_start, k):
        """Speed, mid-sample attitude and gravity for the errors."""
        from . import earth

        kw = {}
        if self.errors is None:
            return kw
        if self.errors.needs_speed:
            traj = self.traj
            kw["speed_fn"] = lambda t: np.linalg.norm(
                traj.sample(np.clip(np.atleast_1d(t), traj.t[0], traj.t[-1])).v_n[:, :2], axis=-1)
        if self.errors.needs_attitude:
            tm = t_start + (np.arange(k) + 0.5) * self.dt
            s = self.traj.sample(tm)
            q = s.q_nb if self.mounting is None else quat.mul(s.q_nb, self.mounting)
            kw["attitude"] = q
            kw["gravity"] = earth.gravity(s.lat, s.h)
        return kw

    def records(self, chunk: int | None = None):
        """Yield consecutive :class:`ImuRecord` chunks of shape (M, k, 3).

        The process states, quantisation remainders and random draws carry
        over from chunk to chunk, so one pass gives one realisation; a
        second pass continues the same processes (make a new simulator, or
        new :class:`SensorErrors`, to start again).
        """
        chunk = self.chunk if chunk is None else int(chunk)
        M = self.n_runs
        qa, qv = self.quantization
        ra, rv = self.saturation
        res_a = np.zeros((M, 3))
        res_v = np.zeros((M, 3))
        for a in range(0, self.n_samples, chunk):
            k = min(chunk, self.n_samples - a)
            ts = self.t0 + a * self.dt
            dth, dv = self._true_increments(ts, k)
            if self.errors is not None:
                e_th, e_v = self.errors.increment_errors(ts, self.dt, dth, dv, **self._context(ts, k))
                dth = dth + e_th
                dv = dv + e_v
            dth = np.broadcast_to(dth, (M, k, 3))
            dv = np.broadcast_to(dv, (M, k, 3))
            if ra is not None:
                dth = np.clip(dth, -ra * self.dt, ra * self.dt)
            if rv is not None:
                dv = np.clip(dv, -rv * self.dt, rv * self.dt)
            if qa is not None:
                dth, res_a = _quantize(dth, qa, res_a)
            if qv is not None:
                dv, res_v = _quantize(dv, qv, res_v)
            yield ImuRecord(ts, self.dt, np.ascontiguousarray(dth), np.ascontiguousarray(dv))

    def record(self) -> ImuRecord:
        """The whole span as one record (M, K, 3) (memory permitting)."""
        recs = list(self.records())
        return ImuRecord(self.t0, self.dt, np.concatenate([r.dtheta for r in recs], axis=-2),
                         np.concatenate([r.dv for r in recs], axis=-2))


def _quantize(x, lsb, residual):
    """Pulse-count quantisation with the remainder carried, (M, k, 3)."""
    c = residual[:, None, :] + np.cumsum(x, axis=1)
    qc = np.round(c / lsb) * lsb
    out = np.diff(qc, axis=1, prepend=0.0)
    return out, c[:, -1, :] - qc[:, -1, :]
