"""The model library: truth models, filters and IMU grades, found by name."""

from __future__ import annotations

from dataclasses import dataclass, field
import importlib.resources
import os
from pathlib import Path

from covtool.errors import InputError, ModelFileError
from covtool.io.config import is_library_name, resolve_input
from covtool.io.model_file import load_model


def default_model_dir() -> Path:
    """The model library: ``$COVTOOL_MODELS``, else the package data ``covtool.models``.

    The repository's top-level ``models/`` folder ships as the package
    ``covtool.models`` (``pip install .`` or ``pip install -e .``) and is
    found with :func:`importlib.resources.files`; a source checkout used
    without installing (``PYTHONPATH``) falls back to the ``models/``
    beside the ``covtool`` package.  Never the current directory: a study
    must give the same answer wherever it is run from.  A path given in a
    study or filter file resolves against that file's folder
    (:func:`resolve_model_path`) and comes before the library.
    """
    env = os.environ.get("COVTOOL_MODELS")
    if env:
        return Path(env)
    try:
        return Path(str(importlib.resources.files("covtool.models")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "models"


def model_files(directory=None) -> list[Path]:
    """All truth-model files in the library (filter declarations live in ``models/filters``)."""
    d = Path(directory) if directory else default_model_dir()
    return sorted(p for p in d.glob("*.toml"))


def resolve_model_path(name_or_path, directory=None, *, base_dir=None, where=None) -> Path:
    """Absolute path of a model given by library name or by path.

    Parameters
    ----------
    name_or_path : str or Path
        A bare library name (``"sdins58"``: no suffix, no separator) is
        looked up in ``directory`` (default :func:`default_model_dir`).
        Anything else is a path; a relative one resolves against
        ``base_dir``, the directory of the file that names it (the current
        directory only when no file names it: the command line, a dict).
    where : str, optional
        Error-message location (default: the name itself).

    Raises
    ------
    ModelFileError
        No such model, naming where it looked.
    """
    w = where or str(name_or_path)
    if isinstance(name_or_path, Path):
        name_or_path = str(name_or_path)
    if not isinstance(name_or_path, str) or not name_or_path.strip():
        raise ModelFileError(w, f"{name_or_path!r} is not a model name or file")
    if is_library_name(name_or_path):
        d = Path(directory) if directory else default_model_dir()
        c = d / f"{name_or_path}.toml"
        if c.is_file():
            return Path(os.path.abspath(c))
        known = ", ".join(p.stem for p in model_files(d)) or "none"
        raise ModelFileError(w, f"no such model {name_or_path!r} in the library {str(d)!r} (known: {known}); "
                             "a file needs a path, e.g. 'm.toml'")
    return resolve_input(name_or_path, base_dir, w, ModelFileError, what="model file")


def load_model_by_name(name_or_path, directory=None, *, base_dir=None, where=None):
    """Load a library model by name or path (see :func:`resolve_model_path`)."""
    return load_model(resolve_model_path(name_or_path, directory, base_dir=base_dir, where=where))


def _default_truth(d: Path) -> str | None:
    """The truth a filter file that names none is projected onto: ``sdins58`` if valid, else the first valid."""
    names = [p.stem for p in model_files(d)]
    for name in (["sdins58"] if "sdins58" in names else []) + names:
        try:
            load_model(d / f"{name}.toml")
            return name
        except InputError:
            continue
    return None


def filter_files(directory=None) -> list[Path]:
    """The library's filter files, the flagship's (``zupt_filters.toml``) first."""
    d = Path(directory) if directory else default_model_dir()
    files = sorted((d / "filters").glob("*.toml"))
    return sorted(files, key=lambda p: p.name != "zupt_filters.toml")


def load_filter_file(path, directory=None, *, default_truth: str | None = None):
    """A filter file's filters, projected onto the truth they name.

    Parameters
    ----------
    path : path-like
        A ``[[filter]]`` file.
    directory : path, optional
        The library (default :func:`default_model_dir`), where a truth named
        by a bare name is found.
    default_truth : str, optional
        The truth of a file that names none (it projects whichever truth a
        study runs); default ``sdins58`` or the library's first valid truth.

    Returns
    -------
    truth : Model
    specs : dict of str to FilterSpec
    raw : dict of str to dict
        Each filter's declaration as written (its ``base``).

    Raises
    ------
    ModelFileError
        The file is invalid, names several truths, or there is no truth.
    """
    from covtool.io.config import load_toml
    from covtool.io.filters import load_filters

    p = Path(path)
    d = Path(directory) if directory else default_model_dir()
    decl = load_toml(p, ModelFileError)
    raw_filters = decl.get("filter", []) if isinstance(decl.get("filter"), list) else []
    named = {f["truth"] for f in raw_filters if isinstance(f, dict) and isinstance(f.get("truth"), str)}
    if len(named) > 1:
        raise ModelFileError(f"{p}: truth", f"the filters name {len(named)} truth models "
                             f"({', '.join(sorted(map(repr, named)))}); listing needs one")
    name = named.pop() if named else (default_truth or _default_truth(d))
    if name is None:
        raise ModelFileError(str(p), "no valid truth model in the library to project the filters of")
    truth = load_model_by_name(name, d, base_dir=p.parent, where=f"{p}: truth")
    specs = load_filters(p, truth)
    raw = {f.get("name"): f for f in raw_filters if isinstance(f, dict)}
    return truth, specs, raw


def list_models(directory=None) -> pd.DataFrame:
    """The library's contents: truth models, filters and IMU grades, one row each.

    Parameters
    ----------
    directory : path, optional
        The library (default :func:`default_model_dir`): ``*.toml`` truth
        models, ``filters/*.toml`` filter files, ``imu/*.toml`` IMU grades.

    Returns
    -------
    pandas.DataFrame
        Columns ``kind`` (``"truth model"``, ``"filter"``, ``"IMU grade"``),
        ``name``, ``states`` (of the truth model, kept by the filter, of the
        grade's error model), ``base`` (a filter's base filter, a truth
        model's base model; empty otherwise), ``truth`` (the truth model a
        filter is projected onto), ``description`` and ``file``.  A filter
        file that names no truth (it projects whichever truth a study runs)
        is listed against ``sdins58`` (else the library's first valid truth
        model).  A file that does not validate is listed once,
        its description ``INVALID:`` and the error.
    """
    from covtool.io.config import load_toml
    from covtool.io.imu_grade import load_imu_grade

    d = Path(directory) if directory else default_model_dir()
    rows = []

    def row(kind, name, states, base, description, path, truth=""):
        rows.append({"kind": kind, "name": name, "states": states, "base": base, "truth": truth,
                     "description": description, "file": str(path)})

    for p in model_files(d):
        try:
            m = load_model(p)
            head = load_toml(p, ModelFileError).get("model")
            base = head.get("base", "") if isinstance(head, dict) else ""
            row("truth model", m.name, m.n, base if isinstance(base, str) else "", m.description, p)
        except InputError as exc:
            row("truth model", p.stem, 0, "", f"INVALID: {exc}", p)
    default = _default_truth(d)
    for p in filter_files(d):
        try:
            truth, specs, raw = load_filter_file(p, d, default_truth=default)
            for fname, spec in specs.items():
                base = raw.get(fname, {}).get("base", "")
                row("filter", fname, len(spec.kept), base if isinstance(base, str) else "", spec.description, p,
                    truth.name)
        except InputError as exc:
            row("filter", p.stem, 0, "", f"INVALID: {exc}", p)
    for p in sorted((d / "imu").glob("*.toml")):
        try:
            g = load_imu_grade(str(p))
            row("IMU grade", g.name, g.to_model().n, "", g.description, p)
        except InputError as exc:
            row("IMU grade", p.stem, 0, "", f"INVALID: {exc}", p)
    import pandas as pd          # here: `covtool show` reads the library without pandas

    return pd.DataFrame(rows, columns=["kind", "name", "states", "base", "truth", "description", "file"])


def markdown_table(model) -> str:
    """The state table of ``model`` as a Markdown table (for docs/)."""
    df = model.state_table()
    lines = ["| # | state | symbol | meaning | 1σ | unit | process | τ / distance | source |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, r in df.iterrows():
        corr = ""
        if r["tau [s]"] == r["tau [s]"]:
            corr = f"τ = {r['tau [s]']:g} s"
        elif r["corr. distance [m]"] == r["corr. distance [m]"]:
            corr = f"d = {r['corr. distance [m]'] / 1000:g} km"
        lines.append(f"| {i + 1} | `{r['state']}` | {r['symbol']} | {r['meaning']} | {r['sigma']:.4g} | "
                     f"{r['unit'] or '–'} | {r['process']} | {corr or '–'} | {r['source']} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------
# one name across the three kinds: covtool show
# ---------------------------------------------------------------------------

#: the kinds of library entry, as ``covtool models`` names them
KINDS = ("truth model", "filter", "IMU grade")


@dataclass(frozen=True)
class Entry:
    """One library entry found by :func:`lookup`.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    name : str
    path : Path
        The file that declares it.
    obj : Model, FilterSpec or ImuGrade
        The validated entry (SI values).
    truth : Model or None
        A filter's truth model (the one it is projected onto).
    raw : dict
        A filter's declaration as written (its ``base``).
    """

    kind: str
    name: str
    path: Path
    obj: object
    truth: object = None
    raw: dict = field(default_factory=dict)


def _kind_of_file(decl: dict, path: Path) -> str:
    """Which of the three file kinds a TOML declaration is, by its top-level tables."""
    keys = set(decl)
    if "filter" in keys:
        return "filter"
    if "imu" in keys:
        return "IMU grade"
    if keys & {"model", "block", "override"}:
        return "truth model"
    raise ModelFileError(str(path), f"is neither a truth model ([model], [[block]]), a filter file ([[filter]]) nor "
                         f"an IMU grade ([imu]); its tables are {', '.join(sorted(keys)) or 'none'}")


def _entries_of_file(path: Path, d: Path) -> list[Entry]:
    from covtool.io.config import load_toml
    from covtool.io.imu_grade import load_imu_grade

    kind = _kind_of_file(load_toml(path, ModelFileError), path)
    if kind == "truth model":
        m = load_model(path)
        return [Entry(kind, m.name, path, m)]
    if kind == "IMU grade":
        g = load_imu_grade(str(path))
        return [Entry(kind, g.name, path, g)]
    truth, specs, raw = load_filter_file(path, d)
    return [Entry(kind, n, path, f, truth, raw.get(n, {})) for n, f in specs.items()]


def lookup(name_or_path, directory=None) -> list[Entry]:
    """Every library entry of a name, or every entry of a file.

    Parameters
    ----------
    name_or_path : str
        A bare name (``"sdins58"``, ``"B1"``, ``"kimu"``) is looked up as a
        truth model, a filter (in every filter file; a name may be declared
        in several) and an IMU grade; anything else is a path to a truth
        model, filter or IMU-grade file (relative to the current directory).
    directory : path, optional
        The library (default :func:`default_model_dir`).

    Returns
    -------
    list of Entry
        At least one; the flagship's filter file comes first among filters.

    Raises
    ------
    ModelFileError
        No entry of that name (naming the library and its names), no such
        file, a file of none of the three kinds, or an invalid file.
    """
    from covtool.io.config import load_toml

    d = Path(directory) if directory else default_model_dir()
    if not isinstance(name_or_path, str) or not name_or_path.strip():
        raise ModelFileError(str(name_or_path), "is not a model, filter or IMU-grade name or file")
    if not is_library_name(name_or_path):
        if Path(name_or_path).expanduser().is_dir():
            raise ModelFileError(name_or_path, "is a directory, not a truth model, filter or IMU-grade file")
        path = resolve_input(name_or_path, None, name_or_path, ModelFileError, what="file")
        return _entries_of_file(path, d)
    name = name_or_path
    found: list[Entry] = []
    truth_file = d / f"{name}.toml"
    if truth_file.is_file():
        m = load_model(truth_file)
        found.append(Entry("truth model", m.name, Path(os.path.abspath(truth_file)), m))
    for p in filter_files(d):
        try:
            decl = load_toml(p, ModelFileError)
        except InputError:
            continue                      # an unreadable file holds no name; `covtool models` flags it
        fs = decl.get("filter")
        if isinstance(fs, list) and any(isinstance(f, dict) and f.get("name") == name for f in fs):
            truth, specs, raw = load_filter_file(p, d)
            found.append(Entry("filter", name, Path(os.path.abspath(p)), specs[name], truth, raw.get(name, {})))
    grade_file = d / "imu" / f"{name}.toml"
    if grade_file.is_file():
        from covtool.io.imu_grade import load_imu_grade

        g = load_imu_grade(str(grade_file))
        found.append(Entry("IMU grade", g.name, Path(os.path.abspath(grade_file)), g))
    if not found:
        df = list_models(d)
        known = "; ".join(f"{kind}s: " + (", ".join(dict.fromkeys(df.loc[df["kind"] == kind, "name"])) or "none")
                          for kind in KINDS)
        raise ModelFileError(name, f"no such model, filter or IMU grade in the library {str(d)!r} ({known}); "
                             "a file needs a path, e.g. './m.toml'")
    return found


# ---------------------------------------------------------------------------
# text for the terminal: datasheet units to sensible digits, SI at full precision
# ---------------------------------------------------------------------------

def _ds(x) -> str:
    """A datasheet-unit value to six significant digits (no float noise: 15, not 14.999999999999996)."""
    return f"{float(x):.6g}"


def _si(x) -> str:
    """An SI value at full precision: the shortest string that reads back to the same float."""
    return repr(float(x))


def _si_unit(dimension: str) -> str:
    from covtool.units import DIMENSIONS

    u = DIMENSIONS.get(dimension, ("",))[0]
    return (u or "1").replace("**", "^")


def _span(seconds: float) -> str:
    """A time span in h (from 1 h), min (from 2 min) or s: 3600 → '1 h', 1800 → '30 min', 20 → '20 s'."""
    for unit, f, lo in (("h", 3600.0, 3600.0), ("min", 60.0, 120.0)):
        if seconds >= lo:
            return f"{seconds / f:.6g} {unit}"
    return f"{seconds:.6g} s"


def _wrap(text: str, width: int, indent: str) -> str:
    import textwrap

    return textwrap.fill(text, width=width, initial_indent=indent, subsequent_indent=indent + "  ",
                         break_long_words=False, break_on_hyphens=False)


def _table(rows: list[list[str]], header: list[str], right: set[int] = frozenset()) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]

    def line(cells):
        return "  ".join(str(c).rjust(w) if i in right else str(c).ljust(w)
                         for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths])] + [line(r) for r in rows])


