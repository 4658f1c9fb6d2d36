"""Rows of the output tables: summary and history rows in SI and paper units, validity per case."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from covtool.analysis.metrics import first_invalid, validity, validity_text
from covtool.errors import ValidityWarning
from covtool.units import ARCMIN, ARCSEC, FT

__all__ = [
    "history_frame", "summary_row", "case_validity",
]


def case_validity(case: str, m: dict, t: np.ndarray, *, warn: bool = True) -> dict:
    """First times a case leaves the linear model's domain; warn once.

    Parameters
    ----------
    case : str
        Case name (in the warning).
    m : dict of ndarray, shape (N,)
        :func:`covtool.analysis.metrics.nav_metrics` along the case's history.
    t : ndarray, shape (N,)
        Times of the history. [s]
    warn : bool
        Issue one :class:`covtool.errors.ValidityWarning` naming the case and
        the first time of each failed test.

    Returns
    -------
    dict of str to float
        :func:`covtool.analysis.metrics.first_invalid`.
    """
    first = first_invalid(m, t)
    if first and warn:
        warnings.warn(f"{case}: outside the linear error model's domain: {validity_text(first)}",
                      ValidityWarning, stacklevel=2)
    return first


def history_frame(case: str, t: np.ndarray, m: dict, every: float | None = None) -> pd.DataFrame:
    """History table with SI and paper units in the headers.

    The ``validity`` column names the domain tests that fail at each time
    (:func:`covtool.analysis.metrics.validity`), empty where the linear model holds.
    """
    sel = np.ones(t.shape, bool)
    if every:
        k = np.round(t / every)
        sel = np.isclose(t, k * every) | (np.arange(t.size) == t.size - 1)
    df = pd.DataFrame({
        "case": case,
        "t [s]": t[sel],
        "t [min]": t[sel] / 60.0,
        "sigma_N [m]": m["sigma_north"][sel],
        "sigma_E [m]": m["sigma_east"][sel],
        "sigma_D [m]": m["sigma_down"][sel],
        "CEP [m]": m["cep"][sel],
        "CEP [ft]": m["cep"][sel] / FT,
        "alt PE [m]": m["alt_pe"][sel],
        "alt PE [ft]": m["alt_pe"][sel] / FT,
        "sigma_vN [m/s]": m["sigma_vn"][sel],
        "sigma_vE [m/s]": m["sigma_ve"][sel],
        "sigma_vD [m/s]": m["sigma_vd"][sel],
        "tilt_N [arcsec]": m["sigma_tilt_n"][sel] / ARCSEC,
        "tilt_E [arcsec]": m["sigma_tilt_e"][sel] / ARCSEC,
        "azimuth [arcmin]": m["sigma_azimuth"][sel] / ARCMIN,
    })
    if "cep_pct_distance" in m:
        df["CEP/distance [%]"] = m["cep_pct_distance"][sel]
    flags = validity(m)
    df["validity"] = [", ".join(name for name, f in flags.items() if f[i]) or "ok" for i in np.flatnonzero(sel)]
    return df


def summary_row(case: str, m: dict, k: int, t: float, distance: float | None, *, first: dict | None = None,
                status: str | None = None) -> dict:
    """Table 3 columns at grid index ``k``.

    Parameters
    ----------
    case : str
    m : dict of ndarray
        :func:`covtool.analysis.metrics.nav_metrics`.
    k : int
        Index into ``m``.
    t : float
        Time of index ``k``. [s]
    distance : float or None
        Distance travelled by then. [m]
    first : dict, optional
        :func:`covtool.analysis.metrics.first_invalid` of the case; the ``validity``
        column lists the tests failed by ``t`` with their first time.  By
        default the tests at index ``k`` alone.
    status : str, optional
        Adds a ``status`` column (``"ok"`` or the guard's message) for
        studies that flag a failed case instead of stopping.
    """
    row = {
        "case": case,
        "t [min]": t / 60.0,
        "CEP [ft]": m["cep"][k] / FT,
        "CEP [m]": m["cep"][k],
        "alt PE [ft]": m["alt_pe"][k] / FT,
        "alt PE [m]": m["alt_pe"][k],
        "azimuth 1sigma [arcmin]": m["sigma_azimuth"][k] / ARCMIN,
        "tilt N 1sigma [arcsec]": m["sigma_tilt_n"][k] / ARCSEC,
        "tilt E 1sigma [arcsec]": m["sigma_tilt_e"][k] / ARCSEC,
        "CEP rule 0.589(s1+s2) [m]": m["cep_rule"][k],
    }
    if distance:
        row["distance [km]"] = distance / 1000.0
        row["CEP/distance [%]"] = 100.0 * m["cep"][k] / distance
    if first is None:
        first = {name: t for name, f in validity(m).items() if f[k]}
    row["validity"] = validity_text(first, until=t)
    if status is not None:
        row["status"] = status or "ok"
    return row
