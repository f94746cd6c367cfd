"""Error metrics for recovered BRDFs and re-rendered images (pure numpy).

BRDF errors compare a bivariate table against a 3D MERL table on the MERL
grid; see :func:`mi_bivariate.bivariate.reduction_error` for Eq. 1 itself.

Where the image looks: Eq. 1 over all cells is dominated by the cells where
the truth is near zero (1e-6..1e-3 1/sr, mostly at grazing angles: under
0.1% of the cells for most shared materials, up to 27% for some; see
docs/results.md, Metrics), which no image constrains. :class:`BRDFErrors` therefore also reports Eq. 1 over the
*observed* cells (:func:`observed_cells`, from a boolean mask of observed st
nodes such as :func:`mi_bivariate.adequacy.observed_nodes`), over the cells
with f > 1e-3 1/sr, and per region of the st domain (:data:`REGIONS`).
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

import numpy as np

from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.coordinates import ST_REGIONS, st_from_half_diff
from mi_bivariate.merl import MERL_SHAPE, MERLBRDF, geometric_mask, node_angles
from mi_bivariate.probes import refuse_probe

#: Regions of the (theta_h, theta_d) domain for the error breakdown (:data:`coordinates.ST_REGIONS`),
#: in order of precedence: a cell belongs to the first region whose bound it meets; "rest" is every other cell.
REGIONS: Tuple[Tuple[str, str, float, float], ...] = ST_REGIONS
REGION_NAMES: Tuple[str, ...] = tuple(r[0] for r in REGIONS) + ("rest",)


def _masked_pair(image: np.ndarray, reference: np.ndarray, mask: Optional[np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    """The two images' masked pixels (float64), after checking their shapes and the mask's.

    Raises:
        ValueError: the images' shapes differ; the mask is not boolean, not ``(H, W)`` of the
            images, or selects no pixel.
    """
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    if mask is None:
        return a, b
    mask = np.asarray(mask)
    if mask.dtype != bool:
        raise ValueError(f"mask must be boolean, got {mask.dtype}")
    if mask.shape != a.shape[:mask.ndim] or mask.ndim not in (a.ndim - 1, a.ndim):
        raise ValueError(f"mask of shape {mask.shape} does not fit images of shape {a.shape}")
    if not mask.any():
        raise ValueError("mask selects no pixel")
    return a[mask], b[mask]


def image_relative_rmse(image: np.ndarray, reference: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """``||image - reference|| / ||reference||`` over masked pixels and all channels.

    Args:
        image, reference: ``(H, W, 3)`` linear images.
        mask: ``(H, W) bool``; all pixels when omitted.
    """
    a, b = _masked_pair(image, reference, mask)
    denom = np.sqrt(np.mean(b * b))
    return float(np.sqrt(np.mean((a - b) ** 2)) / denom) if denom > 0 else float("inf")


def seed_noise(image: np.ndarray, other_seed: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """The per-image noise of a Monte Carlo render, from a second render ``other_seed`` of another seed:
    their relative RMS difference (relative to ``image``) divided by sqrt 2 (the seeds independent)."""
    return image_relative_rmse(other_seed, image, mask) / math.sqrt(2.0)


def image_psnr(image: np.ndarray, reference: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """PSNR in dB with the reference's masked maximum as peak (linear radiance); arguments as
    :func:`image_relative_rmse`."""
    a, b = _masked_pair(image, reference, mask)
    mse = np.mean((a - b) ** 2)
    peak = float(np.max(b)) if b.size else 0.0
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(peak * peak / mse)) if peak > 0 else float("-inf")


# ------------------------------------------------------------- BRDF errors
#
# Every BRDF error below compares an estimate against a 3D truth on the MERL
# grid: the nodes (theta_h_i, theta_d_j, phi_d_k) whose directions are both
# above the horizon and whose truth is finite in all channels ("cells", the
# same cells as Eq. 1 in :func:`mi_bivariate.bivariate.reduction_error`).
# The estimate is a bivariate table (evaluated bilinearly in st at each
# node's (theta_h, theta_d), constant along phi_d) or any 3D BRDF.

def relative_rms(truth: np.ndarray, estimate: np.ndarray, cells: np.ndarray) -> float:
    """Eq. 1's relative RMS error: ``sqrt(mean_cells ((estimate - truth) / truth)^2)``.

    Args:
        truth, estimate: broadcastable arrays (1/sr); ``estimate`` may be
            constant along axes where it broadcasts (e.g. phi_d).
        cells: ``bool`` array of the truth's shape; cells with ``truth <= 0``
            are left out (the relative error is undefined there).

    Returns:
        The error (0.1 = 10 %); NaN if no cell counts.
    """
    truth = np.asarray(truth, np.float64)
    cells = np.asarray(cells, bool) & (truth > 0.0)
    count = int(cells.sum())
    if count == 0:
        return float("nan")
    estimate = np.broadcast_to(np.asarray(estimate, np.float64), truth.shape)
    rel = (estimate[cells] - truth[cells]) / truth[cells]
    return float(np.sqrt(np.mean(rel * rel)))


def weighted_relative_l2(truth: np.ndarray, estimate: np.ndarray, weights: np.ndarray) -> float:
    """``sqrt(sum w (estimate - truth)^2 / sum w truth^2)``: a relative L2 error under weights ``w``.

    Unlike :func:`relative_rms` it weighs absolute errors, so near-zero
    values of the truth barely count. Cells with zero weight (or non-finite
    truth) are ignored. NaN if the weighted truth has no energy.
    """
    truth = np.asarray(truth, np.float64)
    estimate = np.broadcast_to(np.asarray(estimate, np.float64), truth.shape)
    w = np.broadcast_to(np.asarray(weights, np.float64), truth.shape)
    use = (w > 0.0) & np.isfinite(truth)
    energy = float(np.sum(w[use] * truth[use] ** 2))
    if not energy > 0.0:
        return float("nan")
    diff = estimate[use] - truth[use]
    return float(np.sqrt(np.sum(w[use] * diff * diff) / energy))


def log_rms(truth: np.ndarray, estimate: np.ndarray, cells: np.ndarray) -> float:
    """``sqrt(mean_cells (ln(1 + estimate) - ln(1 + truth))^2)`` with BRDF values in 1/sr.

    ``ln(1 + f)`` is linear for f << 1 1/sr (diffuse and grazing values) and
    logarithmic in the specular peak, so neither the near-zero cells (as in
    Eq. 1) nor the peak (as in an absolute L2 error) dominate. Negative
    estimates are clipped to 0. NaN if no cell counts.
    """
    truth = np.asarray(truth, np.float64)
    cells = np.asarray(cells, bool) & np.isfinite(truth)
    if not cells.any():
        return float("nan")
    estimate = np.broadcast_to(np.asarray(estimate, np.float64), truth.shape)
    d = np.log1p(np.maximum(estimate[cells], 0.0)) - np.log1p(np.maximum(truth[cells], 0.0))
    return float(np.sqrt(np.mean(d * d)))


def merl_cell_weights() -> np.ndarray:
    """``(90, 90, 180) float64``: each MERL node's share of ``cos(theta_i) cos(theta_o) dw_i dw_o``.

    In Rusinkiewicz coordinates ``dw_i dw_o = 4 cos(theta_d) dw_h dw_d``
    (for a fixed ``w_i``, ``w_o`` = ``w_i`` mirrored about h has
    ``dw_o = 4 (w_i . h) dw_h``), with ``dw_h = sin(theta_h) dtheta_h dphi_h``
    and ``dw_d = sin(theta_d) dtheta_d dphi_d``. On MERL's nodes
    ``theta_h = t^2 pi / 2`` so ``dtheta_h = pi t dt``; phi_h integrates to
    2 pi, and the folded phi_d in [0, pi) covers half of [0, 2 pi). The node
    gets the value at its lower corner times its cell's extent (a left
    Riemann sum, O(1/90) accurate). Below-horizon nodes get 0; the weights
    sum to ~pi^2 (the integral of ``cos(theta_i) cos(theta_o)`` over both
    hemispheres).
    """
    n_h, n_d, n_p = MERL_SHAPE
    theta_h, theta_d, phi_d = node_angles()
    th, td, pd = theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :]
    along = np.cos(td) * np.cos(th)
    across = np.sin(td) * np.sin(th) * np.cos(pd)
    cos_io = along * along - across * across            # cos(theta_i) cos(theta_o) at phi_h = 0
    t = np.arange(n_h)[:, None, None] / n_h
    measure = (4.0 * np.cos(td) * np.sin(th) * np.sin(td)
               * (np.pi * t / n_h)                      # dtheta_h = pi t dt, dt = 1/90
               * (0.5 * np.pi / n_d)                    # dtheta_d
               * (np.pi / n_p)                          # dphi_d
               * 2.0 * (2.0 * np.pi))                   # both phi_d halves, phi_h
    return np.where(geometric_mask(), np.maximum(cos_io, 0.0) * measure, 0.0)


def estimate_on_merl_grid(estimate) -> np.ndarray:
    """An estimate's values on the MERL nodes: ``(90, 90, 1, 3)`` (bivariate) or ``(90, 90, 180, 3)`` float64.

    Accepts a :class:`~mi_bivariate.bivariate.BivariateBRDF`, a
    :class:`~mi_bivariate.merl.MERLBRDF`, an array of either shape (or
    ``(90, 90, 3)``), or any object with ``eval(theta_h, theta_d, phi_d)``
    (a 3D analytic or parametric BRDF).
    """
    theta_h, theta_d, phi_d = node_angles()
    if isinstance(estimate, BivariateBRDF):
        return estimate.eval(theta_h[:, None], theta_d[None, :])[:, :, None, :]
    if isinstance(estimate, MERLBRDF):
        return np.asarray(estimate.table, np.float64)
    if isinstance(estimate, np.ndarray):
        if estimate.shape == MERL_SHAPE[:2] + (3,):
            return np.asarray(estimate, np.float64)[:, :, None, :]
        if estimate.shape == MERL_SHAPE + (3,):
            return np.asarray(estimate, np.float64)
        raise ValueError(f"estimate array must be (90, 90, 3) or (90, 90, 180, 3), got {estimate.shape}")
    refuse_probe(estimate, "estimate", "score a BRDF, not the probe")
    if callable(getattr(estimate, "eval", None)):
        th, td, pd = np.meshgrid(theta_h, theta_d, phi_d, indexing="ij")
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return np.asarray(estimate.eval(th, td, pd), np.float64)
    raise TypeError(f"cannot evaluate a {type(estimate).__name__} on the MERL grid")


def region_of(theta_h: np.ndarray, theta_d: np.ndarray) -> np.ndarray:
    """Index into :data:`REGION_NAMES` of each (theta_h, theta_d) (radians, broadcast): int array."""
    th, td = np.broadcast_arrays(np.degrees(np.asarray(theta_h, np.float64)),
                                 np.degrees(np.asarray(theta_d, np.float64)))
    out = np.full(th.shape, len(REGIONS), np.int64)
    for k in range(len(REGIONS) - 1, -1, -1):      # first match wins: assign in reverse order
        _, axis, lo, hi = REGIONS[k]
        a = th if axis == "theta_h" else td
        out = np.where((a >= lo) & (a < hi) if hi < 90.0 else (a >= lo), k, out)
    return out


def observed_cells(observed_nodes: np.ndarray, theta_h: Optional[np.ndarray] = None,
                   theta_d: Optional[np.ndarray] = None) -> np.ndarray:
    """Which (theta_h, theta_d) points an st table's observed nodes fully determine.

    A point is observed when every node of its bilinear st stencil (the
    nodes ``floor`` and ``ceil`` of its fractional node coordinate on each
    axis; one node on an axis where it sits exactly on a node) is observed.

    Args:
        observed_nodes: ``(n_t, n_s) bool``.
        theta_h, theta_d: radians (broadcast); default the MERL nodes, giving ``(90, 90) bool``.
    """
    nodes = np.asarray(observed_nodes, bool)
    if nodes.ndim != 2 or min(nodes.shape) < 2:
        raise ValueError(f"observed_nodes must be (n_t >= 2, n_s >= 2) bool, got shape {nodes.shape}")
    if theta_h is None or theta_d is None:
        mh, md, _ = node_angles()
        theta_h, theta_d = mh[:, None], md[None, :]
    s, t = st_from_half_diff(np.asarray(theta_h, np.float64), np.asarray(theta_d, np.float64))
    s, t = np.broadcast_arrays(np.asarray(s), np.asarray(t))
    n_t, n_s = nodes.shape
    u = np.clip(t, 0.0, 1.0) * (n_t - 1)
    v = np.clip(s, 0.0, 1.0) * (n_s - 1)
    i0, i1 = np.floor(u).astype(np.int64), np.minimum(np.ceil(u).astype(np.int64), n_t - 1)
    j0, j1 = np.floor(v).astype(np.int64), np.minimum(np.ceil(v).astype(np.int64), n_s - 1)
    return nodes[i0, j0] & nodes[i0, j1] & nodes[i1, j0] & nodes[i1, j1]


class BRDFErrors:
    """The BRDF errors of estimates against one 3D truth; the truth's cells are prepared once.

    Calling the object with an estimate returns a dict of floats:

    - ``eq1``: the paper's Eq. 1, relative RMS over the cells (channels
      pooled); equals :func:`~mi_bivariate.bivariate.reduction_error` for a
      bivariate estimate. Dominated by near-zero truth values.
    - ``eq1_rgb``: Eq. 1 per channel (list of 3).
    - ``eq1_min``: Eq. 1 over the cells with truth above ``max(min_value, 1e-3)`` 1/sr.
    - ``cosine``: :func:`weighted_relative_l2` with :func:`merl_cell_weights`:
      the relative L2 error of f under the measure ``cos(theta_i) cos(theta_o) dw_i dw_o``
      (what a render under uniform light integrates); dominated by large values.
    - ``log``: :func:`log_rms`, RMS of ``ln(1 + f)`` differences over the cells.
    - ``regions``: per region of :data:`REGION_NAMES`, ``{"eq1", "share", "cells"}``:
      Eq. 1 over the region's cells, the region's share of the summed
      squared relative errors (where Eq. 1 comes from) and its cell count.

    With ``observed_nodes`` (an ``(n_t, n_s) bool`` mask of st nodes, e.g.
    :func:`mi_bivariate.adequacy.observed_nodes`) also:

    - ``eq1_observed``: Eq. 1 over the cells whose (theta_h, theta_d) is
      observed (:func:`observed_cells`);
    - ``observed_fraction``: the share of cells that are.

    Args:
        truth: a :class:`~mi_bivariate.merl.MERLBRDF`.
        min_value: Eq. 1 leaves out cells with truth at or below this (1/sr).
    """

    def __init__(self, truth, min_value: float = 0.0):
        if not isinstance(truth, MERLBRDF):
            raise TypeError(f"the truth must be a 3D MERLBRDF (e.g. mi_bivariate.nbrdf.nbrdf_merl(name)), got a "
                            f"{type(truth).__name__}: the truth comes first, the estimate second")
        valid = truth.valid_mask()
        self.index = np.nonzero(valid)                                   # cells: (i_h, i_d, i_p)
        self.f = np.asarray(truth.table[valid], np.float64)              # (n_cells, 3)
        self.weights = merl_cell_weights()[valid][:, None]
        self.min_value = float(min_value)
        theta_h, theta_d, phi_d = node_angles()
        self.angles = (theta_h[self.index[0]], theta_d[self.index[1]], phi_d[self.index[2]])
        self.region = region_of(self.angles[0], self.angles[1])

    def estimate_at_cells(self, estimate) -> np.ndarray:
        """``(n_cells, 3)`` float64 values of an estimate (see :func:`estimate_on_merl_grid`) at the cells."""
        i_h, i_d, i_p = self.index
        if isinstance(estimate, BivariateBRDF):
            return estimate_on_merl_grid(estimate)[i_h, i_d, 0]
        if isinstance(estimate, (MERLBRDF, np.ndarray)):
            grid = estimate_on_merl_grid(estimate)
            return grid[i_h, i_d, 0] if grid.shape[2] == 1 else grid[i_h, i_d, i_p]
        refuse_probe(estimate, "estimate", "score a BRDF, not the probe")
        if callable(getattr(estimate, "eval", None)):
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                return np.asarray(estimate.eval(*self.angles), np.float64)
        raise TypeError(f"cannot evaluate a {type(estimate).__name__} on the MERL grid")

    def __call__(self, estimate, observed_nodes: Optional[np.ndarray] = None) -> dict:
        f, f_hat = self.f, self.estimate_at_cells(estimate)
        eq1_cells = f > self.min_value
        out = {
            "eq1": relative_rms(f, f_hat, eq1_cells),
            "eq1_rgb": [relative_rms(f[:, c], f_hat[:, c], eq1_cells[:, c]) for c in range(3)],
            "eq1_min": relative_rms(f, f_hat, f > max(self.min_value, 1e-3)),
            "cosine": weighted_relative_l2(f, f_hat, self.weights),
            "log": log_rms(f, f_hat, np.ones_like(f, bool)),
        }
        with np.errstate(invalid="ignore", divide="ignore"):
            rel2 = np.where(eq1_cells & (f > 0), ((f_hat - f) / np.where(f > 0, f, 1.0)) ** 2, 0.0)
        total = float(rel2.sum())
        regions: Dict[str, dict] = {}
        for k, name in enumerate(REGION_NAMES):
            sel = (self.region == k)[:, None] & eq1_cells
            regions[name] = {"eq1": relative_rms(f, f_hat, sel),
                             "share": float(rel2[sel].sum() / total) if total > 0 else float("nan"),
                             "cells": int(sel.sum())}
        out["regions"] = regions
        if observed_nodes is not None:
            cells_obs = observed_cells(observed_nodes)[self.index[0], self.index[1]]
            out["eq1_observed"] = relative_rms(f, f_hat, eq1_cells & cells_obs[:, None])
            out["observed_fraction"] = float(cells_obs.mean()) if cells_obs.size else float("nan")
        return out


def brdf_errors(truth, estimate, min_value: float = 0.0, observed_nodes: Optional[np.ndarray] = None) -> dict:
    """The BRDF errors of ``estimate`` against the 3D ``truth``; see :class:`BRDFErrors`.

    For several estimates of one truth, build a :class:`BRDFErrors` once.
    """
    return BRDFErrors(truth, min_value)(estimate, observed_nodes)


#: A relight floor below this (relative RMSE) gives no ratio: about twice the largest of the references'
#: own noise measured, 2e-4 to 1.1e-3 (``scripts/reference_noise.py`` on the sharpest shared materials). Such
#: a floor (a material whose bivariate table is exact, a Lambertian one) is mostly that noise, and the ratio
#: would not mean anything (a review saw "relight/floor 429734"). The least floor of the 73 shared materials
#: under the five novel probes is 2.8e-3 (pearl-paint under venice_sunset_1k).
MIN_RELIGHT_FLOOR = 2e-3

#: ... and below this many times the reference's own measured noise (:func:`seed_noise`), when it is given:
#: the same "about twice the noise" rule for references less converged than the evaluation's (``--quick``'s
#: measure 5.7e-3). Every ratio of the full evaluation's 23 development materials has a floor at least 3x
#: its reference's noise.
NOISE_FLOOR_FACTOR = 2.0


def relight_errors(image: np.ndarray, floor_image: np.ndarray, truth_image: np.ndarray,
                   mask: np.ndarray, reference_noise: float = 0.0) -> Dict[str, float]:
    """Relighting under one novel probe: the recovery's error, its floor and their ratio.

    ``rel_rmse``: :func:`image_relative_rmse` of the recovered BRDF's image
    against the 3D truth's; ``floor``: the same for the exact reduction's
    table (the paper's phi_d mean on the grid; not a strict lower bound: a
    table fitted to one view can relight that view better, ratios below 1
    are measured); ``ratio``: ``rel_rmse / floor`` (1 = as good as the exact
    reduction; NaN, written as ``null``, where the floor is below :data:`MIN_RELIGHT_FLOOR` or below
    :data:`NOISE_FLOOR_FACTOR` times ``reference_noise``, the truth render's own relative noise). All three
    images must come from the same renderer.
    """
    err = image_relative_rmse(image, truth_image, mask)
    floor = image_relative_rmse(floor_image, truth_image, mask)
    least = max(MIN_RELIGHT_FLOOR, NOISE_FLOOR_FACTOR * float(reference_noise))
    return {"rel_rmse": err, "floor": floor,
            "ratio": err / floor if floor >= least else math.nan,
            "psnr": image_psnr(image, truth_image, mask)}
