"""The study-file reference and ``covtool new``, generated from the typed declarations.

:func:`study_files_markdown` writes ``docs/study_files.md`` (every study kind,
section, key, type or unit dimension, default, range and meaning, a worked
example per kind, the filter-file and model-file keys); :func:`new_study`
returns the commented starting file of one kind.  Regenerate the reference
with ``python -m covtool.studies.reference > docs/study_files.md``.
"""

from __future__ import annotations

import textwrap

import tomli_w

from covtool.studies.config import KINDS, Kind, Section, StudyConfig

__all__ = ["study_files_markdown", "new_study", "FILTER_FILE_KEYS", "MODEL_FILE_KEYS", "section_keys"]

#: ``[[filter]]`` keys of a filter file (checked against :data:`covtool.io.filters._FILTER_KEYS` by the tests)
FILTER_FILE_KEYS = {
    "name": "The filter's name (a case label, a column header): letters, digits, `_`, `-`.",
    "truth": "The truth model it projects: a library name, or a path relative to the filter file "
             "(default: the study's).",
    "description": "One line for the tables.",
    "source": "Where the filter comes from (e.g. 'seed 002, Table 1').",
    "keep": "Truth states or blocks kept (\"all\" for every state); must hold the 10 navigation states.",
    "base": "Start from another filter (of any filter file the study names): its kept states, options and P0.",
    "add": "Truth states or blocks kept in addition (to the base's or to `keep`).",
    "drop": "Truth states or blocks removed (from the base's or from `keep`).",
    "decouple_vertical": "true: the vertical channel decoupled from the horizontal (filter B2). Default false.",
    "coriolis": "false: no Coriolis terms (filter B3). Default true.",
    "equivalent_noise": "Equivalent white noise for the dropped states, seed 002 eq (11)-(13): \"interval\" "
                        "(default; true and \"eq11-13\" mean the same), \"pointwise\", \"matched\" or false.",
    "discretization": "\"taylor\" (default, eq (6b)-(6d)) or \"van_loan\".",
    "taylor_order": "Terms of eq (6b), 2..40 (default: until converged); taylor only.",
    "update": "\"joseph\" (default) or \"standard\" (eq (8)).",
    "zupt_sigma": "The ZUPT 1σ the filter assumes (> 0; default: the study's [zupt] sigma).",
    "P0": "Table state = 1σ: the initial 1σ of kept states (default: the truth model's).",
}

#: keys of a model file (``models/*.toml``), by table
MODEL_FILE_KEYS = {
    "[model]": {
        "name": "The model's name (`covtool show NAME`).",
        "description": "One line.",
        "source": "Where the values come from.",
        "base": "Another model file this one starts from (its [[block]]s), then `override`.",
    },
    "(top level)": {
        "model": "The [model] table.",
        "block": "The [[block]] tables: the navigation block, then sensor and environment blocks.",
        "correlation": "[[correlation]] tables: `states = [a, b]`, `rho` in (-1, 1).",
        "override": "With `base`: per-state changes, as a study's [truth.override.<state>].",
    },
    "[[block]] (kind = \"navigation\")": {
        "kind": "\"navigation\": the 10 states of seed 002 eq (14).",
        "name": "Block name (default: the kind).",
        "position_sigma": "Initial 1σ of latitude, longitude, height (one value or three).",
        "velocity_sigma": "Initial 1σ of the N, E, D velocity.",
        "quaternion_sigma": "Initial 1σ of the four attitude-quaternion components.",
        "angle_random_walk": "Gyro ARW ('0.002 deg/sqrt(h)').",
        "velocity_random_walk": "Accelerometer VRW ('5 ug/sqrt(Hz)').",
        "source": "Where the values come from.",
    },
    "[[block]] (sensor and environment blocks)": {
        "kind": "A block kind of covtool.lincov.model.blocks.BLOCK_KINDS (accel_bias, gyro_bias, ...).",
        "name": "Block name (default: the kind's).",
        "names": "State names (default: the block name with _x, _y, _z, ...).",
        "sigma": "1σ per state (one value for all), in datasheet units.",
        "unit": "Display unit (default: the unit written in sigma).",
        "process": "constant, random_walk, markov or markov_distance.",
        "tau": "markov: correlation time.",
        "distance": "markov_distance: correlation distance.",
        "rw": "random_walk: driving root-PSD.",
        "source": "Where the values come from.",
        "board": "A/D-reset board block: table of `sf`, `n_t`, `n_e_ratio` (seed 000).",
    },
    "[block.board]": {
        "sf": "Board scale factor.",
        "n_t": "Nominal counts N_t.",
        "n_e_ratio": "Error counts over N_t.",
    },
}


