"""Model library: validation errors name file, state and problem; round-trip; CLI (issue 2, acc. 6)."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.cli import main
from covtool.errors import ModelFileError
from covtool.io.model_file import dump_model, load_model, model_from_dict

ROOT = Path(__file__).resolve().parents[1]
SDINS = ROOT / "models" / "sdins58.toml"


@pytest.fixture(scope="module")
def decl():
    return tomllib.loads(SDINS.read_text())


def _block(decl, kind):
    return next(b for b in decl["block"] if b["kind"] == kind)


def test_truth_model_has_58_states_with_table2_values(decl):
    m = model_from_dict(decl)
    assert m.n == 58
    sig = {s.name: s.sigma for s in m.states}
    ug, degh = 9.80665e-6, np.pi / 180 / 3600
    assert sig["acc_bias_x"] == pytest.approx(20 * ug) and sig["acc_bias_z"] == pytest.approx(30 * ug)
    assert sig["gyro_bias_y"] == pytest.approx(0.018 * degh) and sig["gyro_bias_z"] == pytest.approx(0.025 * degh)
    assert sig["acc_sf_y"] == pytest.approx(35e-6) and sig["gyro_sf_z"] == pytest.approx(35e-6)
    assert sig["dvN"] == pytest.approx(0.0003048) and sig["dq3"] == pytest.approx(1.45e-3)
    assert sig["dq1"] == pytest.approx(0.73e-4) and sig["dq0"] == 0.0
    assert m.names[:10] == ["dL", "dl", "dh", "dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3"]


def test_round_trip_load_dump_load():
    m1 = load_model(SDINS)
    m2 = model_from_dict(tomllib.loads(dump_model(m1)), path=str(SDINS))
    assert m1 == m2
    np.testing.assert_array_equal(m1.initial_covariance(), m2.initial_covariance())


@pytest.mark.parametrize("mutate,match", [
    (lambda d: _block(d, "accel_bias").update(colour="red"),
     r"x.toml: block 2 \(accel_bias\): unknown key 'colour'"),
    (lambda d: _block(d, "gyro_bias").update(sigma="0.018 deg/hr/s"),
     r"x.toml: state 'gyro_bias_x': sigma: '0.018 deg/hr/s' is not an angular rate"),
    (lambda d: _block(d, "gyro_bias").update(sigma="0.018 deg/blorp"),
     r"x.toml: state 'gyro_bias_x': sigma: '0.018 deg/blorp': unknown unit"),
    (lambda d: _block(d, "accel_scale_factor").update(sigma="35 arcsec"),
     r"x.toml: state 'acc_sf_x': sigma: '35 arcsec' is not a dimensionless"),
    (lambda d: _block(d, "accel_bias").update(sigma=["20 ug", "-20 ug", "30 ug"]),
     r"x.toml: state 'acc_bias_y': sigma: '-20 ug' is negative"),
    (lambda d: d["block"].append({"kind": "accel_bias", "sigma": "1 ug"}),
     r"x.toml: state 'acc_bias_x': duplicate state name"),
    (lambda d: _block(d, "gyro_markov_drift").pop("tau"),
     r"x.toml: state 'gyro_markov_x': process 'markov' needs a correlation time 'tau'"),
    (lambda d: d.update(correlation=[{"states": ["acc_bias_x", "acc_sf_x"], "rho": 0.9},
                                     {"states": ["acc_bias_x", "acc_mis_xy"], "rho": 0.9},
                                     {"states": ["acc_sf_x", "acc_mis_xy"], "rho": -0.9}]),
     r"x.toml: correlation: initial covariance is not positive semi-definite"),
    (lambda d: d.update(correlation=[{"states": ["acc_bias_x", "acc_sf_x"], "rho": 1.5}]),
     r"x.toml: correlation 1: rho: 1.5 is not a correlation coefficient"),
    (lambda d: _block(d, "accel_bias").update(kind="accel_biass"),
     r"x.toml: block 2 \(accel_biass\): kind: unknown block kind 'accel_biass'"),
    (lambda d: _block(d, "accel_bias").update(process="markov_distance", distance="1 km"),
     r"process: 'markov_distance' is not allowed for kind 'accel_bias'"),
    (lambda d: _block(d, "navigation").update(velocity_sigma="0.001 ft"),
     r"x.toml: state 'dvN': sigma: '0.001 ft' is not a velocity"),
    (lambda d: _block(d, "accel_bias").update(sigma=["20 ug", "20 ug"]),
     r"sigma: expected 3 values, got 2"),
    (lambda d: _block(d, "accel_bias").update(unit="deg/h"),
     r"x.toml: state 'acc_bias_x': unit: 'deg/h' is not a unit of acceleration"),
])
def test_model_file_errors_name_file_state_and_problem(decl, mutate, match):
    d = copy.deepcopy(decl)
    mutate(d)
    with pytest.raises(ModelFileError, match=match):
        model_from_dict(d, path="x.toml")


def test_valid_correlation_is_accepted(decl):
    d = copy.deepcopy(decl)
    d["correlation"] = [{"states": ["acc_bias_x", "acc_sf_x"], "rho": 0.5}]
    P = model_from_dict(d).initial_covariance()
    m = model_from_dict(d)
    i, j = m.index["acc_bias_x"], m.index["acc_sf_x"]
    assert P[i, j] == pytest.approx(0.5 * np.sqrt(P[i, i] * P[j, j]))


def test_toml_syntax_and_missing_file_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[model\nname='x'")
    with pytest.raises(ModelFileError, match=r"bad.toml: TOML syntax error"):
        load_model(bad)
    with pytest.raises(ModelFileError, match=r"nope.toml: file not found"):
        load_model(tmp_path / "nope.toml")


def test_initial_quaternion_covariance_keeps_physical_errors():
    """P0's δq block is rotated to the initial attitude; tilt and azimuth σ do not change."""
    from covtool.nav import attitude as quat
    m = load_model(SDINS)
    for yaw in (0.0, 1.0, np.pi):
        q0 = quat.from_euler(0.01, -0.02, yaw)
        P = m.initial_covariance(q0)[6:10, 6:10]
        M = quat.attitude_error_matrix(q0)
        s = np.sqrt(np.diag(M @ P @ M.T))
        np.testing.assert_allclose(s, [1.46e-4, 1.46e-4, 2.9e-3], rtol=1e-9)
        assert abs(q0 @ P @ q0) < 1e-20            # no norm error


