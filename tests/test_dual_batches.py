"""The dual-IMU study's batches share work without changing a number (issue 13, acceptance 3).

* the Whitener's data-independent covariance side is recorded by the first
  Whitener of a difference model and replayed by the next ones: bitwise the
  same innovations as a Whitener that computes everything itself;
* the flight's exact increments are sampled once for all the simulators of
  one motion (``ImuSimulator(truth_cache=...)``): bitwise the same records;
* the batches after the first run in a forked child and the parent at once:
  bitwise the same study as one process running them in order.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from covtool.dualnav.difference import DifferenceModel
from covtool.dualnav.monitor import Whitener
from covtool.io.flight import high_dynamics_flight
from covtool.nav.imu.simulator import ImuSimulator
from covtool.nav.imu.vibration import Tone, Vibration
from covtool.studies import run_study

from test_dualnav import short_decl   # tests/ is on sys.path (pytest prepend import mode)


def _model(seed=0, J=12, n_main=10, n_kimu=10):
    """A random, valid joint model with velocity and attitude compared (second-order term on)."""
    rng = np.random.default_rng(seed)
    n = n_main + n_kimu
    comps = (3, 4, 5, 6, 7, 8)
    m = len(comps)

    def psd(k, scale):
        A = rng.normal(0, scale, (k, n, n))
        return A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(n)

    t = np.arange(J + 1) * 1.0
    Phi = np.eye(n) + rng.normal(0, 0.05, (J, n, n))
    Qd = psd(J, 0.01)
    H = rng.normal(0, 1, (J + 1, m, n))
    Hphi = rng.normal(0, 0.01, (J + 1, 2, 3, n))
    P0 = psd(1, 0.1)[0]
    Gamma = rng.normal(0, 1, (J, n, 2))
    names = [f"main:s{i}" for i in range(n_main)] + [f"kimu:s{i}" for i in range(n_kimu)]
    return DifferenceModel(t, names, n_main, Phi, Qd, Gamma, H, P0, 1e-2 * np.eye(m), comps, ((2, 0), (1, 1)),
                           Hphi)


def _whiten(model, z, steps=None):
    """Whiten z (M, J+1, m) with feedback of the navigation estimates, the way run_dual does."""
    w = Whitener(model, z.shape[0])
    for j in range(model.t.size):
        w.update(j, z[:, j])
        w.take_navigation()
        if j < model.t.size - 1:
            w.predict(j)
    return w


def test_whitener_replays_its_record_bitwise():
    m = _model()
    z = np.random.default_rng(1).normal(0, 1, (5, m.t.size, m.m))
    first = _whiten(m, z)                                        # records
    assert len(m._whitener_record.steps) == 2 * m.t.size - 1
    z2 = np.random.default_rng(2).normal(0, 1, (7, m.t.size, m.m))
    again = _whiten(m, z2)                                       # replays the record
    assert again._replay
    copy_ = dataclasses.replace(m)
    assert not hasattr(copy_, "_whitener_record")                # a copy has no record: computes everything
    fresh = _whiten(copy_, z2)
    for name in ("nu", "S", "nis", "rho", "P", "mu", "x"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name), err_msg=name)
    # the replayed innovations are those of these data, not of the recording run
    assert not np.array_equal(again.nu[:5], first.nu)
    assert np.isfinite(again.nis).all() and (again.nis > 0).all()


def test_a_model_with_a_record_pickles_without_it_and_whitens_the_same():
    """The record holds a weak reference to a live Whitener: a pickled model leaves it out (the figure
    server receives the dual-IMU runs, issue 13); the copy records again and whitens bitwise the same."""
    import pickle

    m = _model(seed=5)
    z = np.random.default_rng(6).normal(0, 1, (4, m.t.size, m.m))
    ref = _whiten(m, z)                                          # records
    assert hasattr(m, "_whitener_record")
    back = pickle.loads(pickle.dumps(m))
    assert not hasattr(back, "_whitener_record") and hasattr(m, "_whitener_record")
    for f in dataclasses.fields(m):
        a, b = getattr(m, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(b, a, err_msg=f.name)
        else:
            assert b == a, f.name
    w = _whiten(back, z)
    assert len(back._whitener_record.steps) == 2 * m.t.size - 1
    for name in ("nu", "S", "nis", "rho", "P", "mu", "x"):
        np.testing.assert_array_equal(getattr(w, name), getattr(ref, name), err_msg=name)


def test_whitener_departing_from_the_record_computes_its_own():
    """A Whitener that takes other steps than the record (an epoch skipped) is not given the recorded P."""
    m = _model(seed=3)
    z = np.random.default_rng(4).normal(0, 1, (3, m.t.size, m.m))
    _whiten(m, z)                                                # the record: update 0, predict 0, update 1, …
    w = Whitener(m, 3)
    w.update(0, z[:, 0])
    w.predict(0)
    w.predict(1)                                                 # skips the update of epoch 1
    assert not w._replay
    ref = Whitener(dataclasses.replace(m), 3)
    ref.update(0, z[:, 0])
    ref.predict(0)
    ref.predict(1)
    np.testing.assert_array_equal(w.P, ref.P)
    # and the recorded P after the update of epoch 1 would differ from it
    recorded = m._whitener_record.steps[3][2][0]
    assert not np.allclose(w.P, recorded)


class _Counting:
    """A trajectory that counts its ``sample`` calls."""

    def __init__(self, traj):
        self._traj = traj
        self.calls = 0

    def sample(self, t):
        self.calls += 1
        return self._traj.sample(t)

    def __getattr__(self, name):
        return getattr(self._traj, name)


def test_truth_cache_samples_the_flight_once_with_the_same_increments():
    traj = _Counting(high_dynamics_flight())
    kw = dict(t0=12.0, duration=3.0, n_runs=2, mounting=[0.9998, 0.01, -0.01, 0.015], nodes=4, chunk=100)
    plain = ImuSimulator(traj, 400.0, **kw).record()
    calls_plain = traj.calls
    cache = {}
    first = ImuSimulator(traj, 400.0, truth_cache=cache, **kw).record()
    calls_first = traj.calls - calls_plain
    second = ImuSimulator(traj, 400.0, truth_cache=cache, **kw).record()
    assert calls_first == 12 and traj.calls - calls_plain == calls_first     # 1200 samples in 12 chunks, once
    for rec in (first, second):
        np.testing.assert_array_equal(rec.dtheta, plain.dtheta)
        np.testing.assert_array_equal(rec.dv, plain.dv)
    # another rate (or mounting) is another entry, not a wrong hit
    other = ImuSimulator(traj, 100.0, truth_cache=cache, **kw).record()
    assert other.dtheta.shape[1] == 300 and len(cache) == 15
    # the cached arrays cannot be changed by a consumer
    with pytest.raises(ValueError, match="read-only"):
        next(iter(cache.values()))[0][0, 0, 0] = 1.0


def test_truth_cache_refuses_a_vibration_realisation():
    vib = Vibration((Tone("angular", "x", 1e-4, 30.0),))
    with pytest.raises(ValueError, match=r"^truth_cache cannot be shared with a vibration realisation "
                                         r"\(random per simulator\)$"):
        ImuSimulator(high_dynamics_flight(), 400.0, t0=12.0, duration=1.0, vibration=vib, truth_cache={})


def test_forked_batches_equal_one_process(monkeypatch):
    """Four batches: the first, then one in the parent and two in a forked child, as one process would."""
    decl = short_decl(runs=9, fault_runs=3, gaps=True)
    decl["simulation"]["batch"] = 3
    forked = run_study(copy.deepcopy(decl))
    monkeypatch.setattr("covtool.studies.dual_imu.os.cpu_count", lambda: 1)
    serial = run_study(copy.deepcopy(decl))
    for name in ("fault_free_runs", "fault_runs", "candidates", "history", "gaps"):
        a, b = forked.tables[name], serial.tables[name]
        assert a.shape[0] > 0 and a.equals(b), name
    s_a, s_b = forked.tables["summary"], serial.tables["summary"]
    keep = s_a["item"] != "wall time"
    assert s_a[keep].equals(s_b[keep])
    assert len(forked.fault_free) == 3 and len(forked.fault) == 1
    assert all(r.model is forked.fault_free[0].model for r in forked.fault_free + forked.fault)
    # the window figure: one line collection per group, a segment per flight, the curves as computed
    import matplotlib
    matplotlib.use("Agg")
    fig = forked.figures["window_test"]()
    ax = fig.axes[0]
    groups = {c.get_label(): c.get_segments() for c in ax.collections}
    assert [len(groups[k]) for k in ("fault-free", "g-sensitivity injected")] == [9, 3]
    r = forked.fault_free[2]
    np.testing.assert_array_equal(groups["fault-free"][6][:, 1], r.window_stat[0])
    assert ax.get_ylim()[1] >= max(s[:, 1].max() for s in groups["fault-free"])
    import matplotlib.pyplot as plt
    plt.close(fig)


def test_compiled_quantisation_pulse_counts_half_to_even():
    """c = r + Σx: 0.5, 1.0, 1.5, 2.0, 2.75 LSB → counts 0, 1, 2, 2, 3 (halves to even); remainder −0.25 LSB."""
    from covtool.nav.imu.simulator import _quantize

    lsb = 0.25
    x = np.zeros((2, 5, 3))
    x[0, :, 0] = np.array([0.5, 0.5, 0.5, 0.5, 0.75]) * lsb
    x[1, :, 2] = np.array([-0.5, -1.0, 0.25, 3.0, 0.0]) * lsb                # c = −0.25, −1.25, −1, 2, 2
    r = np.zeros((2, 3))
    r[1, 2] = 0.25 * lsb
    out, new = _quantize(np.broadcast_to(x, x.shape), lsb, r)               # a read-only view is accepted
    np.testing.assert_array_equal(out[0, :, 0] / lsb, [0.0, 1.0, 1.0, 0.0, 1.0])
    np.testing.assert_array_equal(out[1, :, 2] / lsb, [0.0, -1.0, 0.0, 3.0, 0.0])
    np.testing.assert_array_equal(new / lsb, [[-0.25, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert not out[0, :, 1:].any() and not out[1, :, :2].any()


def test_strapdown_takes_strided_views_as_they_are():
    """A record that is a strided, read-only view (every other run, a slice in time) navigates bitwise as its
    contiguous copy, and both agree with the numpy reference step (seed 001 eq (1)–(4))."""
    import covtool.nav.strapdown as sd
    from covtool.nav.imu.simulator import ImuRecord
    from covtool.nav.strapdown.mechanization import step

    rng = np.random.default_rng(8)
    big_th = rng.normal(0, 2e-3, (6, 90, 3))
    big_dv = rng.normal(0, 0.05, (6, 90, 3))
    view_th, view_dv = big_th[::2, 10:70], big_dv[::2, 10:70]                # (3, 60, 3), not contiguous
    view_th.flags.writeable = view_dv.flags.writeable = False
    assert not view_th.flags.c_contiguous
    s0 = sd.NavState(0.0, np.full(3, 0.6), np.full(3, 2.2), np.full(3, 100.0), rng.normal(0, 50, (3, 3)),
                     np.tile([1.0, 0.0, 0.0, 0.0], (3, 1)), rng.normal(0, 2e-3, (3, 3)), rng.normal(0, 0.05, (3, 3)))
    a = sd.run(s0, ImuRecord(0.0, 0.0025, view_th, view_dv), 4, every=3)
    b = sd.run(s0, ImuRecord(0.0, 0.0025, np.ascontiguousarray(view_th), np.ascontiguousarray(view_dv)), 4, every=3)
    for name in ("t", "lat", "lon", "h", "v_n", "q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    ref = s0
    for j in range(15):
        ref = step(ref, view_th[:, 4 * j:4 * j + 4], view_dv[:, 4 * j:4 * j + 4], 0.01)
    np.testing.assert_allclose(a.q[-1], ref.q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.v_n[-1], ref.v_n, rtol=1e-12, atol=1e-10)


def test_the_dual_imu_figures_go_to_the_figure_server_with_the_same_pixels(tmp_path):
    """Its makers are partials over the result and its runs pickle (no whitener record): the server
    takes them (issue 13) and draws the PNG files byte for byte as from the result itself."""
    import pickle
    from functools import partial

    from covtool.io import writers
    from covtool.io.figure_server import light_items

    r = run_study(short_decl(runs=6, fault_runs=3, gaps=False))
    assert set(r.figures) == {"difference_envelope", "window_test", "gsens_estimates"}
    assert all(isinstance(m, partial) and m.args[0] is r for m in r.figures.values())
    full, served = tmp_path / "full", tmp_path / "served"
    full.mkdir()
    served.mkdir()
    job = pickle.dumps(light_items(r, [(n, m, served / f"{n}.png") for n, m in r.figures.items()]))
    writers.draw_figures(pickle.loads(job))
    writers.draw_figures([(n, m, full / f"{n}.png") for n, m in r.figures.items()])
    for n in r.figures:
        assert (served / f"{n}.png").read_bytes() == (full / f"{n}.png").read_bytes(), n
    # the view's runs and configuration are plain data: the server unpickles them without the dual-IMU
    # kernels (numba) or the typed study configuration
    import subprocess
    import sys

    blob = tmp_path / "job.pickle"
    blob.write_bytes(job)
    code = ("import pickle, sys; import covtool.results; pickle.loads(open(sys.argv[1], 'rb').read()); "
            "print(sorted(m for m in ('numba', 'covtool.studies', 'covtool.dualnav.monitor') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code, str(blob)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