def _kind(f) -> Kind | None:
    k = next((m for m in f.metadata if isinstance(m, Kind)), None)
    if k is None:
        for arg in getattr(f.annotation, "__args__", ()):
            k = next((m for m in getattr(arg, "__metadata__", ()) if isinstance(m, Kind)), k)
    return k


def _section_of(f):
    ann = f.annotation
    if isinstance(ann, type) and issubclass(ann, Section):
        return ann
    return None


def section_keys(cls: type[Section]) -> list[str]:
    """The keys of a section, as written in a study file."""
    return [f.alias or n for n, f in cls.model_fields.items()]


def _default(f) -> str:
    if f.is_required():
        return "required"
    d = f.get_default(call_default_factory=True)
    if d is None:
        return "–"
    if isinstance(d, dict) and not d:
        return "{}"
    return f"`{_toml(d)}`"


def _sections_of_kind(cls: type[StudyConfig]) -> list[tuple[str, type[Section] | None]]:
    out = []
    for key, f in cls.model_fields.items():
        out.append((key, _section_of(f)))
    return out


def _all_sections() -> list[type[Section]]:
    """Every section class, in the order the kinds use them (nested tables after their parent)."""
    from covtool.studies import config as c

    seen: list[type[Section]] = []

    def visit(s):
        if s is None or s in seen:
            return
        seen.append(s)
        for v in s.nested.values():
            visit(v[0] if isinstance(v, list) else v)

    for cls in KINDS.values():
        for key, s in _sections_of_kind(cls):
            if key == "trajectory" and s is None:
                for t in c.TRAJECTORIES:
                    visit(t)
            visit(cls.lists.get(key, s))
    return seen


def _anchor(s: type[Section]) -> str:
    return s.__name__.lower()


def _table(s: type[Section]) -> list[str]:
    lines = ["| key | type / unit | default | range | meaning |", "|---|---|---|---|---|"]
    for n, f in s.model_fields.items():
        k = _kind(f)
        lines.append(f"| `{f.alias or n}` | {k.text if k else '–'} | {_default(f)} | "
                     f"{(k.range_text if k else '') or '–'} | {(f.description or '').replace('|', '/')} |")
    return lines


def study_files_markdown() -> str:
    """The study-file reference (``docs/study_files.md``) as Markdown."""
    from covtool.studies import config as c

    out = [
        "# Study files",
        "",
        "<!-- generated by `python -m covtool.studies.reference > docs/study_files.md` from the declarations "
        "in covtool/studies/config/; do not edit by hand (tests/test_study_reference.py compares) -->",
        "",
        "A study file is TOML: one table per section. Quantities are strings in datasheet units "
        "(`\"5 min\"`, `\"0.01 ft/s\"`, `\"20 ug\"`, `\"0.002 deg/sqrt(h)\"`; `g` is standard gravity, so "
        "`ug` is micro-g); covtool works in SI inside. A path resolves against the folder of the file "
        "that names it, never the current directory. Every mistake is refused before any computation "
        "with one line naming the file, the section, the key and the problem. `covtool new KIND` prints "
        "the commented starting file of a kind (the worked examples below).",
        "",
        "## Study kinds",
        "",
        "| kind | what it computes | sections |",
        "|---|---|---|",
    ]
    for kind, cls in KINDS.items():
        secs = ", ".join(f"[{k}]" for k, _ in _sections_of_kind(cls))
        out.append(f"| `{kind}` | {cls.kind_doc} | {secs} |")
    out += ["", "## Sections", ""]
    for s in _all_sections():
        head = f"[{s.name}]"
        head = head[:-1] if head.startswith("[[") else head     # an array of tables: "[[grade]] (aided)"
        out += [f"### {head}", "", s.doc, ""] + _table(s) + [""]
    out += ["## Truth overrides and the filters", "",
            "`[truth.override.<name>]` names a state (`gyro_bias_z`) or a block (`gyro_bias`: every state of "
            "the block). A state's own table wins over its block's, key by key. The keys (`sigma`, `tau`, "
            "`distance`, `rw`) are in the state's datasheet units; `tau`, `distance` and `rw` apply only to "
            "states of the process that uses them (`markov`, `markov_distance`, `random_walk`).", "",
            "`[truth] override_filters` (default `false`) says whether the overrides also reach the filters. "
            "The truth model is the real IMU; a filter file is a design. By default an override changes the "
            "truth only: the filters keep the model file's P0, kept-state dynamics and equivalent noise, so "
            "the study shows how the designed filters fare when the sensors depart from their design values "
            "(what an override is usually asked for). `true` builds the filters from the overridden truth (the "
            "designer knows the actual sensors); the trade grid's IMU grades work this way.", ""]
    out += ["## Filter files", "",
            "A filter file (`models/filters/*.toml`, or your own named by `[filters] file`) holds "
            "`[[filter]]` tables: reduced filters declared as projections of the truth model by state name "
            "(seed 002, Table 1). `[filters] file` may list several files; a filter's `base` may name a filter "
            "of any of them (declared before or after), and `add` keeps extra truth states.", "",
            "| key | meaning |", "|---|---|"]
    out += [f"| `{k}` | {v} |" for k, v in FILTER_FILE_KEYS.items()]
    out += ["", "## Model files", "",
            "A truth model file (`models/*.toml`; `covtool models` lists the library, `covtool show NAME` "
            "shows one).", ""]
    for tab, keys in MODEL_FILE_KEYS.items():
        out += [f"### {tab}", "", "| key | meaning |", "|---|---|"]
        out += [f"| `{k}` | {v} |" for k, v in keys.items()] + [""]
    out += ["## Worked examples", ""]
    for kind in KINDS:
        out += [f"### {kind}", "", "```toml", new_study(kind).rstrip(), "```", ""]
    del c
    return "\n".join(out).rstrip() + "\n"


