"""Test-session setup.

Tests call the numeric core directly, not through :func:`covtool.run_study`,
which is where covtool limits the BLAS pool to one thread
(:func:`covtool.studies.one_blas_thread`); the session does the same, so
tests run as the studies do (and xdist's workers do not oversubscribe the cores).

threadpoolctl limits only the BLAS libraries already loaded, and importing
:mod:`covtool.studies` no longer loads numpy (its start-up is lazy): numpy's
and scipy's OpenBLAS are loaded here first.  Without them the limit applied to
nothing, and each xdist worker ran OpenBLAS with one thread per core; on the
two-core CI machine with ``-n 2``, numpy's batched ``eigh`` of the
Monte Carlo null's Q_d factors (1800 × 58 × 58) took 30× the CPU time of one
thread and 20× its wall time.
"""

import numpy  # noqa: F401  (loads numpy's OpenBLAS)
import pytest
import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS)

from covtool.studies import one_blas_thread

_BLAS = one_blas_thread()


# Longest modules first (sums of per-test durations from `pytest -n 2 --durations=0`, December 2026), so
# that `-n 2 --dist worksteal` ends on short tests rather than on one worker's long tail: worksteal hands
# each worker a contiguous half of the collection order and steals from the end of a queue.  Whole
# modules move, in their own order, so their module-scoped fixtures are still built once.  Modules not
# listed (new ones) keep their collection order after these.
_SLOW_FIRST = (
    "test_parallel.py test_aiding_monte_carlo.py test_memory_streaming.py test_guard.py test_study_reference.py "
    "test_aiding_engine.py test_monte_carlo.py test_linear_vs_nonlinear.py test_input_validation.py "
    "test_monte_carlo_null.py test_impact.py test_filters.py test_startup.py test_budget.py test_aiding_study.py "
    "test_sensitivity.py test_results.py test_study_config.py test_aiding_trade.py test_typed_config.py "
    "test_aided_mc_null.py test_outputs.py test_trade.py test_physics.py test_aiding_budget.py test_studies.py"
).split()


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(_SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: order within a module kept


@pytest.fixture
def forking():
    """A test of a forked path: skipped where no fork can help (no ``os.fork``, one core), else it must fork.

    :func:`covtool.forked.can_split` also refuses while another thread runs
    (a lock it holds at the fork would stay held in the child): a test that
    leaves a thread behind would make later tests of this worker take the
    one-process path and pass without testing the forked one.  That fails
    here, naming the threads.
    """
    import os
    import threading

    from covtool.forked import _ACTIVE, _tracing, can_split

    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    if not hasattr(os, "fork") or cores < 2:
        pytest.skip("needs os.fork and two cores")
    assert can_split(), (f"this process does not fork: threads {[t.name for t in threading.enumerate()]}, "
                         f"forked children running {_ACTIVE['children']}, tracemalloc tracing {_tracing()}")


@pytest.fixture
def nan_in_qd(monkeypatch):
    """``nan_in_qd(system, t)``: a NaN in Q_d (state ``dvN``) of the step at time ``t`` of the systems made by
    :func:`covtool.studies.grid.discretize_chunked` whose label names ``system`` ("sdins58", "B1")."""
    import numpy as np

    from covtool.studies import grid

    made = grid.discretize_chunked

    def arm(system: str, t: float):
        def broken(F, Qc, dt, method, order=None, **kw):
            Phi, Qd = made(F, Qc, dt, method, order, **kw)
            i = np.flatnonzero(np.isclose(kw.get("times", np.zeros(0)), t))
            if i.size and system in kw.get("what", ""):
                Qd = np.array(Qd)
                Qd[i[0], 3, 3] = np.nan
            return Phi, Qd

        monkeypatch.setattr(grid, "discretize_chunked", broken)

    return arm
