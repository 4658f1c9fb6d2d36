"""Read, validate and dump model files (``models/*.toml``).

File format
-----------
::

    [model]
    name = "sdins58"
    description = "..."

    [[block]]                      # the 10 navigation states of seed 002 eq (14)
    kind = "navigation"
    position_sigma = ["0 rad", "0 rad", "0 m"]
    velocity_sigma = "0.001 ft/s"          # one value means all three axes
    quaternion_sigma = ["0", "0.73e-4 rad", "0.73e-4 rad", "1.45e-3 rad"]
    angle_random_walk = "0.002 deg/sqrt(h)"
    velocity_random_walk = "5 ug/sqrt(Hz)"
    source = "seed 002, Table 2"

    [[block]]
    kind = "accel_bias"             # see covtool.lincov.model.blocks.BLOCK_KINDS
    sigma = ["20 ug", "20 ug", "30 ug"]
    process = "constant"            # constant | random_walk | markov | markov_distance
    tau = "1 h"                     # markov: required
    distance = "20 km"              # markov_distance: required
    rw = "0.001 deg/h/sqrt(h)"      # random_walk: driving root-PSD
    source = "seed 002, Table 2"

    [[correlation]]
    states = ["acc_bias_x", "acc_sf_x"]
    rho = 0.3

The display unit of each state is the unit written in its σ (``"20 ug"`` →
``ug``), or ``unit = "..."`` if given.  Every error names the file, the state
(or block) and the problem, and is a :class:`~covtool.errors.ModelFileError`.
"""

from __future__ import annotations

import copy
import hashlib
import re

import numpy as np
import tomli_w

from covtool.errors import ModelFileError
from covtool.io.config import as_list, check_keys, choice, load_toml, number, quantity, string
from covtool.io.names import check_name
from covtool.lincov.model.blocks import AXES, BLOCK_KINDS, NAV_DIMS, NAV_MEANING, NAV_SYMBOLS
from covtool.nav.strapdown import NAV_STATES
from covtool.lincov.model.spec import Model, PROCESSES, State
from covtool.units import DIMENSIONS, is_unit

_BLOCK_KEYS = {"kind", "name", "names", "sigma", "unit", "process", "tau", "distance", "rw", "source", "board"}
_BOARD_KEYS = {"sf", "n_t", "n_e_ratio"}
_NAV_KEYS = {"kind", "name", "position_sigma", "velocity_sigma", "quaternion_sigma",
             "angle_random_walk", "velocity_random_walk", "source"}
_TOP_KEYS = {"model", "block", "correlation", "override"}
_MODEL_KEYS = {"name", "description", "source", "base"}

DEFAULT_UNITS = {
    "acceleration": "ug", "angular_rate": "deg/h", "dimensionless": "ppm", "angle": "arcsec",
    "velocity": "m/s", "length": "m", "g_sensitivity": "deg/h/g", "g2_sensitivity": "deg/h/g**2",
    "quaternion": "", "time": "s",
}
_NUM = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*(.*)$")

#: process parameter -> the only process that uses it
_PROCESS_KEYS = {"tau": "markov", "distance": "markov_distance", "rw": "random_walk"}

# dimension of the random-walk intensity (root-PSD) for a state dimension
_RW_DIM = {"angular_rate": "rate_random_walk", "acceleration": "acceleration_random_walk",
           "velocity": "velocity_random_walk", "angle": "angle_random_walk"}


def _unit_of(text, dimension: str) -> str:
    if isinstance(text, str):
        m = _NUM.match(text)
        if m and m.group(3).strip():
            return m.group(3).strip()
    return DEFAULT_UNITS.get(dimension, "")


def _sigma(value, dim, where) -> float:
    """A finite standard deviation >= 0 (quaternion components also <= 1)."""
    x = quantity(value, dim, where, ModelFileError, nonnegative=True)
    if dim == "quaternion" and x > 1.0:
        raise ModelFileError(where, f"{value!r} is above 1; a unit quaternion's component cannot exceed 1")
    return x


def _positive(value, dim, where) -> float:
    return quantity(value, dim, where, ModelFileError, positive=True)


def _source(b: dict, where: str) -> str:
    return string(b.get("source", ""), f"{where}: source", ModelFileError)


