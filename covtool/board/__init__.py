"""Accelerometer-board signal-processing errors (seed 000).

* :mod:`covtool.board.adreset` -- integrate-and-reset board, sample-by-sample
  simulator, AD-reset error expressions (eq (1)-(10)) and the link to the
  truth model's AD-reset velocity-error states;
* :mod:`covtool.board.output_filter` -- the second-order IIR output filter
  and the filtered reset-pulse error (eq (11)-(20));
* :mod:`covtool.board.alignment` -- the leveling loop and its Tustin
  discretisation (eq (21)-(27)), and the accelerometer pre-filter.

Pure numerics: arrays in, arrays out, SI units, no file I/O.
"""
