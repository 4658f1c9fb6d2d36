"""Error budget (issue 4, seed 002 Fig 4): exact split of the truth covariance by source.

The oracles are independent of the budget code: the step-by-step reference
propagation (:mod:`covtool.lincov.reference`), Van Loan, closed forms of the
Schuler and vertical channels, and linearity.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import covtool
from covtool.nav import earth
from covtool.lincov.noise import MemberNoise, compose_noise
from covtool.analysis.budget import (Source, budget_sources, initial_groups, nav_variances, noise_factors,
                                     run_budget, split_initial)
from covtool.lincov.dynamics import physical_nav
from covtool.cli import main
from covtool.lincov.reference import propagate, propagate_with_filter
from covtool.lincov.discretize import per_source, van_loan
from covtool.lincov.dynamics import NoiseSource
from covtool.lincov.batch import compose
from covtool.errors import StudyFileError
from covtool.lincov.reduced import zupt_matrices
from covtool.studies.error_budget import case_budget

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "error_budget.toml"
FT = 0.3048


def decl(duration="6 min", cases=("pure_ins", "B1"), disc="taylor", **truth):
    """The shipped study, shortened (library filter file, own output times)."""
    d = tomllib.loads(STUDY.read_text())
    d["filters"].pop("file")
    d["study"]["duration"] = duration
    d["study"]["discretization"] = disc
    d["filters"]["cases"] = list(cases)
    d["output"] = {"history_every": "30 s", "report_times": [duration]}
    d["truth"].update(truth)
    return d


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    """n ≤ 58 matrices: one BLAS thread is fastest, and robust on a busy machine."""
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture(scope="module")
def flagship():
    """11 min (two ZUPT windows), Van Loan as the flagship: pure INS, B1, D."""
    return covtool.run_study(decl("11 min", ("pure_ins", "B1", "D"), "van_loan"))


@pytest.fixture(scope="module")
def short():
    """6 min, Taylor (eq (6b)-(6d)) truth: pure INS and B1."""
    return covtool.run_study(decl())


def _contribution(r, case, name):
    br = r.runs[case]
    names = [s.name for s in br.sources]
    return br.P[names.index(name)]


def _rel(a, b, q, ref=None):
    """Largest |a−b|_ij / √(r_ii r_jj) of the physical navigation block (t > 0), r = ref or b."""
    A, Bm = physical_nav(a, q), physical_nav(b, q)
    Rm = Bm if ref is None else physical_nav(ref, q)
    d = np.sqrt(np.einsum("kii->ki", Rm))[1:]
    return float((np.abs(A - Bm)[1:] / (d[:, :, None] * d[:, None, :] + 1e-300)).max())


# ---------------------------------------------------------------------------
# sum to total


@pytest.mark.parametrize("case", ["pure_ins", "B1", "D"])
def test_contributions_sum_to_the_step_by_step_total(flagship, case):
    """Σ contributions = the total run of covtool.lincov.reference (Van Loan Q_d, running filter) to ≤ 1e-9.

    The reference shares no code with the budget: its own per-step loop,
    Van Loan's Q_d instead of the per-source Taylor series, and the gains
    it computes itself.
    """
    r = flagship
    S = r.setup
    rec = r.record_steps
    if case == "pure_ins":
        P_ref = propagate(S.Phi, S.Qd, S.P0)[rec][:, :10, :10]
    else:
        fm, Phi_f, Qd_f = S.filter_model(case)
        run = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D,
                                    S.R, S.update_steps, Rf=S.filter_R(case), form=S.specs[case].update)
        P_ref = run.P_truth[rec][:, :10, :10]
    br = r.runs[case]
    q = S.nodes.q_nb[rec]
    P_sum = br.P.sum(axis=0)
    assert _rel(P_sum, P_ref, q) <= 1e-9
    lat, h = S.nodes.lat[rec], S.nodes.h[rec]
    vs, vr = nav_variances(P_sum, lat, h, q), nav_variances(P_ref, lat, h, q)
    for e in ("horizontal", "altitude", "azimuth"):
        assert np.max(np.abs(vs[e] - vr[e])[1:] / vr[e][1:]) <= 1e-9, e
    # and the budget's own residual bookkeeping agrees
    assert r.residuals[case]["same"] <= 1e-9
    assert r.residuals[case]["nominal"] <= 1e-9
    row = r.summary[r.summary["case"] == case].iloc[-1]
    assert row["sum vs nominal run residual"] <= 1e-9


def test_sources_and_ranked_tables(flagship):
    r = flagship
    b1 = [s.name for s in r.runs["B1"].sources]
    pure = [s.name for s in r.runs["pure_ins"].sources]
    assert {"initial tilt", "initial azimuth", "initial velocity", "initial acc_bias", "arw noise", "vrw noise",
            "gyro_markov noise", "ZUPT measurement noise"} <= set(b1)
    assert "initial position" not in b1          # zero initial position error: no source
    assert set(pure) == set(b1) - {"ZUPT measurement noise"}
    for e in ("horizontal", "altitude", "azimuth"):
        t = r.tables[f"budget_{e}"]
        for (case, _), g in t.groupby(["case", "t [min]"]):
            assert g["share [%]"].sum() == pytest.approx(100.0, abs=1e-9)
            assert list(g["rank"]) == list(range(1, len(g) + 1))
            assert np.all(np.diff(g["share [%]"].to_numpy()) <= 0)
    assert {"summary", "budget_horizontal", "budget_altitude", "budget_azimuth", "shares", "history_horizontal",
            "history_altitude", "history_azimuth", "sources"} <= set(r.tables)
    h = r.tables["history_horizontal"]
    cols = [c for c in h.columns if c.endswith("[ft^2]") and not c.startswith("total")]
    g = h[h["case"] == "B1"]
    np.testing.assert_allclose(g[cols].sum(axis=1, skipna=True), g["total [ft^2]"], rtol=1e-12)


# ---------------------------------------------------------------------------
# single source, linearity, resolution


@pytest.mark.parametrize("only, name", [(["acc_bias"], "initial acc_bias"), (["vrw"], "vrw noise")])
def test_single_source_model_is_100_percent_that_source(short, only, name):
    """`[truth] only`: the pure INS budget is that one source, equal to its contribution in the full model."""
    r = covtool.run_study(decl(only=only))
    pure = r.runs["pure_ins"]
    assert [s.name for s in pure.sources] == [name]
    for e in ("horizontal", "altitude", "azimuth"):
        t = r.tables[f"budget_{e}"]
        assert t[t["case"] == "pure_ins"]["share [%]"].tolist() == [pytest.approx(100.0, abs=1e-12)]
    q = r.setup.nodes.q_nb[r.record_steps]
    assert _rel(pure.P[0], _contribution(short, "pure_ins", name), q) <= 1e-12
    # under a filter the measurement noise is the only other source
    assert {s.name for s in r.runs["B1"].sources} == {name, "ZUPT measurement noise"}


def test_doubling_a_source_sigma_quadruples_its_contribution(short):
    """σ of the accelerometer biases and the VRW doubled: ×4 variance for them, others unchanged (pure INS)."""
    over = {"acc_bias_x": {"sigma": "40 ug"}, "acc_bias_y": {"sigma": "40 ug"}, "acc_bias_z": {"sigma": "60 ug"}}
    r = covtool.run_study(decl(override=over, vrw="10 ug/sqrt(Hz)"))
    q = r.setup.nodes.q_nb[r.record_steps]
    for name in ("initial acc_bias", "vrw noise"):
        assert _rel(_contribution(r, "pure_ins", name), 4 * _contribution(short, "pure_ins", name), q) <= 1e-12
    for name in ("initial tilt", "initial azimuth", "arw noise"):
        assert _rel(_contribution(r, "pure_ins", name), _contribution(short, "pure_ins", name), q) <= 1e-12


def test_fixed_gains_make_every_source_linear(short):
    """Under B1's fixed gains, P0 of one source ×4 and R ×4 give ×4 contributions, nothing else moves."""
    S = short.setup
    truth, Qn, rec = short.truth_system, short.noise, short.record_steps
    base = short.runs["B1"]
    sources = [dataclasses.replace(s, P0=4 * s.P0) if s.name == "initial tilt" else
               dataclasses.replace(s, R=4 * s.R) if s.R is not None else s for s in base.sources]
    fm = S.filter_model("B1")[0]
    gains = covtool.lincov.batch.run_batch(truth, S.P0[None], S.H, S.R, fm.D, S.update_steps, rec,
                                     filt=covtool.lincov.batch.System.from_steps(*S.filter_model("B1")[1:], truth.ev),
                                     Pf0=fm.P0[None], Hf=zupt_matrices(fm.names), Rf=S.filter_R("B1")[None]).gains
    br = run_budget(truth, sources, Qn, S.P0, S.H, S.R, fm.D, gains, S.update_steps, rec)
    q = S.nodes.q_nb[rec]
    for b, s in enumerate(base.sources):
        k = 4 if s.name in ("initial tilt", "ZUPT measurement noise") else 1
        assert _rel(br.P[b], k * base.P[b], q) <= 1e-12, s.name


