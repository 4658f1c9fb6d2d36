"""Command-line interface: parse arguments, call the library, write results.

``covtool run STUDY``, ``covtool models``, ``covtool show NAME`` and
``covtool dualnav MAIN.csv KIMU.csv [--study S] --out DIR`` (seed 001,
method II, on two recorded logs; the logs are CSV files with the columns of
:data:`covtool.io.imu_log.LOG_COLUMNS` from the start of the alignment).

Exit status: 0; 2 for a mistake in a file or an argument (one line
``covtool: error: <file>: <field>: <problem>``); 70 for an internal error
(a bug: one line with the exception type; ``COVTOOL_DEBUG=1`` shows the
traceback); 128 + the signal number after SIGINT (130), SIGTERM (143) or
a closed output pipe (141, ``covtool show sdins58 | head``).
"""

from __future__ import annotations

import argparse
import gc
import os
from pathlib import Path
import re
import signal
import sys
import threading
import time
import warnings

from covtool.errors import CovtoolError, CovtoolWarning, InputError


#: exit status of an internal error (a bug), EX_SOFTWARE of sysexits.h
EXIT_BUG = 70
#: exit status of a mistake in a file or an argument
EXIT_INPUT = 2

#: longer summaries are abbreviated on the console (the files hold every row)
MAX_SUMMARY_ROWS = 40


def _output_dir(args) -> Path:
    """``--out`` (or ``out/<study stem>``), checked before any computation."""
    from covtool.io.atomic import check_output_dir

    if args.out:
        return check_output_dir(args.out, "--out")
    return check_output_dir(Path("out") / Path(args.study).stem, "default output directory (--out)")


def _refuse_unused_options(args) -> None:
    """One line, before any worker starts, when the study's kind cannot use an option given."""
    import importlib
    import inspect

    from covtool.studies import load_study, RUNNERS

    decl, path = load_study(args.study)
    study = decl.get("study")
    kind = study.get("kind") if isinstance(study, dict) else None
    if not isinstance(kind, str) or kind not in RUNNERS:
        return                                   # run_study names the problem
    accepts = inspect.signature(importlib.import_module(RUNNERS[kind]).run).parameters
    asked = [opt for opt, param, on in (("--workers", "backend", args.workers is not None),
                                        ("--scheduler", "backend", args.scheduler is not None),
                                        ("--resume", "resume", args.resume)) if on and param not in accepts]
    if asked:
        can = ", ".join(k for k in sorted(RUNNERS) if "backend" in inspect.signature(
            importlib.import_module(RUNNERS[k]).run).parameters)
        raise InputError(f"{path}: [study] kind", f"{kind!r} runs in one process in one piece; it takes no "
                         f"{' or '.join(asked)} (kinds that do: {can})")


def _progress(args) -> bool:
    from covtool.progress import wanted

    return wanted(quiet=args.quiet, force=getattr(args, "progress", False))


def _cmd_run(args) -> int:
    t0 = time.perf_counter()
    out = _output_dir(args)
    _refuse_unused_options(args)
    args.store_dir = out / "cases"                        # named in the interrupt message
    from covtool.io.lock import DirLock

    # one run at a time per output directory: outputs and the result store are written by one process
    with DirLock(out, command=f"covtool run {args.study}"):
        # a figure server prepares matplotlib on the other core while the study computes (stopped with
        # SIGTERM at the end, or at once if the study fails)
        server = None if args.no_figures else _figure_server()
        try:
            result, files = _run_and_write(args, out, server)
        finally:
            if server is not None:
                server.close()
    dt = time.perf_counter() - t0
    if not args.quiet:
        from covtool.io.console import console_table, console_width, KEY_COLUMNS

        width = console_width()
        print(console_table(result.summary, width=width, max_rows=MAX_SUMMARY_ROWS,
                            file_hint=str(out / "summary.csv"), prefer=KEY_COLUMNS.get(result.kind, ())))
        if len(result.summary) > MAX_SUMMARY_ROWS and "pivot_cep" in result.tables:
            print("\n" + console_table(result.tables["pivot_cep"], width=width, file_hint=str(out)))
        print(f"\nwrote {len(files)} files to {out}/ in {dt:.1f} s")
    return 0


