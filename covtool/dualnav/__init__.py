"""Dual navigation and IMU verification in flight (seed 001, method II).

Pure numeric core: arrays in, arrays out.  A development IMU (the KIMU) flies
beside the main IMU; both navigate at once on the main interval (the KIMU at
``r`` samples per interval, seed 001 §2.3, Figs 7–10), each after its own
alignment, and the two solutions are compared after the mounting
misalignment between the IMUs is compensated.  The package

* aligns each IMU on its own (:mod:`~covtool.dualnav.alignment`): levelling from its
  accelerometers, heading from the input heading through the declared
  mounting (seed 001 §2.3.2);
* forms the navigation difference main − KIMU (:mod:`~covtool.dualnav.difference`);
* predicts its covariance by linear covariance analysis: the two INS error
  states, each from its grade's :class:`~covtool.lincov.model.spec.Model`,
  propagated independently along the flight with covtool's error dynamics,
  correlated only through the shared input heading
  (:func:`~covtool.dualnav.difference.difference_model`);
* whitens the difference with the Kalman filter of that model and flags the
  windows whose normalised innovations leave the predicted χ² envelope
  (:mod:`~covtool.dualnav.monitor`);
* detects a g-sensitive gyro scale-factor error of the KIMU and estimates its
  coefficient by generalised least squares on the fault signatures
  (:func:`~covtool.dualnav.monitor.gsens_estimates`, Willsky & Jones 1976);
* bridges telemetry gaps by a declared policy and predicts the extra error
  each bridge costs (:mod:`~covtool.dualnav.gaps`);
* runs the whole comparison of two IMU records (:func:`covtool.dualnav.run.run_dual`).

Conventions: SI; error = computed − true; attitude differences are NED
small angles ``φ`` with ``Ĉ_b^n = (I − [φ×]) C_b^n``; the difference vector
``z`` is ``[δN, δE, δD, δv_N, δv_E, δv_D, δφ_N, δφ_E, δφ_D]`` of main minus
KIMU (:data:`covtool.dualnav.difference.DIFF_NAMES`).

References
----------
A. S. Willsky and H. L. Jones, "A generalized likelihood ratio approach to
the detection and estimation of jumps in linear systems", IEEE Trans.
Automatic Control 21(1), 1976.
"""
