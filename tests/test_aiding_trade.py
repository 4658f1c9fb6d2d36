"""The trade grid's aiding axis (issue 15): aiding mixes as one more grid axis.

* The aided path with no extra measurement (the ZUPTs alone, run by the
  aided engine with the grid's P0/Q/R scales) equals the batched ZUPT
  engine's rows (≤ 1e-9): the two paths agree on what the scales mean.
* Riccati monotonicity: under the optimal filter (A) more measurements never
  increase the covariance, so the odometer + NHC mix has CEP and altitude PE
  no larger than the ZUPTs alone.
* The store keys name the mix; a changed mix is another sweep for --resume.
* Bad declarations are one line.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.errors import StudyFileError
from covtool.io.store import StoreError
from covtool.studies.aided_trade import trade_cases
from covtool.studies.trade_grid import run, TradePlan
from covtool.studies.zupt_setup import setup

ROOT = Path(__file__).resolve().parents[1]
ODO = {"name": "odo", "measurement": [
    {"name": "odo", "kind": "odometer", "sigma": "0.02 m/s", "lever_arm": ["-1.2 m", "0.75 m", "0.9 m"],
     "schedule": {"period": "1 s", "when": "moving"}, "errors": {"scale_factor": {"sigma": "2000 ppm"}}},
    {"name": "nhc", "kind": "nhc", "sigma": ["0.05 m/s", "0.05 m/s"], "schedule": {"period": "1 s", "when": "moving"}}]}


def decl(aiding=("none", "odo"), filters=("A", "B1")) -> dict:
    d = tomllib.loads((ROOT / "studies" / "trade_grid.toml").read_text())
    d["study"].update(duration="6 min", discretization="van_loan")
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = list(filters)
    d["grid"] = {"zupt_interval": ["5 min"], "zupt_sigma": ["0.01 ft/s"], "q_scale": [1.0, 3.0]}
    d["grade"] = d["grade"][:1]
    d["output"] = {"report_times": ["4 min", "6 min"]}
    if aiding is not None:
        d["grid"]["aiding"] = list(aiding)
        d["aiding"] = [copy.deepcopy(ODO)]
    return d


@pytest.fixture(scope="module")
def grids():
    return run(decl()), run(decl(aiding=None))


COLS = ["CEP [ft]", "alt PE [ft]", "azimuth 1sigma [arcmin]", "filter-claimed CEP [ft]"]


def test_none_rows_are_the_zupt_grid(grids):
    a, b = (g.tables["summary"] for g in grids)
    none = a[a["aiding"] == "none"].drop(columns=["aiding", "case"]).reset_index(drop=True)
    np.testing.assert_allclose(none[COLS].to_numpy(), b[COLS].to_numpy(), rtol=1e-12)
    assert list(none["filter"]) == list(b["filter"])


def test_optimal_filter_is_never_worse_with_more_measurements(grids):
    s = grids[0].tables["summary"]
    a = s[s["filter"] == "A"]
    none, odo = (a[a["aiding"] == m].sort_values(["Q scale", "t [min]"]) for m in ("none", "odo"))
    q1 = (none["Q scale"] == 1.0).to_numpy()        # the optimal filter: A with its own Q
    for col in ("CEP [ft]", "alt PE [ft]"):
        assert np.all(odo[col].to_numpy()[q1] <= none[col].to_numpy()[q1] * (1 + 1e-9))
    # and the odometer is worth something: a clearly smaller CEP at 6 min
    assert odo["CEP [ft]"].to_numpy()[q1][-1] < 0.8 * none["CEP [ft]"].to_numpy()[q1][-1]
    pv = grids[0].tables["pivot_cep"]
    assert list(pv["aiding"]) == ["none", "odo"]
    assert list(grids[0].figures) == ["trade_grid_none", "trade_grid_odo"]


def test_aided_path_without_measurements_equals_the_batched_zupt_engine(grids):
    """trade_cases with an empty mix (ZUPTs only) against the batched engine's rows, all scales (≤ 1e-9)."""
    d = decl(aiding=None, filters=("B1",))
    d["grid"].update(p0_scale=[0.5, 2.0], r_scale=[0.3, 1.0])
    ref = run(d).tables["summary"]
    plan = TradePlan(d, None)
    chunk = plan.chunks[0]
    S = setup(chunk["config"], grade=chunk["grade"])
    rec = sorted({int(np.argmin(np.abs(S.t - x))) for x in S.report_times})
    res = trade_cases(S, "B1", chunk["cases"], {"name": "none", "measurement": []}, rec, "test")
    from covtool.analysis.metrics import nav_metrics
    from covtool.units import FT
    geo = (S.nodes.lat[rec], S.nodes.h[rec], S.nodes.q_nb[rec], S.nodes.distance[rec])
    got = np.array([nav_metrics(PT, *geo)["cep"] / FT for PT, _, st in res]).ravel()
    claimed = np.array([nav_metrics(PF, *geo)["cep"] / FT for _, PF, st in res]).ravel()
    assert all(st == "ok" for _, _, st in res)
    np.testing.assert_allclose(got, ref["CEP [ft]"].to_numpy(), rtol=1e-9)
    np.testing.assert_allclose(claimed, ref["filter-claimed CEP [ft]"].to_numpy(), rtol=1e-9)