def test_cli_models_and_show(capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert "sdins58" in out and "58" in out
    assert main(["show", "sdins58"]) == 0
    out = capsys.readouterr().out
    assert "gyro_bias_z" in out and "W_dz" in out and "deg/h" in out and "0.025" in out


def test_cli_show_unknown_model_is_a_clear_error(capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    assert main(["show", "sdins99"]) == 2
    assert "sdins99: no such model" in capsys.readouterr().err


def test_ad_reset_states_take_sigma_from_board_parameters(decl):
    """The AD-reset velocity-error σ is B/√3 with B = SF |N_e| / N̂ (seed 000, eq (7)-(8))."""
    m = model_from_dict(decl)
    sf, n_t, n_e = 0.063611, 1066.5, 0.02 * 1066.5
    bound = sf * n_e / (n_t + n_e)
    assert m.states[m.index["acc_ad_x"]].sigma == pytest.approx(bound / np.sqrt(3), rel=1e-6)
    d = copy.deepcopy(decl)
    blk = _block(d, "ad_reset_velocity")
    blk["board"] = {"sf": "0.063611 m/s", "n_t": 1066.5}
    with pytest.raises(ModelFileError, match=r"board: missing required key 'n_e_ratio'"):
        model_from_dict(d, path="x.toml")
    blk["board"] = {"sf": "0.063611 m/s", "n_t": 1066.5, "n_e_ratio": 0.02}
    blk["sigma"] = "1 mm/s"
    with pytest.raises(ModelFileError, match=r"give either 'sigma' or 'board', not both"):
        model_from_dict(d, path="x.toml")


def test_truth_model_doc_is_in_step_with_the_model_file():
    """docs/truth_model.md carries the generated state table of the current model file."""
    from covtool.io.library import markdown_table
    doc = (ROOT / "docs" / "truth_model.md").read_text()
    assert markdown_table(load_model(SDINS)) in doc, "regenerate: covtool show sdins58 --markdown"


def test_library_lists_truth_models_filters_and_imu_grades():
    """`covtool models`: the truth models, every declared filter with its kept states (seed 002 Table 1:
    58, 22, 22, 22, 16, 10) and the IMU grades, each with its file."""
    from covtool.io.library import list_models

    df = list_models()
    assert set(df["kind"]) == {"truth model", "filter", "IMU grade"}
    zupt = df[df["file"].str.endswith("zupt_filters.toml")].set_index("name")["states"].to_dict()
    assert zupt == {"A": 58, "B1": 22, "B2": 22, "B3": 22, "C": 16, "D": 10}
    grades = df[df["kind"] == "IMU grade"]
    assert {"kimu", "main_imu", "nav_grade_sdins"} <= set(grades["name"])
    assert all(Path(f).is_file() for f in df["file"])
    assert not df["description"].str.startswith("INVALID").any()


def test_library_listing_names_an_invalid_filter_file(tmp_path):
    import shutil

    from covtool.io.library import list_models

    shutil.copy(ROOT / "models" / "sdins58.toml", tmp_path / "sdins58.toml")
    (tmp_path / "filters").mkdir()
    (tmp_path / "filters" / "two.toml").write_text(
        '[[filter]]\nname = "a"\ntruth = "sdins58"\nkeep = "all"\n\n'
        '[[filter]]\nname = "b"\ntruth = "other"\nkeep = "all"\n')
    row = list_models(tmp_path).set_index("name").loc["two"]
    assert row["kind"] == "filter" and row["states"] == 0
    assert row["description"].startswith("INVALID: ") and row["description"].endswith(
        "two.toml: truth: the filters name 2 truth models ('other', 'sdins58'); listing needs one")


def test_library_listing_of_filters_without_a_truth_to_project(tmp_path):
    from covtool.io.library import list_models

    (tmp_path / "filters").mkdir()
    (tmp_path / "filters" / "f.toml").write_text('[[filter]]\nname = "a"\nkeep = "all"\n')
    row = list_models(tmp_path).set_index("name").loc["f"]
    assert row["description"] == f"INVALID: {tmp_path / 'filters' / 'f.toml'}: no valid truth model in the library to project the filters of"
