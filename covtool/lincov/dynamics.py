"""Error dynamics F(t) and process noise along a trajectory (seed 002, eq (1)–(5)).

State order and meaning follow :class:`covtool.lincov.model.spec.Model`; the first
ten states are the navigation errors of seed 002, eq (14)::

    x = [δL δl δh | δV_N δV_E δV_D | δq0 δq1 δq2 δq3 | sensor/environment states]

Error = computed − true.  The continuous model is ``ẋ = F x + G w`` with
``E[w wᵀ] = W δ(t−s)``; this module returns ``F`` and ``Q_c = G W Gᵀ``, both
for every trajectory sample at once (shape ``(N, n, n)``).

Navigation error equations (derivation in docs/error_model.md)
---------------------------------------------------------------
Position (perturbation of ``L̇ = v_N/(R_M+h)``, ``l̇ = v_E/((R_N+h)cos L)``,
``ḣ = −v_D``), including the latitude dependence of the radii.

Velocity, seed 002 eq (4)::

    δv̇ = C_b^n δf^b + J(q, f^b) δq − (2δω_ie + δω_en) × v
          − (2ω_ie + ω_en) × δv + δg

where ``J = ∂(C(q/|q|) f)/∂q`` (:func:`covtool.nav.attitude.dcm_times_vector_jacobian`,
the quaternion scale error ignored as in seed 002 §2.1), ``δω_ie``, ``δω_en``
are the perturbations of Earth and transport rate through ``δL, δh, δv`` and
``δg`` is the normal-gravity perturbation through ``δL, δh`` (the ``−2g/R``
term makes the vertical channel unstable) plus the gravity-disturbance block.

Attitude, seed 002 eq (1)::

    δq̇ = ½[ω_ib^b] δq − ½[ω_in^n] δq + ½ Q(q) δω_ib^b − ½ R(q) δω_in^n

Sensor errors enter through ``δf^b`` (seed 002 eq (5)) and ``δω_ib^b``
(seed 002 eq (3)); each block kind supplies its sensitivity
(:mod:`covtool.lincov.model.blocks`).

Quaternion constraint
---------------------
``qᵀδq`` (the norm error) is an invariant of these equations: ``qᵀQ(q) =
qᵀR(q) = 0`` and the skew parts conserve it, and ``J`` has no component
along ``q``.  The norm error therefore neither grows nor affects any other
state; with the seed 002 Table 2 initial σ (δq0 = 0 at q = 1) it is zero and P
has one structural zero eigenvalue.  Physical attitude errors are
``φ = −2 R(q)ᵀ δq`` (:func:`covtool.nav.attitude.attitude_error_matrix`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from covtool.lincov.model.blocks import BLOCK_KINDS, gravity_sensitivity
from covtool.lincov.model.spec import Model
from covtool.lincov.stacks import gather
from covtool.nav import attitude as quat, earth

I_L, I_l, I_H, I_VN, I_VE, I_VD = range(6)
I_Q = slice(6, 10)
POS = slice(0, 3)
VEL = slice(3, 6)
VERTICAL = (I_H, I_VD)
HORIZONTAL = (I_L, I_l, I_VN, I_VE, 6, 7, 8, 9)


@dataclass(frozen=True)
class NavOptions:
    """Simplifications of the navigation error equations (seed 002, Table 1).

    Attributes
    ----------
    coriolis : bool
        Keep the Coriolis terms ``−2ω_ie × δv`` and ``−2δω_ie × v`` of eq (4).
        Filter B3 drops them.
    couple_vertical : bool
        Keep the coupling between the vertical channel (δh, δV_D) and the
        horizontal/attitude states.  Filter B2 drops it.
    """

    coriolis: bool = True
    couple_vertical: bool = True


@dataclass
class Context:
    """Trajectory quantities needed by the error equations, shape ``(N, ...)``."""

    lat: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    f_b: np.ndarray
    w_ib_b: np.ndarray
    C: np.ndarray = field(init=False)
    speed: np.ndarray = field(init=False)
    g: np.ndarray = field(init=False)

    def __post_init__(self):
        self.lat = np.atleast_1d(np.asarray(self.lat, float))
        self.h = np.atleast_1d(np.asarray(self.h, float))
        self.v_n = np.atleast_2d(np.asarray(self.v_n, float))
        self.q = np.atleast_2d(np.asarray(self.q, float))
        self.f_b = np.atleast_2d(np.asarray(self.f_b, float))
        self.w_ib_b = np.atleast_2d(np.asarray(self.w_ib_b, float))
        self.C = quat.dcm(self.q)
        self.speed = np.linalg.norm(self.v_n[:, :2], axis=-1)
        self.g = earth.gravity(self.lat, self.h)

    @classmethod
    def from_trajectory(cls, traj) -> "Context":
        """Context from a :class:`covtool.nav.trajectory.core.Trajectory` (all its samples)."""
        return cls(traj.lat, traj.h, traj.v_n, traj.q_nb, traj.f_b, traj.w_ib_b)

    @property
    def n(self) -> int:
        return self.lat.shape[0]

    def slice(self, a: int, b: int) -> "Context":
        """The samples ``a … b−1`` (views, the derived fields sliced too: equal to a full build)."""
        out = object.__new__(Context)
        for name in ("lat", "h", "v_n", "q", "f_b", "w_ib_b", "C", "speed", "g"):
            setattr(out, name, getattr(self, name)[a:b])
        return out


@dataclass
class NoiseSource:
    """One white driving noise: ``Q_c += G diag(psd) Gᵀ``.

    Attributes
    ----------
    name : str
    G : ndarray, shape (N, n, k)
    psd : ndarray, shape (N, k)
    """

    name: str
    G: np.ndarray
    psd: np.ndarray

    def qc(self) -> np.ndarray:
        """Contribution to ``Q_c``, shape ``(N, n, n)``."""
        return (self.G * self.psd[:, None, :]) @ np.swapaxes(self.G, 1, 2)

    def add_qc(self, Qc: np.ndarray, a: int = 0, b: int | None = None) -> None:
        """Add the steps ``a … b−1``'s contribution to ``Qc`` (shape ``(b−a, n, n)``), in place."""
        G = self.G[a:b]
        Qc += (G * self.psd[a:b, None, :]) @ np.swapaxes(G, 1, 2)

    def steps(self, a: int, b: int) -> "NoiseSource":
        """The source over the steps ``a … b−1``: ``G`` of shape ``(b−a, n, k)``, ``psd`` ``(b−a, k)``."""
        return NoiseSource(self.name, self.G[a:b], self.psd[a:b])

    def compact(self) -> "NoiseSource":
        """The same source holding only the rows of ``G`` that are not zero (:class:`CompactNoiseSource`)."""
        rows = np.flatnonzero(np.any(np.asarray(self.G) != 0, axis=(0, 2)))
        return CompactNoiseSource(self.name, np.ascontiguousarray(self.G[:, rows, :]), self.psd, rows,
                                  self.G.shape[1])


