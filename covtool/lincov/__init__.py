"""Linear covariance analysis: the truth model propagated under the filters' gains.

* :mod:`~covtool.lincov.model`: the declared error-state model (states, blocks, P0, noises);
* :mod:`~covtool.lincov.dynamics`: F and the driving noise along a trajectory (seed 002, eq (1)–(5));
* :mod:`~covtool.lincov.discretize`: every discretiser (Van Loan, seed 002's Taylor series eq (6b)–(6d));
* :mod:`~covtool.lincov.kalman`: the kernel (gain eq (7), Joseph/eq (8), truth update eq (16), the covariance guard);
* :mod:`~covtool.lincov.reference`: step-by-step propagation (eq (15)–(16)), the reference;
* :mod:`~covtool.lincov.batch`: the batched engine (many cases, one truth), tested against the reference;
* :mod:`~covtool.lincov.noise`: driving noise composed per source;
* :mod:`~covtool.lincov.reduced` and :mod:`~covtool.lincov.equivalent_noise`: reduced filters as projections
  of the truth, equivalent white noise eq (11)–(13);
* :mod:`~covtool.lincov.impact`: what each dropped block costs a reduced filter.

Pure numeric core: models and arrays in, arrays out; no file is read here.
"""