def _figure_server():
    """A :class:`covtool.io.figure_server.FigureServer`, or None where none can run."""
    from covtool.io.figure_server import FigureServer

    return FigureServer.start()


def _run_and_write(args, out, server):
    """Run the study and write its outputs (inside the output lock); ``(result, files)``."""
    from covtool.studies import run_study

    backend = None
    try:
        if args.workers is not None or args.scheduler is not None:
            from covtool.parallel import make_backend

            backend = make_backend(workers=args.workers, scheduler=args.scheduler)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", CovtoolWarning)
            result = run_study(args.study, progress=_progress(args), backend=backend, store=out / "cases",
                               resume=args.resume)
    except BaseException:
        if backend is not None:
            backend.abort()                          # never wait for running chunks on an error
        raise
    if backend is not None:
        backend.close()
    for w in caught:      # one line each (validity, flagged cases); other warnings as Python shows them
        if issubclass(w.category, CovtoolWarning):
            print(f"covtool: warning: {_one_line(w.message)}", file=sys.stderr)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return result, _write_outputs(result, out, args, server)


def _write_outputs(result, out, args, server=None) -> list:
    """:func:`covtool.io.writers.write_outputs` of a command's result, the result frozen out of the collector.

    While the outputs are written, the heap (the result and everything
    imported) is frozen out of Python's cyclic collector (``gc.freeze``):
    the collections that the writers' many small objects set off scan those
    objects alone, not the whole heap (0.06-0.12 s each, two or three per
    flagship run).  Unfrozen after, so that an in-process caller (the
    tests) collects as before; a caller that froze objects itself is left
    as it was (nothing frozen or unfrozen here).
    """
    from covtool.io.writers import write_outputs

    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        return write_outputs(result, out, figures=not args.no_figures, server=server)
    finally:
        if freeze:
            gc.unfreeze()


def _cmd_models(args) -> int:
    from covtool.io.console import console_table, console_width
    from covtool.io.library import default_model_dir, list_models

    d = Path(args.dir) if args.dir else default_model_dir()
    if not d.is_dir():
        raise InputError(f"--dir {str(d)!r}" if args.dir else f"$COVTOOL_MODELS {str(d)!r}",
                         "is not a directory (a model library holds *.toml, filters/ and imu/)")
    df = list_models(d)
    width = console_width()
    print(f"model library: {d}" + ("" if args.dir or os.environ.get("COVTOOL_MODELS") else
                                   "  (set $COVTOOL_MODELS or --dir for another)"))
    groups = [("truth models", df[df["kind"] == "truth model"])]
    for file, g in df[df["kind"] == "filter"].groupby("file", sort=False):
        rel = os.path.relpath(file, d)
        truths = sorted(set(g["truth"]) - {""})
        groups.append((f"filters in {rel}" + (f" (projections of {', '.join(truths)})" if truths else ""), g))
    groups.append(("IMU grades", df[df["kind"] == "IMU grade"]))
    for title, g in groups:
        cols = ["name", "states", "base", "description"] if g["base"].astype(bool).any() else \
            ["name", "states", "description"]
        print(f"\n{title}:")
        if not len(g):
            print("  (none)")
            continue
        text = console_table(g[cols], width=width - 2, max_text=width, stretch="description", fold_constant=False)
        print("\n".join("  " + ln for ln in text.splitlines()))
    print("\ncovtool show NAME prints one of them (values in datasheet units and SI).")
    return 0


