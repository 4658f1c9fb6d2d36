"""covtool benchmarks: wall times, engine GFLOP/s, naive speed-up.

Run from the repository root (not part of the test suite)::

    python benchmarks/run.py              # everything, ~2-4 min on a 2-core machine
    python benchmarks/run.py --quick      # skip the as-is flagship timing
    python benchmarks/run.py --cli --baseline /tmp/base   # [0] and [5] only, against another checkout
    python benchmarks/run.py --long [--baseline /tmp/base] # [L] only: 6 h x 6 cases, 24 h x 20 cases, 24-h aided

``--baseline DIR`` is a checkout of another commit (``git archive <commit> |
tar -x -C DIR``): the CLI runs of [0] alternate between it and this tree.

Everything is measured in this one run and printed as a report:

0. CLI wall time and peak RSS of each study (``python -m covtool run``
   in a subprocess, interpreter start and every output included; peak RSS
   of the child from ``resource.getrusage``), median of ``--repeats`` runs,
   this tree and the ``--baseline`` checkout alternating, each from its
   own bytecode cache as an installed covtool runs (one untimed run of
   each study first).  Then the flagship's *floor*: the same command with
   its computation replaced by the stored result (:func:`cli_floor`), so
   the report says what the ≤ 2 s target leaves the computation.
1. Large-GEMM rate of numpy: 2000×2000 float64 matmul, best of 5, with one
   BLAS thread and with the default pool; measured again in every round of
   [3] (interleaved with the core), and the highest rate is the reference
   of [3]'s ratios: the machine is shared, so both sides are best-of.
2. Wall time of the flagship study (``studies/zupt_filter_order.toml``), as
   run by ``covtool.run_study`` and with the BLAS pool limited to one thread,
   and of the full Fig 8 sweep (``studies/zupt_sensitivity.toml``).
3. The propagation core: :func:`covtool.lincov.batch.run_batch` over the
   flagship's event grid for each filter with B = 27 cases (3 parameters ×
   9 scales, the Fig 8 sweep), counting 4·n³·B FLOP per sandwich
   ``Φ P Φᵀ`` (truth and filter).  One process with one BLAS thread against
   the one-thread GEMM rate; two processes at once against the default
   (two-thread) GEMM rate.
4. Speed-up over a naive reference at equal accuracy: for every case, per
   step, ``scipy.linalg.expm`` of the Van Loan matrix for the truth and the
   filter, then the covariance step and the ZUPT updates, one case at a
   time.  The naive time of one case per filter is measured and multiplied
   by the sweep's 27 cases per filter; the engine does all 162 cases end to
   end (batched Van Loan of the truth and filters once, composition, batched
   propagation).  The accuracy line is the largest difference between the
   two 30-min navigation covariances (position, velocity, tilts, azimuth),
   relative to √(P_ii P_jj).
5. The flagship's covariance computation (truth and six filters
   discretised, pure INS and six cases propagated) against a *fair* dense
   baseline: each system discretised once by per-step ``scipy.linalg.expm``
   of the Van Loan matrix (as pyins's ``compute_process_matrices``), then
   the cases one at a time with dense 58×58 steps; and covtool's truth
   discretisation against that pyins-style per-step Van Loan alone.  Each
   side runs in a fresh interpreter with one BLAS thread, under the command
   line's memory settings (:data:`CLI_MEMORY`, those of ``covtool run``) and
   under numpy's defaults, alternating; the speed-up is given with each side
   at its better setting, and with both at the same one.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

# the in-process parts ([1]-[4]) run with numpy's default transparent-huge-page advice unless the caller sets
# NUMPY_MADVISE_HUGEPAGE; the command line turns it off (covtool.cli._ordinary_pages), which speeds covtool's
# engine and slows the per-step baseline, so [5] runs each side in a fresh interpreter under both settings
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"
SENSITIVITY = ROOT / "studies" / "zupt_sensitivity.toml"
FILTERS = ["A", "B1", "B2", "B3", "C", "D"]
SCALES = np.logspace(-2, 2, 9)           # ×1/100 … ×100, 9 points (×1 included)
B = 3 * len(SCALES)                      # P0, Q, R scaled one at a time


def loadavg() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def gemm_rate(threads: int | None, n: int = 2000, repeats: int = 5) -> float:
    """Best-of-``repeats`` GFLOP/s of an n×n float64 matmul (2n³ FLOP)."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((n, n)), rng.standard_normal((n, n))
    with threadpool_limits(limits=threads, user_api="blas"):
        a @ b
        best = min(_timed(lambda: a @ b) for _ in range(repeats))
    return 2 * n**3 / best / 1e9


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


# --------------------------------------------------------------------------
# the flagship's system, shared by the core and naive benchmarks
# --------------------------------------------------------------------------

def flagship_setup():
    import tomllib

    from covtool.studies.zupt_setup import setup

    return setup(tomllib.loads(FLAGSHIP.read_text()), path=FLAGSHIP)


def sweep_inputs(Pf0, Rf):
    """Pf0, Rf, q_scale of the 27 Fig 8 cases of one filter (P0, Q, R each scaled alone)."""
    one = np.ones_like(SCALES)
    p0 = np.concatenate([SCALES, one, one])
    q = np.concatenate([one, SCALES, one])
    r = np.concatenate([one, one, SCALES])
    return p0[:, None, None] * Pf0, r[:, None, None] * Rf, q


