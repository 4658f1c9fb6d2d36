"""AD-reset scale-error study: reproduce seed 000, eq (1)-(27).

Reads an ``ad_reset`` study declaration, derives the parameters the paper
leaves implicit, and computes:

* Fig 2 -- filtered error extrema at small input (isolated pulses);
* Fig 3 -- the zero and extremum points ``Z(N_a, k)``, ``D(N_a, k)``;
* Fig 4 / Table 1 -- filtered error at large input, sensor and
  navigation rate;
* Fig 5 / Tables 2-3 -- leveling-alignment tilt error, with and without
  the accelerometer pre-filter;
* Bode data of each filter.

Paper values from ``[reference]`` are only compared against, never used in
a computation.  The runner computes; :mod:`covtool.io.writers` writes.
"""

from __future__ import annotations

import math
from pathlib import Path
import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.board import adreset, alignment as align, output_filter as of
from covtool.plotting.ad_reset import ad_reset_figure, ratio_label
from covtool.results import AdResetResult
from covtool.studies.ad_reset_config import parse
from covtool.units import from_si
from covtool.version import __version__


KIND = "ad_reset"


# --------------------------------------------------------------------------- numerics


def derive(p: dict) -> dict:
    """Derive the parameters the paper leaves implicit.

    Returns
    -------
    dict
        ``filt`` (eq (11) filter), ``sf`` [m/s], ``thresholds``
        (eq (19)), ``dt``, ``dt_nav`` [s], per-ratio ``n_e`` [counts],
        ``S`` [m/s^2] and pulse area [m/s].
    """
    d: dict = {}
    d["dt"] = 1.0 / p["fs"]
    d["dt_nav"] = 1.0 / p["f_nav"]
    d["filt"] = of.butterworth_filter(p["fc"], p["fs"], damping=p["damping"])
    if "sf_given" in p:
        d["sf"] = p["sf_given"]
    else:
        d["sf"] = adreset.scale_factor_from_reset_period(p["a_ref"], d["filt"].ringing_period, d["dt"])
    d["thresholds"] = of.regime_thresholds(d["filt"])
    d["n_e"] = [r * p["n_t"] for r in p["ratios"]]
    d["S"] = [adreset.pulse_height(d["sf"], p["n_t"], ne, d["dt"]) for ne in d["n_e"]]
    d["area"] = [s * d["dt"] for s in d["S"]]
    return d


def _scaled_extrema(unit_max: float, unit_min: float, s: float, const: float) -> tuple[float, float]:
    """Extrema of ``const + s * y`` from the extrema of ``y``."""
    hi, lo = (s * unit_max, s * unit_min) if s >= 0 else (s * unit_min, s * unit_max)
    return const + hi, const + lo


def _period(p: dict, d: dict, acc: float) -> int:
    return adreset.reset_period_samples(acc, d["sf"], d["dt"], p["rounding"])


def _effective_accel(p: dict, d: dict, acc: float) -> float:
    """Input whose reset period is the whole-sample period used.

    Rounding ``N_a`` to whole samples changes the mean of the pulse train,
    ``S / N_a``; taking the constant term of eq (10) at this input keeps the
    mean acceleration error zero, as the bounded velocity error of eq (8)
    requires.
    """
    return math.copysign(d["sf"] / (_period(p, d, acc) * d["dt"]), acc)


def output_error(p: dict, d: dict, acc: float, *, factor: int = 1) -> tuple[float, float]:
    """Unit-pulse extrema of the filtered pulse train at input ``acc``."""
    return of.periodic_extrema(d["filt"], _period(p, d, acc), factor=factor)


