"""Dynamic-block propagation and composition of the batched engine (issue 13): exact against dense products."""

from __future__ import annotations

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.lincov.batch import compose, dynamic_states, events, run_batch, sandwich, System


def _structured(rng, K, n, d):
    """K transitions with identity rows outside ``d`` (random constants) and noise in the ``d`` block only."""
    Phi = np.broadcast_to(np.eye(n), (K, n, n)).copy()
    Phi[:, d, :] = rng.normal(0.0, 0.3, (K, d.size, n))
    G = rng.normal(size=(K, d.size, d.size))
    Q = np.zeros((K, n, n))
    Q[:, d[:, None], d[None, :]] = G @ np.swapaxes(G, 1, 2)
    return Phi, Q


def _dense_compose(Phi, Qd, ev):
    """The composition of the engine's docstring, one dense product per step (independent loop)."""
    out_P, out_Q = [], []
    for a, b in zip(ev[:-1], ev[1:]):
        A, Q = np.eye(Phi.shape[1]), np.zeros(Phi.shape[1:])
        for k in range(a, b):
            A = Phi[k] @ A
            Q = Phi[k] @ Q @ Phi[k].T + Qd[k]
        out_P.append(A)
        out_Q.append(Q)
    return np.array(out_P), np.array(out_Q)


def test_dynamic_states_finds_the_identity_rows():
    rng = np.random.default_rng(1)
    d = np.array([0, 1, 2, 7, 8, 11])
    Phi, _ = _structured(rng, 5, 12, d)
    dd, c = dynamic_states(Phi)
    assert np.array_equal(dd, d) and np.array_equal(c, np.setdiff1d(np.arange(12), d))
    Phi[3, 5, 4] = 1e-300                     # one non-zero off-diagonal entry in one step: state 5 is dynamic
    assert 5 in dynamic_states(Phi)[0]
    assert dynamic_states(Phi, fraction=0.5) is None          # 7 of 12 dynamic: the split does not pay
    assert dynamic_states(rng.normal(size=(3, 4, 4))) is None


def test_sandwich_of_the_dynamic_block_equals_the_dense_product():
    """(A P Aᵀ) with identity rows: the block formula of the docstring against the plain product, ≤ 1e-13."""
    rng = np.random.default_rng(2)
    n, d = 20, np.array([0, 3, 4, 9, 15])
    Phi, _ = _structured(rng, 1, n, d)
    X = rng.normal(size=(4, n, n))
    P = X @ np.swapaxes(X, 1, 2)
    got = sandwich(Phi[0], P, dynamic_states(Phi))
    want = np.array([Phi[0] @ p @ Phi[0].T for p in P])
    s = np.sqrt(np.einsum("kii->ki", want))
    assert np.max(np.abs(got - want) / (s[:, :, None] * s[:, None, :])) <= 1e-13
    c = np.setdiff1d(np.arange(n), d)
    assert np.array_equal(got[:, c[:, None], c[None, :]], P[:, c[:, None], c[None, :]])   # P_cc untouched, exactly


def test_compose_of_the_dynamic_block_equals_the_dense_composition():
    rng = np.random.default_rng(3)
    n, d = 16, np.array([1, 2, 5, 6, 10])
    Phi, Qd = _structured(rng, 40, n, d)
    Phi *= 0.9                                # keep the products bounded
    Phi[:, np.setdiff1d(np.arange(n), d)] = np.eye(n)[np.setdiff1d(np.arange(n), d)]
    ev = np.array([0, 1, 7, 8, 25, 40])       # intervals of 1 to 17 steps
    got_P, got_Q = compose(Phi, Qd, ev)
    want_P, want_Q = _dense_compose(Phi, Qd, ev)
    assert np.max(np.abs(got_P - want_P)) <= 1e-13 * np.abs(want_P).max()
    assert np.max(np.abs(got_Q - want_Q)) <= 1e-12 * np.abs(want_Q).max()
    Qd[:, 0, 0] = 1.0                         # noise on a constant state: the dense path, same result
    got_P, got_Q = compose(Phi, Qd, ev)
    want_P, want_Q = _dense_compose(Phi, Qd, ev)
    assert np.max(np.abs(got_Q - want_Q)) <= 1e-12 * np.abs(want_Q).max()



