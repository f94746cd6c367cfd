"""A data-driven prior on whole tables: what measured BRDFs look like in log space.

The smoothness prior of Eq. 6 (:mod:`mi_bivariate.prior`) fills a weakly observed
node by continuing its neighbours; it knows nothing of how real materials behave
there (a Fresnel rise at grazing theta_d, the width of a specular peak). This
prior learns that from a set of measured materials, following the
low-dimensional log-space analysis of Nielsen, Jensen & Ramamoorthi ("On optimal,
minimal BRDF sampling for reflectance acquisition", SIGGRAPH Asia 2015):

- every training table channel is divided by its median over the nodes (a
  brightness-free shape) and mapped to ``g = log(f / level + EPS)``;
- a probabilistic PCA of those maps (mean ``mu`` ``(N,)``, basis ``U``
  ``(N, K)``, component variances ``lambda`` ``(K,)``) and, per node, the
  leave-one-material-out reconstruction error ``tau`` ``(N,)`` (what the basis
  cannot express), so ``g = mu + U c + e``, ``c ~ N(0, diag lambda)``,
  ``e ~ N(0, diag tau^2)``.

Use (:meth:`BasisPrior.predict`): given a first estimate of a table and how well the
image pinned each node (the solve's resolution and posterior spread), the Gaussian
posterior of ``c`` gives a predicted table ``f_hat`` and a per-node standard
deviation ``s`` at *every* node. The solve then adds ``(1/M) sum_n ((f_n - f_hat_n) /
s_n)^2`` to Eq. 6 (:func:`mi_bivariate.solve.solve` with ``mean``/``mean_std``):
nodes the image measured stay with the data (their ``s`` is large next to the data's
precision there), nodes it did not follow what measured materials do. The balance
is the two Gaussians' own variances, decided by the image and the training set,
not tuned per material.

Leave-one-out: a prior used to score a shared material must not have seen it;
:func:`learn_from_tables` takes any subset (``exclude=``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.common import PathLike

from .atomic import atomic_path
from .errors import InputError
from .npzio import provenance_dict, read_npz
from .prior import _table_array, check_grid, interpolation_matrix

FORMAT = "mi_bivariate.basis_prior"
FORMAT_VERSION = 1
#: Relative offset of the log map: values EPS times below a table's median count as ~0.
EPS = 1e-3
#: Components kept (at most; fewer when the training set is small).
DEFAULT_COMPONENTS = 12
#: Log-space noise floor of an observed node (a node is never "known" better than ~5%).
OBSERVATION_FLOOR = 0.05
#: The largest log shape (``log(f / median + EPS)``) a loaded prior's mean, residual or per-node spread
#: (``sqrt(sum_k basis^2 variance)``) may reach: e^80 times a table's median is no material's (the packaged
#: prior reaches 7.9), and the prediction's ``exp`` must stay finite.
MAX_LOG_SHAPE = 80.0


def _log_map(values: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(values, 0.0) + EPS)


def _shape_samples(tables: Mapping[str, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    """``(S, N)`` log shapes of every (material, channel) and ``(S,)`` material index."""
    samples, owner = [], []
    for i, table in enumerate(tables.values()):
        t = np.asarray(table, dtype=np.float64)
        for c in range(t.shape[-1]):
            ch = t[..., c].ravel()
            level = np.median(ch)
            level = level if level > 0 else ch.mean()
            if not level > 0:
                continue
            samples.append(_log_map(ch / level))
            owner.append(i)
    if len(samples) < 3:
        raise InputError("basis prior training set", f"has only {len(samples)} usable table channels",
                         "give at least 3 non-black materials")
    return np.asarray(samples), np.asarray(owner)


def _pca(samples: np.ndarray, k: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    mu = samples.mean(axis=0)
    _, sv, vt = np.linalg.svd(samples - mu, full_matrices=False)
    k = max(1, min(k, len(samples) - 1, vt.shape[0]))
    return mu, vt[:k].T.copy(), sv[:k] ** 2 / max(len(samples) - 1, 1)


@dataclass
class BasisPrior:
    """Probabilistic PCA of log table shapes on an ``(n_t, n_s)`` grid.

    Attributes:
        mean: ``(N,)`` mean log shape ``mu``.
        basis: ``(N, K)`` orthonormal components ``U``.
        variances: ``(K,)`` component variances ``lambda``.
        residual: ``(N,)`` per-node leave-one-out reconstruction error ``tau`` (log units).
        n_t, n_s: grid.
        provenance: materials and settings (no date).
    """
    mean: np.ndarray
    basis: np.ndarray
    variances: np.ndarray
    residual: np.ndarray
    n_t: int
    n_s: int
    provenance: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.provenance = provenance_dict(self.provenance, "provenance")

    @property
    def materials(self) -> Tuple[str, ...]:
        return tuple(self.provenance.get("materials", ()))

    # ---------------------------------------------------------------- learning

    @classmethod
    def learn(cls, tables: Mapping[str, np.ndarray], components: int = DEFAULT_COMPONENTS,
              exclude: Sequence[str] = (), provenance: Optional[dict] = None) -> "BasisPrior":
        """Learn from ``{name: (n_t, n_s, C) table}`` (1/sr; a ``(n_t, n_s)`` array is one channel, a
        BivariateBRDF its ``.table``, as :meth:`mi_bivariate.prior.Prior.learn`) on a common grid.

        Args:
            exclude: names left out (leave-one-out scoring); one name may be given as a string.
        """
        exclude = (exclude,) if isinstance(exclude, str) else exclude
        tables = {k: _table_array(v, k) for k, v in tables.items() if k not in set(exclude)}
        if not tables:
            raise InputError("basis prior training set", "is empty")
        shapes = {t.shape[:2] for t in tables.values()}
        if len(shapes) != 1:
            raise InputError("basis prior training set", f"tables have different grids {sorted(shapes)}")
        n_t, n_s = next(iter(shapes))
        samples, owner = _shape_samples(tables)
        mu, basis, variances = _pca(samples, components)
        # Leave-one-material-out reconstruction error per node: what the basis misses.
        errors = []
        for i in np.unique(owner):
            keep = owner != i
            if keep.sum() < 3:
                continue
            mu_i, basis_i, _ = _pca(samples[keep], components)
            centred = samples[~keep] - mu_i
            errors.append(centred - (centred @ basis_i) @ basis_i.T)
        residual = np.sqrt(np.mean(np.concatenate(errors) ** 2, axis=0)) if errors else np.full(mu.shape, 1.0)
        prov = {"materials": sorted(tables), "components": int(basis.shape[1]), "eps": EPS,
                "samples": int(len(samples)), **(provenance or {})}
        return cls(mu, basis, variances, np.maximum(residual, 1e-3), int(n_t), int(n_s), prov)

    # ------------------------------------------------------------------- use

    def predict(self, table: np.ndarray, resolution: np.ndarray, posterior_std: np.ndarray
                ) -> Tuple[np.ndarray, np.ndarray]:
        """The prior's table and per-node std given a first estimate.

        Args:
            table: ``(n_t, n_s, 3)`` first estimate (1/sr).
            resolution: ``(n_t, n_s, 3)`` in [0, 1], how much the data set each node
                (:attr:`mi_bivariate.solve.SolveResult.resolution`).
            posterior_std: ``(n_t, n_s, 3)`` 1/sr, the estimate's spread.

        Returns:
            ``(mean, std)``, each ``(n_t, n_s, 3) float64`` in 1/sr.
        """
        table = np.asarray(table, dtype=np.float64)
        if table.shape[:2] != (self.n_t, self.n_s):
            raise InputError("basis prior", f"is on a {self.n_t} x {self.n_s} grid, the table is "
                             f"{table.shape[0]} x {table.shape[1]}", "learn it on the recovery's grid")
        mean = np.empty_like(table)
        std = np.empty_like(table)
        u, lam = self.basis, self.variances
        for c in range(table.shape[-1]):
            f = table[..., c].ravel()
            level = np.median(f)
            level = level if level > 0 else max(f.mean(), 1e-30)
            g_obs = _log_map(f / level)
            rel_std = np.asarray(posterior_std[..., c], np.float64).ravel() / (f + EPS * level)
            res = np.clip(np.asarray(resolution[..., c], np.float64).ravel(), 0.0, 1.0)
            precision = res / (rel_std**2 + OBSERVATION_FLOOR**2 + self.residual**2)
            a = np.diag(1.0 / lam) + (u * precision[:, None]).T @ u
            a_inv = np.linalg.inv(a)
            coeff = a_inv @ (u.T @ (precision * (g_obs - self.mean)))
            g_hat = self.mean + u @ coeff
            var = np.einsum("nk,kl,nl->n", u, a_inv, u) + self.residual**2
            shape = np.exp(g_hat)
            mean[..., c] = (level * np.maximum(shape - EPS, 0.0)).reshape(self.n_t, self.n_s)
            std[..., c] = (level * shape * np.sqrt(var)).reshape(self.n_t, self.n_s)
        return mean, std

    def resampled(self, n_t: int, n_s: int) -> "BasisPrior":
        """The same prior on another ``(n_t, n_s)`` st grid, as the smoothness prior's
        :meth:`~mi_bivariate.prior.Prior.resampled`.

        The mean log shape, every component and the per-node residual are interpolated
        bilinearly between the nodes (``i / (n - 1)`` on each axis); the component variances are
        kept, so each new node's prior covariance ``U diag(variances) U^T`` is the interpolation of
        its neighbours' on the old grid (a PCA learnt on the finer grid would have components
        scaled by the node count and variances scaled back: the same covariance).

        Measured (``benchmarks/basis_grid.py``, row level, 6 training materials, leave-one-out,
        48 x 48): median relight / floor 1.40 with the 32 x 32 prior resampled, 1.40 with one learnt
        on 48 x 48, 1.75 with none; on 6 development materials 1.31, 1.32 and 2.13
        (``docs/recovery.md`` section 6).
        """
        check_grid(n_t, n_s, "basis prior grid")
        n_t, n_s = int(n_t), int(n_s)
        if (n_t, n_s) == (self.n_t, self.n_s):
            return self
        w_t = interpolation_matrix(np.linspace(0.0, 1.0, self.n_t), np.linspace(0.0, 1.0, n_t))
        w_s = interpolation_matrix(np.linspace(0.0, 1.0, self.n_s), np.linspace(0.0, 1.0, n_s))

        def on_grid(values: np.ndarray) -> np.ndarray:
            nodes = values.reshape(self.n_t, self.n_s, -1)
            return np.einsum("ti,ijk,sj->tsk", w_t, nodes, w_s).reshape(n_t * n_s, -1)

        provenance = dict(self.provenance, resampled_from=[self.n_t, self.n_s])
        return BasisPrior(on_grid(self.mean)[:, 0], on_grid(self.basis), self.variances.copy(),
                          on_grid(self.residual)[:, 0], n_t, n_s, provenance)

    # ----------------------------------------------------------------- files

    def save(self, path: PathLike) -> None:
        meta = {"format": FORMAT, "version": FORMAT_VERSION, "grid": [self.n_t, self.n_s],
                "model": "g = log(f / median + eps) = mean + basis c + e; c ~ N(0, variances), "
                         "e ~ N(0, residual^2)", "provenance": self.provenance}
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta)), mean=self.mean, basis=self.basis,
                         variances=self.variances, residual=self.residual)

    @classmethod
    def load(cls, path: PathLike) -> "BasisPrior":
        path = Path(path)
        keys = ("meta", "mean", "basis", "variances", "residual")
        z = read_npz(path, what="mi_bivariate basis prior", required=keys,
                     hint="make it with mi-bivariate learn-prior or BasisPrior.save")
        try:
            meta = json.loads(str(z["meta"]))
            arrays = {k: np.asarray(z[k], np.float64) for k in keys[1:]}
        except (ValueError, TypeError) as exc:
            raise InputError(path, f"not a mi_bivariate basis prior ({exc.__class__.__name__}: {exc})") from None
        if not isinstance(meta, dict) or "grid" not in meta:
            raise InputError(path, "not a mi_bivariate basis prior (no grid in its metadata)")
        if meta.get("format") != FORMAT:
            raise InputError(path, f"not a mi_bivariate basis prior (format {meta.get('format')!r})")
        grid = meta["grid"]
        if (not isinstance(grid, list) or len(grid) != 2 or not all(isinstance(v, int) and not isinstance(v, bool)
                                                                    and v >= 2 for v in grid)):
            raise InputError(path, f"not a mi_bivariate basis prior (its grid is {grid!r}, not two node counts)")
        n_t, n_s = grid
        n = n_t * n_s
        if (arrays["mean"].shape != (n,) or arrays["basis"].ndim != 2 or arrays["basis"].shape[0] != n
                or arrays["variances"].shape != (arrays["basis"].shape[1],) or arrays["residual"].shape != (n,)
                or not all(np.all(np.isfinite(a)) for a in arrays.values()) or np.any(arrays["variances"] <= 0)):
            raise InputError(path, "basis prior arrays are inconsistent or non-finite",
                             "learn it again with mi-bivariate learn-prior")
        spread = np.sqrt((arrays["basis"] ** 2 * arrays["variances"]).sum(axis=1))  # each node's, over components
        reach = max(float(np.abs(arrays["mean"]).max(initial=0.0)), float(np.abs(arrays["residual"]).max(initial=0.0)),
                    float(spread.max(initial=0.0)))
        if reach > MAX_LOG_SHAPE:
            raise InputError(path, f"its log shapes reach {reach:.3g}, beyond any table (at most {MAX_LOG_SHAPE:g}: "
                             "e^80 times a table's median)", "learn it again with mi-bivariate learn-prior")
        provenance = meta.get("provenance")
        eps = provenance.get("eps", EPS) if isinstance(provenance, dict) else EPS
        if eps != EPS:  # predict reads the shapes with this module's log map: another offset misreads them
            raise InputError(path, f"learnt with the log map's offset eps = {eps!r}, but this version uses {EPS}",
                             "learn it again with mi-bivariate learn-prior")
        return cls(arrays["mean"], arrays["basis"], arrays["variances"], arrays["residual"], n_t, n_s,
                   provenance_dict(meta.get("provenance"), path))


DEFAULT_BASIS_PRIOR_PATH = Path(__file__).resolve().parent / "data" / "basis_prior.npz"


def default_basis_prior() -> Optional[BasisPrior]:
    """The packaged basis prior (all 73 shared MERL-NBRDF materials, 32 x 32), or None if absent."""
    if not DEFAULT_BASIS_PRIOR_PATH.is_file():
        return None
    return BasisPrior.load(DEFAULT_BASIS_PRIOR_PATH)