def test_state_resolution_refines_the_block_budget(short):
    """Per-state sources sum to their block's source, and to the total (B1, same gains)."""
    S = short.setup
    truth, rec = short.truth_system, short.record_steps
    src, fac = budget_sources(S.truth, S.dyn.noise, S.nodes.q_nb[0], S.R, resolution="state")
    Qn = compose_noise(S.Phi, S.dyn.F, fac, np.diff(S.t), truth.ev)
    br, P_nom = case_budget(S, "B1", truth, src, Qn, rec)
    block = short.runs["B1"]
    q = S.nodes.q_nb[rec]
    assert len(src) > 2 * len(block.sources)
    assert _rel(br.P.sum(axis=0), P_nom, q) <= 1e-9
    for b, s in enumerate(block.sources):
        parts = [i for i, x in enumerate(src) if x.kind == s.kind and (
            x.name == s.name if not s.states else x.states and set(x.states) <= set(s.states))]
        assert parts, s.name
        # relative to the total: a ZUPT cancels most of a small source's variance, leaving the total's round-off
        assert _rel(br.P[parts].sum(axis=0), block.P[b], q, ref=P_nom) <= 1e-9, s.name
    assert "initial dq3 (azimuth)" in {x.name for x in src}


# ---------------------------------------------------------------------------
# initial-condition split with correlations


