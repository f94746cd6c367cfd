"""Cameras, poses and the geometry an image shows: one home for all of them.

- :func:`check_rotation`: the one check of a camera-to-world rotation.
- :class:`Intrinsics` (pinhole pixels), :class:`Camera` (a posed pinhole or
  orthographic camera) and :class:`SphereCamera` (the camera of a synthetic
  render of the unit sphere at the origin).
- :class:`Geometry`: what an image shows, the small interface that
  :func:`mi_bivariate.capture.image_observations` and
  :func:`mi_bivariate.recover.recover` dispatch on: per-pixel
  :class:`SurfaceMaps` and an optional occluder. Implemented by
  :class:`SphereGeometry` (orthographic sphere), :class:`PerspectiveSphereGeometry`
  (pinhole photo of a sphere) and :class:`mi_bivariate.mesh.MeshView` (a mesh).

Default camera (README, "Conventions"): orthographic, on world +z looking towards -z;
image right = world +x, image up = world +y. Pixel (i, j) (column i, row j)
has its centre at x = i + 0.5, y = j + 0.5 with image y pointing down. A
sphere is given by its centre and radius in pixels. Other poses are a
camera-to-world rotation applied to camera-frame directions.
"""

from __future__ import annotations

import abc
import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import mitsuba as mi
import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.images import CHUNK_ROWS, circle_box
from mi_bivariate.limits import finite_number

#: Distance of the orthographic render camera from the sphere's centre (any value > 1 works).
ORTHO_DISTANCE = 5.0


def check_rotation(matrix: Any, source: str = "camera_to_world") -> np.ndarray:
    """A camera-to-world rotation as ``(3, 3) float64`` (identity for ``None``).

    Raises:
        InputError: not a finite proper rotation (orthonormal to 1e-6, det > 0).
    """
    try:
        rot = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(source, f"camera_to_world is not a (3, 3) rotation matrix, got {matrix!r}") from None
    if rot.shape != (3, 3) or not np.all(np.isfinite(rot)) \
            or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise InputError(source, "camera_to_world is not a (3, 3) rotation matrix")
    return rot