def _cmd_show(args) -> int:
    from covtool.io.library import describe, lookup

    if args.dir and not Path(args.dir).is_dir():
        raise InputError(f"--dir {args.dir!r}", "is not a directory (a model library holds *.toml, filters/ "
                         "and imu/)")
    entries = lookup(args.model, args.dir)
    if args.markdown:
        from covtool.io.library import markdown_table

        truths = [e for e in entries if e.kind == "truth model"]
        if not truths:
            raise InputError(f"--markdown {args.model!r}", f"is a {entries[0].kind}; --markdown prints a truth "
                             "model's state table")
        print(markdown_table(truths[0].obj), end="")
        return 0
    from covtool.io.console import console_width

    width = console_width()
    if len(entries) > 1:
        import textwrap

        where = "; ".join(f"{e.kind} in {e.path}" for e in entries)
        print(textwrap.fill(f"{args.model}: {len(entries)} entries of that name ({where}); each is shown below. "
                            "A path selects one file.", width=width, break_long_words=False,
                            break_on_hyphens=False) + "\n")
    print(("\n" + "=" * min(width, 100) + "\n\n").join(describe(e, width=min(width, 100)) for e in entries), end="")
    return 0


def _cmd_new(args) -> int:
    from covtool.studies.reference import new_study

    sys.stdout.write(new_study(args.kind))
    return 0


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive integer")
    return n


class _Parser(argparse.ArgumentParser):
    """argparse with covtool's one-line error (no usage block), exit status 2."""

    def error(self, message):
        self.exit(EXIT_INPUT, f"covtool: error: {self.prog}: {_one_line(message)} (see '{self.prog} --help')\n")


def _version() -> str:
    """``covtool X.Y.Z from <package folder> (Python X.Y.Z)``, the version from the package metadata."""
    import importlib.metadata
    import platform

    import covtool

    try:
        v = importlib.metadata.version("covtool")
    except importlib.metadata.PackageNotFoundError:     # a source checkout on PYTHONPATH, never installed
        v = f"{covtool.__version__} (not installed)"
    if v.split()[0] != covtool.__version__:             # metadata of another installed copy
        v = f"{covtool.__version__} (the installed distribution says {v})"
    return f"covtool {v} from {Path(covtool.__file__).parent} (Python {platform.python_version()})"