def _process(st) -> str:
    if st.process == "markov":
        return f"Markov, τ {_span(st.tau)}"
    if st.process == "markov_distance":
        return f"Markov, d {st.distance / 1000:.6g} km"
    if st.process == "random_walk":
        return "random walk"
    return st.process


def _noise_lines(arw: float, vrw: float, width: int) -> list[str]:
    """ARW and VRW in datasheet units and SI, with their PSDs (white noise, seed 002 eq (1)-(5))."""
    from covtool.units import from_si

    rows = [["ARW", "angle random walk", f"{_ds(from_si(arw, 'deg/sqrt(h)'))} deg/√h", f"{_si(arw)} rad/√s",
             f"{_si(arw * arw)} rad²/s"],
            ["VRW", "velocity random walk", f"{_ds(from_si(vrw, 'ug/sqrt(Hz)'))} µg/√Hz", f"{_si(vrw)} m/s^1.5",
             f"{_si(vrw * vrw)} m²/s³"]]
    return _table(rows, ["", "white sensor noise", "datasheet", "root-PSD [SI]", "PSD [SI]"]).splitlines()


def _squared(unit: str) -> str:
    return f"({unit})²" if any(c in unit for c in "/^") else f"{unit}²"


def _driving_noise(states) -> list[str]:
    """Driving-noise PSD of every stochastic (non-constant) sensor state."""
    rows = []
    for st in states:
        if st.process == "markov":
            rows.append([st.name, "2σ²/τ", _si(st.psd()), f"{_squared(_si_unit(st.dimension))}/s"])
        elif st.process == "markov_distance":
            rows.append([st.name, "2σ²|v|/d", f"{_si(2.0 * st.sigma ** 2 / st.distance)} × |v|",
                         f"{_squared(_si_unit(st.dimension))}/s per m/s"])
        elif st.process == "random_walk":
            rows.append([st.name, "rw²", _si(st.psd()), f"{_squared(_si_unit(st.dimension))}/s"])
    if not rows:
        return []
    return ["", "driving-noise PSD of the Gauss–Markov and random-walk states:"] + \
        _table(rows, ["state", "PSD", "value [SI]", "SI unit"]).splitlines()