def orthonormal_pair(axis: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit ``axis`` to an orthonormal basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


@dataclass
class SurfaceMaps:
    """What each pixel of an image sees, ``(H, W, ...)`` world-space maps.

    Attributes:
        normals: ``(H, W, 3)`` unit shading normals (0 outside ``mask``).
        views: ``(H, W, 3)`` unit directions towards the camera.
        mask: ``(H, W) bool``, the pixels to use.
        positions: optional ``(H, W, 3)`` world positions (NaN outside), for
            shadow rays; ``None`` for a convex object.
        geometric_normals: optional ``(H, W, 3)`` geometric normals.
        hit: optional ``(H, W) bool``, the pixel-centre ray hits the object.
    """

    normals: np.ndarray
    views: np.ndarray
    mask: np.ndarray
    positions: Optional[np.ndarray] = None
    geometric_normals: Optional[np.ndarray] = None
    hit: Optional[np.ndarray] = None


class Geometry(abc.ABC):
    """What an image shows, seen from where: the interface capture and recover dispatch on.

    A subclass writes :meth:`surface_maps`; an object that can shadow itself
    also returns itself from :meth:`occluder`.
    """

    #: The problem to report when no pixel is usable.
    no_pixels = "no pixel sees the object"
    no_pixels_hint: Optional[str] = None

    @abc.abstractmethod
    def surface_maps(self, width: int, height: int, source: str = "image") -> SurfaceMaps:
        """Per-pixel normals, views and the usable mask of a ``width x height`` image."""

    def object_mask(self, width: int, height: int, source: str = "image") -> np.ndarray:
        """``(H, W) bool``: :meth:`surface_maps`'s ``mask`` alone (a subclass may find it without the maps)."""
        return self.surface_maps(width, height, source).mask

    def occluder(self) -> Optional[Any]:
        """The shape that casts shadows on itself (``lighting_matrix(occluder=...)``), or ``None``."""
        return None

    def record(self) -> Dict[str, Any]:
        """A JSON-ready description for a table's provenance: the type and the small fields (numbers,
        and arrays of at most 16 values; a mesh's arrays are left out)."""
        return {"type": type(self).__name__, **_small_fields(self)}


def _small_fields(obj: Any) -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    for f in dataclasses.fields(obj) if dataclasses.is_dataclass(obj) else ():
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = _small_fields(value)
        elif isinstance(value, (bool, int, float, str)) or value is None:
            out[f.name] = value
        elif isinstance(value, (np.ndarray, list, tuple)) and np.size(value) <= 16:
            try:
                out[f.name] = np.asarray(value, np.float64).tolist()
            except (TypeError, ValueError):
                pass
    return out


@dataclass(frozen=True)
class SphereGeometry(Geometry):
    """A sphere seen by an orthographic camera.

    Attributes:
        cx, cy: centre in pixels (x right, y down; pixel centres at k + 0.5).
        radius: radius in pixels.
        camera_to_world: ``(3, 3)`` rotation taking camera-frame vectors
            (x right, y up, z towards the viewer) to world (probe) vectors.
    """

    cx: float
    cy: float
    radius: float
    camera_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))

    def normals(self, width: int, height: int) -> Tuple[np.ndarray, np.ndarray]:
        """Per-pixel world normals ``(H, W, 3) float64`` and the coverage mask ``(H, W) bool``.

        A pixel counts when its centre lies inside the sphere's silhouette. The normals are computed
        there only (the same values, bit for bit, as on the whole frame: 0.2-0.3 s instead of 1-2.5 s
        for a 2048 x 2048 photo).
        """
        x, y = np.arange(width) + 0.5, np.arange(height) + 0.5
        mask = self.object_mask(width, height)
        rows, cols = np.nonzero(mask)
        normals = np.zeros((height, width, 3))
        normals[rows, cols] = self.normals_at(x[cols], y[rows])
        return normals, mask

    def object_mask(self, width: int, height: int, source: str = "image") -> np.ndarray:
        """``(H, W) bool``: the pixels whose centre lies inside the sphere's silhouette (:meth:`normals`' mask),
        computed in the circle's box only (:func:`~mi_bivariate.images.circle_box`)."""
        rows, cols = circle_box((height, width), self.cx, self.cy, self.radius)
        x2 = (((np.arange(cols.start, cols.stop) + 0.5)[None, :] - self.cx) / self.radius) ** 2
        y2 = (((np.arange(rows.start, rows.stop) + 0.5)[:, None] - self.cy) / self.radius) ** 2
        mask = np.zeros((height, width), dtype=bool)
        for start in range(0, y2.shape[0], CHUNK_ROWS):  # by rows: the float64 sums stay small
            part = x2 + y2[start:start + CHUNK_ROWS] < 1.0
            mask[rows.start + start:rows.start + start + len(part), cols] = part
        return mask

    def normals_at(self, x: np.ndarray, y: np.ndarray, onto_sphere: bool = False) -> np.ndarray:
        """World normals ``(..., 3) float64`` at image positions ``x, y`` (pixels, x right, y down).

        Unit vectors inside the silhouette. Outside it the result is ``(x, y, 0)`` in the camera frame,
        longer than 1 and not a normal (:meth:`normals` masks those pixels), unless ``onto_sphere``
        first pulls such a position just inside the rim, so that its normal stays a unit vector in the
        visible hemisphere (a trial geometry that leaves a few pixels off the sphere).
        """
        x = (np.asarray(x, np.float64) - self.cx) / self.radius
        y = -(np.asarray(y, np.float64) - self.cy) / self.radius
        if onto_sphere:
            scale = np.minimum(1.0, (1.0 - 1e-6) / np.maximum(np.hypot(x, y), 1e-300))
            x, y = x * scale, y * scale
        z = np.sqrt(np.clip(1.0 - (x * x + y * y), 0.0, None))
        return np.stack([x, y, z], axis=-1) @ np.asarray(self.camera_to_world, dtype=np.float64).T

    def view_direction(self) -> np.ndarray:
        """World direction from the surface towards the camera, ``(3,) float64``."""
        return np.asarray(self.camera_to_world, dtype=np.float64) @ np.array([0.0, 0.0, 1.0])

    no_pixels = "no pixel centre lies inside the sphere's silhouette"

    def surface_maps(self, width: int, height: int, source: str = "image") -> SurfaceMaps:
        """:meth:`normals` with the one view direction broadcast to every pixel."""
        normals, mask = self.normals(width, height)
        views = np.where(mask[..., None], self.view_direction(), 0.0)
        return SurfaceMaps(normals=normals, views=views, mask=mask)


