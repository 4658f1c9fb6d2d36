"""Monte Carlo and dual-IMU benchmarks (issue 13): CLI wall time, CPU time, peak RSS.

Run from the repository root (not part of the test suite)::

    python benchmarks/bench_mc.py                         # this tree only
    python benchmarks/bench_mc.py --baseline /path/to/old  # and a checkout of an older commit, side by side
    python benchmarks/bench_mc.py --studies monte_carlo_validation --repeat 3

Each study runs as ``python -m covtool run studies/<study>.toml --out <tmp>`` in a
fresh interpreter (imports, numba's cached kernels, the computation, every output),
so the wall time is what a user sees.  The CPU time is the user + system time of the
process and its children (the Monte Carlo chunks run in worker processes); on a shared
machine it moves less with the load than the wall time, so both are printed.  The
baseline and this tree alternate when ``--repeat`` > 1, so both see the same load.

:func:`run` returns the rows, for ``benchmarks/run.py`` to include in its report.
Targets of issue 13: ``monte_carlo_validation`` (200 runs) and ``dual_imu_flight``
at most 30 s wall each on the 2-core machine.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ("monte_carlo_validation", "dual_imu_flight")
TARGET_S = {"monte_carlo_validation": 30.0, "dual_imu_flight": 30.0}


def _once(tree: Path, study: str, keep: Path | None = None) -> dict:
    """One CLI run of ``study`` with the covtool of ``tree`` (outputs kept under ``keep``)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory() as tmp:
        out = tmp if keep is None else str(keep / tree.name / study)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "covtool", "run", str(tree / "studies" / f"{study}.toml"),
                            "--out", out], cwd=tree, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{study} failed in {tree}:\n{p.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    # ru_maxrss of RUSAGE_CHILDREN is the largest child so far: exact for the first run only
    return {"tree": str(tree), "study": study, "wall_s": wall, "cpu_s": cpu,
            "peak_rss_mb": after.ru_maxrss / 1024.0}


def run(studies=STUDIES, *, baseline: Path | None = None, repeat: int = 1, keep: Path | None = None) -> list[dict]:
    """Time each study (and the baseline's), ``repeat`` times, alternating; ``keep``: keep the outputs."""
    rows = []
    trees = ([baseline] if baseline is not None else []) + [ROOT]
    for study in studies:
        for _ in range(repeat):
            for tree in trees:
                rows.append(_once(Path(tree), study, keep))
                r = rows[-1]
                print(f"  {study} with {tree}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, "
                      f"{r['peak_rss_mb']:.0f} MB", flush=True)
    return rows


def report(rows: list[dict]) -> str:
    """Median wall and CPU time per study and tree; the ratio against the baseline."""
    import statistics

    lines = [f"{'study':26s} {'tree':40s} {'wall [s]':>9s} {'CPU [s]':>9s} {'RSS [MB]':>9s}"]
    med = {}
    for study in dict.fromkeys(r["study"] for r in rows):
        for tree in dict.fromkeys(r["tree"] for r in rows):
            sel = [r for r in rows if r["study"] == study and r["tree"] == tree]
            if not sel:
                continue
            w = statistics.median(r["wall_s"] for r in sel)
            c = statistics.median(r["cpu_s"] for r in sel)
            m = max(r["peak_rss_mb"] for r in sel)
            med[(study, tree)] = (w, c)
            flag = ""
            if tree == str(ROOT) and study in TARGET_S:
                flag = f"  target <= {TARGET_S[study]:g} s: {'met' if w <= TARGET_S[study] else 'NOT met'}"
            lines.append(f"{study:26s} {tree[-40:]:40s} {w:9.1f} {c:9.1f} {m:9.0f}{flag}")
    for (study, tree), (w, c) in med.items():
        if tree != str(ROOT) and (study, str(ROOT)) in med:
            w1, c1 = med[(study, str(ROOT))]
            lines.append(f"{study}: {w / w1:.1f}x faster in wall time, {c / c1:.1f}x in CPU time than {tree}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, help="repository root of an older checkout to compare with")
    ap.add_argument("--studies", nargs="+", default=list(STUDIES), choices=STUDIES)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="keep each run's outputs in KEEP/<tree>/<study>")
    a = ap.parse_args(argv)
    rows = run(a.studies, baseline=a.baseline, repeat=a.repeat, keep=a.keep)
    print(report(rows))
    print(f"(load average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
