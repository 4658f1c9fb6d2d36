"""Dropped-state impact table (issue 11, acceptance 4): D'Appolito state deletion.

Oracles: the step-by-step reference propagation (covtool.lincov.reference) of the
declared filter, and of an independently declared filter with the block put
back.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

import covtool
from covtool.lincov.reference import propagate_with_filter
from covtool.errors import StudyFileError
from covtool.lincov.reduced import zupt_matrices
from covtool.lincov.impact import BACK, NOMINAL, NONE, ONLY, dropped_blocks, impact_run
from covtool.lincov.noise import CombinedNoise
from covtool.analysis.metrics import nav_metrics

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"

EXTRA = '''
[[filter]]
name = "D_bias"
description = "D with the accelerometer biases put back"
keep = ["nav", "acc_bias"]
decouple_vertical = true
coriolis = false
'''


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture(scope="module")
def S(tmp_path_factory):
    from covtool.studies.zupt_setup import setup
    ff = tmp_path_factory.mktemp("f") / "filters.toml"
    ff.write_text((ROOT / "models" / "filters" / "zupt_filters.toml").read_text() + EXTRA)
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["file"] = str(ff)
    d["filters"]["cases"] = ["A", "B1", "C", "D", "D_bias"]
    return setup(d, path=FLAGSHIP)


def _reference(S, name):
    fm, Phi_f, Qd_f = S.filter_model(name)
    run = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D, S.R,
                                S.update_steps, Rf=S.filter_R(name), form=fm.spec.update)
    return run.P_truth[-1][:10, :10]


def _metrics(S, P):
    k = S.t.size - 1
    m = nav_metrics(P[None], S.nodes.lat[k:], S.nodes.h[k:], S.nodes.q_nb[k:])
    return np.array([m["cep"][0], m["alt_pe"][0], m["sigma_azimuth"][0]])


@pytest.mark.parametrize("name", ["B1", "D"])
def test_nominal_member_is_the_declared_filter(S, name):
    """The embedded 58-state member with the filter's P0 and noise equals the reduced filter's own run."""
    N = S.t.size - 1
    r = impact_run(S, name, [N])
    assert r.variants[0] == (NOMINAL, None) and r.variants[1] == (NONE, None)
    np.testing.assert_allclose(_metrics(S, r.P[0, -1]), _metrics(S, _reference(S, name)), rtol=1e-8)
    assert r.noise_check < 1e-10          # Σ per-block composed noise = the filter's own Q_f


def test_block_put_back_equals_the_filter_that_keeps_it(S):
    """D with acc_bias put back equals filter D_bias declared on its own (16 → 13 states, eq (11)-(13) elsewhere)."""
    N = S.t.size - 1
    r = impact_run(S, "D", [N])
    b = r.variants.index((BACK, "acc_bias"))
    np.testing.assert_allclose(_metrics(S, r.P[b, -1]), _metrics(S, _reference(S, "D_bias")), rtol=1e-7)
    # and each block appears once alone and once put back
    blocks = dropped_blocks(S.truth, S.specs["D"].kept)
    assert [v for v in r.variants if v[0] == ONLY] == [(ONLY, b_) for b_ in blocks]
    assert [v for v in r.variants if v[0] == BACK] == [(BACK, b_) for b_ in blocks]


def test_impact_sheet_in_the_flagship_outputs(S):
    d = tomllib.loads(FLAGSHIP.read_text())
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    d["filters"]["cases"] = ["A", "D"]
    r = covtool.run_study(d)
    imp = r.tables["impact"]
    assert set(imp["filter"]) == {"D"}
    nom = imp[imp["variant"] == NOMINAL].iloc[0]
    summ = r.summary.set_index("case")
    assert nom["CEP [ft]"] == pytest.approx(summ.loc["D", "CEP [ft]"], rel=1e-8)
    assert nom["alt PE [ft]"] == pytest.approx(summ.loc["D", "alt PE [ft]"], rel=1e-8)
    assert "impact_dropped_states" in r.figures


@pytest.mark.parametrize("impact,match", [
    ({"filters": ["E"]}, r"\[impact\] filters: 'E' is not one of the run's cases"),
    ({"filters": ["A"]}, r"\[impact\] filters: filter 'A' keeps every truth state: it drops nothing"),
    ({"filters": "B1"}, r"\[impact\] filters: expected a list of filter names"),
    ({"filtres": ["B1"]}, r"\[impact\].*unknown key 'filtres'"),
])
def test_impact_declaration_errors(impact, match):
    d = tomllib.loads(FLAGSHIP.read_text())
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    d["filters"]["cases"] = ["A", "D"]
    d["impact"] = impact
    with pytest.raises(StudyFileError, match=match):
        covtool.run_study(d)


def test_combined_noise_supports_only_member_slices():
    Q = np.arange(2 * 2 * 2, dtype=float).reshape(2, 2, 2)
    cn = CombinedNoise([(Q, np.array([0, 2]))], np.array([[1.0], [2.0]]), 3)
    out = cn[:, 1]
    np.testing.assert_allclose(out[1][np.ix_([0, 2], [0, 2])], 2 * Q[1])
    assert out[0, 1, 1] == 0.0
    with pytest.raises(IndexError, match=r"CombinedNoise supports Q\[:, i\] only"):
        cn[0]


def _embed(Q, ix, n):
    out = np.zeros((n, n))
    out[np.ix_(ix, ix)] = Q
    return out


def test_combined_noise_is_the_weighted_sum_of_embedded_components():
    """Components on different state sets, weighed per member: Σ_c coef[b, c] · embed(Q_c[i]), against the
    embedding written out matrix by matrix; a component no member weighs is left out (its NaN does not
    reach any member)."""
    rng = np.random.default_rng(3)
    n, K = 7, 4
    sets = [np.array([0, 2, 3]), np.array([1, 2, 5, 6]), np.array([0, 2, 3])]
    comps = []
    for ix in sets:
        A = rng.standard_normal((K, ix.size, ix.size))
        comps.append((A @ np.swapaxes(A, 1, 2), ix))
    comps.append((np.full((K, 2, 2), np.nan), np.array([4, 5])))          # weighed by no member
    coef = rng.standard_normal((3, len(comps)))
    coef[:, -1] = 0.0
    coef[1, 0] = 0.0
    cn = CombinedNoise(comps, coef, n)
    for i in range(K):
        want = np.zeros((3, n, n))
        for b in range(3):
            for c, (Q, ix) in enumerate(comps[:-1]):
                want[b][np.ix_(ix, ix)] += coef[b, c] * Q[i]
        np.testing.assert_allclose(cn[:, i], want, rtol=1e-13, atol=1e-13)
    # the same states in another order form their own group; a component on no state adds nothing
    perm = np.array([3, 0, 2])                              # comps[0]'s states (0, 2, 3) in another order
    Qp = comps[0][0][:, [2, 0, 1]][:, :, [2, 0, 1]]         # its matrix on that order: the same embedding
    two = CombinedNoise([comps[0], (Qp, perm), (np.zeros((K, 0, 0)), np.zeros(0, int))],
                        np.array([[1.0, 2.0, 5.0]]), n)
    for i in range(K):
        np.testing.assert_allclose(two[:, i][0], 3.0 * _embed(comps[0][0][i], comps[0][1], n), rtol=1e-13,
                                   atol=1e-13)


def test_equivalent_noise_sheet_reports_navigation_errors(S):
    """Issue 11 item 2: each dropped state's noise in the errors it drives, against an
    independent composition (covtool.lincov.noise.compose_noise, exact per-step Q_d) of that
    state's noise alone through the filter's Φ_f over each ZUPT interval."""
    from covtool.lincov.noise import compose_noise
    from covtool.lincov.reduced import ewn_navigation_effect
    from covtool.analysis.metrics import ned_position_covariance
    from covtool.nav.attitude import attitude_error_matrix

    fm, Phi_f, _ = S.filter_model("B1")
    nodes = S.nodes
    eff = ewn_navigation_effect(fm, Phi_f, S.t, nodes.lat, nodes.h, nodes.q_nb).set_index("dropped state")
    b = fm.bounds
    ends = b[1:]
    for name in ("grav_xi", "gyro_mis_xz", "acc_mis_xz"):
        src = next(x for x in fm.ewn_noise if x.name == name)
        Q = compose_noise(Phi_f, fm.F, [src], np.diff(S.t), b)[0]            # (K, nf, nf) at the interval ends
        pos = ned_position_covariance(Q[:, :3, :3], nodes.lat[ends], nodes.h[ends])
        att = attitude_error_matrix(nodes.q_nb[ends]) @ Q[:, 6:10, 6:10] @ np.swapaxes(
            attitude_error_matrix(nodes.q_nb[ends]), 1, 2)
        FT, AS = 0.3048, np.pi / 180 / 3600
        row = eff.loc[name]
        assert row["vN [ft/s]"] == pytest.approx(np.sqrt(Q[:, 3, 3].mean()) / FT, rel=0.01), name
        assert row["horizontal position [ft]"] == pytest.approx(
            np.sqrt((pos[:, 0, 0] + pos[:, 1, 1]).mean()) / FT, rel=0.01), name
        assert row["tilt E [arcsec]"] == pytest.approx(np.sqrt(att[:, 1, 1].mean()) / AS, rel=0.01, abs=1e-6), name
    # the gyro misalignments act on the attitude, the accelerometer misalignments on velocity
    assert eff.loc["gyro_mis_xz", "tilt share [%]"] > 100 * eff.loc["acc_mis_xz", "tilt share [%]"]
    assert abs(eff["horizontal share [%]"].sum() - 100.0) < 1e-9


def test_member_covariances_are_checked():
    from covtool.errors import NumericalError
    from covtool.lincov.impact import check_members
    P = np.zeros((1, 1, 10, 10))
    P[0, 0] = np.eye(10)
    P[0, 0, 3, 3] = np.nan
    with pytest.raises(NumericalError, match=r"impact: filter X: nominal: t = 60 s: covariance has a non-finite entry"):
        check_members(P, np.array([[1.0, 0, 0, 0]]), np.array([60.0]), ["impact: filter X: nominal"])
    # several members and records: the first bad matrix in member order, then time, is the one named
    P = np.broadcast_to(np.eye(10), (3, 5, 10, 10)).copy()
    P[2, 0, 4, 4] = -1.0                                   # member 2, first record: a negative variance
    P[1, 3, 0, 1] = 0.5                                    # member 1, fourth record: asymmetric
    q, t = np.tile([1.0, 0, 0, 0], (5, 1)), 60.0 * np.arange(5)
    labels = ["impact: filter X: nominal", "impact: filter X: gyro put back", "impact: filter X: acc only"]
    with pytest.raises(NumericalError, match=r"impact: filter X: gyro put back: t = 180 s: covariance lost "
                                             r"symmetry"):
        check_members(P, q, t, labels)
    P[1, 3] = np.eye(10)
    with pytest.raises(NumericalError, match=r"impact: filter X: acc only: t = 0 s: covariance has a negative "
                                             r"variance"):
        check_members(P, q, t, labels)
    with pytest.raises(ValueError, match=r"check_members: 2 labels for 3 members"):
        check_members(P, q, t, labels[:2])


def test_filters_of_one_option_set_share_compositions_without_changing_the_table(S):
    """C and D share B3's navigation options: D's run after C's takes C's compositions (cache hits) and
    equals D's run on its own (issue 13: the truth transition and noise composition shared between filters)."""
    from covtool.lincov.noise import ComposedCache

    N = S.t.size - 1
    key = ("impact noise",)
    S._dyn_cache.pop(key, None)
    alone = impact_run(S, "D", [N])
    S._dyn_cache[key] = ComposedCache()
    impact_run(S, "C", [N])
    cache = S._dyn_cache[key]
    hits = cache.hits
    shared = impact_run(S, "D", [N])
    assert cache.hits > hits                                   # D's kept-state sources come from C's run
    assert shared.variants == alone.variants
    np.testing.assert_allclose(shared.P, alone.P, rtol=1e-12, atol=1e-14 * np.abs(alone.P).max())
    assert shared.noise_check < 1e-10


