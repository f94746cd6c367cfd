"""From images of a known shape to observations: normals, views and pixel values.

Each observation is one pixel: the world normal ``n`` it sees, the world
direction ``v`` towards the camera, and its linear RGB value ``I(v, n)``; it
becomes one row of the lighting matrix (Eq. 5).

Normal selection follows the paper (Sect. 4): ``n_normals`` normals spread
uniformly (in solid angle) over the visible hemisphere, of which those more
than ``max_view_angle_deg`` from the view are discarded (low signal to noise
near the silhouette). The spread comes from a spherical Fibonacci lattice
about the view axis: ``cos theta_k = 1 - (k + 1/2) / n`` is stratified in
``cos theta`` (uniform in solid angle) and the azimuths follow the golden
angle, with a seeded azimuthal rotation. Each lattice normal is mapped to its
nearest pixel (exactly, for a sphere; by nearest pixel normal, for a normal
map), duplicates are merged, and the pixel's own (centre) normal is used.

Every lattice normal that does not become an observation is counted in
``Observations.dropped`` under the first reason that applies, in this order:

==================  =========================================================
``view_angle``      further than ``max_view_angle_deg`` from the view (the
                    lattice normal, or the normal of the pixel it maps to)
``outside_image``   its pixel lies outside the image
``silhouette``      its pixel is not entirely inside the sphere's silhouette
                    (a mixed sphere/background pixel), or has no valid normal
``outside_mask``    its pixel is outside the user's mask
``duplicate``       its pixel was already chosen by an earlier lattice normal
``nonfinite``       NaN or Inf in any channel
``negative``        a negative channel
``saturated``       a channel at or above ``saturation``
==================  =========================================================
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.errors import InputError, InputWarning, array_from
from mi_bivariate.geometry import Geometry, SphereGeometry, check_rotation, check_sphere
from mi_bivariate.images import bounding_box
from mi_bivariate.limits import check_brightest

DROP_REASONS: Tuple[str, ...] = ("view_angle", "outside_image", "silhouette", "outside_mask",
                                 "duplicate", "nonfinite", "negative", "saturated")

#: Fewer usable observations than this gives an :class:`InputWarning`.
MIN_OBSERVATIONS = 256

#: Warn when more than this fraction of in-sphere samples has bad values.
BAD_VALUE_WARN_FRACTION = 0.05

#: The finest sub-pixel grid of the pixel-footprint model (per side).
FOOTPRINT_MAX_SIDE = 8

_GOLDEN = (1.0 + math.sqrt(5.0)) / 2.0


@dataclass
class Observations:
    """Pixels of one or more images as constraints on the BRDF (rows of Eq. 5).

    Attributes:
        normals: ``(M, 3) float64`` unit world normals.
        views: ``(M, 3) float64`` unit world directions towards the camera.
        values: ``(M, 3) float32`` linear RGB pixel values.
        probe_index: ``(M,) int32`` which probe (of the list given to
            :func:`mi_bivariate.lighting.lighting_matrix`) lit each row.
        dropped: lattice normals that did not become rows, per reason
            (:data:`DROP_REASONS`).
        pixels: ``(M, 2) int32`` (row, column) of each observation in its image.
        image_index: ``(M,) int32`` which image each row came from (after
            :func:`stack`).
        positions: ``(M, 3) float64`` world positions of the surface points
            (meshes; NaN rows or ``None`` where unknown). Rows with a position
            get shadow rays when the lighting matrix is given an occluder.
        geometric_normals: ``(M, 3) float64`` unit geometric (face) normals at
            ``positions``, used to offset shadow rays exactly as Mitsuba does
            (``None``: the shading normals).
        footprint_normals: ``(P, 3) float64`` unit world normals across the
            pixel footprints of the rows that need more than their centre
            normal (the pixel-footprint model, :func:`observations_from_sphere`
            with ``footprint``): such a row's lighting-matrix row is the mean
            of the rows of its footprint normals. ``None``: every row is its
            centre normal (the paper's model).
        footprint_rows: ``(P,) int64`` the row of each footprint normal, ascending.
    """

    normals: np.ndarray
    views: np.ndarray
    values: np.ndarray
    probe_index: np.ndarray
    dropped: Dict[str, int] = field(default_factory=lambda: {k: 0 for k in DROP_REASONS})
    pixels: Optional[np.ndarray] = None
    image_index: Optional[np.ndarray] = None
    positions: Optional[np.ndarray] = None
    geometric_normals: Optional[np.ndarray] = None
    footprint_normals: Optional[np.ndarray] = None
    footprint_rows: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        m = len(self.normals)
        if self.pixels is None:
            self.pixels = np.full((m, 2), -1, dtype=np.int32)
        if self.image_index is None:
            self.image_index = np.zeros(m, dtype=np.int32)
        names = ["views", "values", "probe_index", "pixels", "image_index"]
        names += [k for k in ("positions", "geometric_normals") if getattr(self, k) is not None]
        for name in names:
            if len(getattr(self, name)) != m:
                raise ValueError(f"Observations.{name} has {len(getattr(self, name))} rows, normals have {m}")
        if (self.footprint_normals is None) != (self.footprint_rows is None):
            raise ValueError("Observations.footprint_normals and footprint_rows go together")
        if self.footprint_rows is not None:
            rows = self.footprint_rows
            if len(rows) != len(self.footprint_normals) or (len(rows) and (rows.min() < 0 or rows.max() >= m
                                                                           or np.any(np.diff(rows) < 0))):
                raise ValueError("Observations.footprint_rows must be ascending row indices, one per footprint normal")

    def __len__(self) -> int:
        return len(self.normals)

    def subset(self, rows: np.ndarray) -> "Observations":
        """The observations at ``rows`` (distinct indices or a boolean mask); ``dropped`` is kept."""
        def pick(a: Optional[np.ndarray]) -> Optional[np.ndarray]:
            return None if a is None else a[rows]

        fp_normals = fp_rows = None
        if self.footprint_rows is not None:
            new_of_old = np.full(len(self), -1, dtype=np.int64)
            new_of_old[np.arange(len(self))[rows]] = np.arange(len(self.normals[rows]))
            new = new_of_old[self.footprint_rows]
            keep = np.flatnonzero(new >= 0)
            keep = keep[np.argsort(new[keep], kind="stable")]
            fp_normals, fp_rows = self.footprint_normals[keep], new[keep]
        return Observations(self.normals[rows], self.views[rows], self.values[rows],
                            self.probe_index[rows], dict(self.dropped), self.pixels[rows],
                            self.image_index[rows], pick(self.positions), pick(self.geometric_normals),
                            fp_normals, fp_rows)

    @property
    def has_footprints(self) -> bool:
        """Whether some rows are modelled by their pixel footprint (see ``footprint_normals``)."""
        return self.footprint_rows is not None and len(self.footprint_rows) > 0

    @property
    def has_positions(self) -> bool:
        """Whether any row knows its surface position (and so can be shadow-tested)."""
        return self.positions is not None and bool(np.any(np.all(np.isfinite(self.positions), axis=1)))

    def with_probe_index(self, index: int) -> "Observations":
        """A copy with every row lit by probe ``index``."""
        return replace(self, probe_index=np.full(len(self), int(index), dtype=np.int32),
                       dropped=dict(self.dropped))


def hemisphere_lattice(n: int, seed: int = 0) -> np.ndarray:
    """Spherical Fibonacci lattice on the upper (+z) hemisphere, ``(n, 3) float64``.

    Uniform in solid angle: ``z_k = 1 - (k + 1/2) / n``, golden-angle azimuths,
    rotated about z by a seeded random angle.
    """
    k = np.arange(n, dtype=np.float64)
    z = 1.0 - (k + 0.5) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    offset = np.random.default_rng(seed).random()
    phi = 2.0 * np.pi * np.mod(k / _GOLDEN + offset, 1.0)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _frame_about(axis: np.ndarray) -> np.ndarray:
    """A ``(3, 3)`` rotation whose third column is the unit vector ``axis``."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def check_image(image: np.ndarray, source: str = "image") -> np.ndarray:
    """``image`` as ``(H, W, 3) float32`` linear RGB (no copy when it is one), else :class:`InputError`
    naming ``source``: another shape (a grey or RGBA image), no pixels, a type other than real numbers,
    values beyond :data:`~mi_bivariate.limits.MAX_RADIANCE`, or all (zeros aside) below
    :data:`~mi_bivariate.limits.MIN_RADIANCE`. Integers are read as they
    are, with an :class:`InputWarning`."""
    image = array_from(image, source, "an (H, W, 3) RGB image")
    if image.ndim != 3 or image.shape[2] != 3:
        hint = None
        if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
            hint = "a grey image: repeat it into three channels, np.dstack([image] * 3), under a grey probe"
        elif image.ndim == 3 and image.shape[2] == 4:
            hint = "drop the alpha channel: image[..., :3]"
        raise InputError(source, f"expected an (H, W, 3) RGB image, got shape {image.shape}", hint)
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise InputError(source, f"empty image of shape {image.shape}")
    if not np.issubdtype(image.dtype, np.number) or np.issubdtype(image.dtype, np.complexfloating):
        raise InputError(source, f"image has dtype {image.dtype}; expected real numbers (linear radiance)")
    if np.issubdtype(image.dtype, np.integer):
        warnings.warn(f"{source}: the image holds integers ({image.dtype}), read as linear radiance as they are; "
                      "an 8- or 16-bit photo is usually gamma-encoded and clipped (give a linear HDR image, "
                      "e.g. an EXR merged from several exposures)", InputWarning, stacklevel=3)
    else:  # the brightest finite magnitude: two passes and no copy where every value is finite
        brightest = max(abs(float(np.max(image))), abs(float(np.min(image))))
        if not math.isfinite(brightest):
            brightest = float(np.max(np.abs(image), initial=0.0, where=np.isfinite(image)))
        check_brightest(brightest, source)
    return image.astype(np.float32, copy=False)


def check_mask(mask: Optional[np.ndarray], shape: Tuple[int, int], source: str) -> Optional[np.ndarray]:
    """A user's usable-pixel ``mask`` as an ``(H, W) bool`` array (``None`` stays ``None``: every pixel),
    else :class:`InputError` naming ``source``: a mask not of the image's ``shape`` ``(H, W)``."""
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise InputError(source, f"mask has shape {mask.shape} but the image is {shape[0]}x{shape[1]}",
                         "pass an (H, W) boolean mask of the image's size")
    return mask.astype(bool)


def _plateau_warning(image: np.ndarray, mask: np.ndarray, source: str) -> None:
    """Warn when many of the ``mask``'s pixels (``(h, w) bool``, of the ``(h, w, 3)`` ``image``) sit exactly at
    their maximum (a clipped image). Pixels with a non-finite channel are left out."""
    channels = [image[..., c] for c in range(3)]
    finite = mask.copy()
    for channel in channels:
        finite &= np.isfinite(channel)
    n_finite = int(np.count_nonzero(finite))
    if n_finite == 0:
        return
    peak = max(float(np.max(channel, initial=-np.inf, where=finite)) for channel in channels)
    if peak <= 0.0:
        return
    at_peak = np.zeros_like(finite)
    for channel in channels:
        at_peak |= channel == peak
    at_peak = int(np.count_nonzero(at_peak & finite))
    if at_peak >= max(16, int(0.002 * n_finite)):
        warnings.warn(f"{source}: {at_peak} sphere pixels sit exactly at the maximum value {peak:g}; "
                      f"the image looks clipped (drop them with --saturation {peak:g}, or saturation={peak:g} "
                      "in Python)",
                      InputWarning, stacklevel=3)


def _finish(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, normals: np.ndarray,
            views: np.ndarray, dropped: Dict[str, int], saturation: Optional[float],
            source: str, probe_index: int) -> Observations:
    """Deduplicate pixels, check their values and build :class:`Observations`.

    ``rows, cols, normals, views`` are per lattice normal that survived the
    geometric checks, in lattice order.
    """
    flat = rows.astype(np.int64) * image.shape[1] + cols
    _, first = np.unique(flat, return_index=True)
    first.sort()  # keep lattice order: deterministic and spatially interleaved
    dropped["duplicate"] += len(flat) - len(first)
    rows, cols, normals, views = rows[first], cols[first], normals[first], views[first]

    values = image[rows, cols]
    keep = np.ones(len(values), dtype=bool)
    bad = ~np.all(np.isfinite(values), axis=1)
    dropped["nonfinite"] += int(np.count_nonzero(bad))
    keep &= ~bad
    with np.errstate(invalid="ignore"):
        bad = keep & np.any(values < 0.0, axis=1)
        dropped["negative"] += int(np.count_nonzero(bad))
        keep &= ~bad
        if saturation is not None:
            bad = keep & np.any(values >= saturation, axis=1)
            dropped["saturated"] += int(np.count_nonzero(bad))
            keep &= ~bad

    n_ok = int(np.count_nonzero(keep))
    if n_ok == 0:
        raise InputError(source, "no usable pixel on the object (dropped: "
                         f"{', '.join(f'{k} {v}' for k, v in dropped.items() if v)})",
                         "check where the object is (the sphere, or the mesh and its camera), the mask and "
                         "--max-view-angle")
    if not np.any(values[keep] > 0.0):
        # None of the object's pixels, dropped or kept, is lit, but the photo is: the object is placed where
        # the photo is dark (a perspective sphere far too large for the image, a mesh seen from elsewhere).
        if not np.any(np.nan_to_num(values, nan=0.0, posinf=0.0) > 0.0) and np.any(np.isfinite(image) & (image > 0.0)):
            raise InputError(source, "no positive pixel value where the object is placed, though the photo has "
                             "light elsewhere", "check where the object is (the sphere's centre and radius, the "
                             "field of view, or the mesh and its camera) and the mask")
        raise InputError(source, "the image is black on the object (no positive pixel value)",
                         "check the exposure, the sphere position and the mask")
    n_bad = len(values) - n_ok
    if len(values) and n_bad > BAD_VALUE_WARN_FRACTION * len(values):
        parts = ", ".join(f"{k} {dropped[k]}" for k in ("nonfinite", "negative", "saturated") if dropped[k])
        warnings.warn(f"{source}: {n_bad} of {len(values)} sampled sphere pixels have unusable values "
                      f"({parts}) and were dropped", InputWarning, stacklevel=3)
    if n_ok < MIN_OBSERVATIONS:
        warnings.warn(f"{source}: only {n_ok} usable observations (fewer than {MIN_OBSERVATIONS}); "
                      "the recovered BRDF will be poorly constrained", InputWarning, stacklevel=3)
    return Observations(normals=normals[keep], views=views[keep], values=values[keep].astype(np.float32),
                        probe_index=np.full(n_ok, probe_index, dtype=np.int32), dropped=dropped,
                        pixels=np.stack([rows[keep], cols[keep]], axis=1).astype(np.int32),
                        image_index=np.zeros(n_ok, dtype=np.int32))


def observations_from_sphere(image: np.ndarray, geometry: SphereGeometry, n_normals: int = 8000,
                             max_view_angle_deg: float = 80.0, saturation: Optional[float] = None,
                             mask: Optional[np.ndarray] = None, seed: int = 0, probe_index: int = 0,
                             source: str = "image", footprint: Optional[float] = None) -> Observations:
    """Observations from an orthographic image of a sphere of known position.

    A camera pixel integrates the radiance over its square footprint, whose
    normals spread by about ``1 / (radius cos theta)`` radians at view angle
    theta: 0.6 degrees at the centre of a 100 px-radius sphere, 3.3 at 80
    degrees, 16 at 88 (5.7 and 28 at a 57 px radius). The paper's model
    (``footprint=None``) takes the centre normal, which is exact for images
    of pixel centres and good away from the rim. The pixel-footprint model
    (``footprint=DEG``) gives every row whose footprint spreads more than
    ``DEG`` an ``s x s`` grid of sub-pixel normals (``s = ceil(spread /
    DEG)``, at most :data:`FOOTPRINT_MAX_SIDE`), whose lighting-matrix rows
    are averaged: the model of an area-integrating camera, which makes rim
    pixels usable (raise ``max_view_angle_deg`` towards 90 with it).

    Args:
        image: ``(H, W, 3)`` linear RGB.
        geometry: the sphere (centre and radius in pixels, camera pose).
        n_normals: lattice normals over the visible hemisphere (before drops).
        max_view_angle_deg: drop normals further than this from the view.
        saturation: drop pixels with any channel ``>=`` this (``None``: keep
            all, but warn when the image looks clipped).
        mask: optional ``(H, W) bool``, True where pixels may be used.
        seed: seeds the lattice's azimuthal rotation.
        probe_index: probe lighting this image (see :func:`stack`).
        source: name of the image in messages.
        footprint: ``None`` (centre normals) or the largest normal spread,
            degrees, one sub-pixel sample may stand for (e.g. ``2.0``).
    """
    image = check_image(image, source)
    if footprint is not None and not (math.isfinite(footprint) and footprint > 0.0):
        raise InputError(source, f"footprint must be a positive angle in degrees, got {footprint!r}")
    height, width = image.shape[:2]
    mask = check_mask(mask, (height, width), source)
    rot = check_rotation(check_sphere(geometry, source).camera_to_world, source)
    cx, cy, radius = float(geometry.cx), float(geometry.cy), float(geometry.radius)
    if cx + radius <= 0 or cy + radius <= 0 or cx - radius >= width or cy - radius >= height:
        raise InputError(source, f"the sphere (centre ({cx:g}, {cy:g}), radius {radius:g} px) "
                                 f"lies outside the {width}x{height} image",
                         "give the sphere's centre and radius in this image's pixels")
    if cx - radius < 0 or cy - radius < 0 or cx + radius > width or cy + radius > height:
        warnings.warn(f"{source}: the sphere extends beyond the {width}x{height} image; "
                      "its cut-off part is not observed", InputWarning, stacklevel=2)
    if n_normals < 1:
        raise InputError(source, f"n_normals must be positive, got {n_normals}")

    dropped = {k: 0 for k in DROP_REASONS}
    cos_max = math.cos(math.radians(max_view_angle_deg))
    lattice = hemisphere_lattice(int(n_normals), seed)  # camera frame, z towards the viewer
    ok = lattice[:, 2] >= cos_max
    dropped["view_angle"] = int(np.count_nonzero(~ok))
    lattice = lattice[ok]

    # Orthographic projection: image x = cx + r n_x, image y = cy - r n_y.
    cols = np.floor(cx + radius * lattice[:, 0]).astype(np.int64)
    rows = np.floor(cy - radius * lattice[:, 1]).astype(np.int64)
    ok = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    dropped["outside_image"] = int(np.count_nonzero(~ok))
    cols, rows = cols[ok], rows[ok]

    # The pixel's own normal, at its centre; the whole pixel (centre + half
    # diagonal) must lie inside the silhouette, else it mixes in background.
    x = (cols + 0.5 - cx) / radius
    y = -(rows + 0.5 - cy) / radius
    rho = np.sqrt(x * x + y * y)
    ok = rho + math.sqrt(0.5) / radius < 1.0
    dropped["silhouette"] = int(np.count_nonzero(~ok))
    cols, rows, x, y = cols[ok], rows[ok], x[ok], y[ok]
    if mask is not None:
        ok = mask[rows, cols]
        dropped["outside_mask"] = int(np.count_nonzero(~ok))
        cols, rows, x, y = cols[ok], rows[ok], x[ok], y[ok]

    n_cam = np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1)
    # The pixel's own normal can lie slightly beyond the lattice normal's angle.
    ok = n_cam[:, 2] >= cos_max
    dropped["view_angle"] += int(np.count_nonzero(~ok))
    cols, rows, n_cam = cols[ok], rows[ok], n_cam[ok]
    normals = n_cam @ rot.T
    view = rot[:, 2]
    views = np.broadcast_to(view, normals.shape).copy()

    if saturation is None:
        on_object = geometry.object_mask(width, height)
        box = bounding_box(on_object)
        _plateau_warning(image[box], on_object[box], source)
    obs = _finish(image, rows, cols, normals, views, dropped, saturation, source, probe_index)
    if footprint is not None:
        obs.footprint_normals, obs.footprint_rows = _sphere_footprints(obs.pixels, cx, cy, radius, rot, footprint)
    return obs


