"""The batched engine equals the step-by-step reference (seed 002, eq (6)-(8), (15)-(16))."""

from __future__ import annotations

import numpy as np
import pytest

import covtool
from covtool.lincov.reference import propagate_with_filter
from covtool.lincov.batch import System, compose, events, run_batch, sandwich
from covtool.lincov.reduced import zupt_matrices
from covtool.nav.attitude import attitude_error_matrix


def test_sandwich_equals_per_case_products():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((7, 7))
    P = rng.standard_normal((5, 7, 7))
    np.testing.assert_allclose(sandwich(A, P), A @ P @ A.T, rtol=1e-12, atol=1e-12)


def test_compose_equals_stepwise_propagation():
    rng = np.random.default_rng(1)
    Phi = np.eye(4) + 0.05 * rng.standard_normal((30, 4, 4))
    L = rng.standard_normal((30, 4, 4))
    Qd = 1e-3 * L @ np.swapaxes(L, 1, 2)
    P = np.eye(4)
    for k in range(30):
        P = Phi[k] @ P @ Phi[k].T + Qd[k]
    ev = np.array([0, 11, 30])
    Pc, Qc = compose(Phi, Qd, ev)
    P2 = np.eye(4)
    for i in range(2):
        P2 = Pc[i] @ P2 @ Pc[i].T + Qc[i]
    np.testing.assert_allclose(P2, P, rtol=1e-12)


def _physical(P, q):
    """Nav block in physical coordinates (tilt/azimuth instead of δq; norm direction dropped)."""
    T = np.zeros(q.shape[:1] + (9, 10))
    T[:, :6, :6] = np.eye(6)
    T[:, 6:, 6:] = attitude_error_matrix(q)
    return T @ P @ np.swapaxes(T, -1, -2)


@pytest.fixture(scope="module")
def setup():
    from covtool.studies.zupt_setup import setup as zsetup
    import tomllib
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "studies" / "zupt_filter_order.toml"
    d = tomllib.loads(path.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    return zsetup(d, path=path)


@pytest.mark.parametrize("case", ["B1", "D"])
def test_batched_engine_equals_stepwise_reference(setup, case):
    """run_batch over scaled cases equals propagate_with_filter with the same scaled inputs.

    Cases: nominal, P_f(0)×10, Q_f×0.1, R_f×100.  Compared in physical
    coordinates, relative to sqrt(P_ii P_jj): ≤ 1e-8.
    """
    S = setup
    fm, Phi_f, Qd_f = S.filter_model(case)
    Hf = zupt_matrices(fm.names)
    Rf = S.filter_R(case)
    scales = [(1, 1, 1), (10, 1, 1), (1, 0.1, 1), (1, 1, 100)]
    N = len(S.t) - 1
    rec = np.arange(0, N + 1, 30)
    ev = events(N, S.update_steps, rec)
    truth = System.from_steps(S.Phi, S.Qd, ev)
    filt = System.from_steps(Phi_f, Qd_f, ev)
    B = len(scales)
    res = run_batch(truth, S.P0, S.H, S.R, fm.D, S.update_steps, rec, filt=filt,
                    Pf0=np.stack([s[0] * fm.P0 for s in scales]), Hf=Hf,
                    Rf=np.stack([s[2] * Rf for s in scales]), q_scale=np.array([s[1] for s in scales]))
    q = S.nodes.q_nb[rec]
    for b, (sp, sq, sr) in enumerate(scales):
        ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, sq * Qd_f, sp * fm.P0, S.H, Hf, fm.D, S.R,
                                    S.update_steps, Rf=sr * Rf)
        a = _physical(res.P_truth[b], q)
        r = _physical(ref.P_truth[rec][:, :10, :10], q)
        d = np.sqrt(np.einsum("kii->ki", r))
        rel = np.abs(a - r) / (d[:, :, None] * d[:, None, :] + 1e-300)
        assert rel.max() < 1e-8, (case, b, rel.max())


def test_fixed_gains_reproduce_the_running_filter(setup):
    """Replaying recorded gains (error-budget mode) reproduces the truth covariance exactly."""
    S = setup
    fm, Phi_f, Qd_f = S.filter_model("B1")
    Hf = zupt_matrices(fm.names)
    N = len(S.t) - 1
    rec = [N]
    ev = events(N, S.update_steps, rec)
    truth = System.from_steps(S.Phi, S.Qd, ev)
    filt = System.from_steps(Phi_f, Qd_f, ev)
    run = run_batch(truth, S.P0, S.H, S.R, fm.D, S.update_steps, rec, filt=filt, Pf0=fm.P0[None], Hf=Hf,
                    Rf=S.filter_R("B1")[None])
    fixed = run_batch(truth, S.P0[None], S.H, S.R, fm.D, S.update_steps, rec, gains=run.gains)
    np.testing.assert_allclose(fixed.P_truth, run.P_truth, rtol=1e-12, atol=1e-30)