def test_impact_shares_keep_option_groups_together_and_balance_the_processes():
    """B1 | B2 | B3, C, D (three navigation-option sets), costs 1.0 | 1.3 | 1.7 (IMPACT_COST); this process also
    propagates 7 runs (1.05) and makes the 5 reduced filters' systems (1.5): forking B2 and B3, C, D (3.0
    against 1.0 + 2.55) leaves the smallest gap (0.55; B1 and B3, C, D: 1.15; all three: 1.45)."""
    from covtool.studies.zupt_filter_order import impact_shares
    from covtool.studies.zupt_setup import setup
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    S6 = setup(d, path=FLAGSHIP)
    assert impact_shares(S6, ["B1", "B2", "B3", "C", "D"]) == (["B2", "B3", "C", "D"], ["B1"])
    assert impact_shares(S6, ["B1", "B2"]) == (["B1", "B2"], [])          # 2.3 against 2.55
    assert impact_shares(S6, ["B3", "C", "D"]) == (["B3", "C", "D"], [])          # one group: not split
    assert impact_shares(S6, ["C", "B1"]) == (["C", "B1"], [])
    assert impact_shares(S6, []) == ([], [])


def test_impact_split_between_processes_equals_one_process(tmp_path):
    """The table assembled from the forked and the own share equals the one computed in one process."""
    import covtool.forked as forked
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    split = covtool.run_study(d).tables["impact"]
    old = forked._tracing
    forked._tracing = lambda: True                            # every Forked call runs in this process
    try:
        one = covtool.run_study(d).tables["impact"]
    finally:
        forked._tracing = old
    assert list(split["filter"].unique()) == ["B1", "B2", "B3", "C", "D"]
    assert split[["filter", "variant", "block"]].equals(one[["filter", "variant", "block"]])
    num = split.select_dtypes("number").columns
    np.testing.assert_allclose(split[num].to_numpy(float), one[num].to_numpy(float), rtol=1e-12)


