"""The error-state model: states with names, blocks of a kind, P0 and driving noises.

:mod:`~covtool.lincov.model.spec` holds the :class:`Model` object,
:mod:`~covtool.lincov.model.blocks` the block kinds and their sensitivities
(seed 002, eq (3)–(5)).  Model files are read by :mod:`covtool.io.model_file`
and found by name in the library by :mod:`covtool.io.library`.
"""
