"""Is the environment adequate for reflectometry? (Sect. 3.1 of the paper)

Two conditions, both reported by :func:`analyse`:

1. **Algebraic** (the paper's): the lighting matrix L must have a rank that
   approaches the number of st nodes. Measured on the luminance of L with
   every observed column scaled to unit norm (so the node parametrisation's
   cell sizes do not count as ill-conditioning): singular values relative to
   the largest, the numerical rank at :data:`RANK_TOL`, the effective rank
   (exp of the entropy of the normalised singular values; Roy & Vetterli
   2007) and the condition number over the observed columns. A constant
   environment or a few point lights leave L with rank well below half the
   nodes and are flagged (:data:`MIN_RANK_FRACTION`).

2. **Angular detail** (the band-limit condition of Ramamoorthi & Hanrahan,
   which the paper cites): a specular lobe narrower than the finest detail of
   the environment leaves the same image as a wider one, so it cannot be
   recovered. :func:`environment_detail` is the share of the probe's
   log-luminance variation at angular scales below ``scale_deg`` (the probe
   against itself box-filtered to that scale, compared on a uniform spherical
   lattice). A pre-blurred environment has almost none and is flagged
   (:data:`MIN_DETAIL`). This needs the probes; L alone cannot show it: its
   spectrum is dominated by geometry and by quadrature noise in the tiny
   specular cells (measured on the shared probes, the blurred
   ``royal_esplanade_1k`` reaches the same numerical rank as the sharp
   ``venice_sunset_1k`` and ``pisa_256``).

The report also maps how densely each st node is observed
(:func:`observation_map`), with the specular (theta_h ~ 0), retro-reflective
(theta_d ~ 0) and grazing (theta_d ~ pi/2) regions summarised.
:func:`node_observation_strength` and :func:`observed_nodes` decide which
nodes count as *observed* (enough distinct rows and enough signal); the
evaluation scores Eq. 1 over the MERL cells those nodes determine
(:func:`mi_bivariate.metrics.observed_cells`), and a solver may use the same
numbers as a per-node confidence.

Calibration on the shared probes (M ~ 2000 sphere normals, K = 8000, 32x32;
numerical rank at 1e-3 of 1024 nodes; detail at 3 degrees):

======================  ==============  ========
probe                   rank fraction   detail
======================  ==============  ========
grace_latlong_1k        0.86            0.19
grace_256               0.84            0.32
uffizi_256              0.71            0.23
pisa_256                0.72            0.14
venice_sunset_1k        0.70            0.16
pedestrian_overpass_1k  0.82            0.25
royal_esplanade_1k      0.69            0.02   (blurred: flagged)
constant                0.23            0       (flagged)
======================  ==============  ========
"""

from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import mitsuba as mi
import numpy as np
from scipy.linalg import eigvalsh

from mi_bivariate.capture import hemisphere_lattice
from mi_bivariate.common import LUMINANCE_WEIGHTS, luminance, node_extent
from mi_bivariate.coordinates import ST_REGIONS
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.lighting import gram as gram_mod
from mi_bivariate.threads import blas_threads, thread_map, with_blas_threads

#: Parts of the rows whose luminance Gram matrices are summed on worker threads (fixed, so the sums
#: are the same on any machine), and the memory their matrices may take together (bytes).
PARTS = 2
PARTS_MEMORY = 1 << 28
#: Singular values below this fraction of the largest do not count towards the rank.
RANK_TOL = 1e-3
#: Flag L when its numerical rank is below this fraction of the st nodes.
MIN_RANK_FRACTION = 0.5
#: Flag an environment with less than this share of detail below ``DETAIL_SCALE_DEG``.
MIN_DETAIL = 0.06
#: Angular scale (degrees) of the detail test.
DETAIL_SCALE_DEG = 3.0
#: Regions of the st domain (:data:`coordinates.ST_REGIONS`): name -> (axis, low, high) in degrees.
REGIONS: Dict[str, Tuple[str, float, float]] = {name: (axis, lo, hi) for name, axis, lo, hi in ST_REGIONS}


def _luminance(L: np.ndarray) -> np.ndarray:
    """Luminance of ``(M, N, 3)`` (or a channel ``(M, N)``) as ``(M, N) float64``.

    Accumulated channel by channel in float64 (no ``(M, N, 3) float64`` copy):
    the same numbers as ``L.astype(float64) @ LUMINANCE_WEIGHTS`` up to rounding order.
    """
    L = np.asarray(L)
    if L.ndim == 3 and L.shape[2] == 3:
        lum = L[..., 0] * np.float64(LUMINANCE_WEIGHTS[0])
        lum += L[..., 1] * np.float64(LUMINANCE_WEIGHTS[1])
        lum += L[..., 2] * np.float64(LUMINANCE_WEIGHTS[2])
        return lum
    if L.ndim == 2:
        return L.astype(np.float64)
    raise InputError(None, f"lighting matrix must be (M, N, 3) or (M, N), got shape {L.shape}")