def _nav_states(b: dict, where: str) -> tuple[list[State], float, float]:
    check_keys(b, _NAV_KEYS, where, ModelFileError)
    src = _source(b, where)
    block_name = check_name(b.get("name", "nav"), f"{where}: name", ModelFileError, what="block name")
    pos = as_list(b.get("position_sigma", 0.0), 3, f"{where}: position_sigma", ModelFileError)
    vel = as_list(b.get("velocity_sigma", 0.0), 3, f"{where}: velocity_sigma", ModelFileError)
    qs = as_list(b.get("quaternion_sigma", 0.0), 4, f"{where}: quaternion_sigma", ModelFileError)
    values = pos + vel + qs
    states = []
    for k, (name, sym, dim, meaning, v) in enumerate(zip(NAV_STATES, NAV_SYMBOLS, NAV_DIMS, NAV_MEANING, values)):
        w = f"{where.split(':')[0]}: state {name!r}: sigma"
        sig = _sigma(v, dim, w)
        states.append(State(name, sym, block_name, "navigation", meaning, dim,
                            _unit_of(v, dim) if dim != "quaternion" else _unit_of(v, dim),
                            sig, "navigation", source=src))
    arw = _sigma(b.get("angle_random_walk", 0.0), "angle_random_walk", f"{where}: angle_random_walk")
    vrw = _sigma(b.get("velocity_random_walk", 0.0), "velocity_random_walk", f"{where}: velocity_random_walk")
    return states, arw, vrw


def _block_states(b: dict, where: str, file: str) -> list[State]:
    check_keys(b, _BLOCK_KEYS, where, ModelFileError)
    kind = b["kind"]
    bk = BLOCK_KINDS[kind]
    prefix = check_name(b.get("name", bk.prefix), f"{where}: name", ModelFileError, what="block name")
    n = bk.n
    names = b.get("names")
    if names is None:
        names = [f"{prefix}_{s}" for s in bk.suffixes]
    else:
        names = as_list(names, n, f"{where}: names", ModelFileError)
        for nm in names:
            check_name(nm, f"{where}: names", ModelFileError, what="state name")
    process = choice(b.get("process", "constant"), PROCESSES, f"{where}: process", ModelFileError)
    if process not in bk.processes:
        raise ModelFileError(f"{where}: process", f"{process!r} is not allowed for kind {kind!r} "
                             f"(allowed: {', '.join(bk.processes)})")
    # a parameter of another process would be silently ignored: refuse it, naming the process
    for key, needs in _PROCESS_KEYS.items():
        if key in b and process != needs:
            raise ModelFileError(f"{where}: {key}", f"'{key}' applies only to process {needs!r}; the states "
                                 f"{', '.join(names)} follow process {process!r}")
    source = _source(b, where)
    if "board" in b:
        if kind != "ad_reset_velocity":
            raise ModelFileError(f"{where}: board", "'board' parameters apply only to kind 'ad_reset_velocity'")
        if "sigma" in b:
            raise ModelFileError(f"{where}: board", "give either 'sigma' or 'board', not both")
        b = {**b, "sigma": [_board_sigma(b["board"], f"{where}: board")] * n}
    sig = as_list(b.get("sigma", 0.0), n, f"{where}: sigma", ModelFileError)
    units = as_list(b["unit"], n, f"{where}: unit", ModelFileError) if "unit" in b else [None] * n
    taus = as_list(b["tau"], n, f"{where}: tau", ModelFileError) if "tau" in b else [None] * n
    dists = as_list(b["distance"], n, f"{where}: distance", ModelFileError) if "distance" in b else [None] * n
    rws = as_list(b.get("rw", 0.0), n, f"{where}: rw", ModelFileError)
    out = []
    for k in range(n):
        name, dim = names[k], bk.dims[k]
        sw = f"{file}: state {name!r}"
        sigma = _sigma(sig[k], dim, f"{sw}: sigma")
        unit = units[k] if units[k] is not None else _unit_of(sig[k], dim)
        if units[k] is not None and (not isinstance(unit, str) or not is_unit(unit, dim)):
            raise ModelFileError(f"{sw}: unit", f"{unit!r} is not a unit of {dim.replace('_', ' ')}")
        tau = dist = None
        rw = 0.0
        if process == "markov":
            if taus[k] is None:
                raise ModelFileError(sw, "process 'markov' needs a correlation time 'tau'")
            tau = _positive(taus[k], "time", f"{sw}: tau")
        elif process == "markov_distance":
            if dists[k] is None:
                raise ModelFileError(sw, "process 'markov_distance' needs a correlation 'distance'")
            dist = _positive(dists[k], "length", f"{sw}: distance")
        elif process == "random_walk":
            rw = _sigma(rws[k], _RW_DIM.get(dim, dim), f"{sw}: rw")
        axis = bk.suffixes[k]
        meaning = bk.meaning.format(axis=axis)
        out.append(State(name, bk.symbols[k], prefix, kind, meaning, dim, unit, sigma, process,
                         tau=tau, distance=dist, rw=rw, source=source))
    return out


