"""``covtool dualnav``: compare two recorded IMU logs (seed 001, method II).

Wire it into :mod:`covtool.cli` with one call in ``build_parser``::

    from covtool.cli_dualnav import add_parser as add_dualnav_parser
    add_dualnav_parser(sub)

Usage::

    covtool dualnav MAIN.csv KIMU.csv [--study studies/dual_imu_flight.toml] --out DIR

The logs are CSV files with the columns of :data:`covtool.io.imu_log.LOG_COLUMNS`
(time, Δθ, Δv), from the start of the alignment (vehicle at rest).  The study
file gives the grades, mountings, KIMU rate ratio, alignment inputs (position,
heading), comparison, monitor and gap policy; its ``[trajectory]`` and
``[simulation]`` tables are ignored.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

__all__ = ["add_parser", "cmd_dualnav", "default_study"]


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
    from covtool.studies import load_study
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


def add_parser(subparsers):
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