def check_sphere(geometry: Any, source: str = "geometry") -> SphereGeometry:
    """``geometry`` if it is a :class:`SphereGeometry` with a finite centre, a finite positive radius (real
    numbers, in pixels) and a proper ``camera_to_world`` rotation; else :class:`InputError` naming ``source``
    (the one check of an orthographic sphere given by a caller)."""
    if not isinstance(geometry, SphereGeometry):
        raise InputError(source, f"expected a mi_bivariate.geometry.SphereGeometry, got a {type(geometry).__name__}",
                         "e.g. SphereGeometry(cx, cy, radius) in pixels, or mi_bivariate.spherefit.fit_sphere(image)"
                         ".geometry")
    values = (geometry.cx, geometry.cy, geometry.radius)
    if any(isinstance(v, bool) or not isinstance(v, numbers.Real) for v in values):
        raise InputError(source, f"the sphere's centre and radius must be numbers, got {values!r}")
    cx, cy, radius = (float(v) for v in values)
    if not all(math.isfinite(v) for v in (cx, cy, radius)) or radius <= 0.0:
        raise InputError(source, f"invalid sphere: centre ({cx:g}, {cy:g}), radius {radius:g} px",
                         "the centre must be finite and the radius finite and positive")
    check_rotation(geometry.camera_to_world, source)
    return geometry


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics in pixels (image x right, y down; pixel centres at k + 0.5).

    A pixel position ``(x, y)`` maps to the camera-frame ray direction
    ``((x - cx) / fx, -(y - cy) / fy, -1)``: the camera looks down -z with
    x right, y up and z towards the viewer, as in :class:`SphereGeometry`.
    """

    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> "Intrinsics":
        """Square pixels, principal point at the image centre, horizontal field of view in degrees
        (Mitsuba's ``perspective`` sensor with ``fov_axis="x"``)."""
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        return cls(f, f, 0.5 * width, 0.5 * height)

    @classmethod
    def coerce(cls, value: Any) -> "Intrinsics":
        """An :class:`Intrinsics` from itself or a sequence ``(fx, fy, cx, cy)``."""
        if isinstance(value, cls):
            return value
        try:
            values = np.asarray(value, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            values = np.empty(0)
        if values.shape != (4,):
            raise InputError("intrinsics", f"must be four numbers (fx, fy, cx, cy) in pixels, got {value!r}")
        return cls(*(float(v) for v in values))

    def __post_init__(self) -> None:
        try:
            values = tuple(float(v) for v in (self.fx, self.fy, self.cx, self.cy))
        except (TypeError, ValueError):
            raise InputError("intrinsics", f"must be four numbers (fx, fy, cx, cy) in pixels, got "
                             f"{(self.fx, self.fy, self.cx, self.cy)!r}") from None
        if not all(math.isfinite(v) for v in values) or not (values[0] > 0.0 and values[1] > 0.0):
            raise InputError("intrinsics", "the focal lengths must be finite and positive and the principal point "
                             f"finite, got fx={values[0]:g}, fy={values[1]:g}, cx={values[2]:g}, cy={values[3]:g} px",
                             "flip a mirrored image instead of giving a negative focal length")
        for name, value in zip(("fx", "fy", "cx", "cy"), values):
            object.__setattr__(self, name, value)

    def rays(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit camera-frame ray directions through pixel positions, ``(..., 3) float64``."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        d = np.stack([(x - self.cx) / self.fx, -(y - self.cy) / self.fy, -np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel positions ``(..., 2)`` (x, y) of camera-frame points ``(..., 3)`` in front of the camera."""
        points = np.asarray(points, np.float64)
        depth = -points[..., 2]
        return np.stack([self.cx + self.fx * points[..., 0] / depth,
                         self.cy - self.fy * points[..., 1] / depth], axis=-1)


@dataclass(frozen=True)
class PerspectiveSphereGeometry(Geometry):
    """A sphere seen by a pinhole (perspective) camera.

    Only the ratio of ``radius`` to the centre's distance matters for normals
    and views, so the radius may stay 1 (world units) when the true size is unknown.

    Attributes:
        intrinsics: :class:`Intrinsics` (or ``(fx, fy, cx, cy)`` in pixels).
        centre: ``(3,)`` sphere centre in the camera frame (x right, y up,
            z towards the viewer; visible spheres have ``centre[2] < 0``).
        radius: sphere radius, same units as ``centre``.
        camera_to_world: ``(3, 3)`` rotation from camera-frame to world (probe) vectors.
    """

    intrinsics: Intrinsics
    centre: np.ndarray
    radius: float = 1.0
    camera_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "intrinsics", Intrinsics.coerce(self.intrinsics))
        except InputError as exc:  # named as the geometry's
            raise exc.within("geometry", "intrinsics") from None
        try:
            centre = np.asarray(self.centre, np.float64)
        except (TypeError, ValueError):
            centre = np.empty(0)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise InputError("geometry", f"the sphere's centre must be 3 finite numbers (camera frame), got "
                             f"{self.centre!r}")
        radius = self.radius
        if isinstance(radius, bool) or not isinstance(radius, numbers.Real) or not math.isfinite(radius) \
                or radius <= 0.0:
            raise InputError("geometry", f"the sphere's radius must be a finite positive number, got {radius!r}")
        if float(np.linalg.norm(centre)) <= radius or centre[2] >= 0.0:
            raise InputError("geometry", f"the sphere (centre ({', '.join(f'{v:g}' for v in centre)}), radius {radius:g}) is not in front "
                             "of the camera", "the camera looks down -z: a visible sphere has centre[2] < 0 and "
                             "lies outside the camera's centre")
        object.__setattr__(self, "centre", centre)
        object.__setattr__(self, "radius", float(radius))
        object.__setattr__(self, "camera_to_world", check_rotation(self.camera_to_world, "geometry"))

    @property
    def distance(self) -> float:
        """Distance from the camera's centre of projection to the sphere centre."""
        return float(np.linalg.norm(self.centre))

    @property
    def half_angle(self) -> float:
        """Angular radius of the silhouette cone, radians: ``asin(radius / distance)``."""
        return math.asin(min(1.0, self.radius / self.distance))

    def normals_and_views(self, width: int, height: int, coverage: str = "centre"
                          ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-pixel world normals, views and coverage by exact ray-sphere intersection.

        Args:
            width, height: image size in pixels.
            coverage: ``"centre"``: a pixel counts when its centre ray hits
                the sphere (as :meth:`SphereGeometry.normals`); ``"full"``: when
                the rays through all four corners hit it (no background mixed in;
                the silhouette is convex).

        Returns:
            ``normals (H, W, 3) float64`` unit world normals at the pixel
            centres' hit points, ``views (H, W, 3) float64`` unit world
            directions from those points towards the camera, and ``mask
            (H, W) bool``; normals and views are 0 outside the mask.
        """
        x, y = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        d = self.intrinsics.rays(x, y)
        c = self.centre
        dc = d @ c
        disc = dc * dc - (c @ c - self.radius ** 2)
        mask = (disc >= 0.0) & (dc - np.sqrt(np.clip(disc, 0.0, None)) > 0.0)
        if coverage == "full":
            mask &= self._corner_hits(width, height)
        elif coverage != "centre":
            raise ValueError(f"coverage must be 'centre' or 'full', got {coverage!r}")
        t = dc - np.sqrt(np.clip(disc, 0.0, None))
        n_cam = (t[..., None] * d - c) / self.radius
        # Renormalise: at grazing hits (disc ~ 0) rounding leaves |n| slightly off 1.
        n_cam /= np.maximum(np.linalg.norm(n_cam, axis=-1, keepdims=True), 1e-300)
        n_cam[~mask] = 0.0
        v_cam = np.where(mask[..., None], -d, 0.0)
        rot = self.camera_to_world
        return n_cam @ rot.T, v_cam @ rot.T, mask

    no_pixels = "no pixel lies fully inside the sphere's silhouette"

    def surface_maps(self, width: int, height: int, source: str = "image") -> SurfaceMaps:
        """:meth:`normals_and_views` of the fully covered pixels (no background mixed in)."""
        normals, views, mask = self.normals_and_views(width, height, coverage="full")
        return SurfaceMaps(normals=normals, views=views, mask=mask)

    def _corner_hits(self, width: int, height: int) -> np.ndarray:
        x, y = np.meshgrid(np.arange(width + 1, dtype=np.float64), np.arange(height + 1, dtype=np.float64))
        d = self.intrinsics.rays(x, y)
        dc = d @ self.centre
        hit = (dc * dc - (self.centre @ self.centre - self.radius ** 2) > 0.0) & (dc > 0.0)
        return hit[:-1, :-1] & hit[:-1, 1:] & hit[1:, :-1] & hit[1:, 1:]

    def silhouette(self, n: int = 360) -> np.ndarray:
        """``(n, 2)`` pixel positions (x, y) on the silhouette (an ellipse under perspective)."""
        axis = self.centre / self.distance
        e1, e2 = orthonormal_pair(axis)
        phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        alpha = self.half_angle
        rays = math.cos(alpha) * axis + math.sin(alpha) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        return self.intrinsics.project(rays)


@dataclass(frozen=True)
class Camera:
    """A posed pinhole or orthographic camera, in world units.

    Attributes:
        width, height: image size in pixels.
        intrinsics: perspective: focal lengths and principal point in pixels;
            orthographic: ``fx, fy`` in pixels per world unit and the pixel
            position of the optical axis.
        camera_to_world: ``(3, 3)`` rotation from camera-frame to world vectors.
        position: ``(3,)`` world position of the centre of projection
            (perspective) or of the optical axis' point on the image plane,
            where rays start (orthographic).
        orthographic: parallel projection along the camera's -z.
    """

    width: int
    height: int
    intrinsics: Intrinsics
    camera_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orthographic: bool = False

    def __post_init__(self) -> None:
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputError("camera", f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        try:
            k = Intrinsics.coerce(self.intrinsics)
        except InputError as exc:  # named as the camera's
            raise exc.within("camera", "intrinsics") from None
        object.__setattr__(self, "intrinsics", k)
        object.__setattr__(self, "camera_to_world", check_rotation(self.camera_to_world, "camera"))
        position = np.asarray(self.position, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise InputError("camera", f"position must be a finite 3-vector, got {self.position!r}")
        object.__setattr__(self, "position", position)

    @classmethod
    def look_at(cls, origin: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 1.0, 0.0),
                width: int = 128, height: Optional[int] = None, fov_deg: Optional[float] = 30.0,
                scale: Optional[float] = None) -> "Camera":
        """A camera at ``origin`` looking at ``target``.

        Args:
            fov_deg: horizontal field of view (perspective, square pixels,
                centred principal point).
            scale: instead, pixels per world unit: an orthographic camera.
        """
        height = width if height is None else height
        origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
        back = origin - target
        if not np.linalg.norm(back) > 0:
            raise InputError("camera", "origin and target coincide")
        z = back / np.linalg.norm(back)
        x = np.cross(up, z)
        if not np.linalg.norm(x) > 1e-9:
            raise InputError("camera", "the up vector is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z], axis=1)
        if scale is not None:
            k = Intrinsics(float(scale), float(scale), 0.5 * width, 0.5 * height)
            return cls(width, height, k, rot, origin, orthographic=True)
        if fov_deg is None or not 0.0 < fov_deg < 180.0:
            raise InputError("camera", f"fov must be in (0, 180) degrees, got {fov_deg}")
        return cls(width, height, Intrinsics.from_fov(width, height, fov_deg), rot, origin)

    def rays(self, x: np.ndarray, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """World ray origins and unit directions through pixel positions (x right, y down), ``(..., 3)``."""
        k, rot = self.intrinsics, self.camera_to_world
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        if self.orthographic:
            local = np.stack([(x - k.cx) / k.fx, -(y - k.cy) / k.fy, np.zeros_like(x)], axis=-1)
            origins = self.position + local @ rot.T
            directions = np.broadcast_to(-rot[:, 2], origins.shape).copy()
        else:
            directions = k.rays(x, y) @ rot.T
            origins = np.broadcast_to(self.position, directions.shape).copy()
        return origins, directions

    def sensor_dict(self) -> dict:
        """Mitsuba sensor dictionary (box filter, RGB float film) for a render from this camera.

        Raises:
            InputError: non-square pixels, or (perspective) an off-centre
                principal point, which Mitsuba's sensors do not model here.
        """
        k, rot = self.intrinsics, self.camera_to_world
        if abs(k.fx - k.fy) > 1e-6 * k.fx:
            raise InputError("camera", "cannot render non-square pixels (fx != fy)")
        origin = self.position.copy()
        if self.orthographic:
            origin += rot @ np.array([(0.5 * self.width - k.cx) / k.fx, -(0.5 * self.height - k.cy) / k.fy, 0.0])
        elif abs(k.cx - 0.5 * self.width) > 1e-6 or abs(k.cy - 0.5 * self.height) > 1e-6:
            raise InputError("camera", "cannot render an off-centre principal point")
        look = mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=(origin - rot[:, 2]).tolist(),
                                              up=rot[:, 1].tolist())
        film = {"type": "hdrfilm", "width": self.width, "height": self.height, "pixel_format": "rgb",
                "rfilter": {"type": "box"}}
        if self.orthographic:
            # Mitsuba's orthographic film spans [-1, 1] across the width (times the scale).
            half = 0.5 * self.width / k.fx
            return {"type": "orthographic", "film": film, "near_clip": 1e-4, "far_clip": 1e5,
                    "to_world": look @ mi.ScalarTransform4f().scale([half, half, 1.0])}
        fov = math.degrees(2.0 * math.atan(0.5 * self.width / k.fx))
        return {"type": "perspective", "film": film, "fov": fov, "fov_axis": "x", "near_clip": 1e-4,
                "far_clip": 1e5, "to_world": look}


def _resolution(resolution: Union[int, Sequence[int]]) -> Tuple[int, int]:
    if isinstance(resolution, (int, np.integer)):
        width = height = int(resolution)
    else:
        width, height = (int(v) for v in resolution)
    if width < 1 or height < 1:
        raise InputError("resolution", f"must be positive, got {resolution!r}")
    return width, height


def default_distance(fov: float, radius_fraction: float) -> float:
    """Perspective distance at which the silhouette radius is ``radius_fraction`` of the image width.

    The silhouette of a unit sphere at distance d has angular radius asin(1/d).
    """
    tan_sil = 2.0 * radius_fraction * math.tan(math.radians(fov) / 2.0)
    return 1.0 / math.sin(math.atan(tan_sil))


@dataclass(frozen=True)
class SphereCamera:
    """The camera of a synthetic render of the unit sphere at the origin.

    It sits at ``camera_to_world @ (0, 0, distance)`` looking at the origin
    with image up along ``camera_to_world @ (0, 1, 0)``. Film positions are
    in units of half the image width (Mitsuba's x-axis convention).

    Attributes:
        kind: ``"orthographic"`` or ``"perspective"``.
        resolution: ``(width, height)`` in pixels.
        camera_to_world: ``(3, 3)`` rotation.
        distance: camera distance from the sphere's centre (world units).
        half_width: orthographic: half the film width in world units; else ``None``.
        fov: perspective: horizontal field of view in degrees; else ``None``.
        to_world: ``(4, 4)`` Mitsuba sensor transform (look-at times film scale).
    """

    kind: str
    resolution: Tuple[int, int]
    camera_to_world: np.ndarray
    distance: float
    half_width: Optional[float]
    fov: Optional[float]
    to_world: np.ndarray

    @classmethod
    def create(cls, kind: str = "orthographic", resolution: Union[int, Sequence[int]] = 256,
               radius_fraction: float = 0.45, fov: float = 30.0, distance: Optional[float] = None,
               camera_to_world: Any = None) -> "SphereCamera":
        """A camera whose silhouette of the unit sphere has radius ``radius_fraction`` of ``min(W, H)``
        (orthographic) or of the width (perspective, unless ``distance`` is given)."""
        width, height = _resolution(resolution)
        rot = check_rotation(camera_to_world)
        radius_fraction = finite_number("radius_fraction", radius_fraction)
        if not radius_fraction > 0.0:
            raise InputError("radius_fraction", f"must be positive, got {radius_fraction}")
        half_width = None
        if kind == "orthographic":
            # Silhouette radius in pixels = radius_fraction * min(W, H); one pixel = 2 half / W world units.
            radius_px = radius_fraction * min(width, height)
            half_width, d, fov = 0.5 * width / radius_px, ORTHO_DISTANCE, None
            scale = mi.ScalarTransform4f().scale([half_width] * 2 + [1.0])
        elif kind == "perspective":
            fov = finite_number("fov", fov)
            if not 0.0 < fov < 180.0:
                raise InputError("fov", f"must be in (0, 180) degrees, got {fov}")
            d = default_distance(fov, radius_fraction) if distance is None else finite_number("distance", distance)
            if d <= 1.0:
                raise InputError("distance", f"the camera must be outside the unit sphere, got {d}")
            fov = float(fov)
            scale = mi.ScalarTransform4f()
        else:
            raise InputError("camera", f"unknown camera {kind!r}", "use 'orthographic' or 'perspective'")
        origin = rot @ np.array([0.0, 0.0, d])
        up = rot @ np.array([0.0, 1.0, 0.0])
        look = mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=[0.0, 0.0, 0.0], up=up.tolist())
        return cls(kind, (width, height), rot, d, half_width, fov, np.array((look @ scale).matrix, np.float64))

    def rays(self, px: np.ndarray, py: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """World ray origins and unit directions through film positions (pixels, y down), ``(..., 3) float64``."""
        width, height = self.resolution
        rot = np.asarray(self.camera_to_world, np.float64)
        px, py = np.broadcast_arrays(np.asarray(px, np.float64), np.asarray(py, np.float64))
        u = (px - 0.5 * width) / (0.5 * width)
        v = (0.5 * height - py) / (0.5 * width)
        if self.kind == "orthographic":
            half = self.half_width
            local_o = np.stack([u * half, v * half, np.full_like(u, self.distance)], axis=-1)
            local_d = np.broadcast_to(np.array([0.0, 0.0, -1.0]), local_o.shape)
        else:
            tan = math.tan(math.radians(self.fov) / 2.0)
            local_d = np.stack([u * tan, v * tan, -np.ones_like(u)], axis=-1)
            local_d = local_d / np.linalg.norm(local_d, axis=-1, keepdims=True)
            local_o = np.broadcast_to(np.array([0.0, 0.0, self.distance]), local_d.shape)
        return local_o @ rot.T, local_d @ rot.T

    def coverage_mask(self) -> np.ndarray:
        """``(H, W) bool``: pixels whose four corner rays all hit the unit sphere (full coverage)."""
        width, height = self.resolution
        cx, cy = np.meshgrid(np.arange(width + 1, dtype=np.float64), np.arange(height + 1, dtype=np.float64))
        o, d = self.rays(cx, cy)
        # Distance^2 from the centre to the ray's line: |o|^2 - (o.d)^2 (d unit; camera outside the sphere).
        od = np.einsum("...k,...k->...", o, d)
        hit = (np.einsum("...k,...k->...", o, o) - od * od < 1.0) & (od < 0.0)
        return hit[:-1, :-1] & hit[:-1, 1:] & hit[1:, :-1] & hit[1:, 1:]

    def sensor_dict(self) -> dict:
        """Mitsuba sensor dictionary (box filter, float32 RGB film)."""
        width, height = self.resolution
        film = {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                "rfilter": {"type": "box"}}
        sensor = {"type": self.kind, "film": film, "to_world": mi.ScalarTransform4f(self.to_world)}
        if self.kind == "perspective":
            sensor.update(fov=float(self.fov), fov_axis="x", near_clip=1e-3, far_clip=1e4)
        else:
            sensor.update(near_clip=1e-3, far_clip=1e4)
        return sensor

    def sphere_geometry(self, radius_fraction: float) -> Optional[SphereGeometry]:
        """The orthographic render's sphere in pixels (``None`` for perspective)."""
        if self.kind != "orthographic":
            return None
        width, height = self.resolution
        return SphereGeometry(cx=0.5 * width, cy=0.5 * height, radius=radius_fraction * min(width, height),
                              camera_to_world=np.array(self.camera_to_world))
