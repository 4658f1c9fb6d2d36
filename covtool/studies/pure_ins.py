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

import numpy as np
import pandas as pd

from covtool.analysis.metrics import nav_metrics
from covtool.errors import StudyFileError
from covtool.io.config import check_keys
from covtool.lincov.reference import propagate
from covtool.results import StudyResult
from covtool.studies.grid import initial_covariance, time_grid, truth_system
from covtool.studies.inputs import load_trajectory, load_truth, output_options, study_header, study_inputs
from covtool.studies.resources import (check_memory, memory_estimate, noise_columns, resource_provenance,
                                       steps_of)
from covtool.studies.tables import case_validity, history_frame, summary_row


def run(decl: dict, *, path=None, progress: bool = False) -> StudyResult:
    """Run a pure-INS covariance study; see the module docstring."""
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    check_keys(decl, {"study", "trajectory", "truth", "output"}, where, StudyFileError)
    hdr = study_header(decl, where)
    every, rtimes = output_options(decl, where, hdr["duration"])
    t0 = time.perf_counter()
    truth = load_truth(decl, where, base_dir)
    est = check_memory(memory_estimate(steps_of(hdr["duration"], hdr["dt"]), truth.n, histories=[truth.n],
                                       noise=noise_columns(truth)),
                       where, hdr["max_memory"], "a larger [study] dt or a shorter duration")
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
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

    def fig_position():
        import matplotlib.pyplot as plt
        fig, axs = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
        tm = t / 60
        axs[0].plot(tm, m["cep"], label="CEP")
        axs[0].plot(tm, m["sigma_north"], "--", label="σ north")
        axs[0].plot(tm, m["sigma_east"], ":", label="σ east")
        axs[0].set_ylabel("horizontal position [m]")
        axs[0].legend()
        axs[1].plot(tm, m["sigma_down"], label="σ altitude")
        axs[1].set_ylabel("altitude error 1σ [m]")
        axs[2].plot(tm, m["sigma_azimuth"] * 180 / np.pi * 60, label="azimuth")
        axs[2].plot(tm, m["sigma_tilt_n"] * 180 / np.pi * 60, "--", label="north tilt")
        axs[2].plot(tm, m["sigma_tilt_e"] * 180 / np.pi * 60, ":", label="east tilt")
        axs[2].set_ylabel("attitude error 1σ [arcmin]")
        axs[2].set_xlabel("time [min]")
        axs[2].legend()
        for a in axs:
            a.grid(True, alpha=0.3)
        fig.suptitle(f"{hdr['name']}: pure INS, truth model {truth.name}")
        return fig

    return StudyResult(
        name=hdr["name"], kind="pure_ins", tables=tables, figures={"pure_ins_errors": fig_position},
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}},
        provenance={**study_inputs(path, decl, truth), "truth_model": truth.name,
                    "truth_model_sha256": truth.sha256, "states": truth.n, **resource_provenance(est),
                    "compute_seconds": f"{elapsed:.2f}"},
        charts=[{"sheet": "history", "x": "t [min]", "y": ["CEP [m]", "sigma_D [m]"], "log_y": True,
                 "x_title": "time [min]", "title": "Pure INS position error", "y_title": "position error [m]",
                 "anchor": "R2"}],
        data={"t": t, "P": P, "metrics": m, "trajectory": nodes, "model": truth},
    )
