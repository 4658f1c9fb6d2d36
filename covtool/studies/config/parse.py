"""Parse a study file into its configuration, and dump one back.

:func:`load_config` and :func:`parse_section` turn pydantic's validation
errors into one :class:`~covtool.errors.StudyFileError` naming the file,
the table and the key; :func:`dump_config` writes quantities as SI strings
that parse back exactly (the dump's own formatter; nothing else turns SI values
back into strings).
"""

from __future__ import annotations

from pydantic import BaseModel, TypeAdapter, ValidationError

from covtool.errors import StudyFileError, TrajectoryError
from covtool.io import config as fields
from covtool.io.names import check_study_name
from covtool.units import DIMENSIONS
from covtool.studies.config.field_types import Kind, Section
from covtool.studies.config.kinds import KINDS, StudyConfig
from covtool.studies.config.sections import Trajectory

_TRAJECTORY = TypeAdapter(Trajectory)


def _keys(cls) -> list[str]:
    return [f.alias or n for n, f in cls.model_fields.items()]


def _where(where: str, loc) -> str:
    parts = [x for x in loc if not (isinstance(x, str) and x.startswith("function-"))]
    if not parts or isinstance(parts[0], int):
        return where
    if len(parts) > 1 and isinstance(parts[1], int):      # an entry of a list of tables: [[measurement]] #2
        head, parts = f"[[{parts[0]}]] #{parts[1] + 1}", parts[2:]
    else:
        head, parts = f"[{parts[0]}]", parts[1:]
    rest = ".".join(str(x) for x in parts if not isinstance(x, int))
    return f"{where}: {head}" + (f" {rest}" if rest else "") + "".join(f" #{x + 1}" for x in parts
                                                                        if isinstance(x, int))


def parse_section(cls: type[Section], value, where: str, section: str, error=StudyFileError):
    """One table parsed into ``cls``; a refusal is one ``error`` naming the file, table and key.

    Unknown keys are refused first, with the allowed keys (as
    :func:`covtool.io.config.check_keys` does).
    """
    w = f"{where}: [{section}]"
    fields.table(value, w, error)
    fields.check_keys(value, _keys(cls), w, error)
    try:
        return cls.model_validate(value)
    except ValidationError as exc:
        _raise(exc, where, (section,), error)


def parse_trajectory(value, where: str, error=StudyFileError):
    """A ``[trajectory]`` table parsed into its form (:data:`~covtool.studies.config.Trajectory`).

    Unknown keys are refused first, with the allowed keys of the form.
    """
    try:
        return _TRAJECTORY.validate_python(value)
    except ValidationError as exc:
        _raise(exc, where, ("trajectory",), error)


class StudyTrajectoryError(StudyFileError, TrajectoryError):
    """A ``[trajectory]`` table of a study file is invalid (both kinds of error)."""


def _raise(exc: ValidationError, where: str, prefix: tuple, error):
    e = exc.errors(include_url=False)[0]
    loc = prefix + tuple(e["loc"])
    if loc and loc[0] == "trajectory" and error is StudyFileError:
        error = StudyTrajectoryError
    if e["type"] == "missing":
        raise error(_where(where, loc[:-1]), f"missing required key {loc[-1]!r}") from None
    if e["type"] == "extra_forbidden":
        raise error(_where(where, loc[:-1]), f"unknown key {loc[-1]!r}") from None
    if e["type"] == "covtool":
        raise error(_where(where, loc) + e["ctx"].get("suffix", ""), e["ctx"]["problem"]) from None
    raise error(_where(where, loc), e["msg"]) from None


def load_config(decl: dict, where: str = "<study>") -> StudyConfig:
    """A study declaration parsed into its kind's typed, frozen configuration.

    Parameters
    ----------
    decl : dict
        The study file's TOML tables.
    where : str
        The study file, for messages.

    Returns
    -------
    StudyConfig
        E.g. :class:`ZuptFilterOrderConfig`; sections are attributes.

    Raises
    ------
    StudyFileError
        Naming the file, the table, the key and the problem.
    """
    st = decl.get("study")
    if not isinstance(st, dict) or "kind" not in st:
        raise StudyFileError(where, "missing [study] table with a 'kind' key "
                             f"(one of: {', '.join(sorted(KINDS))})")
    if st["kind"] not in KINDS:
        raise StudyFileError(f"{where}: [study]", f"unknown kind {st['kind']!r} (one of: {', '.join(sorted(KINDS))})")
    # the outputs' name first: a name that is not a safe file name is refused before anything else
    check_study_name(st, where, StudyFileError, default=st["kind"])
    cls = KINDS[st["kind"]]
    fields.check_keys(decl, _keys(cls), where, StudyFileError)
    for key, f in cls.model_fields.items():
        ann = f.annotation
        if isinstance(ann, type) and issubclass(ann, Section) and key in decl:
            fields.table(decl[key], f"{where}: [{key}]", StudyFileError)
            fields.check_keys(decl[key], _keys(ann), f"{where}: [{key}]", StudyFileError)
    try:
        return cls.model_validate(decl)
    except ValidationError as exc:
        _raise(exc, where, (), StudyFileError)


def _si_text(value: float, dimension: str):
    """An SI value as a quantity string that parses back exactly (a bare number when dimensionless)."""
    unit = "Hz" if dimension == "frequency" else DIMENSIONS[dimension][0]   # '1/s' is not a unit string
    if value == 0 or not unit:
        return float(value)
    return f"{float(value)!r} {unit}"


def _dump(model: BaseModel) -> dict:
    out = {}
    for name, f in type(model).model_fields.items():
        v = getattr(model, name)
        if v is None:
            continue
        key = f.alias or name
        kind = next((m for m in f.metadata if isinstance(m, Kind)), None)
        if kind is None:
            for arg in getattr(f.annotation, "__args__", ()):
                kind = next((m for m in getattr(arg, "__metadata__", ()) if isinstance(m, Kind)), kind)
        if isinstance(v, BaseModel):
            out[key] = _dump(v)
        elif isinstance(v, tuple) and v and all(isinstance(x, BaseModel) for x in v):
            out[key] = [_dump(x) for x in v]
        elif isinstance(v, dict) and v and all(isinstance(x, BaseModel) for x in v.values()):
            out[key] = {k: _dump(x) for k, x in v.items()}
        elif kind is not None and kind.dimension and kind.dimension != "memory":
            out[key] = [_si_text(x, kind.dimension) for x in v] if isinstance(v, tuple) else \
                _si_text(v, kind.dimension)
        elif kind is not None and kind.dimension == "memory":
            out[key] = f"{v!r} B"
        elif isinstance(v, tuple):
            out[key] = list(v)
        else:
            out[key] = v
    return out


def dump_config(config: StudyConfig) -> dict:
    """The TOML tables of a configuration: every field, defaults filled in, quantities as exact SI strings."""
    out = _dump(config)
    for section, keys in type(config).dump_omit.items():
        for key in keys:
            out.get(section, {}).pop(key, None)
    return out
