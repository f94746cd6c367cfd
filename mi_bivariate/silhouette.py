"""The sphere's silhouette in a photograph: its region, boundary points and first circle.

Steps 1 and 2 of :mod:`mi_bivariate.spherefit` (its docstring gives the
method): the region (from a mask or by thresholding the log-luminance), the
boundary points on the cracks between inside and outside pixels, their
sub-pixel refinement, and the algebraic circle through them. The robust
circle or cone fit and the confidence checks are :mod:`mi_bivariate.spherefit`'s.
"""

from __future__ import annotations

import math
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.common import LUMINANCE_WEIGHTS
from mi_bivariate.errors import InputError, array_from
from mi_bivariate.images import CHUNK_ROWS, block_mean, bounding_box, circle_box

#: The smallest sphere radius (pixels) looked for, and trusted.
MIN_RADIUS_PX = 8.0

#: Log-luminance quantiles tried as thresholds besides Otsu's.
THRESHOLD_QUANTILES = tuple(np.linspace(0.05, 0.95, 10))

#: Sub-pixel refinement: pixels on each side of a crack, and the smallest
#: relative contrast |S - B| / max(|S|, |B|) for which it is trusted.
REFINE_HALF_WINDOW = 2
REFINE_MIN_CONTRAST = 0.2
REFINE_PASSES = 2

#: Scale (pixels) of the Gaussian smoothing before edge detection.
EDGE_SIGMA_PX = 1.0

#: The automatic search (no mask) of a photo larger than this on its longer side (pixels) runs first on its
#: log-luminance box-averaged by an integer factor (:func:`segment_sphere`): searched at full resolution, a
#: 2048 x 2048 photo took 5.4 s and a 4096 x 4096 one ~20 s (2-core VM; docs/recovery.md Round 39).
SEARCH_SIDE_PX = 512


# ------------------------------------------------------------------ inputs