class CompactNoiseSource(NoiseSource):
    """A :class:`NoiseSource` whose ``G`` is stored by its non-zero rows only.

    An equivalent-noise source of eq (11)–(13) drives the 3 or 4 states its
    dropped state couples into (a velocity or attitude block), so its
    ``(N, n, k)`` matrix is mostly zeros; over a long study this storage is
    ``n/rows`` times smaller.  ``G`` expands on access (same values).

    Parameters
    ----------
    name : str
    G_rows : ndarray, shape (N, r, k)
        The rows ``rows`` of ``G``.
    psd : ndarray, shape (N, k)
    rows : ndarray of int, shape (r,)
    n : int
        Rows of the full ``G``.
    """

    def __init__(self, name, G_rows, psd, rows, n):
        self.name, self.G_rows, self.psd, self.rows, self.n = name, G_rows, psd, np.asarray(rows, int), int(n)

    @property
    def G(self) -> np.ndarray:
        """The full ``G``, shape ``(N, n, k)`` (built on access)."""
        return self._expand(0, None)

    def _expand(self, a, b):
        Gr = self.G_rows[a:b]
        out = np.zeros((Gr.shape[0], self.n, Gr.shape[2]))
        out[:, self.rows, :] = Gr
        return out

    def add_qc(self, Qc: np.ndarray, a: int = 0, b: int | None = None) -> None:
        # on its rows only, as covtool.lincov.reduced.equivalent_noise_qc adds the whole grid's: each
        # element is the same sum over the source's columns (the other rows' products are zeros)
        Gr = self.G_rows[a:b]
        r = self.rows
        Qc[:, r[:, None], r[None, :]] += (Gr * self.psd[a:b, None, :]) @ np.swapaxes(Gr, 1, 2)

    def steps(self, a: int, b: int) -> NoiseSource:
        """The source over the steps ``a … b−1``, its full ``G`` (shape ``(b−a, n, k)``) expanded."""
        return NoiseSource(self.name, self._expand(a, b), self.psd[a:b])

    def compact(self) -> "CompactNoiseSource":
        return self


