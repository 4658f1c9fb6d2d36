"""Navigation: the nonlinear side of covtool (arrays in, arrays out, no files).

* :mod:`~covtool.nav.earth`: WGS-84 radii, normal gravity, Earth and transport rates;
* :mod:`~covtool.nav.attitude`: quaternion algebra (scalar first, body→NED);
* :mod:`~covtool.nav.trajectory`: reference trajectories and their inverse mechanization;
* :mod:`~covtool.nav.coning` and :mod:`~covtool.nav.strapdown`: the strapdown mechanization;
* :mod:`~covtool.nav.imu`: the IMU simulator and vibration.
"""
