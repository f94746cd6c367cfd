"""Per-node confidence of a solution, from the unconstrained posterior at its alpha.

For one channel with system matrix ``X = gram + lambda P [+ diag(precision)]``
(the normal equations of Eq. 6, :mod:`mi_bivariate.solve.data_term`):

- ``resolution = diag(X^-1 gram)``, the diagonal of the model resolution matrix
  (1: the node's value comes from the image; 0: from the priors);
- ``posterior_std = sqrt(diag(X^-1) / M)`` (1/sr), the posterior spread;
- ``measured = 1 - diag(X^-1) / diag(X_prior^-1)``: how much the image narrowed
  each node, against the priors alone (``X_prior = lambda P + diag(precision)``;
  the smoothness prior alone is improper, so a ridge of 1e-6 of the data's mean
  diagonal stands in where no table prior is given).

All three come from one Cholesky factorisation of ``X`` (the NNLS solve's own,
which factorises the whole ``X`` when it starts with every node passive, as the
solve does) and its inverse factor (LAPACK ``trtri``), read only on the few
diagonals that hold the prior's entries
(:func:`~mi_bivariate.solve.common.inverse_diagonals`); the prior's matrix is
banded (bandwidth ``n_s``), so its inverse's diagonal costs ``O(N n_s^2)``
(:func:`~mi_bivariate.solve.common.banded_inverse_diagonal`).
Nothing is computed before it is asked for: a solve uses the kept variant's
confidence only, and the first stage of a two-stage solve never uses ``measured``.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np

from mi_bivariate.solve.common import (
    add_entries,
    banded_inverse_diagonal,
    entries_bandwidth,
    inverse_diagonals,
    sparse_entries,
    spd_inverse,
)
from mi_bivariate.solve.data_term import DataTerm

#: The confidence maps, in the order of :class:`Confidence`'s ``(n_t, n_s, 3)`` arrays.
NAMES = ("resolution", "posterior_std", "measured")
#: Ridge (fraction of the data's mean diagonal) standing in for the improper smoothness prior.
PRIOR_RIDGE = 1e-6


class Confidence:
    """Lazily computed, cached per-node confidence of one prior variant's solution.

    Args:
        data: the normal equations (kept by reference until every channel is computed).
        penalty: ``(N, N)`` dense ``R^T R`` of the prior variant.
        lam: ``(3,)`` the penalty's weight per channel.
        precision: ``(N, 3)`` diagonal table-prior precision, or ``None``.
        grid: ``(n_t, n_s)``.
        entries: ``penalty``'s non-zero entries if the caller has them
            (:func:`~mi_bivariate.solve.common.sparse_entries`).
    """

    def __init__(self, data: DataTerm, penalty: np.ndarray, lam: np.ndarray,
                 precision: Optional[np.ndarray], grid: Tuple[int, int], entries: Optional[tuple] = None):
        self._data = data
        self._penalty = penalty
        self._entries = sparse_entries(penalty) if entries is None else entries
        self._lam = np.array(lam, np.float64)
        self._precision = precision
        self._grid = grid
        self._factors: List[Optional[Tuple[Optional[Tuple[np.ndarray, bool]], np.ndarray]]] = [None, None, None]
        self._values: Dict[Tuple[str, int], np.ndarray] = {}
        self._post_var: Dict[int, np.ndarray] = {}

    def keep_factor(self, k: int, factor: Optional[Tuple[np.ndarray, bool]], x: np.ndarray) -> None:
        """Remember ``X_k`` and ``cho_factor(X_k)`` (from the NNLS solve; ``None`` if it had no factor
        of the whole ``X_k``) until its posterior is computed (which consumes it)."""
        self._factors[k] = (factor, x)

    def set_weight(self, k: int, lam: float) -> None:
        """The penalty's weight of channel ``k`` (known once its alpha is chosen)."""
        self._lam[k] = lam

    def _system(self, k: int) -> np.ndarray:
        x = add_entries(self._data.gram[k].copy(), self._entries, self._lam[k])
        if self._precision is not None:
            x[np.diag_indices_from(x)] += self._precision[:, k]
        return x

    def _prior_entries(self, k: int):
        """The entries of ``X_k - gram_k`` (the priors' part of the system)."""
        rows, cols, values = self._entries
        if self._precision is None:
            return rows, cols, self._lam[k] * values
        diag = np.arange(self._data.n_nodes)
        return (np.concatenate([rows, diag]), np.concatenate([cols, diag]),
                np.concatenate([self._lam[k] * values, self._precision[:, k]]))

    def _posterior(self, k: int) -> None:
        kept = self._factors[k]
        self._factors[k] = None
        x, factor = (self._system(k), None) if kept is None else (kept[1], kept[0])
        # The factor is dropped here: its memory takes the inverse.
        var, resolution = inverse_diagonals(x, self._data.gram[k], factor, prior=self._prior_entries(k),
                                            overwrite_factor=True)
        self._values["resolution", k] = np.clip(resolution, 0.0, 1.0)
        self._values["posterior_std", k] = np.sqrt(np.maximum(var, 0.0) / self._data.n_rows)
        self._post_var[k] = var

    def _prior_variance(self, k: int) -> np.ndarray:
        n = self._data.n_nodes
        prior_x = self._lam[k] * self._penalty
        ridge = (self._precision[:, k] if self._precision is not None
                 else np.full(n, PRIOR_RIDGE * float(np.mean(np.diag(self._data.gram[k])))))
        prior_x[np.diag_indices(n)] += ridge
        band = entries_bandwidth(self._entries)
        diag = banded_inverse_diagonal(prior_x, band) if 4 * band < n else None
        if diag is None:
            diag = np.diag(spd_inverse(prior_x))
        return diag

    def channel(self, name: str, k: int) -> np.ndarray:
        """``(N,)`` one map (:data:`NAMES`) of channel ``k``."""
        key = (name, k)
        if key not in self._values:
            if k not in self._post_var:
                self._posterior(k)
            if name == "measured":
                prior_var = self._prior_variance(k)
                self._values[key] = np.clip(1.0 - self._post_var[k] / np.maximum(prior_var, 1e-300), 0.0, 1.0)
        return self._values[key]

    def map(self, name: str) -> np.ndarray:
        """``(n_t, n_s, 3)`` one map of every channel."""
        return np.stack([self.channel(name, k) for k in range(3)], axis=-1).reshape(*self._grid, 3)
