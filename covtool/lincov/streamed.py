"""Per-step systems Φ_k, Q_d,k generated chunk by chunk in time, for step-by-step consumers.

A run that walks the grid one step at a time (the aided truth-under-filter
loop, seed 002 eq (15)–(16) with general measurements; the pure-INS
propagation) reads ``Phi[k]`` and ``Qd[k]`` in order.  :class:`StreamedSystem`
stands for the two ``(N, n, n)`` stacks: the steps ``a … b−1`` of a chunk are
made on the first read of any of them (``make(a, b)``, which discretises and
guards them), and held for later reads (the next filter of the study) while
a :class:`ChunkPool` shared by the study's systems has room; beyond it, only
the chunk last read is kept and later passes make the others again.  So the
memory is bounded by the pool, not by the duration × n², and a study that
fits holds every chunk once, as the whole-grid stacks did.

The values are those of the whole-grid stacks when ``make`` discretises each
chunk as the whole grid would (chunks a multiple of
:data:`covtool.studies.resources.DISCRETIZE_CHUNK` steps).

Pure numeric core: no I/O.
"""

from __future__ import annotations

import threading

import numpy as np

from covtool.errors import NumericalError, SystemCheckError
# steps per chunk: a multiple of the discretisation's batch, so each step is discretised as on the whole grid
from covtool.lincov.dynamics import STREAM_CHUNK

__all__ = ["ChunkPool", "ScaledSteps", "StreamedSystem"]


#: chunks a system keeps beside those its pool holds: the last ones read
LAST_CHUNKS = 2


class ChunkPool:
    """Byte budget for the chunks the streamed systems of one study hold.

    Parameters
    ----------
    budget : float
        Bytes of held chunks, summed over the systems that share the pool.
    """

    def __init__(self, budget: float):
        self.budget = float(budget)
        self.held = 0.0
        self._lock = threading.Lock()          # systems read in threads share it

    def take(self, nbytes: float) -> bool:
        """Reserve ``nbytes`` if they fit (True), else leave the pool as it is (False)."""
        with self._lock:
            if self.held + nbytes > self.budget:
                return False
            self.held += float(nbytes)
            return True


class _Steps:
    """One of the two stacks of a :class:`StreamedSystem`: ``obj[k]`` is step ``k``'s matrix.

    Holds the system's chunk store, not the system: no reference cycle, so
    the chunks are freed as soon as the last view of them goes.
    """

    def __init__(self, store: "_Store", which: int):
        self._store, self._which = store, which
        self.shape = (store.n_steps, store.n, store.n)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, k):
        if isinstance(k, (slice, tuple, list, np.ndarray)):
            raise TypeError("a streamed stack is read one step at a time (obj[k], k an integer)")
        return self._store.step(int(k))[self._which]


