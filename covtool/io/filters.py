"""Reduced-order filters declared as projections of the truth model (seed 002, Table 1).

A filter keeps a subset of the truth states *by name*, may simplify the
navigation equations (decoupled vertical channel, no Coriolis terms), and
replaces every truth state it drops by an equivalent white noise
(seed 002, eq (11)–(13)) mapped onto its kept states through the truth
coupling ``F_kept,dropped``.

Filter file (``models/filters/*.toml``)::

    [[filter]]
    name = "B1"
    truth = "sdins58"                 # the truth model it is a projection of: a library name, or a
                                      # path relative to this file ("../sdins58.toml")
    description = "22 states, eq (14)"
    keep = ["nav", "acc_bias", "gyro_bias", "acc_sf", "gyro_sf"]   # blocks or states
    # base = "B1"; drop = [...]       # or derive from another filter (of any filter file the study names)
    # add = ["acc_markov"]            #   and keep extra truth states or blocks
    decouple_vertical = false         # B2
    coriolis = true                   # B3: false
    equivalent_noise = "interval"     # eq (11)-(13) for the dropped states (or "pointwise", "matched", false)
    discretization = "taylor"         # eq (6b)-(6d); or "van_loan"
    taylor_order = 12                 # optional: terms of eq (6b), 2..40 (default: until converged)
    update = "joseph"                 # or "standard" (eq (8))
    zupt_sigma = "0.01 ft/s"          # optional: the ZUPT 1σ the filter assumes (> 0)
    [filter.P0]                       # optional overrides of the kept states' 1σ
    acc_bias_z = "30 ug"
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

from covtool.errors import ModelFileError
from covtool.io.config import (boolean, check_keys, choice, integer, is_library_name, load_toml, names,
                               quantity, resolve_input, string, table)
from covtool.io.names import check_name
from covtool.lincov.dynamics import NavOptions
from covtool.nav.strapdown import NAV_STATES
from covtool.lincov.model.spec import Model
from covtool.lincov.reduced import FilterSpec


_FILTER_KEYS = {"name", "truth", "description", "keep", "base", "drop", "decouple_vertical", "coriolis",
                "equivalent_noise", "discretization", "taylor_order", "update", "P0", "zupt_sigma", "source",
                "add"}


def load_filters(path, truth: Model) -> dict[str, FilterSpec]:
    """Load every ``[[filter]]`` of one or several filter files, validated against ``truth``.

    Parameters
    ----------
    path : path-like or list of path-like
        One filter file, or several (``[filters] file = ["a.toml", "b.toml"]``);
        a filter's ``base`` may name a filter of any of them.
    truth : Model

    Raises
    ------
    ModelFileError
        Unknown key, unknown truth state, a filter declared for another truth
        model, a P0 override of a state the filter does not keep, a filter
        without the velocity states that ZUPT measures, a filter name
        declared twice (in one file or across files), an unknown or
        circular ``base``, ...
    """
    paths = list(path) if isinstance(path, (list, tuple)) else [path]
    files = [(str(p), load_toml(p, ModelFileError)) for p in paths]
    return filters_from_files(files, truth)


#: a filter name: it becomes a case label, a column header and part of a sheet name
#: equivalent_noise values; true and "eq11-13" mean "interval" (seed 002 eq (11)-(13), interval-matched)
_EWN = (False, True, "eq11-13", "interval", "pointwise", "matched")


def filters_from_dict(decl: dict, truth: Model, *, path: str = "<dict>") -> dict[str, FilterSpec]:
    """Validate the filter declarations of one file; see :func:`load_filters`.

    A ``truth`` given as a path (``"../sdins58.toml"``) resolves against the
    directory of the filter file and must be the study's truth model file.
    """
    return filters_from_files([(path, decl)], truth)


def filters_from_files(files, truth: Model) -> dict[str, FilterSpec]:
    """Validate the filter declarations of several files, ``base`` resolved across them.

    Parameters
    ----------
    files : list of (str, dict)
        ``(path, parsed TOML)`` of each filter file, in the order the study
        names them; the filters come out in that order.
    truth : Model

    Notes
    -----
    A derived filter (``base = "B1"``) starts from its base's resolved
    declaration (its kept states, options and P0), without the base's
    ``drop`` and ``description``; its own keys replace the base's, ``add``
    appends truth states or blocks to the kept set and ``drop`` removes
    them.  The base may be declared anywhere in the files (before or after,
    in the same file or another); a cycle is refused.
    """
    raw: dict[str, tuple[str, dict, str]] = {}
    order = []
    for path, decl in files:
        check_keys(decl, {"filter"}, path, ModelFileError)
        lst = decl.get("filter", [])
        if not isinstance(lst, list) or not lst:
            raise ModelFileError(path, "no [[filter]] declared")
        for i, f in enumerate(lst):
            where = (f"{path}: filter {f.get('name', i + 1)!r}" if isinstance(f, dict)
                     else f"{path}: filter {i + 1}")
            check_keys(f, _FILTER_KEYS, where, ModelFileError)
            if "name" not in f:
                raise ModelFileError(where, "missing required key 'name'")
            name = check_name(f["name"], f"{path}: filter {i + 1}: name", ModelFileError, what="filter name")
            if name in raw:
                other = raw[name][0]
                raise ModelFileError(where, "duplicate filter name" + ("" if other == path else
                                                                       f" (also declared in {other})"))
            raw[name] = (path, f, where)
            order.append(name)
    resolved: dict[str, dict] = {}
    out: dict[str, FilterSpec] = {}

    def resolve(name: str, chain: tuple) -> dict:
        if name in resolved:
            return resolved[name]
        path, f, where = raw[name]
        base_dir = Path(path).parent if path != "<dict>" else None
        f = dict(f)
        if isinstance(f.get("truth"), str) and not is_library_name(f["truth"]):
            # a path is relative to the file that declares it, also when a derived filter inherits it
            f["truth"] = str(resolve_input(f["truth"], base_dir, f"{where}: truth", ModelFileError,
                                           what="truth model file"))
        if "base" in f:
            b = f["base"]
            if not isinstance(b, str) or b not in raw:
                raise ModelFileError(f"{where}: base", f"unknown base filter {b!r} (declared in none of the "
                                     f"filter files: {', '.join(sorted({p for p, _, _ in raw.values()}))})")
            if b in chain or b == name:
                raise ModelFileError(f"{where}: base", "circular base: " + " -> ".join((*chain, name, b)))
            merged = copy.deepcopy(resolve(b, (*chain, name)))
            merged.pop("description", None)
            merged.update({k: v for k, v in f.items() if k not in ("base", "keep")})
            if "keep" in f:
                merged["keep"] = f["keep"]
            f = merged
        spec = _spec(f, truth, where, path, base_dir)
        out[name] = spec
        res = {k: v for k, v in f.items() if k not in ("drop", "add", "base")}
        res["keep"] = list(spec.kept)
        resolved[name] = res
        return res

    for name in order:
        resolve(name, ())
    return {name: out[name] for name in order}


def _check_truth(tname, truth: Model, where: str, base_dir) -> None:
    """The filter's ``truth``: a library name equal to the study's, or a path to the same file."""
    w = f"{where}: truth"
    string(tname, w, ModelFileError, nonempty=True)
    if is_library_name(tname):
        if tname != truth.name:
            raise ModelFileError(w, f"filter was declared for truth model {tname!r}, "
                                 f"but the study's truth model is {truth.name!r}")
        return
    from covtool.io.model_file import load_model

    p = resolve_input(tname, base_dir, w, ModelFileError, what="truth model file")
    same = Path(truth.path).is_file() and os.path.samefile(p, truth.path)
    if not same and load_model(p).sha256 != truth.sha256:
        raise ModelFileError(w, f"filter was declared for truth model file {str(p)!r}, but the study's truth "
                             f"model is {truth.path!r} ({truth.name!r}), a different declaration")


def _spec(f: dict, truth: Model, where: str, path: str, base_dir=None) -> FilterSpec:
    _check_truth(f.get("truth", truth.name), truth, where, base_dir)
    for key in ("description", "source"):
        if key in f:
            string(f[key], f"{where}: {key}", ModelFileError)
    keep = f.get("keep", "all")
    if isinstance(keep, str) and keep != "all":
        keep = [keep]
    if keep != "all":
        names(keep, f"{where}: keep", ModelFileError, what="truth state or block")
    drop = names(f.get("drop", []), f"{where}: drop", ModelFileError, nonempty=False,
                 what="truth state or block")
    add = f.get("add", [])
    add = names([add] if isinstance(add, str) else add, f"{where}: add", ModelFileError, nonempty=False,
                what="truth state or block")

    def expand(sel, key):
        try:
            return truth.states_of(sel)
        except KeyError as exc:
            raise ModelFileError(f"{where}: {key}", f"unknown truth state or block {exc.args[0]!r} "
                                 f"(truth model {truth.name!r})") from None

    kept = truth.names if keep == "all" else expand(keep, "keep")
    added = expand(add, "add")
    dropped = set(expand(drop, "drop"))
    both = dropped & set(added)
    if both:
        raise ModelFileError(f"{where}: add", f"state {sorted(both)[0]!r} is both added and dropped")
    kept_set = (set(kept) | set(added)) - dropped
    kept = tuple(nm for nm in truth.names if nm in kept_set)   # truth order
    for v in NAV_STATES:
        if v not in kept_set:
            raise ModelFileError(f"{where}: keep", f"a ZUPT filter must keep the navigation state {v!r} "
                                 "(the 10 states of seed 002 eq (14))")
    P0 = {}
    for nm, val in table(f.get("P0") or {}, f"{where}: P0", ModelFileError).items():
        if nm not in truth.index:
            raise ModelFileError(f"{where}: P0", f"unknown truth state {nm!r}")
        if nm not in kept_set:
            raise ModelFileError(f"{where}: P0", f"state {nm!r} is not kept by this filter")
        st = truth.states[truth.index[nm]]
        P0[nm] = quantity(val, st.dimension, f"{where}: P0: {nm}", ModelFileError, nonnegative=True)
    disc = choice(f.get("discretization", "taylor"), ("taylor", "van_loan"), f"{where}: discretization",
                  ModelFileError)
    upd = choice(f.get("update", "joseph"), ("joseph", "standard"), f"{where}: update", ModelFileError)
    order = None
    if "taylor_order" in f:
        if disc != "taylor":
            raise ModelFileError(f"{where}: taylor_order", f"applies only to discretization 'taylor'; this filter "
                                 f"uses {disc!r}")
        order = integer(f["taylor_order"], f"{where}: taylor_order", ModelFileError, limit="taylor_order")
    zs = None
    if "zupt_sigma" in f:
        # R_f = 0 makes S = H P_f H^T + R_f of eq (7) singular as soon as P_f's velocity block is
        # (a previous zero-noise ZUPT leaves it exactly zero): the gain is undefined
        zs = quantity(f["zupt_sigma"], "velocity", f"{where}: zupt_sigma", ModelFileError, positive=True)
    options = {key: boolean(f[key], f"{where}: {key}", ModelFileError)
               for key in ("decouple_vertical", "coriolis") if key in f}
    ewn = choice(f.get("equivalent_noise", "interval"), _EWN, f"{where}: equivalent_noise", ModelFileError)
    if ewn is True or ewn == "eq11-13":
        ewn = "interval"
    return FilterSpec(
        name=f["name"], truth=truth.name, kept=kept,
        options=NavOptions(coriolis=options.get("coriolis", True),
                           couple_vertical=not options.get("decouple_vertical", False)),
        equivalent_noise=ewn, discretization=disc,
        taylor_order=order, update=upd, P0_sigma=P0, zupt_sigma=zs,
        description=f.get("description", ""), path=path, decl=copy.deepcopy(f))


def default_filter_file() -> Path:
    """The library's ZUPT filter declarations."""
    from covtool.io.library import default_model_dir

    return default_model_dir() / "filters" / "zupt_filters.toml"
