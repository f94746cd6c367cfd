"""Gram matrices of lighting matrices, by blocks of rows that touch few st nodes.

A row of L (one pixel: a normal seen from a view) reaches only the st nodes its
light directions map to: at normal view a single curve (theta_h = theta_d), at
grazing view a wider band. Neighbouring rows (the observations keep pixel order)
reach nearly the same nodes, so a block of a few hundred rows leaves most columns
exactly zero. ``a^T a`` summed block by block over the columns each block touches
costs a fraction of the dense product (measured on the benchmark sphere, 6564 x
1024 under grace: 15-17% of the flops at 256-512 rows per block) and equals it up
to the order of float64 summation (~1e-16 relative).

Used by :func:`mi_bivariate.adequacy.analyse` (the luminance Gram matrix); the
solve's noise-weighted normal equations ``L_k^T W L_k`` have the same structure
(:func:`weighted_gram`).
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

#: Rows per block: a block of 512 rows x 1024 nodes x RGB float32 is 6 MB; its
#: compacted float64 columns ~1.7 MB. 256 and 1024 were measured 10-20% slower.
BLOCK_ROWS = 512


def touched_columns(block: np.ndarray) -> np.ndarray:
    """Ascending indices of the columns (axis 1) of ``block`` with any non-zero entry.

    Args:
        block: ``(B, N)`` or ``(B, N, C)`` rows of a lighting matrix.
    """
    b, n = block.shape[:2]
    touched = block.reshape(b, -1).any(axis=0)
    return np.flatnonzero(touched.reshape(n, -1).any(axis=1) if block.ndim == 3 else touched)


def add_block_gram(gram: np.ndarray, cols: np.ndarray, a: np.ndarray) -> None:
    """``gram[cols][:, cols] += a^T a`` in place (both triangles; callers read the upper one).

    Args:
        gram: ``(N, N) float64``, C-contiguous; both triangles are updated.
        cols: ``(n,)`` ascending column indices (so the block's upper triangle
            lands in the upper triangle).
        a: ``(B, n) float64``, the block's compacted columns.
    """
    n = gram.shape[0]
    # numpy's matmul recognises a^T a (BLAS syrk) and, unlike scipy's BLAS wrappers, releases the GIL
    # (the solve's channels build their normal equations on worker threads: mi_bivariate.threads).
    product = a.T @ a
    gram.reshape(-1)[(cols[:, None] * n + cols).reshape(-1)] += product.reshape(-1)


def weighted_gram(channel: np.ndarray, w: np.ndarray, y: Optional[np.ndarray] = None,
                  block_rows: int = BLOCK_ROWS) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """``(A^T A, A^T y)`` of ``A = diag(w) channel`` block by block (the normal equations' data term).

    Args:
        channel: ``(M, N)`` one colour channel of L (any float dtype; a strided view is fine).
        w: ``(M,) float64`` row weights (e.g. ``1 / (sigma sqrt(M))``).
        y: optional ``(M,) float64`` weighted observations.
        block_rows: rows per block.

    Returns:
        ``(gram, rhs)``: ``(N, N) float64`` symmetric (both triangles filled) and
        ``(N,) float64`` (``None`` without ``y``). Equal to the dense
        ``A.T @ A`` and ``A.T @ y`` up to float64 summation order.
    """
    m, n = channel.shape
    w = np.asarray(w, np.float64)
    gram = np.zeros((n, n))
    rhs = None if y is None else np.zeros(n)
    step = max(1, int(block_rows))
    for start in range(0, m, step):
        block = channel[start:start + step]
        cols = touched_columns(block)
        if not len(cols):
            continue
        a = np.take(block, cols, axis=1) * w[start:start + step, None]
        add_block_gram(gram, cols, a)
        if rhs is not None:
            rhs[cols] += a.T @ y[start:start + step]
    lower = np.tril_indices(n, -1)
    gram[lower] = gram.T[lower]
    return gram, rhs