def core_systems(S, discretization="declared"):
    """Truth and per-filter composed systems on the flagship's event grid (record: the end)."""
    from covtool.lincov.discretize import van_loan
    from covtool.lincov.batch import System, events
    from covtool.lincov.reduced import zupt_matrices

    N = S.t.size - 1
    rec = [N]
    ev = events(N, S.update_steps, rec)
    truth = System.from_steps(S.Phi, S.Qd, ev)
    out = {}
    for f in FILTERS:
        fm, Phi_f, Qd_f = S.filter_model(f)
        if discretization == "van_loan":
            Phi_f, Qd_f = van_loan(fm.F, fm.Qc, np.diff(S.t))
        out[f] = {"D": fm.D, "P0": fm.P0, "n": fm.spec.n, "form": fm.spec.update,
                  "filt": System.from_steps(Phi_f, Qd_f, ev), "Hf": zupt_matrices(fm.names), "Rf": S.filter_R(f)}
    return truth, out, rec


def core_times(payload, warm: bool = True) -> tuple[dict, float]:
    """run_batch of every filter's 27 cases: (best-of-repeats seconds per filter, sandwich FLOP)."""
    from threadpoolctl import threadpool_limits

    from covtool.lincov.batch import run_batch

    truth, filters, rec, P0, H, R, upd, repeats = payload
    n = truth.n
    K = len(truth.ev) - 1
    times, total_f = {}, 0.0
    with threadpool_limits(limits=1, user_api="blas"):
        for f, c in filters.items():
            Pf0, Rfs, q = sweep_inputs(c["P0"], c["Rf"])
            run = lambda: run_batch(truth, P0, H, R, c["D"], upd, rec, filt=c["filt"], Pf0=Pf0,  # noqa: E731
                                    Hf=c["Hf"], Rf=Rfs, q_scale=q, form=c["form"])
            if warm:
                run()
            times[f] = min(_timed(run) for _ in range(repeats))
            total_f += K * 4 * B * (n**3 + c["n"] ** 3)
    return times, total_f


def core_run(payload, warm: bool = True) -> tuple[float, float]:
    """run_batch of every filter's 27 cases: (seconds summed over filters, sandwich FLOP)."""
    times, flop = core_times(payload, warm)
    return sum(times.values()), flop


_PAYLOAD = {}


def _load_payload(payload) -> None:
    """Worker initializer: keep the systems, so the timed calls send nothing large."""
    _PAYLOAD["p"] = payload


def _core_in_worker(repeats: int) -> tuple[int, float, float]:
    t, f = core_run(_PAYLOAD["p"][:-1] + (repeats,), warm=False)
    return os.getpid(), t, f