@dataclass
class ErrorDynamics:
    """F(t), Q_c(t) and the noise sources of a model along a trajectory.

    ``options`` are the navigation options F was built under (seed 002
    eq (1), (4) with or without the Coriolis terms and the vertical
    coupling): a filter built from these dynamics must declare the same
    (:func:`covtool.lincov.reduced.build_filter` checks).
    """

    names: list
    F: np.ndarray
    noise: list
    options: "NavOptions" = NavOptions()

    @property
    def Qc(self) -> np.ndarray:
        """Continuous process-noise PSD matrix ``G W Gᵀ``, shape ``(N, n, n)``."""
        if getattr(self, "_qc", None) is None:
            out = np.zeros_like(self.F)
            for src in self.noise:
                nz = np.flatnonzero(np.any(src.G != 0, axis=(0, 2)))
                if nz.size == 0:
                    continue
                G = src.G[:, nz, :]
                out[:, nz[:, None], nz[None, :]] += (G * src.psd[:, None, :]) @ np.swapaxes(G, 1, 2)
            self._qc = out
        return self._qc

    def F_block(self, rows, cols=None) -> np.ndarray:
        """``F[:, rows][:, :, cols]`` as a new C-contiguous stack (:func:`covtool.lincov.stacks.gather`).

        Parameters
        ----------
        rows : array_like of int, shape (r,)
        cols : array_like of int, shape (c,), optional
            Default ``rows``.

        Returns
        -------
        ndarray, shape (N, r, c)
        """
        return gather(self.F, rows, cols)

    def F_steps(self, a: int, b: int) -> np.ndarray:
        """``F[a:b]``, shape ``(b − a, n, n)``: the steps ``a … b−1``, C-contiguous."""
        return self.F[a:b]


class OptionsDynamics(ErrorDynamics):
    """The dynamics of :func:`with_nav_options`: another model's F with its navigation block replaced.

    ``F`` (shape ``(N, n, n)``) is built on first access; :meth:`F_block`
    gathers a sub-block from the base F and the new navigation block
    without building it (a reduced filter needs only its own rows), and
    :meth:`F_steps` a run of steps, with the same values.  Q_c and the noise sources are the base's own.

    Parameters
    ----------
    base : ErrorDynamics
        The model's dynamics under the default options.
    nav : ndarray, shape (N, 10, 10)
        :func:`nav_matrix` under the other options (seed 002 eq (1), (4)).
    options : NavOptions
        Those options (:attr:`ErrorDynamics.options`).
    """

    def __init__(self, base: ErrorDynamics, nav: np.ndarray, options: "NavOptions"):
        self.names, self.noise, self.options = base.names, base.noise, options
        self._base, self._nav, self._F = base, nav, None
        self._qc = base.Qc

    @property
    def F(self) -> np.ndarray:
        if self._F is None:
            F = self._base.F.copy()
            F[:, :10, :10] = self._nav
            self._F = F
        return self._F

    def F_steps(self, a: int, b: int) -> np.ndarray:
        if self._F is not None:
            return self._F[a:b]
        F = self._base.F[a:b].copy()                     # the values of F[a:b], without building F
        F[:, :10, :10] = self._nav[a:b]
        return F

    def F_block(self, rows, cols=None) -> np.ndarray:
        if self._F is not None:
            return gather(self._F, rows, cols)
        rows = np.asarray(rows, np.intp).reshape(-1)
        cols = rows if cols is None else np.asarray(cols, np.intp).reshape(-1)
        out = gather(self._base.F, rows, cols)
        n = self._base.F.shape[1]
        r, c = np.flatnonzero(rows % n < 10), np.flatnonzero(cols % n < 10)
        if r.size and c.size:
            out[:, r[:, None], c[None, :]] = self._nav[:, (rows[r] % n)[:, None], (cols[c] % n)[None, :]]
        return out