def test_store_keys_name_the_mix_and_a_changed_mix_is_another_sweep(tmp_path):
    d = decl(filters=("D",))
    d["grid"]["q_scale"] = [1.0]
    r = run(d, store=tmp_path / "s")
    assert sorted(p.name for p in (tmp_path / "s").glob("chunk-*.json")) == ["chunk-g00-i00-a00.json",
                                                                            "chunk-g00-i00-a01.json"]
    again = run(d, store=tmp_path / "s", resume=True)
    assert again.provenance["chunks_reused"] == 2
    np.testing.assert_allclose(again.tables["summary"]["CEP [ft]"], r.tables["summary"]["CEP [ft]"], rtol=0)
    d["aiding"][0]["measurement"][0]["sigma"] = "0.05 m/s"
    with pytest.raises(StoreError, match=r"was written for a different sweep \(differs in: study\)"):
        run(d, store=tmp_path / "s", resume=True)


def _with(change):
    d = decl()
    change(d)
    return d


@pytest.mark.parametrize("change,match", [
    (lambda d: d["grid"].update(aiding=["none", "gnss"]),
     r"^<study>: \[grid\] aiding: 'gnss' has no \[\[aiding\]\] table \(declared: odo\)"),
    (lambda d: d["grid"].update(aiding="odo"), r"^<study>: \[grid\] aiding: expected a non-empty list of aiding mix names, got 'odo'"),
    (lambda d: d["grid"].update(aiding=["odo", "odo"]), r"^<study>: \[grid\] aiding: aiding mix name 'odo' is listed twice"),
    (lambda d: d["grid"].update(aiding=["none"]), r"^<study>: \[\[aiding\]\] 'odo': is not in \[grid\] aiding"),
    (lambda d: d["grid"].pop("aiding"), r"^<study>: \[\[aiding\]\]: declared but not used: list it in \[grid\] aiding"),
    (lambda d: d["aiding"].append({"name": "none", "measurement": ODO["measurement"]}),
     r"^<study>: \[\[aiding\]\] #2 name: 'none' is reserved"),
    (lambda d: d["aiding"][0].update(measurement=[]), r"^<study>: \[\[aiding\]\] #1 measurement: Tuple should have at least 1 item"),
    (lambda d: d.update(aiding=ODO), r"^<study>: \[aiding\]: Input should be a valid tuple"),
    (lambda d: d["aiding"].append(copy.deepcopy(ODO)), r"^<study>: \[\[aiding\]\] #2 name: 'odo' is declared twice"),
    (lambda d: d["aiding"][0]["measurement"][0].update(kind="lidar"),
     r"^<study>: \[\[aiding\]\] #1 measurement\.kind #1: 'lidar' is not one of: 'zupt', 'cupt', 'odometer'"),
    (lambda d: d["aiding"][0]["measurement"][0].update(name="zupt"),
     r"^<study>: \[\[aiding\]\] 'odo' \[\[measurement\]\] 'zupt': the name is used twice"),
    (lambda d: d["aiding"][0]["measurement"][1]["schedule"].update(end="10 min"),
     r"^<study>: \[grid\] zupt_interval = '5 min': \[\[aiding\]\] 'odo' \[\[measurement\]\] 'nhc' schedule: end 600 s"),
])
def test_bad_aiding_axis_is_one_line(change, match):
    with pytest.raises(StudyFileError, match=match):
        TradePlan(_with(change), None)


# ---------------------------------------------------------------------------
# an aiding mix streams in time: the whole-grid numbers, memory bounded


def _long_decl(duration="12 min", filters=("A", "B1", "D")):
    d = decl(filters=filters)
    d["study"]["duration"] = duration
    d["output"] = {"report_times": ["10 min", duration]}
    return d