def test_impact_reads_no_whole_grid_dynamics(S, monkeypatch):
    """The impact makes each chunk's truth F under the filter's own options itself (D: no Coriolis terms,
    vertical channel decoupled): on a setup that holds nothing, reading the whole-grid truth dynamics, the
    options' whole-grid F or a filter's whole-grid system fails, and the run still gives the members of the
    setup that holds them (to round-off) -- whose put-back member is the independently declared D_bias
    (test_block_put_back_equals_the_filter_that_keeps_it)."""
    from covtool.studies.zupt_setup import setup, ZuptSetup

    N = S.t.size - 1
    fresh = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)

    def refuse(*_a, **_k):
        raise AssertionError("a whole-grid array was built")

    monkeypatch.setattr(ZuptSetup, "options_dynamics", refuse)
    monkeypatch.setattr(ZuptSetup, "filter_system", refuse)
    monkeypatch.setattr(ZuptSetup, "_whole_truth", refuse)
    monkeypatch.setattr(ZuptSetup, "dyn", property(refuse))
    streamed = impact_run(fresh, "D", [N])
    monkeypatch.undo()
    held = impact_run(S, "D", [N])
    np.testing.assert_allclose(streamed.P, held.P, rtol=1e-12, atol=1e-14 * np.abs(held.P).max())