def _luminance_statistics(L: np.ndarray, block_rows: int = gram_mod.BLOCK_ROWS) -> Tuple[np.ndarray, np.ndarray]:
    """The luminance Gram matrix and the observation shares of L in one pass over its rows.

    Equal to ``(lum.T @ lum, sum_m lum[m] / sum(lum[m]))`` of ``lum = _luminance(L)`` up to
    the order of float64 summation (~1e-16 relative), without the ``(M, N) float64`` copy.
    Blocks of ``block_rows`` rows; each block's luminance, Gram update and shares are
    computed on the columns it touches only (:mod:`mi_bivariate.lighting.gram`: a block
    of neighbouring pixels reaches a small part of the st domain; 15% of the dense
    Gram's flops on the benchmark sphere), in :data:`PARTS` parts of the rows on worker threads.

    Args:
        L: ``(M, N, 3)`` (RGB, luminance by :data:`LUMINANCE_WEIGHTS`) or ``(M, N)``.

    Returns:
        ``(gram, shares)``: ``(N, N) float64`` (symmetric; :func:`_spectrum_from_gram` reads its upper
        triangle) and ``(N,) float64``, the :func:`observation_map` before reshaping.
    """
    L = np.asarray(L)
    if not (L.ndim == 2 or (L.ndim == 3 and L.shape[2] == 3)):
        raise InputError(None, f"lighting matrix must be (M, N, 3) or (M, N), got shape {L.shape}")
    m, n = L.shape[:2]
    step = max(1, int(block_rows))

    def part(starts: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        gram, shares = np.zeros((n, n)), np.zeros(n)
        for start in starts:
            block = L[start:start + step]
            cols = gram_mod.touched_columns(block)
            if not len(cols):
                continue
            lum = _luminance(np.take(block, cols, axis=1))
            totals = lum.sum(axis=1)
            inv = np.divide(1.0, totals, out=np.zeros_like(totals), where=totals > 0)
            shares[cols] += inv @ lum
            gram_mod.add_block_gram(gram, cols, lum)
        return gram, shares

    # The rows in a fixed number of parts (the sums do not depend on the threads), each part's Gram
    # matrix on a worker thread (its products release the GIL), added in order.
    parts = PARTS if n * n * 8 * PARTS <= PARTS_MEMORY else 1
    results = thread_map(part, np.array_split(np.arange(0, m, step), parts))
    gram, shares = results[0]
    for g, sh in results[1:]:
        gram += g
        shares += sh
    return gram, shares


def _spectrum_from_gram(gram: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`singular_spectrum` from the upper triangle of the luminance Gram matrix."""
    norms = np.sqrt(np.clip(np.diag(gram), 0.0, None))
    observed = norms > 1e-12 * max(float(norms.max()) if norms.size else 0.0, 1e-300)
    if not np.any(observed):
        return np.zeros(0), observed
    inv = 1.0 / norms[observed]
    # Column normalisation of L is a diagonal scaling of its Gram matrix.
    a = gram[np.ix_(observed, observed)] * inv[:, None] * inv[None, :]
    # The Gram matrix is N x N whatever M is; its eigenvalues are sigma^2,
    # accurate to ~1e-8 relative sigma in float64, far below RANK_TOL.
    eig = eigvalsh(a, lower=False, driver="evd", check_finite=False, overwrite_a=True)[::-1]
    sigma = np.sqrt(np.clip(eig, 0.0, None))
    return sigma / sigma[0], observed


def singular_spectrum(L: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Relative singular values of the column-normalised (luminance) L.

    Args:
        L: ``(M, N, 3)`` or one channel ``(M, N)``.

    Returns:
        ``(sigma, observed)``: descending ``sigma / sigma_max`` over the observed
        columns, and the ``(N,) bool`` mask of observed columns (non-zero).
    """
    return _spectrum_from_gram(_luminance_statistics(L)[0])


def observation_map(L: np.ndarray, n_t: int, n_s: int) -> np.ndarray:
    """Effective number of observations of each st node, ``(n_t, n_s) float64``.

    Each row's luminance weights are normalised to sum to one (the share of
    that pixel's value each node would carry for a constant BRDF); summed
    over rows, a node's value is how many pixels' worth of signal constrain it.
    The map sums to M.
    """
    if np.ndim(L) >= 2 and np.shape(L)[1] != n_t * n_s:
        raise InputError(None, f"lighting matrix has {np.shape(L)[1]} columns, expected {n_t}x{n_s}")
    return _luminance_statistics(L)[1].reshape(n_t, n_s)


#: A node is *observed* when at least this many rows (Kish effective number, share-weighted) see it ...
OBSERVED_MIN_EFFECTIVE = 8.0
#: ... and together they carry at least this many pixels' worth of its signal (sum of shares).
OBSERVED_MIN_SIGNAL = 0.5


def node_observation_strength(L: np.ndarray, n_t: int, n_s: int) -> Tuple[np.ndarray, np.ndarray]:
    """How well each st node is observed: ``(effective_rows, signal)``, each ``(n_t, n_s) float64``.

    With ``q_mj`` node j's share of row m (the row's luminance weights
    normalised to sum to one, as in :func:`observation_map`):

    - ``signal_j = sum_m q_mj``: how many pixels' worth of signal constrain
      the node (:func:`observation_map`);
    - ``effective_rows_j = (sum_m q_mj)^2 / sum_m q_mj^2``: Kish's effective
      number of rows seeing the node, each row weighted by the node's share
      of it (1 when a single row dominates, M when all rows share it equally).

    Neither alone suffices: the Kish number is blind to scale (a node with a
    1e-9 share in every row has M effective rows) and the signal sum is
    blind to concentration (one pixel that is all node j, e.g. a mirror
    reflection of a single texel, gives signal 1 from a single row). See
    :func:`observed_nodes` for the thresholds.

    Args:
        L: ``(M, n_t * n_s, 3)`` or ``(M, n_t * n_s)`` lighting matrix.
    """
    lum = _luminance(L)
    if lum.shape[1] != n_t * n_s:
        raise InputError(None, f"lighting matrix has {lum.shape[1]} columns, expected {n_t}x{n_s}")
    totals = lum.sum(axis=1, keepdims=True)
    share = np.divide(lum, totals, out=np.zeros_like(lum), where=totals > 0)
    signal = share.sum(axis=0)
    square = np.einsum("mj,mj->j", share, share)
    effective = np.divide(signal * signal, square, out=np.zeros_like(signal), where=square > 0)
    return effective.reshape(n_t, n_s), signal.reshape(n_t, n_s)


def observed_nodes(L: np.ndarray, n_t: int, n_s: int, min_effective: float = OBSERVED_MIN_EFFECTIVE,
                   min_signal: float = OBSERVED_MIN_SIGNAL) -> np.ndarray:
    """``(n_t, n_s) bool``: nodes with ``effective_rows >= min_effective`` and ``signal >= min_signal``.

    See :func:`node_observation_strength`. Defaults: 8 effective rows and
    half a pixel's worth of signal. The metrics take this mask as a plain
    boolean array, so a saved per-node confidence can replace it.
    """
    effective, signal = node_observation_strength(L, n_t, n_s)
    return (effective >= float(min_effective)) & (signal >= float(min_signal))


def region_masks(n_t: int, n_s: int) -> Dict[str, np.ndarray]:
    """``(n_t, n_s) bool`` node masks of :data:`REGIONS`."""
    t = np.linspace(0.0, 1.0, n_t)[:, None]
    s = np.linspace(0.0, 1.0, n_s)[None, :]
    angles = {"theta_h": np.broadcast_to(np.degrees(t * t * math.pi / 2), (n_t, n_s)),
              "theta_d": np.broadcast_to(np.degrees(s * math.pi / 2), (n_t, n_s))}
    return {name: (angles[axis] >= lo) & (angles[axis] <= hi) for name, (axis, lo, hi) in REGIONS.items()}


#: Most recent :func:`environment_detail` values kept, by probe content (:meth:`Probe.content_digest`).
DETAIL_CACHE_SIZE = 16
_DETAIL_CACHE: "OrderedDict[Tuple[str, str, float, int], float]" = OrderedDict()


def environment_detail(probe: Any, scale_deg: float = DETAIL_SCALE_DEG, n_points: int = 40000) -> float:
    """Share of a probe's log-luminance variation at angular scales below ``scale_deg``.

    The value depends on the probe alone (not on the image), so it is cached by the
    probe's content (:meth:`Probe.content_digest`: data and rotation), the arguments
    and the Mitsuba variant: a recovery sweep over images, priors or settings under one
    probe computes it once (~20-60 ms at 1k). See :func:`_environment_detail`.
    """
    digest = getattr(probe, "content_digest", None)
    if digest is None:  # not a Probe: nothing to key on
        return _environment_detail(probe, scale_deg, n_points)
    key = (digest(), str(mi.variant()), float(scale_deg), int(n_points))
    value = _DETAIL_CACHE.get(key)
    if value is None:
        value = _environment_detail(probe, scale_deg, n_points)
        _DETAIL_CACHE[key] = value
        while len(_DETAIL_CACHE) > DETAIL_CACHE_SIZE:
            _DETAIL_CACHE.popitem(last=False)
    else:
        _DETAIL_CACHE.move_to_end(key)
    return value


@with_blas_threads  # its row re-binning is a BLAS product: no oversubscription on a shared machine
def _environment_detail(probe: Any, scale_deg: float, n_points: int) -> float:
    """Share of a probe's log-luminance variation at angular scales below ``scale_deg`` (uncached).

    The probe (first brought to texels of about ``scale_deg / 2``) is compared
    with itself box-filtered to texels of about ``scale_deg``
    (:meth:`Probe.downsampled`, bilinearly looked up as Mitsuba does), at
    ``n_points`` directions uniform on the sphere: ``||log E - log E_blur|| /
    ||log E - mean||``. Logarithms (floored at 1e-3 of the mean) keep a
    bright sun from deciding alone. 0: no detail finer than the scale.
    """
    def divisor_at_most(width: int, factor: float) -> int:
        return max(f for f in range(1, max(1, int(factor)) + 1) if width % f == 0)

    texel_deg = 360.0 / probe.width
    base = probe.downsampled(divisor_at_most(probe.width, 0.5 * scale_deg / texel_deg))
    coarse = base.downsampled(divisor_at_most(base.width, scale_deg / (360.0 / base.width)))
    half = hemisphere_lattice(n_points // 2)
    directions = np.concatenate([half, half * [1.0, 1.0, -1.0]])
    e = luminance(base.eval(directions).astype(np.float64))
    b = luminance(coarse.eval(directions).astype(np.float64))
    floor = 1e-3 * max(float(e.mean()), 1e-30)
    le, lb = np.log(e + floor), np.log(b + floor)
    spread = np.linalg.norm(le - le.mean())
    return float(np.linalg.norm(le - lb) / spread) if spread > 0 else 0.0


@dataclass
class AdequacyReport:
    """Rank, conditioning and coverage of a lighting matrix (see the module doc).

    Attributes:
        n_t, n_s: st grid.
        singular_values: descending relative singular values (observed columns).
        numerical_rank: count of ``singular_values > RANK_TOL``.
        effective_rank: exp of the entropy of the normalised singular values.
        condition_number: ``sigma_max / sigma_min`` over the observed columns.
        unobserved_nodes: st nodes no light direction reaches.
        observation_map: ``(n_t, n_s)`` effective observations per node.
        regions: per region of :data:`REGIONS`: ``nodes``, ``observed`` (nodes
            with at least 0.01 effective observations), ``share`` (of all
            weight), ``median_per_node``.
        detail: :func:`environment_detail` per probe (empty without probes).
        adequate: no condition failed.
        reasons: why not.
    """

    n_t: int
    n_s: int
    singular_values: np.ndarray
    numerical_rank: int
    effective_rank: float
    condition_number: float
    unobserved_nodes: int
    observation_map: np.ndarray
    regions: Dict[str, Dict[str, float]]
    detail: List[float] = field(default_factory=list)
    adequate: bool = True
    reasons: List[str] = field(default_factory=list)

    @property
    def rank_fraction(self) -> float:
        return self.numerical_rank / (self.n_t * self.n_s)

    def summary(self) -> str:
        """One line for logs and the CLI."""
        parts = [f"rank {self.numerical_rank}/{self.n_t * self.n_s} (tol {RANK_TOL:g})",
                 f"effective rank {self.effective_rank:.0f}", f"cond {self.condition_number:.3g}",
                 f"unobserved nodes {self.unobserved_nodes}"]
        if self.detail:
            parts.append("detail " + ", ".join(f"{d:.3f}" for d in self.detail))
        parts += [f"{k} {v['observed']:.0f}/{v['nodes']:.0f} nodes" for k, v in self.regions.items()]
        verdict = "adequate" if self.adequate else "INADEQUATE: " + "; ".join(self.reasons)
        return ", ".join(parts) + f" -> {verdict}"

    def figure(self) -> Any:
        """Coverage map (log10 effective observations per node) and the singular spectrum."""
        import matplotlib.pyplot as plt

        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
        img = ax0.imshow(np.log10(np.maximum(self.observation_map, 1e-3)), origin="lower",
                         extent=node_extent(*self.observation_map.shape[:2]), cmap="viridis", aspect="auto")
        ax0.set_xlim(0.0, 1.0)
        ax0.set_ylim(0.0, 1.0)
        ax0.set_xlabel("s = 2 theta_d / pi")
        ax0.set_ylabel("t = sqrt(2 theta_h / pi)")
        ax0.set_title("observations per st node (log10)")
        fig.colorbar(img, ax=ax0)
        ax1.semilogy(self.singular_values)
        ax1.axhline(RANK_TOL, color="grey", linestyle="--")
        ax1.set_xlabel("index")
        ax1.set_ylabel("sigma / sigma_max")
        ax1.set_title(f"spectrum of column-normalised L (rank {self.numerical_rank})")
        fig.tight_layout()
        return fig


def analyse(L: np.ndarray, n_t: int = 32, n_s: int = 32, probes: Optional[Sequence[Any]] = None,
            warn: bool = True, min_rank_fraction: float = MIN_RANK_FRACTION,
            min_detail: float = MIN_DETAIL) -> AdequacyReport:
    """Adequacy of the illumination behind a lighting matrix.

    Args:
        L: ``(M, n_t * n_s, 3)`` from :func:`mi_bivariate.lighting.lighting_matrix`.
        n_t, n_s: st grid.
        probes: the probes that lit the rows, or one probe (enables the detail test; the
            best probe counts, since its rows constrain the specular region). None or an
            empty list: no detail test.
        warn: issue an :class:`InputWarning` when inadequate.
    """
    if np.ndim(L) >= 2 and np.shape(L)[1] != n_t * n_s:
        raise InputError(None, f"lighting matrix has {np.shape(L)[1]} columns, expected {n_t}x{n_s}")
    with blas_threads():
        gram, shares = _luminance_statistics(L)  # one pass over L for both the spectrum and the coverage
        omap = shares.reshape(n_t, n_s)
        sigma, observed = _spectrum_from_gram(gram)
        del gram
        probe_list = [] if probes is None else list(probes) if isinstance(probes, (list, tuple)) else [probes]
        detail = [environment_detail(p) for p in probe_list] or None  # no probes (None or []): no detail test
    if len(sigma):
        p = sigma / sigma.sum()
        p = p[p > 0]
        effective_rank = float(np.exp(-np.sum(p * np.log(p))))
        condition = float(1.0 / sigma[-1]) if sigma[-1] > 0 else math.inf
    else:
        effective_rank, condition = 0.0, math.inf
    rank = int(np.count_nonzero(sigma > RANK_TOL))

    regions = {}
    for name, mask in region_masks(n_t, n_s).items():
        values = omap[mask]
        regions[name] = {"nodes": float(mask.sum()), "observed": float(np.count_nonzero(values >= 0.01)),
                         "share": float(values.sum() / max(omap.sum(), 1e-300)),
                         "median_per_node": float(np.median(values))}

    report = AdequacyReport(n_t=n_t, n_s=n_s, singular_values=sigma, numerical_rank=rank,
                            effective_rank=effective_rank, condition_number=condition,
                            unobserved_nodes=int(np.count_nonzero(~observed)), observation_map=omap,
                            regions=regions)
    if rank < min_rank_fraction * n_t * n_s:
        rows = int(np.shape(L)[0]) if np.ndim(L) >= 2 else 0
        cause = (f"only {rows} observed normals for {n_t * n_s} nodes (use more pixels: a larger sphere or more "
                 "normals)" if rows < min_rank_fraction * n_t * n_s else "too little variety in the lighting")
        report.reasons.append(f"the lighting matrix has numerical rank {rank} of {n_t * n_s} nodes "
                              f"(below {min_rank_fraction:.0%}): {cause}")
    if detail is not None:
        report.detail = detail
        if max(report.detail) < min_detail:
            report.reasons.append(f"the environment has almost no detail finer than {DETAIL_SCALE_DEG:g} degrees "
                                  f"(detail {max(report.detail):.3f} < {min_detail:g}): sharp specular "
                                  "lobes cannot be told from blurred ones")
    report.adequate = not report.reasons
    if warn and not report.adequate:
        warnings.warn("inadequate illumination for reflectometry: " + "; ".join(report.reasons),
                      InputWarning, stacklevel=2)
    return report
