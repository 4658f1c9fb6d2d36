"""Field types of the study declarations: each validator is a typed helper.

``Quantity``, ``QuantityList``, ``Integer``, ``Number``, ``Bool``, ``Text``,
``OneOf``, ``Names``, ``Table``, ``Memory`` and ``Raw`` are annotated types
whose validator is one of :mod:`covtool.io.config`'s typed field helpers
(so the messages are the runners'), carrying a :class:`Kind` (the type
text and unit dimension of the reference); ``F`` declares a field's
default (datasheet units) and meaning; :class:`Section` is the frozen base
of every table (unknown keys refused, defaults validated).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field
from pydantic_core import PydanticCustomError

from covtool.errors import InputError
from covtool.io import config as fields
from covtool.io.config import LIMITS


# ---------------------------------------------------------------------------
# field types: each validator is one of covtool.io.config's typed helpers
# ---------------------------------------------------------------------------

class _Problem(InputError):
    """A field helper's refusal inside a pydantic validator (no location yet)."""


def _wrap(check):
    def validate(value):
        try:
            return check(value)
        except InputError as exc:
            # exc.where is the helper's own suffix (``[i]`` of a list item), "" otherwise
            raise PydanticCustomError("covtool", "{problem}", {"problem": exc.problem,
                                                               "suffix": exc.where or ""}) from None
    return validate


class Kind:
    """What a field holds, for the reference: ``"time"``, ``"integer"``, ``"list of names"``, ..."""

    def __init__(self, text: str, dimension: str | None = None, range_text: str = ""):
        self.text, self.dimension, self.range_text = text, dimension, range_text


def Quantity(dimension: str, *, positive=False, nonnegative=False, hi=None, why=""):
    """A quantity in SI from a datasheet string (``"5 min"``); see :func:`covtool.io.config.quantity`."""
    rng = "> 0" if positive else ">= 0" if nonnegative else ""
    if hi is not None:
        rng = (rng + " and " if rng else "") + f"<= {hi:g} (SI)"
    return Annotated[float, BeforeValidator(_wrap(lambda v: fields.quantity(
        v, dimension, "", _Problem, positive=positive, nonnegative=nonnegative, hi=hi, why=why))),
        Kind(f"quantity ({dimension})", dimension, rng)]


def _once(values: tuple, raw) -> tuple:
    if len(set(values)) != len(values):
        raise _Problem("", f"repeated values in {raw!r}")
    return values


def QuantityList(dimension: str, *, limit=None, unique=False, **kw):
    """A non-empty list of quantities in SI (``unique``: each value once)."""
    def check(v):
        out = tuple(fields.quantity_list(v, dimension, "", _Problem, limit=limit, **kw))
        return _once(out, v) if unique else out
    return Annotated[tuple[float, ...], BeforeValidator(_wrap(check)),
                     Kind(f"list of quantities ({dimension})", dimension)]


def NumberList(*, limit=None, bound=None, unique=False):
    """A non-empty list of bare numbers.

    ``limit``: the :data:`LIMITS` entry bounding the count; ``bound``: the
    entry bounding each value (read when a file is parsed); ``unique``:
    each value once.
    """
    def check(v):
        if not isinstance(v, list) or not v:
            raise _Problem("", "expected a non-empty list")
        if limit is not None and len(v) > LIMITS[limit].hi:
            raise _Problem("", f"{len(v)} values; at most {LIMITS[limit].hi:g} ({LIMITS[limit].reason})")
        b = LIMITS[bound] if bound is not None else None
        out = []
        for i, x in enumerate(v):
            try:
                out.append(fields.number(x, "", _Problem, lo=b.lo if b else None, hi=b.hi if b else None,
                                         why=b.reason if b else ""))
            except InputError as exc:
                raise _Problem(f"[{i}]", exc.problem) from None
        return _once(tuple(out), v) if unique else tuple(out)
    b = LIMITS.get(bound)
    rng = f">= {b.lo:g} and <= {b.hi:g}" if b is not None else ""
    return Annotated[tuple[float, ...], BeforeValidator(_wrap(check)), Kind("list of numbers", None, rng)]


def Integer(*, limit=None, lo=None, hi=None):
    """An integer in a range (a :data:`~covtool.io.config.LIMITS` entry or ``lo``/``hi``)."""
    b = LIMITS.get(limit)
    lo_, hi_ = (b.lo if b else lo), (b.hi if b else hi)
    rng = f"{lo_:g}..{hi_:g}" if lo_ is not None and hi_ is not None else ""
    return Annotated[int, BeforeValidator(_wrap(lambda v: fields.integer(v, "", _Problem, lo=lo, hi=hi,
                                                                           limit=limit))),
                     Kind("integer", None, rng + (f" ({b.reason})" if b else ""))]


def Number(*, lo=None, hi=None, lo_open=False, hi_open=False, why=""):
    """A finite bare number in a range."""
    parts = [p for p in ((("> " if lo_open else ">= ") + f"{lo:g}") if lo is not None else "",
                         (("< " if hi_open else "<= ") + f"{hi:g}") if hi is not None else "") if p]
    return Annotated[float, BeforeValidator(_wrap(lambda v: fields.number(
        v, "", _Problem, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, why=why))),
        Kind("number", None, " and ".join(parts) + (f" ({why})" if why else ""))]


Bool = Annotated[bool, BeforeValidator(_wrap(lambda v: fields.boolean(v, "", _Problem))), Kind("true or false")]


def Text(*, nonempty=False):
    return Annotated[str, BeforeValidator(_wrap(lambda v: fields.string(v, "", _Problem, nonempty=nonempty))),
                     Kind("string")]


def OneOf(*options):
    shown = ", ".join(repr(o) if isinstance(o, str) else str(o).lower() for o in options)
    return Annotated[Any, BeforeValidator(_wrap(lambda v: fields.choice(v, options, "", _Problem))),
                     Kind(f"one of {shown}")]


def Names(*, known=None, nonempty=True, what="name"):
    return Annotated[tuple[str, ...], BeforeValidator(_wrap(lambda v: tuple(fields.names(
        v, "", _Problem, known=known, nonempty=nonempty, what=what)))), Kind(f"list of {what}s")]


def Table(what: str):
    """A TOML table validated by the runner (its keys are declared by a nested section)."""
    return Annotated[dict, BeforeValidator(_wrap(lambda v: fields.table(v, "", _Problem))), Kind(what)]


def _memory(v):
    from covtool.studies.resources import parse_bytes

    return parse_bytes(v, "", _Problem)


Memory = Annotated[float, BeforeValidator(_wrap(_memory)), Kind("memory size ('6 GB', '512 MiB')", "memory")]

#: any TOML value, validated by the runner (a list of tables, a value of the truth state's dimension)
Raw = Annotated[Any, Kind("see the description")]


def F(default=..., doc: str = "", example=None):
    """A declared field: its default (datasheet units) and meaning; ``example`` for ``covtool new``."""
    extra = {"example": example} if example is not None else None
    return Field(default, description=doc, json_schema_extra=extra)


class Section(BaseModel):
    """One table of a study file: frozen, unknown keys refused, defaults validated."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    #: ``[name]`` of the table in a study file
    name: ClassVar[str] = ""
    #: what the table is for (first line of its reference entry)
    doc: ClassVar[str] = ""
    #: nested tables: key -> Section class (a list of tables for ``[[key]]``)
    nested: ClassVar[dict] = {}