EXTRA_MARKOV = '''
[[filter]]
name = "B1_markov"
description = "B1 with the accelerometer Markov biases put back"
keep = ["nav", "acc_bias", "gyro_bias", "acc_sf", "gyro_sf", "acc_markov"]
equivalent_noise = "eq11-13"
'''


def test_put_back_block_follows_the_filters_model_under_a_truth_override(tmp_path):
    """With an override that only the truth sees, a block put back has the filter model's dynamics.

    The truth's accelerometer Markov biases get τ = 2 min; the filters keep the
    model file's 30 min (``override_filters = false``).  B1 (the truth's
    navigation options) with the block put back equals B1_markov declared on
    its own; the truth's Φ, which has the overridden τ, in the filter's place
    moved the put-back member's CEP, altitude PE and azimuth by 0.4 %.
    """
    from covtool.studies.zupt_setup import setup

    ff = tmp_path / "filters.toml"
    ff.write_text((ROOT / "models" / "filters" / "zupt_filters.toml").read_text() + EXTRA_MARKOV)
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["file"] = str(ff)
    d["filters"]["cases"] = ["B1", "B1_markov"]
    d["truth"]["override"] = {"acc_markov": {"tau": "2 min"}}
    S = setup(d, path=FLAGSHIP)
    assert S.filter_truth is not None and S.filter_truth is not S.truth
    N = S.t.size - 1
    r = impact_run(S, "B1", [N])
    b = r.variants.index((BACK, "acc_markov"))
    np.testing.assert_allclose(_metrics(S, r.P[b, -1]), _metrics(S, _reference(S, "B1_markov")), rtol=1e-7)
    np.testing.assert_allclose(_metrics(S, r.P[0, -1]), _metrics(S, _reference(S, "B1")), rtol=1e-8)