def test_streamed_aiding_mix_equals_the_whole_grid_runs():
    """12 min (two stream chunks), filters A (the truth's own system), B1 and D (own options), Q × 1 and × 3:
    trade_cases' navigation blocks equal propagate_aided on whole-grid stacks (≤ 1e-12 of σ_i σ_j)."""
    from covtool.lincov.aided import augment, build_epochs, error_processes, Jacobians, propagate_aided
    from covtool.lincov.measurements import Zupt
    from covtool.lincov.streamed import ScaledSteps
    from covtool.studies.aided import parse_measurement

    d = _long_decl()
    plan = TradePlan(d, None)
    chunk = next(c for c in plan.chunks if c["aiding"]["measurement"])
    St = setup(chunk["config"], grade=chunk["grade"])             # streamed only
    S = setup(chunk["config"], grade=chunk["grade"])              # the whole-grid reference
    rec = sorted({int(np.argmin(np.abs(S.t - x))) for x in S.report_times})
    meas = [parse_measurement(m, i, "t") for i, m in enumerate(chunk["aiding"]["measurement"])]
    states = [s for m, _ in meas for s in m.states]
    names_all = list(S.truth.names) + [s.name for s in states]
    err = error_processes(states, np.diff(S.t))[:2]
    for f in ("A", "B1", "D"):
        cs = [c for c in chunk["cases"] if c["filter"] == f]
        got = trade_cases(St, f, cs, chunk["aiding"], rec, "test")
        assert St._Phi is None and (f, None) not in St._filters   # nothing over the whole grid
        assert St.streamed_system().Phi.shape[0] == St.t.size - 1 > 600
        fm, Phi_f, Qd_f, _ = S.filter_system(f)
        P0a, Pf_e, D = augment(S.P0, fm.D, states, [s.name for s in states])
        fnames = list(fm.names) + [s.name for s in states]
        for c, (PT, PF, st) in zip(cs, got):
            assert st == "ok"
            sig = float(c["_sigma"])
            fsig = sig if S.specs[f].zupt_sigma is None else float(S.specs[f].zupt_sigma)
            z = Zupt(name="zupt", sigma=np.full(3, sig), filter_sigma=np.full(3, fsig))
            pairs = [(z, S.update_steps)] + [(m, sch.steps(S.t, S.nodes)) for m, sch in meas]
            Pf0 = np.zeros((len(fnames),) * 2)
            Pf0[:fm.P0.shape[0], :fm.P0.shape[0]], Pf0[fm.P0.shape[0]:, fm.P0.shape[0]:] = fm.P0, Pf_e
            q = float(c["Q scale"])
            ref = propagate_aided(S.Phi, S.Qd, P0a, Phi_f, Qd_f * q, Pf0, D,
                                  build_epochs(pairs, S.nodes, names_all, fnames, jacobians=Jacobians(S.nodes)),
                                  err=err, err_f=(err[0], err[1] * q), record=rec, form=S.specs[f].update,
                                  times=S.t, names=names_all, filter_names=fnames)
            for a, b in ((PT, ref.P_truth[:, :10, :10]), (PF, ref.P_filter[:, :10, :10])):
                s_ = np.sqrt(np.abs(np.einsum("kii->ki", b)))
                s_[:, 6:10] = s_[:, 6:10].max(axis=1, keepdims=True)
                assert np.max(np.abs(a - b) / (s_[:, :, None] * s_[:, None, :])) <= 1e-12, (f, c["case"])
        assert ScaledSteps(St.streamed_system(f).Qd, 3.0)[5].tolist() == (3.0 * St.streamed_system(f).Qd[5]).tolist()
    assert St.streamed_system("A") is St.streamed_system()              # filter A reads the truth's own system


def test_aiding_mix_memory_estimate_bounds_its_peak():
    """A 12-min grid of filters A and D with an aiding mix, in one process: traced peak ≤ the estimate ≤ 6 × the peak."""
    from memory_peaks import traced_peak

    d = _long_decl(filters=("A", "D"))
    d["grid"]["aiding"] = ["odo"]
    plan = TradePlan(d, None)
    est = plan.memory(1)["bytes"]
    _, peak = traced_peak(lambda: run(d), warm=True)
    assert 0 < peak <= est <= 6.0 * peak, (peak, est)
    # 24 h of the same grid: under a third of what whole-grid systems need (the estimate before it streamed)
    from covtool.studies.resources import memory_estimate, noise_columns, steps_of

    d = _long_decl("24 h")
    d["grid"]["aiding"] = ["odo"]
    plan = TradePlan(d, None)
    whole = memory_estimate(steps_of(86400.0, 1.0), plan.n_truth, filters=list(plan.states.values()),
                            dynamics=plan.dynamics, noise=noise_columns(plan.truth_decl))["bytes"]
    long = plan.memory(1)["bytes"]
    assert long < 5e9 and 3.0 * long < whole, (long, whole)


@pytest.mark.parametrize("target", ["truth model 'sdins58'", "filter B1"])
def test_a_bad_streamed_chunk_stops_the_grid_naming_its_step(nan_in_qd, target):
    """A NaN in Q_d at t = 700 s of the truth's or B1's system (made in the second chunk, inside the runs):
    the grid stops with the guard's own message, as on the whole grid; not a flagged case, no "gain at" prefix."""
    from covtool.errors import SystemCheckError

    nan_in_qd(target.split()[-1].strip("'"), 700.0)
    d = _long_decl(filters=("B1",))
    d["grid"]["aiding"] = ["odo"]
    with pytest.raises(SystemCheckError, match=rf"^<study>: {target}: Q_d of the step at t = 700\.0 s \(11\.7 min\): "
                                               r"covariance has a non-finite entry \(nan\) in state 'dvN'$"):
        run(d)
