"""Sub-blocks of stacks of matrices, gathered in one pass and C-contiguous.

``X[:, rows][:, :, cols]`` on a stack of shape ``(N, n, m)`` is two
fancy-index passes, and numpy lays their result out with the step axis
fastest (strides ``(8, …)``): three times slower to gather than one pass
over the flattened matrices, and slow in the batched products that follow
(``matmul`` on that layout does not reach BLAS).  :func:`gather` returns the
same values, C-contiguous.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np


def _as_range(idx: np.ndarray):
    """``slice(a, b)`` if ``idx`` is ``a, a+1, …, b−1`` (non-empty), else None."""
    if idx.size and idx[-1] - idx[0] == idx.size - 1 and (idx.size == 1 or np.all(np.diff(idx) == 1)):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return None


def gather(X, rows, cols=None) -> np.ndarray:
    """``X[..., rows, :][..., cols]`` as a new C-contiguous array.

    Parameters
    ----------
    X : array_like, shape (..., n, m)
        A stack of matrices.
    rows : array_like of int, shape (r,)
        Row indices (any order, repeats allowed).
    cols : array_like of int, shape (c,), optional
        Column indices; default ``rows`` (a principal sub-block).

    Returns
    -------
    ndarray, shape (..., r, c)
        A copy (never a view of ``X``), C-contiguous.

    Raises
    ------
    ValueError
        ``X`` has fewer than two dimensions.
    IndexError
        An index is out of range.
    """
    X = np.asarray(X)
    if X.ndim < 2:
        raise ValueError(f"gather needs a stack of matrices, got shape {X.shape}")
    rows = np.asarray(rows, np.intp).reshape(-1)
    cols = rows if cols is None else np.asarray(cols, np.intp).reshape(-1)
    n, m = X.shape[-2:]
    for name, idx, size in (("row", rows, n), ("column", cols, m)):
        if idx.size and (idx.min() < -size or idx.max() >= size):
            raise IndexError(f"{name} index out of range for a stack of {n} × {m} matrices")
    rows, cols = rows % max(n, 1), cols % max(m, 1)
    rs, cs = _as_range(rows), _as_range(cols)
    if rs is not None and cs is not None:
        return np.array(X[..., rs, cs], order="C", copy=True)
    if not X.flags.c_contiguous:
        return np.ascontiguousarray(X[..., rows[:, None], cols[None, :]])
    lead = X.shape[:-2]
    flat = (rows[:, None] * m + cols[None, :]).reshape(-1)
    return np.take(X.reshape(lead + (n * m,)), flat, axis=-1).reshape(lead + (rows.size, cols.size))
