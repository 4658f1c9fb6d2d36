"""Test-session setup.

Tests call the numeric core directly, not through :func:`covtool.run_study`,
which is where covtool limits the BLAS pool to one thread
(:func:`covtool.studies.one_blas_thread`); the session does the same, so
tests run as the studies do (and xdist's workers do not oversubscribe the cores).
"""

from covtool.studies import one_blas_thread

_BLAS = one_blas_thread()