def _state_rows(states, sigma=None, marks=None) -> list[list[str]]:
    from covtool.units import from_si

    rows = []
    for i, st in enumerate(states):
        s = st.sigma if sigma is None else sigma[i]
        shown = from_si(s, st.unit) if st.unit else s
        row = [str(i + 1), st.name, st.symbol, _ds(shown), st.unit or "1", _si(s), _si_unit(st.dimension),
               _process(st)]
        if marks is not None:
            row.append(marks[i])
        rows.append(row)
    return rows


_STATE_HEADER = ["#", "state", "symbol", "1σ", "unit", "1σ [SI]", "SI unit", "process"]


def describe_truth(m, width: int = 100) -> str:
    """A truth model as text: header, noise densities, state table, block sources.

    Parameters
    ----------
    m : Model
    width : int
        Wrap long lines (descriptions, sources) at this many columns.

    Returns
    -------
    str
        Values in datasheet units to six significant digits and in SI at
        full precision (``repr``: reads back to the same float).
    """
    out = [f"truth model {m.name}: {m.n} states", _wrap(m.description, width, "  "), f"  file: {m.path}", ""]
    out += _noise_lines(m.arw, m.vrw, width) + [""]
    out += _table(_state_rows(m.states), _STATE_HEADER, right={0, 3, 5}).splitlines()
    out += _driving_noise(m.states)
    if m.correlations:
        out += ["", "initial correlations:"] + [f"  ρ({a}, {b}) = {_si(r)}" for a, b, r in m.correlations]
    out += ["", "sources (by block):"]
    seen = {}
    for st in m.states:
        seen.setdefault(st.block, st.source)
    for block, src in seen.items():
        out.append(_wrap(f"{block}: {src or '(none given)'}", width, "  "))
    return "\n".join(out) + "\n"