def test_streamed_impact_holds_nothing_over_the_grid_and_equals_the_held_one(S):
    """A setup that holds no whole-grid system (a long flagship's layout): the impact makes each chunk's
    truth and filter systems itself (11 min: two chunks of 600 steps), builds nothing of size N × n², and
    gives the members of the setup that holds them (whose nominal member is the step-by-step reference's,
    test above) to round-off; its nominal member equals the reference on its own too."""
    from covtool.studies.zupt_setup import setup

    N = S.t.size - 1
    S.Phi, S.filter_model("D")                                  # the whole-grid systems, sliced by the impact
    held = impact_run(S, "D", [N])
    fresh = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)
    streamed = impact_run(fresh, "D", [N])
    assert fresh._Phi is None and fresh._dyn is None and not fresh._filters
    assert streamed.variants == held.variants
    # (the held setup's cache may hold compositions from other filters' runs: equal to round-off)
    np.testing.assert_allclose(streamed.P, held.P, rtol=1e-12, atol=1e-14 * np.abs(held.P).max())
    assert streamed.noise_check < 1e-10
    np.testing.assert_allclose(_metrics(S, streamed.P[0, -1]), _metrics(S, _reference(S, "D")), rtol=1e-8)


def tomli_w_dumps(S):
    """The module fixture's declaration (11 min, filters A, B1, C, D, D_bias) as TOML text."""
    import tomli_w

    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["file"] = str(S.filter_file)
    d["filters"]["cases"] = list(S.cases)
    return tomli_w.dumps(d)


def test_flagship_streamed_layout_equals_the_whole_grid_one(monkeypatch):
    """Above WHOLE_GRID_BYTES the flagship holds no whole-grid system: both of its processes stream the impact
    (and the cases) chunk by chunk.  21 min (three chunks, B1 forked, D here): the same summary and impact
    table as the whole-grid layout, to 1e-12; the estimate it records says which layout ran."""
    import covtool.studies.zupt_setup as zs

    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "21 min"
    d["output"]["report_times"] = ["10 min", "21 min"]
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = ["A", "B1", "D"]
    whole = covtool.run_study(d)
    monkeypatch.setattr(zs, "WHOLE_GRID_BYTES", 0.0)
    streamed = covtool.run_study(d)
    for name in ("impact", "summary"):
        a, b = whole.tables[name], streamed.tables[name]
        assert a.shape == b.shape and list(a.columns) == list(b.columns)
        num = a.select_dtypes("number").columns
        np.testing.assert_allclose(b[num].to_numpy(float), a[num].to_numpy(float), rtol=1e-12, atol=0)
    assert set(streamed.tables["impact"]["filter"]) == {"B1", "D"}
    assert whole.provenance["estimated_peak_memory"] != streamed.provenance["estimated_peak_memory"]


