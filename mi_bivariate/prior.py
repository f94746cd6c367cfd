"""The learned smoothness prior of Eq. 6: difference operators and per-node weights.

Eq. 6 regularises the bivariate table f (``(n_t, n_s)`` per channel, flattened in C
order, column ``it * n_s + is``) with

    ||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2,

where Ds, Dt are finite differences on the st grid and Λs, Λt are diagonal weights
learned from measured materials. This module builds the operators, learns the weights
and stores them.

Choices (each one documented where it is made):

- **Operators.** Forward differences between neighbouring nodes, scaled by
  ``n - 1`` so that they estimate the derivatives dF/ds, dF/dt on the unit st square
  (a prior learned on a 32 x 32 grid then means the same thing on any other grid).
  Only differences between two real nodes are kept: ``Ds`` is
  ``(n_t (n_s - 1), n_t n_s)`` and ``Dt`` is ``((n_t - 1) n_s, n_t n_s)``, i.e. the
  paper's ``|S| x |S|`` matrices without their last row per grid line. A square
  operator would need a boundary rule for the last node: a zero row (equivalent to
  dropping it), a periodic wrap (couples grazing to retro-reflection, which is
  physically meaningless) or a Dirichlet condition f = 0 outside the grid (pulls the
  grazing and specular edges, where BRDFs are largest, towards zero).
- **Weights are standard deviations, not variances.** The paper calls the diagonal
  entries "the variance"; Λ^-1 sits inside a squared norm, so the Gaussian-prior
  reading (MAP with independent zero-mean Gaussians on the derivatives) needs the
  standard deviation on the diagonal.
- **Zero-mean spread.** Because the prior is zero-mean, sigma is learned as the root
  mean square of the derivative across materials (the maximum-likelihood scale of a
  zero-mean Gaussian), not the spread about the sample mean (``centred=True`` gives
  the latter).
- **Brightness-free.** Each material's table is divided, per channel, by its median
  over the grid nodes (a robust diffuse level) before differentiating, so bright materials do not dominate and
  the weights are dimensionless; the solve's data term is normalised the same way
  (see :mod:`mi_bivariate.solve`), so one alpha serves dark and bright materials.
- **Two pairs.** Materials are split into diffuse and glossy by their specular ratio
  (see :func:`specular_ratio`); each pair is learned on its own subset and then scaled
  so that the geometric mean of its sigmas is 1. The pairs then differ only in
  *where* they allow variation, and comparing the two solutions' data residuals
  (the paper's selection rule) compares shapes, not overall strengths (which alpha
  sets); otherwise the gloss pair, whose derivatives are larger everywhere, would win
  on every material.
- **Floor.** Sigmas below ``floor`` times the median of their map (the mean if the
  median is 0; 1 if every training table is flat) are raised to it, so a node where
  every training material happens to be flat does not get an effectively infinite
  weight. (On the 73 shared MERL-NBRDF materials the smallest sigma is ~2.1e-2 of the median,
  so the default floor of 1e-2 is a guard, not a change.)

Storage: each sigma map is ``(n_t, n_s)`` float64 indexed like the table. The entry
``sigma_s[it, is]`` belongs to the difference from node ``is`` to ``is + 1`` (likewise
``sigma_t[it, is]`` from ``it`` to ``it + 1``); the last column of ``sigma_s`` and the
last row of ``sigma_t`` have no difference of their own and hold a copy of their
neighbour so the maps keep the table's shape for plotting and resampling. The
operators never use them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import scipy.sparse as sp

from mi_bivariate.common import PathLike, node_extent

from .atomic import atomic_path
from .errors import InputError
from .npzio import provenance_dict, read_npz

PAIRS: Tuple[str, str] = ("diffuse", "gloss")
FORMAT = "mi_bivariate.prior"
FORMAT_VERSION = 1

#: A material is glossy when its specular ratio exceeds this (see :func:`specular_ratio`).
#: On the 23 MERL-NBRDF materials the ratios run 1.0 (black-fabric) ... 8.4 (purple-paint),
#: 17.7 (yellow-matte-plastic), 23.6 (silver-metallic-paint2), then 71 (white-acrylic) ...
#: 7.8e5 (tungsten-carbide): 30 sits in the widest gap, giving 10 diffuse and 13 glossy. Chosen on
#: those development materials; on the 50 training materials alone it falls in their widest gap
#: below 100 on a log scale, 14.0 (special-walnut-224) to 37.1 (green-metallic-paint): the same split.
DEFAULT_GLOSS_THRESHOLD = 30.0
#: Sigmas are floored at this fraction of their map's median.
DEFAULT_FLOOR = 1e-2
#: Sigmas are capped at this multiple of their map's median (None: no cap). Without a cap the
#: learned maps span ~5 decades (the specular row of glossy materials), leaving weakly
#: observed nodes effectively unregularised: a rendered Lambertian sphere then came back
#: with spikes of 100x its albedo there (Eq. 1 error 294); capped at 100 it is 0.6, and
#: the median Eq. 1 / floor ratio over 10 MERL-NBRDF materials fell from 9.2 to 5.2 at
#: an unchanged novel-lighting error (benchmarks/tune_alpha.py, docs/results.md).
DEFAULT_CEILING: Optional[float] = 100.0

SigmaPair = Tuple[np.ndarray, np.ndarray]


# ---------------------------------------------------------------------------
# Difference operators
# ---------------------------------------------------------------------------

def _forward_difference(n: int) -> sp.csr_matrix:
    """``(n - 1, n)`` forward difference scaled by ``n - 1`` (a derivative on [0, 1])."""
    h_inv = float(n - 1)
    return sp.diags([-h_inv, h_inv], [0, 1], shape=(n - 1, n), format="csr")


def difference_operators(n_t: int, n_s: int) -> Tuple[sp.csr_matrix, sp.csr_matrix]:
    """Derivative operators ``(Ds, Dt)`` on the ``(n_t, n_s)`` st grid.

    Returns:
        ``Ds``: ``(n_t (n_s - 1), n_t n_s)``, row ``it * (n_s - 1) + is`` is
        ``(f[it, is + 1] - f[it, is]) (n_s - 1)`` ~ dF/ds.
        ``Dt``: ``((n_t - 1) n_s, n_t n_s)``, row ``it * n_s + is`` is
        ``(f[it + 1, is] - f[it, is]) (n_t - 1)`` ~ dF/dt.
        Columns follow the table's C order (``it * n_s + is``).
    """
    check_grid(n_t, n_s)
    ds = sp.kron(sp.identity(n_t, format="csr"), _forward_difference(n_s), format="csr")
    dt = sp.kron(_forward_difference(n_t), sp.identity(n_s, format="csr"), format="csr")
    return ds, dt


def check_grid(n_t: int, n_s: int, what: str = "prior grid") -> None:
    """Raise :class:`InputError` (source ``what``) unless ``(n_t, n_s)`` is at least 2 x 2 integer nodes."""
    if int(n_t) != n_t or int(n_s) != n_s or n_t < 2 or n_s < 2:
        raise InputError(what, f"needs at least 2 x 2 integer nodes, got {n_t} x {n_s}")


#: A node of the st grid is in at most four differences (two along s, two along t): its row of the
#: precision R^T R sums at most four 1/sigma^2.
_MAX_EDGES_PER_NODE = 4.0
#: The largest precision entry (1/sigma^2 summed) a prior may hold: float64's largest number over 1e14, the
#: room the solve needs to weight it (alpha up to 1e6) and sum it over products of up to 4096^2 terms. A
#: learnt prior's sigmas are ~1 (each pair divided by their geometric mean): this only refuses sigmas
#: below ~1.5e-147.
_MAX_PRECISION = float(np.finfo(np.float64).max) / 1e14


def _edge_sigmas(sigma_s: np.ndarray, sigma_t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Per-row sigmas of ``Ds`` and ``Dt`` (the stored maps without their padding)."""
    return sigma_s[:, :-1].ravel(), sigma_t[:-1, :].ravel()