#: steps of F, Q_c, Φ and Q_d generated at once when a study streams in time (a multiple of
#: covtool.studies.resources.DISCRETIZE_CHUNK, so that each step is discretised in the same batch as when
#: the whole grid is held)
STREAM_CHUNK = 600


class DynamicsStream:
    """F(t) and Q_c(t) of a model along a trajectory, generated chunk by chunk in time.

    Nothing of size ``N × n²`` is held: :meth:`chunk` builds the
    :class:`ErrorDynamics` of the steps ``a … b−1`` (the same values as the
    rows of :func:`error_dynamics` over the whole context), and
    :meth:`columns` gathers a few columns of F over the whole span.

    Parameters
    ----------
    model : Model
    ctx : Context
        Trajectory at the propagation mid-points, shape (N, ...).
    options : NavOptions
    chunk : int
        Steps per chunk.
    """

    def __init__(self, model: Model, ctx: Context, options: "NavOptions" = None, chunk: int = STREAM_CHUNK):
        self.model, self.ctx, self.options, self.chunk_steps = model, ctx, options or NavOptions(), int(chunk)
        self.names = model.names
        # the whole span's noise sources, in every chunk (a chunk at rest has its distance-driven ones at zero)
        self.sources = noise_source_names(model, ctx)

    @property
    def n_steps(self) -> int:
        return self.ctx.n

    def bounds(self):
        """``(a, b)`` of every chunk, in order."""
        N = self.ctx.n
        return [(a, min(N, a + self.chunk_steps)) for a in range(0, N, self.chunk_steps)]

    def chunk(self, a: int, b: int) -> "ErrorDynamics":
        """F, Q_c and the noise sources of the steps ``a … b−1``."""
        return error_dynamics(self.model, self.ctx.slice(a, b), self.options, sources=self.sources)

    def columns(self, rows, cols) -> np.ndarray:
        """``F[rows, cols]`` over the whole span, column-major: shape ``(len(cols), len(rows), N)``.

        ``out[c].T`` is ``F[:, rows, cols[c]]`` (shape ``(N, len(rows))``)
        with the memory layout of that fancy index of a whole-grid ``F``
        (time fastest), and ``out[c0:c1].transpose(2, 1, 0)`` is
        ``F[:, rows][:, :, cols[c0:c1]]``, as laid out by numpy: views, no
        copies, and the same round-off in what consumes them.
        """
        rows, cols = np.asarray(rows, int), np.asarray(cols, int)
        out = np.empty((cols.size, rows.size, self.ctx.n))
        for a, b in self.bounds():
            F = self.chunk(a, b).F
            out[:, :, a:b] = F[:, rows[:, None], cols[None, :]].transpose(2, 1, 0)
        return out