def _board_sigma(board: dict, where: str) -> str:
    """AD-reset velocity-error 1σ from board parameters (seed 000, eq (7)-(8)).

    ``board = {sf = "0.0636 m/s", n_t = 1066.5, n_e_ratio = 0.02}``: the
    velocity worth of one reset pulse, the true AD counts per pulse and the
    relative error of the counts the software assumes.  The bound
    ``B = SF |N_e| / N̂`` of eq (7)-(8) with a uniformly distributed reset
    phase gives ``σ = B/√3`` (:func:`covtool.board.adreset.velocity_error_sigma`).
    """
    from covtool.board.adreset import velocity_error_sigma

    check_keys(board, _BOARD_KEYS, where, ModelFileError)
    for k in _BOARD_KEYS:
        if k not in board:
            raise ModelFileError(where, f"missing required key {k!r}")
    sf = _positive(board["sf"], "velocity", f"{where}: sf")
    n_t = number(board["n_t"], f"{where}: n_t", ModelFileError, lo=0.0, lo_open=True)
    # N_e/N_t: the relative count error the software assumes; at 1 the assumed count is zero
    ratio = number(board["n_e_ratio"], f"{where}: n_e_ratio", ModelFileError, lo=0.0, hi=1.0, lo_open=True,
                   hi_open=True)
    sigma = velocity_error_sigma(sf, n_t, ratio * n_t)
    return f"{sigma * 1e3!r} mm/s"


def model_from_dict(decl: dict, *, path: str = "<dict>") -> Model:
    """Validate a model declaration and build a :class:`Model`.

    Raises
    ------
    ModelFileError
        With the file, the state or block, and the problem.
    """
    file = str(path)
    check_keys(decl, _TOP_KEYS, file, ModelFileError)
    decl = resolve_base(decl, file)
    meta = decl.get("model", {})
    check_keys(meta, _MODEL_KEYS, f"{file}: [model]", ModelFileError)
    if "name" not in meta:
        raise ModelFileError(f"{file}: [model]", "missing required key 'name'")
    check_name(meta["name"], f"{file}: [model] name", ModelFileError, what="model name")
    for key in ("description", "source"):
        if key in meta:
            string(meta[key], f"{file}: [model] {key}", ModelFileError)
    blocks = decl.get("block", [])
    if not isinstance(blocks, list) or not blocks:
        raise ModelFileError(file, "no [[block]] declared")
    states: list[State] = []
    arw = vrw = 0.0
    seen_nav = False
    for i, b in enumerate(blocks):
        if not isinstance(b, dict):
            raise ModelFileError(f"{file}: block {i + 1}", "expected a table")
        kind = b.get("kind")
        where = f"{file}: block {i + 1} ({b.get('name', kind)})"
        if kind is None:
            raise ModelFileError(where, "missing required key 'kind'")
        if not isinstance(kind, str):
            raise ModelFileError(f"{where}: kind", f"{kind!r} is not a block kind (a string)")
        if kind == "navigation":
            if seen_nav:
                raise ModelFileError(where, "a model has exactly one navigation block")
            seen_nav = True
            nav, arw, vrw = _nav_states(b, where)
            states = nav + states
        elif kind in BLOCK_KINDS:
            states.extend(_block_states(b, where, file))
        else:
            raise ModelFileError(f"{where}: kind", f"unknown block kind {kind!r} "
                                 f"(one of: navigation, {', '.join(sorted(BLOCK_KINDS))})")
    if not seen_nav:
        raise ModelFileError(file, "missing the navigation block (kind = \"navigation\")")
    seen = {}
    for s in states:
        check_name(s.name, f"{file}: block {s.block!r}: names", ModelFileError, what="state name")
        if s.name in seen:
            raise ModelFileError(f"{file}: state {s.name!r}", "duplicate state name")
        seen[s.name] = s
    corr = []
    correlations = decl.get("correlation", [])
    if not isinstance(correlations, list):
        raise ModelFileError(f"{file}: correlation", "expected an array of tables [[correlation]]")
    pairs = set()
    for i, c in enumerate(correlations):
        where = f"{file}: correlation {i + 1}"
        check_keys(c, {"states", "rho"}, where, ModelFileError)
        pair = c.get("states")
        if not isinstance(pair, list) or len(pair) != 2:
            raise ModelFileError(f"{where}: states", "expected a list of two state names")
        for nm in pair:
            if not isinstance(nm, str) or nm not in seen:
                raise ModelFileError(f"{where}: states", f"unknown state {nm!r}")
        if pair[0] == pair[1]:
            raise ModelFileError(f"{where}: states", f"{pair[0]!r} twice; a state's correlation with itself is 1")
        if frozenset(pair) in pairs:
            raise ModelFileError(f"{where}: states", f"the pair {pair[0]!r}, {pair[1]!r} is correlated twice")
        pairs.add(frozenset(pair))
        if "rho" not in c:
            raise ModelFileError(where, "missing required key 'rho'")
        rho = c["rho"]
        if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not -1.0 <= rho <= 1.0:
            raise ModelFileError(f"{where}: rho", f"{rho!r} is not a correlation coefficient in [-1, 1]")
        corr.append((pair[0], pair[1], float(rho)))
    digest = hashlib.sha256(tomli_w.dumps(decl).encode()).hexdigest()
    model = Model(meta["name"], meta.get("description", ""), file, tuple(states), tuple(corr),
                  arw=arw, vrw=vrw, decl=copy.deepcopy(decl), sha256=digest)
    _check_psd(model, file)
    return model