def test_a_deferred_noise_check_is_made_from_the_filters_own_system(S):
    """A forked share that does not hold its filter's Φ_f, Q_f leaves the noise check NaN (own_systems=False);
    check_filter_noise makes it from the whole-grid system: the summed per-source filter noise equals the
    filter's own composed Q_f to round-off, as the check made chunk by chunk finds; a wrong total is caught."""
    from covtool.lincov.impact import check_filter_noise, impact_runs
    from covtool.studies.zupt_setup import setup

    N = S.t.size - 1
    fresh = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)
    deferred = impact_runs(fresh, ["B1"], [N], own_systems=False)[0]
    assert np.isnan(deferred.noise_check) and not fresh._filters
    inline = impact_runs(fresh, ["B1"], [N])[0]
    assert 0 <= inline.noise_check < 1e-10
    _, Phi_f, Qd_f = S.filter_model("B1")
    assert 0 <= check_filter_noise(deferred, Phi_f, Qd_f).noise_check < 1e-10
    np.testing.assert_array_equal(deferred.P, inline.P)
    deferred.noise_total[-1] *= 1.01                           # 1 % more noise in the last interval
    assert check_filter_noise(deferred, Phi_f, Qd_f).noise_check == pytest.approx(0.01, rel=0.05)


@pytest.mark.parametrize("order", [["C", "B1", "D"], ["D", "B2", "B1", "B3", "C"], ["B3", "B1"]])
def test_impact_rows_belong_to_their_filter_in_any_listed_order(order):
    """``[impact] filters`` in an order that interleaves the navigation-option groups (the forked share returns
    its runs grouped): each filter's rows are its own -- its nominal member is its own case's summary, its
    blocks are the ones it drops.  Found in review: B1's rows carried D's (both the old and the new split)."""
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = ["A", "B1", "B2", "B3", "C", "D"]
    d["impact"] = {"filters": order}
    r = covtool.run_study(d)
    imp = r.tables["impact"]
    summ = r.summary.set_index("case")
    assert list(dict.fromkeys(imp["filter"])) == order
    from covtool.studies.zupt_setup import setup
    S11 = setup(d, path=FLAGSHIP)
    for name in order:
        rows = imp[imp["filter"] == name]
        nom = rows[rows["variant"] == NOMINAL].iloc[0]
        assert nom["CEP [ft]"] == pytest.approx(summ.loc[name, "CEP [ft]"], rel=1e-8), name
        assert nom["alt PE [ft]"] == pytest.approx(summ.loc[name, "alt PE [ft]"], rel=1e-8), name
        assert list(rows.loc[rows["variant"] == BACK, "block"]) == dropped_blocks(S11.truth, S11.specs[name].kept)


def test_impact_table_refuses_runs_of_other_filters(S):
    from covtool.studies.zupt_filter_order import impact_table

    N = S.t.size - 1
    runs = [impact_run(S, "B1", [N]), impact_run(S, "D", [N])]
    with pytest.raises(ValueError, match=r"impact_table: runs of \['B1', 'D'\] for the filters \['D', 'B1'\]"):
        impact_table(S, ["D", "B1"], {}, runs=runs)


