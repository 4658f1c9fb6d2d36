"""The limits and tolerances of the discretisers, in one place.

Every sub-module of :mod:`covtool.lincov.discretize` reads them from here;
the notes of :mod:`covtool.lincov.discretize` explain the choices.
"""
from __future__ import annotations

from covtool.lincov.kalman import PSD_TOL

#: base-step bound ``νh ≤ θ`` (see the module notes)
THETA = 0.5
#: unit round-off: the adaptive series stops when its tail is below this fraction of the sum
UNIT_ROUNDOFF = 2.0**-53
#: cap of the adaptive base-step series: ``νh ≤ θ`` gains a factor ≥ 10 per term, so reaching it is an error
MAX_TERMS = 40
#: largest fixed order accepted (terms beyond ~30 are below round-off for any step the criterion accepts)
MAX_ORDER = 100
#: use the block path of the exact discretisation when at least this fraction of the states are sensor states
BLOCK_FRACTION = 0.25

__all__ = ["PSD_TOL", "THETA", "UNIT_ROUNDOFF", "MAX_TERMS", "MAX_ORDER", "BLOCK_FRACTION"]