def board_simulation_amplitude(p: dict, d: dict, acc: float, n_e: float, seconds: float = 2.0) -> float:
    """Peak-to-peak filtered error from the sample-by-sample board.

    The board fires resets at the real, non-periodic instants (spacing
    alternating between ``floor(N_a)`` and ``ceil(N_a)``).
    """
    n = int(round(seconds * p["fs"]))
    rec = adreset.simulate_board(np.full(n, acc), dt=d["dt"], sf=d["sf"], n_t=p["n_t"], n_e=n_e,
                                 v_bound=p["v_bound"])
    y = of.filter_signal(d["filt"], rec.d_vel_error / d["dt"])[n // 2:]
    return float(y.max() - y.min())


def alignment_error(p: dict, d: dict, acc: float, gains: dict, *, prefiltered: bool,
                    n_e: float) -> tuple[float, float]:
    """Steady-state tilt extrema [rad] of the leveling loop at ``acc``."""
    loop = align.leveling_tf_discrete(gains["k"], gains["kb_g"] / p["g"], p["g"], d["dt_nav"])
    pre = align.prefilter(p["pre_fc"], d["dt_nav"], p["pre_order"]) if prefiltered else None
    period = _period(p, d, acc)
    m = p["decim"]
    radii = [float(np.max(np.abs(loop.poles())))]
    if pre is not None:
        radii.append(float(np.max(np.abs(pre.poles()))))
    settle = int(math.ceil(math.log(1e-12) / math.log(max(radii))))
    window = period // math.gcd(period, m)  # navigation samples in one full period of the pattern
    n_nav = settle + window
    acc_nav = align.navigation_rate_error(_effective_accel(p, d, acc), n_nav, m, sf=d["sf"], n_t=p["n_t"], n_e=n_e,
                                          dt_sensor=d["dt"], period=period)
    return align.alignment_extrema(acc_nav, loop, pre, settle=settle)


def _pct(a, b):
    return 100.0 * (np.asarray(a, dtype=float) / np.asarray(b, dtype=float) - 1.0)


_ratio_label = ratio_label


# --------------------------------------------------------------------------- tables


def _fig2(p, d, tables, figs, charts, summary):
    filt = d["filt"]
    accs = np.linspace(*p["fig2"], p["points"])
    rows = []
    for a in accs:
        hi, lo = output_error(p, d, a)
        row = {"input acceleration [m/s^2]": a, "reset period [samples]": adreset.reset_period(a, d["sf"], d["dt"])}
        for r, s, ne in zip(p["ratios"], d["S"], d["n_e"]):
            const = float(adreset.constant_error(_effective_accel(p, d, a), p["n_t"], ne))
            mx, mn = _scaled_extrema(hi, lo, s, const)
            row[f"max {_ratio_label(r)} [m/s^2]"] = mx
            row[f"min {_ratio_label(r)} [m/s^2]"] = mn
        rows.append(row)
    _register_extrema("fig2", pd.DataFrame(rows), "input acceleration [m/s^2]", "m/s^2",
                      "Fig 2: filtered error extrema, N_a > 2 pi/omega_n", p, tables, figs, charts,
                      ylabel="acceleration error", anchor="K2")
    iso_cf = of.isolated_amplitude(filt, method="closed_form")
    iso_ex = of.isolated_amplitude(filt, method="exact")
    cases = [(r, ne, s) for r, ne, s in zip(p["ratios"], d["n_e"], d["S"])]
    ne0 = p["n_e_stated"]
    cases.append((ne0 / p["n_t"], ne0, adreset.pulse_height(d["sf"], p["n_t"], ne0, d["dt"])))
    amp_rows = []
    ref = p["ref"].get("fig2")
    for i, (r, ne, s) in enumerate(cases):
        td = abs(s) * iso_ex
        row = {"N_e ratio [%]": 100 * r, "N_e [counts]": ne,
               "paper [m/s^2]": float(ref[i]) if ref is not None and i < len(p["ratios"]) else np.nan,
               "covtool time domain [m/s^2]": td,
               "closed form eq 13-14 [m/s^2]": abs(s) * iso_cf}
        row["diff [%]"] = float(_pct(td, row["paper [m/s^2]"]))
        amp_rows.append(row)
        if not np.isnan(row["paper [m/s^2]"]):
            summary.append(("Fig 2 small-input amplitude", f"N_e = {100 * r:g}% N_t", row["paper [m/s^2]"], td,
                            "m/s^2"))
    tables["fig2_amplitude"] = pd.DataFrame(amp_rows)


def _fig3(p, d, tables, figs, charts):
    filt = d["filt"]
    n_a = np.linspace(*p["fig3"], 4 * p["points"])
    df = pd.DataFrame({
        "N_a [samples]": n_a,
        "Z(N_a,0) [samples]": [of.zero_point(filt, x, 0) for x in n_a],
        "Z(N_a,1) [samples]": [of.zero_point(filt, x, 1) for x in n_a],
        "D(N_a,0) [samples]": [of.extremum_point(filt, x, 0) for x in n_a],
        "D(N_a,1) [samples]": [of.extremum_point(filt, x, 1) for x in n_a],
        "N_a - 1 [samples]": n_a - 1,
    })
    tables["fig3"] = df
    charts.append({"sheet": "fig3", "x": "N_a [samples]", "y": list(df.columns[1:]), "anchor": "I2",
                   "title": "Fig 3: Z(N_a,k) and D(N_a,k)", "x_title": "N_a [samples]",
                   "y_title": "n [samples]"})
    t = d["thresholds"]

    figs["fig3"] = {"kind": "fig3", "thresholds": {k: float(v) for k, v in t.items()}}


def _table1_fig4(p, d, tables, figs, charts, summary, progress):
    from covtool.progress import progress_iter

    filt, t = d["filt"], d["thresholds"]
    ref = p["ref"].get("table1")
    if ref is not None:
        rows = []
        for i, a in enumerate(ref["acc"]):
            n_real = adreset.reset_period(a, d["sf"], d["dt"])
            n_int = _period(p, d, a)
            hi, lo = output_error(p, d, a)
            hin, lon = output_error(p, d, a, factor=p["decim"])
            cf = of.amplitude_closed_form(filt, n_int, t)
            ex = of.periodic_error(filt, n_int, np.arange(n_int), approx=False)
            for j, (r, ne, s) in enumerate(zip(p["ratios"], d["n_e"], d["S"])):
                cov = abs(s) * (hi - lo)
                paper = float(ref["amp"][i, j])
                board = board_simulation_amplitude(p, d, a, ne)
                rows.append({
                    "input acceleration [m/s^2]": a, "N_e ratio [%]": 100 * r,
                    "N_a = SF/(a dT) [samples]": n_real, "N_a used [samples]": n_int,
                    "paper [m/s^2]": paper, "covtool [m/s^2]": cov, "diff [%]": float(_pct(cov, paper)),
                    "closed form eq 16/20 [m/s^2]": abs(s) * cf,
                    "closed form diff [%]": float(_pct(abs(s) * cf, paper)),
                    "exact sum eq 12/15 [m/s^2]": abs(s) * float(ex.max() - ex.min()),
                    "board simulation [m/s^2]": board, "board simulation diff [%]": float(_pct(board, paper)),
                    "navigation rate [m/s^2]": abs(s) * (hin - lon),
                })
        df = pd.DataFrame(rows)
        tables["table1"] = df
        diff = df["diff [%]"].abs()
        summary.append(("Table 1 entries within 2 %", f"of {len(df)}", np.nan, float((diff <= 2).sum()), "count"))
        summary.append(("Table 1 worst |diff|", "", np.nan, float(diff.max()), "%"))

    accs = np.linspace(*p["fig4"], 2 * p["points"])
    rows = []
    for a in progress_iter(accs, "fig 4", progress, unit="input"):
        hi, lo = output_error(p, d, a)
        hin, lon = output_error(p, d, a, factor=p["decim"])
        row = {"input acceleration [m/s^2]": a, "N_a used [samples]": _period(p, d, a)}
        for r, s, ne in zip(p["ratios"], d["S"], d["n_e"]):
            c = float(adreset.constant_error(_effective_accel(p, d, a), p["n_t"], ne))
            row[f"max {_ratio_label(r)} [m/s^2]"], row[f"min {_ratio_label(r)} [m/s^2]"] = \
                _scaled_extrema(hi, lo, s, c)
            row[f"max {_ratio_label(r)} nav [m/s^2]"], row[f"min {_ratio_label(r)} nav [m/s^2]"] = \
                _scaled_extrema(hin, lon, s, c)
        rows.append(row)
    _register_extrema("fig4", pd.DataFrame(rows), "input acceleration [m/s^2]", "m/s^2",
                      "Fig 4: filtered error extrema, N_a < 2 pi/omega_n (dotted/nav: navigation rate)",
                      p, tables, figs, charts, ylabel="acceleration error", anchor="R2", nav=True)


def _tables23_fig5(p, d, tables, figs, charts, summary, progress):
    from covtool.progress import progress_iter

    gains = p["coarse"]
    as_ = from_si(1.0, "arcsec")
    peak = align.impulse_peak_continuous(gains["k"], gains["kb_g"] / p["g"], p["g"])
    unfiltered = {}
    for key, pre in (("table2", False), ("table3", True)):
        ref = p["ref"].get(key)
        if ref is None:
            continue
        rows = []
        for i, a in enumerate(ref["acc"]):
            for j, (r, ne, area) in enumerate(zip(p["ratios"], d["n_e"], d["area"])):
                hi, lo = alignment_error(p, d, a, gains, prefiltered=pre, n_e=ne)
                cov = (hi - lo) * as_
                paper = float(ref["amp"][i, j]) * as_
                row = {"input acceleration [mg]": a / (1e-3 * p["g"]), "N_e ratio [%]": 100 * r,
                       "reset period [s]": adreset.reset_period(a, d["sf"], d["dt"]) * d["dt"],
                       "paper [arcsec]": paper, "covtool [arcsec]": cov, "diff [%]": float(_pct(cov, paper))}
                if pre:
                    base = unfiltered[(i, j)]
                    row["paper ratio to Table 2 [%]"] = 100 * paper / base[0]
                    row["covtool ratio to Table 2 [%]"] = 100 * cov / base[1]
                else:
                    row["isolated-pulse closed form [arcsec]"] = abs(area) * peak * as_
                    unfiltered[(i, j)] = (paper, cov)
                rows.append(row)
        df = pd.DataFrame(rows)
        tables[key] = df
        label = "Table 2 (no pre-filter)" if key == "table2" else "Table 3 (pre-filter)"
        summary.append((f"{label} worst |diff|", "", np.nan, float(df["diff [%]"].abs().max()), "%"))
        if pre:
            for mg in (1, 5):
                sel = df[np.isclose(df["input acceleration [mg]"], mg)]
                if len(sel):
                    summary.append((f"Table 3 / Table 2 at {mg} mg", "mean over ratios",
                                    float(sel["paper ratio to Table 2 [%]"].mean()),
                                    float(sel["covtool ratio to Table 2 [%]"].mean()), "%"))

    accs = np.linspace(*p["fig5"], p["points"])
    rows = []
    for a in progress_iter(accs, "fig 5", progress, unit="input"):
        row = {"input acceleration [mg]": a / (1e-3 * p["g"])}
        for pre, tag in ((False, ""), (True, " pre-filter")):
            # the tilt error is linear in the pulse height; compute for the first ratio and scale
            hi, lo = alignment_error(p, d, a, gains, prefiltered=pre, n_e=d["n_e"][0])
            for r, ne in zip(p["ratios"], d["n_e"]):
                k = (ne / (p["n_t"] + ne)) / (d["n_e"][0] / (p["n_t"] + d["n_e"][0]))
                mx, mn = (k * hi, k * lo) if k >= 0 else (k * lo, k * hi)
                row[f"max {_ratio_label(r)}{tag} [arcsec]"] = mx * as_
                row[f"min {_ratio_label(r)}{tag} [arcsec]"] = mn * as_
        rows.append(row)
    _register_extrema("fig5", pd.DataFrame(rows), "input acceleration [mg]", "arcsec",
                      "Fig 5: coarse leveling tilt error (dotted: with pre-filter)", p, tables, figs, charts,
                      ylabel="tilt error", anchor="O2", tag=" pre-filter")

    # fine alignment: gains about 4x lower (no paper values)
    fine = p["fine"]
    rows = []
    ref2 = p["ref"].get("table2")
    for a in (ref2["acc"] if ref2 is not None else np.linspace(*p["fig5"], 5)):
        row = {"input acceleration [mg]": a / (1e-3 * p["g"])}
        for r, ne in zip(p["ratios"], d["n_e"]):
            hi, lo = alignment_error(p, d, a, fine, prefiltered=False, n_e=ne)
            row[f"fine {_ratio_label(r)} [arcsec]"] = (hi - lo) * as_
            hi, lo = alignment_error(p, d, a, p["coarse"], prefiltered=False, n_e=ne)
            row[f"coarse {_ratio_label(r)} [arcsec]"] = (hi - lo) * as_
        rows.append(row)
    tables["alignment_fine"] = pd.DataFrame(rows)


def _bode(p, d, tables, figs, charts):
    import control

    c = p["coarse"]
    loop_c = align.leveling_tf(c["k"], c["kb_g"] / p["g"], p["g"])
    loop_d = align.leveling_tf_discrete(c["k"], c["kb_g"] / p["g"], p["g"], d["dt_nav"])
    pre = align.prefilter(p["pre_fc"], d["dt_nav"], p["pre_order"])
    specs = {
        "bode_output_filter": [("H(z) eq 11", d["filt"].tf, np.geomspace(0.1, p["fs"] / 2 * 0.999, 300))],
        "bode_alignment": [("H2(s) eq 26", loop_c, np.geomspace(1e-3, p["f_nav"] / 2 * 0.999, 300)),
                           ("H2(z) eq 27", loop_d, np.geomspace(1e-3, p["f_nav"] / 2 * 0.999, 300))],
        "bode_prefilter": [("pre-filter", pre, np.geomspace(1e-3, p["f_nav"] / 2 * 0.999, 300))],
    }
    for name, systems in specs.items():
        freq = systems[0][2]
        df = pd.DataFrame({"frequency [Hz]": freq})
        for label, sys, f in systems:
            resp = control.frequency_response(sys, 2 * np.pi * f)
            h = np.asarray(resp.complex).ravel()
            df[f"{label} magnitude [dB]"] = 20 * np.log10(np.abs(h))
            df[f"{label} phase [deg]"] = np.degrees(np.unwrap(np.angle(h)))
        tables[name] = df
        charts.append({"sheet": name, "x": "frequency [Hz]", "log_x": True, "anchor": "H2",
                       "y": [col for col in df.columns if "magnitude" in col],
                       "title": f"Bode magnitude: {', '.join(s[0] for s in systems)}",
                       "x_title": "frequency [Hz]", "y_title": "magnitude [dB]"})

        figs[name] = {"kind": "bode"}


def _register_extrema(name, df, xcol, unit, title, p, tables, figs, charts, *, ylabel, anchor, nav=False,
                      tag=None):
    """Store an extrema sweep as a table, a chart and a PNG figure."""
    tables[name] = df
    ycols = [c for c in df.columns if c.startswith(("max", "min"))]
    charts.append({"sheet": name, "x": xcol, "y": ycols, "anchor": anchor, "title": title,
                   "x_title": xcol, "y_title": f"{ylabel} [{unit}]"})
    figs[name] = {"kind": "extrema", "xcol": xcol, "ratios": list(p["ratios"]), "unit": unit, "title": title,
                  "ylabel": ylabel, "nav": nav, "tag": tag}


def _derived_table(p, d) -> pd.DataFrame:
    filt, t = d["filt"], d["thresholds"]
    c = p["coarse"]
    c1, c2, dd = align.tustin_coefficients(c["k"], c["kb_g"] / p["g"], p["g"], d["dt_nav"])
    bound = adreset.velocity_error_bound(d["sf"], p["n_t"], d["n_e"][0], v_bound=p["v_bound"])
    sigma = adreset.velocity_error_sigma(d["sf"], p["n_t"], d["n_e"][0], v_bound=p["v_bound"])
    sf_src = ("given" if "sf_given" in p else
              f"SF = a* (2 pi/omega_n) dT with a* = {p.get('a_ref', float('nan')):g} m/s^2: "
              "reset period equals the ringing period 2 pi/omega_n at a*")
    rows = [
        ("SF (velocity per reset pulse)", d["sf"], "m/s", sf_src),
        ("b (eq 11)", filt.b, "-", "Butterworth, bilinear with pre-warping at the cutoff"),
        ("zeta (eq 11 pole radius)", filt.zeta, "-", "sqrt(a2) of the designed filter"),
        ("omega_n (eq 11 pole angle)", filt.omega_n, "rad/sample", "acos(-a1 / (2 zeta))"),
        ("2 pi / omega_n", filt.ringing_period, "samples", "second zero of eq 13"),
        ("input where N_a = 2 pi/omega_n", d["sf"] / (filt.ringing_period * d["dt"]), "m/s^2", "SF / (N dT)"),
        ("D0", t["D0"], "samples", "D(N_a,0) = N_a - 1 (eq 18-19)"),
        ("Z1", t["Z1"], "samples", "Z(N_a,1) = N_a - 1 (eq 17-19)"),
        ("D1", t["D1"], "samples", "D(N_a,1) = N_a - 1 (eq 18-19)"),
        ("pi / omega_n", math.pi / filt.omega_n, "samples", "eq 19"),
        ("navigation decimation", p["decim"], "samples", "board rate / navigation rate, moving average"),
        ("k^b (coarse)", c["kb_g"] / p["g"], "1/m", "kb_g / g"),
        ("c1 (eq 27, coarse)", c1, "-", "(2 - k^b g dT^2/2) / D"),
        ("c2 (eq 27, coarse)", c2, "-", "(1 - k dT/2 + k^b g dT^2/4) / D"),
        ("d (eq 27, coarse)", dd, "s^2", "(dT^2/4) / D"),
        ("loop natural frequency (coarse)", math.sqrt(c["kb_g"]), "rad/s", "sqrt(k^b g)"),
        ("loop damping (coarse)", c["k"] / (2 * math.sqrt(c["kb_g"])), "-", "k / (2 sqrt(k^b g))"),
        (f"velocity-error bound, N_e = {_ratio_label(p['ratios'][0])}", bound, "m/s", "eq 7-8, exact"),
        (f"velocity-error 1-sigma, N_e = {_ratio_label(p['ratios'][0])}", sigma, "m/s", "bound / sqrt(3)"),
        ("sawtooth time constant at 1 g", adreset.suggested_time_constant(d["sf"], p["g"]), "s", "SF / (6 g)"),
    ]
    for r, ne, s, area in zip(p["ratios"], d["n_e"], d["S"], d["area"]):
        rows.append((f"N_e at {_ratio_label(r)}", ne, "counts", "ratio * N_t"))
        rows.append((f"S at {_ratio_label(r)} (eq 10)", s, "m/s^2", "SF N_e / (N_hat dT)"))
    return pd.DataFrame(rows, columns=["parameter", "value", "unit", "derivation"])


# --------------------------------------------------------------------------- entry point


def run(decl: dict, *, path: Path | None = None, progress: bool = False) -> AdResetResult:
    """Run an ``ad_reset`` study.

    Parameters
    ----------
    decl : dict
        Study declaration (see ``studies/ad_reset_scale_error.toml``).
    path : Path, optional
        Study file, for messages and provenance.
    progress : bool
        Show progress bars for the sweeps.

    Returns
    -------
    AdResetResult
        Tables ``summary``, ``derived_parameters``, ``fig2``,
        ``fig2_amplitude``, ``fig3``, ``table1``, ``fig4``, ``table2``,
        ``table3``, ``fig5``, ``alignment_fine`` and Bode data; figures
        ``fig2`` .. ``fig5`` and the Bode plots.
    """
    t0 = time.perf_counter()
    p = parse(decl, path)
    d = derive(p)
    tables: dict[str, pd.DataFrame] = {}
    figs: dict = {}
    charts: list = []
    summary: list = [("SF (derived)", "", np.nan, d["sf"], "m/s")]
    _fig2(p, d, tables, figs, charts, summary)
    _fig3(p, d, tables, figs, charts)
    _table1_fig4(p, d, tables, figs, charts, summary, progress)
    _tables23_fig5(p, d, tables, figs, charts, summary, progress)
    _bode(p, d, tables, figs, charts)
    sm = pd.DataFrame(summary, columns=["quantity", "case", "paper", "covtool", "unit"])
    sm["diff [%]"] = _pct(sm["covtool"], sm["paper"])
    out = {"summary": sm, "derived_parameters": _derived_table(p, d)}
    out.update(tables)
    result = AdResetResult(
        name=p["name"], kind=KIND, tables=out, resolved=decl, charts=charts, figure_specs=figs,
        provenance={"covtool_version": __version__, "runtime_s": round(time.perf_counter() - t0, 3),
                    "study_file": str(path) if path else "<dict>"},
        params=p, derived=d,
    )
    result.figures = {name: partial(ad_reset_figure, result, name) for name in figs}
    return result