def test_cross_block_correlations_are_a_source_of_their_own(short):
    """P0 = Σ group pieces + cross exactly; the budget with the cross source sums to the correlated total."""
    S = short.setup
    model = dataclasses.replace(S.truth, correlations=(("acc_bias_x", "acc_bias_y", 0.5),     # inside a block
                                                       ("acc_bias_z", "acc_sf_z", -0.6),      # across blocks
                                                       ("dq1", "gyro_bias_y", 0.8)))          # nav x sensor
    q0 = S.nodes.q_nb[0]
    P0 = model.initial_covariance(q0)
    groups = initial_groups(model)
    pieces, cross = split_initial(model, groups, q0)
    assert cross is not None
    total = sum(P for _, P in pieces) + cross
    np.testing.assert_allclose(total, P0, rtol=0, atol=1e-15 * np.abs(P0).max())
    ix = model.index
    Pb = dict(pieces)["acc_bias"]
    assert Pb[ix["acc_bias_x"], ix["acc_bias_y"]] != 0.0                      # kept inside its piece
    assert cross[ix["acc_bias_x"], ix["acc_bias_y"]] == pytest.approx(0.0, abs=1e-30)
    assert cross[ix["acc_bias_z"], ix["acc_sf_z"]] == pytest.approx(P0[ix["acc_bias_z"], ix["acc_sf_z"]])
    # the quaternion rows of the nav x sensor correlation are rotated to q0, as in P0
    qi = model.idx(["dq0", "dq1", "dq2", "dq3"])
    np.testing.assert_allclose(cross[qi, ix["gyro_bias_y"]], P0[qi, ix["gyro_bias_y"]], rtol=1e-12)
    src, _ = budget_sources(model, S.dyn.noise, q0)
    assert "initial cross-correlations" in [s.name for s in src]
    truth, Qn, rec = short.truth_system, short.noise, short.record_steps
    br, P_nom = case_budget(S, "pure_ins", truth, src, Qn, rec, P0=P0)
    q = S.nodes.q_nb[rec]
    assert _rel(br.P.sum(axis=0), P_nom, q) <= 1e-9
    no_corr, _ = split_initial(S.truth, initial_groups(S.truth), q0)
    assert split_initial(S.truth, initial_groups(S.truth), q0)[1] is None and len(no_corr) > 10


