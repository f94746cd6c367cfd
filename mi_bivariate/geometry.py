"""Camera and sphere geometry shared by the renderer and the capture step.

Default camera (design.md): orthographic, on world +z looking towards -z;
image right = world +x, image up = world +y. Pixel (i, j) (column i, row j)
has its centre at x = i + 0.5, y = j + 0.5 with image y pointing down. A
sphere is given by its centre and radius in pixels. Other poses are a
camera-to-world rotation applied to camera-frame directions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Tuple

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
