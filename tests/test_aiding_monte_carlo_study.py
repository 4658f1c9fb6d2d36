"""The ``monte_carlo`` study kind with declared measurements (issue 15).

``studies/monte_carlo_aided.toml`` shortened (2 min, filter B1, 60 runs as in the shipped study):
run through :func:`covtool.run_study`, every cell must pass the acceptance test
of the ZUPT Monte Carlo (T = time-mean RMS²/σ_cond² against the linear-MC
null, Bonferroni; its size and power: ``tests/test_aided_mc_null.py``), and
the null of T must be centred on 1 (σ_cond, from the covariance recursion, is
the expectation of the sampled mean squares); its linear σ must be the
``aided`` kind's for the same declaration (an independent run of the aided
study, ≤ 1e-9 relative).
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

import covtool
from covtool.analysis.consistency import rms_bounds
from covtool.errors import StudyFileError

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "monte_carlo_aided.toml"


def short_decl():
    d = tomllib.loads(STUDY.read_text())
    d["study"]["duration"] = "2 min"
    d["filters"] = {"file": str(ROOT / "models" / "filters" / "zupt_filters.toml"), "cases": ["B1"]}
    d["monte_carlo"]["runs"] = 60
    return d


@pytest.fixture(scope="module")
def result():
    return covtool.run_study(short_decl())


def test_every_cell_passes_the_acceptance_test(result, capsys):
    s = result.summary
    assert list(s["quantity"]) == ["north", "east", "down", "horizontal", "azimuth"]
    lo, hi = rms_bounds(1.0, 60, 1.0, confidence=0.99)
    with capsys.disabled():
        print("\n" + s[["case", "quantity", "mean RMS/σ", "conditional: inside [%]",
                        "null: inside 5th percentile [%]", "T = time-mean RMS^2/sigma_cond^2", "z = (T-1)/std",
                        "p-value", "verdict"]].to_string(index=False))
    alpha = 0.01 / 5                                   # confidence 0.99, Bonferroni over 5 cells
    for _, row in s.iterrows():
        assert row["cell false-alarm rate"] == pytest.approx(alpha, rel=1e-12)
        assert row["verdict"] == "accept" and row["p-value"] >= alpha, row.to_dict()
        # the null of T is centred on 1 within 4 standard errors of its 100 replicas
        assert abs(row["T null mean"] - 1.0) < 4 * row["T null std"] / np.sqrt(100), row.to_dict()
        assert 0 <= row["null: inside 5th percentile [%]"] <= 100
        if row["quantity"] != "horizontal":          # 1 dof per run: the one-time bounds of RMS/σ
            assert row["ratio lower bound"] == pytest.approx(lo, rel=1e-12)
            assert row["ratio upper bound"] == pytest.approx(hi, rel=1e-12)
    assert result.provenance["verdict"] == "pass"
    h = result.tables["history"]
    for q in ("north", "east", "down", "azimuth"):
        x = h[(h["quantity"] == q) & (h["t [s]"] > 0)]
        inside = (x["RMS"] >= x["conditional lower bound"]) & (x["RMS"] <= x["conditional upper bound"])
        row = s[s["quantity"] == q].iloc[0]
        assert 100 * inside.mean() == pytest.approx(row["conditional: inside [%]"], abs=1e-9), q


def test_no_null_replicas_no_verdict():
    d = short_decl()
    d["study"]["duration"] = "20 s"
    d["monte_carlo"].update(null_replicas=0, runs=4)
    r = covtool.run_study(d)
    assert set(r.summary["verdict"]) == {"no test (null_replicas = 0)"}
    assert r.provenance["verdict"] == "none (null_replicas = 0)"
    assert "T null std" not in r.summary


def test_too_few_null_replicas_are_refused():
    d = short_decl()
    d["monte_carlo"]["null_replicas"] = 5
    with pytest.raises(StudyFileError, match=r"<study>: \[monte_carlo\] null_replicas: 5 replicas cannot give a null "
                                             r"distribution; use at least 10"):
        covtool.run_study(d)


def test_linear_sigma_is_the_aided_kinds(result):
    d = short_decl()
    del d["monte_carlo"]
    d["study"]["kind"] = "aided"
    d["filters"]["pure_ins"] = False
    d["output"] = {"history_every": "1 s", "report_times": ["2 min"]}
    ah = covtool.run_study(d).tables["history"]
    ah = ah[ah["case"] == "B1"]
    h = result.tables["history"]
    for q, col in (("north", "sigma_N [m]"), ("east", "sigma_E [m]"), ("down", "sigma_D [m]"),
                   ("azimuth", "azimuth [arcmin]")):
        x = h[h["quantity"] == q]
        np.testing.assert_array_equal(x["t [s]"].to_numpy(), ah["t [s]"].to_numpy())
        a, b = x["linear σ"].to_numpy(), ah[col].to_numpy()
        assert b.max() > 0
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * b.max(), err_msg=q)


def test_zupt_next_to_measurements_is_refused():
    d = short_decl()
    d["zupt"] = {"interval": "5 min"}
    with pytest.raises(StudyFileError, match=r"<study>: \[zupt\]: a Monte Carlo with \[\[measurement\]\] declares "
                                             r"its ZUPTs as a measurement"):
        covtool.run_study(d)


@pytest.mark.parametrize("key, value", [("runs_per_chunk", 10), ("nees_every", "10 s")])
def test_zupt_only_monte_carlo_keys_are_refused(key, value):
    d = short_decl()
    d["monte_carlo"][key] = value
    with pytest.raises(StudyFileError, match=rf"<study>: \[monte_carlo\] {key}: not used with \[\[measurement\]\]"):
        covtool.run_study(d)


def test_filters_pure_ins_is_refused():
    d = short_decl()
    d["filters"]["pure_ins"] = True
    with pytest.raises(StudyFileError, match=r"<study>: \[filters\]: unknown key 'pure_ins'"):
        covtool.run_study(d)


def test_shipped_study_declaration():
    d = tomllib.loads(STUDY.read_text())
    assert d["study"]["kind"] == "monte_carlo" and "zupt" not in d
    assert {m["kind"] for m in d["measurement"]} == {"odometer", "nhc"}
    assert 30 <= d["monte_carlo"]["runs"] <= 60


@pytest.mark.parametrize("opt", [{"resume": True}, {"backend": "serial"}])
def test_workers_and_resume_are_refused(opt, tmp_path):
    with pytest.raises(StudyFileError, match=r"<study>: \[\[measurement\]\]: a Monte Carlo with declared measurements "
                                             r"runs in-process in one piece; it takes no --workers"):
        covtool.run_study(short_decl(), store=tmp_path / "cases", **opt)


def test_resolved_declaration_runs_again(result):
    """The resolved study keeps the file's forms and the defaults: it is itself a valid declaration."""
    mc = result.resolved["monte_carlo"]
    assert mc == {"runs": 60, "seed": 1, "imu_rate": "100 Hz", "samples_per_step": 4, "confidence": 0.99,
                  "sensor_noise": True, "measurement_noise": True, "null_replicas": 100}
    from covtool.studies.monte_carlo import mc_options
    assert mc_options(result.resolved, "<resolved>")["imu_rate"] == 100.0
