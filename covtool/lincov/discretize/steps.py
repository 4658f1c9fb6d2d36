"""Stacks of steps: validation, repeated steps and the Q_d check.

:class:`StepInfo` (how each step was discretised), :func:`repeated_steps`
(runs of equal ``(F, Q_c, Δt)`` computed once), the shape/finiteness checks
of the inputs that name the offending step, and :func:`check_qd`, the PSD
check (correlation scaling) of every exact ``Q_d`` of Van Loan's integral
(seed 002, eq (6c)–(6d)).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.discretize.limits import PSD_TOL  # noqa: F401 - re-exported


@dataclass(frozen=True)
class StepInfo:
    """How each step of a stack was discretised.

    Attributes
    ----------
    terms : ndarray of int, shape (N,)
        Terms ``N_t`` of the series eq (6b)–(6d) at the base step
        (``i = 0 … N_t−1``).
    squarings : ndarray of int, shape (N,)
        ``s``: the step was computed over ``Δt/2^s`` and doubled ``s`` times.
    norm_dt : ndarray, shape (N,)
        ``νΔt`` with ``ν = max(‖F̃‖₁, ‖F̃‖_∞)`` of the balanced ``F``. [-]
    """

    terms: np.ndarray
    squarings: np.ndarray
    norm_dt: np.ndarray


# ---------------------------------------------------------------------------
# helpers


def repeated_steps(*stacks):
    """Steps equal to their predecessor in every stack: ``(first, inverse)``.

    Parameters
    ----------
    *stacks : ndarray, shape (N, ...)
        Per-step inputs (``F``, ``Q_c``, ``Δt``, ...), broadcast views allowed.

    Returns
    -------
    first : ndarray of int, shape (M,)
        Steps that differ from the one before (step 0 always).
    inverse : ndarray of int, shape (N,)
        ``first[inverse[k]]`` has exactly the inputs of step ``k``.

    Notes
    -----
    At a stop the vehicle's state, hence ``F`` and ``Q_c``, repeats step
    after step (726 of the flagship's 1800 steps): a discretisation is a
    function of its step's inputs alone, so computing each run of equal
    steps once is exact.  Non-finite entries never compare equal, so a bad
    step is always computed (and reported) itself.
    """
    N = np.shape(stacks[0])[0]
    same = np.ones(max(N - 1, 0), bool)
    for X in stacks:
        X = np.asarray(X)
        X = X.reshape(N, -1) if X.ndim != 1 else X[:, None]
        same &= (X[1:] == X[:-1]).all(axis=1)
    head = np.r_[True, ~same] if N else np.zeros(0, bool)
    return np.flatnonzero(head), np.cumsum(head) - 1


def _dedup(fn, F, others, dt, times, expand):
    """``fn(F, *others, dt, times)`` computed on the distinct steps only, then expanded (exact).

    ``others`` are ``(array, per-step ndim)`` pairs: a stack of the same
    length as ``F``, or one per-step value shared by every step.  A
    step that fails is recomputed on the full stack, so that the error
    names the step of the caller's grid.
    """
    F = np.asarray(F, float)
    if F.ndim != 3 or F.shape[0] < 2:
        return fn(F, *(o for o, _ in others), dt, times)
    N = F.shape[0]
    try:
        dtb = np.broadcast_to(np.asarray(dt, float), (N,))
        oth = [np.broadcast_to(np.asarray(o, float), (N,) + np.shape(o)) if np.ndim(o) == nd
               else np.asarray(o, float) for o, nd in others]
        if any(o.shape[0] != N for o in oth):
            return fn(F, *(o for o, _ in others), dt, times)
    except ValueError:
        return fn(F, *(o for o, _ in others), dt, times)
    first, inv = repeated_steps(F, *oth, dtb)
    if first.size > 0.9 * N:
        return fn(F, *(o for o, _ in others), dt, times)
    tm = None if times is None else np.broadcast_to(np.asarray(times, float), (N,))[first]
    try:
        out = fn(F[first], *(o[first] for o in oth), dtb[first], tm)
    except (NumericalError, ValueError):
        return fn(F, *(o for o, _ in others), dt, times)
    return expand(out, inv)


def _step_where(what, k, dt, times):
    t = f"t = {times[k]:.6g} s, " if times is not None else ""
    return f"{what + ': ' if what else ''}step {k} ({t}Δt = {dt[k]:.6g} s)"


def _prepare(F, Qc, dt, what, times):
    F = np.asarray(F, float)
    if F.ndim != 3 or F.shape[1] != F.shape[2]:
        raise ValueError(f"F must have shape (N, n, n), got {F.shape}")
    N, n, _ = F.shape
    Qc = None if Qc is None else np.broadcast_to(np.asarray(Qc, float), F.shape)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    if times is not None:
        times = np.broadcast_to(np.asarray(times, float), (N,))
    for name, X in (("F", F), ("Q_c", Qc)):
        if X is None:
            continue
        bad = ~np.isfinite(X).all(axis=(1, 2))
        if bad.any():
            raise NumericalError(f"{_step_where(what, int(np.argmax(bad)), dt, times)}: {name} has non-finite entries")
    bad = ~(np.isfinite(dt) & (dt >= 0))
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{_step_where(what, k, dt, times)}: the step must be finite and non-negative")
    if Qc is None:                                      # a caller without Q_c (per_source)
        return F, None, dt, times
    Qs = Qc + np.swapaxes(Qc, 1, 2)
    Qs *= 0.5
    return F, Qs, dt, times


def _check_result(Phi, Qd, dt, info, what, times, psd):
    bad = ~(np.isfinite(Phi).all(axis=(1, 2)) & np.isfinite(Qd).all(axis=(1, 2)))
    if bad.any():
        k = int(np.argmax(bad))
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Φ or Q_d overflows (νΔt = "
                             f"{info.norm_dt[k]:.4g}: an unstable mode grows beyond the floating-point "
                             "range over this step); use shorter steps or a shorter span")
    if psd:
        check_qd(Qd, what, dt=dt, times=times)


def check_qd(Qd: np.ndarray, what: str = "", *, dt=None, times=None, tol: float = PSD_TOL) -> None:
    """Raise if a stack of ``Q_d`` is not PSD within ``tol``.

    Parameters
    ----------
    Qd : ndarray, shape (N, n, n)
    what : str
        Names the computation in the message.
    dt, times : ndarray, shape (N,), optional
        Step lengths and start times, for the message. [s]
    tol : float
        Tolerance on the smallest eigenvalue of the correlation-scaled
        ``Q_d`` (a Cholesky factorisation of ``R + tol·I``, cheap for stacks).

    Raises
    ------
    NumericalError
        Naming the first failing step.
    """
    N, n, _ = Qd.shape
    dg = np.einsum("kii->ki", Qd)
    neg = (dg < -tol * np.maximum(np.max(np.abs(dg), axis=1, keepdims=True), np.finfo(float).tiny)).any(axis=1)
    sd = np.sqrt(np.clip(dg, 0.0, None))
    s = np.where(sd > 0, sd, 1.0)
    R = np.divide(Qd, s[:, :, None])
    R /= s[:, None, :]                                  # (Q_ij / s_i) / s_j, in place: no second stack
    idx = np.arange(n)
    R[:, idx, idx] = np.where(sd > 0, 1.0, 0.0) + tol
    try:
        np.linalg.cholesky(R)
        ok = ~neg
    except np.linalg.LinAlgError:
        ok = np.array([_chol_ok(R[k]) for k in range(N)]) & ~neg
    if not ok.all():
        k = int(np.argmax(~ok))
        dt = np.broadcast_to(np.nan if dt is None else np.asarray(dt, float), (N,))
        w = np.linalg.eigvalsh(0.5 * (R[k] + R[k].T)).min() - tol
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Q_d is not positive semi-definite "
                             f"(smallest eigenvalue of its correlation matrix {w:.3g})")


def _chol_ok(A):
    try:
        np.linalg.cholesky(A)
        return True
    except np.linalg.LinAlgError:
        return False


def _expand_phi_qd(out, inv):
    Phi, Qd, inf = out
    return Phi[inv], Qd[inv], StepInfo(inf.terms[inv], inf.squarings[inv], inf.norm_dt[inv])


def on_grid(e: Exception, first: int) -> None:
    """Renumber, in place, the steps ``e`` names from a chunk starting at step ``first`` to the whole grid.

    A discretisation error names its step as ``step k (t = …`` within its
    input (:func:`covtool.lincov.discretize.steps.repeated_steps` keeps the
    caller's numbering); every such mention in the message (its ``args``,
    and an :class:`~covtool.errors.InputError`'s ``problem``) is shifted
    by ``first``.  Nothing else is changed; the error keeps its traceback.
    """
    if not first:
        return

    def shift(text):
        return re.sub(r"\bstep (\d+) \(", lambda m: f"step {int(m.group(1)) + first} (", text)

    e.args = tuple(shift(a) if isinstance(a, str) else a for a in e.args)
    if isinstance(getattr(e, "problem", None), str):
        e.problem = shift(e.problem)
