"""Exceptions raised by covtool.

Every error that can be caused by a user's file or argument is a subclass of
:class:`CovtoolError` *and* of ``ValueError``, and its message names the file,
the field and the problem, e.g.::

    models/x.toml: state 'gyro_bias_z': sigma '0.018 deg/h/s' is not an angular rate
"""

from __future__ import annotations


class CovtoolError(Exception):
    """Base class of all covtool errors."""


class InputError(CovtoolError, ValueError):
    """A user-supplied file or argument is invalid.

    Parameters
    ----------
    where : str
        Location prefix, usually ``"<file>: <field>"``.
    problem : str
        What is wrong with it.
    """

    def __init__(self, where: str, problem: str):
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}" if where else problem)


class UnitError(InputError):
    """A quantity string has an unknown or dimensionally wrong unit."""


class ModelFileError(InputError):
    """A model file (``models/*.toml``) is invalid."""


class StudyFileError(InputError):
    """A study file (``studies/*.toml``) is invalid."""


class TrajectoryError(InputError):
    """A trajectory declaration or CSV file is invalid."""


class NumericalError(CovtoolError, ArithmeticError):
    """A covariance lost symmetry or positive semi-definiteness.

    The message names the step (time and operation) where it happened.
    """


class SystemCheckError(NumericalError):
    """Φ or Q_d of a step failed its guard when it was made on demand (a streamed system's chunk).

    Raised by :class:`covtool.lincov.streamed.StreamedSystem` for the
    :class:`NumericalError` of its ``make``, with the same message (the
    system, the step's time and the state).  The runs that read a streamed
    system let it through unchanged: it is not a failure of the run's own
    covariances (a gain, a flagged case) but of the model, so it stops the
    study as a whole-grid system's guard would have before the run.
    """


class CovtoolWarning(UserWarning):
    """Base class of the warnings a study run gives; the CLI prints each on one line."""


class ValidityWarning(CovtoolWarning):
    """A result left the linear error model's domain (:func:`covtool.analysis.metrics.validity`).

    The numbers are still written, with the reason in the summary's
    ``validity`` column.
    """


class FlaggedCaseWarning(CovtoolWarning):
    """Cases of a sweep or grid failed the covariance guard and were flagged.

    Their numbers are NaN and the ``status`` column gives the guard's
    message (:func:`covtool.lincov.kalman.check_covariance`).
    """
