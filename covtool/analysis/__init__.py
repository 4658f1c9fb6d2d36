"""Analysis of covariance results: navigation metrics, error budgets, sensitivity, cost, consistency.

* :mod:`~covtool.analysis.metrics`: CEP, probable errors, NED position and attitude errors from P;
* :mod:`~covtool.analysis.budget`: the truth covariance split exactly by source (seed 002 Fig 4);
* :mod:`~covtool.analysis.sensitivity`: tuning sweeps and log-log fits (seed 002 Fig 8);
* :mod:`~covtool.analysis.cost`: FLOPs and timing of one on-board filter cycle (seed 002 Table 4);
* :mod:`~covtool.analysis.consistency`: NEES and the χ² bounds of an ensemble against a covariance.

Pure numeric core: arrays in, arrays out.
"""
