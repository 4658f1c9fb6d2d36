"""Block kinds of the error-state library and how each couples into the navigation errors.

A model file declares *blocks*; each block kind here declares its states
(names, symbols, dimension) and its physics:

* a **sensor block** returns the body-frame sensitivity ``S`` with
  ``δf^b = S_a x`` (accelerometer, seed 002 eq (5)) or ``δω_ib^b = S_g x``
  (gyro, seed 002 eq (3)); :mod:`covtool.lincov.dynamics` maps them into the velocity
  rows (``C_b^n S_a``) and quaternion rows (``½ Q(q) S_g``);
* an **environment block** returns the NED gravity-error sensitivity;
* the **AD-reset block** (seed 000) is a bounded velocity error whose time
  derivative is a specific-force error.

Sensitivities are evaluated for all time samples at once: ``f`` and ``w`` have
shape ``(N, 3)`` and the result has shape ``(N, 3, n_block)``.

Axis conventions
----------------
Sensor axes coincide with body axes (their non-orthogonality is the
misalignment block).  Off-diagonal misalignment states ``m_ij`` couple axis
``j``'s input into sensor ``i``.  For the g-sensitive gyro terms the spin
(output) axis of gyro ``i`` is taken cyclically: x→y, y→z, z→x.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

AXES = ("x", "y", "z")
OFFDIAG = (("x", "y"), ("x", "z"), ("y", "x"), ("y", "z"), ("z", "x"), ("z", "y"))
_IDX = {"x": 0, "y": 1, "z": 2}
SPIN = {0: 1, 1: 2, 2: 0}

NAV_SYMBOLS = ("δL", "δl", "δh", "δV_N", "δV_E", "δV_D", "δq0", "δq1", "δq2", "δq3")
NAV_DIMS = ("angle", "angle", "length", "velocity", "velocity", "velocity",
            "quaternion", "quaternion", "quaternion", "quaternion")
NAV_MEANING = ("latitude error", "longitude error", "height error",
               "north velocity error", "east velocity error", "down velocity error",
               "additive quaternion error, scalar part", "additive quaternion error, x",
               "additive quaternion error, y", "additive quaternion error, z")


@dataclass(frozen=True)
class BlockKind:
    """Declaration of one kind of error block.

    Attributes
    ----------
    kind : str
        Name used in model files (``kind = "accel_bias"``).
    prefix : str
        Default state-name prefix.
    suffixes : tuple of str
        Per-state name suffixes (``prefix + "_" + suffix``).
    symbols : tuple of str
        Per-state symbols (seed 002 notation where it has one).
    dims : tuple of str
        Per-state dimension (see :data:`covtool.units.DIMENSIONS`).
    meaning : str
        Human-readable description with ``{axis}`` placeholder.
    sensor : str
        ``"accel"``, ``"gyro"``, ``"gravity"``, ``"ad_reset"`` or ``"nav"``.
    sensitivity : callable
        ``(f_b, w_ib_b) -> ndarray (N, 3, n)``.
    processes : tuple of str
        Stochastic processes allowed.
    ref : str
        Equation reference.
    """

    kind: str
    prefix: str
    suffixes: tuple
    symbols: tuple
    dims: tuple
    meaning: str
    sensor: str
    sensitivity: Callable | None = None
    processes: tuple = ("constant", "random_walk", "markov")
    ref: str = ""
    extra_keys: tuple = field(default=())

    @property
    def n(self) -> int:
        return len(self.suffixes)


def _diag(v):
    n = v.shape[0]
    out = np.zeros((n, 3, 3))
    out[:, [0, 1, 2], [0, 1, 2]] = v
    return out


def _identity(f, w):
    return np.broadcast_to(np.eye(3), (f.shape[0], 3, 3)).copy()


def _misalignment(v):
    n = v.shape[0]
    out = np.zeros((n, 3, 6))
    for k, (i, j) in enumerate(OFFDIAG):
        out[:, _IDX[i], k] = v[:, _IDX[j]]
    return out


def _gsens(f, w):
    n = f.shape[0]
    out = np.zeros((n, 3, 6))
    for i in range(3):
        out[:, i, 2 * i] = f[:, i]
        out[:, i, 2 * i + 1] = f[:, SPIN[i]]
    return out


def _aniso(f, w):
    out = np.zeros((f.shape[0], 3, 3))
    for i in range(3):
        out[:, i, i] = f[:, i] * f[:, SPIN[i]]
    return out


def _xyz(p, sym):
    return tuple(f"{sym}{a}" for a in AXES)


BLOCK_KINDS: dict[str, BlockKind] = {}


def _register(bk: BlockKind):
    BLOCK_KINDS[bk.kind] = bk
    return bk


_register(BlockKind(
    "accel_bias", "acc_bias", AXES, ("B_x", "B_y", "B_z"), ("acceleration",) * 3,
    "accelerometer bias, {axis} axis", "accel", _identity, ref="seed 002 eq (5), B^a"))
_register(BlockKind(
    "accel_scale_factor", "acc_sf", AXES, ("K_x", "K_y", "K_z"), ("dimensionless",) * 3,
    "accelerometer scale-factor error, {axis} axis", "accel", lambda f, w: _diag(f),
    ref="seed 002 eq (5), K^a f^b"))
_register(BlockKind(
    "accel_misalignment", "acc_mis", tuple(i + j for i, j in OFFDIAG),
    tuple(f"ΔCa_{i}{j}" for i, j in OFFDIAG), ("angle",) * 6,
    "accelerometer misalignment, sensor {axis} input", "accel", lambda f, w: _misalignment(f),
    ref="seed 002 eq (5), (ΔC_a^b)^T f^b"))
_register(BlockKind(
    "accel_markov_bias", "acc_markov", AXES, ("Bm_x", "Bm_y", "Bm_z"), ("acceleration",) * 3,
    "accelerometer correlated (Markov) bias, {axis} axis", "accel", _identity,
    processes=("markov",), ref="seed 002 eq (5), bias; eq (11) process"))
_register(BlockKind(
    "accel_asymmetric_scale_factor", "acc_asym", AXES, ("Ka_x", "Ka_y", "Ka_z"), ("dimensionless",) * 3,
    "accelerometer asymmetric scale factor (|f| term), {axis} axis", "accel",
    lambda f, w: _diag(np.abs(f)), ref="seed 002 eq (5), scale-factor term, asymmetric part"))
_register(BlockKind(
    "gyro_bias", "gyro_bias", AXES, ("W_dx", "W_dy", "W_dz"), ("angular_rate",) * 3,
    "gyro bias, {axis} axis", "gyro", _identity, ref="seed 002 eq (3), δW_d"))
_register(BlockKind(
    "gyro_markov_drift", "gyro_markov", AXES, ("Wm_x", "Wm_y", "Wm_z"), ("angular_rate",) * 3,
    "gyro correlated (Markov) drift, {axis} axis", "gyro", _identity,
    processes=("markov",), ref="seed 002 eq (3), δW_d; eq (11) process"))
_register(BlockKind(
    "gyro_scale_factor", "gyro_sf", AXES, ("T_x", "T_y", "T_z"), ("dimensionless",) * 3,
    "gyro scale-factor error, {axis} axis", "gyro", lambda f, w: _diag(w),
    ref="seed 002 eq (3), δW_g"))
_register(BlockKind(
    "gyro_misalignment", "gyro_mis", tuple(i + j for i, j in OFFDIAG),
    tuple(f"ΔCg_{i}{j}" for i, j in OFFDIAG), ("angle",) * 6,
    "gyro misalignment, sensor {axis} input", "gyro", lambda f, w: _misalignment(w),
    ref="seed 002 eq (3), (ΔC_g^b)^T ω_ib^b"))
_register(BlockKind(
    "gyro_g_sensitivity", "gyro_gs", ("xx", "xy", "yy", "yz", "zz", "zx"),
    ("Dm_xx", "Dm_xy", "Dm_yy", "Dm_yz", "Dm_zz", "Dm_zx"), ("g_sensitivity",) * 6,
    "gyro mass-unbalance (g-sensitive) drift, gyro/accel axes {axis}", "gyro", _gsens,
    ref="seed 002 eq (3), δW_m"))
_register(BlockKind(
    "gyro_anisoelastic", "gyro_aniso", AXES, ("Da_x", "Da_y", "Da_z"), ("g2_sensitivity",) * 3,
    "gyro anisoelastic drift (f_input·f_spin), {axis} gyro", "gyro", _aniso,
    ref="seed 002 eq (3), δW_a"))
_register(BlockKind(
    "gravity_disturbance", "grav", ("xi", "eta", "dg"), ("ξ", "η", "Δg"),
    ("angle", "angle", "acceleration"),
    "gravity disturbance: north deflection, east deflection, anomaly", "gravity", None,
    processes=("markov_distance", "constant"), ref="seed 002 eq (4), δg^n"))
_register(BlockKind(
    "ad_reset_velocity", "acc_ad", AXES, ("δv_AD,x", "δv_AD,y", "δv_AD,z"), ("velocity",) * 3,
    "accelerometer-board AD-reset velocity error (seed 000), {axis} axis", "ad_reset", None,
    processes=("markov",), ref="seed 000 eq (6)-(8); enters seed 002 eq (4) via δf^b = d(δv_AD)/dt"))


def gravity_sensitivity(g):
    """NED gravity-error sensitivity of the gravity-disturbance block.

    The INS uses normal gravity; the truth adds the disturbance
    ``Δg^n = [−g ξ, −g η, Δg]`` (deflections ξ, η of the vertical, anomaly Δg).
    The velocity error (computed − true) therefore sees ``−Δg^n``.

    Parameters
    ----------
    g : ndarray, shape (N,)
        Normal gravity. [m/s^2]

    Returns
    -------
    ndarray, shape (N, 3, 3)
    """
    n = g.shape[0]
    out = np.zeros((n, 3, 3))
    out[:, 0, 0] = g
    out[:, 1, 1] = g
    out[:, 2, 2] = -1.0
    return out