def test_nav_groups_are_the_physical_tilt_and_azimuth(short):
    """'initial tilt' carries no azimuth variance at t = 0, 'initial azimuth' no tilt (any initial attitude)."""
    S = short.setup
    pieces = dict(split_initial(S.truth, initial_groups(S.truth), S.nodes.q_nb[0])[0])
    q0 = S.nodes.q_nb[:1]
    tilt = physical_nav(pieces["tilt"][None, :10, :10], q0)[0]
    az = physical_nav(pieces["azimuth"][None, :10, :10], q0)[0]
    assert tilt[8, 8] == pytest.approx(0.0, abs=1e-20) and az[6, 6] == pytest.approx(0.0, abs=1e-20)
    assert np.sqrt(az[8, 8]) == pytest.approx(2 * 1.45e-3, rel=1e-12)
    assert np.sqrt(tilt[6, 6]) == pytest.approx(2 * 0.73e-4, rel=1e-12)


# ---------------------------------------------------------------------------
# per-source discretisation


def test_per_source_noise_matches_van_loan_and_the_ou_closed_form():
    """Each column's Q_d equals Van Loan's; a scalar OU gives q τ/2 (1 − e^{−2Δt/τ})."""
    rng = np.random.default_rng(3)
    N, n, k = 4, 6, 3
    F = 0.05 * rng.standard_normal((N, n, n))
    G = rng.standard_normal((N, n, k))
    psd = rng.uniform(0.5, 2.0, (N, k))
    dt = np.array([1.0, 0.5, 2.0, 1.0])
    Q = per_source(F, G, psd, dt)
    for p in range(k):
        Qc = (G[:, :, p:p + 1] * psd[:, None, p:p + 1]) @ np.swapaxes(G[:, :, p:p + 1], 1, 2)
        np.testing.assert_allclose(Q[:, p], van_loan(F, Qc, dt)[1], rtol=1e-12, atol=1e-14)
    tau, qc, h = 20.0, 3.0, 1.0
    Qou = per_source(np.full((1, 1, 1), -1 / tau), np.ones((1, 1, 1)), np.full((1, 1), qc), h)
    assert Qou[0, 0, 0, 0] == pytest.approx(qc * tau / 2 * (1 - np.exp(-2 * h / tau)), rel=1e-14)