class _Store:
    """The chunks of a :class:`StreamedSystem` and how to make them (see there)."""

    def __init__(self, make, n_steps: int, n: int, chunk: int, pool):
        self.make, self.n_steps, self.n, self.chunk, self.pool = make, int(n_steps), int(n), int(chunk), pool
        self.held: dict = {}
        # the chunks last read that the pool does not hold: two, so that two runs reading the system in
        # threads (the Monte Carlo's analyses beside its null) do not make each other's chunk again and again
        self.last: dict = {}
        self.made = 0
        # runs in threads of one process read the same system (the Monte Carlo's analyses beside its null):
        # a chunk is made by one of them, and the others wait for it rather than make it again
        self.lock = threading.Lock()

    def bounds(self, m: int) -> tuple[int, int]:
        a = m * self.chunk
        return a, min(self.n_steps, a + self.chunk)

    def part(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        held = self.held.get(m)
        if held is not None:
            return held
        with self.lock:
            return self._part(m)

    def _part(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        if m in self.held:
            return self.held[m]
        if m in self.last:                                    # the most recent read last: evicted last
            self.last[m] = self.last.pop(m)
            return self.last[m]
        a, b = self.bounds(m)
        while len(self.last) >= LAST_CHUNKS:                  # the oldest freed before the next is made
            self.last.pop(next(iter(self.last)))
        try:
            Phi, Qd = self.make(a, b)
        except SystemCheckError:
            raise
        except NumericalError as exc:
            # the model's own failure, not the reading run's: passed through the runs unchanged
            raise SystemCheckError(str(exc)) from None
        Phi, Qd = np.asarray(Phi, float), np.asarray(Qd, float)
        if Phi.shape != (b - a, self.n, self.n) or Qd.shape != Phi.shape:
            raise ValueError(f"make({a}, {b}) gave Φ {Phi.shape} and Q_d {Qd.shape}, expected "
                             f"{(b - a, self.n, self.n)}")
        Phi.flags.writeable = Qd.flags.writeable = False
        self.made += 1
        if self.pool is None or self.pool.take(Phi.nbytes + Qd.nbytes):
            self.held[m] = (Phi, Qd)
        else:
            self.last[m] = (Phi, Qd)
        return Phi, Qd

    def step(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k < 0:
            k += self.n_steps
        if not 0 <= k < self.n_steps:
            raise IndexError(f"step {k} outside 0 … {self.n_steps - 1}")
        m = k // self.chunk
        Phi, Qd = self.part(m)
        j = k - m * self.chunk
        return Phi[j], Qd[j]


class StreamedSystem:
    """Φ_k and Q_d,k of ``N`` steps, made a chunk at a time on first read.

    Parameters
    ----------
    make : callable
        ``make(a, b) -> (Phi, Qd)``, each shape ``(b − a, n, n)``: the steps
        ``a … b−1``, discretised and guarded (it raises
        :class:`~covtool.errors.NumericalError` for a bad step, naming it;
        a read raises it again as :class:`~covtool.errors.SystemCheckError`,
        which the runs pass through unchanged).
    n_steps : int
        ``N``.
    n : int
        States.
    chunk : int
        Steps per chunk (:data:`~covtool.lincov.dynamics.STREAM_CHUNK`).
    pool : ChunkPool, optional
        Shared budget of held chunks (None: hold every chunk).

    Attributes
    ----------
    Phi, Qd : sequence of ndarray, shape (N, n, n)
        ``Phi[k]``, ``Qd[k]`` for an integer ``k`` (shape ``(n, n)``);
        ``.shape`` as the stacks'.  Read only.
    """

    def __init__(self, make, n_steps: int, n: int, *, chunk: int = STREAM_CHUNK, pool: ChunkPool | None = None):
        if chunk < 1:
            raise ValueError(f"chunk must be a positive number of steps, got {chunk}")
        self._store = _Store(make, n_steps, n, chunk, pool)
        self.n_steps, self.n, self.chunk = self._store.n_steps, self._store.n, self._store.chunk
        self.Phi, self.Qd = _Steps(self._store, 0), _Steps(self._store, 1)

    @property
    def made(self) -> int:
        """Chunks made so far (counting those made again)."""
        return self._store.made

    def step(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(Φ_k, Q_d,k)``, each shape ``(n, n)``.

        Raises
        ------
        IndexError
            ``k`` outside ``0 … N−1``.
        """
        return self._store.step(k)


class ScaledSteps:
    """``obj[k] = scale · steps[k]``: a stack read one step at a time, scaled on read (no copy of the stack).

    For a filter's ``Q_f × q`` (a trade grid's Q scale) over a streamed
    ``Q_f`` (:class:`StreamedSystem`), or a whole-grid one.

    Parameters
    ----------
    steps : sequence of ndarray, shape (N, n, n)
        Read as ``steps[k]`` (an integer ``k``); has ``.shape``.
    scale : float
        The factor each step's matrix is multiplied by on read.

    Raises
    ------
    TypeError
        On a read by slice or index array (one step at a time only).
    """

    def __init__(self, steps, scale: float):
        self._steps, self.scale = steps, float(scale)
        self.shape = tuple(steps.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, k):
        if isinstance(k, (slice, tuple, list, np.ndarray)):
            raise TypeError("a scaled stack is read one step at a time (obj[k], k an integer)")
        return self._steps[int(k)] * self.scale