def luminance_map(image: np.ndarray, source: str = "image") -> np.ndarray:
    """Linear luminance ``(H, W) float64`` of an ``(H, W)``, ``(H, W, 1|3|4)`` image; NaN where not finite."""
    image = array_from(image, source, "an (H, W) or (H, W, 3) image")
    if not np.issubdtype(image.dtype, np.number) or np.iscomplexobj(image):
        raise InputError(source, f"image has non-numeric dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        lum = np.empty(image.shape[:2])
        # By rows: the float64 copy of the colours stays small (a 4096 px photo's would take 400 MB).
        for start in range(0, lum.shape[0], CHUNK_ROWS):
            rows = slice(start, start + CHUNK_ROWS)
            lum[rows] = image[rows, :, :3].astype(np.float64) @ LUMINANCE_WEIGHTS
    elif image.ndim == 3 and image.shape[2] == 1 or image.ndim == 2:
        lum = np.array(image[..., 0] if image.ndim == 3 else image, dtype=np.float64)  # a copy: written below
    else:
        raise InputError(source, f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")
    if lum.shape[0] < 3 or lum.shape[1] < 3:
        raise InputError(source, f"image of {lum.shape[1]}x{lum.shape[0]} pixels is too small to hold a sphere",
                         "give a photo with the sphere at least a few pixels across")
    lum[~np.isfinite(lum)] = np.nan
    return lum


def _check_mask(mask: Any, shape: Tuple[int, int], source: str) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim == 3 and mask.shape[2] in (1, 3, 4):
        mask = np.any(mask[..., :3] > 0, axis=2)
    if mask.shape != shape:
        raise InputError(source, f"mask is {mask.shape[1] if mask.ndim > 1 else '?'}x{mask.shape[0] if mask.ndim else '?'}"
                                 f" but the image is {shape[1]}x{shape[0]}", "give a mask of the image's size")
    mask = mask.astype(bool)
    if not mask.any():
        raise InputError(source, "the mask selects no pixel", "check the mask: the sphere's pixels must be True (> 0 in an image)")
    return mask


# ------------------------------------------------------------- segmentation

def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of the finite ``values`` (maximises the between-class variance)."""
    values = values[np.isfinite(values)]
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return lo
    hist, edges = np.histogram(values, bins=bins, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist).astype(np.float64)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[1:][np.argmax(between[:-1])])


def log_luminance(lum: np.ndarray) -> np.ndarray:
    """``log(lum + eps)`` with ``eps`` a 1e-4 fraction of the bright pixels (black stays finite)."""
    positive = lum[np.isfinite(lum) & (lum > 0.0)]
    eps = 1e-4 * float(np.percentile(positive, 99.0, overwrite_input=True)) if positive.size else 1.0
    out = np.clip(lum, 0.0, None)  # then in place: one array of the photo's size, not three
    out += eps
    with np.errstate(invalid="ignore"):
        return np.log(out, out=out)


def crack_points(region: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints of the cracks between inside and outside pixels of a region.

    Returns:
        ``points (N, 2)`` (x, y) in pixels, ``axis (N,) int`` (0: crack
        between horizontal neighbours, 1: vertical), ``outward (N,) int``
        (+1 when the outside pixel has the larger index along ``axis``).
    """
    region = np.asarray(region, bool)
    # Within the region's box and a pixel around it (within the frame), where every crack is: the same
    # cracks, in the same order, as over the whole frame.
    rows, cols = bounding_box(region)
    y0, x0 = max(rows.start - 1, 0), max(cols.start - 1, 0)
    region = region[y0:rows.stop + 1, x0:cols.stop + 1]
    jh, ih = np.nonzero(region[:, :-1] != region[:, 1:])
    jv, iv = np.nonzero(region[:-1, :] != region[1:, :])
    points = np.concatenate([np.stack([ih + (x0 + 1.0), jh + (y0 + 0.5)], axis=1),
                             np.stack([iv + (x0 + 0.5), jv + (y0 + 1.0)], axis=1)])
    axis = np.concatenate([np.zeros(len(jh), int), np.ones(len(jv), int)])
    outward = np.concatenate([np.where(region[jh, ih], 1, -1), np.where(region[jv, iv], 1, -1)])
    return points, axis, outward


def _fill_components(binary: np.ndarray, min_area: int, keep: int = 4) -> list:
    """Hole-filled connected components of ``binary``, the ``keep`` largest with at least ``min_area`` pixels."""
    from scipy import ndimage

    labels, n = ndimage.label(binary)
    if n == 0:
        return []
    areas = np.bincount(labels.ravel())[1:]
    boxes = ndimage.find_objects(labels)
    parts = []
    for k in np.argsort(areas)[::-1][:keep]:
        if areas[k] < min_area:
            break
        # Fill holes inside the bounding box only: much cheaper than the whole image.
        box = boxes[k]
        region = np.zeros(binary.shape, bool)
        region[box] = filled(labels[box] == k + 1)
        parts.append(region)
    return parts


def filled(binary: np.ndarray) -> np.ndarray:
    """``(H, W) bool``: ``binary`` with its holes filled, as :func:`scipy.ndimage.binary_fill_holes` (the
    background pixels that no 4-connected path of background joins to the frame's edge become True),
    found by labelling the background once instead of dilating from the edge until nothing changes:
    the same pixels (``tests/test_spherefit.py`` compares the two), ~2.5x faster on a 3600 px sphere
    (0.08 s against 0.19-0.22 s on this project's 2-core VM)."""
    from scipy import ndimage

    labels, n = ndimage.label(~binary)
    if n == 0:
        return binary.copy()
    outside = np.zeros(n + 1, dtype=bool)
    outside[np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])] = True
    outside[0] = False  # binary's own pixels
    return ~outside[labels]


