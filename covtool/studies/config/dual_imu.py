"""Sections of the dual-IMU study (seed 001, method II).

``[imu]`` (the two units), the high-dynamics flight ``[trajectory]``,
``[alignment]``, ``[comparison]``, ``[monitor]`` (the g-sensitivity fault
monitor), ``[gaps]`` and ``[simulation]`` with its fault and gaps.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import ConfigDict, Field

from covtool.studies.config.field_types import F, Integer, Names, Number, OneOf, Quantity, Raw, Section, Table, Text


class ImuUnit(Section):
    name: ClassVar[str] = "imu.main / imu.kimu"
    doc: ClassVar[str] = "One IMU of the pair."
    grade: Text(nonempty=True) | None = F(None, "IMU grade: a library name (`covtool models`) or a path "
                                                "relative to the study file (default: main_imu, kimu).")
    mounting: Raw = F(["0 deg", "0 deg", "0 deg"], "[roll, pitch, yaw] of the sensor frame in the body.")
    ratio: Integer(limit="kimu_ratio") | None = F(None, "imu.kimu only: KIMU samples per main sample "
                                                        "(default 4; must match the grades' rates).")


class ImuSection(Section):
    name: ClassVar[str] = "imu"
    doc: ClassVar[str] = "The two IMUs compared (seed 001)."
    nested: ClassVar[dict] = {"main": ImuUnit, "kimu": ImuUnit}
    main: Table("[imu.main] table") = F({}, "The main IMU.")
    kimu: Table("[imu.kimu] table") = F({}, "The KIMU.")


class FlightSegment(Section):
    name: ClassVar[str] = "[trajectory.segment]] (flight)"
    doc: ClassVar[str] = "One piece of a flight: `stand` (duration) or `fly`."
    kind: OneOf("stand", "fly") = F(..., "The segment kind.", example="stand")
    duration: Quantity("time") | None = F(None, "Duration.")
    to_speed: Quantity("velocity") | None = F(None, "fly: speed at the end.")
    to_pitch: Quantity("angle") | None = F(None, "fly: pitch at the end.")
    to_roll: Quantity("angle") | None = F(None, "fly: roll at the end.")
    turn: Quantity("angle") | None = F(None, "fly: heading change.")
    transition: Quantity("time") | None = F(None, "fly: ramp time of the changes.")


class FlightInitial(Section):
    name: ClassVar[str] = "trajectory.initial (flight)"
    doc: ClassVar[str] = "Start of a flight."
    lat: Quantity("angle") = F(..., "Latitude.", example="36.37 deg")
    lon: Quantity("angle") = F(..., "Longitude.", example="127.36 deg")
    h: Quantity("length") = F(..., "Height.", example="60 m")
    heading: Quantity("angle") = F("0 deg", "Heading.")
    pitch: Quantity("angle") = F("0 deg", "Pitch.")


class FlightTrajectory(Section):
    name: ClassVar[str] = "trajectory (dual_imu flight)"
    doc: ClassVar[str] = ("The flight of a dual-IMU study: `builtin = \"high_dynamics_flight\"` (seed 001's "
                          "profile), or `segment` and `initial`.")
    nested: ClassVar[dict] = {"initial": FlightInitial, "segment": [FlightSegment]}
    builtin: OneOf("high_dynamics_flight") | None = F(None, "A built-in flight.", example="high_dynamics_flight")
    vibration: Raw = F(True, "Add the flight's vibration to the sensed motion (true/false, or a vibration "
                             "table for a segment flight).")
    segment: Raw = F(None, "The segments: [[trajectory.segment]] tables.")
    initial: Raw = F(None, "The start: [trajectory.initial].")
    name_: Text() | None = Field(None, alias="name", description="Label of the flight.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class DualAlignment(Section):
    name: ClassVar[str] = "alignment (dual_imu)"
    doc: ClassVar[str] = "Initial alignment of the pair."
    duration: Quantity("time", positive=True) = F("10 s", "Alignment duration.")
    heading_sigma: Quantity("angle", nonnegative=True) = F("0.1 deg", "Heading 1σ after alignment.")
    lat: Quantity("angle") | None = F(None, "Start latitude (default: the trajectory's).")
    lon: Quantity("angle") | None = F(None, "Start longitude.")
    h: Quantity("length") | None = F(None, "Start height.")
    heading: Quantity("angle") | None = F(None, "Start heading.")


class Comparison(Section):
    name: ClassVar[str] = "comparison"
    doc: ClassVar[str] = "The navigation difference between the two IMUs."
    interval: Quantity("time", positive=True) = F("1 s", "Comparison interval (whole main samples).")
    model_step: Quantity("time", positive=True) = F("0.04 s", "Model step (an even number of main samples "
                                                              "dividing the interval).")
    components: Names(known=["position", "velocity", "attitude"], what="component") = F(
        ["velocity", "attitude"], "Compared components.")
    noise: Table("table position/velocity/attitude = 1σ") = F({}, "Comparison noise 1σ per component (default "
                                                                  "1 mm, 0.1 mm/s, 2 urad).")


class Monitor(Section):
    name: ClassVar[str] = "monitor"
    doc: ClassVar[str] = "The g-sensitivity fault monitor."
    window: Quantity("time", positive=True) = F("10 s", "Test window (whole comparison intervals).")
    false_alarm: Number(lo=0.0, hi=1.0, lo_open=True, hi_open=True, why="a probability") = F(
        0.01, "False-alarm probability per window.")
    candidates: Raw = F("all", "'all' or a list of gyro/accel axis pairs such as ['z/x'].")


class Gaps(Section):
    name: ClassVar[str] = "gaps"
    doc: ClassVar[str] = "Bridging data gaps."
    policy: OneOf("interpolate", "hold", "skip") = F("interpolate", "How a gap is bridged.")
    window: Integer(limit="gap_window") = F(10, "Samples averaged by a bridge.")
    trials: Integer(limit="gap_trials") = F(8, "Trial bridges per side for the error prediction.")


class Fault(Section):
    name: ClassVar[str] = "simulation.fault"
    doc: ClassVar[str] = "The injected g-sensitivity fault."
    gyro: Raw = F(..., "Gyro axis ('x', 'y', 'z').", example="z")
    accel: Raw = F(..., "Accelerometer axis.", example="x")
    coefficient: Raw = F(..., "g-sensitivity ('10 deg/h/g').", example="10 deg/h/g")


class GapEntry(Section):
    name: ClassVar[str] = "[simulation.gap]]"
    doc: ClassVar[str] = "A data gap in one IMU."
    imu: OneOf("main", "kimu") = F(..., "The IMU.", example="main")
    start: Quantity("time", nonnegative=True) = F(..., "Start.", example="60 s")
    duration: Quantity("time", positive=True) = F(..., "Duration.", example="1 s")


class Simulation(Section):
    name: ClassVar[str] = "simulation"
    doc: ClassVar[str] = "Simulated flights."
    nested: ClassVar[dict] = {"fault": Fault, "gap": [GapEntry]}
    runs: Integer(limit="dual_runs") = F(100, "Fault-free flights.")
    fault_runs: Integer(limit="dual_runs") = F(20, "Flights with the injected fault (needs "
                                                   "[simulation.fault]).")
    batch: Integer(limit="dual_batch") = F(50, "Flights per batch.")
    seed: Integer(limit="seed") = F(1, "Seed of the random streams.")
    fault: Raw = F(None, "[simulation.fault].")
    gap: Raw = F([], "[[simulation.gap]] tables.")