def describe_filter(spec, truth, raw: dict | None = None, width: int = 100) -> str:
    """A filter as text: base, options, kept states with their P0, dropped blocks.

    Parameters
    ----------
    spec : FilterSpec
    truth : Model
        The truth model it is projected onto.
    raw : dict, optional
        The declaration as written (for ``base``).
    width : int
        Wrap long lines at this many columns.

    Returns
    -------
    str
        P0 1σ of each kept state in datasheet units and SI (full
        precision); an override from ``[filter.P0]`` is marked.
    """
    raw = raw or {}
    kept = [truth.states[truth.index[n]] for n in spec.kept]
    sigma = [spec.P0_sigma.get(st.name, st.sigma) for st in kept]
    marks = ["[filter.P0]" if st.name in spec.P0_sigma else "truth" for st in kept]
    ewn = {False: "none (dropped states ignored)", "interval": "interval-matched, seed 002 eq (11)-(13)",
           "pointwise": "pointwise, seed 002 eq (11)-(13)",
           "matched": "matched (absorbed constants, interval-matched residual)"}.get(spec.equivalent_noise,
                                                                                       str(spec.equivalent_noise))
    disc = "Taylor series, seed 002 eq (6b)-(6d)" if spec.discretization == "taylor" else "Van Loan (exact)"
    if spec.discretization == "taylor":
        disc += f", {spec.taylor_order} terms" if spec.taylor_order else ", terms until converged"
    opts = [
        ("base filter", raw.get("base") or "none (declared in full)"),
        ("truth model", f"{truth.name} ({truth.n} states, {truth.path})"),
        ("kept states", f"{len(kept)} of {truth.n}"),
        ("Coriolis terms", "kept" if spec.options.coriolis else "dropped (B3)"),
        ("vertical channel", "coupled" if spec.options.couple_vertical else "decoupled (B2)"),
        ("equivalent white noise", ewn),
        ("discretisation", disc),
        ("measurement update", "Joseph form" if spec.update == "joseph" else "standard, seed 002 eq (8)"),
        ("ZUPT 1σ assumed", f"{_ds(spec.zupt_sigma / 0.3048)} ft/s = {_si(spec.zupt_sigma)} m/s"
         if spec.zupt_sigma is not None else "the study's ZUPT σ"),
    ]
    out = [f"filter {spec.name}: {len(kept)} states, a projection of {truth.name}"]
    if spec.description:
        out.append(_wrap(spec.description, width, "  "))
    out += [f"  file: {spec.path}", ""]
    w = max(len(k) for k, _ in opts)
    out += [_wrap(f"{k.ljust(w)}  {v}", width, "  ") for k, v in opts]
    out += ["", "kept states and their initial 1σ (P0):"]
    out += _table(_state_rows(kept, sigma, marks), _STATE_HEADER + ["P0 from"], right={0, 3, 5}).splitlines()
    dropped = [st for st in truth.states if st.name not in set(spec.kept)]
    if dropped:
        blocks = {}
        for st in dropped:
            blocks.setdefault(st.block, []).append(st.name)
        text = ", ".join(f"{b} ({len(v)})" for b, v in blocks.items())
        out += ["", _wrap(f"dropped states ({len(dropped)}), by block: {text}", width, "")]
    return "\n".join(out) + "\n"