def disc_mask(shape: Tuple[int, int], cx: float, cy: float, r: float) -> np.ndarray:
    """``(H, W) bool``: pixel centres inside the circle (computed in the circle's box only)."""
    mask = np.zeros(shape, dtype=bool)
    rows, cols = circle_box(shape, cx, cy, r)
    x2 = (np.arange(cols.start, cols.stop) + 0.5 - cx)[None, :] ** 2
    y2 = (np.arange(rows.start, rows.stop) + 0.5 - cy)[:, None] ** 2
    for start in range(0, y2.shape[0], CHUNK_ROWS):  # by rows: the float64 sums stay small
        part = x2 + y2[start:start + CHUNK_ROWS] < r * r
        mask[rows.start + start:rows.start + start + len(part), cols] = part
    return mask


def _region_circle(region: np.ndarray) -> Optional[Tuple[float, float, float]]:
    """The circle of a region whose outline is one (>= 90% of its cracks within 1.5 px,
    area within 10% of the disc's part inside the image, half the outline seen), else None."""
    points, _, _ = crack_points(region)
    if len(points) < 16:
        return None
    cx, cy, r = kasa_circle(points)
    if not np.isfinite(r) or r < MIN_RADIUS_PX / 2 or r > 2 * max(region.shape):
        return None
    inliers = np.abs(np.hypot(points[:, 0] - cx, points[:, 1] - cy) - r) < 1.5
    disc = int(np.count_nonzero(disc_mask(region.shape, cx, cy, r)))  # a sphere may be cut off by the frame
    if np.mean(inliers) < 0.9 or abs(float(region.sum()) / max(disc, 1) - 1.0) > 0.1 \
            or arc_fraction(points[inliers], cx, cy) < 0.5:
        return None
    return cx, cy, r


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples at pixel positions (x, y) (pixel centres at k + 0.5); NaN outside."""
    from scipy import ndimage

    out = ndimage.map_coordinates(image, [y - 0.5, x - 0.5], order=1, mode="constant", cval=np.nan)
    inside = (x >= 0.5) & (y >= 0.5) & (x <= image.shape[1] - 0.5) & (y <= image.shape[0] - 0.5)
    return np.where(inside, out, np.nan)


def edge_support(log_lum: np.ndarray, cx: float, cy: float, r: float, contrast: float = 0.1) -> int:
    """Length (pixels) of a circle's outline along which the image has a silhouette-like edge.

    A point of the outline supports the circle when the log-luminance steps
    by more than ``contrast`` across it (1.5 px either side) and that step is
    larger than the steps just inside and just outside it (an edge, not texture).
    """
    n = max(16, int(2 * math.pi * r))
    phi = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    c, s = np.cos(phi), np.sin(phi)
    level = [_sample(log_lum, cx + (r + d) * c, cy + (r + d) * s) for d in EDGE_RINGS_PX]
    step = np.abs(level[1] - level[2])
    with np.errstate(invalid="ignore"):
        ok = (step > contrast) & (step > np.abs(level[0] - level[1])) & (step > np.abs(level[2] - level[3]))
    return int(np.count_nonzero(ok))


#: The rings :func:`edge_support` samples, at these distances (pixels) from the circle.
EDGE_RINGS_PX = (-4.5, -1.5, 1.5, 4.5)
#: Tile side (pixels) of :func:`_smoothed_near`.
SMOOTHED_TILE_PX = 64


def _smoothed_near(log_lum: np.ndarray, circles: Sequence[Tuple[float, float, float]],
                   sigma: float = EDGE_SIGMA_PX) -> np.ndarray:
    """:func:`_smoothed` where :func:`edge_support` reads it for each of the ``circles`` ``(cx, cy, r)``, NaN
    elsewhere: the tiles of :data:`SMOOTHED_TILE_PX` that come within its rings and their bilinear
    neighbours of an outline, each filtered with the kernel's reach of pixels around it (the image's own
    edge where it is there), so the values are the whole image's bit for bit. A large sphere's box is
    mostly inside its outline: for a 3686 px box and two circles, 0.42 s (0.71-0.75 s on a first call) for
    the whole box against 0.12-0.15 s here (2-core VM)."""
    from scipy import ndimage

    height, width = log_lum.shape
    finite = np.isfinite(log_lum)
    fill = None if finite.all() else (np.median(log_lum[finite]) if finite.any() else 0.0)
    kernel = int(4.0 * sigma + 0.5)  # scipy's radius at gaussian_filter's default truncate (4 sigma)
    reach = max(abs(d) for d in EDGE_RINGS_PX) + 2.0  # a sample's bilinear neighbours lie within sqrt(2) px
    tile = SMOOTHED_TILE_PX
    y0, x0 = np.arange(0, height, tile), np.arange(0, width, tile)
    y1, x1 = np.minimum(y0 + tile, height), np.minimum(x0 + tile, width)
    need = np.zeros((len(y0), len(x0)), dtype=bool)
    for cx, cy, r in circles:  # each tile's nearest and farthest pixel centre from the circle's centre
        near = np.hypot((np.clip(cy, y0 + 0.5, y1 - 0.5) - cy)[:, None],
                        (np.clip(cx, x0 + 0.5, x1 - 0.5) - cx)[None, :])
        far = np.hypot(np.maximum(np.abs(y0 + 0.5 - cy), np.abs(y1 - 0.5 - cy))[:, None],
                       np.maximum(np.abs(x0 + 0.5 - cx), np.abs(x1 - 0.5 - cx))[None, :])
        need |= (near <= r + reach) & (far >= r - reach)
    out = np.full(log_lum.shape, np.nan)
    for i, j in zip(*np.nonzero(need)):
        rows = slice(max(y0[i] - kernel, 0), min(y1[i] + kernel, height))
        cols = slice(max(x0[j] - kernel, 0), min(x1[j] + kernel, width))
        part = log_lum[rows, cols] if fill is None else np.where(finite[rows, cols], log_lum[rows, cols], fill)
        out[y0[i]:y1[i], x0[j]:x1[j]] = ndimage.gaussian_filter(part, sigma)[
            y0[i] - rows.start:y1[i] - rows.start, x0[j] - cols.start:x1[j] - cols.start]
    return out


def _smoothed(log_lum: np.ndarray, sigma: float = EDGE_SIGMA_PX) -> np.ndarray:
    """Gaussian-smoothed log-luminance (non-finite pixels replaced by the median):
    edges at the scale of the silhouette, not of pixel noise."""
    from scipy import ndimage

    finite = np.isfinite(log_lum)
    if finite.all():  # (the median of a 4096 px photo's pixels costs ~0.3 s, for nothing to fill)
        return ndimage.gaussian_filter(log_lum, sigma)
    image = np.where(finite, log_lum, np.median(log_lum[finite]) if finite.any() else 0.0)
    return ndimage.gaussian_filter(image, sigma)


def _edge_pixels(log_lum: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Edge pixels of the log-luminance (gradient maxima across the edge): ``(x, y) (N, 2)``, unit gradients ``(N, 2)``."""
    from scipy import ndimage

    image = _smoothed(log_lum)
    gx, gy = ndimage.sobel(image, axis=1) / 8.0, ndimage.sobel(image, axis=0) / 8.0
    mag = np.hypot(gx, gy)
    # Non-maximum suppression along the gradient, quantised to 4 directions.
    angle = np.mod(np.arctan2(gy, gx), np.pi)
    q = np.round(angle / (np.pi / 4)).astype(int) % 4
    steps = np.array([[0, 1], [1, 1], [1, 0], [1, -1]])  # (dy, dx) per direction
    padded = np.pad(mag, 1)
    h, w = mag.shape
    rows, cols = np.mgrid[0:h, 0:w]
    dy, dx = steps[q, 0], steps[q, 1]
    peak = (mag >= padded[rows + 1 + dy, cols + 1 + dx]) & (mag >= padded[rows + 1 - dy, cols + 1 - dx])
    # Edges stand out of the noise (median gradient) and step by >= ~10% in radiance.
    edge = peak & (mag > max(0.05, 4.0 * float(np.median(mag))))
    jy, ix = np.nonzero(edge)
    grad = np.stack([gx[jy, ix], gy[jy, ix]], axis=1) / mag[jy, ix, None]
    return np.stack([ix + 0.5, jy + 0.5], axis=1), grad


