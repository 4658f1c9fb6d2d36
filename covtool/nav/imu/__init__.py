"""The IMU: exact increments of a trajectory (:mod:`~covtool.nav.imu.simulator`), vibration (:mod:`~covtool.nav.imu.vibration`).

Sensor errors drawn from an error-state model are injected by
:mod:`covtool.validation.sensor_errors`; IMU grade files are read by
:mod:`covtool.io.imu_grade`.
"""
