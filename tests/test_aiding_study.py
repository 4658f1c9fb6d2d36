"""The 'aided' study kind (issue 15): bad measurement declarations, the optimal filter's bound, the CLI.

Acceptance 5: an unknown kind, a missing σ, a schedule outside the trajectory
and a lever arm with the wrong unit are one-line errors naming the file and
the field, before any computation, and exit status 2 from the CLI.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from covtool.cli import main
from covtool.errors import NumericalError, StudyFileError
from covtool.studies.aided import run

ROOT = Path(__file__).resolve().parents[1]
ODO = ROOT / "studies" / "aided_odometer_nhc.toml"


def odo_decl(duration="6 min") -> dict:
    d = tomllib.loads(ODO.read_text())
    d["study"]["duration"] = duration
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["output"]["report_times"] = [duration]
    return d


def with_meas(change, i=0):
    d = odo_decl()
    change(d["measurement"][i])
    return d


BAD = [
    ("unknown kind", lambda m: m.update(kind="lidar"),
     r"\[\[measurement\]\] 'odo' kind: unknown measurement kind 'lidar' \(one of: baro, cupt, gnss_position"),
    ("missing sigma", lambda m: m.pop("sigma"),
     r"\[\[measurement\]\] 'odo' sigma: missing: the odometer's white-noise 1σ \(a velocity\)"),
    ("sigma wrong unit", lambda m: m.update(sigma="0.02 m"),
     r"\[\[measurement\]\] 'odo' sigma: .*velocity"),
    ("sigma per component count", lambda m: m.update(sigma=["0.02 m/s", "0.02 m/s"]),
     r"'odo' sigma: 2 values for the 1 components \(along\) of an odometer"),
    ("lever arm wrong unit", lambda m: m.update(lever_arm=["-1.2 m", "0.75 deg", "0.9 m"]),
     r"\[\[measurement\]\] 'odo' lever_arm\[1\]: .*length"),
    ("lever arm not three", lambda m: m.update(lever_arm=["1 m", "2 m"]),
     r"'odo' lever_arm: expected three lengths \(body x, y, z\)"),
    ("schedule after the end", lambda m: m.update(schedule={"period": "1 s", "end": "10 min"}),
     r"\[\[measurement\]\] 'odo' schedule: end 600 s is outside the study \[0, 360\] s"),
    ("outage outside", lambda m: m.update(schedule={"period": "1 s", "outages": [["5 min", "7 min"]]}),
     r"'odo' schedule: outage \[300, 420\] s is not a window inside the study \[0, 360\] s"),
    ("explicit time outside", lambda m: m.update(schedule={"at": ["1 min", "8 min"]}),
     r"'odo' schedule: update time 480 s is outside the study"),
    ("stationary at a moving time", lambda m: m.update(schedule={"period": "1 min", "when": "stationary"}),
     r"'odo' schedule: update at t = 0 s is not at a stop of the trajectory"),
    ("off the grid", lambda m: m.update(schedule={"period": "1.5 s"}),
     r"'odo' schedule: update time 1.5 s is not on the 1 s grid"),
    ("unknown error state", lambda m: m["errors"].update(bias={"sigma": "0.1 m/s"}),
     r"'odo' errors.bias: an odometer has no error state 'bias' \(known: scale_factor, scale_factor_markov, "),
    ("missing error sigma", lambda m: m["errors"]["scale_factor"].pop("sigma"),
     r"'odo' errors.scale_factor sigma: missing: the initial 1σ \(a dimensionless\)"),
    ("markov without tau", lambda m: m["errors"]["scale_factor"].update(process="markov"),
     r"'odo' errors.scale_factor: missing required key 'tau'"),
    ("tau on a constant", lambda m: m["errors"]["scale_factor"].update(tau="1 h"),
     r"'odo' errors.scale_factor tau: only a markov state has a correlation time"),
    ("unknown key", lambda m: m.update(rate="1 Hz"),
     r"\[\[measurement\]\] 'odo'.*rate"),
    ("lever arm on a kind without one", lambda m: m.update(kind="baro", sigma="1 m", errors={}, lever_arm=["0 m"] * 3),
     r"'odo' lever_arm: a baro takes no lever arm"),
]


@pytest.mark.parametrize("case, change, message", BAD, ids=[b[0] for b in BAD])
def test_bad_measurement_declaration_is_one_line(case, change, message):
    with pytest.raises(StudyFileError, match=message) as exc:
        run(with_meas(change), path=None)
    assert "\n" not in str(exc.value) and str(exc.value).startswith("<study>: [[measurement]]")


def test_variant_dropping_an_unknown_state():
    d = odo_decl()
    d["filters"]["variant"][0]["drop"] = ["odo_bias"]
    with pytest.raises(StudyFileError, match=r"\[\[filters.variant\]\] #1 drop: .*odo_bias"):
        run(d)


def test_duplicate_measurement_names():
    d = odo_decl()
    d["measurement"][1]["name"] = "odo"
    with pytest.raises(StudyFileError, match=r"\[\[measurement\]\] 'odo': the name is used twice"):
        run(d)


def test_no_measurement():
    d = odo_decl()
    del d["measurement"]
    with pytest.raises(StudyFileError, match=r"an aided study needs at least one measurement"):
        run(d)


def test_cli_prints_one_line_and_exits_2(tmp_path, capsys):
    d = with_meas(lambda m: m.update(lever_arm=["-1.2 m", "0.75 s", "0.9 m"]))
    p = tmp_path / "bad.toml"
    p.write_text(tomli_w.dumps(d))
    rc = main(["run", str(p), "--out", str(tmp_path / "out"), "--quiet", "--no-figures"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith(f"covtool: error: {p}: [[measurement]] 'odo' lever_arm[1]:")
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def small_run():
    return run(odo_decl("6 min"))


def test_optimal_filter_bounds_every_filter(small_run):
    """Filter A is the Kalman filter of the truth itself: no filter's truth CEP is below it, and its claim is exact."""
    s = small_run.summary
    a = s[s["case"] == "A"].iloc[0]
    others = s[~s["case"].isin(["A", "pure_ins"])]
    assert len(others) == 5
    assert np.all(others["CEP [m]"] >= a["CEP [m]"] * (1 - 1e-9))
    assert np.all(others["alt PE [m]"] >= a["alt PE [m]"] * (1 - 1e-9))
    np.testing.assert_allclose(a["filter-claimed CEP [m]"], a["CEP [m]"], rtol=1e-9)
    pure = s[s["case"] == "pure_ins"].iloc[0]
    assert pure["CEP [m]"] > 10 * a["CEP [m]"]


