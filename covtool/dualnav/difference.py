"""The navigation difference main − KIMU and its predicted covariance.

:func:`nav_difference` forms the difference vector ``z`` (:data:`DIFF_NAMES`:
``[δN, δE, δD, δv_N, δv_E, δv_D, δφ_N, δφ_E, δφ_D]`` of main minus KIMU);
:func:`difference_model` predicts its covariance by linear covariance
analysis: the two INS error states, each from its grade's
:class:`~covtool.lincov.model.spec.Model`, propagated independently along
the flight with covtool's error dynamics, correlated only through the
shared input heading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.dualnav.alignment import alignment_jacobian, alignment_second_order, small_angle
from covtool.lincov.discretize import block_triangular, is_block_triangular, taylor
from covtool.lincov.dynamics import Context, error_dynamics, nav_error_matrix
from covtool.lincov.batch import compose
from covtool.lincov.kalman import check_covariance, predict, symmetrize
from covtool.lincov.model.spec import Model
from covtool.nav import attitude as quat, earth, strapdown as sd

__all__ = [
    "DIFF_NAMES", "COMPONENTS", "nav_difference", "ImuLinearization", "DifferenceModel",
    "difference_model",
]


#: components of the difference vector z (main − KIMU)
DIFF_NAMES = ("pos_N", "pos_E", "pos_D", "vel_N", "vel_E", "vel_D", "att_N", "att_E", "att_D")
#: groups of difference components
COMPONENTS = {"position": (0, 1, 2), "velocity": (3, 4, 5), "attitude": (6, 7, 8)}


# --------------------------------------------------------------------------
# the navigation difference
# --------------------------------------------------------------------------


def nav_difference(main: sd.NavHistory, kimu: sd.NavHistory, mount_main=None, mount_kimu=None) -> np.ndarray:
    """Main − KIMU navigation difference after mounting compensation.

    Parameters
    ----------
    main, kimu : covtool.nav.strapdown.NavHistory
        Solutions at the same output times (S, M); each navigates its own
        sensor frame.
    mount_main, mount_kimu : array_like, shape (4,), optional
        Declared ``q_bs`` of each sensor frame in the vehicle body.

    Returns
    -------
    ndarray, shape (S, M, 9)
        ``[δN, δE, δD]`` [m] (north/east/down metres at the main solution),
        ``δv^n`` [m/s] and ``δφ`` [rad] with
        ``δφ = −rotvec(q̂_b,main ⊗ q̂_b,KIMU*)``, ``q̂_b = q̂_s ⊗ q_bs*``
        (the vehicle-body attitude each IMU implies).
    """
    if main.t.shape != kimu.t.shape or not np.allclose(main.t, kimu.t, atol=1e-9):
        raise ValueError("the two solutions must be given at the same output times")
    rm, rn = earth.radii(main.lat)
    dN = (main.lat - kimu.lat) * (rm + main.h)
    dE = np.angle(np.exp(1j * (main.lon - kimu.lon))) * (rn + main.h) * np.cos(main.lat)
    dD = -(main.h - kimu.h)

    def body(q, mount):
        return q if mount is None else quat.mul(q, quat.conj(np.asarray(mount, float)))

    phi = small_angle(body(main.q, mount_main), body(kimu.q, mount_kimu))
    return np.concatenate([np.stack([dN, dE, dD], -1), main.v_n - kimu.v_n, phi], axis=-1)


@dataclass
class ImuLinearization:
    """One IMU's linear error model along the flight.

    Attributes
    ----------
    model : Model
        Its error-state model (:meth:`covtool.io.imu_grade.ImuGrade.to_model`).
    ctx : Context
        Its own sensor-frame quantities at the mid-points of the propagation
        steps (mean ``f``, ``ω`` over each step, attitude at the mid-point).
    q_epochs : ndarray, shape (J+1, 4)
        Its attitude at the comparison epochs.
    rest_ctx : Context
        The rest condition of the alignment (one sample: position, aligned
        attitude, mean ``f`` and ``ω`` over the window).
    align_time : float
        Length of the alignment window. [s]
    heading : float
        The input heading used by the alignment. [rad]
    mounting : ndarray, shape (4,) or None
        Declared ``q_bs``.
    """

    model: Model
    ctx: Context
    q_epochs: np.ndarray
    rest_ctx: Context
    align_time: float
    heading: float
    mounting: np.ndarray | None = None

    def initial_map(self, heading_sigma: float = 0.0):
        """Map of the sensor states, the levelling noise and δψ onto x0.

        Parameters
        ----------
        heading_sigma : float
            1σ of the input heading. [rad]

        Returns
        -------
        T_s : ndarray, shape (n, n - 10)
            ``x0`` per unit sensor state (identity on the sensor states, the
            levelling attitude error on ``δq``).
        T_noise : ndarray, shape (n, 3)
            Per unit specific-force noise averaged over the window.
        T_psi : ndarray, shape (n,)
            Per unit input heading error.
        P_res : ndarray, shape (n, n)
            Covariance of the second-order alignment residual
            (:func:`alignment_second_order`), on ``δq``.

        Notes
        -----
        ``δf^s = Cᵀ (F_{v,s} x_s)`` at rest (the velocity rows of F are
        ``C_b^n S_a``), ``φ0 = A [δf^s; δψ]`` (:func:`alignment_jacobian`)
        and ``δq0 = −½ R(q) φ0`` (:func:`covtool.nav.attitude.attitude_error_matrix`
        inverted on the unit-norm complement).  The accelerometer Markov
        states enter with their value at the end of the window, a ~T/(2τ)
        approximation of their window mean.
        """
        m = self.model
        n = m.n
        dyn = error_dynamics(m, self.rest_ctx)
        C = self.rest_ctx.C[0]
        Sf = C.T @ dyn.F[0, 3:6, 10:]                  # δf^s per sensor state
        q0 = self.rest_ctx.q[0]
        f0 = self.rest_ctx.f_b[0]
        Rq = -0.5 * quat.R_matrix(q0)                  # δq = Rq φ
        A = alignment_jacobian(f0, self.heading, self.mounting)
        T_s = np.zeros((n, n - 10))
        T_s[10:, :] = np.eye(n - 10)
        T_s[6:10, :] = Rq @ A[:, :3] @ Sf
        T_noise = np.zeros((n, 3))
        T_noise[6:10, :] = Rq @ A[:, :3]
        T_psi = np.zeros(n)
        T_psi[6:10] = Rq @ A[:, 3]
        cov_u = np.zeros((4, 4))
        cov_u[:3, :3] = Sf @ m.initial_covariance()[10:, 10:] @ Sf.T + np.eye(3) * m.vrw**2 / self.align_time
        cov_u[3, 3] = heading_sigma**2
        _, cov_r = alignment_second_order(f0, self.heading, self.mounting, cov_u)
        P_res = np.zeros((n, n))
        P_res[6:10, 6:10] = Rq @ cov_r @ Rq.T
        return T_s, T_noise, T_psi, P_res


@dataclass
class DifferenceModel:
    """Joint linear model of the two INS errors at the epochs.

    Attributes
    ----------
    t : ndarray, shape (J+1,)
        Comparison epochs. [s]
    names : list of str
        Joint state names (``main:…``, ``kimu:…``).
    n_main : int
        States of the main IMU (the KIMU's follow).
    Phi, Qd : ndarray, shape (J, n, n)
        Transition and process noise from epoch j to j+1 (block diagonal).
    Gamma : ndarray, shape (J, n, n_c)
        Response at epoch j+1 to a unit g-sensitive scale-factor
        coefficient of each candidate acting over epoch interval j.
    H : ndarray, shape (J+1, m, n)
        Map of the joint state onto the compared components of ``z``.
    P0 : ndarray, shape (n, n)
    R : ndarray, shape (m, m)
        Comparison noise (quantisation and algorithm differences).
    components : tuple of int
        Indices into :data:`DIFF_NAMES` of the compared components.
    candidates : tuple of (int, int)
        ``(gyro axis, accel axis)`` of every g-sensitivity hypothesis.
    Hphi : ndarray, shape (J+1, 2, 3, n), optional
        Maps of the joint state onto the attitude errors ``φ`` of main and
        KIMU, for the second-order term of the attitude difference
        (:class:`Whitener`).
    """

    t: np.ndarray
    names: list
    n_main: int
    Phi: np.ndarray
    Qd: np.ndarray
    Gamma: np.ndarray
    H: np.ndarray
    P0: np.ndarray
    R: np.ndarray
    components: tuple
    candidates: tuple
    Hphi: np.ndarray | None = None

    def __getstate__(self):
        """The fields only: the whitener's record of covariance steps (``_whitener_record``,
        :class:`covtool.dualnav.monitor.Whitener`) belongs to a live whitener of this process (a weak
        reference) and is recorded again by the first whitener of the copy."""
        state = dict(self.__dict__)
        state.pop("_whitener_record", None)
        return state

    @property
    def n(self) -> int:
        """Joint states."""
        return self.P0.shape[0]

    @property
    def m(self) -> int:
        """Compared components."""
        return len(self.components)

    def open_loop(self) -> np.ndarray:
        """Predicted covariance of the compared difference (open loop).

        ``P_z = H P Hᵀ + R`` with ``P`` propagated without any comparison:
        the envelope the difference should stay in.
        """
        P = self.P0
        out = np.empty((self.t.size, self.m, self.m))
        with np.errstate(over="ignore", invalid="ignore"):    # a blow-up is reported by the guard
            for j in range(self.t.size):
                out[j] = self.H[j] @ P @ self.H[j].T + self.R
                if j < self.t.size - 1:
                    P = predict(self.Phi[j], P, self.Qd[j])
        check_covariance(out, "dual-IMU open-loop difference", times=self.t,
                         names=[DIFF_NAMES[c] for c in self.components])
        return out


def discretize_difference(F, Qc, dt, Fc=None, chunk=200, nav=10):
    """Φ, Q_d and the fault response of every step, exploiting the structure.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
        Dynamics and noise PSD, constant over each step.
    dt : float
        Step. [s]
    Fc : ndarray, shape (N, n, n_c), optional
        Columns of constant augmented states (faults), navigation rows only.
    chunk : int
        Steps of the general fallback at once.
    nav : int
        Navigation states (the first ones).

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    Gamma : ndarray, shape (N, n, n_c)

    Notes
    -----
    A grade model is ``F = [[A, B], [0, D]]``: the navigation block ``A``
    driven by sensor states that are random constants, random walks or
    first-order Markov (``D`` diagonal, independent noise).  The faults are
    more random constants (zero rows, no noise), so the system augmented
    with them keeps that form and :func:`covtool.lincov.discretize.block_triangular`
    gives ``Φ``, ``Q_d`` and the fault response ``Γ = ∫_0^Δ Φ(Δ−u) F_c du``
    (the fault columns of the augmented ``Φ``) exactly, with its products
    done by blocks.  Any other structure falls back to the exact
    discretisation of the whole augmented system.
    """
    N, n, _ = F.shape
    nc = 0 if Fc is None else Fc.shape[-1]
    if nc:
        Fa = np.zeros((N, n + nc, n + nc))
        Fa[:, :n, :n] = F
        Fa[:, :n, n:] = Fc
        Qa = np.zeros_like(Fa)
        Qa[:, :n, :n] = Qc
    else:
        Fa, Qa = F, Qc
    what = "dual-IMU linear model"
    if is_block_triangular(Fa, Qa, nav):
        Phi, Qd = block_triangular(Fa, Qa, dt, nav, what=what)
    else:
        Phi = np.empty_like(Fa)
        Qd = np.empty_like(Fa)
        for a in range(0, N, chunk):
            b = min(N, a + chunk)
            Phi[a:b], Qd[a:b] = taylor(Fa[a:b], Qa[a:b], dt, what=what)
    return Phi[:, :n, :n], Qd[:, :n, :n], Phi[:, :n, n:]


def difference_model(main: ImuLinearization, kimu: ImuLinearization, *, t_epochs, lat_epochs, h_epochs,
                     substeps_per_epoch: int, dt_sub: float, heading_sigma: float, products=None,
                     candidates=(), components=tuple(range(9)), noise=None, extra_noise=None,
                     chunk: int = 200) -> DifferenceModel:
    """Linear model of the main − KIMU difference (seed 001 method II).

    Parameters
    ----------
    main, kimu : ImuLinearization
        The two IMUs along the flight (contexts of N = J·substeps_per_epoch
        propagation steps).
    t_epochs, lat_epochs, h_epochs : ndarray, shape (J+1,)
        Comparison epochs and the position there. [s], [rad], [m]
    substeps_per_epoch : int
        Propagation steps per comparison interval.
    dt_sub : float
        Propagation step. [s]
    heading_sigma : float
        1σ of the input heading both alignments share. [rad]
    products : ndarray, shape (N, 3, 3), optional
        Step means of ``ω_i f_j`` of the KIMU (``[i, j]``), the regressors
        of the g-sensitive scale-factor candidates. [rad/s · m/s²]
    candidates : sequence of (int, int)
        ``(gyro axis i, accel axis j)`` hypotheses.
    components : sequence of int
        Compared components (indices into :data:`DIFF_NAMES`).
    noise : array_like, shape (9,), optional
        1σ comparison noise per component (default zero).
    extra_noise : sequence of (str, int, ndarray, ndarray), optional
        ``(imu, epoch interval j, σ_φ (3,), σ_v (3,))``: white errors added
        by a bridged telemetry gap, sensor axes ([rad], [m/s]).
    chunk : int
        Steps discretised at once.

    Returns
    -------
    DifferenceModel

    Notes
    -----
    Each block is ``ẋ_i = F_i(t) x_i + w_i`` (:func:`covtool.lincov.dynamics.error_dynamics`
    along the IMU's own context), discretised by Van Loan per step and
    chained over the epoch interval.  The fault of candidate ``(i, j)``
    adds the column ``½ Q(q) e_i ⟨ω_i f_j⟩`` to the KIMU's quaternion rows
    (a g-sensitive scale factor is ``δω_i = k f_j ω_i``), discretised with
    the same exponential (the augmented state is a random constant with no
    noise).  ``z = H_main x_main − H_kimu x_kimu``.
    """
    cands = tuple((int(i), int(j)) for i, j in candidates)
    comps = tuple(int(c) for c in components)
    J = t_epochs.size - 1
    N = J * int(substeps_per_epoch)
    for imu, lin in (("main", main), ("kimu", kimu)):
        if lin.ctx.n != N:
            raise ValueError(f"{imu}: context has {lin.ctx.n} steps, expected {N}")
    if cands and (products is None or products.shape != (N, 3, 3)):
        raise ValueError(f"products must have shape ({N}, 3, 3) for the fault candidates")
    blocks = []
    k = int(substeps_per_epoch)
    for idx, lin in enumerate((main, kimu)):
        model = lin.model
        n = model.n
        dyn = error_dynamics(model, lin.ctx)
        Fc = None
        if idx == 1 and cands:
            halfQ = 0.5 * quat.Q_matrix(lin.ctx.q)                   # (N, 4, 3)
            Fc = np.zeros((N, n, len(cands)))
            for c, (i, j) in enumerate(cands):
                Fc[:, 6:10, c] = halfQ[:, :, i] * products[:, i, j][:, None]
        Phi_s, Qd_s, Gam_s = discretize_difference(dyn.F, dyn.Qc, dt_sub, Fc, chunk)
        nc = Gam_s.shape[-1]
        Phi, Qd = compose(Phi_s, Qd_s, np.arange(0, N + 1, k))        # chained over each epoch interval
        Gam = np.zeros((J, n, nc))
        for jj in range(J):
            G = np.zeros((n, nc))
            for s in range(jj * k, (jj + 1) * k):
                G = Phi_s[s] @ G + Gam_s[s]
            Gam[jj] = G
        blocks.append((Phi, Qd, Gam))
    nm, nk = main.model.n, kimu.model.n
    n = nm + nk
    Phi = np.zeros((J, n, n))
    Qd = np.zeros((J, n, n))
    Gamma = np.zeros((J, n, len(cands)))
    Phi[:, :nm, :nm], Qd[:, :nm, :nm] = blocks[0][0], blocks[0][1]
    Phi[:, nm:, nm:], Qd[:, nm:, nm:] = blocks[1][0], blocks[1][1]
    Gamma[:, nm:, :] = blocks[1][2]
    for imu, jj, s_phi, s_v in (extra_noise or ()):
        off = 0 if imu == "main" else nm
        lin = main if imu == "main" else kimu
        s = int(jj) * int(substeps_per_epoch)
        q = lin.ctx.q[min(s, N - 1)]
        G = 0.5 * quat.Q_matrix(q)
        C = quat.dcm(q)
        Qd[jj, off + 6:off + 10, off + 6:off + 10] += G @ np.diag(np.square(s_phi)) @ G.T
        Qd[jj, off + 3:off + 6, off + 3:off + 6] += C @ np.diag(np.square(s_v)) @ C.T
    # initial covariance: sensor states, levelling noise and the shared heading
    Ts_m, Tn_m, Tp_m, Pr_m = main.initial_map(heading_sigma)
    Ts_k, Tn_k, Tp_k, Pr_k = kimu.initial_map(heading_sigma)
    Ps_m = main.model.initial_covariance()[10:, 10:]
    Ps_k = kimu.model.initial_covariance()[10:, 10:]
    T = np.zeros((n, (nm - 10) + (nk - 10) + 7))
    c0 = 0
    T[:nm, c0:c0 + nm - 10] = Ts_m
    c0 += nm - 10
    T[nm:, c0:c0 + nk - 10] = Ts_k
    c0 += nk - 10
    T[:nm, c0:c0 + 3] = Tn_m
    T[nm:, c0 + 3:c0 + 6] = Tn_k
    T[:nm, c0 + 6] = Tp_m
    T[nm:, c0 + 6] = Tp_k
    Su = np.zeros((T.shape[1], T.shape[1]))
    Su[:nm - 10, :nm - 10] = Ps_m
    Su[nm - 10:nm + nk - 20, nm - 10:nm + nk - 20] = Ps_k
    for lin, a in ((main, c0), (kimu, c0 + 3)):
        Su[a:a + 3, a:a + 3] = np.eye(3) * lin.model.vrw**2 / lin.align_time
    Su[c0 + 6, c0 + 6] = heading_sigma**2
    P0 = T @ Su @ T.T
    P0[:nm, :nm] += Pr_m
    P0[nm:, nm:] += Pr_k
    P0 = symmetrize(P0)
    H = np.zeros((J + 1, len(comps), n))
    Hphi = np.zeros((J + 1, 2, 3, n))
    for jj in range(J + 1):
        rows_m = nav_error_matrix(main.q_epochs[jj], lat_epochs[jj], h_epochs[jj])
        rows_k = nav_error_matrix(kimu.q_epochs[jj], lat_epochs[jj], h_epochs[jj])
        H[jj, :, :10] = rows_m[list(comps)]
        H[jj, :, nm:nm + 10] = -rows_k[list(comps)]
        Hphi[jj, 0, :, :10] = rows_m[6:9]
        Hphi[jj, 1, :, nm:nm + 10] = rows_k[6:9]
    sig = np.zeros(9) if noise is None else np.asarray(noise, float)
    R = np.diag(sig[list(comps)] ** 2)
    names = [f"main:{s}" for s in main.model.names] + [f"kimu:{s}" for s in kimu.model.names]
    return DifferenceModel(np.asarray(t_epochs, float), names, nm, Phi, Qd, Gamma, H, P0, R, comps, cands, Hphi)