# ---------------------------------------------------------------------------
# covtool new
# ---------------------------------------------------------------------------

#: what ``covtool new`` writes for a kind beyond the declarations' defaults and examples: a short,
#: runnable first study (each value is a key of the file, so the user sees what to lengthen)
STARTERS = {
    "pure_ins": {"study": {"duration": "10 min"}},
    "zupt_filter_order": {"study": {"duration": "30 min"}, "filters": {"cases": ["A", "B1", "C", "D"]}},
    "error_budget": {"study": {"duration": "6 min"}, "filters": {"cases": ["pure_ins", "B1"]}},
    "zupt_sensitivity": {"study": {"duration": "6 min"}, "filters": {"cases": ["B1", "D"]},
                         "sweep": {"scales": {"from": 0.1, "to": 10, "per_decade": 2}, "fit_degree": 2},
                         "cost": {"measure": False}},
    "monte_carlo": {"study": {"duration": "6 min", "dt": "1 s"}, "filters": {"cases": ["D"]},
                    "monte_carlo": {"runs": 4, "runs_per_chunk": 4, "imu_rate": "20 Hz", "samples_per_step": 4}},
    "magnitude_sweep": {"study": {"duration": "6 min"}, "filters": {"cases": ["A", "D"]},
                        "sweep": {"values": ["5 arcsec", "30 arcsec"],
                                  "group": [{"name": "gyro misalignment", "states": ["gyro_mis"]}]}},
    "trade_grid": {"study": {"duration": "10 min"}, "filters": {"cases": ["D"]},
                   "grid": {"zupt_interval": ["5 min"]},
                   "grade": [{"name": "navigation", "scale": 1}, {"name": "tactical", "scale": 10}]},
    "dual_imu": {"simulation": {"runs": 2, "fault_runs": 0, "batch": 2}},
    "aided": {"study": {"duration": "10 min"},
              "filters": {"cases": ["B1"], "pure_ins": True, "ewn_interval": "1 s",
                          "variant": [{"name": "B1 no GNSS errors", "base": "B1",
                                       "drop": ["gnss_N", "gnss_E", "gnss_D"]}]},
              "measurement": [{"name": "gnss", "kind": "gnss_position", "sigma": ["1 m", "1 m", "2 m"],
                               "lever_arm": ["0.5 m", "0 m", "-1.5 m"],
                               "schedule": {"period": "1 s", "start": "1 s", "outages": [["4 min", "6 min"]]},
                               "errors": {"N": {"sigma": "1.5 m", "process": "markov", "tau": "10 min"},
                                          "E": {"sigma": "1.5 m", "process": "markov", "tau": "10 min"},
                                          "D": {"sigma": "3 m", "process": "markov", "tau": "10 min"}}},
                              {"name": "zupt", "kind": "zupt", "sigma": "0.01 ft/s",
                               "schedule": {"period": "5 min", "start": "5 min", "when": "stationary"}}],
              "grade": [{"name": "navigation", "scale": 1.0}]},
    "ad_reset": {"study": {"name": "ad_reset"}, "sweeps": {"points": 10},
                 "alignment": {"coarse": {"k": 4.0, "kb_g": 4.0}, "fine": {"k": 1.0, "kb_g": 0.25}}},
}


