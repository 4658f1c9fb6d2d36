"""Start-up cost: what each command imports (issue 13, acceptance 1 and 3).

Before: every CLI start imported numba (the strapdown kernels, 0.3-0.5 s)
and scipy (through the filter files' FilterSpec), also for ``covtool
models``; the writer imported matplotlib in each of two figure processes.
Each check runs in a fresh interpreter, so that another test's imports
cannot hide one.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import platform
import resource
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: libraries a command imports only when it uses them
HEAVY = ("numba", "scipy", "matplotlib", "openpyxl", "pint", "pandas")

_PROBE = """
import contextlib, io, json, sys
from covtool.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    status = main({argv!r})
print(json.dumps({{"status": status, "modules": sorted(m for m in {heavy!r} if m in sys.modules),
                   "chars": len(out.getvalue())}}))
"""


def _probe(argv, cwd=ROOT) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", _PROBE.format(argv=list(argv), heavy=HEAVY)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("argv", [["models"], ["show", "sdins58"], ["show", "B1"], ["show", "kimu"],
                                  ["new", "zupt_filter_order"]])
def test_library_commands_import_no_heavy_library(argv):
    got = _probe(argv)
    assert got["status"] == 0 and got["chars"] > 100          # the command printed its listing
    # a table (models) and a filter's FilterSpec (lincov.reduced) still bring pandas
    allowed = ["pandas"] if argv in (["models"], ["show", "B1"]) else []
    assert got["modules"] == allowed


def test_run_draws_figures_without_importing_matplotlib_or_numba_in_the_cli_process(tmp_path):
    import tomllib

    import tomli_w

    decl = tomllib.loads((ROOT / "studies" / "pure_ins_land_vehicle.toml").read_text())
    decl["study"]["duration"] = "5 min"
    decl["output"]["report_times"] = ["5 min"]
    study = tmp_path / "short.toml"
    study.write_text(tomli_w.dumps(decl))
    out = tmp_path / "out"
    got = _probe(["run", str(study), "--out", str(out), "--quiet"], cwd=tmp_path)
    assert got["status"] == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["pure_ins_errors.png"]     # drawn, in child processes
    assert "matplotlib" not in got["modules"] and "numba" not in got["modules"]


_PAGES = """
import json, os, sys
from covtool.cli import main
status = main(["models"])
import numpy
from numpy._core.multiarray import _set_madvise_hugepage
print(json.dumps({"status": status, "env": os.environ.get("NUMPY_MADVISE_HUGEPAGE"),
                  "advised": bool(_set_madvise_hugepage(True))}))
"""


@pytest.mark.parametrize("user, env, advised", [(None, "0", False), ("1", "1", True), ("0", "0", False)])
def test_the_command_line_keeps_numpy_from_advising_huge_pages(user, env, advised):
    """Off unless the user set ``NUMPY_MADVISE_HUGEPAGE`` (first touches of large arrays stall on compaction)."""
    e = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    e["PYTHONPATH"] = str(ROOT)
    if user is not None:
        e["NUMPY_MADVISE_HUGEPAGE"] = user
    proc = subprocess.run([sys.executable, "-c", _PAGES], cwd=ROOT, env=e, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"status": 0, "env": env, "advised": advised}


def test_a_library_user_keeps_numpys_page_advice():
    """Imported after numpy (a library user's process), the command line leaves numpy's setting alone."""
    code = ("import json, os, numpy; from numpy._core.multiarray import _set_madvise_hugepage as s; "
            "from covtool.cli import _ordinary_pages; _ordinary_pages(); "
            "print(json.dumps({'env': os.environ.get('NUMPY_MADVISE_HUGEPAGE'), 'advised': bool(s(True))}))")
    e = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    e["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=e, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    import numpy
    from numpy._core.multiarray import _set_madvise_hugepage
    default = bool(_set_madvise_hugepage(True))
    _set_madvise_hugepage(default)
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {"env": None, "advised": default}


_FAULTS = """
import ctypes, json, resource, sys
from covtool.cli import _keep_freed_memory
tuned = _keep_freed_memory() if sys.argv[1] == "tuned" else None
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
libc.memset.argtypes = (ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t)
size, faults = 6 * 2**20, []
for _ in range(4):                        # eight 6-MB blocks held together, freed, then again (a study's stacks)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    blocks = [libc.malloc(size) for _ in range(8)]
    for b in blocks:
        libc.memset(b, 1, size)
    for b in blocks:
        libc.free(b)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({"tuned": tuned, "faults": faults}))
"""


def _faults(mode: str, env=None) -> dict:
    e = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    e["PYTHONPATH"] = str(ROOT)
    e.update(env or {})
    proc = subprocess.run([sys.executable, "-c", _FAULTS, mode], cwd=ROOT, env=e, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_command_line_keeps_freed_memory_for_reuse():
    """Freed blocks are reused, not mapped afresh and faulted in page by page (glibc's default trims them).

    48 MB in 6-MB blocks is 12 288 pages: glibc's default gives the heap top
    back at every free, so each round faults most of them in again; tuned,
    the rounds after the first fault in almost none.  Another C library
    has no such setting: the command line then changes nothing.
    """
    plain, tuned = _faults("plain"), _faults("tuned")
    if platform.libc_ver()[0] != "glibc":
        assert tuned["tuned"] is False
        return
    pages = 8 * 6 * 2**20 // resource.getpagesize()
    assert tuned["tuned"] is True
    assert min(plain["faults"][1:]) > 0.5 * pages           # the default: faulted in again, every round
    assert max(tuned["faults"][1:]) < 0.02 * pages          # tuned: reused
    assert tuned["faults"][0] > 0.5 * pages                 # (the first round does touch the pages)


@pytest.mark.parametrize("env", [{"MALLOC_TRIM_THRESHOLD_": "131072"}, {"MALLOC_MMAP_THRESHOLD_": "65536"},
                                 {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=131072"}])
def test_a_users_allocator_settings_are_respected(env):
    """With the user's own glibc malloc setting the command line changes nothing."""
    assert _faults("tuned", env)["tuned"] is False
