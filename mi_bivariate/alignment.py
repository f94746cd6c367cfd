"""Probe alignment: which rotation of the environment explains an image best.

A light probe captured separately from the photo rarely shares its frame
exactly; the paper names this misalignment the main error source for
captured data. Tilt is usually fixed by gravity (world y up), so the free
parameter is the rotation about the vertical axis, the *yaw*. It is
estimated by analysis by synthesis: for a candidate yaw the probe is turned
(:meth:`Probe.rotated`), the lighting matrix of the image's observations is
rebuilt with few normals, and the relative residual
``||I - L f|| / ||I||`` of the best BRDF measures the fit:

- material unknown (``brdf=None``): ``f`` is the constrained, regularised
  solve of Eq. 6 on a coarse st grid (the bivariate model has enough freedom
  to explain any lighting a little, but the right one best);
- material roughly known (``brdf`` given): ``f`` is that BRDF with one free
  scale per channel (exposure and albedo uncertainty), a linear fit.

Search: a coarse grid over 360 degrees, then bounded Brent refinement
(``scipy.optimize.minimize_scalar``) around the best grid point. The
residual curve (every evaluated yaw) is kept for inspection.

Quadrature: the per-candidate lighting matrix uses the environment's texels
(:func:`mi_bivariate.lighting.texel_lighting_matrix`, the probe area-averaged
to about :data:`ALIGN_TEXEL_WIDTH` texels across), not sampled directions.
Its directions turn with the probe, so the residual is a smooth,
deterministic function of the yaw. Measured (red-phenolic MERL-NBRDF sphere,
96 px, grace_256 turned by 25 degrees, 1500 normals): sampled K = 4000
directions put the residual's minimum near 30 degrees (quadrature noise on the
cathedral's small bright windows, residual 0.46 at the minimum); texels put it
at 24-25 degrees (residual 0.065) for 0.3 s per candidate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple

import numpy as np

from mi_bivariate import capture, lighting
from mi_bivariate import prior as prior_mod
from mi_bivariate import solve as solve_mod
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.limits import check_seed, finite_number, whole_number
from mi_bivariate.probes import check_probe

#: Default grid of the per-candidate solve (coarse: only the residual's minimum matters).
ALIGN_GRID = (16, 16)
#: The probe is area-averaged to about this many texels across for the per-candidate lighting matrix.
ALIGN_TEXEL_WIDTH = 128


@dataclass
class YawEstimate:
    """The estimated rotation of a probe about world y.

    Attributes:
        yaw_deg: the estimate in degrees, in (-180, 180]: the image is best
            explained by ``probe.rotated(euler_deg=(0, yaw_deg, 0))``.
        residual: relative residual ``||I - L f|| / ||I||`` there.
        angles_deg: every evaluated yaw (sorted), degrees.
        residuals: the residual at each of them (the residual curve).
        probe: the aligned probe.
        rows: observations used.
    """

    yaw_deg: float
    residual: float
    angles_deg: np.ndarray
    residuals: np.ndarray
    probe: Any
    rows: int = 0
    timings: Dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        return (f"probe yaw {self.yaw_deg:+.2f} deg (relative residual {self.residual:.4f}; "
                f"{len(self.angles_deg)} yaws evaluated on {self.rows} observations)")


def _wrap(angle_deg: float) -> float:
    """An angle in (-180, 180]."""
    a = math.fmod(angle_deg, 360.0)
    a = a - 360.0 if a > 180.0 else a
    return a + 360.0 if a <= -180.0 else a


def _reference_table(brdf: Any, n_t: int, n_s: int) -> np.ndarray:
    """``(n_t * n_s, 3)`` values of a known BRDF at the st nodes."""
    if not isinstance(brdf, BivariateBRDF):
        brdf = BivariateBRDF.reduce(brdf, n_t=n_t, n_s=n_s)
    s = np.linspace(0.0, 1.0, n_s)
    t = np.linspace(0.0, 1.0, n_t)
    return np.asarray(brdf.eval_st(s[None, :], t[:, None]), np.float64).reshape(n_t * n_s, 3)


class _YawResidual:
    """The residual of one observation set as a function of the probe's yaw."""

    def __init__(self, obs: capture.Observations, probe: Any, brdf: Any, grid: Tuple[int, int],
                 texel_width: int, alpha: Optional[float]):
        self.obs, self.probe, self.alpha = obs, probe, alpha
        self.downsample = max(1, int(probe.width) // max(1, int(texel_width)))
        self.n_t, self.n_s = (int(g) for g in grid)
        self.table = None if brdf is None else _reference_table(brdf, self.n_t, self.n_s)
        self.prior = prior_mod.default_prior().resampled(self.n_t, self.n_s) if brdf is None else None
        self.values = obs.values.astype(np.float64)
        self.norm = float(np.linalg.norm(self.values))
        self.sigma = solve_mod.row_sigma(self.values, form="constant")
        self.cache: Dict[float, float] = {}

    def __call__(self, yaw_deg: float) -> float:
        key = round(float(yaw_deg), 9)
        if key not in self.cache:
            probe = self.probe.rotated(euler_deg=(0.0, float(yaw_deg), 0.0))
            L = lighting.texel_lighting_matrix(self.obs, probe, n_t=self.n_t, n_s=self.n_s,
                                               downsample=self.downsample)
            if self.table is None:
                # The residual below is unweighted, so the fit is too (each row counts alike). The
                # pair with the lower residual is kept (the paper's rule): the residual is what the
                # candidates are compared by, and the evidence's pair can switch from one yaw to the
                # next, which made the curve jump (test_capture_realism: -5 deg estimated as -3.5).
                table = solve_mod.solve(L, self.obs.values, self.prior, alpha=self.alpha, sigma=self.sigma,
                                        mean=None, pair_rule="residual").table
                predicted = np.einsum("mnc,nc->mc", L, table.reshape(-1, 3).astype(np.float64))
            else:
                basis = np.einsum("mnc,nc->mc", L, self.table)
                # One non-negative scale per channel: exposure and albedo are not known exactly.
                scale = np.maximum(np.sum(basis * self.values, axis=0) / np.maximum(np.sum(basis * basis, axis=0),
                                                                                   1e-300), 0.0)
                predicted = basis * scale
            self.cache[key] = float(np.linalg.norm(self.values - predicted) / max(self.norm, 1e-300))
        return self.cache[key]


def estimate_yaw(image: np.ndarray, probe: Any, geometry: Any, *, brdf: Any = None, n_normals: int = 1500,
                 texel_width: int = ALIGN_TEXEL_WIDTH, grid: Tuple[int, int] = ALIGN_GRID,
                 coarse_step_deg: float = 15.0,
                 tol_deg: float = 0.05, search_deg: Optional[Tuple[float, float]] = None,
                 mask: Optional[np.ndarray] = None, saturation: Optional[float] = None,
                 max_view_angle_deg: float = 75.0, alpha: Optional[float] = None,
                 seed: int = 0) -> YawEstimate:
    """Estimate the probe's rotation about world y that best explains ``image``.

    Args:
        image: ``(H, W, 3)`` linear image of the known object.
        probe: the probe as captured (:class:`~mi_bivariate.probes.Probe`).
        geometry: the object in the image (any geometry
            :func:`mi_bivariate.capture.image_observations` takes).
        brdf: a roughly known material (:class:`~mi_bivariate.bivariate.BivariateBRDF`,
            MERL table, analytic BRDF, ...), fitted with a free scale per
            channel; ``None``: the material is recovered for every candidate.
        n_normals: rows of the (small) lighting matrix per candidate.
        texel_width: the probe is area-averaged to about this many texels
            across for the per-candidate lighting matrix.
        grid: st grid of the per-candidate solve / reference table.
        coarse_step_deg: spacing of the coarse grid over 360 degrees.
        tol_deg: tolerance of the Brent refinement.
        search_deg: optional ``(low, high)`` yaw interval in degrees instead
            of the full turn (e.g. when the misalignment is known to be small).
        mask, saturation, max_view_angle_deg: as for the observations.
        alpha: regularisation weight of the per-candidate solve (default
            :data:`mi_bivariate.solve.DEFAULT_ALPHA`: one fixed weight, so that the
            candidates' residuals compare; a rule that re-chooses alpha per candidate
            would let a wrong yaw buy a closer fit). For the same reason each channel
            keeps the weight pair with the lower residual (the paper's rule), not the
            evidence's.
        seed: seeds normal selection.

    Returns:
        The estimate, its residual and the residual curve.
    """
    import time

    from scipy.optimize import minimize_scalar

    probe = check_probe(probe)
    n_normals = whole_number("n_normals", n_normals)
    texel_width = whole_number("texel_width", texel_width)
    coarse_step_deg = finite_number("coarse_step_deg", coarse_step_deg)
    tol_deg = finite_number("tol_deg", tol_deg)
    seed = check_seed(seed)
    if n_normals < 1:
        raise InputError("n_normals", f"must be at least 1, got {n_normals}")
    if texel_width < 2:
        raise InputError("texel_width", f"must be at least 2 texels, got {texel_width}")
    if not 0.0 < coarse_step_deg <= 90.0:
        raise InputError("coarse_step_deg", f"must be in (0, 90], got {coarse_step_deg}")
    if not tol_deg > 0.0:
        raise InputError("tol_deg", f"must be above 0, got {tol_deg}")
    if alpha is not None and not finite_number("alpha", alpha) >= 0.0:  # one fixed number (see above)
        raise InputError("alpha", f"must be a number >= 0, got {alpha!r}")
    if search_deg is not None:
        if not isinstance(search_deg, (tuple, list, np.ndarray)) or len(search_deg) != 2:
            raise InputError("search_deg", f"must be (low, high) in degrees, got {search_deg!r}")
        search = tuple(finite_number("search_deg", v) for v in search_deg)
        if not search[1] > search[0]:
            raise InputError("search_deg", f"needs low < high, got {search_deg}")
    t0 = time.perf_counter()
    obs = capture.image_observations(image, geometry, n_normals=n_normals, max_view_angle_deg=max_view_angle_deg,
                                     saturation=saturation, mask=mask, seed=seed)
    residual = _YawResidual(obs, probe, brdf, grid, texel_width,
                            solve_mod.DEFAULT_ALPHA if alpha is None else alpha)
    if search_deg is None:
        coarse = np.arange(-180.0, 180.0, coarse_step_deg)
        low, high = -math.inf, math.inf
    else:
        low, high = search
        coarse = np.linspace(low, high, max(3, int(math.ceil((high - low) / coarse_step_deg)) + 1))
    values = np.array([residual(a) for a in coarse])
    best = float(coarse[int(np.argmin(values))])
    bounds = (max(best - coarse_step_deg, low), min(best + coarse_step_deg, high))
    refined = minimize_scalar(residual, bounds=bounds, method="bounded", options={"xatol": tol_deg})
    yaw = float(refined.x) if refined.fun <= values.min() else best
    angles = np.array(sorted(residual.cache))
    curve = np.array([residual.cache[a] for a in angles])
    yaw = _wrap(yaw)
    return YawEstimate(yaw_deg=yaw, residual=residual(yaw), angles_deg=angles, residuals=curve,
                       probe=probe.rotated(euler_deg=(0.0, yaw, 0.0)), rows=len(obs),
                       timings={"total": time.perf_counter() - t0})