def test_filter_chunk_hands_over_the_dynamics_its_system_is_made_from(S):
    """ZuptSetup.filter_chunk's on_chunk sees the chunk's F_f, Q_c,f: the whole grid's slices where the study
    holds the filter's system (and its Φ_f is their discretisation), the same arrays where it is made per chunk."""
    from covtool.lincov.discretize import discretize
    from covtool.studies.zupt_setup import setup

    a, b = 0, 600
    fm, Phi_f, _, _ = S.filter_system("B1")
    seen = []
    Phi, _ = S.filter_chunk("B1", a, b, S.chunk_dynamics(a, b), on_chunk=lambda *x: seen.append(x))
    (a_, F, Qc), = seen
    assert a_ == a and np.array_equal(F, fm.F[a:b]) and np.array_equal(Qc, fm.Qc[a:b])
    np.testing.assert_array_equal(Phi, Phi_f[a:b])
    again, _ = discretize(F, Qc, np.diff(S.t)[a:b], fm.spec.discretization, fm.spec.taylor_order)
    np.testing.assert_allclose(again, Phi, rtol=0, atol=1e-12)
    fresh = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)          # nothing held: made from the chunk
    made = []
    Phi2, _ = fresh.filter_chunk("B1", a, b, fresh.chunk_dynamics(a, b), on_chunk=lambda *x: made.append(x))
    np.testing.assert_array_equal(made[0][1], F)
    np.testing.assert_array_equal(made[0][2], Qc)
    np.testing.assert_allclose(Phi2, Phi, rtol=0, atol=1e-12)


def test_a_non_finite_transition_under_the_filters_options_names_the_impact_the_filter_and_the_step(S, monkeypatch):
    """A NaN in the truth's F under D's options at grid step 640 (t = 640 s, in the second chunk): the impact's
    transition refuses it in one line naming the study, the impact, the filter, the grid step and its time."""
    from covtool.errors import NumericalError
    from covtool.lincov import dynamics
    from covtool.studies.zupt_setup import setup

    N = S.t.size - 1
    fresh = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)
    real = dynamics.DynamicsStream.chunk

    def chunk(self, a, b):
        d = real(self, a, b)
        if dynamics.dyn_key(self.options) == dynamics.dyn_key(fresh.specs["D"].options) and a <= 640 < b:
            d.F[640 - a, 3, 4] = np.nan
        return d

    monkeypatch.setattr(dynamics.DynamicsStream, "chunk", chunk)
    with pytest.raises(NumericalError, match=r"zupt_filter_order.toml: impact: filter D: truth Φ under its "
                                             r"navigation options: step 640 \(t = 640 s, Δt = 1 s\)"):
        impact_run(fresh, "D", [N])
    # C and D share that transition (B3's options): the message names both
    from covtool.lincov.impact import impact_runs
    both = setup(tomllib.loads(tomli_w_dumps(S)), path=FLAGSHIP)
    with pytest.raises(NumericalError, match=r"zupt_filter_order.toml: impact: filters C, D: truth Φ under their "
                                             r"navigation options: step 640 \(t = 640 s, Δt = 1 s\)"):
        impact_runs(both, ["B1", "C", "D"], [N])          # B1 (the truth's own options) takes the truth's Φ