def _pad_edges(edges_s: np.ndarray, edges_t: np.ndarray) -> SigmaPair:
    """``(n_t, n_s - 1)``, ``(n_t - 1, n_s)`` edge maps -> two ``(n_t, n_s)`` maps."""
    return (np.concatenate([edges_s, edges_s[:, -1:]], axis=1),
            np.concatenate([edges_t, edges_t[-1:, :]], axis=0))


# ---------------------------------------------------------------------------
# Learning
# ---------------------------------------------------------------------------

def _table_array(obj: Any, name: str) -> np.ndarray:
    """``(n_t, n_s, 3)`` float64 from a BivariateBRDF (``.table``) or an array."""
    table = np.asarray(getattr(obj, "table", obj), dtype=np.float64)
    if table.ndim == 2:
        table = table[..., None]
    if table.ndim != 3 or table.shape[0] < 2 or table.shape[1] < 2:
        raise InputError(name, f"expected a bivariate table (n_t, n_s, channels), got shape {table.shape}")
    if not np.all(np.isfinite(table)):
        raise InputError(name, "bivariate table has non-finite values")
    return table


def _named_tables(tables: Union[Mapping[str, Any], Sequence[Any]]) -> Dict[str, np.ndarray]:
    if isinstance(tables, Mapping):
        items = list(tables.items())
    else:
        items = []
        for i, obj in enumerate(tables):
            prov = getattr(obj, "provenance", None) or {}
            name = str(prov.get("name", getattr(obj, "name", f"table{i}")))
            if any(name == seen for seen, _ in items):  # (a dict would keep the later table only)
                raise InputError("prior training set", f"material {name!r} given twice", "give each material once")
            items.append((name, obj))
    if not items:
        raise InputError("prior training set", "is empty")
    named = {name: _table_array(obj, name) for name, obj in items}
    shapes = {t.shape[:2] for t in named.values()}
    if len(shapes) != 1:
        raise InputError("prior training set", f"tables have different grids {sorted(shapes)}",
                         "reduce all materials to the same n_t x n_s")
    return named


