"""Reference trajectories: the true motion the error model is linearised about.

* :mod:`~covtool.nav.trajectory.core`: the :class:`Trajectory` object and the inverse mechanization;
* :mod:`~covtool.nav.trajectory.segments`: segment kinematics (speed, heading, grade changes);
* :mod:`~covtool.nav.trajectory.profiles`: the built-in land-vehicle route and a static vehicle;
* :mod:`~covtool.nav.trajectory.flight`: high-dynamics flight profiles with vibration.

Declarations with datasheet units and CSV files are read by :mod:`covtool.io.trajectory`,
:mod:`covtool.io.flight` and :mod:`covtool.io.trajectory_csv`.
"""
