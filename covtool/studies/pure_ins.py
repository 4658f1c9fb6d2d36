"""Pure-INS covariance study (seed 002 eq (15) with no measurements).

Study file::

    [study]
    kind = "pure_ins"
    name = "pure_ins_land_vehicle"
    duration = "30 min"
    dt = "1 s"
    discretization = "van_loan"      # or "taylor" (seed 002 eq (6b)-(6d))

    [trajectory]
    builtin = "land_vehicle"         # see covtool.io.trajectory.trajectory_from_config

    [truth]
    model = "sdins58"
    # only = ["acc_bias_x"]          # keep only these error sources
    # [truth.override.acc_bias_x]
    # sigma = "50 ug"

    [output]
    history_every = "10 s"
    report_times = ["5 min", "30 min"]
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.metrics import nav_metrics
from covtool.lincov.reference import propagate
from covtool.lincov.history import CovarianceHistory
from covtool.plotting.navigation import pure_ins_figure
from covtool.results import PureInsResult
from covtool.studies.grid import initial_covariance, time_grid, truth_system
from covtool.studies.inputs import (length_unit, load_trajectory, load_truth, output_options, study_config,
                                    study_header, study_inputs)
from covtool.studies.resources import (check_memory, memory_estimate, noise_columns, resource_provenance,
                                       steps_of)
from covtool.studies.tables import case_validity, history_frame, summary_row


def run(decl: dict, *, path=None, progress: bool = False, config=None) -> PureInsResult:
    """Run a pure-INS covariance study; see the module docstring.

    ``config`` is ``decl`` parsed (:func:`covtool.run_study` passes it);
    parsed here, once, if not given.
    """
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    cfg = study_config(decl if config is None else config, where)
    hdr = study_header(cfg, where)
    every, rtimes = output_options(cfg, where, hdr["duration"])
    t0 = time.perf_counter()
    truth = load_truth(cfg, where, base_dir)
    est = check_memory(memory_estimate(steps_of(hdr["duration"], hdr["dt"]), truth.n, histories=[truth.n],
                                       noise=noise_columns(truth)),
                       where, hdr["max_memory"], "a larger [study] dt or a shorter duration")
    traj = load_trajectory(cfg, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"])
    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"], progress=progress, where=where)
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, where)
    P = propagate(Phi, Qd, P0, label=f"{where}: pure INS", names=truth.names, times=t, system_checked=True)
    m = nav_metrics(P, nodes.lat, nodes.h, nodes.q_nb, nodes.distance)
    first = case_validity("pure_ins", m, t)
    hist = history_frame("pure_ins", t, m, every)
    rows = []
    for tr in rtimes:
        k = int(np.argmin(np.abs(t - tr)))
        rows.append(summary_row("pure_ins", m, k, t[k], float(nodes.distance[k]), first=first))
    summary = pd.DataFrame(rows)
    elapsed = time.perf_counter() - t0
    tables = {"summary": summary, "history": hist, "truth_states": truth.state_table()}

    unit = length_unit(cfg, where)
    result = PureInsResult(
        name=hdr["name"], kind="pure_ins", tables=tables,
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}},
        provenance={**study_inputs(path, decl, truth), "truth_model": truth.name,
                    "truth_model_sha256": truth.sha256, "states": truth.n, **resource_provenance(est),
                    "compute_seconds": f"{elapsed:.2f}"},
        charts=[{"sheet": "history", "x": "t [min]", "y": [f"CEP [{unit}]", f"alt PE [{unit}]"], "log_y": True,
                 "skip": 1, "x_title": "time [min]", "title": "Pure INS position error",
                 "y_title": f"position error [{unit}]", "anchor": "R2"}],
        times=t, metrics=m, length_unit=unit, truth_history=CovarianceHistory(t, truth.names, P, label="pure INS"))
    result.history = result.truth_history.nav()
    result.figures = {"pure_ins_errors": partial(pure_ins_figure, result)}
    return result
