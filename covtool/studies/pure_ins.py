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
from covtool.lincov.streamed import ChunkPool
from covtool.studies.grid import initial_covariance, record_steps, time_grid, truth_stream
from covtool.studies.inputs import (length_unit, load_trajectory, load_truth, output_options, study_config,
                                    study_header, study_inputs)
from covtool.studies.resources import (check_memory, noise_columns, resource_provenance, steps_of,
                                       stream_memory_estimate)
from covtool.studies.tables import case_validity, history_frame, summary_row
from covtool.studies.zupt_setup import history_records


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
    N = steps_of(hdr["duration"], hdr["dt"])
    records = history_records(N, hdr["dt"], every, rtimes, 0)[0]
    est = stream_memory_estimate(N, truth.n, histories=[truth.n], noise=noise_columns(truth), records=records,
                                 intervals=0)
    # the navigation block of every step and the metrics of it (a few (N+1, 10, 10) stacks)
    est["parts"]["navigation block at every step"] = 3 * (N + 1) * 100 * 8
    est["bytes"] = float(sum(est["parts"].values()))
    est = check_memory(est, where, hdr["max_memory"], "a larger [study] dt, a shorter duration or a larger "
                       "[output] history_every")
    traj = load_trajectory(cfg, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"])
    # streamed in time (covtool.studies.grid.truth_stream): Φ, Q_d exist one chunk at a time, each guarded
    # when made; every covariance is guarded, the full P recorded at the history spacing and report times
    _, _, system = truth_stream(truth, traj, t, hdr["discretization"], pool=ChunkPool(0), where=where)
    rec = record_steps(t, every, [int(np.argmin(np.abs(t - tr))) for tr in rtimes])
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, where)
    P, P_nav = propagate(system.Phi, system.Qd, P0, label=f"{where}: pure INS", names=truth.names, times=t,
                         system_checked=True, record=rec, all_steps=10)
    tr = t[rec]
    # the navigation metrics at every step (the validity time to the step), the full P at the records
    m = nav_metrics(P_nav, nodes.lat, nodes.h, nodes.q_nb, nodes.distance)
    first = case_validity("pure_ins", m, t)
    hist = history_frame("pure_ins", t, m, every)
    rows = []
    for r_ in rtimes:
        k = int(np.argmin(np.abs(t - r_)))
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
        times=t, metrics=m, length_unit=unit, truth_history=CovarianceHistory(tr, truth.names, P, label="pure INS"))
    # the navigation block (seed 002 eq (14)) at every step; the full model at the record steps only
    result.history = CovarianceHistory(t, truth.names[:10], P_nav, label="pure INS")
    result.figures = {"pure_ins_errors": partial(pure_ins_figure, result)}
    return result
