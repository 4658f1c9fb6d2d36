"""Names checked at load time: identifiers and output file names.

Every model, state, block, filter, IMU-grade and study name becomes a table
label, a workbook cell, a chart series and, for a study, the file name
``<name>.xlsx``.  Such names must match :data:`NAME_PATTERN`: a letter, then
letters, digits, ``_``, ``.`` or ``-``, ending in a letter, digit or ``_``,
at most :data:`MAX_NAME` characters.  Every name shipped in ``models/`` and
``studies/`` matches it (``sdins58``, ``acc_bias_x``, ``B1_matched``,
``high-tactical``, ``navigation-3x``, …).  A name that matches can never be a
spreadsheet formula (it starts with a letter), a path (no ``/``, ``\\``, no
leading ``.``) or a control character.

Free text (descriptions, sources) is not restricted; the writers make it safe
instead (:mod:`covtool.io.cells`).
"""

from __future__ import annotations

import re
from pathlib import PurePath

from covtool.errors import InputError

#: longest accepted name [characters]
MAX_NAME = 64

#: strict identifier pattern of every model, state, block, filter and study name
NAME_PATTERN = re.compile(rf"^[A-Za-z](?:[A-Za-z0-9_.-]{{0,{MAX_NAME - 2}}}[A-Za-z0-9_])?\Z")

_NAME_RULE = (f"a name is a letter, then up to {MAX_NAME - 1} letters, digits, '_', '.' or '-', "
              "ending in a letter, digit or '_'")

# device names that Windows refuses as a file name, with any extension
_RESERVED = {"con", "prn", "aux", "nul", *(f"com{i}" for i in range(10)), *(f"lpt{i}" for i in range(10))}

#: characters never accepted in an output file name (path separators, NUL, Windows-reserved)
_BAD_FILE_CHARS = set('/\\:*?"<>|')

#: longest output file name stem [characters]; leaves room for a suffix within 255 bytes
MAX_FILE_STEM = 200


def check_name(value, where: str, error=InputError, *, what: str = "name") -> str:
    """Return ``value`` if it is a valid name, else raise ``error``.

    Parameters
    ----------
    value : object
        The name as read from the file.
    where : str
        ``"<file>: <field>"`` for the message.
    error : type
        An :class:`~covtool.errors.InputError` subclass.
    what : str
        What the name names (``"state name"``), for the message.

    Returns
    -------
    str

    Raises
    ------
    InputError
        (``error``) ``value`` is not a string or does not match
        :data:`NAME_PATTERN`.
    """
    if not isinstance(value, str):
        raise error(where, f"{value!r} is not a string; a {what} must be text")
    if not NAME_PATTERN.match(value):
        raise error(where, f"{value!r} is not a valid {what}: {_NAME_RULE}")
    return value


def check_file_stem(value, where: str, error=InputError, *, strict: bool = True) -> str:
    """Return ``value`` if it is one plain, safe file-name component.

    Parameters
    ----------
    value : object
        The stem of an output file (``<value>.xlsx``).
    where : str
        ``"<file>: <field>"`` for the message.
    error : type
        An :class:`~covtool.errors.InputError` subclass.
    strict : bool
        True: the stem must also be a valid name (:func:`check_name`), as a
        study name must.  False: any single component without path
        separators, control characters, a leading ``.`` or ``-``, or a
        Windows device name (for stems derived from an input file name).

    Returns
    -------
    str

    Raises
    ------
    InputError
        (``error``) the stem could name a path outside the output
        directory, a hidden file, a device, or could not be written.
    """
    if strict:
        check_name(value, where, error, what="study name")
    if not isinstance(value, str) or not value:
        raise error(where, f"{value!r} is not a file name")
    bad = sorted({c for c in value if c in _BAD_FILE_CHARS or ord(c) < 32 or ord(c) == 127})
    if bad:
        raise error(where, f"{value!r} cannot be a file name: it contains {', '.join(map(repr, bad))}")
    if value[0] in ".-" or value != value.strip() or value.endswith("."):
        raise error(where, f"{value!r} cannot be a file name: it starts with '.' or '-', or has leading "
                    "or trailing blanks or dots")
    if value.split(".")[0].lower() in _RESERVED:
        raise error(where, f"{value!r} cannot be a file name: it is a reserved device name on Windows")
    if len(value.encode("utf-8")) > MAX_FILE_STEM:
        raise error(where, f"{value[:20]!r}... is longer than {MAX_FILE_STEM} bytes")
    return value


def check_study_name(study: dict, where: str, error=InputError, *, default: str) -> str:
    """The study's name, checked to be a safe ``<name>.xlsx`` before any computation.

    Parameters
    ----------
    study : dict
        The ``[study]`` table.
    where : str
        The study file (``"<study>"`` for a declaration given as a dict).
    error : type
        An :class:`~covtool.errors.InputError` subclass.
    default : str
        Name of a study given as a dict without ``name``.

    Returns
    -------
    str
        ``[study] name``, else the study file's stem, else ``default``.

    Raises
    ------
    InputError
        (``error``) The name (given or taken from the file name) is not a
        valid name (:func:`check_name`) or not a safe file name
        (:func:`check_file_stem`): ``"/abs/victim"``, ``"../x"``, ``"a/b"``,
        control characters, ``"CON"``, ...
    """
    if "name" in study:
        return check_file_stem(study["name"], f"{where}: [study] name", error)
    if where in ("<study>", ""):
        return check_file_stem(default, f"{where}: [study] name", error)
    stem = PurePath(where).stem
    try:
        return check_file_stem(stem, f"{where}: [study] name", error)
    except InputError as exc:
        raise error(exc.where, f"{exc.problem} (taken from the file name; set [study] name)") from None


__all__ = ["NAME_PATTERN", "MAX_NAME", "check_name", "check_file_stem", "check_study_name"]
