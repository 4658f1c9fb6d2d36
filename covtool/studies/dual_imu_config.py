"""The ``dual_imu`` study file, validated into a :class:`DualConfig` (SI).

Every table and key of the study (see :mod:`covtool.studies.dual_imu` for
the file) is checked here, before any computation, with the file, the
table, the key and the problem named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.dualnav.gaps import GAP_POLICIES
from covtool.dualnav.monitor import candidate_label
from covtool.errors import ModelFileError, StudyFileError
from covtool.io.config import check_keys, choice, integer, names, number, quantity, string, table
from covtool.io.names import check_study_name
from covtool.nav import attitude as quat


COMPONENT_GROUPS = {"position": (0, 1, 2), "velocity": (3, 4, 5), "attitude": (6, 7, 8)}


_TOP = {"study", "trajectory", "imu", "alignment", "comparison", "monitor", "gaps", "simulation"}


@dataclass(frozen=True)
class DualConfig:
    """A validated dual-IMU study (SI)."""

    name: str
    description: str
    grades: dict            # "main"/"kimu" -> ImuGrade
    mounting: dict          # "main"/"kimu" -> quaternion
    ratio: int
    align_time: float
    heading_sigma: float
    initial: dict           # lat, lon, h, heading (may be partial)
    interval: float
    model_step: float
    components: tuple
    noise: np.ndarray
    window: float
    false_alarm: float
    candidates: tuple
    gap_policy: str
    gap_window: int
    gap_trials: int
    runs: int
    fault_runs: int
    batch: int
    seed: int
    fault: tuple | None     # (gyro axis, accel axis, coefficient SI)
    gaps: tuple             # ((imu, start, duration), ...)


def _axis(value, where):
    return "xyz".index(choice(value, ("x", "y", "z"), where, StudyFileError))


def _candidate(text, where):
    if not isinstance(text, str) or len(text.split("/")) != 2:
        raise StudyFileError(where, f"{text!r} is not 'gyro axis/accel axis', e.g. 'z/x'")
    g, a = text.split("/")
    return (_axis(g.strip(), where), _axis(a.strip(), where))


def gsens_coefficient(value, where) -> float:
    """A g-sensitive scale factor (``"1000 ppm/g"``) in 1/(m/s²)."""
    from covtool.units import parse_quantity
    from covtool.errors import UnitError

    if not isinstance(value, str):
        raise StudyFileError(where, f"{value!r} is not a quantity such as '1000 ppm/g'")
    try:
        return parse_quantity(value, "inverse_acceleration", where=where)
    except UnitError:
        raise StudyFileError(where, f"{value!r} is not a scale factor per g (e.g. '1000 ppm/g')") from None


def parse_study(decl: dict, where: str, base_dir=None) -> DualConfig:
    """Validate a ``dual_imu`` declaration.

    Raises
    ------
    StudyFileError
        Naming the file, the table and key, and the problem.
    """
    from covtool.io.imu_grade import load_imu_grade

    check_keys(decl, _TOP, where, StudyFileError)
    st = table(decl.get("study", {}), f"{where}: [study]", StudyFileError)
    check_keys(st, {"kind", "name", "description"}, f"{where}: [study]", StudyFileError)
    name = check_study_name(st, where, StudyFileError, default="dual_imu")
    string(st.get("description", ""), f"{where}: [study] description", StudyFileError)
    imu = table(decl.get("imu", {}), f"{where}: [imu]", StudyFileError)
    check_keys(imu, {"main", "kimu"}, f"{where}: [imu]", StudyFileError)
    grades, mounting = {}, {}
    defaults = {"main": "main_imu", "kimu": "kimu"}
    ratio = 4
    for key in ("main", "kimu"):
        w = f"{where}: [imu.{key}]"
        t = table(imu.get(key, {}), w, StudyFileError)
        check_keys(t, {"grade", "mounting", "ratio"} if key == "kimu" else {"grade", "mounting"}, w, StudyFileError)
        g = string(t.get("grade", defaults[key]), f"{w} grade", StudyFileError, nonempty=True)
        try:
            # a library name, or a path relative to the study file
            grades[key] = load_imu_grade(g, base_dir=base_dir)
        except ModelFileError as exc:
            raise StudyFileError(f"{w} grade", str(exc)) from None
        if grades[key].rate is None:
            raise StudyFileError(f"{w} grade", f"IMU grade {grades[key].name!r} declares no rate")
        m = t.get("mounting", ["0 deg", "0 deg", "0 deg"])
        if not isinstance(m, list) or len(m) != 3:
            raise StudyFileError(f"{w} mounting", "expected [roll, pitch, yaw] of the sensor frame in the body")
        ang = [quantity(v, "angle", f"{w} mounting[{i}]", StudyFileError) for i, v in enumerate(m)]
        mounting[key] = np.asarray(quat.from_euler(*ang), float)
        if key == "kimu" and "ratio" in t:
            ratio = integer(t["ratio"], f"{w} ratio", StudyFileError, limit="kimu_ratio")
    r_rates = grades["kimu"].rate / grades["main"].rate
    if abs(r_rates - ratio) > 1e-9 * ratio:
        raise StudyFileError(f"{where}: [imu.kimu] ratio", f"{ratio} does not match the grades' rates "
                             f"({grades['kimu'].rate:g} Hz / {grades['main'].rate:g} Hz = {r_rates:g})")
    w = f"{where}: [alignment]"
    al = table(decl.get("alignment", {}), w, StudyFileError)
    check_keys(al, {"duration", "heading_sigma", "lat", "lon", "h", "heading"}, w, StudyFileError)
    align = quantity(al.get("duration", "10 s"), "time", f"{w} duration", StudyFileError, positive=True)
    hsig = quantity(al.get("heading_sigma", "0.1 deg"), "angle", f"{w} heading_sigma", StudyFileError,
                    nonnegative=True)
    initial = {}
    for key, dim in (("lat", "angle"), ("lon", "angle"), ("h", "length"), ("heading", "angle")):
        if key in al:
            initial[key] = quantity(al[key], dim, f"{w} {key}", StudyFileError)
    if "lat" in initial and not abs(initial["lat"]) < np.radians(89.9):
        raise StudyFileError(f"{w} lat", f"{al['lat']!r} is not within ±89.9 deg (the NED frame is singular at "
                             "the poles)")
    if "lon" in initial and not abs(initial["lon"]) <= np.pi:
        raise StudyFileError(f"{w} lon", f"{al['lon']!r} is not within ±180 deg")
    w = f"{where}: [comparison]"
    cp = table(decl.get("comparison", {}), w, StudyFileError)
    check_keys(cp, {"interval", "model_step", "components", "noise"}, w, StudyFileError)
    interval = quantity(cp.get("interval", "1 s"), "time", f"{w} interval", StudyFileError, positive=True)
    step = quantity(cp.get("model_step", "0.04 s"), "time", f"{w} model_step", StudyFileError, positive=True)
    hm = 1.0 / grades["main"].rate
    for key, val in (("interval", interval), ("model_step", step)):
        n = round(val / hm)
        if n < 1 or abs(n * hm - val) > 1e-6 * hm:
            raise StudyFileError(f"{w} {key}", f"{val:g} s is not a whole number of main samples ({hm:g} s)")
    n_step, n_int = round(step / hm), round(interval / hm)
    if n_step % 2 or n_int % n_step:
        raise StudyFileError(f"{w} model_step", f"{step:g} s must be an even number of main samples and divide "
                             f"the interval {interval:g} s")
    comps = names(cp.get("components", ["velocity", "attitude"]), f"{w} components", StudyFileError,
                  known=list(COMPONENT_GROUPS), what="component")
    components = tuple(sorted({i for c in comps for i in COMPONENT_GROUPS[c]}))
    nz = table(cp.get("noise", {}), f"{w} noise", StudyFileError)
    check_keys(nz, set(COMPONENT_GROUPS), f"{w} noise", StudyFileError)
    dims = {"position": "length", "velocity": "velocity", "attitude": "angle"}
    dflt = {"position": "1 mm", "velocity": "0.1 mm/s", "attitude": "2 urad"}
    noise = np.zeros(9)
    for key, idx in COMPONENT_GROUPS.items():
        noise[list(idx)] = quantity(nz.get(key, dflt[key]), dims[key], f"{w} noise.{key}", StudyFileError,
                                    nonnegative=True)
    w = f"{where}: [monitor]"
    mo = table(decl.get("monitor", {}), w, StudyFileError)
    check_keys(mo, {"window", "false_alarm", "candidates"}, w, StudyFileError)
    window = quantity(mo.get("window", "10 s"), "time", f"{w} window", StudyFileError, positive=True)
    if round(window / interval) < 1 or abs(round(window / interval) * interval - window) > 1e-6 * interval:
        raise StudyFileError(f"{w} window", f"{window:g} s is not a whole number of comparison intervals "
                             f"({interval:g} s)")
    fa = number(mo.get("false_alarm", 0.01), f"{w} false_alarm", StudyFileError, lo=0.0, hi=1.0, lo_open=True,
                hi_open=True, why="a probability")
    cands = mo.get("candidates", "all")
    if cands == "all":
        candidates = tuple((i, j) for i in range(3) for j in range(3))
    elif isinstance(cands, list) and cands:
        candidates = tuple(_candidate(c, f"{w} candidates[{k}]") for k, c in enumerate(cands))
        if len(set(candidates)) != len(candidates):
            raise StudyFileError(f"{w} candidates", "lists a candidate twice")
    else:
        raise StudyFileError(f"{w} candidates", f"{cands!r}: expected 'all' or a list such as ['z/x']")
    w = f"{where}: [gaps]"
    gp = table(decl.get("gaps", {}), w, StudyFileError)
    check_keys(gp, {"policy", "window", "trials"}, w, StudyFileError)
    policy = choice(gp.get("policy", "interpolate"), tuple(GAP_POLICIES), f"{w} policy", StudyFileError)
    gwin = integer(gp.get("window", 10), f"{w} window", StudyFileError, limit="gap_window")
    trials = integer(gp.get("trials", 8), f"{w} trials", StudyFileError, limit="gap_trials")
    w = f"{where}: [simulation]"
    sim = table(decl.get("simulation", {}), w, StudyFileError)
    check_keys(sim, {"runs", "fault_runs", "batch", "seed", "fault", "gap"}, w, StudyFileError)
    runs = integer(sim.get("runs", 100), f"{w} runs", StudyFileError, limit="dual_runs")
    fruns = integer(sim.get("fault_runs", 20), f"{w} fault_runs", StudyFileError, limit="dual_runs")
    batch = integer(sim.get("batch", 50), f"{w} batch", StudyFileError, limit="dual_batch")
    seed = integer(sim.get("seed", 1), f"{w} seed", StudyFileError, limit="seed")
    fault = None
    if "fault" in sim:
        wf = f"{where}: [simulation.fault]"
        f = table(sim["fault"], wf, StudyFileError)
        check_keys(f, {"gyro", "accel", "coefficient"}, wf, StudyFileError)
        for key in ("gyro", "accel", "coefficient"):
            if key not in f:
                raise StudyFileError(wf, f"missing required key {key!r}")
        fault = (_axis(f["gyro"], f"{wf} gyro"), _axis(f["accel"], f"{wf} accel"),
                 gsens_coefficient(f["coefficient"], f"{wf} coefficient"))
        if (fault[0], fault[1]) not in candidates:
            raise StudyFileError(wf, f"the injected {candidate_label(fault)} is not among [monitor] candidates")
    elif fruns:
        raise StudyFileError(w, f"fault_runs = {fruns} needs a [simulation.fault] table")
    gaps = []
    glist = sim.get("gap", [])
    if not isinstance(glist, list):
        raise StudyFileError(f"{w} gap", "expected an array of tables [[simulation.gap]]")
    for k, g in enumerate(glist):
        wg = f"{where}: [[simulation.gap]][{k}]"
        check_keys(g, {"imu", "start", "duration"}, wg, StudyFileError)
        choice(g.get("imu"), ("main", "kimu"), f"{wg} imu", StudyFileError)
        for key in ("start", "duration"):
            if key not in g:
                raise StudyFileError(wg, f"missing required key {key!r}")
        gaps.append((g["imu"], quantity(g["start"], "time", f"{wg} start", StudyFileError, nonnegative=True),
                     quantity(g["duration"], "time", f"{wg} duration", StudyFileError, positive=True)))
    return DualConfig(name, st.get("description", ""), grades, mounting, ratio, align, hsig, initial, interval, step,
                      components, noise, window, float(fa), candidates, policy, gwin, trials, runs, fruns, batch,
                      seed, fault, tuple(gaps))