def _sphere_footprints(pixels: np.ndarray, cx: float, cy: float, radius: float, rot: np.ndarray,
                       footprint_deg: float) -> Tuple[np.ndarray, np.ndarray]:
    """Sub-pixel normals of the pixels whose footprint's normals spread more than ``footprint_deg``.

    The spread is twice the largest angle between the centre normal and a
    corner's (every corner lies inside the silhouette: the pixels passed the
    silhouette check). Returns ``(normals (P, 3) float64 world, rows (P,) int64)``.
    """
    rows, cols = pixels[:, 0].astype(np.float64), pixels[:, 1].astype(np.float64)

    def normal(dx: np.ndarray, dy: np.ndarray, sel: slice = slice(None)) -> np.ndarray:
        """Camera-frame normals ``(m, k, 3)`` at pixel offsets ``(1, k)`` of the pixels ``sel``."""
        x = (cols[sel, None] + 0.5 + dx - cx) / radius
        y = -(rows[sel, None] + 0.5 + dy - cy) / radius
        return np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=-1)

    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])
    centre = normal(np.zeros((1, 1)), np.zeros((1, 1)))
    cos = np.sum(normal(corners[None, :, 0], corners[None, :, 1]) * centre, axis=-1).min(axis=1)
    spread = 2.0 * np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    sides = np.clip(np.ceil(spread / footprint_deg), 1, FOOTPRINT_MAX_SIDE).astype(np.int64)
    out_normals, out_rows = [], []
    for side in np.unique(sides[sides > 1]):
        sel = np.flatnonzero(sides == side)
        offs = (np.arange(side) + 0.5) / side - 0.5
        ox, oy = np.meshgrid(offs, offs)
        n_cam = normal(ox.reshape(1, -1), oy.reshape(1, -1), sel)  # (m, side^2, 3)
        n_cam /= np.linalg.norm(n_cam, axis=-1, keepdims=True)
        out_normals.append((n_cam @ rot.T).reshape(-1, 3))
        out_rows.append(np.repeat(sel, side * side))
    if not out_rows:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    normals, which = np.concatenate(out_normals), np.concatenate(out_rows)
    order = np.argsort(which, kind="stable")
    return normals[order], which[order].astype(np.int64)


