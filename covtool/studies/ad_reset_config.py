"""The ``ad_reset`` study file (seed 000), validated into the parameters of the runner (SI).

Every table and key of the study (``studies/ad_reset_scale_error.toml``)
is checked here, before any computation, with the file, the table, the key
and the problem named; :func:`covtool.studies.ad_reset.derive` then derives
what the paper leaves implicit.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from covtool.errors import StudyFileError
from covtool.io.config import check_keys, number, quantity, require, string
from covtool.io.names import check_study_name


_SECTIONS = {"study", "board", "output_filter", "navigation", "alignment", "sweeps", "reference"}
_ROUNDINGS = ("floor", "round", "ceil")


# --------------------------------------------------------------------------- parsing


def _number(value, where: str, *, positive=False) -> float:
    x = number(value, where, StudyFileError)
    if positive and not x > 0:
        raise StudyFileError(where, f"{value!r} must be positive")
    return x


def _range(value, dim: str, where: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2:
        raise StudyFileError(where, f"expected [low, high], got {value!r}")
    lo, hi = (quantity(v, dim, where, StudyFileError, positive=True) for v in value)
    if not lo < hi:
        raise StudyFileError(where, f"low {value[0]!r} must be below high {value[1]!r}")
    return lo, hi


def _reference_table(d: dict, where: str, dim: str, n_cols: int) -> dict:
    check_keys(d, {"accelerations", "amplitude", "unit", "note"}, where, StudyFileError)
    accs = require(d, "accelerations", where, StudyFileError)
    if not isinstance(accs, list) or not accs:
        raise StudyFileError(f"{where} accelerations", "expected a non-empty list")
    acc = [quantity(a, "acceleration", f"{where} accelerations", StudyFileError, positive=True) for a in accs]
    unit = require(d, "unit", where, StudyFileError)
    scale = quantity(f"1 {unit}", dim, f"{where} unit", StudyFileError, positive=True)
    amp = require(d, "amplitude", where, StudyFileError)
    if (not isinstance(amp, list) or len(amp) != len(acc)
            or any(not isinstance(r, list) or len(r) != n_cols for r in amp)):
        raise StudyFileError(f"{where} amplitude",
                             f"expected {len(acc)} rows of {n_cols} values (one per error ratio)")
    vals = np.array([[_number(v, f"{where} amplitude", positive=True) for v in r] for r in amp])
    return {"acc": np.array(acc), "acc_text": [str(a) for a in accs], "amp": vals * scale, "unit": unit}


def parse(decl: dict, path: Path | None) -> dict:
    """Validate an ``ad_reset`` declaration; return SI parameters.

    Parameters
    ----------
    decl : dict
        The TOML declaration.
    path : Path or None
        Study file (for messages).

    Returns
    -------
    dict
        Parameters in SI units.

    Raises
    ------
    StudyFileError
        Naming the file, section and key at fault.
    """
    f = str(path) if path else "<study>"
    check_keys(decl, _SECTIONS, f, StudyFileError)
    p: dict = {}

    w = f"{f}: [study]"
    study = require(decl, "study", f, StudyFileError)
    check_keys(study, {"kind", "name", "title", "description"}, w, StudyFileError)
    require(study, "name", w, StudyFileError)
    p["name"] = check_study_name(study, f, StudyFileError, default="ad_reset")
    p["title"] = string(study.get("title", p["name"]), f"{w} title", StudyFileError)
    string(study.get("description", ""), f"{w} description", StudyFileError)

    w = f"{f}: [board]"
    board = require(decl, "board", f, StudyFileError)
    check_keys(board, {"sample_rate", "n_t", "error_ratios", "n_e_stated", "v_bound",
                       "reset_period_reference", "scale_factor", "period_rounding"}, w, StudyFileError)
    p["fs"] = quantity(require(board, "sample_rate", w, StudyFileError), "frequency", f"{w} sample_rate",
                       StudyFileError, positive=True)
    p["n_t"] = _number(require(board, "n_t", w, StudyFileError), f"{w} n_t", positive=True)
    ratios = require(board, "error_ratios", w, StudyFileError)
    if not isinstance(ratios, list) or not ratios:
        raise StudyFileError(f"{w} error_ratios", "expected a non-empty list of ratios, e.g. [0.02, 0.05]")
    p["ratios"] = [_number(r, f"{w} error_ratios") for r in ratios]
    for r in p["ratios"]:
        if not -0.5 < r < 0.5 or r == 0:
            raise StudyFileError(f"{w} error_ratios", f"{r!r} must be non-zero and within (-0.5, 0.5)")
    p["n_e_stated"] = _number(board.get("n_e_stated", p["ratios"][0] * p["n_t"]), f"{w} n_e_stated")
    p["v_bound"] = _number(board.get("v_bound", p["n_t"]), f"{w} v_bound", positive=True)
    if not p["v_bound"] > p["n_t"] / 2:
        raise StudyFileError(f"{w} v_bound", f"must exceed n_t/2 = {p['n_t'] / 2:g} counts")
    has_sf, has_ref = "scale_factor" in board, "reset_period_reference" in board
    if has_sf == has_ref:
        raise StudyFileError(w, "give exactly one of 'scale_factor' (velocity per reset pulse) "
                                "or 'reset_period_reference' (input at which N_a = 2 pi/omega_n)")
    if has_sf:
        p["sf_given"] = quantity(board["scale_factor"], "velocity", f"{w} scale_factor", StudyFileError,
                                 positive=True)
    else:
        p["a_ref"] = quantity(board["reset_period_reference"], "acceleration", f"{w} reset_period_reference",
                              StudyFileError, positive=True)
    p["rounding"] = board.get("period_rounding", "floor")
    if p["rounding"] not in _ROUNDINGS:
        raise StudyFileError(f"{w} period_rounding", f"{p['rounding']!r} is not one of {', '.join(_ROUNDINGS)}")

    w = f"{f}: [output_filter]"
    flt = require(decl, "output_filter", f, StudyFileError)
    check_keys(flt, {"cutoff", "damping"}, w, StudyFileError)
    p["fc"] = quantity(require(flt, "cutoff", w, StudyFileError), "frequency", f"{w} cutoff", StudyFileError,
                       positive=True)
    p["damping"] = _number(flt.get("damping", 1 / math.sqrt(2)), f"{w} damping", positive=True)
    if not p["fc"] < p["fs"] / 2:
        raise StudyFileError(f"{w} cutoff", "must be below half the board sample rate")

    w = f"{f}: [navigation]"
    nav = require(decl, "navigation", f, StudyFileError)
    check_keys(nav, {"rate", "decimation"}, w, StudyFileError)
    p["f_nav"] = quantity(require(nav, "rate", w, StudyFileError), "frequency", f"{w} rate", StudyFileError,
                          positive=True)
    ratio = p["fs"] / p["f_nav"]
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise StudyFileError(f"{w} rate", f"must divide the board rate ({p['fs']:g} Hz) into whole samples")
    p["decim"] = int(round(ratio))
    dec = nav.get("decimation", "moving_average")
    if dec != "moving_average":
        raise StudyFileError(f"{w} decimation", f"{dec!r} is not supported (only 'moving_average')")

    w = f"{f}: [alignment]"
    al = require(decl, "alignment", f, StudyFileError)
    check_keys(al, {"gravity", "coarse", "fine", "prefilter"}, w, StudyFileError)
    p["g"] = quantity(al.get("gravity", "1 g"), "acceleration", f"{w} gravity", StudyFileError, positive=True)
    for key in ("coarse", "fine"):
        ww = f"{f}: [alignment.{key}]"
        gains = require(al, key, w, StudyFileError)
        check_keys(gains, {"k", "kb_g"}, ww, StudyFileError)
        p[key] = {"k": _number(require(gains, "k", ww, StudyFileError), f"{ww} k", positive=True),
                  "kb_g": _number(require(gains, "kb_g", ww, StudyFileError), f"{ww} kb_g", positive=True)}
    ww = f"{f}: [alignment.prefilter]"
    pre = require(al, "prefilter", w, StudyFileError)
    check_keys(pre, {"cutoff", "order"}, ww, StudyFileError)
    p["pre_fc"] = quantity(require(pre, "cutoff", ww, StudyFileError), "frequency", f"{ww} cutoff",
                           StudyFileError, positive=True)
    p["pre_order"] = pre.get("order", 1)
    if type(p["pre_order"]) is not int or p["pre_order"] not in (1, 2):
        raise StudyFileError(f"{ww} order", f"{p['pre_order']!r} must be 1 or 2")
    if not p["pre_fc"] < p["f_nav"] / 2:
        raise StudyFileError(f"{ww} cutoff", "must be below half the navigation rate")

    w = f"{f}: [sweeps]"
    sw = require(decl, "sweeps", f, StudyFileError)
    check_keys(sw, {"fig2", "fig3", "fig4", "fig5", "points"}, w, StudyFileError)
    p["fig2"] = _range(require(sw, "fig2", w, StudyFileError), "acceleration", f"{w} fig2")
    p["fig4"] = _range(require(sw, "fig4", w, StudyFileError), "acceleration", f"{w} fig4")
    p["fig5"] = _range(require(sw, "fig5", w, StudyFileError), "acceleration", f"{w} fig5")
    fig3 = require(sw, "fig3", w, StudyFileError)
    if not isinstance(fig3, list) or len(fig3) != 2:
        raise StudyFileError(f"{w} fig3", f"expected [low, high] pulse periods in samples, low >= 2, got {fig3!r}")
    lo3, hi3 = (number(v, f"{w} fig3", StudyFileError) for v in fig3)
    if not 2 <= lo3 < hi3 <= 1e6:
        raise StudyFileError(f"{w} fig3", f"expected [low, high] pulse periods in samples, low >= 2, got {fig3!r}")
    p["fig3"] = (lo3, hi3)
    pts = sw.get("points", 60)
    if isinstance(pts, bool) or not isinstance(pts, int) or not 5 <= pts <= 2000:
        raise StudyFileError(f"{w} points", f"{pts!r} must be an integer in [5, 2000]")
    p["points"] = pts

    w = f"{f}: [reference]"
    ref = decl.get("reference", {})
    check_keys(ref, {"fig2", "table1", "table2", "table3"}, w, StudyFileError)
    n_r = len(p["ratios"])
    p["ref"] = {}
    if "fig2" in ref:
        ww = f"{f}: [reference.fig2]"
        check_keys(ref["fig2"], {"amplitude", "unit", "note"}, ww, StudyFileError)
        amp = require(ref["fig2"], "amplitude", ww, StudyFileError)
        if not isinstance(amp, list) or len(amp) != n_r:
            raise StudyFileError(f"{ww} amplitude", f"expected {n_r} values (one per error ratio)")
        scale = quantity(f"1 {require(ref['fig2'], 'unit', ww, StudyFileError)}", "acceleration",
                         f"{ww} unit", StudyFileError, positive=True)
        p["ref"]["fig2"] = np.array([_number(a, f"{ww} amplitude", positive=True) for a in amp]) * scale
    for key, dim in (("table1", "acceleration"), ("table2", "angle"), ("table3", "angle")):
        if key in ref:
            p["ref"][key] = _reference_table(ref[key], f"{f}: [reference.{key}]", dim, n_r)
    return p
