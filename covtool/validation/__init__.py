"""Validation of the linear analysis against the nonlinear strapdown INS.

* :mod:`~covtool.validation.sensor_errors`: sensor errors drawn from the truth model, injected into IMU increments;
* :mod:`~covtool.validation.monte_carlo`: the Monte Carlo ensemble with real feedback filters.
"""