def core_two_processes(payload) -> tuple[float, float, set]:
    """Both workers run the core at once: (best wall [s], FLOP, pids)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"), initializer=_load_payload,
                             initargs=(payload,)) as pool:
        list(pool.map(_core_in_worker, [1, 1]))                   # warm-up: imports, caches
        walls, pids = [], set()
        for _ in range(3):                                         # best of 3 rounds
            t0 = time.perf_counter()
            res = list(pool.map(_core_in_worker, [1, 1]))
            walls.append(time.perf_counter() - t0)
            pids |= {r[0] for r in res}
    return min(walls), sum(r[2] for r in res), pids


def sandwich_rate(truth, repeats=3) -> float:
    from threadpoolctl import threadpool_limits

    from covtool.lincov.batch import sandwich

    P = np.broadcast_to(np.eye(truth.n), (B, truth.n, truth.n)).copy()
    K = len(truth.ev) - 1

    def loop():
        for i in range(K):
            sandwich(truth.Phi[i], P)
    with threadpool_limits(limits=1, user_api="blas"):
        loop()
        best = min(_timed(loop) for _ in range(repeats))
    return K * 4 * truth.n**3 * B / best / 1e9


# --------------------------------------------------------------------------
# naive reference: per-step expm Van Loan, one case at a time
# --------------------------------------------------------------------------

def naive_case(S, fm, Hf, Rf, Pf0, q_scale):
    """One case: per-step scipy expm Van Loan of truth and filter, then eq (6)-(8), (15)-(16)."""
    from scipy.linalg import expm

    from covtool.lincov.kalman import filter_update, kalman_gain, truth_update

    def vl(F, Qc, dt):
        n = F.shape[0]
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n] = -F
        M[:n, n:] = Qc
        M[n:, n:] = F.T
        E = expm(M * dt)
        Phi = E[n:, n:].T
        return Phi, Phi @ E[:n, n:]

    dts = np.diff(S.t)
    upd = set(int(k) for k in S.update_steps)
    P, Pf = S.P0.copy(), Pf0.copy()
    N = dts.size
    for k in range(N + 1):
        if k in upd:
            K = kalman_gain(Pf, Hf, Rf)
            Pf = filter_update(Pf, K, Hf, Rf, fm.spec.update)
            P = truth_update(P, fm.D, K, S.H, S.R)
        if k < N:
            Phi, Qd = vl(S.dyn.F[k], S.dyn.Qc[k], dts[k])
            Phi_f, Qd_f = vl(fm.F[k], q_scale * fm.Qc[k], dts[k])
            P = Phi @ P @ Phi.T + Qd
            P = 0.5 * (P + P.T)
            Pf = Phi_f @ Pf @ Phi_f.T + Qd_f
            Pf = 0.5 * (Pf + Pf.T)
    return P


def engine_sweep(S):
    """All 162 Fig 8 cases end to end: batched Van Loan of truth and filters, compose, run_batch."""
    from threadpoolctl import threadpool_limits

    from covtool.lincov.discretize import van_loan
    from covtool.lincov.batch import System, events, run_batch
    from covtool.lincov.reduced import zupt_matrices

    out = {}
    with threadpool_limits(limits=1, user_api="blas"):
        t0 = time.perf_counter()
        dts = np.diff(S.t)
        Phi, Qd = van_loan(S.dyn.F, S.dyn.Qc, dts)
        N = dts.size
        ev = events(N, S.update_steps, [N])
        truth = System.from_steps(Phi, Qd, ev)
        for f in FILTERS:
            fm = S.filter_model(f)[0]
            Phi_f, Qd_f = van_loan(fm.F, fm.Qc, dts)
            Pf0, Rfs, q = sweep_inputs(fm.P0, S.filter_R(f))
            res = run_batch(truth, S.P0, S.H, S.R, fm.D, S.update_steps, [N], filt=System.from_steps(Phi_f, Qd_f, ev),
                            Pf0=Pf0, Hf=zupt_matrices(fm.names), Rf=Rfs, q_scale=q, form=fm.spec.update)
            out[f] = res.P_truth[:, 0]
        return time.perf_counter() - t0, out


# --------------------------------------------------------------------------
# [0] the CLI in a subprocess: wall time and peak RSS
# --------------------------------------------------------------------------

#: the studies of issue 13's time targets (flagship 2 s, sensitivity 3 s, budget 4 s, Monte Carlo and dual IMU 30 s)
CLI_STUDIES = ["zupt_filter_order", "zupt_sensitivity", "error_budget", "monte_carlo_validation", "dual_imu_flight"]

_CHILD = """
import resource, runpy, sys, time
t0 = time.perf_counter()
sys.argv = ["covtool"] + sys.argv[1:]
try:
    runpy.run_module("covtool", run_name="__main__")
except SystemExit as e:
    code = e.code
else:
    code = 0
ru = resource.getrusage(resource.RUSAGE_SELF)
rc = resource.getrusage(resource.RUSAGE_CHILDREN)            # the forked impact and figure processes
print("@@", time.perf_counter() - t0, max(ru.ru_maxrss, rc.ru_maxrss),
      ru.ru_utime + ru.ru_stime + rc.ru_utime + rc.ru_stime, code, file=sys.stderr)
"""


def cli_run(tree: Path, study: Path, out: Path, pycache: Path | None = None) -> tuple[float, float, float]:
    """One ``covtool run`` in a fresh interpreter: (wall [s] incl. interpreter start, peak RSS [MB], CPU [s]).

    With ``pycache``, the tree's modules are byte-compiled once into it and loaded from there, as from an
    installed covtool (``pip install .`` byte-compiles every module; a source tree run under
    ``PYTHONDONTWRITEBYTECODE``, as on this machine, would compile all of covtool at every start).
    """
    import resource
    import shutil
    import subprocess

    shutil.rmtree(out, ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    if pycache is not None:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(pycache)
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", _CHILD, "run", str(study), "--out", str(out)], cwd=tree, env=env,
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    shutil.rmtree(out, ignore_errors=True)
    if r.returncode != 0:
        raise RuntimeError(f"{tree}: covtool run {study.name} failed:\n{r.stderr[-2000:]}")
    rss, cpu = max(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, before), float("nan")
    for line in r.stderr.splitlines():
        if line.startswith("@@"):
            rss, cpu = float(line.split()[2]), float(line.split()[3])
    return wall, rss / 1024.0, cpu


#: the command line with the computation replaced by a stored result (:func:`cli_floor`): covtool.studies is
#: patched as it is first imported, so the command line's own start (its memory settings before numpy) is kept
_FLOOR_CHILD = """
import importlib.abc, importlib.util, pickle, sys, time
RESULT, WAIT = sys.argv[1], float(sys.argv[2])
spent = []

def stored(*args, **kwargs):
    import covtool.studies.zupt_filter_order          # what the real run imports before it computes
    t0 = time.perf_counter()
    with open(RESULT, "rb") as f:
        result = pickle.load(f)
    time.sleep(WAIT)                                  # the figure server imports matplotlib meanwhile, as it would
    spent.append(time.perf_counter() - t0)            # beside the computation
    return result

class Patch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "covtool.studies":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module
        def exec_module(module):
            run(module)
            module.run_study = stored
        spec.loader.exec_module = exec_module
        return spec

sys.meta_path.insert(0, Patch())
sys.argv = ["covtool"] + sys.argv[3:]
import runpy
try:
    runpy.run_module("covtool", run_name="__main__")
except SystemExit as e:
    if e.code:
        raise