def test_dropping_the_odometer_scale_factor_is_costed(small_run):
    """Acceptance 4: the impact table shows the cost of B1 without the odometer scale-factor state."""
    imp = small_run.tables["measurement_state_impact"]
    row = imp[imp["filter"] == "B1 no odo SF"].iloc[0]
    s = small_run.summary
    b1 = s[s["case"] == "B1"].iloc[0]
    v = s[s["case"] == "B1 no odo SF"].iloc[0]
    assert row["dropped states"] == "odo_scale_factor"
    np.testing.assert_allclose(row["CEP base [m]"], b1["CEP [m]"], rtol=1e-12)
    np.testing.assert_allclose(row["CEP [m]"], v["CEP [m]"], rtol=1e-12)
    np.testing.assert_allclose(row["CEP cost [%]"], 100 * (v["CEP [m]"] / b1["CEP [m]"] - 1), rtol=1e-9)
    assert row["CEP cost [%]"] > 20            # the scale factor matters (2000 ppm at 47 km/h)
    bs = imp[imp["filter"] == "B1 no boresight"].iloc[0]
    assert abs(bs["CEP cost [%]"]) < 1         # the boresight enters through v_b,y and v_b,z ≈ 0: second order
    assert v["states"] == b1["states"] - 1


@pytest.mark.parametrize("bad, problem", [(np.nan, r"non-finite entry \(nan\)"), (-1.0, r"negative variance")])
def test_aided_study_refuses_an_invalid_process_noise(bad, problem, monkeypatch):
    """A bad truth Q_d at one step (the discretiser's output) stops the study with the time and the state."""
    import covtool.studies.grid as grid
    original = grid.discretize_chunked
    calls = []

    def poisoned(F, Qc, dt, method, order=None, **kw):
        Phi, Qd = original(F, Qc, dt, method, order, **kw)
        if not calls:                                   # the truth is discretised first
            Qd = Qd.copy()
            Qd[7, 3, 3] = bad * (abs(Qd[7, 3, 3]) or 1.0) if bad < 0 else bad
        calls.append(1)
        return Phi, Qd

    monkeypatch.setattr(grid, "discretize_chunked", poisoned)
    with pytest.raises(NumericalError, match=r"Q_d of the step at t = 7\.0 s: covariance has a " + problem
                                        + r".* state 'dvN'"):
        run(odo_decl("2 min"))