@pytest.mark.parametrize("block", [None, 1.0])
def test_compose_of_uneven_intervals_in_any_order_equals_the_dense_composition(block, monkeypatch):
    """Intervals of 1–13 steps in no order of length, a grid from step 3 to 38, both paths of compose.

    ``compose`` advances the intervals longest first and gathers their steps'
    operands in blocks of ``_COMPOSE_BLOCK`` bytes (``block = 1.0``: one step
    position per block); the results come back in interval order, equal to the
    independent per-interval loop to 1e-13 (Φ) and 1e-12 (Q) of their scale,
    and equal bit for bit whatever the block size.
    """
    import covtool.lincov.batch as batch

    rng = np.random.default_rng(5)
    n, d = 16, np.array([0, 3, 4, 9, 15])
    Phi, Qd = _structured(rng, 40, n, d)
    Phi *= 0.9
    const = np.setdiff1d(np.arange(n), d)
    Phi[:, const] = np.eye(n)[const]
    ev = np.array([3, 4, 17, 19, 20, 26, 38])     # lengths 1, 13, 2, 1, 6, 12
    ref = {}
    for dense in (False, True):
        Q = Qd.copy()
        if dense:
            Q[:, 1, 1] = 1.0                     # noise on a constant state: the dense path
        ref[dense] = compose(Phi, Q, ev)
        if block is not None:
            monkeypatch.setattr(batch, "_COMPOSE_BLOCK", block)
        got_P, got_Q = compose(Phi, Q, ev)
        monkeypatch.undo()
        want_P, want_Q = _dense_compose(Phi, Q, ev)
        assert np.max(np.abs(got_P - want_P)) <= 1e-13 * np.abs(want_P).max()
        assert np.max(np.abs(got_Q - want_Q)) <= 1e-12 * np.abs(want_Q).max()
        np.testing.assert_array_equal(got_P, ref[dense][0])
        np.testing.assert_array_equal(got_Q, ref[dense][1])

def _blowing_up():
    """Two cases on a 3-state system whose Φ grows P by 1e200 per interval; case 1 starts at P = 0."""
    n, K = 3, 6
    Phi = np.broadcast_to(np.eye(n), (K, n, n)).copy()
    Phi[:, 0, 0] = 1e100
    sys_ = System(np.arange(K + 1), Phi, np.zeros((K, n, n)))
    P0 = np.zeros((2, n, n))
    P0[0] = np.eye(n)
    H = np.zeros((1, n))
    H[0, 1] = 1.0
    return sys_, P0, H


def test_deferred_record_guard_flags_the_first_bad_record():
    """The record guard is batched; a case is still flagged at its first bad record, NaN from there on."""
    sys_, P0, H = _blowing_up()
    r = run_batch(sys_, P0, H, np.eye(1), np.zeros((3, 0)), [], np.arange(7), gains=np.zeros((1, 0, 0, 1)),
                  keep=slice(0, 3), on_invalid="flag", label="blow-up")
    # P_00 = 1e200 after one interval, inf after two: the first bad record is step 2
    assert r.status[1] == "" and np.all(np.isfinite(r.P_truth[1]))
    assert r.status[0].startswith("blow-up (case 0): truth at step 2 (it passed the guard at step 1): ")
    assert np.all(np.isfinite(r.P_truth[0, :2])) and np.all(np.isnan(r.P_truth[0, 2:]))
    with pytest.raises(NumericalError, match=r"^blow-up \(case 0\): truth at step 2 \(it passed the guard at step 1\)"):
        run_batch(sys_, P0, H, np.eye(1), np.zeros((3, 0)), [], np.arange(7), gains=np.zeros((1, 0, 0, 1)),
                  keep=slice(0, 3), label="blow-up")