print("@@", spent[0], file=sys.stderr)
"""

#: the floor's wait for the figure server (longer than its matplotlib import, 0.3-0.8 s on the 2-core machine) [s]
FLOOR_WAIT = 1.5


def cli_floor(study: Path, out: Path, repeats: int, pycache: Path) -> float:
    """The command line's wall time without its computation: interpreter start, imports and all outputs [s].

    ``covtool run`` as [0] runs it, from the same bytecode cache, but with ``run_study`` returning the study's
    result stored beforehand (pickled from an in-process run); the load and a wait of :data:`FLOOR_WAIT`
    (in which the figure server prepares, as it does beside the computation) are subtracted.  Median of
    ``repeats``.  ``2 s − floor`` is what the flagship's computation may take for the ≤ 2 s target.
    """
    import shutil
    import subprocess

    stored = out.parent / "floor-result.pkl"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONPYCACHEPREFIX": str(pycache)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    walls = []
    try:
        # the result of this tree's covtool (ROOT), whichever covtool this process imports
        subprocess.run([sys.executable, "-c", "import pickle, sys, covtool; pickle.dump(covtool.run_study(sys.argv[1]), "
                        "open(sys.argv[2], 'wb'), protocol=pickle.HIGHEST_PROTOCOL)", str(study), str(stored)],
                       cwd=ROOT, env=env, check=True)
        for _ in range(max(repeats, 1) + 1):              # the first untimed (bytecode cache)
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-c", _FLOOR_CHILD, str(stored), str(FLOOR_WAIT), "run", str(study),
                                "--out", str(out)], cwd=ROOT, env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if r.returncode != 0:
                raise RuntimeError(f"the floor run of {study.name} failed:\n{r.stderr[-2000:]}")
            spent = [float(x.split()[1]) for x in r.stderr.splitlines() if x.startswith("@@")][0]
            walls.append(wall - spent)
    finally:
        stored.unlink(missing_ok=True)
        shutil.rmtree(out, ignore_errors=True)
    return float(np.median(walls[1:]))


def cli_table(trees: dict, studies, repeats: int, out: Path) -> dict:
    """Median CLI wall, peak RSS and median CPU per (tree, study), the trees alternating within each repeat.

    Each tree runs from its own bytecode cache (:func:`cli_run`), written by one untimed run of each study
    first (which also fills the numba caches of the Monte Carlo and dual-IMU kernels).
    """
    res = {}
    caches = {label: out.parent / f"pycache-{label}" for label in trees}
    for st in studies:
        for label, tree in trees.items():
            cli_run(tree, tree / "studies" / f"{st}.toml", out, caches[label])
        for _ in range(repeats):
            for label, tree in trees.items():
                res.setdefault((label, st), []).append(cli_run(tree, tree / "studies" / f"{st}.toml", out,
                                                               caches[label]))
    return {k: (float(np.median([w for w, _, _ in v])), float(max(m for _, m, _ in v)),
                float(np.median([c for _, _, c in v]))) for k, v in res.items()}


def print_cli(table: dict, trees: dict, studies) -> None:
    """One row per study: wall, CPU (user + system, the robust figure on a shared machine), peak RSS."""
    labels = list(trees)
    print("    " + f"{'study':22s}" + "".join(f" | {lab:>9.9s}: wall [s]  CPU [s]  RSS [MB]" for lab in labels)
          + (" | speed-up wall, CPU" if len(labels) > 1 else ""))
    for st in studies:
        row = f"    {st:22s}" + "".join(f" | {table[(lab, st)][0]:19.2f} {table[(lab, st)][2]:8.2f} "
                                        f"{table[(lab, st)][1]:9.0f}" for lab in labels)
        if len(labels) > 1:
            a, b = table[(labels[0], st)], table[(labels[1], st)]
            row += f" | {b[0] / a[0]:6.2f} x, {b[2] / a[2]:5.2f} x"
        print(row)


# --------------------------------------------------------------------------
# [5] the flagship computation against a fair dense baseline
# --------------------------------------------------------------------------

def vl_expm(F, Qc, dt):
    """pyins-style Van Loan of one step: expm of [[−F, Q_c], [0, Fᵀ]] Δt."""
    from scipy.linalg import expm

    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = Qc
    M[n:, n:] = F.T
    E = expm(M * dt)
    Phi = E[n:, n:].T
    return Phi, Phi @ E[:n, n:]


def flagship_engine(path: Path):
    """covtool's own flagship computation, timed: truth and filter systems, pure INS and 6 cases.

    As :func:`covtool.studies.zupt_filter_order.run` does it: Φ, Q_d composed between the events (ZUPTs,
    history spacing, report times), the batched engine propagating only the dynamic block and recording
    the navigation block.
    """
    import tomllib

    from covtool.lincov.batch import System, events, run_batch
    from covtool.lincov.reduced import zupt_matrices
    from covtool.studies.zupt_filter_order import record_steps
    from covtool.studies.zupt_setup import setup

    decl = tomllib.loads(path.read_text())
    S = setup(decl, path=path)
    t0 = time.perf_counter()
    # the truth's F, Q_c, Φ and Q_d as the study builds them (ZuptSetup.Phi: once, shared by filter A)
    Phi, Qd = S.Phi, S.Qd
    t_truth = time.perf_counter() - t0
    N = S.t.size - 1
    rec = record_steps(S.t, S.every, [N])
    ev = events(N, S.update_steps, rec)
    truth = System.from_steps(Phi, Qd, ev)
    m = S.H.shape[0]
    r = run_batch(truth, S.P0[None], S.H, S.R, np.zeros((S.truth.n, 0)), [], rec, gains=np.zeros((1, 0, 0, m)))
    out = {"pure_ins": r.P_truth[0, -1]}
    for c in S.cases:
        fm, Phi_f, Qd_f, reused = S.filter_system(c)
        fsys = truth if reused else System.from_steps(Phi_f, Qd_f, ev)
        r = run_batch(truth, S.P0[None], S.H, S.R, fm.D, S.update_steps, rec, filt=fsys, Pf0=fm.P0[None],
                      Hf=zupt_matrices(fm.names), Rf=S.filter_R(c)[None], form=fm.spec.update)
        out[c] = r.P_truth[0, -1]
    return time.perf_counter() - t0, t_truth, out, S


def fresh_setup(path: Path):
    """The flagship's :func:`covtool.studies.zupt_setup.setup` (trajectory, truth F and Q_c), nothing cached yet."""
    import tomllib

    from covtool.studies.zupt_setup import setup

    return setup(tomllib.loads(path.read_text()), path=path)


