"""Work split between this process and a forked child, results in shared memory (issue 13).

:func:`covtool.forked.split` runs the first part here and the others in
forked children at once, each writing its slice of a
:func:`covtool.forked.shared_empty` array; :func:`covtool.studies.grid.discretize_chunked`
gives each half of its chunks to one of them.  The numbers must be the
same as in one process (the same chunks), an error must name the step of
the caller's grid, and the earliest failing part's error wins.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.forked import can_split, shared_empty, split
from covtool.studies import grid

pytestmark = pytest.mark.usefixtures("forking")     # skipped without os.fork or two cores; fails if a thread is left


def test_children_write_their_slices_into_shared_memory():
    out = shared_empty((3, 2))

    def part(i):
        out[i] = (i, os.getpid())
        return i * 10

    assert split(part, [0, 1, 2]) == [0, 10, 20]
    np.testing.assert_array_equal(out[:, 0], [0, 1, 2])
    assert out[0, 1] == os.getpid()
    assert len({int(p) for p in out[1:, 1]} - {os.getpid()}) == 2       # two other processes wrote them


def test_an_ordinary_array_when_not_shared_and_an_empty_one():
    a = shared_empty((2, 2), shared=False)
    assert not _shared(a) and _shared(shared_empty((2, 2))) and a.shape == (2, 2)
    assert shared_empty((0, 58, 58)).shape == (0, 58, 58)


def test_the_earliest_failing_part_is_reported_and_every_child_reaped():
    def part(i):
        if i >= 1:
            raise NumericalError(f"part {i} failed")
        return i

    with pytest.raises(NumericalError, match="part 1 failed"):
        split(part, [0, 1, 2])

    def here_fails(i):
        raise NumericalError(f"part {i} failed")

    with pytest.raises(NumericalError, match="part 0 failed"):
        split(here_fails, [0, 1])
    with pytest.raises(ChildProcessError):
        os.waitpid(-1, os.WNOHANG)                         # no child left behind


def test_no_split_from_a_forked_child_or_while_another_child_runs():
    from covtool.forked import Forked

    assert Forked(can_split).result() is False             # a child does not fork again
    job = Forked(lambda: None)
    assert can_split() is False                            # the other core is taken
    job.result()
    assert can_split() is True


def _shared(a) -> bool:
    """``a`` lives in a shared mapping (:func:`shared_empty`)."""
    import mmap

    while isinstance(a, np.ndarray):
        a = a.base
    return isinstance(a, memoryview) and isinstance(a.obj, mmap.mmap)


def _system(N, n=44, seed=3):
    rng = np.random.default_rng(seed)
    F = rng.normal(scale=0.05, size=(N, n, n))
    F[N // 3: N // 3 + 40] = F[N // 3]                     # a stop: repeated steps, computed once
    G = rng.normal(size=(N, n, 3))
    Qc = G @ np.swapaxes(G, 1, 2) * 1e-4
    return F, Qc, np.full(N, 1.0)


@pytest.mark.parametrize("method", ["van_loan", "taylor"])
def test_split_discretisation_equals_one_process_bit_for_bit(monkeypatch, method):
    F, Qc, dt = _system(5 * 40 + 7)
    Phi, Qd = grid.discretize_chunked(F, Qc, dt, method, chunk=40)
    assert _shared(Phi) and _shared(Qd)                    # filled in two processes
    monkeypatch.setattr(grid, "SPLIT_CHUNKS", 10**9)
    Phi1, Qd1 = grid.discretize_chunked(F, Qc, dt, method, chunk=40)
    assert not _shared(Phi1)
    np.testing.assert_array_equal(Phi, Phi1)
    np.testing.assert_array_equal(Qd, Qd1)


@pytest.mark.parametrize("bad", [17, 190])                 # in this process's half, in the child's
def test_an_error_in_either_half_names_the_step_of_the_whole_grid(bad):
    F, Qc, dt = _system(5 * 40)
    F[bad, 2, 3] = np.nan
    times = 100.0 + np.arange(F.shape[0])
    with pytest.raises(NumericalError, match=rf"test system: step {bad} \(t = {100 + bad:g} s"):
        grid.discretize_chunked(F, Qc, dt, "van_loan", chunk=40, what="test system", times=times)


def test_no_split_while_another_thread_runs():
    import threading

    stop = threading.Event()
    th = threading.Thread(target=stop.wait, daemon=True)
    th.start()
    try:
        assert can_split() is False                        # a lock it holds at the fork would stay held
    finally:
        stop.set()
        th.join()
    assert can_split() is True


def test_a_progress_bar_starts_no_thread_and_so_does_not_stop_the_split():
    from covtool.progress import progress_bar

    with progress_bar(10, "test", True) as bar:
        bar.update(1)
        assert can_split() is True


def test_renumbering_touches_only_step_mentions_and_keeps_the_error():
    from covtool.errors import StudyFileError
    from covtool.lincov.discretize.steps import on_grid

    e = StudyFileError("s.toml: [study] dt", "the series diverges at step 30 (t = 190 s); 2 steps (of 40) fail")
    on_grid(e, 160)
    assert str(e) == "s.toml: [study] dt: the series diverges at step 190 (t = 190 s); 2 steps (of 40) fail"
    assert e.problem == "the series diverges at step 190 (t = 190 s); 2 steps (of 40) fail"
    v = ValueError("singular matrix")
    on_grid(v, 160)
    assert v.args == ("singular matrix",)


def _arrays():
    a = np.random.default_rng(5).normal(size=(400, 30, 30))            # 2.9 MB: out of band
    return {"big": a, "ints": np.arange(200_000, dtype=np.int64), "strided": a[:, ::2],
            "small": np.arange(5.0), "text": "x", "nested": [a[:3].copy(), (1, 2)]}


def test_a_childs_large_arrays_come_back_through_shared_memory():
    """A Forked result's arrays of 1 MB or more are mapped from the child's memory file, equal and writable."""
    from covtool.forked import Forked, OUT_OF_BAND_BYTES

    got, want = Forked(_arrays).result(), _arrays()
    assert want["big"].nbytes >= OUT_OF_BAND_BYTES and want["ints"].nbytes >= OUT_OF_BAND_BYTES
    for k in ("big", "ints", "strided", "small"):
        assert got[k].dtype == want[k].dtype and np.array_equal(got[k], want[k])
    assert np.array_equal(got["nested"][0], want["nested"][0]) and got["nested"][1] == (1, 2) and got["text"] == "x"
    # the large contiguous ones are views of the mapping (not copies read through the pipe), and writable
    for k in ("big", "ints"):
        base = got[k]
        while isinstance(base, np.ndarray):
            base = base.base
        assert isinstance(base, memoryview), k
        assert got[k].flags.writeable
    got["big"][0, 0, 0] = 1.5
    assert got["big"][0, 0, 0] == 1.5


def test_a_child_without_a_result_memory_still_returns_its_arrays(monkeypatch):
    """No memfd on this system: everything travels through the pipe, the same values."""
    import covtool.forked as fk

    monkeypatch.setattr(fk, "_result_memory", lambda: None)
    got = fk.Forked(_arrays).result()
    assert np.array_equal(got["big"], _arrays()["big"])
    assert np.array_equal(got["ints"], _arrays()["ints"])


def test_a_failing_child_leaves_no_memory_file_open():
    """An error in the child is re-raised here; the result memory is closed on every path."""
    from covtool.forked import Forked

    def bad():
        raise ValueError("no result")

    def result_files():
        out = []
        for fd in os.listdir("/proc/self/fd"):
            try:
                if "covtool-forked-result" in os.readlink(f"/proc/self/fd/{fd}"):
                    out.append(fd)
            except OSError:                                 # closed meanwhile (the listing's own fd)
                pass
        return out

    before = result_files()
    job = Forked(bad)
    assert len(result_files()) == len(before) + 1          # the memory file is open while the child runs
    with pytest.raises(ValueError, match="no result"):
        job.result()
    dropped = Forked(_arrays)
    dropped.cancel()
    assert result_files() == before


def test_a_memory_file_that_cannot_grow_sends_the_arrays_through_the_pipe(monkeypatch):
    """The child cannot size the memory file (shared memory full): the result comes whole through the pipe."""
    import covtool.forked as fk

    def full(fd, n):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fk.os, "ftruncate", full)
    got = fk.Forked(_arrays).result()
    assert np.array_equal(got["big"], _arrays()["big"]) and got["big"].flags.writeable