def observations_from_normal_map(image: np.ndarray, normals: np.ndarray, mask: np.ndarray,
                                 view: np.ndarray, n_normals: int = 8000,
                                 max_view_angle_deg: float = 80.0, saturation: Optional[float] = None,
                                 seed: int = 0, probe_index: int = 0,
                                 source: str = "image", positions: Optional[np.ndarray] = None,
                                 geometric_normals: Optional[np.ndarray] = None) -> Observations:
    """Observations from an image with a per-pixel normal map (e.g. render AOVs).

    The lattice is laid about the (mean) view direction and each lattice
    normal takes the pixel whose normal is nearest to it, so the selection
    is uniform over the normals the object shows.

    Pixels of the mask without usable surface data are dropped with one
    :class:`InputWarning` that counts them per cause (none at all usable: an
    :class:`InputError`), never passed on as NaN or zero vectors: a normal
    that is not finite or shorter than 0.5 (a zero, or the average of a
    pixel's disagreeing normals), a per-pixel view likewise, a position that
    is not finite, or a geometric normal that is not finite or zero.

    Args:
        image: ``(H, W, 3)`` linear RGB.
        normals: ``(H, W, 3)`` world normals (need not be exactly unit:
            lengths above 0.5 are normalised).
        mask: ``(H, W) bool``, True on the object.
        view: ``(3,)`` world direction towards an orthographic camera, or
            ``(H, W, 3)`` per-pixel directions towards the camera.
        n_normals, max_view_angle_deg, saturation, seed, probe_index, source:
            as in :func:`observations_from_sphere`.
        positions: optional ``(H, W, 3)`` world positions of the surface seen
            by each pixel (e.g. ray-cast from a mesh); kept per row for
            visibility (shadow rays) in the lighting matrix.
        geometric_normals: optional ``(H, W, 3)`` geometric normals there (any
            non-zero length: normalised).
    """
    from scipy.spatial import cKDTree

    image = check_image(image, source)
    height, width = image.shape[:2]
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != (height, width, 3):
        raise InputError(source, f"normal map has shape {normals.shape} but the image is {height}x{width}x3")
    mask = check_mask(mask, (height, width), source)
    view = np.asarray(view, dtype=np.float64)
    if view.shape not in ((3,), (height, width, 3)):
        raise InputError(source, f"view must be (3,) or ({height}, {width}, 3), got {view.shape}")
    if n_normals < 1:
        raise InputError(source, f"n_normals must be positive, got {n_normals}")
    surface = {}
    for name, value in (("positions", positions), ("geometric_normals", geometric_normals)):
        if value is not None:
            value = np.asarray(value, dtype=np.float64)
            if value.shape != (height, width, 3):
                raise InputError(source, f"{name} map has shape {value.shape} but the image is {height}x{width}x3")
            surface[name] = value

    length = np.linalg.norm(normals, axis=-1)
    unusable = {"normal (not finite, or shorter than 0.5)": ~(np.all(np.isfinite(normals), axis=-1) & (length > 0.5))}
    if view.ndim == 3:
        view_len = np.linalg.norm(view, axis=-1)
        unusable["view (not finite, or shorter than 0.5)"] = ~(np.all(np.isfinite(view), axis=-1) & (view_len > 0.5))
    if "positions" in surface:
        unusable["position (not finite)"] = ~np.all(np.isfinite(surface["positions"]), axis=-1)
    if "geometric_normals" in surface:
        g = surface["geometric_normals"]
        unusable["geometric normal (not finite, or zero)"] = ~(np.all(np.isfinite(g), axis=-1)
                                                               & (np.linalg.norm(g, axis=-1) > 0.0))
    usable = mask.copy()
    for bad in unusable.values():
        usable &= ~bad
    if not np.any(usable):
        raise InputError(source, "the mask selects no pixel with a valid normal")
    n_left_out = int(np.count_nonzero(mask & ~usable))
    if n_left_out:
        causes = ", ".join(f"{int(np.count_nonzero(mask & bad))} without a usable {what}"
                           for what, bad in unusable.items() if np.any(mask & bad))
        warnings.warn(f"{source}: {n_left_out} of {int(np.count_nonzero(mask))} pixels in the mask are not used: "
                      f"{causes} (check the normal map, or leave such pixels out of the mask)",
                      InputWarning, stacklevel=2)
    prow, pcol = np.nonzero(usable)
    pnormal = normals[prow, pcol] / length[prow, pcol, None]
    if view.ndim == 3:
        pview = view[prow, pcol] / view_len[prow, pcol, None]
        axis = pview.mean(axis=0)
    else:
        if not np.all(np.isfinite(view)) or np.linalg.norm(view) == 0.0:
            raise InputError(source, f"invalid view direction {view}")
        axis = view
        pview = np.broadcast_to(view / np.linalg.norm(view), pnormal.shape)

    dropped = {k: 0 for k in DROP_REASONS}
    cos_max = math.cos(math.radians(max_view_angle_deg))
    lattice = hemisphere_lattice(int(n_normals), seed)
    ok = lattice[:, 2] >= cos_max
    lattice = lattice[ok] @ _frame_about(axis).T
    _, nearest = cKDTree(pnormal).query(lattice)
    # The chosen pixel's own normal must also face its own view closely enough.
    own = np.sum(pnormal[nearest] * pview[nearest], axis=1) >= cos_max
    dropped["view_angle"] = int(np.count_nonzero(~ok)) + int(np.count_nonzero(~own))
    nearest = nearest[own]
    obs = _finish(image, prow[nearest], pcol[nearest], pnormal[nearest], np.array(pview[nearest]),
                  dropped, saturation, source, probe_index)
    rows, cols = obs.pixels[:, 0], obs.pixels[:, 1]
    if "positions" in surface:
        obs.positions = surface["positions"][rows, cols]
    if "geometric_normals" in surface:
        g = surface["geometric_normals"][rows, cols]
        obs.geometric_normals = g / np.linalg.norm(g, axis=1, keepdims=True)  # non-zero: checked above
    return obs


