"""Measured memory for the tests of the estimates: a run's traced peak, and the estimate it recorded.

``tracemalloc`` counts every numpy and Python allocation of the run,
deterministically (unlike the RSS of a process that shares its allocator
pools with a test session).
"""

from __future__ import annotations

import tracemalloc

from covtool.studies.resources import parse_bytes


def traced_peak(run, *, warm: bool = False):
    """``(result, peak bytes)`` of ``run()``; ``warm``: call it once first (its first-use imports not counted)."""
    if warm:
        run()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        result = run()
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    return result, peak


def recorded_estimate(result) -> float:
    """The memory check's estimate a study recorded in its provenance, in bytes."""
    return parse_bytes(result.provenance["estimated_peak_memory"], "estimated_peak_memory")