def specular_ratio(table: np.ndarray) -> float:
    """How much brighter the specular peak is than the off-specular level.

    ``mean f(theta_h = 0, theta_d <= 45 deg) / mean f(theta_h ~ 45 deg, theta_d <= 45 deg)``
    on the grey (channel-mean) table: the peak row against the row nearest
    ``theta_h = 45 deg`` (t = sqrt(1/2)), both over theta_d up to 45 deg so that grazing
    Fresnel gain does not count as gloss. A Lambertian gives 1.

    Args:
        table: ``(n_t, n_s, C)`` or ``(n_t, n_s)`` bivariate table (any units).
    """
    grey = np.asarray(table, dtype=np.float64)
    grey = grey.mean(axis=-1) if grey.ndim == 3 else grey
    n_t, n_s = grey.shape
    cols = np.arange(n_s) <= 0.5 * (n_s - 1)
    off_row = int(round(np.sqrt(0.5) * (n_t - 1)))
    peak, off = grey[0, cols].mean(), grey[off_row, cols].mean()
    tiny = np.finfo(np.float64).tiny
    return float(peak / max(off, tiny)) if peak > 0 else 1.0


def _normalised_samples(tables: Mapping[str, np.ndarray]) -> np.ndarray:
    """``(n_samples, n_t, n_s)``: every (material, channel) divided by its grid median.

    The median over the nodes is a robust diffuse level. The mean would be dominated
    by the grazing corner (theta_h ~ 0, theta_d ~ 90 deg), where measured tables reach
    1e3 1/sr, and would make the gloss of a material depend on its grazing extrapolation.
    Channels with median 0 fall back to their mean; black channels carry no shape and
    are left out.
    """
    stack = np.concatenate([np.moveaxis(t, -1, 0) for t in tables.values()], axis=0)
    level = np.median(stack, axis=(1, 2))
    level = np.where(level > 0, level, stack.mean(axis=(1, 2)))
    keep = level > 0
    return stack[keep] / level[keep, None, None]