def image_observations(image: np.ndarray, geometry: Geometry, *, n_normals: int = 8000,
                       max_view_angle_deg: float = 80.0, saturation: Optional[float] = None,
                       mask: Optional[np.ndarray] = None, seed: int = 0, probe_index: int = 0,
                       source: str = "image", footprint: Optional[float] = None) -> Observations:
    """Observations of one image for any :class:`~mi_bivariate.geometry.Geometry`.

    A :class:`SphereGeometry` (orthographic sphere) takes the lattice route of
    :func:`observations_from_sphere`. Any other geometry, a
    :class:`PerspectiveSphereGeometry` (pinhole photo of a sphere: exact
    per-pixel normals and views, fully covered pixels only) or a
    :class:`mi_bivariate.mesh.MeshView` (any mesh with a posed camera), gives
    its :meth:`~mi_bivariate.geometry.Geometry.surface_maps` to
    :func:`observations_from_normal_map`; rows keep the surface points, when the
    geometry has them, for visibility. ``footprint``: the pixel-footprint model
    of :func:`observations_from_sphere` (orthographic spheres only).
    """
    common = dict(n_normals=n_normals, max_view_angle_deg=max_view_angle_deg, saturation=saturation, seed=seed,
                  probe_index=probe_index, source=source)
    if isinstance(geometry, SphereGeometry):
        return observations_from_sphere(image, geometry, mask=mask, footprint=footprint, **common)
    if footprint is not None:
        raise InputError(source, f"the pixel-footprint model needs an orthographic sphere, not a "
                                 f"{type(geometry).__name__}", "leave footprint=None")
    if not isinstance(geometry, Geometry):
        raise InputError(source, f"unsupported geometry {type(geometry).__name__}",
                         "use SphereGeometry, PerspectiveSphereGeometry or mesh.MeshView")
    image = array_from(image, source, "an (H, W, 3) RGB image")
    if image.ndim != 3:
        raise InputError(source, f"expected an (H, W, 3) RGB image, got shape {image.shape}")
    maps = geometry.surface_maps(image.shape[1], image.shape[0], source)
    usable = maps.mask
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != usable.shape:
            raise InputError(source, f"mask has shape {mask.shape} but the image is "
                                     f"{image.shape[0]}x{image.shape[1]}")
        usable = usable & mask.astype(bool)
    if not usable.any():
        raise InputError(source, geometry.no_pixels, geometry.no_pixels_hint)
    return observations_from_normal_map(image, maps.normals, usable, maps.views, positions=maps.positions,
                                        geometric_normals=maps.geometric_normals, **common)