class _VersionAction(argparse.Action):
    """``--version``: one unwrapped line on stdout, exit 0."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(_version())
        parser.exit()


_MODELS_ENV = ("The model library is $COVTOOL_MODELS if set, else the one installed with covtool "
               "(the repository's models/): truth models *.toml, filters filters/*.toml, IMU grades imu/*.toml. "
               "A study names them by library name or by a path relative to the study file.")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="covtool", description=__doc__.split("\n\n")[0],
                epilog="Run 'covtool COMMAND --help' for a command's options. " + _MODELS_ENV)
    p.add_argument("--version", action=_VersionAction, help="print covtool's version and where it runs from")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser("run", help="run a study file and write its outputs",
                       description="Run a study file (studies/*.toml) and write its tables, workbook, figures and "
                                   "resolved_study.toml to --out.")
    r.add_argument("study", help="study file, e.g. studies/zupt_filter_order.toml")
    r.add_argument("--out", help="output directory (default out/<study name>), checked before anything runs")
    r.add_argument("--quiet", action="store_true",
                   help="no progress bars and no summary (warnings and errors still print)")
    r.add_argument("--progress", action="store_true",
                   help="show progress bars even when stderr is not a terminal (default: only on a terminal)")
    r.add_argument("--no-figures", action="store_true", help="skip PNG figures")
    r.add_argument("-j", "--workers", "--jobs", dest="workers", type=_positive_int, metavar="N",
                   help="run chunks of cases in N local processes (or N workers of '--scheduler local'); "
                        "study kinds trade_grid and monte_carlo")
    r.add_argument("--scheduler", metavar="ADDRESS",
                   help="run chunks on a Dask cluster: a scheduler address (tcp://host:8786) or 'local'")
    r.add_argument("--resume", action="store_true",
                   help="reuse the cases an interrupted run stored in OUT/cases/ and compute only the rest")
    r.set_defaults(func=_cmd_run)
    m = sub.add_parser("models", help="list the model library: truth models, filters, IMU grades",
                       description="List the truth models (state counts), the filters of every filter file (kept "
                                   "states, base filter) and the IMU grades. " + _MODELS_ENV)
    m.add_argument("--dir", default=None, help="model library folder (default: $COVTOOL_MODELS, else the installed "
                                                "library)")
    m.set_defaults(func=_cmd_models)
    s = sub.add_parser("show", help="show a truth model, filter or IMU grade",
                       description="Show a truth model (its states, noise densities and sources), a filter (kept "
                                   "states, options, P0) or an IMU grade (every value), by library name or file, "
                                   "in datasheet units and in SI at full precision. " + _MODELS_ENV)
    s.add_argument("model", metavar="NAME", help="library name (sdins58, B1, kimu) or path to a .toml file")
    s.add_argument("--dir", default=None, help="model library folder (default: $COVTOOL_MODELS, else the installed "
                                                "library)")
    s.add_argument("--markdown", action="store_true", help="print a truth model's state table as Markdown (docs/)")
    s.set_defaults(func=_cmd_show)
    from covtool.studies import KINDS as _KINDS
    n = sub.add_parser("new", help="print a commented starting study file of a kind (docs/study_files.md)")
    n.add_argument("kind", choices=_KINDS, metavar="KIND", help="study kind: " + ", ".join(_KINDS))
    n.set_defaults(func=_cmd_new)
    add_dualnav_parser(sub)
    return p


def _one_line(message) -> str:
    """A message on one line (an error or warning is one line on stderr)."""
    return re.sub(r"\s*\n\s*", "; ", str(message).strip())


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM received (raised in the main thread)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum, frame):
    """First SIGINT/SIGTERM: unwind (the ``finally`` blocks stop the workers).

    A second one while unwinding exits at once: the workers then die with
    this process (their watchdog, :class:`covtool.parallel.ProcessBackend`)
    and the store holds only whole chunks.
    """
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _on_second_signal)
    raise Interrupted(signum)


def _on_second_signal(signum, frame):
    print(f"covtool: {signal.Signals(signum).name} again; exiting at once", file=sys.stderr, flush=True)
    os._exit(128 + signum)


def _interrupt_message(args, signum: int) -> str:
    name = signal.Signals(signum).name
    store = getattr(args, "store_dir", None)
    if store is not None and Path(store).is_dir():
        return (f"covtool: interrupted by {name}; the chunks finished so far are kept in {store} "
                "(continue with --resume); earlier outputs are untouched")
    return f"covtool: interrupted by {name}; earlier outputs are untouched"


def _stdout_closed() -> bool:
    """True if stdout is a pipe whose reader has gone (``covtool show sdins58 | head``).

    The write end of such a pipe polls as an error (POLLERR).  stdout then
    goes to /dev/null, so that the interpreter's last flush stays quiet.
    """
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        closed = any(ev & select.POLLERR for _, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):       # no real stdout (captured, closed)
        return False
    if closed:
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, fd)
            os.close(devnull)
        except OSError:
            pass
    return closed


def _ordinary_pages() -> None:
    """Keep numpy from advising huge pages for this process, unless the user chose.

    numpy advises the kernel to back every array of 4 MB or more with
    transparent huge pages (``madvise``).  Where the kernel must compact
    memory to find them (``defrag = madvise``, common on virtual machines),
    every first touch of such an array stalls: on the 2-core benchmark
    machine a fresh (1800, 58, 58) stack took 110 ms to fill against 17 ms
    on ordinary pages, and the flagship study 0.6 s more wall time (0.7 s
    more system time).  Done only before numpy is imported (the command
    line, not a library user's process); a ``NUMPY_MADVISE_HUGEPAGE`` the
    user set is respected.  Worker processes inherit the setting.
    """
    if "numpy" not in sys.modules:
        os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


#: glibc's mallopt parameters and the values the command line sets (:func:`_keep_freed_memory`)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: blocks below this are served from the heap, not mapped afresh (glibc's largest on 64-bit) [bytes]
MMAP_THRESHOLD = 32 * 2**20
#: free memory at the heap's top is returned to the system only beyond this [bytes]
TRIM_THRESHOLD = 2**30
#: the environment variables by which a user tunes glibc's allocator (then it is left alone)
_MALLOC_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")


def _keep_freed_memory() -> bool:
    """Keep glibc from handing freed array memory back to the system at once.

    By default glibc maps every block above a threshold that it adjusts
    between 128 kB and 32 MB, and gives a freed heap top back to the system
    when it exceeds twice that threshold.  A study allocates and frees
    stacks of 58×58 matrices of 1-50 MB all the time, so the same memory is
    mapped, returned and faulted in again, page by page.  With a fixed
    threshold of :data:`MMAP_THRESHOLD` and a trim threshold of
    :data:`TRIM_THRESHOLD`, freed memory is reused.  Measured on the 2-core
    machine in alternating CLI runs (page faults, system time): the flagship
    450-500 k and 1.5-1.6 s before, 350 k and 1.15-1.4 s after; the error
    budget 310 k, 1.0-1.2 s and 224 k, 0.8-0.9 s; the Monte Carlo 1.3 M,
    4.3-4.5 s and 0.9 M, 3.4-3.6 s.  Peak RSS: +1 to +3 %.

    Done by the command line only (a process-wide setting is not a
    library's to make), on glibc only, and not when the user set one of
    :data:`_MALLOC_ENV` or a ``glibc.malloc`` tunable.  Forked workers
    inherit the setting; spawned ones (the Monte Carlo's local processes)
    get it from the same environment variables, which are set here.

    Returns
    -------
    bool
        Whether both settings were made.
    """
    if any(k in os.environ for k in _MALLOC_ENV) or "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    import platform

    if platform.libc_ver()[0] != "glibc":
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    if not (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)):
        return False
    os.environ["MALLOC_MMAP_THRESHOLD_"] = str(MMAP_THRESHOLD)
    os.environ["MALLOC_TRIM_THRESHOLD_"] = str(TRIM_THRESHOLD)
    return True


def main(argv=None) -> int:
    """Entry point of the ``covtool`` command.

    Returns
    -------
    int
        The exit status: 0; 2 for a mistake in a file or an argument
        (one line ``covtool: error: ...`` on stderr); 70 for an internal
        error, a bug (one line naming the exception type, the traceback
        with ``COVTOOL_DEBUG=1``); 128 + the signal number after SIGINT
        (130), SIGTERM (143) or a closed stdout pipe (141).  Argument
        errors raise ``SystemExit(2)`` after their one line, as argparse
        does.

    Notes
    -----
    Run as the command (``argv`` None) it also tunes glibc's allocator
    (:func:`_keep_freed_memory`); a caller of ``main(argv)`` in its own
    process keeps its allocator as it is.
    """
    _ordinary_pages()
    if argv is None:                            # the command itself, not a caller of main() in its own process
        _keep_freed_memory()
    args = build_parser().parse_args(argv)
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            handlers[s] = signal.signal(s, _on_signal)
    try:
        status = args.func(args)
        sys.stdout.flush()                      # a closed pipe is found here, not at interpreter exit
        return status
    except CovtoolError as exc:
        print(f"covtool: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        print(_interrupt_message(args, signum), file=sys.stderr)
        return 128 + signum
    except BrokenPipeError as exc:
        if _stdout_closed():
            return 128 + signal.SIGPIPE
        return _internal_error(exc)
    except OSError as exc:               # the system refused a file operation: named, not a bug
        if os.environ.get("COVTOOL_DEBUG") == "1":
            raise
        name = f"{exc.filename}: " if exc.filename else ""
        print(f"covtool: error: {name}{exc.strerror or _one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except MemoryError:
        print("covtool: error: out of memory (shorten the study or lower [resources] memory_limit)", file=sys.stderr)
        return EXIT_INPUT
    except Exception as exc:                 # noqa: BLE001  (everything else is a bug)
        return _internal_error(exc)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)


def _internal_error(exc: BaseException) -> int:
    """One line for a bug, or the traceback with ``COVTOOL_DEBUG=1``."""
    if os.environ.get("COVTOOL_DEBUG") == "1":
        raise exc
    print(f"covtool: internal error (a bug in covtool, please report it with the command): "
          f"{type(exc).__name__}: {_one_line(exc)} (COVTOOL_DEBUG=1 shows the traceback)", file=sys.stderr)
    return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())


def default_study() -> Path:
    """The study file used when ``--study`` is not given.

    ``$COVTOOL_DUALNAV_STUDY``, else ``./studies/dual_imu_flight.toml``,
    else the one of the source checkout covtool runs from.

    Raises
    ------
    InputError
        None of them exists (an installed covtool ships no study files).
    """
    env = os.environ.get("COVTOOL_DUALNAV_STUDY")
    if env:
        return Path(env)
    for c in (Path.cwd() / "studies" / "dual_imu_flight.toml",
              Path(__file__).resolve().parents[1] / "studies" / "dual_imu_flight.toml"):
        if c.is_file():
            return c
    raise InputError("--study", "not given, and there is no $COVTOOL_DUALNAV_STUDY nor ./studies/dual_imu_flight.toml;"
                     " name a dual_imu study file (the repository's studies/dual_imu_flight.toml is one)")


def cmd_dualnav(args) -> int:
    """Run the comparison of two logs and write its outputs."""
    from covtool.errors import StudyFileError
    from covtool.io.imu_log import load_imu_log
    from covtool.studies import load_study, one_blas_thread
    from covtool.studies.dual_imu import compare_logs

    from covtool.io.atomic import check_output_dir

    t0 = time.perf_counter()
    out = check_output_dir(args.out, "--out")
    study = Path(args.study) if args.study else default_study()
    decl, path = load_study(study)
    kind = decl.get("study", {}).get("kind") if isinstance(decl.get("study"), dict) else None
    if kind != "dual_imu":
        raise StudyFileError(f"{path}: [study] kind", f"{kind!r}: covtool dualnav needs a 'dual_imu' study")
    main = load_imu_log(args.main)
    kimu = load_imu_log(args.kimu)
    from covtool.io.lock import DirLock

    # one run at a time per output directory, as for `covtool run`
    with DirLock(out, command=f"covtool dualnav {args.main} {args.kimu}"):
        with one_blas_thread():
            result = compare_logs(main, kimu, decl, path=path, progress=_progress(args))
        files = _write_outputs(result, out, args)
    if not args.quiet:
        from covtool.io.console import console_table, console_width

        width = console_width()
        print(console_table(result.summary, width=width, file_hint=str(out / "summary.csv")))
        gaps = result.tables["gaps"]
        if len(gaps):
            cols = ["imu", "after [s]", "before [s]", "samples bridged", "policy",
                    "predicted att x [urad]", "predicted att y [urad]", "predicted att z [urad]",
                    "predicted vel x [mm/s]", "predicted vel y [mm/s]", "predicted vel z [mm/s]"]
            print("\nbridged gaps:")
            print(console_table(gaps[cols], width=width, file_hint=str(out)))
        print(f"\nwrote {len(files)} files to {out}/ in {time.perf_counter() - t0:.1f} s")
    return 0


def add_dualnav_parser(subparsers):
    """Add the ``dualnav`` sub-command to a ``covtool`` sub-parser set.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The result of ``parser.add_subparsers(...)``.

    Returns
    -------
    argparse.ArgumentParser
        The new sub-parser (its ``func`` is :func:`cmd_dualnav`).
    """
    p = subparsers.add_parser(
        "dualnav", help="compare a main-IMU and a KIMU log by dual navigation (seed 001 method II)",
        description="Align, navigate and compare two recorded IMU logs; predict the difference envelope, flag "
                    "the intervals that leave it, estimate a KIMU g-sensitive gyro scale factor, and report "
                    "every bridged telemetry gap.")
    p.add_argument("main", help="main IMU log: CSV with 't [s]', 'dtheta_x [rad]' … 'dv_z [m/s]'")
    p.add_argument("kimu", help="KIMU log, same columns, at the study's rate ratio")
    p.add_argument("--study", default=None,
                   help="dual_imu study file (default: studies/dual_imu_flight.toml)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars and no summary (warnings and errors still print)")
    p.add_argument("--progress", action="store_true",
                   help="show progress bars even when stderr is not a terminal (default: only on a terminal)")
    p.add_argument("--no-figures", action="store_true", help="skip PNG figures")
    p.set_defaults(func=cmd_dualnav)
    return p