def transport_rate_partials(lat, h, v_n):
    """Partials of ω_en^n with respect to L, h and v^n.

    Returns
    -------
    dL : ndarray, shape (N, 3)
    dh : ndarray, shape (N, 3)
    dv : ndarray, shape (N, 3, 3)
    """
    rm, rn = earth.radii(lat)
    drm, drn = earth.radii_derivatives(lat)
    rmh, rnh = rm + h, rn + h
    vn, ve = v_n[:, 0], v_n[:, 1]
    t = np.tan(lat)
    dL = np.stack([-ve * drn / rnh**2, vn * drm / rmh**2,
                   -ve * (1.0 / np.cos(lat) ** 2 / rnh - t * drn / rnh**2)], -1)
    dh = np.stack([-ve / rnh**2, vn / rmh**2, ve * t / rnh**2], -1)
    dv = np.zeros((lat.shape[0], 3, 3))
    dv[:, 0, 1] = 1.0 / rnh
    dv[:, 1, 0] = -1.0 / rmh
    dv[:, 2, 1] = -t / rnh
    return dL, dh, dv


def nav_matrix(ctx: Context, options: NavOptions = NavOptions()) -> np.ndarray:
    """The 10×10 navigation block of F, shape ``(N, 10, 10)`` (see module notes)."""
    N = ctx.n
    lat, h, v = ctx.lat, ctx.h, ctx.v_n
    F = np.zeros((N, 10, 10))
    rm, rn = earth.radii(lat)
    drm, drn = earth.radii_derivatives(lat)
    rmh, rnh = rm + h, rn + h
    cl, sl = np.cos(lat), np.sin(lat)
    vn, ve = v[:, 0], v[:, 1]
    # position
    F[:, I_L, I_VN] = 1.0 / rmh
    F[:, I_L, I_L] = -vn * drm / rmh**2
    F[:, I_L, I_H] = -vn / rmh**2
    F[:, I_l, I_VE] = 1.0 / (rnh * cl)
    F[:, I_l, I_L] = -ve * drn / (rnh**2 * cl) + ve * sl / (rnh * cl**2)
    F[:, I_l, I_H] = -ve / (rnh**2 * cl)
    F[:, I_H, I_VD] = -1.0
    # rates and their partials
    w_ie = earth.earth_rate_n(lat)
    w_en = earth.transport_rate_n(lat, h, v)
    dwie_dL = np.stack([-earth.OMEGA_IE * sl, np.zeros_like(sl), -earth.OMEGA_IE * cl], -1)
    dwen_dL, dwen_dh, dwen_dv = transport_rate_partials(lat, h, v)
    cor = 2.0 if options.coriolis else 0.0
    vx = quat.skew(v)
    # velocity, seed 002 eq (4)
    F[:, VEL, I_L] = np.einsum("tij,tj->ti", vx, cor * dwie_dL + dwen_dL)
    F[:, VEL, I_H] = np.einsum("tij,tj->ti", vx, dwen_dh)
    F[:, VEL, VEL] = -quat.skew(cor * w_ie + w_en) + vx @ dwen_dv
    dg_dL, dg_dh = earth.gravity_derivatives(lat, h)
    F[:, I_VD, I_L] += dg_dL
    F[:, I_VD, I_H] += dg_dh
    F[:, VEL, I_Q] = quat.dcm_times_vector_jacobian(ctx.q, ctx.f_b)
    # attitude, seed 002 eq (1)
    w_in = w_ie + w_en
    F[:, I_Q, I_Q] = 0.5 * quat.omega_body(ctx.w_ib_b) - 0.5 * quat.omega_nav(w_in)
    mR = -0.5 * quat.R_matrix(ctx.q)                       # (N,4,3)
    F[:, I_Q, I_L] = np.einsum("tij,tj->ti", mR, dwie_dL + dwen_dL)
    F[:, I_Q, I_H] = np.einsum("tij,tj->ti", mR, dwen_dh)
    F[:, I_Q, VEL] = mR @ dwen_dv
    if not options.couple_vertical:
        F[:, np.ix_(VERTICAL, HORIZONTAL)[0], np.ix_(VERTICAL, HORIZONTAL)[1]] = 0.0
        F[:, np.ix_(HORIZONTAL, VERTICAL)[0], np.ix_(HORIZONTAL, VERTICAL)[1]] = 0.0
    return F


