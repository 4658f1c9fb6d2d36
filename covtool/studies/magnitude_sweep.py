"""Truth-magnitude sweep: where the reduced filters stop being near-optimal.

Sweeps the 1σ of groups of truth states (e.g. the accelerometer and gyro
misalignments and the gravity deflections) and reports, per filter, the true
30-min errors and their ratio to the optimal filter A.  The truth and every
filter follow the swept magnitude (the designer knows the IMU: filter A's
P0 and Q, and the reduced filters' equivalent noise, seed 002 eq (11)–(13),
all change with it).

Study file::

    [study]
    kind = "magnitude_sweep"
    duration = "30 min"
    dt = "1 s"

    [trajectory]
    builtin = "land_vehicle"

    [truth]
    model = "sdins58"

    [filters]
    cases = ["A", "B1", "B2", "B3", "C", "D"]   # must include "A" (the reference)

    [zupt]                         # as zupt_filter_order
    interval = "5 min"
    duration = "0 s"

    [sweep]
    values = ["0.5 arcsec", "1 arcsec", "2 arcsec", "5 arcsec", "10 arcsec", "20 arcsec"]
    threshold = 1.5                # CEP / CEP_A that counts as "near-optimal"

    [[sweep.group]]
    name = "gyro misalignment"
    states = ["gyro_mis"]          # blocks or states, swept together, the others as declared

How it is computed: the truth Φ and F do not depend on the magnitudes, and
the truth P0, the truth noise (gravity's Markov driving noise ∝ σ²), the
filters' P_f(0) and their equivalent noise (∝ P0) are linear in the swept
variances.  Each noise source is composed once (:func:`covtool.lincov.noise.compose_noise`)
and every sweep point is a member of one batched engine call per filter
(:func:`covtool.lincov.batch.run_batch`) with its own combination.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.metrics import nav_metrics
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, quantity
from covtool.lincov.batch import events, run_batch, System
from covtool.lincov.impact import check_members
from covtool.lincov.noise import CombinedNoise, compose_noise, compose_transition, restricted_noise
from covtool.lincov.reduced import zupt_matrices
from covtool.plotting.magnitude_sweep import sweep_figure
from covtool.results import MagnitudeSweepResult
from covtool.studies.resources import (composed_memory_estimate, noise_columns, progress_bar,
                                       resource_provenance, STREAM_CHUNK)
from covtool.studies.zupt_setup import setup
from covtool.units import ARCMIN, FT, si_unit


def sweep_options(decl: dict, where: str, truth) -> dict:
    """Validate ``[sweep]``: values, threshold and the groups of states.

    Raises
    ------
    StudyFileError
        Unknown key, missing or empty ``values``/``group``, a group with an
        unknown state or block, states of different dimensions, a value of
        the wrong dimension or negative, a state declared with σ = 0 (its
        sources cannot be scaled), or a threshold ≤ 1.
    """
    w = f"{where}: [sweep]"
    cfg = decl.get("sweep")
    if not isinstance(cfg, dict):
        raise StudyFileError(w, "missing [sweep] table (values = [...], [[sweep.group]] ...)")
    check_keys(cfg, {"values", "threshold", "group"}, w, StudyFileError)
    groups = cfg.get("group")
    if not isinstance(groups, list) or not groups:
        raise StudyFileError(f"{w} group", "declare at least one [[sweep.group]] with name and states")
    thr = cfg.get("threshold", 1.5)
    if isinstance(thr, bool) or not isinstance(thr, (int, float)) or not thr > 1:
        raise StudyFileError(f"{w} threshold", f"{thr!r} is not a number greater than 1")
    vals = cfg.get("values")
    if not isinstance(vals, list) or not vals:
        raise StudyFileError(f"{w} values", "expected a non-empty list of magnitudes")
    out = []
    for k, g in enumerate(groups):
        gw = f"{w} group {k + 1}"
        if not isinstance(g, dict):
            raise StudyFileError(gw, "expected a table with name and states")
        check_keys(g, {"name", "states"}, gw, StudyFileError)
        if not isinstance(g.get("name"), str) or not isinstance(g.get("states"), list) or not g["states"]:
            raise StudyFileError(gw, "needs name = \"...\" and states = [...] (blocks or states)")
        try:
            names = truth.states_of(g["states"])
        except KeyError as exc:
            raise StudyFileError(f"{gw} states", f"unknown state or block {exc.args[0]!r} of truth model "
                                 f"{truth.name!r}") from None
        sts = [truth.states[truth.index[n]] for n in names]
        dims = {s.dimension for s in sts}
        if len(dims) != 1:
            raise StudyFileError(f"{gw} states", f"states of different dimensions ({', '.join(sorted(dims))}) "
                                 "cannot share one swept magnitude")
        for s in sts:
            if s.sigma == 0:
                raise StudyFileError(f"{gw} states", f"state {s.name!r} is declared with sigma 0; give it a "
                                     "non-zero sigma to sweep it")
        dim = dims.pop()
        mags = [quantity(v, dim, f"{w} values", StudyFileError, nonnegative=True) for v in vals]
        out.append({"name": g["name"], "states": names, "values": np.array(mags), "text": list(vals),
                    "unit_text": vals[0].split()[-1] if isinstance(vals[0], str) and " " in vals[0] else ""})
    return {"groups": out, "threshold": float(thr)}


def _memory(decl: dict, where: str):
    """What a magnitude sweep holds at its peak (an upper estimate, checked before anything is built).

    The truth's and each filter's systems and per-source noises are made
    chunk by chunk and composed on the events
    (:func:`~covtool.studies.resources.composed_memory_estimate`); the
    composed per-source noise stacks (every noise source of the truth and of
    the largest filter, on the ``K`` intervals) and one filter's batch of
    members are added.
    """

    def memory(steps, truth, filters, dynamics, *, records=None, intervals=None, shared=0, distinct=None,
               updates=0, reports=1):
        groups = sweep_options(decl, where, truth)["groups"]
        B = sum(len(g["values"]) for g in groups)
        swept = len({nm for g in groups for nm in g["states"]})
        n, nf, nmin = truth.n, max(filters, default=truth.n), min(filters, default=truth.n)
        est = composed_memory_estimate(steps, n, filters=list(filters), dynamics=dynamics,
                                       noise=noise_columns(truth), updates=updates, reports=reports, batch=B)
        K = int(updates) + int(reports) + int(steps) // STREAM_CHUNK + 2
        # composed per-source noise: "rest" and each swept state's source (truth), and in the filter also an
        # equivalent noise per dropped state; every chunk's and their concatenation
        Jt, Jf = 1 + swept, 1 + swept + (n - nmin)
        parts = {**est["parts"], "per-source composed noise": 2 * K * (Jt * n * n + Jf * nf * nf) * 8}
        return {**est, "bytes": float(sum(parts.values())), "parts": parts}

    memory.records = True
    memory.updates = True
    return memory


def run(decl: dict, *, path=None, progress: bool = False, config=None) -> MagnitudeSweepResult:
    """Run a magnitude sweep; see the module docstring."""
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    S = setup(decl if config is None else config, path=path, progress=progress, extra_sections=("sweep",),
              memory=_memory(decl, where))
    opts = sweep_options(decl, where, S.truth)
    if "A" not in S.cases:
        raise StudyFileError(f"{where}: [filters] cases", "a magnitude sweep needs filter \"A\" (the optimal "
                             "reference of the ratios)")
    truth, t, nodes = S.truth, S.t, S.nodes
    N = t.size - 1
    dt = np.diff(t)
    rep = sorted({int(np.argmin(np.abs(t - tr))) for tr in S.report_times})
    # the events with the stream's chunk boundaries: Φ, Q_d, F and the noise sources exist one chunk at a
    # time, each source's noise composed on these events as it is made (nothing of size N x n^2 held)
    ev = S.stream_grid(events(N, S.update_steps, rep))
    ix = truth.index
    sig = np.array([s.sigma for s in truth.states])
    # members: (group, value); scale of each truth state's sigma per member
    members, scale = [], []
    for g in opts["groups"]:
        gi = np.array([ix[n] for n in g["states"]])
        for v, text in zip(g["values"], g["text"]):
            s = np.ones(truth.n)
            s[gi] = v / sig[gi]
            members.append((g["name"], float(v), text))
            scale.append(s)
    scale = np.array(scale)                                   # (B, n)
    B = len(members)
    # truth: P0 and the driving noise of every state scale with sigma^2 (arw, vrw unchanged)
    P0s = scale[:, :, None] * S.P0[None] * scale[:, None, :]
    swept = sorted({i for g in opts["groups"] for i in (ix[n] for n in g["states"])})
    names_sw = {truth.states[i].name for i in swept}
    allrows = np.arange(truth.n)
    own_names, Qt_parts = [], []

    def truth_noise(a, cev, dyn, Phi):
        own = [src for src in dyn.noise if src.name in names_sw]
        rest = [src for src in dyn.noise if src.name not in names_sw]
        if not own_names:
            own_names.extend(src.name for src in own)
        tfac = [restricted_noise("rest", rest, allrows)] + [restricted_noise(src.name, [src], allrows)
                                                             for src in own]
        Qt_parts.append(compose_noise(Phi, dyn.F, tfac, dt[a:a + Phi.shape[0]], cev - a))

    tsys = S.composed_truth(ev, on_chunk=truth_noise)
    Qt = np.concatenate(Qt_parts, axis=1)
    Qt_parts.clear()
    tcoef = np.ones((B, Qt.shape[0]))
    for k, nm in enumerate(own_names, start=1):
        tcoef[:, k] = scale[:, ix[nm]] ** 2
    truth_Q = CombinedNoise([(Qt[k], allrows) for k in range(Qt.shape[0])], tcoef, truth.n)
    rows = []
    results = {}
    # every filter's Φ_f and per-source noise, chunk by chunk: the chunks outer, so that the truth's dynamics
    # of a chunk under each set of navigation options are built once for all the filters of those options
    fms = {name: S.filter_stream(name)[0] for name in S.cases}
    acc = {name: ([], [], []) for name in S.cases}          # per chunk: coefficient rows, Q_f parts, Φ_f parts
    for a, b, cev in S.chunks(ev):
        dyn_of = S.chunk_dynamics(a, b)
        for name, fm in fms.items():
            dyn = dyn_of(fm.spec.options)
            kidx = truth.idx(fm.names)
            fown = [src for src in dyn.noise if src.name in names_sw]
            frest = [src for src in dyn.noise if src.name not in names_sw]
            fac = [restricted_noise("rest", frest, kidx)] + [restricted_noise(src.name, [src], kidx)
                                                             for src in fown]
            coef_idx = [None] + [ix[src.name] for src in fown]
            for src in fm.ewn_noise:
                fac.append(restricted_noise(f"ewn {src.name}", [src.steps(a, b)], np.arange(len(kidx))))
                coef_idx.append(ix[src.name])
            seen = []
            Phi_f, _ = S.filter_chunk(name, a, b, dyn_of, on_chunk=lambda a_, F_f, Qc_f: seen.append(F_f))
            acc[name][0].append(coef_idx)
            acc[name][1].append(compose_noise(Phi_f, seen[0], fac, dt[a:b], cev - a))
            acc[name][2].append(compose_transition(Phi_f, cev - a))
            del Phi_f
    with progress_bar(len(S.cases), "filters", progress) as bar:
        for name in S.cases:
            fm = fms[name]
            kidx = truth.idx(fm.names)
            nf = len(kidx)
            fac_of, QF_parts, T_parts = acc.pop(name)
            coef_idx = fac_of[0]
            QF = np.concatenate(QF_parts, axis=1)
            del QF_parts
            fcoef = np.ones((B, len(coef_idx)))
            for k, i in enumerate(coef_idx):
                if i is not None:
                    fcoef[:, k] = scale[:, i] ** 2
            filt_Q = CombinedNoise([(QF[k], np.arange(nf)) for k in range(len(coef_idx))], fcoef, nf)
            # filter P0: kept states scale like the truth's; absorbed ("matched") parts with their source
            P0n = fm.P0 - sum((sig[ix[nm]] ** 2 * np.outer(a, a) for nm, a in fm.ewn_absorb.items()),
                              np.zeros((nf, nf)))
            sk = scale[:, kidx]
            Pf0 = sk[:, :, None] * P0n[None] * sk[:, None, :]
            for nm, a in fm.ewn_absorb.items():
                Pf0 += (scale[:, ix[nm]] * sig[ix[nm]])[:, None, None] ** 2 * np.outer(a, a)[None]
            fsys = System(ev, np.concatenate(T_parts), np.zeros((len(ev) - 1, 0, 0)))
            del T_parts
            res = run_batch(tsys, P0s, S.H, S.R, fm.D, S.update_steps, rep, filt=fsys, Pf0=Pf0,
                            Hf=zupt_matrices(fm.names), Rf=S.filter_R(name)[None], filter_Q=filt_Q,
                            truth_Q=truth_Q, form=fm.spec.update)
            check_members(res.P_truth, nodes.q_nb[rep], t[rep],
                          [f"magnitude sweep: filter {name}: {g} = {text}" for g, _, text in members])
            results[name] = res
            bar.update(1)
    k_last = -1
    lat, h, q = nodes.lat[rep], nodes.h[rep], nodes.q_nb[rep]
    mets = {name: [nav_metrics(res.P_truth[b], lat, h, q) for b in range(B)] for name, res in results.items()}
    for b, (gname, v, text) in enumerate(members):
        a = mets["A"][b]
        for name in S.cases:
            m = mets[name][b]
            rows.append({"group": gname, "magnitude": text, "magnitude, SI value": v,
                         "SI unit": si_unit({g["name"]: g["unit_text"] for g in opts["groups"]}[gname]),
                         "filter": name,
                         "states": S.specs[name].n,
                         "CEP [ft]": m["cep"][k_last] / FT, "alt PE [ft]": m["alt_pe"][k_last] / FT,
                         "azimuth 1sigma [arcmin]": m["sigma_azimuth"][k_last] / ARCMIN,
                         "CEP / A [-]": m["cep"][k_last] / a["cep"][k_last],
                         "alt PE / A [-]": m["alt_pe"][k_last] / a["alt_pe"][k_last]})
    sweep = pd.DataFrame(rows)
    # one group, then one filter, in contiguous rows: a workbook chart series per filter
    gpos = {g["name"]: i for i, g in enumerate(opts["groups"])}
    fpos = {c: i for i, c in enumerate(S.cases)}
    sweep = sweep.iloc[np.lexsort((sweep["magnitude, SI value"].to_numpy(), sweep["filter"].map(fpos).to_numpy(),
                                   sweep["group"].map(gpos).to_numpy()))].reset_index(drop=True)
    charts = [{"sheet": "sweep", "where": {"group": g["name"]}, "group": "filter", "x": "magnitude, SI value",
               "y": ["CEP / A [-]"], "log_x": True, "marker": "circle", "target": "charts", "anchor": (1 + 19 * k, 1),
               "title": f"{g['name']}: true CEP / CEP of filter A at the report time, per filter",
               "x_title": f"{g['name']} 1sigma [{si_unit(g['unit_text'])}]", "y_title": "CEP / CEP_A [-]"}
              for k, g in enumerate(opts["groups"])]
    thresholds = threshold_table(sweep, opts["threshold"], [g["name"] for g in opts["groups"]],
                                 [c for c in S.cases if c != "A"], truth, opts)
    elapsed = time.perf_counter() - t_start
    provenance = {"truth_model": truth.name, "truth_model_file": truth.path, "truth_model_sha256": truth.sha256,
                  "filter_file": ", ".join(map(str, S.filter_files)), "zupt_updates": int(len(S.update_steps)),
                  "threshold CEP / A": opts["threshold"], "members per filter": B,
                  **resource_provenance(S.resources), "compute_seconds": f"{elapsed:.2f}"}
    result = MagnitudeSweepResult(
        name=S.hdr["name"], kind="magnitude_sweep", tables={"summary": thresholds, "sweep": sweep},
        resolved={**decl, "study": {**decl["study"], "name": S.hdr["name"]}}, provenance=provenance, charts=charts,
        sweep=sweep, groups=list(opts["groups"]), threshold=opts["threshold"],
        declared={g["name"]: truth.states[truth.index[g["states"][0]]].sigma for g in opts["groups"]})
    result.figures = {"magnitude_sweep": partial(sweep_figure, result)}
    return result


def threshold_table(sweep: pd.DataFrame, thr: float, groups, filters, truth, opts) -> pd.DataFrame:
    """Per group and filter: the magnitude at which CEP / CEP_A first reaches ``thr``.

    The crossing is interpolated linearly in log(magnitude) between the two
    swept points that bracket it; a filter that stays below (above) the
    threshold over the whole sweep is reported as beyond (below) its range.
    """
    rows = []
    for gi, g in enumerate(groups):
        decl_sig = {truth.states[truth.index[n]].sigma for n in opts["groups"][gi]["states"]}
        for f in filters:
            s = sweep[(sweep["group"] == g) & (sweep["filter"] == f)].sort_values("magnitude, SI value")
            x, r = s["magnitude, SI value"].to_numpy(), s["CEP / A [-]"].to_numpy()
            above = np.flatnonzero(r >= thr)
            row = {"group": g, "filter": f, "threshold CEP / A": thr,
                   "declared magnitude, SI value": ", ".join(f"{v:.4g}" for v in sorted(decl_sig)),
                   "SI unit": si_unit(opts["groups"][gi]["unit_text"]),
                   "CEP / A at smallest [-]": r[0], "CEP / A at largest [-]": r[-1]}
            if above.size == 0:
                row["crossing, SI value"] = np.inf
                row["crossing"] = f"beyond the sweep (> {s['magnitude'].iloc[-1]})"
            elif above[0] == 0:
                row["crossing, SI value"] = 0.0
                row["crossing"] = f"below the sweep (<= {s['magnitude'].iloc[0]})"
            else:
                i = above[0]
                lx = np.log(x[i - 1]) + (thr - r[i - 1]) / (r[i] - r[i - 1]) * (np.log(x[i]) - np.log(x[i - 1]))
                row["crossing, SI value"] = float(np.exp(lx))
                unit = opts["groups"][gi]["unit_text"]
                if unit:
                    from covtool.units import from_si
                    row["crossing"] = f"{float(from_si(np.exp(lx), unit)):.3g} {unit}"
                else:
                    row["crossing"] = f"{np.exp(lx):.4g}"
            rows.append(row)
    return pd.DataFrame(rows)
