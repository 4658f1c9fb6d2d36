"""covtool: linear covariance analysis of strapdown INS and their Kalman filters.

Conventions (stated once, used everywhere)
-------------------------------------------
* SI inside: rad, m, s, m/s, m/s^2, rad/s.  Datasheet units only in files,
  spreadsheet headers and plot axes (:mod:`covtool.units`).
* Navigation frame NED; position geodetic (L, l, h) on WGS-84 (:mod:`covtool.nav.earth`).
* Attitude quaternion ``q`` scalar first, body→NED (``C_b^n``); the attitude
  error state is the additive quaternion error ``δq = q̂ − q`` (seed 002, eq (1)).
* Error = computed − true.  White noise is specified by its power spectral
  density (two-sided, [unit^2/Hz] = [unit^2·s]).
* Matrices carry state names; reduced filters are projections of the truth
  model selected by name.
"""

from covtool.version import __version__

__all__ = ["__version__", "run_study"]


def run_study(path_or_dict, **overrides):
    """Run a study file (or an equivalent dict) and return its result.

    Parameters
    ----------
    path_or_dict : str, Path or dict
        A ``studies/*.toml`` file, or the same declaration as a dict.
    **overrides
        Top-level keys replaced in the declaration (e.g. ``duration="10 min"``
        applies to ``[study]``).

    Returns
    -------
    covtool.results.StudyResult
        Tables as pandas DataFrames, figure builders and provenance.
    """
    from covtool.studies import run_study as _run

    return _run(path_or_dict, **overrides)