def test_composed_source_noise_sums_to_the_composed_total():
    rng = np.random.default_rng(4)
    N, n = 12, 5
    F = 0.1 * rng.standard_normal((N, n, n))
    Phi, _ = van_loan(F, np.zeros((N, n, n)), 1.0)
    factors = [NoiseSource("a", rng.standard_normal((N, n, 2)), np.ones((N, 2))),
               NoiseSource("b", rng.standard_normal((N, n, 1)), np.full((N, 1), 0.3))]
    Qc = sum((f.G * f.psd[:, None, :]) @ np.swapaxes(f.G, 1, 2) for f in factors)
    Qd = van_loan(F, Qc, 1.0)[1]
    ev = np.array([0, 3, 4, 9, 12])
    Qn = compose_noise(Phi, F, factors, 1.0, ev, chunk=5)
    np.testing.assert_allclose(Qn.sum(axis=0), compose(Phi, Qd, ev)[1], rtol=1e-12, atol=1e-14)
    Qa = van_loan(F, (factors[0].G * factors[0].psd[:, None, :]) @ np.swapaxes(factors[0].G, 1, 2), 1.0)[1]
    np.testing.assert_allclose(Qn[0], compose(Phi, Qa, ev)[1], rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------------
# physics of the pure-INS ranking


@pytest.fixture(scope="module")
def pure30():
    """Pure INS, 30 min, default truth, block resolution, on the built-in route (1 s steps: its 5°/s
    turns allow at most 1.14 s)."""
    d = decl("30 min", ("pure_ins",))
    d["study"]["dt"] = "1 s"
    return covtool.run_study(d)


#: sensor-error blocks of sdins58 (seed 002 eq (3), (5)); the rest are navigation errors and gravity
SENSOR_BLOCKS = ("acc_bias", "gyro_bias", "acc_sf", "gyro_sf", "acc_mis", "acc_markov", "acc_asym",
                 "gyro_markov", "gyro_mis", "gyro_gs", "gyro_aniso", "acc_ad")
BIAS_SF = ("acc_bias", "gyro_bias", "acc_sf", "gyro_sf")


def test_pure_ins_budget_ranks_biases_and_scale_factors_first(pure30):
    """Issue 11 acceptance 2 (seed 002 Fig 4, §3.1.1): among the systematic sensor errors of the
    default (calibrated) truth, biases and scale factors are the major sources of the pure-INS
    error on the route, horizontally and in altitude.

    The largest sensor-error source is a bias or a scale factor, and the bias and
    scale-factor blocks together carry more variance than every other sensor block
    together (the white ARW/VRW noises, which no filter state can carry, excluded).
    """
    for e in ("horizontal", "altitude"):
        b = pure30.tables[f"budget_{e}"]
        b = b[b["t [min]"] == 30.0]
        sensor = b[b["source"].isin([f"initial {x}" for x in SENSOR_BLOCKS] +
                                    [f"{x} noise" for x in SENSOR_BLOCKS])]
        top = sensor.iloc[0]["source"]
        assert any(top == f"initial {x}" for x in BIAS_SF), (e, top)
        is_bsf = sensor["source"].isin([f"initial {x}" for x in BIAS_SF])
        assert sensor.loc[is_bsf, "share [%]"].sum() > sensor.loc[~is_bsf, "share [%]"].sum(), e


def test_pure_ins_ranking_follows_the_closed_forms(pure30):
    """Pure INS, 30 min on the land-vehicle route (seed 002 Fig 4's question).

    Expectations from physics, before looking at the output:

    * horizontal: the initial tilt φ0 = 2·0.73e-4 rad (Table 2) drives the
      Schuler loop, δx = R φ0 (1 − cos ω_s t) per axis, the largest source;
      the initial azimuth ψ0 = 2·1.45e-3 rad misresolves Earth rate into an
      east-tilt drift ε = Ω cos L ψ0, δx = R ε (t − sin ω_s t / ω_s).
    * altitude: the vertical channel responds identically to every
      vertical specific-force error, so the three largest are, by size,
      the z scale factor (35 ppm · g), the z bias (30 µg) and the gravity
      anomaly (25 mGal); the first two in the ratio (35 ppm g / 30 µg)².
    * azimuth: ψ0 = 9.97′ against ≤ 0.75′ of z-gyro drift in 30 min.
    """
    r = pure30
    S = r.setup
    lat, h = S.nodes.lat[0], S.nodes.h[0]
    rm, rn = earth.radii(lat)
    R = np.sqrt(rm * rn)
    g = earth.gravity(lat, h)
    w = np.sqrt(g / R)
    t = 1800.0
    tilt = 2 * (R * 2 * 0.73e-4 * (1 - np.cos(w * t))) ** 2 / FT**2
    eps = earth.OMEGA_IE * np.cos(lat) * 2 * 1.45e-3
    az = (R * eps * (t - np.sin(w * t) / w)) ** 2 / FT**2

    hz = r.tables["budget_horizontal"].set_index("source")
    assert hz.index[0] == "initial tilt"
    assert hz.loc["initial tilt", "variance [ft^2]"] == pytest.approx(tilt, rel=0.05)
    assert hz.loc["initial azimuth", "variance [ft^2]"] == pytest.approx(az, rel=0.10)
    alt = r.tables["budget_altitude"]
    assert list(alt["source"][:3]) == ["initial acc_sf", "initial acc_bias", "initial grav"]
    ratio = alt["variance [ft^2]"].iloc[0] / alt["variance [ft^2]"].iloc[1]
    assert ratio == pytest.approx((35e-6 * g / (30e-6 * 9.80665)) ** 2, rel=0.01)
    azt = r.tables["budget_azimuth"]
    assert azt["source"].iloc[0] == "initial azimuth" and azt["share [%]"].iloc[0] > 95.0


# ---------------------------------------------------------------------------
# outputs


def test_cli_writes_tables_workbook_and_figures(tmp_path):
    d = decl("6 min", ("pure_ins", "D"))
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    import tomli_w
    p = tmp_path / "eb.toml"
    p.write_text(tomli_w.dumps(d))
    out = tmp_path / "out"
    assert main(["run", str(p), "--out", str(out), "--quiet"]) == 0
    names = {x.name for x in out.iterdir()}
    assert {"summary.csv", "budget_horizontal.csv", "budget_altitude.csv", "budget_azimuth.csv", "shares.csv",
            "history_horizontal.csv", "sources.csv", "error_budget.xlsx", "budget_pure_ins.png", "budget_D.png",
            "resolved_study.toml"} <= names
    s = pd.read_csv(out / "summary.csv")
    assert {"horizontal RMS (drms) [ft]", "altitude 1sigma [ft]", "azimuth 1sigma [arcmin]",
            "sum-to-total residual (same Q_d)"} <= set(s.columns)
    prov = pd.read_excel(out / "error_budget.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert float(prov["D: sum vs nominal run residual"]) <= 1e-9
    b = pd.read_excel(out / "error_budget.xlsx", sheet_name="budget_horizontal")
    assert {"1sigma-equivalent [ft]", "share [%]", "cumulative [%]"} <= set(b.columns)


def test_figure_sources_are_ranked_by_peak_share(flagship):
    """Stacked figures show the sources with the largest peak share (zero totals at t = 0 skipped)."""
    from covtool.studies.error_budget import top_sources
    v = np.array([[0.0, 1.0, 1.0], [0.0, 0.0, 9.0], [0.0, 5.0, 1.0], [0.0, 0.0, 0.0]])
    assert top_sources(v, 2) == [2, 1]            # peaks 5/6 and 9/11 beat 1/6
    assert top_sources(v, 10) == [2, 1, 0]        # a source that never contributes is left out
    assert top_sources(np.zeros((2, 3)), 2) == []
    var = flagship.variances["pure_ins"]["horizontal"]
    names = [flagship.runs["pure_ins"].sources[i].name for i in top_sources(var, 3)]
    assert "initial tilt" in names


def test_shipped_study_files_validate():
    """Both shipped studies pass validation (the runs themselves are the CLI's job)."""
    from covtool.studies.error_budget import budget_cases, budget_options
    for f in ("error_budget.toml", "error_budget_pure_ins.toml"):
        d = tomllib.loads((ROOT / "studies" / f).read_text())
        assert d["study"]["kind"] == "error_budget"
        budget_options(d, f)
        budget_cases(d, f)


# ---------------------------------------------------------------------------
# errors


def _bad(**sections):
    d = decl()
    for k, v in sections.items():
        if v is None:
            d.pop(k, None)
        else:
            d[k] = v
    return d


@pytest.mark.parametrize("change, match", [
    ({"budget": {"resolution": "block", "colour": "red"}}, r"\[budget\]: unknown key 'colour'"),
    ({"budget": "block"}, r"\[budget\]: expected a table"),
    ({"budget": {"resolution": "axis"}}, r"\[budget\] resolution: 'axis' is not one of: 'block', 'state'"),
    ({"budget": {"top": 0}}, r"\[budget\] top: 0 is not an integer in 1\.\.60"),
    ({"budget": {"top": "5"}}, r"\[budget\] top: '5' is not an integer in 1\.\.60"),
    ({"budget": {"top": True}}, r"\[budget\] top: True is not an integer in 1\.\.60"),
    ({"filters": {"cases": ["B1"], "pure_ins": True}}, r"\[filters\] pure_ins: an error budget lists the pure INS"),
    ({"filters": {"cases": []}}, r"\[filters\] cases: expected a non-empty list"),
    ({"filters": {"cases": "B1"}}, r"\[filters\] cases: expected a non-empty list"),
    ({"filters": {"cases": ["B1", 3]}}, r"\[filters\] cases: 3 is not a case"),
    ({"filters": {"cases": ["B1", "pure_ins", "B1"]}}, r"\[filters\] cases: case .* 'B1' is listed twice"),
    ({"filters": ["B1"]}, r"\[filters\]: expected a table"),
    ({"filters": {"cases": ["pure_ins", "B9"]}}, r"\[filters\] cases: unknown filter 'B9'"),
    ({"output": {"report_times": ["40 min"]}}, r"report_times\[0\]: '40 min' is after the end"),
    ({"sweep": {}}, r"unknown key 'sweep'"),
])
def test_study_file_errors_name_the_culprit(change, match):
    with pytest.raises(StudyFileError, match=match):
        covtool.run_study(_bad(**change))


def test_numeric_core_errors():
    with pytest.raises(ValueError, match="unknown budget resolution 'axis'"):
        initial_groups(None, "axis")
    with pytest.raises(ValueError, match="unknown budget resolution 'axis'"):
        noise_factors(None, [], "axis")
    mn = MemberNoise([None, np.ones((2, 3, 3))], 2, 3)
    np.testing.assert_array_equal(mn[:, 1], np.stack([np.zeros((3, 3)), np.ones((3, 3))]))
    with pytest.raises(IndexError, match=r"supports Q\[:, i\] only"):
        mn[0]
    from covtool.lincov.batch import System
    sysm = System(np.array([0, 1]), np.eye(3)[None], np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match="update steps given without gains"):
        run_budget(sysm, [Source("x", "initial", (), P0=np.eye(3))], np.zeros((0, 1, 3, 3)), np.eye(3),
                   np.eye(1, 3), np.eye(1), None, None, [1], [1])