def flagship_fair(S):
    """Fair dense baseline: each system discretised once (per-step expm), the cases one at a time.

    Its filter models (eq (11)-(13): F_f, Q_f, D, P_f(0), and F under each filter's navigation options) are
    built inside its timing, as the engine's are (:meth:`covtool.studies.zupt_setup.ZuptSetup.filter_build`,
    the same code: there is no other), from a setup ``S`` of its own.
    """
    from covtool.lincov.kalman import filter_update, kalman_gain, truth_update
    from covtool.lincov.reduced import zupt_matrices

    dts = np.diff(S.t)
    N = dts.size
    t0 = time.perf_counter()
    sysT = [vl_expm(S.dyn.F[k], S.dyn.Qc[k], dts[k]) for k in range(N)]
    t_truth = time.perf_counter() - t0
    upd = set(int(k) for k in S.update_steps)
    P = S.P0.copy()
    for k in range(N):
        P = sysT[k][0] @ P @ sysT[k][0].T + sysT[k][1]
        P = 0.5 * (P + P.T)
    out = {"pure_ins": P}
    for c in S.cases:
        fm = S.filter_build(c)
        sysF = [vl_expm(fm.F[k], fm.Qc[k], dts[k]) for k in range(N)]
        Hf, Rf = zupt_matrices(fm.names), S.filter_R(c)
        P, Pf = S.P0.copy(), fm.P0.copy()
        for k in range(N + 1):
            if k in upd:
                K = kalman_gain(Pf, Hf, Rf)
                Pf = filter_update(Pf, K, Hf, Rf, fm.spec.update)
                P = truth_update(P, fm.D, K, S.H, S.R)
            if k < N:
                P = sysT[k][0] @ P @ sysT[k][0].T + sysT[k][1]
                P = 0.5 * (P + P.T)
                Pf = sysF[k][0] @ Pf @ sysF[k][0].T + sysF[k][1]
                Pf = 0.5 * (Pf + Pf.T)
        out[c] = P
    return time.perf_counter() - t0, t_truth, out


#: the memory settings of the command line (covtool.cli._ordinary_pages, _keep_freed_memory), as environment
#: variables for a fresh interpreter; "numpy default" removes them
CLI_MEMORY = {"NUMPY_MADVISE_HUGEPAGE": "0", "MALLOC_MMAP_THRESHOLD_": str(32 * 2**20),
              "MALLOC_TRIM_THRESHOLD_": str(2**30)}


def fair_side(side: str, out: Path, path: Path = FLAGSHIP) -> None:
    """One side of [5] in this process (1 BLAS thread), its times and end covariances written to ``out`` (npz).

    ``side`` is ``"engine"`` (the better of two runs) or ``"fair"``.
    """
    from threadpoolctl import threadpool_limits

    from covtool.studies import grid

    # one core: the engine's large discretisations would otherwise be split with a forked child
    # (covtool.studies.grid.discretize_chunked), the baseline's not
    grid.SPLIT_CHUNKS = 10**9
    with threadpool_limits(limits=1, user_api="blas"):
        if side == "engine":
            t, t_truth, P, S = flagship_engine(path)
            t2, t_truth2, _, _ = flagship_engine(path)
            t, t_truth = min(t, t2), min(t_truth, t_truth2)
        else:
            S = fresh_setup(path)
            t, t_truth, P = flagship_fair(S)
    np.savez(out, t=t, t_truth=t_truth, q_end=S.nodes.q_nb[-1], cases=np.array(list(P)),
             **{f"P_{c}": v for c, v in P.items()})


