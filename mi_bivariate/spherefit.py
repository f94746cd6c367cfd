"""Find the sphere in a photograph: its silhouette, centre and radius.

The capture step needs to know where the sphere is. In a render it is known;
in a photograph it must be measured. This module does it from the silhouette:

1. **Region.** From a user mask (its largest connected component) or from the
   image: the log-luminance is thresholded at Otsu's threshold and a ladder
   of quantiles, in both polarities (the sphere may be brighter or darker
   than its background), holes are filled, and the connected component
   (``scipy.ndimage``) whose outline is most convincingly a full circle wins.
2. **Boundary.** Points on the cracks between inside and outside pixels
   (within half a pixel of the true silhouette, without bias). With an image,
   each point is moved to sub-pixel accuracy: along the pixel row (or column)
   that crosses the edge, the mixed pixels' coverages ``(I - B) / (S - B)``
   (``S`` inside, ``B`` outside, linear luminance) sum to the edge's position
   (the area of the strip inside the silhouette).
3. **Fit.** An algebraic circle (Kasa) starts a robust least-squares fit
   (soft-L1 loss, :func:`soft_l1_fit`) of the orthographic
   circle; outliers beyond a MAD-scaled threshold are dropped and the fit
   repeated. With camera intrinsics the silhouette is a cone of rays about
   the centre ray with constant half-angle ``asin(r / d)``; the same robust
   fit finds the centre direction and that angle, hence ``d`` for a given
   radius (only ``r / d`` matters for normals).

The result reports the RMS boundary distance in pixels, the inlier
fraction and how much of the circle was seen, and is flagged confident or
not. An explicit sphere (``CX, CY, R``) always wins over the fit.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import (
    Intrinsics,
    PerspectiveSphereGeometry,
    SphereGeometry,
    check_rotation,
    orthonormal_pair,
)
from mi_bivariate.silhouette import (
    MIN_RADIUS_PX,
    REFINE_PASSES,
    arc_fraction,
    crack_points,
    disc_mask,
    kasa_circle,
    luminance_map,
    refine_boundary,
    segment_luminance,
    segment_sphere,
)

#: Confidence thresholds: RMS boundary distance (pixels), inlier fraction,
#: fraction of the circle's outline observed (and silhouette.MIN_RADIUS_PX).
CONFIDENT_RMS_PX = 0.75
CONFIDENT_INLIER_FRACTION = 0.9
CONFIDENT_ARC_FRACTION = 0.75
#: An explicit sphere's radius may be at most this many times the image's larger side (a close-up
#: of a part of a big sphere still fits; a radius beyond is a mistake).
MAX_RADIUS_FACTOR = 100.0


Geometry = Union[SphereGeometry, PerspectiveSphereGeometry]


@dataclass
class SphereFit:
    """A sphere found in an image.

    Attributes:
        geometry: :class:`SphereGeometry` (orthographic) or
            :class:`PerspectiveSphereGeometry` (with intrinsics).
        cx, cy, radius: the silhouette's best circle in pixels (x right,
            y down, pixel centres at k + 0.5); under perspective the silhouette
            is an ellipse and this is only its approximate circle.
        rms_px: RMS distance of the inlier boundary points to the fitted
            silhouette, pixels (NaN when there was no boundary to measure).
        inlier_fraction: fraction of boundary points kept by the robust fit.
        arc_fraction: fraction of the silhouette's outline (64 angular bins)
            holding inlier points; < 1 when the sphere is cut off or occluded.
        n_boundary: number of boundary points.
        confident: all the checks of :data:`CONFIDENT_RMS_PX` and friends pass.
        problems: why it is not confident (empty when it is).
        method: ``"image"``, ``"mask"`` or ``"user"`` (explicit sphere).
        region: ``(H, W) bool`` the segmented sphere region (None for ``"user"``).
        boundary: ``(N, 2) float64`` boundary points (x, y) in pixels.
        inliers: ``(N,) bool`` boundary points kept by the fit.
    """

    geometry: Geometry
    cx: float
    cy: float
    radius: float
    rms_px: float
    inlier_fraction: float
    arc_fraction: float
    n_boundary: int
    confident: bool
    problems: Tuple[str, ...] = ()
    method: str = "image"
    region: Optional[np.ndarray] = field(default=None, repr=False)
    boundary: Optional[np.ndarray] = field(default=None, repr=False)
    inliers: Optional[np.ndarray] = field(default=None, repr=False)

    def summary(self) -> str:
        """One line: centre, radius, residual and confidence."""
        text = f"sphere ({self.method}): centre ({self.cx:.2f}, {self.cy:.2f}) px, radius {self.radius:.2f} px, "
        if self.method == "user":  # given, not fitted: no inliers or arc of its own, only how the image agrees
            text += (f"the image's outline {self.rms_px:.3f} px RMS from it over {self.n_boundary} points"
                     if self.n_boundary else "not checked against the image (no outline found)")
        else:
            text += (f"boundary RMS {self.rms_px:.3f} px over {self.n_boundary} points "
                     f"({100 * self.inlier_fraction:.0f}% inliers, {100 * self.arc_fraction:.0f}% of the outline)")
        if isinstance(self.geometry, PerspectiveSphereGeometry):
            text += f", distance {self.geometry.distance:.4g} radii" if self.geometry.radius == 1.0 else \
                f", distance {self.geometry.distance:.4g}"
        return text + ("" if self.confident else "; NOT confident: " + "; ".join(self.problems))


def soft_l1_fit(residual_fn: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, f_scale: float,
                max_iterations: int = 100) -> np.ndarray:
    """Robust non-linear least squares with the soft-L1 loss.

    Minimises ``sum_i f^2 rho((r_i(x) / f)^2)``, ``rho(z) = 2 (sqrt(1 + z) - 1)``: quadratic within
    ``f_scale`` of zero, linear beyond (``scipy.optimize.least_squares(loss="soft_l1")``'s problem).
    Iteratively reweighted Gauss-Newton: each step solves the linearised problem with row weights
    ``rho'(z_i) = 1 / sqrt(1 + z_i)``, whose fixed point is the loss's stationary point; a step that
    raises the loss is halved (up to 30 times). The Jacobian is by central differences (step
    ``1e-6 max(1, |x_j|)``). It stops when a step moves no parameter by more than ``1e-10 max(1, |x_j|)``.
    The sphere fit's problems have 3 unknowns and a few hundred residuals; this spares a ``recover``
    process the import of ``scipy.optimize`` (~0.09 s, bytecode compiled), and
    ``tests/test_spherefit.py`` checks it against ``least_squares``.

    Args:
        residual_fn: ``x (P,) -> residuals (N,)`` float64.
        x0: ``(P,)`` start.
        f_scale: the loss's inlier scale, in the residuals' units.

    Returns:
        ``(P,)`` float64.
    """
    x = np.array(x0, dtype=np.float64)

    def loss(r: np.ndarray) -> float:
        return float(np.sum(np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0))

    r = residual_fn(x)
    current = loss(r)
    for _ in range(max_iterations):
        h = 1e-6 * np.maximum(1.0, np.abs(x))
        jac = np.stack([(residual_fn(x + h[j] * e) - residual_fn(x - h[j] * e)) / (2.0 * h[j])
                        for j, e in enumerate(np.eye(len(x)))], axis=1)
        w = 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)
        step = np.linalg.lstsq(jac * np.sqrt(w)[:, None], -np.sqrt(w) * r, rcond=None)[0]
        for _ in range(30):
            trial = x + step
            r_trial = residual_fn(trial)
            trial_loss = loss(r_trial)
            if trial_loss <= current:
                break
            step = step / 2.0
        else:
            break
        x, r, current = trial, r_trial, trial_loss
        if np.all(np.abs(step) <= 1e-10 * np.maximum(1.0, np.abs(x))):
            break
    return x


def _robust_fit(residual_fn, x0: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Robust fit (:func:`soft_l1_fit`), then drop outliers (> max(1 px, 3 MAD-sigmas)) and refit;
    ``(params, inliers)``."""
    x = soft_l1_fit(residual_fn, x0, f_scale=1.0)
    res = residual_fn(x)
    sigma = 1.4826 * np.median(np.abs(res - np.median(res)))
    inliers = np.abs(res) <= max(1.0, 3.0 * sigma)
    if inliers.sum() >= 8 and not inliers.all():
        x = soft_l1_fit(lambda p: residual_fn(p)[inliers], x, f_scale=0.5)
        res = residual_fn(x)
        inliers = np.abs(res) <= max(1.0, 3.0 * sigma)
    return x, inliers


def fit_circle(points: np.ndarray) -> Tuple[float, float, float, np.ndarray, np.ndarray]:
    """Robust circle through boundary points.

    Returns:
        ``(cx, cy, r, residuals (N,), inliers (N,) bool)``; residuals are
        signed distances to the circle in pixels (positive outside).
    """
    points = np.asarray(points, np.float64)

    def residuals(p):
        return np.hypot(points[:, 0] - p[0], points[:, 1] - p[1]) - p[2]

    x, inliers = _robust_fit(residuals, np.array(kasa_circle(points)))
    return float(x[0]), float(x[1]), abs(float(x[2])), residuals(x), inliers


def fit_cone(points: np.ndarray, intrinsics: Intrinsics, circle: Tuple[float, float, float]
             ) -> Tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Silhouette cone of a sphere under perspective: centre ray and half-angle.

    The rays through the silhouette make the constant angle ``asin(r / d)``
    with the ray to the sphere's centre. Each residual is the pixel distance
    between a boundary point and the projection of its ray rotated (in the
    plane of the centre ray) onto the cone, signed positive outside.

    Args:
        points: ``(N, 2)`` boundary points (x, y) in pixels.
        intrinsics: the camera.
        circle: ``(cx, cy, r)`` a pixel circle to start from.

    Returns:
        ``(axis (3,) unit camera-frame centre direction, half_angle radians,
        residuals (N,) pixels, inliers (N,) bool)``.
    """
    rays = intrinsics.rays(points[:, 0], points[:, 1])
    a0 = intrinsics.rays(circle[0], circle[1])
    e1, e2 = orthonormal_pair(a0)

    def cone(p):
        a = a0 + p[0] * e1 + p[1] * e2
        return a / np.linalg.norm(a), p[2]

    def residuals(p):
        a, alpha = cone(p)
        cos_b = rays @ a
        w = rays - cos_b[:, None] * a
        sin_b = np.linalg.norm(w, axis=1)
        w /= np.maximum(sin_b, 1e-15)[:, None]
        on_cone = math.cos(alpha) * a + math.sin(alpha) * w
        distance = np.linalg.norm(intrinsics.project(on_cone) - points, axis=1)
        return np.sign(np.arctan2(sin_b, cos_b) - alpha) * distance

    alpha0 = float(np.median(np.arccos(np.clip(rays @ a0, -1.0, 1.0))))
    x, inliers = _robust_fit(residuals, np.array([0.0, 0.0, alpha0]))
    a, alpha = cone(x)
    return a, float(alpha), residuals(x), inliers


# ----------------------------------------------------------- front door

def _check_intrinsics(intrinsics: Any, source: str) -> Intrinsics:
    try:
        return Intrinsics.coerce(intrinsics)
    except InputError as exc:  # named as the photo's
        raise exc.within(source, "intrinsics") from None


def _cone_from_circle(k: Intrinsics, cx: float, cy: float, r: float) -> Tuple[np.ndarray, float]:
    """The silhouette cone that best fits a pixel circle (:func:`fit_cone` on 64 points of it).

    Off the image's centre the silhouette is an ellipse whose best circle is not centred on the
    sphere's centre ray: that ray with the mean angle to four rim points (kept only for a circle no
    cone in front of the camera fits) put a sphere 15 degrees off-axis at 4.2 radii 1 degree off,
    its normals 5 degrees.
    """
    phi = np.linspace(0.0, 2.0 * math.pi, 64, endpoint=False)
    axis, alpha, _, _ = fit_cone(np.stack([cx + r * np.cos(phi), cy + r * np.sin(phi)], axis=1), k, (cx, cy, r))
    if axis[2] < 0.0 and 0.0 < alpha < 0.5 * math.pi:
        return axis, alpha
    axis = k.rays(cx, cy)
    rim = k.rays(np.array([cx + r, cx - r, cx, cx]), np.array([cy, cy, cy + r, cy - r]))
    return axis, float(np.mean(np.arccos(np.clip(rim @ axis, -1.0, 1.0))))


def _make_geometry(cx: float, cy: float, r: float, k: Optional[Intrinsics], cone: Optional[Tuple],
                   radius: float, rot: np.ndarray) -> Geometry:
    if k is None:
        return SphereGeometry(cx, cy, r, camera_to_world=rot)
    axis, alpha = cone
    return PerspectiveSphereGeometry(k, axis * radius / math.sin(alpha), radius, rot)


def fit_sphere(image: Optional[np.ndarray] = None, mask: Optional[np.ndarray] = None, *,
               sphere: Optional[Sequence[float]] = None, intrinsics: Any = None, radius: float = 1.0,
               camera_to_world: Any = None, source: str = "image", warn: bool = True,
               seed: int = 0) -> SphereFit:
    """Find the sphere in an image (or mask) and describe it as a geometry.

    Args:
        image: ``(H, W, 3)`` (or ``(H, W)``) linear image; refines the
            boundary to sub-pixel accuracy and, without ``mask``, finds the sphere.
        mask: ``(H, W) bool`` user mask of the sphere (largest component used).
        sphere: explicit ``(cx, cy, r)`` in pixels: wins over any fit
            (the fit still runs when possible, to warn if they disagree).
        intrinsics: ``(fx, fy, cx, cy)`` in pixels or :class:`Intrinsics`:
            perspective model (else orthographic).
        radius: sphere radius in world units for the perspective model
            (only ``radius / distance`` matters for normals).
        camera_to_world: ``(3, 3)`` camera rotation (default identity).
        source: name of the image in messages.
        warn: emit an :class:`InputWarning` when the fit is not confident.
        seed: seeds the RANSAC stage of :func:`segment_sphere`.

    Raises:
        InputError: neither image nor mask, bad shapes, an empty mask, an
            explicit sphere outside the image, or no sphere found.
    """
    rot = check_rotation(camera_to_world, source)
    k = None if intrinsics is None else _check_intrinsics(intrinsics, source)
    if not (isinstance(radius, (int, float, np.floating, np.integer)) and math.isfinite(radius) and radius > 0):
        raise InputError(source, f"sphere radius must be a positive number, got {radius!r}")
    if image is None and mask is None and sphere is None:
        raise InputError(source, "nothing to fit: give an image, a mask or an explicit sphere")
    lum = None if image is None else luminance_map(image, source)
    shape = lum.shape if lum is not None else (None if mask is None else np.shape(mask)[:2])

    if sphere is not None:
        return _user_sphere(sphere, lum, mask, shape, k, radius, rot, source)

    if lum is not None and mask is None and not np.isfinite(lum).any():
        raise InputError(source, "has no finite pixel", "check the file: every value is NaN or infinite")
    # Without an image, the mask's own size is checked as an image's would be.
    region = segment_luminance(lum if lum is not None else luminance_map(np.zeros(shape), source), mask, source,
                               seed=seed)
    points, _, _ = crack_points(region)
    if len(points) < 8:
        raise InputError(source, f"the sphere's outline has only {len(points)} boundary points",
                         "check the mask: it leaves no sphere outline inside the image" if mask is not None else
                         "the object covers the whole image or is tiny: crop the photo around the sphere, or give "
                         "the sphere (sphere=(cx, cy, r); --sphere on the command line)")
    cx, cy, r, res, inliers = fit_circle(points)
    cone = fit_cone(points, k, (cx, cy, r)) if k is not None else None
    if lum is not None:
        # A user mask says where the outline is visible: refine only near its own outline.
        near = None
        if mask is not None:
            from scipy import ndimage

            outline = region ^ ndimage.binary_erosion(region)
            near = ndimage.distance_transform_edt(~outline) <= 3.0
        for _ in range(REFINE_PASSES):
            # Cracks of the current model's silhouette lie within a pixel of the true
            # one, where the coverage windows of refine_boundary are centred.
            model = disc_mask(shape, cx, cy, r) if k is None else \
                _make_geometry(cx, cy, r, k, cone[:2], radius, rot).normals_and_views(shape[1], shape[0])[2]
            crack, axis, outward = crack_points(model)
            refined, _ = refine_boundary(lum, crack, axis, outward, (cx, cy))
            if near is not None:
                keep = near[np.clip(refined[:, 1].astype(int), 0, shape[0] - 1),
                            np.clip(refined[:, 0].astype(int), 0, shape[1] - 1)]
                refined = refined[keep]
            if len(refined) < max(8, len(crack) // 4):
                break
            points = refined
            cx, cy, r, res, inliers = fit_circle(points)
            if k is not None:
                cone = fit_cone(points, k, (cx, cy, r))
    if k is not None:
        res, inliers = cone[2], cone[3]
    geometry = _make_geometry(cx, cy, r, k, None if cone is None else cone[:2], radius, rot)
    result = _assess(geometry, cx, cy, r, points, res, inliers, shape, "mask" if mask is not None else "image",
                     region)
    if warn and not result.confident:
        warnings.warn(f"{source}: sphere fit is not confident: {'; '.join(result.problems)} "
                      f"(found centre ({cx:.1f}, {cy:.1f}), radius {r:.1f} px; pass the sphere explicitly "
                      "if this is wrong)", InputWarning, stacklevel=2)
    return result


def _assess(geometry: Geometry, cx: float, cy: float, r: float, points: np.ndarray, res: np.ndarray,
            inliers: np.ndarray, shape: Tuple[int, int], method: str, region: Optional[np.ndarray]) -> SphereFit:
    height, width = shape
    rms = float(np.sqrt(np.mean(res[inliers] ** 2))) if inliers.any() else float("nan")
    inlier_fraction = float(np.mean(inliers)) if len(inliers) else 0.0
    arc = arc_fraction(points[inliers], cx, cy)
    problems = []
    if not rms <= CONFIDENT_RMS_PX:
        problems.append(f"boundary RMS {rms:.2f} px > {CONFIDENT_RMS_PX} px")
    if inlier_fraction < CONFIDENT_INLIER_FRACTION:
        problems.append(f"only {100 * inlier_fraction:.0f}% of the outline fits a circle")
    if arc < CONFIDENT_ARC_FRACTION:
        problems.append(f"only {100 * arc:.0f}% of the outline is seen")
    if r < MIN_RADIUS_PX:
        problems.append(f"radius {r:.1f} px < {MIN_RADIUS_PX} px")
    if cx - r < 0 or cy - r < 0 or cx + r > width or cy + r > height:
        problems.append(f"the sphere extends beyond the {width}x{height} image")
    return SphereFit(geometry=geometry, cx=cx, cy=cy, radius=r, rms_px=rms, inlier_fraction=inlier_fraction,
                     arc_fraction=arc, n_boundary=len(points), confident=not problems, problems=tuple(problems),
                     method=method, region=region, boundary=points, inliers=inliers)


def _user_sphere(sphere: Sequence[float], lum: Optional[np.ndarray], mask: Optional[np.ndarray],
                 shape: Tuple[int, int], k: Optional[Intrinsics], radius: float, rot: np.ndarray,
                 source: str) -> SphereFit:
    """An explicit ``(cx, cy, r)``: checked against the image, compared with the fit when there is one."""
    try:
        cx, cy, r = (float(v) for v in sphere)
    except (TypeError, ValueError):
        raise InputError(source, f"sphere must be (CX, CY, R) in pixels, got {sphere!r}") from None
    if not all(math.isfinite(v) for v in (cx, cy, r)) or r <= 0:
        raise InputError(source, f"invalid sphere: centre ({cx:g}, {cy:g}), radius {r:g} px")
    height, width = shape if shape is not None else (math.inf, math.inf)
    if r > MAX_RADIUS_FACTOR * max(width, height):  # a typo or a unit slip, whose numbers would overflow
        raise InputError(source, f"the sphere's radius {r:g} px is more than {MAX_RADIUS_FACTOR:g} times the "
                                 f"{width}x{height} image's larger side",
                         "give the sphere's centre and radius (--sphere CX,CY,R) in this image's pixels")
    if cx + r <= 0 or cy + r <= 0 or cx - r >= width or cy - r >= height:
        raise InputError(source, f"the sphere (centre ({cx:g}, {cy:g}), radius {r:g} px) lies outside "
                                 f"the {width}x{height} image",
                         "give the sphere's centre and radius (--sphere CX,CY,R) in this image's pixels")
    geometry = _make_geometry(cx, cy, r, k, None if k is None else _cone_from_circle(k, cx, cy, r), radius, rot)
    fit = None
    if lum is not None or mask is not None:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", InputWarning)
                fit = fit_sphere(lum, mask, source=source, warn=False)
        except InputError:
            fit = None
    if fit is not None and fit.confident:
        off = math.hypot(fit.cx - cx, fit.cy - cy) + abs(fit.radius - r)
        if off > max(2.0, 0.02 * r):
            warnings.warn(f"{source}: the given sphere ({cx:g}, {cy:g}, {r:g}) is {off:.1f} px away from the "
                          f"silhouette found in the image ({fit.cx:.1f}, {fit.cy:.1f}, {fit.radius:.1f}); "
                          "using the given one", InputWarning, stacklevel=3)
    problems: Tuple[str, ...] = ()
    if cx - r < 0 or cy - r < 0 or cx + r > width or cy + r > height:
        problems = (f"the sphere extends beyond the {width}x{height} image",)
    rms = float("nan")
    if fit is not None:
        rms = float(np.sqrt(np.mean((np.hypot(fit.boundary[:, 0] - cx, fit.boundary[:, 1] - cy) - r) ** 2)))
    return SphereFit(geometry=geometry, cx=cx, cy=cy, radius=r, rms_px=rms, inlier_fraction=1.0, arc_fraction=1.0,
                     n_boundary=0 if fit is None else fit.n_boundary, confident=not problems, problems=problems,
                     method="user", region=None if fit is None else fit.region,
                     boundary=None if fit is None else fit.boundary)