def noise_source_names(model: Model, ctx: Context) -> frozenset:
    """Names of the noise sources :func:`error_dynamics` builds along ``ctx``: those with a PSD above zero
    somewhere (ARW, VRW, and each state's driving noise; a distance-driven one is zero at rest)."""
    names = {nm for nm, q in (("arw", model.arw), ("vrw", model.vrw)) if q > 0}
    for s in model.states:
        if s.kind != "navigation" and np.any(np.asarray(s.psd(ctx.speed)) > 0):
            names.add(s.name)
    return frozenset(names)


def error_dynamics(model: Model, ctx: Context, options: NavOptions = NavOptions(), *,
                   sources: frozenset | None = None) -> ErrorDynamics:
    """Build F(t) and the noise sources of ``model`` along ``ctx``.

    Parameters
    ----------
    model : Model
        Error-state model whose first ten states are the navigation states.
    ctx : Context
        Trajectory samples (usually the mid-points of the propagation steps).
    options : NavOptions
        Simplifications of the navigation block (filters B2, B3).
    sources : frozenset of str, optional
        The noise sources to build (:func:`noise_source_names` of a longer
        span: a chunk of a stream keeps the whole span's list, a source
        that is zero over the chunk included with a zero PSD); default:
        those with a PSD above zero somewhere along ``ctx``.

    Returns
    -------
    ErrorDynamics
        ``F`` of shape ``(N, n, n)`` and the list of :class:`NoiseSource`.
    """
    names = noise_source_names(model, ctx) if sources is None else sources
    N, n = ctx.n, model.n
    F = np.zeros((N, n, n))
    F[:, :10, :10] = nav_matrix(ctx, options)
    noise: list[NoiseSource] = []
    halfQ = 0.5 * quat.Q_matrix(ctx.q)                     # (N,4,3)
    C = ctx.C
    if "arw" in names:
        G = np.zeros((N, n, 3))
        G[:, I_Q, :] = halfQ
        noise.append(NoiseSource("arw", G, np.full((N, 3), model.arw**2)))
    if "vrw" in names:
        G = np.zeros((N, n, 3))
        G[:, VEL, :] = C
        noise.append(NoiseSource("vrw", G, np.full((N, 3), model.vrw**2)))
    # sensor and environment blocks
    for block in model.block_names():
        idx = [i for i, s in enumerate(model.states) if s.block == block]
        states = [model.states[i] for i in idx]
        kind = states[0].kind
        if kind == "navigation":
            continue
        bk = BLOCK_KINDS[kind]
        cols = np.array(idx)
        if bk.sensor == "accel":
            S = bk.sensitivity(ctx.f_b, ctx.w_ib_b)
            F[:, VEL, cols] = C @ S
        elif bk.sensor == "gyro":
            S = bk.sensitivity(ctx.f_b, ctx.w_ib_b)
            F[:, I_Q, cols] = halfQ @ S
        elif bk.sensor == "gravity":
            F[:, VEL, cols] = gravity_sensitivity(ctx.g)
        elif bk.sensor == "ad_reset":
            # the bounded velocity error e enters as δf^b = ė (seed 000 → seed 002 eq (4))
            inv_tau = np.array([1.0 / s.tau for s in states])
            F[:, VEL, cols] = -C * inv_tau[None, None, :]
        # own dynamics and driving noise
        for k, (i, s) in enumerate(zip(idx, states)):
            if s.process == "markov":
                F[:, i, i] = -1.0 / s.tau
            elif s.process == "markov_distance":
                F[:, i, i] = -ctx.speed / s.distance
            psd = s.psd(ctx.speed)
            if s.name in names:
                G = np.zeros((N, n, 1))
                G[:, i, 0] = 1.0
                if bk.sensor == "ad_reset":
                    G[:, VEL, 0] = C[:, :, k]
                noise.append(NoiseSource(s.name, G, np.broadcast_to(np.asarray(psd, float), (N,))[:, None].copy()))
    return ErrorDynamics(model.names, F, noise, options)


