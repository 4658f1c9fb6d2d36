"""IMU vibration as a real motion: sinusoidal tones and random vibration."""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

__all__ = [
    "Tone", "RandomVibration", "Vibration", "VibrationRealization",
]


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


def right_jacobian_apply(theta, dtheta):
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
