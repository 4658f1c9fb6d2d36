"""IMU grade files (``models/imu/*.toml``): spec-sheet values in datasheet units.

Seed 001, Table 2; seed 002 magnitudes.  :func:`load_imu_grade` validates a
file into an :class:`ImuGrade` (SI values) and :meth:`ImuGrade.to_model`
turns a grade into a covtool error-state model, so the linear analysis and
the simulator share one declaration.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
import os
from pathlib import Path

import tomli_w

from covtool.errors import ModelFileError
from covtool.io.config import (as_list, check_keys, is_library_name, LIMITS, load_toml, quantity,
                               resolve_input, string, table as as_table)
from covtool.io.names import check_name
from covtool.io.model_file import model_from_dict
from covtool.lincov.model.spec import Model

__all__ = [
    "ImuGrade", "load_imu_grade", "imu_grade_from_dict", "dump_imu_grade", "list_imu_grades",
    "imu_grade_dir", "GYRO_KEYS", "ACCEL_KEYS",
]


# --------------------------------------------------------------------------
# grades
# --------------------------------------------------------------------------

#: gyro keys of a grade file: (dimension, number of values)
GYRO_KEYS = {
    "bias": ("angular_rate", 3),
    "bias_instability": ("angular_rate", 3),
    "bias_instability_tau": ("time", 3),
    "scale_factor": ("dimensionless", 3),
    "misalignment": ("angle", 6),
    "g_sensitivity": ("g_sensitivity", 6),
    "anisoelastic": ("g2_sensitivity", 3),
    "angle_random_walk": ("angle_random_walk", 1),
    "quantization": ("angle", 1),
    "range": ("angular_rate", 1),
}
#: accelerometer keys of a grade file: (dimension, number of values)
ACCEL_KEYS = {
    "bias": ("acceleration", 3),
    "bias_instability": ("acceleration", 3),
    "bias_instability_tau": ("time", 3),
    "scale_factor": ("dimensionless", 3),
    "asymmetric_scale_factor": ("dimensionless", 3),
    "misalignment": ("angle", 6),
    "velocity_random_walk": ("velocity_random_walk", 1),
    "quantization": ("velocity", 1),
    "range": ("acceleration", 1),
}
# grade key -> model block kind (the Markov key handled with its tau)
_GYRO_BLOCKS = {"bias": "gyro_bias", "bias_instability": "gyro_markov_drift",
                "scale_factor": "gyro_scale_factor", "misalignment": "gyro_misalignment",
                "g_sensitivity": "gyro_g_sensitivity", "anisoelastic": "gyro_anisoelastic"}
_ACCEL_BLOCKS = {"bias": "accel_bias", "bias_instability": "accel_markov_bias",
                 "scale_factor": "accel_scale_factor", "asymmetric_scale_factor": "accel_asymmetric_scale_factor",
                 "misalignment": "accel_misalignment"}
_POSITIVE = {"bias_instability_tau", "quantization", "range"}
_TOP_KEYS = {"imu", "gyro", "accel"}
_IMU_KEYS = {"name", "description", "rate", "source"}


@dataclass(frozen=True)
class ImuGrade:
    """IMU error specification (one grade), SI values.

    Attributes
    ----------
    name, description : str
    path : str
        File it was read from (``"<dict>"`` otherwise).
    rate : float or None
        Nominal output rate. [Hz]
    gyro, accel : dict
        Parameter name → tuple of SI values (3 per axis, 6 for
        misalignment and g-sensitivity, 1 for random walk, quantisation and
        range); see :data:`GYRO_KEYS`, :data:`ACCEL_KEYS`.  Absent keys are
        effects switched off.
    sources : dict
        ``"gyro.bias"`` → where the value comes from.
    decl : dict
        The declaration as written (datasheet units).
    """

    name: str
    description: str
    path: str
    rate: float | None
    gyro: dict
    accel: dict
    sources: dict = field(default_factory=dict)
    decl: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def quantization(self) -> tuple:
        """``(angle LSB [rad], velocity LSB [m/s])``, None where not given."""
        g = self.gyro.get("quantization")
        a = self.accel.get("quantization")
        return (None if g is None else g[0], None if a is None else a[0])

    @property
    def range(self) -> tuple:
        """``(rate range [rad/s], specific-force range [m/s²])``, None where not given."""
        g = self.gyro.get("range")
        a = self.accel.get("range")
        return (None if g is None else g[0], None if a is None else a[0])

    def to_model(self, name: str | None = None) -> Model:
        """The grade as a covtool error-state model.

        Parameters
        ----------
        name : str, optional
            Model name (default ``imu_<grade name>``).

        Returns
        -------
        Model
            A navigation block with zero initial σ (alignment is the
            caller's), the grade's ARW and VRW, and one block per given
            sensor parameter: turn-on biases, scale factors, misalignments,
            g-sensitivity and anisoelasticity as random constants, in-run
            bias instability as first-order Markov processes (σ = the
            instability, τ = ``bias_instability_tau``).
        """
        d = self.decl
        nav = {"kind": "navigation", "source": f"IMU grade {self.name!r} ({self.path})"}
        if "angle_random_walk" in d.get("gyro", {}):
            nav["angle_random_walk"] = d["gyro"]["angle_random_walk"]
        if "velocity_random_walk" in d.get("accel", {}):
            nav["velocity_random_walk"] = d["accel"]["velocity_random_walk"]
        blocks = [nav]
        for sensor, table in (("gyro", _GYRO_BLOCKS), ("accel", _ACCEL_BLOCKS)):
            sd = d.get(sensor, {})
            src = sd.get("source", {})
            for key, kind in table.items():
                if key not in sd:
                    continue
                b = {"kind": kind, "sigma": copy.deepcopy(sd[key]),
                     "source": src.get(key, f"IMU grade {self.name!r}: {sensor}.{key}")}
                if key == "bias_instability":
                    b["process"] = "markov"
                    b["tau"] = copy.deepcopy(sd["bias_instability_tau"])
                blocks.append(b)
        decl = {"model": {"name": name or f"imu_{self.name}",
                          "description": f"sensor errors of IMU grade {self.name!r}: {self.description}"},
                "block": blocks}
        return model_from_dict(decl, path=self.path)


def imu_grade_dir(directory=None) -> Path:
    """The grade library, ``<models>/imu``.

    ``<models>`` is :func:`covtool.io.library.default_model_dir`.
    """
    if directory is not None:
        return Path(directory)
    from covtool.io.library import default_model_dir

    return default_model_dir() / "imu"


def list_imu_grades(directory=None) -> list[str]:
    """Names of the grade files in the library."""
    return sorted(p.stem for p in imu_grade_dir(directory).glob("*.toml"))


def imu_grade_from_dict(decl: dict, *, path: str = "<dict>") -> ImuGrade:
    """Validate a grade declaration.

    Parameters
    ----------
    decl : dict
        ``[imu]`` (``name``, ``description``, ``rate``, ``source``),
        ``[gyro]`` and ``[accel]`` tables of :data:`GYRO_KEYS` /
        :data:`ACCEL_KEYS` in datasheet units (one value = all axes), each
        with an optional ``[gyro.source]``/``[accel.source]`` table naming
        the origin of every value.
    path : str
        File name used in messages.

    Returns
    -------
    ImuGrade

    Raises
    ------
    ModelFileError
        Naming the file, the field and the problem: unknown table or key,
        missing name, wrong unit or count, negative value, non-positive
        τ/quantisation/range/rate, instability without τ (or τ without
        instability), a source for an undeclared key.
    """
    file = str(path)
    check_keys(decl, _TOP_KEYS, file, ModelFileError)
    meta = decl.get("imu")
    if not isinstance(meta, dict):
        raise ModelFileError(file, "missing the [imu] table")
    check_keys(meta, _IMU_KEYS, f"{file}: [imu]", ModelFileError)
    name = meta.get("name")
    if not isinstance(name, str) or not name:
        raise ModelFileError(f"{file}: [imu] name", "missing or not a non-empty string")
    check_name(name, f"{file}: [imu] name", ModelFileError, what="IMU grade name")
    for key in ("description", "source"):
        if key in meta:
            string(meta[key], f"{file}: [imu] {key}", ModelFileError)
    rate = None
    if "rate" in meta:
        lim = LIMITS["imu_rate"]
        rate = quantity(meta["rate"], "frequency", f"{file}: [imu] rate", ModelFileError, positive=True,
                        hi=lim.hi, why=lim.reason)
    sources = {}
    parsed = {}
    for sensor, keys in (("gyro", GYRO_KEYS), ("accel", ACCEL_KEYS)):
        where = f"{file}: [{sensor}]"
        table = as_table(decl.get(sensor, {}), where, ModelFileError)
        check_keys(table, set(keys) | {"source"}, where, ModelFileError)
        out = {}
        for key, (dim, count) in keys.items():
            if key not in table:
                continue
            w = f"{file}: {sensor}.{key}"
            if count == 1:
                if isinstance(table[key], (list, tuple)):
                    raise ModelFileError(w, "expected one value, got a list")
                vals = [table[key]]
            else:
                vals = as_list(table[key], count, w, ModelFileError)
            si = tuple(quantity(v, dim, w, ModelFileError, nonnegative=True, positive=key in _POSITIVE)
                       for v in vals)
            out[key] = si
        if ("bias_instability" in out) != ("bias_instability_tau" in out):
            raise ModelFileError(f"{file}: [{sensor}]", "give 'bias_instability' together with "
                                 "'bias_instability_tau' (its correlation time)")
        src = table.get("source", {})
        check_keys(src, set(out), f"{file}: [{sensor}.source]", ModelFileError)
        for key, text in src.items():
            if not isinstance(text, str):
                raise ModelFileError(f"{file}: {sensor}.source.{key}", f"{text!r} is not a string")
            sources[f"{sensor}.{key}"] = text
        parsed[sensor] = out
    return ImuGrade(name, str(meta.get("description", "")), file, rate, parsed["gyro"], parsed["accel"],
                    sources, copy.deepcopy(decl))


def load_imu_grade(name_or_path, directory=None, *, base_dir=None) -> ImuGrade:
    """Load a grade by library name (``"kimu"``) or by path.

    A bare name (no suffix, no separator) is looked up in the grade library
    (:func:`imu_grade_dir`); anything else is a path, relative to
    ``base_dir`` (the directory of the file that names it; the current
    directory when none does).

    Raises
    ------
    ModelFileError
        No such grade (naming where it looked), or an invalid file.
    """
    if isinstance(name_or_path, Path):
        name_or_path = str(name_or_path)
    if isinstance(name_or_path, str) and is_library_name(name_or_path):
        path = imu_grade_dir(directory) / f"{name_or_path}.toml"
        if not path.is_file():
            known = ", ".join(list_imu_grades(directory)) or "none"
            raise ModelFileError(str(name_or_path), f"no such IMU grade (looked in {path.parent}; "
                                 f"known: {known})")
        path = Path(os.path.abspath(path))
    else:
        path = resolve_input(name_or_path, base_dir, str(name_or_path), ModelFileError, what="IMU grade file")
    return imu_grade_from_dict(load_toml(path, ModelFileError), path=str(path))


def dump_imu_grade(grade: ImuGrade) -> str:
    """The grade's declaration as TOML (datasheet units kept)."""
    return tomli_w.dumps(grade.decl)
