"""One covariance guard on every path; NaN, never 0; validity warnings (issue 9, cases 4-5, acceptance 3).

Every covariance covtool produces passes :func:`covtool.lincov.kalman.check_covariance`
(finite, symmetric, PSD within ``PSD_TOL`` on the correlation matrix); a metric
of a covariance that fails it is NaN; a result outside the linear error
model's domain is flagged in the summary and warned about, with its time.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import covtool
from covtool.nav import earth
from covtool.lincov.kalman import PSD_TOL, check_covariance, covariance_status, scale_groups
from covtool.lincov.reference import propagate, propagate_with_filter
from covtool.lincov.batch import System, events, run_batch
from covtool.errors import FlaggedCaseWarning, InputError, NumericalError, StudyFileError, ValidityWarning
from covtool.analysis.metrics import (ALTITUDE_LIMIT, ATTITUDE_LIMIT, POSITION_LIMIT, cep, cep_approx,
                                      first_invalid, nav_metrics, validity, validity_text)
from covtool.lincov.model.spec import Model

ROOT = Path(__file__).resolve().parents[1]
G0 = 9.80665


# --------------------------------------------------------------------------
# case 4: metrics of an invalid covariance are NaN, never 0
# --------------------------------------------------------------------------

@pytest.mark.parametrize("P2", [np.full((1, 2, 2), np.nan), np.array([[np.inf, 0.0], [0.0, 1.0]]),
                                np.array([[-1.0, 0.0], [0.0, -4.0]]), np.array([[1.0, 2.0], [2.0, 1.0]])],
                         ids=["nan", "inf", "negative", "indefinite"])
def test_cep_of_an_invalid_covariance_is_nan(P2):
    """Case 4: CEP was 0 for each of these; now NaN (and the 0.589 rule too)."""
    assert np.all(np.isnan(cep(P2)))
    assert np.all(np.isnan(cep_approx(P2)))


def test_cep_of_valid_covariances_is_unchanged_in_a_mixed_stack():
    """A bad matrix in a stack does not spoil the others: circular CEP = √(2 ln 2) σ, zero stays 0."""
    P = np.stack([np.eye(2) * 4.0, np.full((2, 2), np.nan), np.zeros((2, 2))])
    out = cep(P)
    assert out[0] == pytest.approx(2.0 * np.sqrt(2.0 * np.log(2.0)), rel=1e-12)
    assert np.isnan(out[1]) and out[2] == 0.0


def test_nav_metrics_are_nan_where_the_navigation_block_is_invalid():
    """Every metric at a bad time is NaN; the good times keep σ_N = (R_M + h) σ_L exactly."""
    N = 3
    P = np.zeros((N, 10, 10))
    P[:] = np.diag([1e-12, 1e-12, 4.0, 1e-2, 1e-2, 1e-2, 0.0, 1e-8, 1e-8, 1e-6])
    P[1, 2, 2] = -4.0                                                  # negative altitude variance
    P[2, 5, 5] = np.nan
    lat, h = np.full(N, 0.6), np.full(N, 100.0)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (N, 1))
    m = nav_metrics(P, lat, h, q, distance=np.full(N, 1000.0))
    rm, _ = earth.radii(0.6)
    assert m["sigma_north"][0] == pytest.approx((rm + 100.0) * 1e-6, rel=1e-12)
    for key, v in m.items():
        assert np.isfinite(v[0]), key
        assert np.isnan(v[1]) and np.isnan(v[2]), key


# --------------------------------------------------------------------------
# the guard itself
# --------------------------------------------------------------------------

NAMES = ["a", "b", "c"]


@pytest.mark.parametrize("P, pattern", [
    (np.diag([1.0, np.nan, 1.0]), r"has a non-finite entry \(nan\) in state 'b'"),
    (np.diag([1.0, 1.0, np.inf]), r"has a non-finite entry \(inf\) in state 'c'"),
    (np.array([[1.0, 0.5, 0], [0.1, 1.0, 0], [0, 0, 1]]),
     r"lost symmetry \(max relative asymmetry 0\.4 > 1e-09\) between states 'a' and 'b'"),
    (np.diag([1.0, -0.99, 1.0]), r"has a negative variance \(-0\.99\) of state 'b'"),
    (np.array([[1.0, 0, 0], [0, 1.0, 1.5], [0, 1.5, 1.0]]),
     r"lost positive semi-definiteness \(min eigenvalue of the correlation matrix -0\.5 < -1e-09\), "
     r"mostly in state '[bc]'"),
])
def test_guard_names_the_problem_the_time_and_the_state(P, pattern):
    """One line: what, when (the first bad matrix of a stack), which state."""
    stack = np.stack([np.eye(3), np.eye(3), P])
    with pytest.raises(NumericalError, match=r"^filter X at t = 20\.0 s: covariance " + pattern + "$"):
        check_covariance(stack, "filter X", names=NAMES, times=[0.0, 10.0, 20.0])


@pytest.mark.parametrize("scale", [1.0, 1e-9, 1e6])
def test_psd_tolerance_is_on_the_correlation_matrix_whatever_the_units(scale):
    """ρ = 1 + ε has the correlation eigenvalue −ε: passes for ε = 0.5·PSD_TOL, fails for 2·PSD_TOL.

    The σ's (1e-6 rad and 1e4 m, times ``scale``) do not matter: the test is unit-free.
    """
    s = np.array([1e-6, 1e4]) * scale
    for eps, ok in ((0.5 * PSD_TOL, True), (2.0 * PSD_TOL, False)):
        C = np.array([[1.0, 1.0 + eps], [1.0 + eps, 1.0]])
        P = C * np.outer(s, s)
        assert bool(covariance_status(P).ok) is ok
    bad = np.array([[1.0, 1.0 + 2 * PSD_TOL], [1.0 + 2 * PSD_TOL, 1.0]]) * np.outer(s, s)
    assert covariance_status(bad).value == pytest.approx(-2 * PSD_TOL, rel=1e-3)


def test_quaternion_error_block_is_scaled_as_one_rotation():
    """q·δq = 0 makes the block's norm direction null; its round-off must not fail the guard.

    A δq covariance σ²(I − q qᵀ) with q = (cos 1e-4, 0, 0, sin 1e-4) (δq0 variance ≈ 1e-8 σ²) plus
    round-off −1e-16·σ² along q: scaled state by state the correlation eigenvalue is ≈ −1e-8
    (beyond PSD_TOL), scaled as one block it is −1e-16.  A genuine −1e-6·σ² fails either way.
    """
    names = ["dL", "dl", "dh", "dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3"]
    assert [list(g) for g in scale_groups(names)] == [[6, 7, 8, 9]]
    assert [list(g) for g in scale_groups(["main:dq0", "main:dq1", "main:dq2", "main:dq3", "kimu:dq0"])] \
        == [[0, 1, 2, 3]]
    q = np.array([np.cos(1e-4), 0.0, 0.0, np.sin(1e-4)])
    sig2 = 1e-6
    P = np.eye(10) * 1e-4
    for err, ok in ((1e-16, True), (1e-6, False)):
        P[6:, 6:] = sig2 * (np.eye(4) - np.outer(q, q)) - err * sig2 * np.outer(q, q)
        assert bool(covariance_status(P, groups=scale_groups(names)).ok) is ok
        assert not covariance_status(P).ok                                    # own scaling: ≈ −err/1e-8
    P[6:, 6:] = sig2 * (np.eye(4) - np.outer(q, q)) - 1e-16 * sig2 * np.outer(q, q)
    check_covariance(P, "x", names=names)                                     # names give the grouping


def test_pure_propagation_is_judged_at_the_scale_its_states_have_had():
    """A rank-1 oscillation, u = (cos kθ, sin kθ), P_k = u uᵀ (θ = 1 rad, no noise): exactly PSD.

    Near kθ = 113π (k = 355) sin kθ = 3e-5 and P_22 ≈ 9e-10 is formed by cancellation of O(1)
    terms: judged by its own σ the correlation eigenvalue is −1.8e-7 (beyond PSD_TOL); judged by
    the largest σ the state has had (1) it is round-off, and the propagation passes the guard.
    The entries themselves match the closed form to 1e-12.
    """
    from covtool.lincov.kalman import running_scale
    N = 400
    R = np.array([[np.cos(1.0), -np.sin(1.0)], [np.sin(1.0), np.cos(1.0)]])
    Phi = np.broadcast_to(R, (N, 2, 2)).copy()
    P = propagate(Phi, np.zeros((N, 2, 2)), np.diag([1.0, 0.0]), names=["x", "y"], times=np.arange(N + 1.0))
    k = np.arange(N + 1)
    u = np.stack([np.cos(k), np.sin(k)], -1)
    np.testing.assert_allclose(P, u[:, :, None] * u[:, None, :], atol=1e-12)
    own = covariance_status(P)
    assert np.flatnonzero(~own.ok).tolist() == [355] and own.value[355] < -PSD_TOL
    assert covariance_status(P, scale=running_scale(P)).ok.all()


# --------------------------------------------------------------------------
# case 5: every path checks its covariance
# --------------------------------------------------------------------------

def _system(n=3, N=6, dt=1.0):
    rng = np.random.default_rng(0)
    Phi = np.eye(n) + 0.1 * rng.standard_normal((N, n, n))
    L = rng.standard_normal((N, n, n))
    Qd = 1e-3 * L @ np.swapaxes(L, 1, 2)
    return Phi, Qd, np.arange(N + 1) * dt


def test_engine_refuses_a_negative_initial_variance():
    """Case 5: run_batch returned σ² = −0.99 for this P0; now a one-line error naming the case and state."""
    Phi, Qd, t = _system()
    ev = events(6, [], [6])
    P0 = np.diag([1.0, -0.99, 1.0])
    with pytest.raises(NumericalError, match=r"^sweep X: truth P0: covariance has a negative variance \(-0\.99\) "
                                             r"of state 'b'$"):
        run_batch(System.from_steps(Phi, Qd, ev), P0, np.zeros((1, 3)), np.eye(1), np.eye(3), [], [6],
                  gains=np.zeros((1, 0, 3, 1)), label="sweep X", names=NAMES)


def test_reference_paths_refuse_bad_inputs():
    """P0, Q_d, R of the step-by-step reference and of pure INS, named with time and state."""
    Phi, Qd, t = _system()
    bad = Qd.copy()
    bad[3, 2, 2] = -1e-3
    with pytest.raises(NumericalError, match=r"^pure INS: Q_d of the step at t = 3\.0 s: covariance has a negative "
                                             r"variance \(-0\.001\) of state 'c'$"):
        propagate(Phi, bad, np.eye(3), names=NAMES, times=t)
    H = np.array([[1.0, 0.0, 0.0]])
    with pytest.raises(NumericalError, match=r"^filter F \(filter\): P0: covariance has a non-finite entry \(nan\) "
                                             r"in state 'a'$"):
        propagate_with_filter(Phi, Qd, np.eye(3), Phi, Qd, np.diag([np.nan, 1, 1]), H, H, np.eye(3), np.eye(1),
                              [2], label="filter F", names=NAMES, filter_names=NAMES, times=t)
    with pytest.raises(NumericalError, match=r"^filter F \(truth\): R: covariance has a negative variance"):
        propagate_with_filter(Phi, Qd, np.eye(3), Phi, Qd, np.eye(3), H, H, np.eye(3), -np.eye(1), [2],
                              label="filter F", times=t)


def test_pure_ins_overflow_is_reported_at_its_first_time():
    """Φ = 1e10·I: P_k = 1e20k, finite up to k = 15 (1e300), inf at k = 16 (1e320 > 1.8e308)."""
    N = 20
    Phi = np.broadcast_to(1e10 * np.eye(2), (N, 2, 2)).copy()
    Qd = np.zeros((N, 2, 2))
    with pytest.raises(NumericalError, match=r"^pure INS at t = 16\.0 s: covariance has a non-finite entry \(inf\) "
                                             r"in state 'x'$"):
        propagate(Phi, Qd, np.eye(2), names=["x", "y"], times=np.arange(N + 1.0))
    P = propagate(Phi[:15], Qd[:15], np.eye(2))
    assert P[-1, 0, 0] == pytest.approx(1e300, rel=1e-12)


def test_reference_filter_run_names_the_first_bad_step():
    """A filter whose Φ_f blows up: the filter covariance is named with the first step it is inf."""
    N = 20
    Phi = np.broadcast_to(np.eye(2), (N, 2, 2)).copy()
    Qd = np.broadcast_to(1e-3 * np.eye(2), (N, 2, 2)).copy()
    Phi_f = np.broadcast_to(1e10 * np.eye(2), (N, 2, 2)).copy()
    H = np.array([[1.0, 0.0]])
    with pytest.raises(NumericalError, match=r"^filter F: filter after the propagation at t = 16\.0 s: covariance "
                                             r"has a non-finite entry \(inf\) in state 'x'$"):
        propagate_with_filter(Phi, Qd, np.eye(2), Phi_f, Qd, np.eye(2), H, H, np.eye(2), np.eye(1), [18],
                              label="filter F", names=["x", "y"], filter_names=["x", "y"], times=np.arange(N + 1.0))


def test_engine_flags_a_diverging_case_and_keeps_the_others():
    """on_invalid = "flag": the case with a gain of 1e200 (P ~ K R Kᵀ ~ 1e400 = inf) is NaN and named;
    the other case equals its own run alone, bit for bit."""
    Phi, Qd, t = _system()
    upd = [2, 4]
    ev = events(6, upd, [2, 4, 6])
    sysm = System.from_steps(Phi, Qd, ev)
    H = np.array([[1.0, 0.0, 0.0]])
    gains = np.zeros((2, 2, 3, 1))
    gains[0, :, 0, 0] = 0.5
    gains[1, :, 0, 0] = 1e200
    kw = dict(label="budget X", names=NAMES, times=t, cases=["fine", "wild"])
    res = run_batch(sysm, np.eye(3), H, np.eye(1), np.eye(3), upd, [2, 4, 6], gains=gains, on_invalid="flag",
                    keep=slice(None), **kw)
    assert list(res.failed) == [False, True]
    assert res.status[0] == ""
    assert res.status[1] == ("budget X (case wild): truth after the eq (16) update at t = 2.0 s: covariance has a "
                             "non-finite entry (inf) in state 'a'")
    assert np.all(np.isnan(res.P_truth[1]))
    alone = run_batch(sysm, np.eye(3), H, np.eye(1), np.eye(3), upd, [2, 4, 6], gains=gains[:1], keep=slice(None))
    np.testing.assert_array_equal(res.P_truth[0], alone.P_truth[0])
    with pytest.raises(NumericalError, match=r"^budget X \(case wild\): truth after the eq \(16\) update at "
                                             r"t = 2\.0 s"):
        run_batch(sysm, np.eye(3), H, np.eye(1), np.eye(3), upd, [2, 4, 6], gains=gains, **kw)


def test_dual_imu_whitener_guards_its_model():
    """The whitener refuses a NaN Q_d (names the epoch time) and a non-PSD P0 (names the joint state)."""
    from covtool.dualnav.difference import DifferenceModel
    from covtool.dualnav.monitor import Whitener
    J = 5
    t = np.arange(J + 1) * 2.0
    Phi = np.broadcast_to(np.eye(2), (J, 2, 2)).copy()
    Qd = np.broadcast_to(1e-2 * np.eye(2), (J, 2, 2)).copy()
    H = np.broadcast_to(np.array([[[1.0, -1.0]]]), (J + 1, 1, 2)).copy()
    names = ["main:x", "kimu:x"]

    def model(Qd=Qd, P0=np.eye(2)):
        return DifferenceModel(t, names, 1, Phi, Qd, np.zeros((J, 2, 0)), H, P0, np.eye(1), (0,), ())

    bad = Qd.copy()
    bad[3, 1, 1] = np.nan
    with pytest.raises(NumericalError, match=r"^dual-IMU whitener: Q_d of the epoch interval at t = 6\.0 s: "
                                             r"covariance has a non-finite entry \(nan\) in state 'kimu:x'$"):
        Whitener(model(Qd=bad), 1)
    with pytest.raises(NumericalError, match=r"^dual-IMU whitener: P0: covariance lost positive semi-definiteness"):
        Whitener(model(P0=np.array([[1.0, 2.0], [2.0, 1.0]])), 1)
    # a valid model: a random walk difference, whitened: S_0 = H P0 Hᵀ + R = 3 (closed form)
    w = Whitener(model(), 1)
    w.update(0, np.zeros((1, 1)))
    assert w.S[0, 0, 0] == pytest.approx(3.0, rel=1e-15)


# --------------------------------------------------------------------------
# studies: pure INS for days (cases 4 and 5 end to end)
# --------------------------------------------------------------------------

def static_pure_ins(duration, dt="1 min", **truth):
    return {"study": {"kind": "pure_ins", "duration": duration, "dt": dt},
            "trajectory": {"builtin": "static", "duration": duration, "lat": "37.5 deg", "lon": "127 deg",
                           "h": "50 m"},
            "truth": {"model": "sdins58", **truth},
            "output": {"history_every": "10 min", "report_times": [duration]}}


def test_72_hour_pure_ins_stops_at_the_overflow_instead_of_reporting_cep_0():
    """Case 4: CEP 0 m and altitude NaN with exit 0 before; now the time and state of the overflow."""
    with pytest.raises(NumericalError, match=r"^<study>: pure INS at t = 199620\.0 s \(55\.45 h\): covariance has a "
                                             r"non-finite entry \(inf\) in state 'dh'$"):
        covtool.run_study(static_pure_ins("72 h"))


def test_six_hour_pure_ins_is_flagged_outside_the_linear_domain():
    """Case 5: CEP 2.4e17 ft at 6 h 'without a word'; now every domain test is named with its first time."""
    with pytest.warns(ValidityWarning, match=r"pure_ins: outside the linear error model's domain: altitude 1sigma "
                                             r"> 63\.8 km \(vertical channel diverged\) from t = \d+\.\d min; "
                                             r"horizontal position"):
        d = static_pure_ins("6 h")
        d["output"]["history_every"] = "1 min"           # every step
        r = covtool.run_study(d)
    text = r.summary["validity"].iloc[0]
    assert "altitude 1sigma > 63.8 km" in text and "horizontal position 1sigma > 1 % of the Earth radius" in text \
        and "attitude 1sigma > 0.0333 rad" in text
    h = r.tables["history"]
    first = h[h["validity"].str.contains("altitude")].iloc[0]
    assert first["sigma_D [m]"] > ALTITUDE_LIMIT
    assert f"from t = {first['t [min]']:.1f} min" in text


def test_vertical_channel_warning_time_matches_the_closed_form():
    """Only a 30 µg vertical accelerometer bias, at rest: σ_h = σ_b (cosh ω t − 1)/ω² with ω² = −∂g/∂h.

    σ_h at 60 min agrees with the closed form to 1 % (the Coriolis and Schuler couplings of the full
    model make it 0.7 % smaller).  The validity test fires when σ_h crosses ALTITUDE_LIMIT: at the
    first 10-s step after t* = acosh(1 + L ω²/σ_b)/ω (≈ 68 min), allowing the 1 % in σ, which is
    0.01/ω in time (σ_h grows as e^{ωt}).
    """
    with pytest.warns(ValidityWarning, match=r"^pure_ins: outside the linear error model's domain: altitude 1sigma "
                                             r"> 63\.8 km \(vertical channel diverged\) from t = 68\.5 min$"):
        r = covtool.run_study(static_pure_ins("80 min", dt="10 s", only=["acc_bias_z"]))
    _, dg_dh = earth.gravity_derivatives(np.radians(37.5), 50.0)
    w = np.sqrt(-dg_dh)
    sb = 30e-6 * G0
    h = r.tables["history"]
    row = h[np.isclose(h["t [s]"], 3600.0)].iloc[0]
    assert row["sigma_D [m]"] == pytest.approx(sb * (np.cosh(w * 3600.0) - 1.0) / w**2, rel=0.01)
    t_star = np.arccosh(1.0 + ALTITUDE_LIMIT * w**2 / sb) / w
    first = first_invalid(r.metrics, r.times)
    assert set(first) == {"altitude"}
    assert t_star <= first["altitude"] < t_star + 0.01 / w + 10.0
    assert r.summary["validity"].iloc[0] == (f"altitude 1sigma > 63.8 km (vertical channel diverged) from "
                                             f"t = {first['altitude'] / 60:.1f} min")


def test_validity_limits_and_text():
    """The three limits: 1 % of R for position and altitude, 0.05/1.5 rad for attitude; 'ok' otherwise."""
    assert POSITION_LIMIT == pytest.approx(63781.37) and ALTITUDE_LIMIT == POSITION_LIMIT
    assert ATTITUDE_LIMIT == pytest.approx(1 / 30)
    z = np.zeros(4)
    m = {k: z.copy() for k in ("sigma_north", "sigma_east", "sigma_down", "sigma_tilt_n", "sigma_tilt_e",
                              "sigma_azimuth")}
    m["sigma_east"][2:] = 1.0001 * POSITION_LIMIT
    m["sigma_azimuth"][1:] = 1.0001 * ATTITUDE_LIMIT
    m["sigma_down"][:] = np.nan                                     # NaN is the guard's business, not a validity
    flags = validity(m)
    assert list(flags["position"]) == [False, False, True, True]
    assert list(flags["attitude"]) == [False, True, True, True] and not flags["altitude"].any()
    first = first_invalid(m, [0.0, 60.0, 120.0, 180.0])
    assert validity_text(first) == ("attitude 1sigma > 0.0333 rad (1.9 deg) from t = 1.0 min; horizontal position "
                                    "1sigma > 1 % of the Earth radius (63.8 km) from t = 2.0 min")
    assert validity_text(first, until=90.0) == "attitude 1sigma > 0.0333 rad (1.9 deg) from t = 1.0 min"
    assert validity_text({}) == "ok"


def test_an_initial_azimuth_of_83_degrees_is_refused():
    """Case 5: an initial azimuth σ of 83° was accepted; the linear model cannot start there."""
    d = static_pure_ins("10 min", override={"dq3": {"sigma": "0.724 rad"}})
    with pytest.raises(StudyFileError, match=r"\[truth\]: the initial covariance of truth model 'sdins58' is outside "
                                             r"the linear error model's domain: attitude 1sigma > 0\.0333 rad "
                                             r"\(1\.9 deg\) \(initial 1sigma: azimuth 83(\.\d+)? deg"):
        covtool.run_study(d)


def test_cli_prints_each_warning_on_one_line(tmp_path, capsys):
    import tomli_w
    from covtool.cli import main
    study = tmp_path / "long.toml"
    study.write_text(tomli_w.dumps(static_pure_ins("100 min")))
    assert main(["run", str(study), "--out", str(tmp_path / "out"), "--quiet", "--no-figures"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["covtool: warning: pure_ins: outside the linear error model's domain: altitude 1sigma > 63.8 km "
                   "(vertical channel diverged) from t = 63.0 min; horizontal position 1sigma > 1 % of the Earth "
                   "radius (63.8 km) from t = 93.0 min"]
    s = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert s["validity"].iloc[0].startswith("altitude 1sigma > 63.8 km")


def test_end_to_end_overrides_give_an_error_not_cep_0():
    """Case 4 end to end: these overrides wrote CEP 0.0 with exit 0.  Whatever layer refuses them
    (input validation or the guard), it is a one-line error, never a summary.

    The guard's own message: σ = 1e200 µg overflows P0 (σ² = 1e389 m²/s⁴) in that state.  τ = 1e-12 s is
    now discretised exactly and gives the right (non-zero) answer.
    """
    with pytest.raises((NumericalError, InputError), match=r"acc_bias_x"):
        covtool.run_study(static_pure_ins("10 min", override={"acc_bias_x": {"sigma": "1e200 ug"}}))
    # τ = 1e-12 s: the exact discretiser gives a finite Φ; the Markov bias is then white noise of PSD 2σ²τ
    # (≈ 1e-20 m²/s³), so the answer must equal the run without that source, not 0
    fast = covtool.run_study(static_pure_ins("10 min", override={"acc_markov_x": {"tau": "1e-12 s"}})).summary
    off = covtool.run_study(static_pure_ins("10 min", override={"acc_markov_x": {"sigma": "0 ug"}})).summary
    assert fast["CEP [m]"].iloc[0] > 1.0
    assert fast["CEP [m]"].iloc[0] == pytest.approx(off["CEP [m]"].iloc[0], rel=1e-9)


# --------------------------------------------------------------------------
# acceptance 3: every study kind that produces a covariance, with NaN, inf and a negative variance
# --------------------------------------------------------------------------

def _short(path, duration="6 min"):
    d = tomllib.loads(Path(path).read_text())
    d["study"]["duration"] = duration
    d.setdefault("output", {})["report_times"] = [duration]
    return d


def _pure_ins():
    return _short(ROOT / "studies" / "pure_ins_land_vehicle.toml")


def _filter_order():
    d = _short(ROOT / "studies" / "zupt_filter_order.toml")
    d["filters"].pop("file", None)                      # the library's filters (the dict has no directory)
    d["filters"]["cases"] = ["D"]
    return d, ROOT / "studies" / "zupt_filter_order.toml"


def _sensitivity():
    d = _short(ROOT / "studies" / "zupt_sensitivity.toml")
    d["filters"].pop("file", None)
    d["filters"]["cases"] = ["D"]
    d["sweep"].update(parameters=["R"], scales={"from": 0.1, "to": 10, "per_decade": 1}, fit_degree=0)
    d["cost"] = {"measure": False, "paper_seconds": {"D": 0.08}}
    return d, ROOT / "studies" / "zupt_sensitivity.toml"


def _budget():
    d = _short(ROOT / "studies" / "error_budget.toml")
    d["filters"].pop("file", None)
    d["filters"]["cases"] = ["pure_ins", "D"]
    return d, ROOT / "studies" / "error_budget.toml"


def _trade():
    d = tomllib.loads((ROOT / "studies" / "trade_grid.toml").read_text())
    d["study"].update(duration="6 min", dt="1 s")      # the route's turns allow at most 1.14 s
    d["output"]["report_times"] = ["6 min"]
    d["filters"] = {"cases": ["D"]}
    d["grid"].update(zupt_interval=["3 min"], zupt_sigma=["0.01 ft/s"], q_scale=[1.0])
    d["grade"] = [d["grade"][0]]
    return d, ROOT / "studies" / "trade_grid.toml"


MC_MODEL = """
[model]
name = "mc_tiny"
description = "navigation errors and a vertical accelerometer bias"
[[block]]
kind = "navigation"
position_sigma = ["0 rad", "0 rad", "0 m"]
velocity_sigma = "0.01 m/s"
quaternion_sigma = ["0", "1e-4 rad", "1e-4 rad", "1e-3 rad"]
angle_random_walk = "0.002 deg/sqrt(h)"
velocity_random_walk = "5 ug/sqrt(Hz)"
[[block]]
kind = "accel_bias"
sigma = ["20 ug", "20 ug", "30 ug"]
"""

MC_FILTERS = """
[[filter]]
name = "N"
truth = "mc_tiny"
keep = ["nav"]
"""


def _monte_carlo(tmp_path):
    (tmp_path / "mc_tiny.toml").write_text(MC_MODEL)
    (tmp_path / "filters.toml").write_text(MC_FILTERS)
    return {
        "study": {"kind": "monte_carlo", "name": "mc_guard", "duration": "150 s", "dt": "1 s"},
        "trajectory": {"builtin": "land_vehicle", "cycles": 1, "period": "150 s", "stop_duration": "40 s",
                       "distance": "1500 m", "accel_duration": "10 s", "grade_duration": "20 s"},
        "truth": {"model": str(tmp_path / "mc_tiny.toml")},
        "filters": {"file": str(tmp_path / "filters.toml"), "cases": ["N"], "pure_ins": True},
        "zupt": {"interval": "150 s", "duration": "20 s", "rate": "1 Hz", "sigma": "0.01 ft/s"},
        "monte_carlo": {"runs": 2, "runs_per_chunk": 2, "seed": 1, "imu_rate": "100 Hz", "samples_per_step": 4},
        "output": {"history_every": "10 s", "report_times": ["150 s"]},
    }, None


def _dual_imu():
    from test_dualnav import short_decl
    return short_decl(runs=1, fault_runs=0, gaps=False), None


KINDS = ["pure_ins", "zupt_filter_order", "zupt_sensitivity", "error_budget", "trade_grid", "monte_carlo",
         "dual_imu"]
BAD = {"nan": (np.nan, r"non-finite entry \(nan\)"), "inf": (np.inf, r"non-finite entry \(inf\)"),
       "negative": (-1.0, r"negative variance \(-")}


def _study(kind, tmp_path):
    if kind == "pure_ins":
        return _pure_ins(), None
    return {"zupt_filter_order": _filter_order, "zupt_sensitivity": _sensitivity, "error_budget": _budget,
            "trade_grid": _trade, "dual_imu": _dual_imu}[kind]() if kind != "monte_carlo" else _monte_carlo(tmp_path)


def _poison(P, index, bad):
    """``P`` with ``P[index, index]`` made NaN, inf or minus its variance."""
    P = np.array(P, float, copy=True)
    value = BAD[bad][0]
    P[index, index] = -(abs(P[index, index]) or 1.0) if bad == "negative" else value
    return P


@pytest.mark.parametrize("bad", list(BAD))
@pytest.mark.parametrize("kind", KINDS)
def test_every_study_kind_refuses_an_invalid_initial_covariance(kind, bad, tmp_path, monkeypatch):
    """A NaN, an inf or a negative variance in the initial covariance, injected past the model
    loader's own checks, stops every study kind with the guard's one-line message naming P0 and
    the state; no summary is returned.  The truth's P0 is poisoned where a study asks the model
    for it at the initial attitude; dual_imu's joint P0 where its difference model is built.
    (The seed 000 ad_reset study propagates no covariance: there is nothing to guard.)"""
    decl, _ = _study(kind, tmp_path)
    if kind == "dual_imu":
        from covtool.dualnav.difference import difference_model
        original = difference_model

        def poisoned(*args, **kwargs):
            m = original(*args, **kwargs)
            m.P0 = _poison(m.P0, 10, bad)
            return m

        monkeypatch.setattr("covtool.dualnav.run.difference_model", poisoned)
        pattern = r"^dual-IMU whitener: P0: covariance has a " + BAD[bad][1] + r".* state 'main:"
    else:
        original = Model.initial_covariance

        def poisoned(self, *args, **kwargs):
            P = original(self, *args, **kwargs)
            return _poison(P, 10, bad) if args or kwargs else P     # not the loader's own PSD check

        monkeypatch.setattr(Model, "initial_covariance", poisoned)
        pattern = r"truth model '\w+': P0: covariance has a " + BAD[bad][1] + r".* state 'acc_bias_x'$"
    with pytest.raises(NumericalError, match=pattern):
        covtool.run_study(decl)


@pytest.mark.parametrize("bad", list(BAD))
@pytest.mark.parametrize("kind", [k for k in KINDS if k != "dual_imu"])
def test_every_study_kind_refuses_an_invalid_process_noise(kind, bad, tmp_path, monkeypatch):
    """The same three values injected into the truth's discrete process noise Q_d at one step
    (the discretiser's output) stop the study with the step's time and the state."""
    import covtool.studies.grid as grid
    decl, _ = _study(kind, tmp_path)
    value, problem = BAD[bad]
    original = grid.discretize_chunked
    calls = []

    def poisoned(F, Qc, dt, method, order=None, **kw):
        Phi, Qd = original(F, Qc, dt, method, order, **kw)
        if not calls:                                   # the truth is discretised first
            Qd = Qd.copy()
            Qd[7, 3, 3] = value * (abs(Qd[7, 3, 3]) or 1.0) if bad == "negative" else value
        calls.append(1)
        return Phi, Qd

    monkeypatch.setattr(grid, "discretize_chunked", poisoned)
    with pytest.raises(NumericalError, match=r": Q_d of the step at t = \d+\.0 s: covariance has a "
                                             + problem + r".* state 'dvN'"):
        covtool.run_study(decl)


def test_dual_imu_refuses_an_invalid_process_noise(monkeypatch):
    """dual_imu builds its own Q_d (covtool.dualnav.difference.difference_model): a NaN there stops the whitener."""
    from covtool.dualnav.difference import difference_model
    original = difference_model

    def poisoned(*args, **kwargs):
        m = original(*args, **kwargs)
        m.Qd = m.Qd.copy()
        m.Qd[2, 4, 4] = np.nan
        return m

    monkeypatch.setattr("covtool.dualnav.run.difference_model", poisoned)
    from test_dualnav import short_decl
    with pytest.raises(NumericalError, match=r"^dual-IMU whitener: Q_d of the epoch interval at t = [\d.]+ s: "
                                             r"covariance has a non-finite entry \(nan\) in state 'main:dvE'$"):
        covtool.run_study(short_decl(runs=1, fault_runs=0, gaps=False))


# --------------------------------------------------------------------------
# a study that goes on: a flagged trade-grid case is NaN with a status, never 0
# --------------------------------------------------------------------------

def test_trade_grid_flags_a_diverging_case(monkeypatch):
    """A case whose filter covariance overflows (Q_f × 1e308) is NaN with its status; the nominal case is not.

    Input validation refuses such a scale ([grid] q_scale ≤ 1e6); it is let through here to test the guard
    behind it."""
    from covtool.io import config
    monkeypatch.setitem(config.LIMITS, "filter_scale", config.LIMITS["filter_scale"].__class__(
        1e-6, 1e309, "test"))
    d, _ = _trade()
    d["grid"]["q_scale"] = [1.0, 1e308]
    with pytest.warns(FlaggedCaseWarning, match=r"1 of 2 trade-grid cases failed the covariance guard"):
        r = covtool.run_study(d)
    s = r.summary.set_index("Q scale")
    assert s.loc[1.0, "status"] == "ok" and np.isfinite(s.loc[1.0, "CEP [ft]"])
    assert s.loc[1e308, "status"].startswith("trade grid: g00-i00: filter D (case 1): ")
    assert "after the" in s.loc[1e308, "status"] and "covariance has a non-finite entry" in s.loc[1e308, "status"]
    for col in ("CEP [ft]", "CEP [m]", "alt PE [ft]", "azimuth 1sigma [arcmin]", "filter-claimed CEP [ft]"):
        assert np.isnan(s.loc[1e308, col]), col


# --------------------------------------------------------------------------
# the remaining refusals of the kernel
# --------------------------------------------------------------------------

def test_kalman_gain_refuses_a_singular_or_non_finite_innovation_covariance():
    from covtool.lincov.kalman import kalman_gain
    H = np.array([[1.0, 0.0]])
    np.testing.assert_allclose(kalman_gain(np.eye(2), H, np.eye(1)), [[0.5], [0.0]], rtol=1e-15)   # P Hᵀ/(1+1)
    with pytest.raises(NumericalError, match=r"^innovation covariance H P Hᵀ \+ R is singular$"):
        kalman_gain(np.zeros((2, 2)), H, np.zeros((1, 1)))
    with pytest.raises(NumericalError, match=r"^innovation covariance H P Hᵀ \+ R is not finite$"):
        kalman_gain(np.diag([np.inf, 1.0]), H, np.eye(1))


def test_a_singular_gain_is_named_with_its_filter_and_time():
    """R = 0 and a filter that knows its measured state exactly: S = 0 at the second update."""
    from covtool.validation.feedback import FeedbackFilter
    N = 4
    Phi = np.broadcast_to(np.eye(2), (N, 2, 2)).copy()
    Qd = np.zeros((N, 2, 2))
    H = np.array([[1.0, 0.0]])
    t = np.arange(N + 1.0)
    with pytest.raises(NumericalError, match=r"^filter F: gain at t = 3\.0 s: innovation covariance H P Hᵀ \+ R is "
                                             r"singular$"):
        propagate_with_filter(Phi, Qd, np.eye(2), Phi, Qd, np.eye(2), H, H, np.eye(2), np.zeros((1, 1)), [1, 3],
                              label="filter F", times=t)
    names = ("dL", "dl", "dh", "dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3")
    Phi10 = np.broadcast_to(np.eye(10), (N, 10, 10)).copy()
    with pytest.raises(NumericalError, match=r"^Monte Carlo filter F: gain at t = 3\.0 s: innovation covariance"):
        FeedbackFilter.design("F", names, Phi10, np.zeros((N, 10, 10)), np.eye(10), np.zeros((3, 3)), [1, 3],
                              times=t)
    ev = events(N, [1, 3], [N])
    sysm = System.from_steps(Phi, Qd, ev)
    with pytest.raises(NumericalError, match=r"^sweep: innovation covariance H P_f Hᵀ \+ R_f is singular at "
                                             r"t = 3\.0 s$"):
        run_batch(sysm, np.eye(2), H, np.zeros((1, 1)), np.eye(2), [1, 3], [N], filt=sysm, Pf0=np.eye(2)[None],
                  Hf=H, Rf=np.zeros((1, 1, 1)), label="sweep", times=t)


def test_engine_refuses_bad_options():
    Phi, Qd, t = _system()
    ev = events(6, [], [6])
    sysm = System.from_steps(Phi, Qd, ev)
    H = np.zeros((1, 3))
    with pytest.raises(ValueError, match=r"^on_invalid must be 'raise' or 'flag', got 'skip'$"):
        run_batch(sysm, np.eye(3), H, np.eye(1), np.eye(3), [], [6], gains=np.zeros((1, 0, 3, 1)), on_invalid="skip")
    with pytest.raises(NumericalError, match=r"^batch: Q_f scale .* is not finite and non-negative$"):
        run_batch(sysm, np.eye(3), H, np.eye(1), np.eye(3), [], [6], filt=sysm, Pf0=np.eye(3)[None], Hf=H,
                  Rf=np.eye(1)[None], q_scale=np.array([-1.0]))
    with pytest.raises(NumericalError, match=r"^batch: fixed gain \(matrix \(0, 0\)\): non-finite entry \(nan\) in "
                                             r"the row of state #0$"):
        run_batch(System.from_steps(Phi, Qd, events(6, [2], [6])), np.eye(3), H, np.eye(1), np.eye(3), [2], [6],
                  gains=np.full((1, 1, 3, 1), np.nan))


def test_check_finite_names_the_matrix_time_and_row():
    from covtool.lincov.kalman import check_finite
    A = np.zeros((3, 2, 2))
    A[2, 1, 0] = np.inf
    with pytest.raises(NumericalError, match=r"^truth: Φ of the step at t = 20\.0 s: non-finite entry \(inf\) in the "
                                             r"row of state 'y'$"):
        check_finite(A, "truth: Φ of the step", names=["x", "y"], times=[0.0, 10.0, 20.0])


def test_covariance_status_refuses_a_non_square_array():
    with pytest.raises(ValueError, match=r"^a covariance must have shape \(\.\.\., n, n\), got \(2, 3\)$"):
        covariance_status(np.zeros((2, 3)))


def test_sweep_fit_leaves_out_flagged_cases():
    """A flagged (NaN) point is left out of the log-log fit; too few points give a NaN fit, not an error."""
    from covtool.analysis.sensitivity import fit_loglog
    from covtool.studies.zupt_sensitivity import _fit, _ratio
    s = np.array([0.01, 0.1, 1.0, 10.0, 100.0])
    e = 3.0 * s ** 0.25
    e_bad = e.copy()
    e_bad[-1] = np.nan
    f = _fit(s, e_bad, 1)
    np.testing.assert_allclose(f.coef, fit_loglog(s[:-1], e[:-1], 1).coef, rtol=1e-14)
    np.testing.assert_allclose(f.coef, [np.log10(3.0), 0.25], rtol=1e-12)
    assert np.all(np.isnan(_fit(s, np.full(5, np.nan), 1).coef))
    assert np.isnan(_ratio(np.nan, 2.0)) and _ratio(1.0, 0.0) == np.inf and _ratio(1.0, 2.0) == 0.5


@pytest.mark.parametrize("tol", [PSD_TOL, 1e-3])
def test_states_zero_in_every_matrix_do_not_change_the_psd_verdict(tol):
    """A Q_d stack whose random constants have zero rows and columns (36 of 58 in sdins58).

    The PSD test factorises only the states that are non-zero somewhere:
    the verdicts, states and values equal those of the stack with every
    row live (a tiny variance on the dead states), and the closed form:
    one correlation ρ between otherwise uncorrelated states gives the
    smallest eigenvalue 1 − |ρ|.
    """
    from covtool.lincov.guard import NOT_PSD, OK

    rng = np.random.default_rng(3)
    n, live = 12, np.array([1, 4, 5, 9])               # dead states in between and at both ends
    X = np.zeros((6, n, n))
    X[:, live, live] = 10.0 ** rng.uniform(-8, 4, (6, live.size))       # uncorrelated, any units
    sig = np.sqrt(X[2, 4, 4] * X[2, 9, 9])
    X[2, 4, 9] = X[2, 9, 4] = (1.0 + 10 * tol) * sig             # |ρ| > 1 + tol: λ_min = −10 tol
    X[4, 1, 5] = X[4, 5, 1] = (1.0 + 0.5 * tol) * np.sqrt(X[4, 1, 1] * X[4, 5, 5])   # within tol
    st = covariance_status(X, tol)
    assert st.code.tolist() == [OK, OK, NOT_PSD, OK, OK, OK]
    assert st.state[2] in (4, 9)
    assert st.value[2] == pytest.approx(-10 * tol, rel=1e-6)
    Y = X.copy()
    dead = np.setdiff1d(np.arange(n), live)
    Y[:, dead, dead] = 1e-30                              # every state live: the full factorisation
    full = covariance_status(Y, tol)
    assert full.code.tolist() == st.code.tolist() and full.state[2] == st.state[2]
    assert full.value[2] == pytest.approx(st.value[2], rel=1e-9)


@pytest.mark.parametrize("fault", ["nan", "inf", "asymmetric"])
def test_a_fault_off_the_diagonal_of_a_zero_variance_state_is_found(fault):
    """The guard screens the block of states with a non-zero entry; a state with zero variance
    everywhere but a non-zero off-diagonal entry belongs to that block.

    Twelve matrices, states 0–2 with unit variance, states 3–5 zero; matrix 7
    gets a fault in entry (4, 1) only (NaN, −inf, or 1e-3 against a mirror of
    0).  Its code and the state reported are those of that entry; every other
    matrix stays OK.
    """
    from covtool.lincov.guard import ASYMMETRIC, NONFINITE, OK

    X = np.zeros((12, 6, 6))
    X[:, [0, 1, 2], [0, 1, 2]] = 1.0
    X[7, 4, 1] = {"nan": np.nan, "inf": -np.inf, "asymmetric": 1e-3}[fault]
    st = covariance_status(X)
    assert np.all(st.code[np.arange(12) != 7] == OK)
    assert st.code[7] == (ASYMMETRIC if fault == "asymmetric" else NONFINITE)
    if fault == "asymmetric":
        assert {int(st.state[7]), int(st.other[7])} == {1, 4}
    else:
        assert int(st.state[7]) == 4                   # the row of the non-finite entry


def test_symmetrize_into_out_gives_the_same_bits_as_a_new_array():
    """``symmetrize(P, out=)`` (the engine's record slots) equals ``symmetrize(P)`` bit for bit, in ``out``."""
    from covtool.lincov.guard import symmetrize

    rng = np.random.default_rng(3)
    P = rng.normal(size=(4, 7, 7)) * 10.0 ** rng.uniform(-20, 20, (4, 7, 7))
    out = np.full_like(P, np.nan)
    got = symmetrize(P, out=out)
    assert got is out
    np.testing.assert_array_equal(got, symmetrize(P))
    np.testing.assert_array_equal(got, np.swapaxes(got, 1, 2))
