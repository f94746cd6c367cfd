"""Camera and sphere geometry shared by the renderer and the capture step.

Default camera (design.md): orthographic, on world +z looking towards -z;
image right = world +x, image up = world +y. Pixel (i, j) (column i, row j)
has its centre at x = i + 0.5, y = j + 0.5 with image y pointing down. A
sphere is given by its centre and radius in pixels. Other poses are a
camera-to-world rotation applied to camera-frame directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Tuple

import numpy as np


@dataclass(frozen=True)
class SphereGeometry:
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

        A pixel counts when its centre lies inside the sphere's silhouette.
        """
        x = (np.arange(width) + 0.5 - self.cx) / self.radius
        y = -(np.arange(height) + 0.5 - self.cy) / self.radius
        xx, yy = np.meshgrid(x, y)
        r2 = xx * xx + yy * yy
        mask = r2 < 1.0
        zz = np.sqrt(np.clip(1.0 - r2, 0.0, None))
        n_cam = np.stack([xx, yy, zz], axis=-1)
        n_cam[~mask] = 0.0
        return n_cam @ np.asarray(self.camera_to_world, dtype=np.float64).T, mask

    def view_direction(self) -> np.ndarray:
        """World direction from the surface towards the camera, ``(3,) float64``."""
        return np.asarray(self.camera_to_world, dtype=np.float64) @ np.array([0.0, 0.0, 1.0])


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
        values = np.asarray(value, dtype=np.float64).ravel()
        if values.shape != (4,):
            raise ValueError(f"intrinsics must be (fx, fy, cx, cy), got {value!r}")
        return cls(*(float(v) for v in values))

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
class PerspectiveSphereGeometry:
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
        object.__setattr__(self, "intrinsics", Intrinsics.coerce(self.intrinsics))
        object.__setattr__(self, "centre", np.asarray(self.centre, np.float64).reshape(3))
        object.__setattr__(self, "camera_to_world", np.asarray(self.camera_to_world, np.float64))

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

    def _corner_hits(self, width: int, height: int) -> np.ndarray:
        x, y = np.meshgrid(np.arange(width + 1, dtype=np.float64), np.arange(height + 1, dtype=np.float64))
        d = self.intrinsics.rays(x, y)
        dc = d @ self.centre
        hit = (dc * dc - (self.centre @ self.centre - self.radius ** 2) > 0.0) & (dc > 0.0)
        return hit[:-1, :-1] & hit[:-1, 1:] & hit[1:, :-1] & hit[1:, 1:]

    def silhouette(self, n: int = 360) -> np.ndarray:
        """``(n, 2)`` pixel positions (x, y) on the silhouette (an ellipse under perspective)."""
        axis = self.centre / self.distance
        e1, e2 = _orthonormal_pair(axis)
        phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        alpha = self.half_angle
        rays = math.cos(alpha) * axis + math.sin(alpha) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        return self.intrinsics.project(rays)


def _orthonormal_pair(axis: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit ``axis`` to an orthonormal basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)