def ransac_circles(points: np.ndarray, gradients: np.ndarray, r_range: Tuple[float, float], n_trials: int = 2000,
                   keep: int = 4, seed: int = 0, max_points: int = 3000) -> list:
    """Circles with the most edge points on them (within 1.5 px, gradient within ~25 deg of radial).

    Random triplets of edge points define candidate circles (their
    circumcircles); each is scored by its consistent edge points, and the
    ``keep`` best are refitted (Kasa) to their inliers. At most ``max_points``
    edge points (a random subset) vote. Deterministic for a seed.
    """
    if len(points) < 3:
        return []
    rng = np.random.default_rng(seed)
    if len(points) > max_points:
        pick = rng.choice(len(points), max_points, replace=False)
        points, gradients = points[pick], gradients[pick]
    tri = points[rng.integers(0, len(points), (n_trials, 3))]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    d = 2.0 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    ok = np.abs(d) > 1e-9
    a, b, c, d = a[ok], b[ok], c[ok], d[ok]
    sa, sb, sc = (np.sum(v * v, axis=1) for v in (a, b, c))
    ux = (sa * (b[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - b[:, 1])) / d
    uy = (sa * (c[:, 0] - b[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (b[:, 0] - a[:, 0])) / d
    radius = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    ok = (radius >= r_range[0]) & (radius <= r_range[1])
    ux, uy, radius = ux[ok], uy[ok], radius[ok]
    votes = np.zeros(len(radius), int)
    points32, gradients32 = points.astype(np.float32), gradients.astype(np.float32)
    ux32, uy32, radius32 = ux.astype(np.float32), uy.astype(np.float32), radius.astype(np.float32)
    for lo in range(0, len(radius), 256):  # chunks bound the (hypotheses x points) memory
        sl = slice(lo, lo + 256)
        dx = points32[None, :, 0] - ux32[sl, None]
        dy = points32[None, :, 1] - uy32[sl, None]
        dist = np.sqrt(dx * dx + dy * dy)
        radial = np.abs(dx * gradients32[None, :, 0] + dy * gradients32[None, :, 1]) > 0.9 * dist
        votes[sl] = np.count_nonzero((np.abs(dist - radius32[sl, None]) < 1.5) & radial, axis=1)
    circles = []
    for k in np.argsort(votes)[::-1][:keep]:
        dist = np.hypot(points[:, 0] - ux[k], points[:, 1] - uy[k])
        inliers = np.abs(dist - radius[k]) < 2.0
        if inliers.sum() >= 8:
            circles.append(kasa_circle(points[inliers]))
    return circles


def segment_sphere(image: np.ndarray, mask: Optional[np.ndarray] = None, source: str = "image",
                   seed: int = 0) -> np.ndarray:
    """The sphere's silhouette region ``(H, W) bool``.

    With ``mask``: its largest connected component, holes filled. Otherwise
    candidate circles come from (a) connected components of the
    log-luminance thresholded at Otsu's threshold and at
    :data:`THRESHOLD_QUANTILES` (both polarities, holes filled) whose outline
    is a circle, and (b) RANSAC circles through edge pixels (for spheres in
    front of a background as bright as themselves). The candidate with the
    longest :func:`edge_support` wins; its region (a component, or the disc
    of a RANSAC circle) is returned.

    A photo larger than :data:`SEARCH_SIDE_PX` on its longer side is searched first in its
    log-luminance box-averaged by an integer factor (:func:`_coarse_region`,
    :func:`~mi_bivariate.images.block_mean`); where a threshold component wins there, the
    region is cut again at full resolution in the circle's bounding box, at that threshold and at
    the radiance midway across the circle, and the cut whose outline passes the same circle checks
    at full resolution with the longer edge support is kept. Otherwise (a RANSAC circle, a sphere
    under :data:`MIN_RADIUS_PX` coarse pixels, no cut that holds up) the full-resolution search runs
    as for a small image.

    Raises:
        InputError: no finite pixel, empty mask, or no circular region found.
    """
    return segment_luminance(luminance_map(image, source), mask, source, seed)


def segment_luminance(lum: np.ndarray, mask: Optional[np.ndarray] = None, source: str = "image",
                      seed: int = 0) -> np.ndarray:
    """:func:`segment_sphere` of the luminance ``lum`` (:func:`luminance_map`'s ``(H, W) float64``) a caller
    has already computed."""
    height, width = lum.shape
    if mask is not None:
        mask = _check_mask(mask, (height, width), source)
        return _fill_components(mask, min_area=1, keep=1)[0]
    if not np.isfinite(lum).any():
        raise InputError(source, "has no finite pixel", "check the file: every value is NaN or infinite")
    log_lum = log_luminance(lum)
    factor = math.ceil(max(height, width) / SEARCH_SIDE_PX)
    if factor >= 2:
        region = _coarse_region(log_lum, factor, seed)
        if region is not None:
            return region
    (cx, cy, r), region, _ = _search(log_lum, source, seed)
    return region if region is not None else disc_mask(lum.shape, cx, cy, r)


def _search(log_lum: np.ndarray, source: str, seed: int) -> Tuple[Tuple[float, float, float], Optional[np.ndarray],
                                                                   Optional[Tuple[float, bool]]]:
    """The winning candidate of :func:`segment_sphere`'s search: ``(circle, region, cut)``, with
    ``region`` and ``cut`` (its threshold and whether the region is above it) ``None`` for a RANSAC circle."""
    height, width = log_lum.shape
    finite = log_lum[np.isfinite(log_lum)]
    thresholds = np.unique(np.concatenate([[otsu_threshold(finite)], np.quantile(finite, THRESHOLD_QUANTILES)]))
    min_area = max(int(math.pi * MIN_RADIUS_PX ** 2), int(2e-4 * height * width))
    candidates = []
    with np.errstate(invalid="ignore"):
        classes = [(log_lum > t, (float(t), True)) for t in thresholds] + \
                  [(log_lum <= t, (float(t), False)) for t in thresholds]
    for binary, cut in classes:
        for region in _fill_components(binary, min_area):
            circle = _region_circle(region)
            if circle is not None:
                candidates.append((circle, region, cut))
    smooth = _smoothed(log_lum)
    support = [edge_support(smooth, *circle) for circle, _, _ in candidates]
    # RANSAC only when no threshold region has a clear edge all round (it costs more).
    if not any(n >= 0.9 * 2 * math.pi * c[2] for n, (c, _, _) in zip(support, candidates)):
        edges, gradients = _edge_pixels(log_lum)
        for circle in ransac_circles(edges, gradients, (MIN_RADIUS_PX, max(height, width)), seed=seed):
            candidates.append((circle, None, None))
            support.append(edge_support(smooth, *circle))
    if not candidates:
        raise InputError(source, "no sphere found: no region of the image has a circular outline",
                         "pass the sphere explicitly (CX,CY,R) or a mask of it")
    best = candidates[int(np.argmax(support))]
    if max(support) < 0.25 * 2 * math.pi * best[0][2]:
        raise InputError(source, "no sphere found: no circular outline with a clear edge",
                         "pass the sphere explicitly (CX,CY,R) or a mask of it")
    return best


def _coarse_region(log_lum: np.ndarray, factor: int, seed: int) -> Optional[np.ndarray]:
    """:func:`segment_sphere`'s region found in ``log_lum`` box-averaged by ``factor``, cut again at full
    resolution, or ``None`` where the full-resolution search must decide.

    The coarse search places the circle. At full resolution, in the circle's bounding box, two
    thresholds are cut: the coarse winner's, and the radiance midway between the medians just inside
    and just outside the circle (``2 factor + 2`` pixels either side; where they differ by at least
    ``edge_support``'s contrast). The coarse winner's is one of several that tie at the coarse scale;
    the first of them lies near the background's level, and its contour sits pixels outside a soft edge
    or bleeds into a noisy background, while the midpoint can notch a dark rim on a black background.
    Of the cuts whose region (the component covering most of the coarse disc, holes filled) passes
    :func:`_region_circle` at full resolution, the one whose circle has the longer
    :func:`edge_support` wins, as in the full search."""
    from scipy import ndimage

    try:
        (cx, cy, r), _, cut = _search(block_mean(log_lum, factor), "", seed)
    except InputError:
        return None
    if cut is None:  # a RANSAC circle: the coarse pixels cannot place its edge well enough
        return None
    cx, cy, r = cx * factor, cy * factor, r * factor
    margin = 2 * factor + 2
    height, width = log_lum.shape
    y0, y1 = max(0, math.floor(cy - r - margin)), min(height, math.ceil(cy + r + margin))
    x0, x1 = max(0, math.floor(cx - r - margin)), min(width, math.ceil(cx + r + margin))
    if y1 - y0 < 3 or x1 - x0 < 3:
        return None
    box = log_lum[y0:y1, x0:x1]
    cuts = [cut]
    if r > 2 * margin:
        phi = np.linspace(0.0, 2.0 * math.pi, max(64, int(2.0 * math.pi * r)), endpoint=False)
        inside, outside = (_sample(log_lum, cx + (r + d) * np.cos(phi), cy + (r + d) * np.sin(phi))
                           for d in (-margin, margin))
        inside, outside = inside[np.isfinite(inside)], outside[np.isfinite(outside)]
        if inside.size >= 16 and outside.size >= 16:
            level_in, level_out = float(np.median(inside)), float(np.median(outside))
            if abs(level_in - level_out) >= 0.1:
                # Midway in radiance: a blurred step's contour there is its edge (midway in log-luminance,
                # the contour of a 10:1 step blurred by 2 px lay 1.3 px outside it).
                cuts.insert(0, (float(np.logaddexp(level_in, level_out) - math.log(2.0)), level_in > level_out))
    disc = disc_mask(box.shape, cx - x0, cy - y0, r)
    found = []  # (circle in the box, region) of each cut that holds up
    for threshold, above in cuts:
        with np.errstate(invalid="ignore"):
            labels, n = ndimage.label(box > threshold if above else box <= threshold)
        overlap = np.bincount(labels[disc], minlength=n + 1)  # the component covering most of the coarse disc
        overlap[0] = 0
        if not overlap.any():
            continue
        region = np.zeros(log_lum.shape, bool)
        region[y0:y1, x0:x1] = filled(labels == int(np.argmax(overlap)))
        circle = _region_circle(region)
        if circle is not None:
            found.append(((circle[0] - x0, circle[1] - y0, circle[2]), region))
    if not found:
        return None
    smooth = _smoothed_near(box, [circle for circle, _ in found])
    support = [edge_support(smooth, *circle) for circle, _ in found]
    return found[int(np.argmax(support))][1]  # the first of the longest, as the cuts' order


# ---------------------------------------------------------------- boundary

def refine_boundary(lum: np.ndarray, points: np.ndarray, axis: np.ndarray, outward: np.ndarray,
                    centre: Tuple[float, float]) -> Tuple[np.ndarray, np.ndarray]:
    """Sub-pixel silhouette points from the coverage of the mixed pixels.

    Along the row (``axis`` 0) or column (1) through each crack, the pixels
    ``m = -h..h-1`` around it are mixes of the inside value ``S`` (mean of the
    two pixels beyond them inside) and the outside value ``B`` (two beyond
    outside). Their coverages ``clip((I - B) / (S - B), 0, 1)`` sum to the
    length of the strip inside the silhouette, which places the edge.

    Only cracks crossed within 45 degrees of the edge normal (radial
    direction from ``centre``) with enough contrast are refined.

    Returns:
        ``points (K, 2)`` refined (x, y) and ``used (N,) bool`` (which cracks).
    """
    height, width = lum.shape
    h = REFINE_HALF_WINDOW
    radial = points - np.asarray(centre)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
    along = np.abs(radial[np.arange(len(points)), axis])
    # Pixel index of the first pixel beyond the crack (outside), then offsets.
    pos = np.where(axis == 0, points[:, 0], points[:, 1])
    other = np.where(axis == 0, points[:, 1], points[:, 0]).astype(int)  # row (axis 0) or column centre - 0.5
    first_out = np.where(outward > 0, pos, pos - 1.0).astype(int)
    offsets = np.arange(-h - 2, h + 2)  # m: pixels at pos + outward * (m + 0.5)
    index = np.where(outward[:, None] > 0, first_out[:, None] + offsets, first_out[:, None] - offsets)
    limit = np.where(axis == 0, width, height)
    ok = (index.min(axis=1) >= 0) & (index.max(axis=1) < limit) & (along >= math.sqrt(0.5) - 1e-9)
    index = np.clip(index, 0, limit[:, None] - 1)
    rows = np.where(axis[:, None] == 0, other[:, None], index)
    cols = np.where(axis[:, None] == 0, index, other[:, None])
    values = lum[rows, cols]
    inside, mixed, outside = values[:, :2].mean(axis=1), values[:, 2:2 + 2 * h], values[:, -2:].mean(axis=1)
    contrast = inside - outside
    scale = np.maximum(np.abs(inside), np.abs(outside))
    ok &= np.all(np.isfinite(values), axis=1) & (np.abs(contrast) > REFINE_MIN_CONTRAST * np.maximum(scale, 1e-30))
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = np.clip((mixed - outside[:, None]) / contrast[:, None], 0.0, 1.0)
    shift = coverage.sum(axis=1) - h  # edge offset from the crack, outward positive
    ok &= np.abs(shift) <= 1.0
    refined = points.copy()
    refined[np.arange(len(points)), axis] += outward * np.where(ok, shift, 0.0)
    return refined[ok], ok


def arc_fraction(points: np.ndarray, cx: float, cy: float, bins: int = 64) -> float:
    if len(points) == 0:
        return 0.0
    angle = np.arctan2(points[:, 1] - cy, points[:, 0] - cx)
    k = np.floor((angle + math.pi) / (2 * math.pi) * bins).astype(int) % bins
    return float(np.unique(k).size) / bins


# --------------------------------------------------------------------- fits

def kasa_circle(points: np.ndarray) -> Tuple[float, float, float]:
    """Algebraic (Kasa) circle ``(cx, cy, r)`` through ``(N, 2)`` points (linear least squares)."""
    x, y = points[:, 0], points[:, 1]
    mx, my = x.mean(), y.mean()  # centred for conditioning
    u, v = x - mx, y - my
    a = np.stack([u, v, np.ones_like(u)], axis=1)
    sol, *_ = np.linalg.lstsq(a, u * u + v * v, rcond=None)
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    r2 = sol[2] + cx * cx + cy * cy
    return float(cx + mx), float(cy + my), float(math.sqrt(r2)) if r2 > 0 else float("nan")