def test_impact_figure_draws_the_tables_values_and_no_bar_for_an_untrusted_one():
    """Each bar of the impact figure is its table row's value; the lines the nominal and no-noise members.

    A synthetic table (two filters, blocks in a given order, a NaN and a
    negative bar value, an infinite reference): the rectangles' widths and
    rows are read back from the figure; an untrusted value has no bar (a bar
    of zero would read as "no error") but an "n/a", an untrusted reference
    line an "n/a" in the title; the legend in its order.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd
    from types import SimpleNamespace
    from matplotlib.collections import PolyCollection

    from covtool.plotting.zupt_filter_order import impact_figure

    rng = np.random.default_rng(3)
    blocks = {"F1": ["b1", "b2", "b3"], "F2": ["x", "y"]}
    rows = []
    for f, bl in blocks.items():
        for variant, block in [(NOMINAL, ""), (NONE, "")] + [(v, b) for b in bl for v in (ONLY, BACK)]:
            for t in (10.0, 30.0):                        # the last report time is drawn
                rows.append({"filter": f, "t [min]": t, "variant": variant, "block": block,
                             "CEP [ft]": rng.uniform(1, 20), "alt PE [ft]": rng.uniform(1, 50)})
    tab = pd.DataFrame(rows)
    tab.loc[(tab["filter"] == "F2") & (tab["block"] == "y") & (tab["variant"] == BACK), "alt PE [ft]"] = np.nan
    tab.loc[(tab["filter"] == "F2") & (tab["block"] == "x") & (tab["variant"] == ONLY), "CEP [ft]"] = -1.0
    tab.loc[(tab["filter"] == "F1") & (tab["variant"] == NONE), "alt PE [ft]"] = np.inf
    fig = impact_figure(SimpleNamespace(tables={"impact": tab}, report_times=[600.0, 1800.0]))
    try:
        axes = np.array(fig.axes[:4]).reshape(2, 2)
        last = tab[tab["t [min]"] == 30.0]
        for r, (f, bl) in enumerate(blocks.items()):
            assert [t.get_text() for t in axes[r, 0].get_yticklabels()] == bl
            for c, col in enumerate(("CEP [ft]", "alt PE [ft]")):
                ax = axes[r, c]
                pick = lambda v, b="": last.loc[(last["filter"] == f) & (last["variant"] == v)
                                                & (last["block"] == b), col].iloc[0]
                got = [pc.get_paths() for pc in ax.collections if isinstance(pc, PolyCollection)]
                assert len(got) == 2
                for (variant, off), paths in zip(((ONLY, -0.2), (BACK, 0.2)), got):
                    want = {(round(float(i + off), 6), pick(variant, b)) for i, b in enumerate(bl)
                            if np.isfinite(pick(variant, b)) and pick(variant, b) >= 0}
                    seen = {(round(float(p.vertices[:4, 1].mean()), 6), float(p.vertices[:4, 0].max()))
                            for p in paths}
                    assert {k: pytest.approx(v, rel=1e-15) for k, v in want} == dict(seen)
                    assert all(p.vertices[:4, 0].min() == 0.0 for p in paths)
                refs = [pick(NOMINAL), pick(NONE)]
                lines = [float(ln.get_xdata()[0]) for ln in ax.lines]
                assert lines == pytest.approx([x if np.isfinite(x) else np.nan for x in refs], nan_ok=True)
                vals = last.loc[last["filter"] == f, col]
                assert ax.get_xlim()[1] >= vals[np.isfinite(vals)].max()
                lo, hi = ax.get_ylim()
                assert hi < -0.4 and lo > len(bl) - 0.6            # every bar inside, the first block on top
        na = {(r, c): [t.get_position()[1] for t in axes[r, c].texts if t.get_text().strip() == "n/a"]
              for r in range(2) for c in range(2)}
        assert na == {(0, 0): [], (0, 1): [], (1, 0): [pytest.approx(-0.2)], (1, 1): [pytest.approx(1.2)]}
        assert axes[0, 1].get_title() == "filter F1: alt PE (no equivalent noise n/a)"
        assert axes[0, 0].get_title() == "filter F1: CEP"
        assert axes[0, 1].get_xlabel() == "true alt PE [ft] at 30 min"
        assert [t.get_text() for t in fig.legends[0].get_texts()] == [
            "nominal (all dropped blocks as noise)", "no equivalent noise",
            "(a) eq (11)-(13) noise of this block only", "(b) this block put back into the filter"]
    finally:
        plt.close(fig)
    # [output] units = "m": the same bars in metres (the table keeps ft), and the axes say so
    fig = impact_figure(SimpleNamespace(tables={"impact": tab}, report_times=[600.0, 1800.0], length_unit="m"))
    try:
        ax = fig.axes[0]
        w = max(p.vertices[:4, 0].max() for p in ax.collections[0].get_paths() if p.vertices[:4, 1].mean() < 0)
        ft = tab.loc[(tab["t [min]"] == 30.0) & (tab["filter"] == "F1") & (tab["block"] == "b1")
                     & (tab["variant"] == ONLY), "CEP [ft]"].iloc[0]
        assert w == pytest.approx(ft * 0.3048, rel=1e-15)
        assert ax.get_xlabel() == "true CEP [m] at 30 min"
    finally:
        plt.close(fig)