def _check_psd(model: Model, file: str) -> None:
    P = model.initial_covariance()
    sig = np.sqrt(np.diag(P))
    scale = np.where(sig > 0, sig, 1.0)
    R = P / scale[:, None] / scale[None, :]
    w, V = np.linalg.eigh(R)
    if w.min() < -1e-10:
        v = V[:, np.argmin(w)]
        culprits = [model.names[i] for i in np.argsort(-np.abs(v))[:3] if abs(v[i]) > 1e-3]
        raise ModelFileError(f"{file}: correlation",
                             f"initial covariance is not positive semi-definite (eigenvalue {w.min():.3g} "
                             f"of the correlation matrix; involves {', '.join(culprits)})")


def load_model(path) -> Model:
    """Load and validate a model file (a ``base`` model's overrides resolved, :func:`resolve_base`)."""
    decl = load_toml(path, ModelFileError)
    return model_from_dict(decl, path=str(path))


def resolve_base(decl: dict, path: str = "<dict>") -> dict:
    """A model declared as overrides of another: the merged declaration.

    ::

        [model]
        name = "sdins58_uncalibrated"
        base = "sdins58"              # library name, or a path relative to this file
        [override.acc_mis]            # a block of the base, by name
        sigma = "10 arcsec"           # replaces these keys of the block
        source = "..."

    Parameters
    ----------
    decl : dict
        A model declaration; returned unchanged if ``[model]`` has no ``base``.
    path : str
        File it was read from (names it in errors, anchors a relative base).

    Returns
    -------
    dict
        The base's declaration with this model's ``[model]`` table, each
        overridden block's keys replaced, and its own ``[[correlation]]``
        appended.

    Raises
    ------
    ModelFileError
        Unknown base, a base that has a base itself, an override of a block
        the base does not have, or of its ``kind``/``name``.
    """
    meta = decl.get("model", {})
    if not isinstance(meta, dict) or "base" not in meta:
        if "override" in decl:
            raise ModelFileError(f"{path}: override", "overrides need [model] base = \"<model>\"")
        return decl
    from pathlib import Path

    from covtool.io.library import resolve_model_path

    here = Path(path).parent if path != "<dict>" else None
    bpath = resolve_model_path(meta["base"], here if here is not None else None, base_dir=here)
    base = load_toml(bpath, ModelFileError)
    if "base" in base.get("model", {}):
        raise ModelFileError(f"{path}: [model] base", f"{meta['base']!r} has a base itself (one level only)")
    merged = copy.deepcopy(base)
    merged["model"] = {k: v for k, v in meta.items() if k != "base"}
    merged["model"].setdefault("source", f"{meta['base']} with overrides")
    names = []
    for b in merged.get("block", []):
        kind = b.get("kind")
        names.append(b.get("name", "nav" if kind == "navigation" else BLOCK_KINDS[kind].prefix
                           if kind in BLOCK_KINDS else kind))
    for bname, ov in (decl.get("override") or {}).items():
        w = f"{path}: [override.{bname}]"
        if bname not in names:
            raise ModelFileError(w, f"base model {meta['base']!r} has no block {bname!r} "
                                 f"(blocks: {', '.join(names)})")
        if not isinstance(ov, dict):
            raise ModelFileError(w, "expected a table of block keys")
        for key in ("kind", "name"):
            if key in ov:
                raise ModelFileError(f"{w} {key}", "the kind and name of a base block cannot be overridden")
        merged["block"][names.index(bname)].update(copy.deepcopy(ov))
    merged["correlation"] = merged.get("correlation", []) + copy.deepcopy(decl.get("correlation", []))
    if not merged["correlation"]:
        merged.pop("correlation")
    return merged


def dump_model(model: Model) -> str:
    """Serialise a model back to TOML (the declaration, datasheet units kept)."""
    return tomli_w.dumps(model.decl)


def save_model(model: Model, path) -> None:
    """Write a model file atomically."""
    from covtool.io.atomic import write_text

    write_text(path, dump_model(model))


__all__ = ["load_model", "model_from_dict", "dump_model", "save_model", "DEFAULT_UNITS", "AXES", "DIMENSIONS"]