def stack(observations: Sequence[Observations],
          probe_index: Optional[Sequence[int]] = None) -> Observations:
    """Stack observations of several images (views or probes) into one system.

    Args:
        observations: per image.
        probe_index: optional probe per image; by default each part keeps
            its own ``probe_index``.

    Returns:
        All rows; ``image_index`` is the position in ``observations`` and
        ``dropped`` the summed counts.
    """
    parts = list(observations)
    if not parts:
        raise InputError(None, "no observations to stack")
    if probe_index is not None:
        if len(probe_index) != len(parts):
            raise InputError(None, f"{len(probe_index)} probe indices for {len(parts)} observation sets")
        parts = [p.with_probe_index(k) for p, k in zip(parts, probe_index)]
    dropped = {k: sum(p.dropped.get(k, 0) for p in parts) for k in DROP_REASONS}

    def surface(name: str, fallback: str) -> Optional[np.ndarray]:
        # Parts without positions (e.g. a convex sphere) get NaN rows: no shadow rays.
        if all(getattr(p, name) is None for p in parts):
            return None
        return np.concatenate([getattr(p, name) if getattr(p, name) is not None
                               else (np.full((len(p), 3), np.nan) if fallback == "nan" else getattr(p, fallback))
                               for p in parts])

    return Observations(
        normals=np.concatenate([p.normals for p in parts]),
        views=np.concatenate([p.views for p in parts]),
        values=np.concatenate([p.values for p in parts]).astype(np.float32),
        probe_index=np.concatenate([p.probe_index for p in parts]).astype(np.int32),
        dropped=dropped,
        pixels=np.concatenate([p.pixels for p in parts]).astype(np.int32),
        image_index=np.concatenate([np.full(len(p), k, dtype=np.int32) for k, p in enumerate(parts)]),
        positions=surface("positions", "nan"),
        geometric_normals=surface("geometric_normals", "normals"),
        **_stacked_footprints(parts),
    )


def _stacked_footprints(parts: Sequence[Observations]) -> Dict[str, Optional[np.ndarray]]:
    """The footprint arrays of stacked parts (rows offset by the parts before), or ``None``."""
    if not any(p.footprint_rows is not None for p in parts):
        return {"footprint_normals": None, "footprint_rows": None}
    offsets = np.cumsum([0] + [len(p) for p in parts[:-1]])
    normals = [p.footprint_normals for p in parts if p.footprint_rows is not None]
    rows = [p.footprint_rows + o for p, o in zip(parts, offsets) if p.footprint_rows is not None]
    return {"footprint_normals": np.concatenate(normals), "footprint_rows": np.concatenate(rows).astype(np.int64)}
