"""Sensitivity sweep of a declared measurement's σ in the aided kind (issue 15).

Closed form: a CUPT on a static vehicle under the optimal filter (A, the
truth itself).  With the prior NED position covariance P⁻ (the same for every
scale: nothing updates before the fix) and the fix's R = diag(σ s)²:

* ``what = "sigma"`` (the sensor's σ, truth and filter): the information
  form, ``P⁺ = (P⁻⁻¹ + R⁻¹)⁻¹``;
* ``what = "filter_sigma"`` (only what the filter assumes, R_f = s² R): the
  Joseph form with the mistuned gain ``G = P⁻ (P⁻ + R_f)⁻¹``,
  ``P⁺ = (I − G) P⁻ (I − G)ᵀ + G R Gᵀ``, smallest at s = 1.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from covtool.errors import StudyFileError
from covtool.lincov.dynamics import Context, error_dynamics
from covtool.lincov.discretize import discretize
from covtool.lincov.measurements.base import ned_metres
from covtool.lincov.reference import propagate
from covtool.nav.trajectory.profiles import static
from covtool.studies.aided import run
from covtool.studies.grid import initial_covariance
from covtool.studies.inputs import load_truth

ROOT = Path(__file__).resolve().parents[1]
SIG = np.array([0.5, 0.8, 1.2])
LAT, LON, H = 45.0, 10.0, 100.0


def decl(what="sigma", scales=(0.1, 10.0)) -> dict:
    return {"study": {"kind": "aided", "name": "cupt_sweep", "duration": "10 min", "dt": "1 s",
                      "discretization": "van_loan"},
            "trajectory": {"builtin": "static", "lat": f"{LAT} deg", "lon": f"{LON} deg", "h": f"{H} m"},
            "truth": {"model": "sdins58"},
            "filters": {"file": str(ROOT / "models" / "filters" / "zupt_filters.toml"), "cases": ["A"],
                        "pure_ins": False},
            "measurement": [{"name": "mark", "kind": "cupt", "sigma": [f"{x} m" for x in SIG],
                             "schedule": {"at": ["10 min"]}}],
            "sweep": {"measurement": "mark", "what": what, "scales": list(scales)},
            "output": {"history_every": "1 min", "report_times": ["10 min"]}}


@pytest.fixture(scope="module")
def prior():
    """NED position covariance of the static INS at 10 min, propagated independently of the study."""
    truth = load_truth({"truth": {"model": "sdins58"}}, "<test>", None)
    traj = static(600.0, lat=math.radians(LAT), lon=math.radians(LON), h=H, dt=1.0)
    dyn = error_dynamics(truth, Context.from_trajectory(traj.sample(traj.t[:1])))
    Phi1, Qd1 = discretize(dyn.F, dyn.Qc, np.array([1.0]), "van_loan")
    N = traj.t.size - 1
    P = propagate(np.broadcast_to(Phi1, (N,) + Phi1.shape[1:]), np.broadcast_to(Qd1, (N,) + Qd1.shape[1:]),
                  initial_covariance(truth, traj, "<test>"))[-1]
    M = ned_metres(np.array([math.radians(LAT), math.radians(LON), H]))
    return M @ P[:3, :3] @ M


def sigmas(df):
    return df[["sigma_N [m]", "sigma_E [m]", "sigma_D [m]"]].to_numpy()


def test_sensor_sigma_sweep_follows_the_information_form(prior):
    df = run(decl("sigma", (0.1, 0.3, 3.0, 10.0))).tables["measurement_sweep"].sort_values("scale")
    assert list(df["scale"]) == [0.1, 0.3, 1.0, 3.0, 10.0]
    expect = [np.sqrt(np.diag(np.linalg.inv(np.linalg.inv(prior) + np.diag(1 / (SIG * s) ** 2))))
              for s in df["scale"]]
    np.testing.assert_allclose(sigmas(df), expect, rtol=1e-6)
    # the optimal filter claims what the truth has
    np.testing.assert_allclose(df["filter-claimed CEP [m]"], df["CEP [m]"], rtol=1e-9)
    assert np.all(np.diff(df["CEP [m]"]) > 0)


def test_filter_sigma_sweep_is_the_mistuned_joseph_form(prior):
    df = run(decl("filter_sigma", (0.1, 10.0))).tables["measurement_sweep"].sort_values("scale")
    R = np.diag(SIG**2)
    expect = []
    for s in df["scale"]:
        G = prior @ np.linalg.inv(prior + s**2 * R)
        A = np.eye(3) - G
        expect.append(np.sqrt(np.diag(A @ prior @ A.T + G @ R @ G.T)))
    np.testing.assert_allclose(sigmas(df), expect, rtol=1e-6)
    cep = df.set_index("scale")["CEP [m]"]
    assert cep[1.0] < cep[0.1] and cep[1.0] < cep[10.0]          # the tuned filter does best
    # the sensor is not scaled: the truth R is the declared one in every row
    assert set(df["sigma [SI]"]) == {", ".join(f"{x:g}" for x in SIG)}


@pytest.mark.parametrize("sweep,match", [
    ({"measurement": "gps"}, r"^<study>: \[sweep\] measurement: 'gps' is not one of: 'mark'"),
    ({"measurement": "mark", "what": "R"}, r"^<study>: \[sweep\] what: 'R' is not one of: 'sigma', 'filter_sigma'"),
    ({"measurement": "mark", "scales": []}, r"^<study>: \[sweep\] scales: expected at least one scale"),
    ({"measurement": "mark", "scales": [0.0]}, r"^<study>: \[sweep\] scales\[0\]: "),
    ({"measurement": "mark", "scales": {"from": 0.3, "to": 10, "per_decade": 2}}, r"^<study>: \[sweep\] scales: "),
    ({"measurement": "mark", "scale": [2.0]}, r"^<study>: \[sweep\]: unknown key 'scale'"),
    ({"what": "sigma"}, r"^<study>: \[sweep\]: missing required key 'measurement'"),
    ({"measurement": "mark", "scales": [float(x) for x in range(2, 1003)]},
     r"^<study>: \[sweep\] scales: 1002 scales; at most 1000"),
])
def test_bad_sweep_is_one_line(sweep, match):
    d = decl()
    d["sweep"] = sweep
    with pytest.raises(StudyFileError, match=match):
        run(d)