def with_nav_options(dyn: ErrorDynamics, ctx: Context, options: NavOptions) -> ErrorDynamics:
    """The dynamics ``dyn`` of a model under other navigation options.

    Parameters
    ----------
    dyn : ErrorDynamics
        :func:`error_dynamics` of a model along ``ctx`` with the default
        :class:`NavOptions`.
    ctx : Context
        The trajectory ``dyn`` was built on.
    options : NavOptions

    Returns
    -------
    ErrorDynamics
        Equal to ``error_dynamics(model, ctx, options)``: the options change
        only the 10×10 navigation block of F (:func:`nav_matrix`; seed 002
        eq (1), (4) without the Coriolis terms or the vertical coupling),
        never the sensor columns or the noise, so F is ``dyn.F`` with that
        block replaced (an :class:`OptionsDynamics`: the full stack is built
        only when it is read; a reduced filter gathers its rows without it),
        and the noise sources and Q_c are ``dyn``'s own (shared, not copied).
    """
    if dyn_key(options) == dyn_key(None):
        return dyn
    return OptionsDynamics(dyn, nav_matrix(ctx, options), options)


def attitude_errors(P_qq: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Covariance of the NED attitude error φ from that of δq.

    Parameters
    ----------
    P_qq : ndarray, shape (..., 4, 4)
    q : ndarray, shape (..., 4)

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Covariance of (north tilt, east tilt, azimuth). [rad²]
    """
    M = quat.attitude_error_matrix(q)
    return M @ P_qq @ np.swapaxes(M, -1, -2)


def nav_error_matrix(q, lat=None, h=None) -> np.ndarray:
    """Map from the navigation error state to physical errors, 9 × 10.

    The one home of the "physical navigation" transform: the velocity
    errors unchanged, the quaternion error to the attitude error
    ``φ = −2 R(q)ᵀ δq`` (north tilt, east tilt, azimuth;
    :func:`covtool.nav.attitude.attitude_error_matrix`), and the position
    errors ``(δL, δl, δh)`` either unchanged or, given ``lat`` and ``h``, in
    metres north, east and down: ``δN = (R_M + h) δL``,
    ``δE = (R_N + h) cos L δl``, ``δD = −δh``.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Attitude quaternion (body→NED).
    lat, h : float or array_like, shape (...), optional
        Geodetic latitude [rad] and height [m]; None keeps the position
        errors in ``(δL, δl, δh)``.

    Returns
    -------
    ndarray, shape (..., 9, 10)
        Rows: position (3), velocity N/E/D (3), north tilt, east tilt,
        azimuth; columns: the navigation states of seed 002 eq (14).
    """
    q = np.asarray(q, float)
    T = np.zeros(q.shape[:-1] + (9, 10))
    if lat is None:
        T[..., :3, :3] = np.eye(3)
    else:
        rm, rn = earth.radii(lat)
        T[..., 0, 0] = rm + h
        T[..., 1, 1] = (rn + h) * np.cos(lat)
        T[..., 2, 2] = -1.0
    T[..., 3:6, 3:6] = np.eye(3)
    T[..., 6:9, 6:10] = quat.attitude_error_matrix(q)
    return T


def physical_nav(P: np.ndarray, q) -> np.ndarray:
    """Navigation block in physical coordinates (δq → tilt, azimuth).

    Parameters
    ----------
    P : ndarray, shape (..., n_rec, 10, 10)
    q : ndarray, shape (n_rec, 4)

    Returns
    -------
    ndarray, shape (..., n_rec, 9, 9)
        Position (δL, δl, δh), velocity, then (north tilt, east tilt, azimuth):
        ``T P Tᵀ`` with ``T`` of :func:`nav_error_matrix`.
    """
    T = nav_error_matrix(q)
    return T @ P @ np.swapaxes(T, -1, -2)


def dyn_key(options):
    """Cache key of a NavOptions (None: the truth's own)."""
    if options is None:
        return (True, True)
    return (options.coriolis, options.couple_vertical)