def _typical(sigma: np.ndarray) -> float:
    """The level the floor is relative to: the median, else the mean, else 1 (all flat)."""
    for level in (np.median(sigma), sigma.mean()):
        if level > 0:
            return float(level)
    return 1.0


def _sigma_maps(samples: np.ndarray, floor: float, centred: bool,
                ceiling: Optional[float] = None) -> Tuple[SigmaPair, float]:
    """Per-edge derivative spread of ``samples`` -> (padded sigma maps, pair scale)."""
    n_t, n_s = samples.shape[1:]
    d_s = np.diff(samples, axis=2) * (n_s - 1)
    d_t = np.diff(samples, axis=1) * (n_t - 1)
    if centred:
        sig_s, sig_t = d_s.std(axis=0), d_t.std(axis=0)
    else:
        sig_s, sig_t = np.sqrt(np.mean(d_s**2, axis=0)), np.sqrt(np.mean(d_t**2, axis=0))
    sig_s = np.maximum(sig_s, floor * _typical(sig_s))
    sig_t = np.maximum(sig_t, floor * _typical(sig_t))
    if ceiling is not None:
        sig_s = np.minimum(sig_s, ceiling * _typical(sig_s))
        sig_t = np.minimum(sig_t, ceiling * _typical(sig_t))
    scale = float(np.exp(np.mean(np.log(np.concatenate([sig_s.ravel(), sig_t.ravel()])))))
    return _pad_edges(sig_s / scale, sig_t / scale), scale