def fair_report(path: Path = FLAGSHIP) -> dict:
    """[5]: engine vs fair dense baseline on the flagship computation, each in a fresh interpreter (1 BLAS thread).

    Each side runs under the command line's memory settings (:data:`CLI_MEMORY`, what ``covtool run``
    uses) and under numpy's defaults, alternating; the speed-up is given with each side at its better
    setting and with both at the same one.
    """
    import subprocess
    import tempfile

    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for side, setting in (("engine", "command line"), ("fair", "numpy default"), ("engine", "numpy default"),
                              ("fair", "command line")):
            env = {k: v for k, v in os.environ.items() if k not in CLI_MEMORY}
            if setting == "command line":
                env.update(CLI_MEMORY)
            env["PYTHONPATH"] = str(ROOT)
            out = Path(tmp) / f"{side}-{setting.replace(' ', '_')}.npz"
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--fair-side", side, str(out)],
                           env=env, check=True, timeout=1200)
            with np.load(out) as z:
                res[side, setting] = {"t": float(z["t"]), "t_truth": float(z["t_truth"]), "q_end": z["q_end"],
                                      "P": {str(c): z[f"P_{c}"] for c in z["cases"]}}
    eng, fair = res["engine", "command line"], res["fair", "numpy default"]
    q_end = eng["q_end"]
    diff = max(rel_diff(physical(eng["P"][c][:10, :10], q_end), physical(fair["P"][c][:10, :10], q_end))
               for c in eng["P"])
    return {"runs": {f"{side}, {setting}": (r["t"], r["t_truth"]) for (side, setting), r in res.items()},
            "engine": min(r["t"] for (sd, _), r in res.items() if sd == "engine"),
            "fair": min(r["t"] for (sd, _), r in res.items() if sd == "fair"),
            "engine_truth": min(r["t_truth"] for (sd, _), r in res.items() if sd == "engine"),
            "fair_truth": min(r["t_truth"] for (sd, _), r in res.items() if sd == "fair"),
            "same": {st: res["fair", st]["t"] / res["engine", st]["t"] for st in ("command line", "numpy default")},
            "diff": diff, "cases": len(eng["P"])}


def physical(P, q):
    """Nav block in physical coordinates: δL, δl, δh, δv, tilts, azimuth (δq's norm direction dropped)."""
    from covtool.nav.attitude import attitude_error_matrix

    T = np.zeros((9, 10))
    T[:6, :6] = np.eye(6)
    T[6:, 6:] = attitude_error_matrix(q)
    return T @ P @ T.T


def rel_diff(a, b) -> float:
    """max |a − b| / √(b_ii b_jj)."""
    d = np.sqrt(np.abs(np.diag(b)))
    return float(np.max(np.abs(a - b) / (d[:, None] * d[None, :] + 1e-300)))


# --------------------------------------------------------------------------
# --long: the 6-h x 6-case flagship variant, a 24-h x 20-case study and a 24-h aided survey
# --------------------------------------------------------------------------

#: the long variants, declared as study files (benchmarks/long/): 6 h x 6 cases and 24 h x 20 cases of the
#: flagship, the aided PADS-like survey over 24 h (4 filters and the pure INS), the sensitivity sweep over
#: 24 h, and the Monte Carlo validation over 6 h and 24 h (20 runs, 20 null replicas)
LONG = [ROOT / "benchmarks" / "long" / f"zupt_filter_order_{h}.toml" for h in ("6h", "24h")] + \
    [ROOT / "benchmarks" / "long" / "aided_pads_survey_24h.toml", ROOT / "benchmarks" / "long" / "zupt_sensitivity_24h.toml"] + \
    [ROOT / "benchmarks" / "long" / f"monte_carlo_{h}.toml" for h in ("6h", "24h")]


def memory_estimate_of(tree: Path, study: Path) -> str:
    """The memory check's estimate of ``study`` in ``tree``: its refusal under a 1-kB limit, before any computation."""
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(tree), "COVTOOL_MAX_MEMORY": "1000"}
    r = subprocess.run([sys.executable, "-m", "covtool", "run", str(study), "--out", "/nonexistent/never-written"],
                       cwd=tree, env=env, capture_output=True, text=True, timeout=600)
    text = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
    if "needs about" not in text:
        return f"n/a ({text[-200:]})"
    return text.split("needs about", 1)[1].split(" of memory", 1)[0].strip()