def test_gnss_outage_table_and_grade_monotonicity():
    """One outage row per grade, filter and window; under the optimal filter a worse grade never does better.

    Riccati monotonicity: a larger P0 and Q give a larger optimal covariance, so
    filter A's CEP is ordered by grade at every time, in and out of the outage.
    """
    d = tomllib.loads((ROOT / "studies" / "aided_gnss_outage.toml").read_text())
    d["study"]["duration"] = "4 min"
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = ["A"]
    for m in d["measurement"]:
        m["schedule"]["outages"] = [["2 min", "3 min"]]
    d["grade"] = [d["grade"][0], d["grade"][2]]
    d["output"]["report_times"] = ["2 min", "3 min", "4 min"]
    r = run(d)
    out = r.tables["outages"]
    assert len(out) == 2 and set(out["measurements"]) == {"gnss, gnss_vel"}
    nav, tac = (out[out["grade"] == g].iloc[0] for g in ("navigation", "tactical"))
    assert tac["CEP at end [m]"] > nav["CEP at end [m]"] > nav["CEP at start [m]"]
    h = r.tables["history"]
    a, b = (h[h["grade"] == g]["CEP [m]"].to_numpy() for g in ("navigation", "tactical"))
    assert np.all(b >= a * (1 - 1e-9))
    # the outage row is the history at the window's ends
    hn = h[h["grade"] == "navigation"].set_index("t [s]")
    np.testing.assert_allclose([nav["CEP at start [m]"], nav["CEP at end [m]"]], hn.loc[[120.0, 180.0], "CEP [m]"],
                               rtol=1e-12)


def test_pads_sparse_updates_table():
    """ZUPT + CUPT at the stops: the CUPT brings every filter's CEP down to the fix's (0.1 m per axis: 0.118 m)."""
    d = tomllib.loads((ROOT / "studies" / "aided_pads_survey.toml").read_text())
    d["study"]["duration"] = "10 min"
    d["trajectory"].update(cycles=2, distance="5 km")
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = ["A", "D"]
    d["measurement"][1]["schedule"].update(period="5 min", start="5 min")
    d["output"]["report_times"] = ["4 min", "9 min"]
    r = run(d)
    up = r.tables["sparse_updates"]
    assert set(up["measurement"]) == {"zupt", "cupt"}
    cupt = up[up["measurement"] == "cupt"]
    assert len(cupt) == 4 and list(cupt["t [min]"]) == [5.0, 10.0, 5.0, 10.0]
    cep_fix = 0.1 * 1.1774100225154747                 # CEP of a circular 2-D normal: σ √(2 ln 2)
    assert np.all(cupt["CEP before [m]"] > 10 * cep_fix)
    a = cupt[cupt["case"] == "A"]
    assert np.all(a["CEP after [m]"] <= cep_fix) and np.all(a["CEP after [m]"] > 0.97 * cep_fix)
    assert np.all(cupt["CEP after [m]"] < 1.05 * cep_fix)


def test_memory_limit_is_checked_before_computing():
    d = odo_decl("24 h")
    d["study"]["max_memory"] = "2 GB"
    d["trajectory"].update(cycles=288)
    with pytest.raises(StudyFileError, match=r"<study>: \[study\]: needs about .* GB of memory "
                                             r"\(86,400 steps.*more than the 2 GB \[study\] max_memory"):
        run(d)


def test_error_state_named_like_a_truth_block():
    """A measurement 'gyro' with a heading bias would make a state 'gyro_bias', the truth's gyro-bias block."""
    d = odo_decl()
    d["measurement"].append({"name": "gyro", "kind": "heading", "sigma": "1 deg", "schedule": {"period": "10 s"},
                             "errors": {"bias": {"sigma": "2 deg"}}})
    with pytest.raises(StudyFileError, match=r"\[\[measurement\]\] 'gyro' name: its error state 'gyro_bias' has "
                                             r"the name of a truth-model state or block"):
        run(d)