class Prior:
    """Two weight pairs of Eq. 6 (``diffuse`` and ``gloss``) on an ``(n_t, n_s)`` st grid.

    Attributes:
        pairs: ``{"diffuse": (sigma_s, sigma_t), "gloss": (sigma_s, sigma_t)}``, each map
            ``(n_t, n_s)`` float64, dimensionless, > 0 (see the module docstring for
            the storage convention).
        provenance: JSON-serialisable dict: materials, split, criterion, grid (no date: the same
            materials give the same file).
    """

    def __init__(self, pairs: Mapping[str, SigmaPair], provenance: Optional[dict] = None):
        checked: Dict[str, SigmaPair] = {}
        shape = None
        for name in PAIRS:
            if name not in pairs:
                raise InputError("prior", f"missing weight pair {name!r}")
            maps = tuple(np.array(m, dtype=np.float64) for m in pairs[name])
            if len(maps) != 2:
                raise InputError("prior", f"pair {name!r} needs (sigma_s, sigma_t)")
            for m in maps:
                if m.ndim != 2 or (shape is not None and m.shape != shape):
                    raise InputError("prior", f"pair {name!r} has sigma maps of shape {m.shape}, "
                                     f"expected {shape or '(n_t, n_s)'}")
                shape = m.shape
                if not np.all(np.isfinite(m)) or np.any(m <= 0):
                    raise InputError("prior", f"pair {name!r} has non-positive or non-finite sigmas",
                                     "learn it again with mi-bivariate learn-prior")
            checked[name] = maps  # type: ignore[assignment]
        check_grid(*shape)
        for name, (sigma_s, sigma_t) in checked.items():
            # The precision R^T R holds 1/sigma^2 summed over each node's differences: a sigma below
            # ~1e-154 overflows it to infinity, and one a little above (1e-153) still fails the solve's
            # eigen-decomposition; see _MAX_PRECISION.
            e_s, e_t = _edge_sigmas(sigma_s, sigma_t)
            smallest = float(min(e_s.min(initial=np.inf), e_t.min(initial=np.inf)))
            with np.errstate(over="ignore", divide="ignore", under="ignore"):
                largest = _MAX_EDGES_PER_NODE / smallest**2
            if not largest <= _MAX_PRECISION:  # inf or NaN included
                raise InputError("prior", f"pair {name!r} has a sigma ({smallest:.3g}) so small that the "
                                 f"prior's precision (1/sigma^2, up to {largest:.3g}) leaves float64's range "
                                 f"in the solve (at most {_MAX_PRECISION:.3g})",
                                 "learn the prior again, or raise its smallest sigmas")
        self.pairs = checked
        self.provenance = provenance_dict(provenance, "provenance")

    @property
    def n_t(self) -> int:
        return self.pairs[PAIRS[0]][0].shape[0]

    @property
    def n_s(self) -> int:
        return self.pairs[PAIRS[0]][0].shape[1]

    def __repr__(self) -> str:
        return (f"Prior({self.n_t}x{self.n_s}, "
                f"materials={len(self.provenance.get('materials', []))})")

    # -- construction ---------------------------------------------------------

    @classmethod
    def uniform(cls, n_t: int = 32, n_s: int = 32) -> "Prior":
        """Both pairs all ones: plain (unweighted) first-order Tikhonov smoothing."""
        check_grid(n_t, n_s)
        ones = np.ones((n_t, n_s))
        return cls({p: (ones, ones) for p in PAIRS}, {"kind": "uniform", "grid": _grid_meta(n_t, n_s)})

    @classmethod
    def learn(cls,
              tables: Union[Mapping[str, Any], Sequence[Any]],
              *,
              gloss_threshold: float = DEFAULT_GLOSS_THRESHOLD,
              floor: float = DEFAULT_FLOOR,
              ceiling: Optional[float] = DEFAULT_CEILING,
              centred: bool = False,
              sources: Optional[Mapping[str, str]] = None) -> "Prior":
        """Learn both pairs from bivariate tables on a common grid.

        Args:
            tables: ``{name: BivariateBRDF}`` (or a sequence; names then come from each
                table's provenance) or ``{name: (n_t, n_s, C) array}``; 1/sr.
            gloss_threshold: a material with :func:`specular_ratio` above this trains
                the gloss pair, otherwise the diffuse pair.
            floor: relative sigma floor (fraction of the map's median).
            ceiling: relative sigma cap (multiple of the map's median), or None. A cap keeps
                every node regularised: where the training set varies wildly (the
                specular row of glossy materials) an uncapped sigma leaves weakly
                observed nodes free to absorb noise.
            centred: use the spread about the mean instead of about zero.
            sources: optional ``{name: where it came from}`` for the provenance.

        Raises:
            InputError: empty set, mixed grids, or a split with an empty side.
        """
        named = _named_tables(tables)
        ratios = {name: specular_ratio(t) for name, t in named.items()}
        split = {name: "gloss" if r > gloss_threshold else "diffuse" for name, r in ratios.items()}
        pairs: Dict[str, SigmaPair] = {}
        scales: Dict[str, float] = {}
        for pair in PAIRS:
            subset = {n: t for n, t in named.items() if split[n] == pair}
            samples = _normalised_samples(subset) if subset else np.empty((0,))
            if len(samples) == 0:
                raise InputError("prior training set", f"no {pair} materials (specular ratios "
                                 f"{ {n: round(r, 2) for n, r in ratios.items()} }, threshold {gloss_threshold})",
                                 "add materials of both kinds (glossy and diffuse), or change gloss_threshold "
                                 "in Python")
            pairs[pair], scales[pair] = _sigma_maps(samples, floor, centred, ceiling)
        n_t, n_s = next(iter(named.values())).shape[:2]
        provenance = {
            "kind": "learned",
            "materials": sorted(named),
            "sources": dict(sources or {}),
            "split": split,
            "specular_ratio": {n: round(r, 6) for n, r in ratios.items()},
            "split_criterion": ("specular_ratio = mean f(theta_h=0, theta_d<=45deg) / "
                                "mean f(theta_h~45deg, theta_d<=45deg) on the channel-mean table; "
                                f"gloss if > {gloss_threshold}"),
            "gloss_threshold": gloss_threshold,
            "normalisation": "each (material, channel) table divided by its median over the grid nodes",
            "sigma": ("root mean square about zero" if not centred else "standard deviation about the mean")
                     + " of the forward-difference derivative across (material, channel) samples",
            "floor": f"{floor} x median of each map (mean if the median is 0)",
            "ceiling": None if ceiling is None else f"{ceiling} x median of each map",
            "pair_scale": scales,
            "pair_scale_note": "each pair divided by its sigmas' geometric mean (stored as pair_scale)",
            "grid": _grid_meta(n_t, n_s),
        }
        return cls(pairs, provenance)

    # -- use in the solve -----------------------------------------------------

    def regulariser(self, pair: str) -> sp.csr_matrix:
        """``R`` with ``||R f||^2 = ||Λs^-1 Ds f||^2 + ||Λt^-1 Dt f||^2`` (one channel)."""
        sigma_s, sigma_t = self._pair(pair)
        ds, dt = difference_operators(self.n_t, self.n_s)
        e_s, e_t = _edge_sigmas(sigma_s, sigma_t)
        return sp.vstack([sp.diags(1.0 / e_s) @ ds, sp.diags(1.0 / e_t) @ dt], format="csr")

    def penalty_matrix(self, pair: str) -> np.ndarray:
        """``(N, N)`` float64 ``R^T R`` (N = n_t n_s), the prior's precision matrix."""
        r = self.regulariser(pair)
        return (r.T @ r).toarray()

    def _pair(self, pair: str) -> SigmaPair:
        if pair not in self.pairs:
            raise InputError("prior", f"unknown weight pair {pair!r}", f"use one of {PAIRS}")
        return self.pairs[pair]

    # -- grids ----------------------------------------------------------------

    def resampled(self, n_t: int, n_s: int) -> "Prior":
        """The same prior on another grid.

        log sigma is interpolated linearly at the new differences' midpoints (clamped at
        the ends). Because the operators are derivatives on the unit square, sigmas need
        no rescaling with the grid spacing.
        """
        check_grid(n_t, n_s)
        if (n_t, n_s) == (self.n_t, self.n_s):
            return Prior(self.pairs, self.provenance)
        new_pairs = {}
        for name, (sigma_s, sigma_t) in self.pairs.items():
            e_s = resample_2d(np.log(sigma_s[:, :-1]), _nodes(self.n_t), _mids(self.n_s), _nodes(n_t), _mids(n_s))
            e_t = resample_2d(np.log(sigma_t[:-1, :]), _mids(self.n_t), _nodes(self.n_s), _mids(n_t), _nodes(n_s))
            new_pairs[name] = _pad_edges(np.exp(e_s), np.exp(e_t))
        prov = dict(self.provenance)
        prov["resampled_from"] = _grid_meta(self.n_t, self.n_s)
        prov["grid"] = _grid_meta(n_t, n_s)
        return Prior(new_pairs, prov)

    # -- files ----------------------------------------------------------------

    def save(self, path: PathLike) -> None:
        """Write an ``.npz``: keys ``{pair}_sigma_s``, ``{pair}_sigma_t`` and ``meta`` (JSON)."""
        meta = {"format": FORMAT, "version": FORMAT_VERSION, "pairs": list(PAIRS),
                "layout": "[theta_h (t) index, theta_d (s) index]; sigma_s[it, is] belongs to the "
                          "difference is -> is+1, sigma_t[it, is] to it -> it+1; last column/row padding",
                "units": "dimensionless (derivatives of mean-normalised tables on the unit st square)",
                "provenance": self.provenance}
        arrays = {f"{p}_sigma_{axis}": m for p, maps in self.pairs.items() for axis, m in zip("st", maps)}
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: PathLike) -> "Prior":
        """Read a file written by :meth:`save`; InputError naming the file if unusable."""
        path = Path(path)
        keys = ["meta"] + [f"{p}_sigma_{axis}" for p in PAIRS for axis in "st"]
        z = read_npz(path, what="mi_bivariate prior file", required=keys,
                     hint="make it with mi-bivariate learn-prior or Prior.save")
        try:
            meta = json.loads(str(z["meta"]))
        except (ValueError, RecursionError):
            raise InputError(path, "not a mi_bivariate prior file (metadata is not JSON)") from None
        if not isinstance(meta, dict):
            raise InputError(path, "not a mi_bivariate prior file (metadata is not a JSON object)")
        pairs = {p: (z[f"{p}_sigma_s"], z[f"{p}_sigma_t"]) for p in PAIRS}
        if meta.get("format") != FORMAT:
            raise InputError(path, f"not a mi_bivariate prior file (format {meta.get('format')!r})")
        try:
            return cls(pairs, meta.get("provenance"))
        except InputError as exc:
            raise InputError(path, exc.problem, exc.hint) from None