def long_report(trees: dict, run_baseline: bool = False) -> None:
    """Wall time and peak RSS of the long variants (CLI, one run each); the baseline's estimate, or its run."""
    import tempfile
    import tomllib

    print(f"\n[L] long studies (benchmarks/long/): CLI 'covtool run', one run each; peak RSS of the child; "
          f"load avg {loadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        for path in LONG:
            d = tomllib.loads(path.read_text())
            what = f"{d['study']['duration']}, {len(d['filters']['cases'])} cases"
            for label, tree in trees.items():
                est = memory_estimate_of(tree, path)
                if label != "this tree" and not run_baseline:
                    print(f"    {path.stem:24s} {label:10s}: not run (--baseline-run runs it); memory check's "
                          f"estimate {est} ({what})")
                    continue
                try:
                    wall, rss, cpu = cli_run(tree, path, Path(tmp) / "out", Path(tmp) / f"pycache-{label}")
                    print(f"    {path.stem:24s} {label:10s}: {wall:8.1f} s wall, {cpu:8.1f} s CPU, peak RSS "
                          f"{rss:8.0f} MB; estimate {est} ({what}; load avg {loadavg()})")
                except RuntimeError as exc:
                    line = [x for x in str(exc).splitlines() if x.startswith("covtool: error")]
                    print(f"    {path.stem:24s} {label:10s}: refused: {(line or [str(exc)[-300:]])[0]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the as-is flagship timing (BLAS pool unlimited)")
    ap.add_argument("--cli", action="store_true", help="only [0] (CLI wall and RSS) and [5] (fair baseline)")
    ap.add_argument("--baseline", type=Path, help="checkout of another commit to run [0] against, side by side")
    ap.add_argument("--repeats", type=int, default=3, help="CLI runs per study and tree (median) [3]")
    ap.add_argument("--studies", nargs="*", default=CLI_STUDIES, help="studies of [0] (names in studies/)")
    ap.add_argument("--long", action="store_true",
                    help="only [L]: the 6-h x 6-case flagship variant and a 24-h x 20-case study (wall, peak RSS)")
    ap.add_argument("--baseline-run", action="store_true",
                    help="with --long: run the long studies in the --baseline checkout too (else its estimate)")
    ap.add_argument("--fair-side", nargs=2, metavar=("SIDE", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.fair_side:
        fair_side(args.fair_side[0], Path(args.fair_side[1]))
        return 0
    if args.long:
        trees = {"this tree": ROOT}
        if args.baseline is not None:
            trees["baseline"] = args.baseline.resolve()
        long_report(trees, args.baseline_run)
        return 0
    from threadpoolctl import threadpool_info, threadpool_limits

    import covtool

    t_all = time.perf_counter()
    blas = [f"{i['internal_api']} {i.get('version')} ({i['num_threads']} threads, {i.get('architecture')})"
            for i in threadpool_info() if i["user_api"] == "blas"]
    print("covtool benchmark report")
    print("========================")
    print(f"machine   : {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"numpy {np.__version__}, BLAS {', '.join(blas) or 'n/a'}")
    print(f"load avg  : {loadavg()} (start; other processes share this machine)")

    import tempfile

    trees = {"this tree": ROOT}
    if args.baseline is not None:
        trees["baseline"] = args.baseline.resolve()
    print(f"\n[0] CLI 'covtool run <study> --out DIR' in a subprocess, median of {args.repeats}, "
          f"trees alternating ({', '.join(f'{k}: {v}' for k, v in trees.items())})")
    with tempfile.TemporaryDirectory() as tmp:
        cli = cli_table(trees, args.studies, args.repeats, Path(tmp) / "out")
        floor = (cli_floor(FLAGSHIP, Path(tmp) / "out", args.repeats, Path(tmp) / "pycache-this tree")
                 if "zupt_filter_order" in args.studies else None)
    print_cli(cli, trees, args.studies)
    if floor is not None:
        full = cli[("this tree", "zupt_filter_order")][0]
        print("    flagship floor: the same command without its computation (its stored result; interpreter, imports,")
        print(f"    every output): {floor:.2f} s median, of the full run's {full:.2f} s; the computation's share "
              f"{full - floor:.2f} s ({(full - floor) / full:.0%}); <= 2 s needs it in {2.0 - floor:.2f} s")
    fr = fair_report()
    print("\n[5] flagship computation (truth + 6 filters discretised, pure INS + 6 cases propagated), 1 BLAS thread,")
    print("    each side in a fresh interpreter, under the command line's memory settings (as covtool run) and numpy's")
    for label, (t, tt) in fr["runs"].items():
        name = label.replace("engine", "covtool engine").replace("fair", "fair dense baseline (expm once/system)")
        print(f"    {name:58s}: {t:7.2f} s (truth {tt:.2f} s)")
    print(f"    speed-up, each side at its better setting : {fr['fair'] / fr['engine']:7.1f} x   (target >= 10 x)")
    for st, r in fr["same"].items():
        print(f"    speed-up, both at the {st + ' settings':22s}: {r:7.1f} x")
    print(f"    truth discretisation vs pyins-style       : {fr['fair_truth'] / fr['engine_truth']:7.1f} x")
    print(f"    accuracy: max |P_engine - P_fair| / sqrt(P_ii P_jj) at the end, nav block, {fr['cases']} cases: "
          f"{fr['diff']:.1e}")
    if args.cli:
        print(f"\n    load avg at end: {loadavg()};  harness wall time {time.perf_counter() - t_all:.0f} s")
        return 0

    g1 = gemm_rate(1)
    gN = gemm_rate(None)
    print("\n[1] numpy large GEMM, 2000x2000 float64, best of 5")
    print(f"    1 BLAS thread        : {g1:7.1f} GFLOP/s")
    print(f"    default pool ({os.cpu_count()} thr) : {gN:7.1f} GFLOP/s")

    print("\n[2] study wall times (covtool.run_study)")
    if not args.quick:
        t = _timed(lambda: covtool.run_study(FLAGSHIP))
        print(f"    flagship zupt_filter_order, as run       : {t:7.2f} s")
    with threadpool_limits(limits=1, user_api="blas"):
        t = _timed(lambda: covtool.run_study(FLAGSHIP))
    print(f"    flagship zupt_filter_order, 1 BLAS thread: {t:7.2f} s")
    t_sens = None
    if SENSITIVITY.is_file():
        t_sens = _timed(lambda: covtool.run_study(SENSITIVITY))
        print(f"    full Fig 8 sweep zupt_sensitivity, as run: {t_sens:7.2f} s   (target < 10 s)")
    else:
        print("    studies/zupt_sensitivity.toml not found: see [4] for the engine-direct sweep")

    S = flagship_setup()
    truth, filters, rec = core_systems(S)
    payload = (truth, filters, rec, S.P0, S.H, S.R, S.update_steps, 3)
    # GEMM again next to the core: the machine is shared, so both are best-of and the
    # ratio uses the highest GEMM rate seen in this run (the conservative choice)
    g1s, gNs = [g1], [gN, gemm_rate(None)]
    best: dict = {}
    for _ in range(5):                       # interleaved rounds: GEMM shots, then the core
        g1s.append(gemm_rate(1, repeats=2))
        times, f1 = core_times(payload[:-1] + (1,))
        best = {f: min(t, best.get(f, np.inf)) for f, t in times.items()}
    t1 = sum(best.values())
    wall2, f2, pids = core_two_processes(payload)
    sw = sandwich_rate(truth, repeats=5)
    g1s.append(gemm_rate(1))
    gNs.append(gemm_rate(None))
    g1, gN = max(g1s), max(gNs)
    core1, core2 = f1 / t1 / 1e9, f2 / wall2 / 1e9
    print(f"\n[3] propagation core: run_batch, 6 filters x B = {B} cases, {len(truth.ev) - 1} intervals, "
          "4 n^3 B FLOP per sandwich")
    print(f"    large GEMM, 1 thread, at start, in each core round, after: {' / '.join(f'{x:.1f}' for x in g1s)}; "
          f"default pool: {' / '.join(f'{x:.1f}' for x in gNs)} GFLOP/s; ratios use the highest")
    print(f"    sandwich alone, 1 process            : {sw:7.1f} GFLOP/s = {sw / g1:5.1%} of 1-thread GEMM")
    print(f"    run_batch loop, 1 process            : {core1:7.1f} GFLOP/s = {core1 / g1:5.1%} of 1-thread GEMM "
          f"({t1:.2f} s for {f1 / 1e9:.1f} GFLOP, best of 5 rounds per filter)")
    print(f"    run_batch loop, 2 processes at once  : {core2:7.1f} GFLOP/s = {core2 / gN:5.1%} of default-pool "
          f"GEMM ({len(pids)} workers, {wall2:.2f} s wall, best of 3; target >= 30 %)")

    n_naive = len(FILTERS)
    naive_t, diffs = {}, []
    t_eng, eng = engine_sweep(S)
    with threadpool_limits(limits=1, user_api="blas"):
        for f in FILTERS:
            fm = S.filter_model(f)[0]
            Hf, Rf = filters[f]["Hf"], filters[f]["Rf"]
            Pf0, Rfs, q = sweep_inputs(fm.P0, Rf)
            b = len(SCALES) + len(SCALES) // 2 + 1        # a mistuned case: Q_f x 10^0.5
            t0 = time.perf_counter()
            P = naive_case(S, fm, Hf, Rfs[b], Pf0[b], q[b])
            naive_t[f] = time.perf_counter() - t0
            q_end = S.nodes.q_nb[-1]
            diffs.append(rel_diff(physical(eng[f][b], q_end), physical(P[:10, :10], q_end)))
    naive_total = sum(B * t for t in naive_t.values())
    print("\n[4] speed-up over a naive reference (per-step scipy expm Van Loan, one case at a time)")
    print("    naive, measured per case             : " + ", ".join(f"{f} {t:.2f} s" for f, t in naive_t.items()))
    print(f"    naive, {len(FILTERS)} filters x {B} cases          : {naive_total:7.1f} s "
          f"(measured per-case time x {B}; {n_naive} cases run)")
    print(f"    engine, all {len(FILTERS) * B} cases end to end      : {t_eng:7.2f} s "
          "(Van Loan once per system, compose, run_batch; 1 process)")
    print(f"    speed-up                             : {naive_total / t_eng:7.1f} x   (target >= 20 x)")
    print(f"    accuracy: max |P_engine - P_naive| / sqrt(P_ii P_jj) at 30 min, position, velocity, tilts, "
          f"azimuth, {n_naive} cases: {max(diffs):.1e}")

    print("\nsummary (one run)")
    if t_sens is not None:
        print(f"    Fig 8 sweep wall time         : {t_sens:.2f} s (studies/zupt_sensitivity.toml)")
    print(f"    Fig 8-size sweep, engine      : {t_eng:.2f} s ({len(FILTERS) * B} cases end to end, [4])")
    print(f"    core / large GEMM             : {core1 / g1:.2f} (1 core vs 1 thread), "
          f"{core2 / gN:.2f} (2 processes vs default pool)")
    print(f"    engine / naive speed-up       : {naive_total / t_eng:.0f}x at max rel. difference {max(diffs):.1e}")
    print(f"    load avg at end               : {loadavg()};  harness wall time {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
