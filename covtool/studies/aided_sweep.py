"""The ``[sweep]`` of one declared measurement's σ in the aided study (issue 15).

Holds the ``[sweep]`` section of the ``aided`` kind (:mod:`covtool.studies.aided`):
its keys (``SWEEP_KEYS``, ``SWEEP_WHAT``), its validation (:func:`parse_sweep`),
the measurement plan with the swept σ scaled (:func:`scaled_plan`) and the
``measurement_sweep`` table and figure; moved unchanged out of
:mod:`covtool.studies.aided` to keep each module under 600 lines (issue 12).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from covtool.analysis.sensitivity import scale_grid
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, choice, integer, LIMITS, number, require, table
from covtool.units import ARCMIN

SWEEP_KEYS = {"measurement", "what", "scales"}
#: what a measurement sweep scales: the sensor's σ (truth R and the filters' R_f) or only the filters' R_f
SWEEP_WHAT = ("sigma", "filter_sigma")


def parse_sweep(cfg, measurements, where: str) -> dict:
    """``[sweep]``: scale one declared measurement's σ (issue 15).

    ``measurement`` names a ``[[measurement]]``; ``what = "sigma"`` scales
    the sensor's white noise (the truth's R and the filters' R_f together:
    a sensor-quality trade), ``"filter_sigma"`` only what the filters
    assume (a tuning sensitivity, as seed 002 §3.2 scales R_f);
    ``scales = {from, to, per_decade}`` (log grid through ×1) or a list of
    positive factors.

    Raises
    ------
    StudyFileError
        Unknown key, unknown measurement, bad ``what``, bad scales.
    """
    w = f"{where}: [sweep]"
    cfg = table(cfg, w, StudyFileError)
    check_keys(cfg, SWEEP_KEYS, w, StudyFileError)
    known = [m.name for m in measurements]
    name = choice(require(cfg, "measurement", w, StudyFileError), known, f"{w} measurement", StudyFileError)
    what = choice(cfg.get("what", "sigma"), SWEEP_WHAT, f"{w} what", StudyFileError)
    bound = LIMITS["filter_scale"]
    sc = cfg.get("scales", {"from": 0.1, "to": 10, "per_decade": 2})
    if isinstance(sc, list):
        if not sc:
            raise StudyFileError(f"{w} scales", "expected at least one scale")
        scales = np.array([number(x, f"{w} scales[{j}]", StudyFileError, lo=bound.lo, hi=bound.hi,
                                  why=bound.reason) for j, x in enumerate(sc)])
        scales = np.unique(np.r_[scales, 1.0])
    else:
        sc = table(sc, f"{w} scales", StudyFileError)
        check_keys(sc, {"from", "to", "per_decade"}, f"{w} scales", StudyFileError)
        lo, hi = (number(require(sc, k, f"{w} scales", StudyFileError), f"{w} scales {k}", StudyFileError,
                         lo=bound.lo, hi=bound.hi, why=bound.reason) for k in ("from", "to"))
        per = integer(require(sc, "per_decade", f"{w} scales", StudyFileError), f"{w} scales per_decade",
                      StudyFileError, limit="per_decade")
        try:
            scales = scale_grid(lo, hi, per)
        except ValueError as exc:
            raise StudyFileError(f"{w} scales", str(exc)) from None
    if scales.size > LIMITS["sweep_points"].hi:
        raise StudyFileError(f"{w} scales", f"{scales.size} scales; at most {LIMITS['sweep_points'].hi:g}")
    return {"measurement": name, "what": what, "scales": tuple(float(x) for x in scales)}


def scaled_plan(pairs, sweep: dict, scale: float) -> list:
    """The plan with the swept measurement's σ (or only its filter σ) times ``scale``."""
    out = []
    for m, st in pairs:
        if m.name == sweep["measurement"] and scale != 1.0:
            fs = m.sigma if m.filter_sigma is None else m.filter_sigma
            m = dataclasses.replace(m, filter_sigma=np.asarray(fs, float) * scale,
                                    **({"sigma": np.asarray(m.sigma, float) * scale} if sweep["what"] == "sigma"
                                       else {}))
        out.append((m, st))
    return out


def _sweep_table(swept, sweep, tr, rtimes):
    rows = []
    for (g, case, sc), (m, mt, mc) in swept.items():
        for x in rtimes:
            i = int(np.argmin(np.abs(tr - x)))
            rows.append({"grade": g, "case": case, "measurement": sweep["measurement"], "scaled": sweep["what"],
                         "scale": sc, "sigma [SI]": ", ".join(f"{v:g}" for v in m.sigma),
                         "filter sigma [SI]": ", ".join(f"{v:g}" for v in np.diag(m.Rf()) ** 0.5),
                         "t [min]": tr[i] / 60, "CEP [m]": mt["cep"][i], "sigma_N [m]": mt["sigma_north"][i],
                         "sigma_E [m]": mt["sigma_east"][i], "sigma_D [m]": mt["sigma_down"][i],
                         "azimuth [arcmin]": mt["sigma_azimuth"][i] / ARCMIN,
                         "filter-claimed CEP [m]": mc["cep"][i]})
    return pd.DataFrame(rows)