def _grid_meta(n_t: int, n_s: int) -> dict:
    return {"n_t": int(n_t), "n_s": int(n_s),
            "nodes": "s, t = i / (n - 1); s = 2 theta_d / pi, t = sqrt(2 theta_h / pi)"}


def _nodes(n: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, n)


def _mids(n: int) -> np.ndarray:
    return (np.arange(n - 1) + 0.5) / (n - 1)


def interpolation_matrix(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(len(dst), len(src))`` linear interpolation weights from coordinates ``src`` to ``dst``,
    clamped at the ends."""
    eye = np.eye(src.size)
    return np.stack([np.interp(dst, src, row) for row in eye], axis=1)


def resample_2d(values: np.ndarray, src_t: np.ndarray, src_s: np.ndarray, dst_t: np.ndarray,
                dst_s: np.ndarray) -> np.ndarray:
    """``(len(dst_t), len(dst_s))`` bilinear resampling of ``values`` ``(len(src_t), len(src_s))``
    given at coordinates ``src_t`` x ``src_s`` (clamped at the ends)."""
    return interpolation_matrix(src_t, dst_t) @ values @ interpolation_matrix(src_s, dst_s).T


# ---------------------------------------------------------------------------
# Packaged default, MERL front end, figure
# ---------------------------------------------------------------------------

DEFAULT_PRIOR_PATH = Path(__file__).resolve().parent / "data" / "default_prior.npz"


def default_prior() -> Prior:
    """The packaged prior (learned from the 73 shared MERL-NBRDF materials on a 32 x 32 grid)."""
    if not DEFAULT_PRIOR_PATH.is_file():
        raise InputError(DEFAULT_PRIOR_PATH, "packaged default prior is missing",
                         "regenerate it with `python scripts/make_priors.py`")
    return Prior.load(DEFAULT_PRIOR_PATH)


def plot_prior(prior: Prior):
    """``matplotlib.figure.Figure``: log10 sigma maps, rows = pairs, columns = (s, t)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 7.0), layout="constrained")
    axes = fig.subplots(len(PAIRS), 2, squeeze=False)
    split = prior.provenance.get("split", {})
    for row, pair in enumerate(PAIRS):
        members = sorted(n for n, p in split.items() if p == pair)
        for col, (axis, sigma) in enumerate(zip(("s", "t"), prior.pairs[pair])):
            ax = axes[row, col]
            # Each sigma belongs to the difference between two nodes, drawn between them: the padded
            # last column (s) or row (t) is a copy and is left out; along the other axis, cells sit on nodes.
            n_t, n_s = sigma.shape
            x0, x1, y0, y1 = node_extent(n_t, n_s)
            if axis == "s":
                sigma, extent = sigma[:, :-1], (0.0, 1.0, y0, y1)
            else:
                sigma, extent = sigma[:-1], (x0, x1, 0.0, 1.0)
            img = ax.imshow(np.log10(sigma), origin="lower", extent=extent, cmap="viridis")
            ax.set_xlim(0.0, 1.0)
            ax.set_ylim(0.0, 1.0)
            fig.colorbar(img, ax=ax, label=r"$\log_{10}\sigma$")
            ax.set_title(f"{pair}: sigma of dF/d{axis}" + (f", {len(members)} mat." if members else ""),
                         fontsize="medium")
            ax.set_xlabel(r"$s = 2\theta_d/\pi$")
            ax.set_ylabel(r"$t = \sqrt{2\theta_h/\pi}$")
    return fig