def test_record_guard_over_several_batches_of_records_flags_the_first_bad_one():
    """More records than one batch of the deferred guard (``RECORD_CHECKS``): the slots are reused.

    Case 0 grows by 2⁸ per interval in state 0 (P_00 = 2^(16k), exact) and
    overflows at record 64 (2^1024), in the third batch; case 1 starts at
    P = 0 and stays at 0.  Every record before the overflow holds its exact
    value, none after.
    """
    from covtool.lincov.batch import RECORD_CHECKS

    n, K = 3, 5 * RECORD_CHECKS + 10
    Phi = np.broadcast_to(np.eye(n), (K, n, n)).copy()
    Phi[:, 0, 0] = 2.0 ** 8
    sys_ = System(np.arange(K + 1), Phi, np.zeros((K, n, n)))
    P0 = np.zeros((2, n, n))
    P0[0] = np.eye(n)
    H = np.zeros((1, n))
    H[0, 1] = 1.0
    r = run_batch(sys_, P0, H, np.eye(1), np.zeros((3, 0)), [], np.arange(K + 1), gains=np.zeros((1, 0, 0, 1)),
                  keep=slice(0, 3), on_invalid="flag", label="blow-up")
    first = 64
    assert r.status[1] == "" and np.all(r.P_truth[1] == 0.0)
    assert r.status[0].startswith(f"blow-up (case 0): truth at step {first} (it passed the guard at step "
                                  f"{first - 1}): ")
    np.testing.assert_array_equal(r.P_truth[0, :first, 0, 0], 2.0 ** (16 * np.arange(first)))
    np.testing.assert_array_equal(r.P_truth[0, :first, 1:, 1:], np.broadcast_to(np.eye(2), (first, 2, 2)))
    assert np.all(np.isnan(r.P_truth[0, first:]))

def test_batch_on_the_event_grid_equals_the_step_by_step_reference():
    """Dynamic-block engine with records every 10 steps against propagate_with_filter (≤ 1e-10)."""
    from covtool.lincov.reference import propagate_with_filter

    rng = np.random.default_rng(4)
    n, d, N = 12, np.array([0, 1, 2, 3, 6]), 60
    Phi, Qd = _structured(rng, N, n, d)
    Phi[:, d[:, None], d[None, :]] *= 0.5
    Phi[:, d[:, None], d[None, :]] += 0.5 * np.eye(d.size)
    X = rng.normal(size=(n, n))
    P0 = X @ X.T + np.eye(n)
    H = np.zeros((2, n))
    H[0, 1] = H[1, 2] = 1.0
    R = 0.1 * np.eye(2)
    upd = [5, 17, 33, 48]
    rec = np.arange(0, N + 1, 10)
    ref = propagate_with_filter(Phi, Qd, P0, Phi, Qd, P0, H, H, np.eye(n), R, upd)
    ev = events(N, upd, rec)
    sys_ = System.from_steps(Phi, Qd, ev)
    assert sys_.dynamic is not None
    r = run_batch(sys_, P0[None], H, R, np.eye(n), upd, rec, filt=sys_, Pf0=P0[None], Hf=H, Rf=R[None],
                  keep=slice(0, n))
    want = ref.P_truth[rec]
    s = np.sqrt(np.einsum("kii->ki", want))
    assert np.max(np.abs(r.P_truth[0] - want) / (s[:, :, None] * s[:, None, :])) <= 1e-10


def test_record_steps_are_the_history_rows_and_the_report_steps():
    """The flagship records what history.csv writes (multiples of history_every, the last) and the reports."""
    from covtool.studies.zupt_filter_order import record_steps
    from covtool.studies.zupt_setup import history_records

    t = np.r_[np.arange(0.0, 95.0, 1.0), 94.5]              # a shortened last step
    rec = record_steps(t, 10.0, [37])
    assert np.array_equal(rec, [0, 10, 20, 30, 37, 40, 50, 60, 70, 80, 90, t.size - 1])
    assert np.array_equal(record_steps(t, None, []), np.arange(t.size))
    n_rec, n_int = history_records(t.size - 1, 1.0, 10.0, [37.0], updates=3)
    assert rec.size <= n_rec and n_int >= rec.size - 1 + 3 - 1        # upper counts
