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
import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS)

from covtool.studies import one_blas_thread

_BLAS = one_blas_thread()
