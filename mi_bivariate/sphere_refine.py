"""Refine a fitted sphere by the photo's own shading.

:func:`mi_bivariate.spherefit.fit_sphere` places the sphere's edge photometrically. A glossy
sphere's rim darkens over its last 2-3 pixels (masking at grazing view), so on such spheres that
fit is 0.1-0.5 px off in centre and 0.2-0.6 px in radius. Under grace_latlong_1k that raised four
metals' relight error by 25-85% over the exact sphere's (``benchmarks/sphere_fit_bias.py``,
docs/recovery.md section 9); refined, the median over 8 materials went 1.17 -> 1.01 times the exact
sphere's, the worst 1.84 -> 1.29 (leave-one-out priors).

This module finds the centre and radius under which the bivariate model explains the image best.
The criterion is the recovery's own: over a fixed set of pixels (the lattice pixels of the
starting geometry, up to :data:`MAX_VIEW_ANGLE_DEG`), minimise over the geometry

    min_f  ||(I - L(geometry) f) / sigma||^2 + lambda ||R f||^2

This is variable projection. ``f`` is the table, re-solved in closed form (ridge, no
non-negativity) at every candidate geometry, with the first recovery's alpha and prior variant
per channel. ``sigma`` is the rows' model error and camera noise, as the first recovery weighs
them (:func:`mi_bivariate.solve.row_sigma` with its noise model): the recovery's own data term. The
geometry moves by ``scipy.optimize.least_squares`` with a central-difference Jacobian (0.05 px
steps). The pixels and the lighting matrix's random numbers stay fixed (one seed), so the
objective changes smoothly with the geometry at the scale of a pixel (not of its hundredth: a
forward-difference Jacobian stopped short of the minimum). The pixel set stays on any sphere within
:data:`MAX_SHIFT_PX` of the start.

A minimum further than :data:`MAX_SHIFT_PX` from the starting outline is found but not taken.

Orthographic spheres (:class:`~mi_bivariate.geometry.SphereGeometry`) only. Each evaluation is a
lighting matrix of ``n_normals`` rows and a solve, about 0.2-0.3 s on two cores. A refinement
takes 32-80 of them (a budget of 80), 10-32 s. ``recover --refine-sphere`` runs it between a
first recovery and the final one (:func:`mi_bivariate.recover.refine_sphere_and_recover`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import scipy.linalg

from mi_bivariate import capture, lighting
from mi_bivariate import solve as solve_mod
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.limits import whole_number
from mi_bivariate.prior import Prior, default_prior
from mi_bivariate.probes import Probe
from mi_bivariate.solve.common import penalty_weight

#: The pixels the objective uses: the starting geometry's lattice pixels within this angle of the
#: view (degrees). Below the recovery's 80 so that a geometry moved by up to ~1 px keeps them all
#: on the sphere.
MAX_VIEW_ANGLE_DEG = 76.0

#: The finite-difference step of the Jacobian, pixels.
STEP_PX = 0.05

#: The farthest the refined circle may lie from the starting one anywhere on its outline,
#: ``|centre shift| + |radius change|``, pixels. The silhouette places the outline to within the
#: rim's last pixel (its fit was at most 0.61 px off in 32 measured cases); a refinement that moves
#: it further is led by the model's own error where the shading says little about the geometry
#: (measured: a dark diffuse fabric moved 1.1-6.3 px and relit 8-11% worse), and is not taken.
MAX_SHIFT_PX = 1.0

#: The most the relative residual of the recovery under the refined sphere may exceed the first
#: recovery's (over the pixels both use) before the refined sphere is given up
#: (:func:`mi_bivariate.recover.refine_sphere_and_recover`): a safety net for an objective led astray.
#: In docs/recovery.md section 9 it never fired: the refined recoveries of clean 256 px spheres
#: fitted at most 0.6% worse than the fitted ones. Over the pixels both use, because each recovery
#: samples its own: on a noisy 96 px sphere one refined recovery's residual was 28% higher on its own
#: pixels and 11% lower on the common ones (bright Monte-Carlo outliers only its lattice sampled).
MAX_RESIDUAL_RISE = 1.05


def outline_shift(a: SphereGeometry, b: SphereGeometry) -> float:
    """The farthest circle ``a``'s outline lies from ``b``'s, ``|centre shift| + |radius change|``, px."""
    return float(np.hypot(a.cx - b.cx, a.cy - b.cy) + abs(a.radius - b.radius))


class _Budget(Exception):
    """The search spent its evaluations (raised inside the objective, caught by :func:`refine_sphere`)."""


@dataclass
class SphereRefinement:
    """The result of :func:`refine_sphere`.

    Attributes:
        geometry: the refined sphere.
        start: the sphere it started from.
        cost_start, cost: half the objective at the start and at the end.
        evaluations: objective evaluations (the Jacobian's included).
        seconds: wall time.
        found: the minimum found (it is ``geometry`` unless it lay beyond :data:`MAX_SHIFT_PX`).
        accepted: whether ``geometry`` is the minimum found; if not, it is ``start``.
        status: why the search stopped (``least_squares``'s message, or the evaluation budget).
        reason: why a minimum within :data:`MAX_SHIFT_PX` was not taken after all (empty otherwise).
    """

    geometry: SphereGeometry
    start: SphereGeometry
    cost_start: float
    cost: float
    evaluations: int
    seconds: float
    found: SphereGeometry
    accepted: bool
    status: str
    reason: str = ""

    @property
    def shift_px(self) -> float:
        """The farthest the found circle lies from the starting one (:func:`outline_shift`), px."""
        return outline_shift(self.found, self.start)

    def summary(self) -> str:
        """One line: refined (from, to, cost, evaluations, time), or why not."""
        f, s = self.found, self.start
        moved = (f"centre ({s.cx:.2f}, {s.cy:.2f}) -> ({f.cx:.2f}, {f.cy:.2f}) px, radius {s.radius:.2f} -> "
                 f"{f.radius:.2f} px, cost {self.cost_start:.4g} -> {self.cost:.4g} ({self.evaluations} evaluations, "
                 f"{self.seconds:.1f} s)")
        if self.accepted and self.shift_px < 1e-3:
            return f"sphere not moved by the shading ({self.status}): {moved}"
        if self.accepted:
            return f"sphere refined by shading: {moved}"
        return f"{self.rejection()}: {moved}"

    def rejection(self) -> str:
        """One short line: why the minimum found was not taken (empty when it was)."""
        if self.accepted:
            return ""
        if self.reason:
            return f"sphere not refined: {self.reason}; kept the fit"
        return (f"sphere not refined: the shading's best sphere lies {self.shift_px:.2f} px from the fitted outline "
                f"(more than {MAX_SHIFT_PX:g} px: the shading does not pin the sphere down; kept the fit)")


def refine_sphere(image: np.ndarray, probe: Probe, geometry: SphereGeometry, *,
                  alphas: Sequence[float], winner: Sequence[str], prior: Optional[Prior] = None,
                  grid: Sequence[int] = (32, 32), n_normals: int = 2000, n_dirs: int = 2000,
                  max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG, saturation: Optional[float] = None,
                  mask: Optional[np.ndarray] = None, seed: int = 0, sampling: str = "mis",
                  noise: Optional[Sequence[float]] = None, max_evaluations: int = 80,
                  source: str = "image") -> SphereRefinement:
    """The sphere's centre and radius that let the bivariate model explain ``image`` best.

    Args:
        image: ``(H, W, 3)`` linear image of the sphere.
        probe: its lighting.
        geometry: the starting sphere (e.g. :func:`mi_bivariate.spherefit.fit_sphere`'s).
        alphas: ``(3,)`` the smoothness prior's alpha per channel (a first recovery's
            ``solution.alphas``).
        winner: ``(3,)`` the prior variant per channel (its ``solution.winner``).
        prior: the smoothness prior (default: the packaged one), resampled to ``grid``.
        grid: ``(n_t, n_s)``.
        n_normals: lattice normals M of the fixed pixel set (before the drops).
        n_dirs: light directions K per row.
        max_view_angle_deg: the pixel set's largest view angle (degrees).
        saturation: drop pixels with any channel at or above it.
        mask: ``(H, W) bool`` usable pixels.
        seed: the lattice's and the lighting matrix's seed.
        sampling: the lighting matrix's light directions (:func:`mi_bivariate.lighting.lighting_matrix`).
        noise: the camera's noise ``(a, b)``, variance ``a I + b`` in the image's units (scalars or
            ``(3,)`` each; the first recovery's estimate), or ``None`` (a clean image).
        max_evaluations: the most objective evaluations, the Jacobian's included (each central-
            difference Jacobian costs 6); at the budget the best geometry evaluated is taken.
        source: the image's name in messages.

    Raises:
        InputError: a geometry other than an orthographic sphere, alphas / winner not one per channel,
            ``max_evaluations`` not a whole number of at least 1, or fewer than 64 pixels to refine with.
    """
    if not isinstance(geometry, SphereGeometry):
        raise InputError(source, f"refining the sphere needs an orthographic sphere, got {type(geometry).__name__}",
                         "refine only orthographic spheres")
    alphas = [float(a) for a in alphas]
    winner = [str(w) for w in winner]
    if len(alphas) != 3 or len(winner) != 3:
        raise InputError(source, "alphas and winner must give one value per channel")
    max_evaluations = whole_number("max_evaluations", max_evaluations)
    if max_evaluations < 1:  # the starting sphere's evaluation is one
        raise InputError("max_evaluations", f"must be at least 1, got {max_evaluations}")
    t0 = time.perf_counter()
    n_t, n_s = (int(v) for v in grid)
    prior = default_prior() if prior is None else prior
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    penalties = {w: prior.penalty_matrix(w) for w in set(winner)}  # R^T R, (N, N)
    # Pixels that stay on any sphere within MAX_SHIFT_PX of the start (a pixel's corner is 0.71 px
    # from its centre): on a small sphere this cuts below max_view_angle_deg.
    inner = max(0.0, 1.0 - (MAX_SHIFT_PX + math.sqrt(0.5)) / float(geometry.radius))
    angle = min(float(max_view_angle_deg), math.degrees(math.asin(inner)))
    with warnings.catch_warnings():  # the recovery this refines has said what it had to say about the image
        warnings.simplefilter("ignore", InputWarning)
        obs0 = capture.observations_from_sphere(image, geometry, n_normals=n_normals, max_view_angle_deg=angle,
                                                saturation=saturation, mask=mask, seed=seed, source=source)
    if len(obs0.values) < 64:
        raise InputError(source, f"only {len(obs0.values)} pixels to refine the sphere with",
                         "refine a larger sphere, or give the sphere explicitly")
    rows = obs0.pixels[:, 0].astype(np.float64) + 0.5
    cols = obs0.pixels[:, 1].astype(np.float64) + 0.5
    values = np.asarray(obs0.values, np.float64)
    sigma = solve_mod.row_sigma(values, obs0.image_index, noise=None if noise is None else [noise])
    count = [0]
    best = [math.inf, None]  # (cost, geometry) of the best evaluation, for a search stopped at the budget

    def residuals(p: np.ndarray) -> np.ndarray:
        if count[0] >= max_evaluations:
            raise _Budget
        count[0] += 1
        trial = dataclasses.replace(geometry, cx=float(p[0]), cy=float(p[1]), radius=float(p[2]))
        # A trial step far beyond MAX_SHIFT_PX can put a rim pixel off the sphere: held just on it.
        obs = dataclasses.replace(obs0, normals=trial.normals_at(cols, rows, onto_sphere=True))
        L = lighting.lighting_matrix(obs, probe, n_t=n_t, n_s=n_s, n_dirs=n_dirs, seed=seed, sampling=sampling,
                                     progress=False)
        data = solve_mod.prepare_data_term(L, values, sigma)
        table = np.empty((n_t * n_s, 3))
        for k in range(3):
            lam = penalty_weight(alphas[k], n_t * n_s, data.level[k])
            table[:, k] = scipy.linalg.solve(data.gram[k] + lam * penalties[winner[k]], data.rhs[k], assume_a="pos")
        predicted = np.einsum("mnc,nc->mc", L, table, optimize=True)
        r = ((values - predicted) / sigma).ravel()
        cost = 0.5 * float(r @ r)
        if cost < best[0]:
            best[0], best[1] = cost, np.array(p, np.float64)
        return r

    start = np.array([geometry.cx, geometry.cy, geometry.radius], np.float64)
    r0 = residuals(start)
    from scipy.optimize import least_squares  # here, not at the top: its import costs ~0.09 s

    try:
        # Central differences: the objective is smooth at the scale of a pixel but not of its
        # hundredth (a forward-difference Jacobian stopped the search short of the minimum).
        fit = least_squares(residuals, start, jac="3-point", diff_step=STEP_PX / np.abs(start).clip(1.0),
                            x_scale=np.ones(3), xtol=1e-3 * STEP_PX / np.linalg.norm(start))
        x, cost, status = fit.x, float(fit.cost), fit.message
    except _Budget:
        x, cost, status = best[1], best[0], f"stopped at the budget of {max_evaluations} evaluations"
    found = dataclasses.replace(geometry, cx=float(x[0]), cy=float(x[1]), radius=float(x[2]))
    accepted = bool(np.all(np.isfinite(x)) and outline_shift(found, geometry) <= MAX_SHIFT_PX)
    return SphereRefinement(geometry=found if accepted else geometry, start=geometry, cost_start=0.5 * float(r0 @ r0),
                            cost=cost, evaluations=count[0], seconds=time.perf_counter() - t0, found=found,
                            accepted=accepted, status=str(status))
