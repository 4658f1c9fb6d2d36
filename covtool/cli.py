"""Command-line interface: parse arguments, call the library, write results.

``covtool run STUDY``, ``covtool models``, ``covtool show MODEL`` and
``covtool dualnav MAIN.csv KIMU.csv [--study S] --out DIR`` (seed 001,
method II, on two recorded logs; the logs are CSV files with the columns of
:data:`covtool.io.imu_log.LOG_COLUMNS` from the start of the alignment).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import signal
import sys
import threading
import time
import warnings

from covtool.errors import CovtoolError, CovtoolWarning


#: longer summaries are abbreviated on the console (the files hold every row)
MAX_SUMMARY_ROWS = 60


def _output_dir(args) -> Path:
    """``--out`` (or ``out/<study stem>``), checked before any computation."""
    from covtool.io.atomic import check_output_dir

    if args.out:
        return check_output_dir(args.out, "--out")
    return check_output_dir(Path("out") / Path(args.study).stem, "default output directory (--out)")


def _cmd_run(args) -> int:
    from covtool.io.writers import write_outputs
    from covtool.io.lock import DirLock
    from covtool.studies import run_study

    t0 = time.perf_counter()
    out = _output_dir(args)
    args.store_dir = out / "cases"                        # named in the interrupt message
    # one run at a time per output directory: outputs and the result store are written by one process
    with DirLock(out, command=f"covtool run {args.study}"):
        backend = None
        try:
            if args.workers is not None or args.scheduler is not None:
                from covtool.parallel import make_backend

                backend = make_backend(workers=args.workers, scheduler=args.scheduler)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", CovtoolWarning)
                result = run_study(args.study, progress=not args.quiet, backend=backend, store=out / "cases",
                                   resume=args.resume)
        except BaseException:
            if backend is not None:
                backend.abort()                          # never wait for running chunks on an error
            raise
        if backend is not None:
            backend.close()
        for w in caught:      # one line each (validity, flagged cases); other warnings as Python shows them
            if issubclass(w.category, CovtoolWarning):
                print(f"covtool: warning: {w.message}", file=sys.stderr)
            else:
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        files = write_outputs(result, out, figures=not args.no_figures)
    dt = time.perf_counter() - t0
    if not args.quiet:
        s = result.summary
        if len(s) <= MAX_SUMMARY_ROWS:
            print(s.to_string(index=False))
        else:
            print(s.head(10).to_string(index=False))
            print(f"... {len(s) - 10} more rows in {out / 'summary.csv'}")
            if "pivot_cep" in result.tables:
                print("\n" + result.tables["pivot_cep"].to_string(index=False))
        print(f"\nwrote {len(files)} files to {out}/ in {dt:.1f} s")
    return 0


def _cmd_models(args) -> int:
    from covtool.io.library import list_models

    df = list_models(args.dir)
    print(df.to_string(index=False))
    return 0


def _cmd_show(args) -> int:
    from covtool.io.library import load_model_by_name

    model = load_model_by_name(args.model, args.dir)
    if args.markdown:
        from covtool.io.library import markdown_table
        print(markdown_table(model), end="")
        return 0
    print(f"{model.name}: {model.n} states, {model.description} [{model.path}]\n")
    print(model.state_table().to_string(index=False))
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="covtool", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a study file and write its outputs")
    r.add_argument("study", help="studies/*.toml")
    r.add_argument("--out", help="output directory (default out/<study name>)")
    r.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    r.add_argument("--no-figures", action="store_true", help="skip PNG figures")
    r.add_argument("--workers", type=_positive_int, metavar="N",
                   help="run chunks of cases in N local processes (or N workers of '--scheduler local')")
    r.add_argument("--scheduler", metavar="ADDRESS",
                   help="run chunks on a Dask cluster: a scheduler address (tcp://host:8786) or 'local'")
    r.add_argument("--resume", action="store_true",
                   help="reuse the cases an interrupted run stored in OUT/cases/ and compute only the rest")
    r.set_defaults(func=_cmd_run)
    m = sub.add_parser("models", help="list the model library")
    m.add_argument("--dir", default=None, help="model directory (default: models/)")
    m.set_defaults(func=_cmd_models)
    s = sub.add_parser("show", help="print a model's state table")
    s.add_argument("model", help="model name or path to a .toml file")
    s.add_argument("--dir", default=None, help="model directory (default: models/)")
    s.add_argument("--markdown", action="store_true", help="print the table as Markdown (docs/)")
    s.set_defaults(func=_cmd_show)
    from covtool.studies import KINDS as _KINDS
    n = sub.add_parser("new", help="print a commented starting study file of a kind (docs/study_files.md)")
    n.add_argument("kind", choices=_KINDS, metavar="KIND", help="study kind: " + ", ".join(_KINDS))
    n.set_defaults(func=_cmd_new)
    add_dualnav_parser(sub)
    return p


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


def main(argv=None) -> int:
    """Entry point of the ``covtool`` command.

    Returns the exit status: 0, 2 for an input error, 128 + the signal
    number after SIGINT (130) or SIGTERM (143), with one line on stderr.
    """
    args = build_parser().parse_args(argv)
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            handlers[s] = signal.signal(s, _on_signal)
    try:
        return args.func(args)
    except CovtoolError as exc:
        print(f"covtool: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        print(_interrupt_message(args, signum), file=sys.stderr)
        return 128 + signum
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)


if __name__ == "__main__":
    sys.exit(main())


def default_study() -> Path:
    """The study file used when ``--study`` is not given.

    ``$COVTOOL_DUALNAV_STUDY``, else ``./studies/dual_imu_flight.toml``,
    else the repository's.
    """
    env = os.environ.get("COVTOOL_DUALNAV_STUDY")
    if env:
        return Path(env)
    cwd = Path.cwd() / "studies" / "dual_imu_flight.toml"
    if cwd.is_file():
        return cwd
    return Path(__file__).resolve().parents[1] / "studies" / "dual_imu_flight.toml"


def cmd_dualnav(args) -> int:
    """Run the comparison of two logs and write its outputs."""
    from covtool.errors import StudyFileError
    from covtool.io.imu_log import load_imu_log
    from covtool.io.writers import write_outputs
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
    with one_blas_thread():
        result = compare_logs(main, kimu, decl, path=path)
    files = write_outputs(result, out, figures=not args.no_figures)
    if not args.quiet:
        print(result.summary.to_string(index=False))
        gaps = result.tables["gaps"]
        if len(gaps):
            cols = ["imu", "after [s]", "before [s]", "samples bridged", "policy",
                    "predicted att x [urad]", "predicted att y [urad]", "predicted att z [urad]",
                    "predicted vel x [mm/s]", "predicted vel y [mm/s]", "predicted vel z [mm/s]"]
            print("\nbridged gaps:")
            print(gaps[cols].to_string(index=False))
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
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.add_argument("--no-figures", action="store_true", help="skip PNG figures")
    p.set_defaults(func=cmd_dualnav)
    return p