def describe_grade(g, width: int = 100) -> str:
    """An IMU grade as text: every value as written and in SI, noise densities, sources.

    Parameters
    ----------
    g : ImuGrade
    width : int
        Wrap long lines at this many columns.

    Returns
    -------
    str
    """
    from covtool.io.imu_grade import ACCEL_KEYS, GYRO_KEYS

    out = [f"IMU grade {g.name}", _wrap(g.description, width, "  "), f"  file: {g.path}"]
    if g.rate is not None:
        out.append(f"  rate: {_ds(g.rate)} Hz")
    out.append("")
    rows = []
    for sensor, keys, vals in (("gyro", GYRO_KEYS, g.gyro), ("accel", ACCEL_KEYS, g.accel)):
        written = g.decl.get(sensor, {})
        for key, (dim, _) in keys.items():
            if key not in vals:
                continue
            v = written.get(key)
            si = vals[key]
            if len(set(si)) == 1:               # one value for every axis
                shown = str(v[0]) if isinstance(v, list) else str(v)
                rows.append([sensor, key, shown, _si(si[0]) + (f" (all {len(si)})" if len(si) > 1 else ""),
                             _si_unit(dim)])
                continue
            labels = ("x", "y", "z") if len(si) == 3 else tuple(f"[{k + 1}]" for k in range(len(si)))
            for k, (lab, x) in enumerate(zip(labels, si)):
                shown = str(v[k]) if isinstance(v, list) else str(v)
                rows.append([sensor if k == 0 else "", f"{key} {lab}", shown, _si(x), _si_unit(dim)])
    out += _table(rows, ["sensor", "parameter", "as written", "SI", "SI unit"]).splitlines()
    arw = g.gyro.get("angle_random_walk", (0.0,))[0]
    vrw = g.accel.get("velocity_random_walk", (0.0,))[0]
    out += [""] + _noise_lines(arw, vrw, width)
    m = g.to_model()
    out += ["", f"as an error-state model: {m.n} states, the navigation block and "
                f"{len(m.block_names()) - 1} sensor blocks"]
    if g.sources:
        out += ["", "sources:"] + [_wrap(f"{k}: {v}", width, "  ") for k, v in g.sources.items()]
    return "\n".join(out) + "\n"


def describe(entry: Entry, width: int = 100) -> str:
    """The text ``covtool show`` prints for one library entry."""
    if entry.kind == "truth model":
        return describe_truth(entry.obj, width)
    if entry.kind == "filter":
        return describe_filter(entry.obj, entry.truth, entry.raw, width)
    return describe_grade(entry.obj, width)