def _toml(value) -> str:
    """One TOML value on one line (inline arrays and tables)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return tomli_w.dumps({"x": value})[4:].strip()
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    raise TypeError(type(value).__name__)


def _value_line(key, value) -> str:
    return f"{key} = {_toml(value)}"


def _comment(text: str, indent: str = "") -> list[str]:
    return textwrap.wrap(text, 100, initial_indent=indent + "# ", subsequent_indent=indent + "# ")


def _write_section(lines, header: str, s: type[Section], given: dict, skip=()):
    lines += ["", f"[{header}]"] + _comment(s.doc)
    nested_out = []
    for n, f in s.model_fields.items():
        key = f.alias or n
        if key in skip:
            continue
        sub = s.nested.get(key)
        if sub is not None and not isinstance(sub, list) and (isinstance(given.get(key), dict) or
                                                              (key not in given and f.is_required())):
            nested_out.append((key, sub, given.get(key, {})))
            continue
        if sub is not None and isinstance(sub, list) and isinstance(given.get(key), list):
            for item in given[key]:
                nested_out.append((key, sub[0], item))
            continue
        extra = f.json_schema_extra or {}
        if key in given:
            value, active = given[key], True
        elif "example" in extra:
            value, active = extra["example"], True
        elif f.is_required():
            continue
        else:
            d = f.get_default(call_default_factory=True)
            value, active = d, False
        k = _kind(f)
        desc = (f.description or "") + (f" [{k.text}]" if k else "")
        lines += _comment(desc)
        if value is None or (isinstance(value, dict) and not value):
            lines.append(f"# {key} = ...")
        else:
            line = _value_line(key, value)
            lines.append(line if active else f"# {line}")
    for key, sub, item in nested_out:
        if isinstance(s.nested[key], list):
            lines += ["", f"[[{header}.{key}]]"] + _comment(sub.doc)
            lines += [_value_line(k, v) for k, v in item.items()]
        else:
            _write_section(lines, f"{header}.{key}", sub, item)


def new_study(kind: str) -> str:
    """The commented starting file of a study kind (``covtool new KIND``).

    Every key of every section of the kind is written with its meaning:
    required keys and the starter values (a short first run) active, the
    others commented out at their defaults.

    Raises
    ------
    InputError
        Unknown kind (the message lists the kinds).
    """
    from covtool.errors import InputError
    from covtool.studies import config as c

    if kind not in KINDS:
        raise InputError("covtool new", f"unknown study kind {kind!r} (one of: {', '.join(KINDS)})")
    cls = KINDS[kind]
    start = STARTERS.get(kind, {})
    article = "An" if kind[0] in "aeiou" else "A"
    lines = [f"# {article} {kind} study: {cls.kind_doc}", "# Generated by `covtool new " + kind + "`; the study-file "
             "reference is docs/study_files.md.", "# Run: covtool run this.toml --out out/" + kind]
    for key, f in cls.model_fields.items():
        s = _section_of(f)
        given = dict(start.get(key, {})) if isinstance(start.get(key, {}), dict) else {}
        if key == "study":
            given = {"kind": kind, **given}
        if key == "trajectory" and s is None:
            s = c.LandVehicle
            given = {"builtin": "land_vehicle", **given}
            if kind == "trade_grid":        # the grid sets the period, cycles and distance per interval
                _write_section(lines, key, s, given, skip=("period", "cycles", "distance"))
                continue
        if key in cls.lists:             # [[key]] tables: the starter's entries, inline values
            lines += [""] + _comment(f.description)
            for g in start.get(key, []):
                # a table of tables (a measurement's errors) as sub-tables, the rest inline
                subs = {k: v for k, v in g.items() if isinstance(v, dict) and v
                        and all(isinstance(x, dict) for x in v.values())}
                lines += [f"[[{key}]]"] + [_value_line(k, v) for k, v in g.items() if k not in subs]
                for k, v in subs.items():
                    for sub, item in v.items():
                        lines += [f"[{key}.{k}.{sub}]"] + [_value_line(a, b) for a, b in item.items()]
                lines += [""]
            continue
        if s is None:
            continue
        _write_section(lines, key, s, given)
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    import sys

    sys.stdout.write(study_files_markdown())
