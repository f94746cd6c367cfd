"""Mitsuba renders of a sphere under a light probe.

The scene is a unit sphere at the world origin lit by a :class:`~mi_bivariate.probes.Probe`
(``envmap`` emitter), rendered with the ``path`` integrator at ``max_depth=2``
(direct lighting only: a convex sphere has no interreflection) and a box
reconstruction filter, so a pixel is the plain average of its samples.

Cameras (pose conventions of :mod:`mi_bivariate.geometry`):

- ``"orthographic"`` (default): on world +z looking towards -z, image right =
  world +x, image up = world +y, pixel centres at k + 0.5. The sphere's
  silhouette has radius ``radius_fraction * min(W, H)`` pixels and is centred
  in the image, so the render's :class:`~mi_bivariate.geometry.SphereGeometry`
  describes it exactly.
- ``"perspective"``: same pose at ``distance`` from the centre, horizontal
  field of view ``fov`` degrees; by default the distance makes the silhouette radius
  ``radius_fraction`` of the image width.

``camera_to_world`` (3, 3) rotates either camera about the sphere's centre.

The ``mask`` marks pixels *fully* covered by the sphere: every point of the
pixel's square footprint sees the sphere. The silhouette is convex (a disc,
or an ellipse under perspective), so this holds exactly when the rays
through the pixel's four corners hit the sphere. Normals are the ``aov``
integrator's ``sh_normal``, averaged over the pixel's samples and
renormalised (world frame; zero outside the mask).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereGeometry


#: Distance of the orthographic camera from the sphere's centre (any value > 1 works).
ORTHO_DISTANCE = 5.0


@dataclass
class SphereRender:
    """A rendered sphere.

    Attributes:
        image: ``(H, W, 3) float32`` linear RGB radiance (background 0).
        normals: ``(H, W, 3) float32`` unit world normals inside ``mask``, 0 elsewhere.
        mask: ``(H, W) bool`` pixels fully covered by the sphere.
        geometry: the sphere in pixels (orthographic camera), else ``None``.
        camera: camera description: ``type``, ``to_world`` (4, 4), ``resolution`` (W, H),
            ``fov`` (degrees; perspective), ``distance``, ``camera_to_world`` (3, 3).
        spp, seed: sampling parameters of the render.
    """

    image: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    geometry: Optional[SphereGeometry]
    camera: Dict[str, Any] = field(default_factory=dict)
    spp: int = 0
    seed: int = 0


# ------------------------------------------------------------------ BSDFs

def _merl_bitmap(table: np.ndarray):
    import mitsuba as mi

    # Keep NaN (missing samples): the plugin fills them from their phi_d row.
    # A writable copy: nanobind rejects read-only arrays (e.g. cached tables).
    return mi.Bitmap(np.array(table, dtype=np.float32, order="C", copy=True).reshape(90 * 90, 180, 3))


def bsdf_dict(source: Any, interpolation: str = "linear", sampling: str = "table") -> dict:
    """A Mitsuba BSDF dictionary for a BRDF of the toolkit.

    Args:
        source: a :class:`~mi_bivariate.bivariate.BivariateBRDF` (-> ``bivariate``),
            a :class:`~mi_bivariate.merl.MERLBRDF` (-> ``merl``), any object with
            ``eval(theta_h, theta_d, phi_d) -> (..., 3)`` such as the analytic BRDFs
            or an NBRDF (tabulated on the MERL grid -> ``merl``), a path to a
            ``.npz`` (bivariate) or ``.binary`` (MERL) file, or a BSDF dictionary
            (returned unchanged).
        interpolation: lookup of the ``merl`` plugin, ``"linear"`` or ``"nearest"``.
        sampling: ``"table"`` or ``"cosine"`` (importance sampling of the plugins).

    Raises:
        InputError: unknown file type or object.
    """
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.merl import MERLBRDF
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    if isinstance(source, dict):
        if "type" not in source:
            raise InputError("bsdf", "a BSDF dictionary needs a 'type' entry")
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        suffix = path.suffix.lower()
        if not path.is_file():
            raise InputError(path, "BRDF file not found")
        if suffix == ".npz":
            return {"type": "bivariate", "filename": str(path), "sampling": sampling}
        if suffix == ".binary":
            return {"type": "merl", "filename": str(path), "interpolation": interpolation, "sampling": sampling}
        raise InputError(path, f"unknown BRDF file type {path.suffix!r}",
                         "use a .npz bivariate table or a MERL .binary file")
    if isinstance(source, BivariateBRDF):
        return {"type": "bivariate", "table": source.to_bitmap(), "sampling": sampling}
    if isinstance(source, MERLBRDF):
        return {"type": "merl", "table": _merl_bitmap(source.table), "interpolation": interpolation,
                "sampling": sampling}
    if callable(getattr(source, "eval", None)):
        name = str(getattr(source, "name", type(source).__name__))
        merl = MERLBRDF.from_function(source.eval, name=name, dtype=np.float32)
        return {"type": "merl", "table": _merl_bitmap(merl.table), "interpolation": interpolation,
                "sampling": sampling}
    raise InputError("bsdf", f"cannot make a BSDF from a {type(source).__name__}",
                     "pass a BivariateBRDF, MERLBRDF, analytic BRDF, .npz/.binary path or a BSDF dict")


# ----------------------------------------------------------------- camera

def _resolution(resolution: Union[int, Sequence[int]]) -> Tuple[int, int]:
    if isinstance(resolution, (int, np.integer)):
        width = height = int(resolution)
    else:
        width, height = (int(v) for v in resolution)
    if width < 1 or height < 1:
        raise InputError("resolution", f"must be positive, got {resolution!r}")
    return width, height


def _rotation(camera_to_world: Any) -> np.ndarray:
    rot = np.eye(3) if camera_to_world is None else np.asarray(camera_to_world, np.float64)
    if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise InputError("camera_to_world", "must be a (3, 3) rotation matrix")
    return rot


def default_distance(fov: float, radius_fraction: float) -> float:
    """Perspective distance at which the silhouette radius is ``radius_fraction`` of the image width.

    The silhouette of a unit sphere at distance d has angular radius asin(1/d).
    """
    tan_sil = 2.0 * radius_fraction * math.tan(math.radians(fov) / 2.0)
    return 1.0 / math.sin(math.atan(tan_sil))


def camera_rays(camera: Dict[str, Any], px: np.ndarray, py: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """World ray origins and unit directions through film positions (pixels, y down).

    Args:
        camera: a :attr:`SphereRender.camera` dictionary.
        px, py: film coordinates in pixels, any broadcastable shape.

    Returns:
        ``(origins, directions)``, ``(..., 3) float64``.
    """
    width, height = camera["resolution"]
    rot = np.asarray(camera["camera_to_world"], np.float64)
    px, py = np.broadcast_arrays(np.asarray(px, np.float64), np.asarray(py, np.float64))
    # Film positions in units of half the image width (Mitsuba's x-axis convention).
    u = (px - 0.5 * width) / (0.5 * width)
    v = (0.5 * height - py) / (0.5 * width)
    if camera["type"] == "orthographic":
        half = camera["half_width"]
        local_o = np.stack([u * half, v * half, np.full_like(u, camera["distance"])], axis=-1)
        local_d = np.broadcast_to(np.array([0.0, 0.0, -1.0]), local_o.shape)
    else:
        tan = math.tan(math.radians(camera["fov"]) / 2.0)
        local_d = np.stack([u * tan, v * tan, -np.ones_like(u)], axis=-1)
        local_d = local_d / np.linalg.norm(local_d, axis=-1, keepdims=True)
        local_o = np.broadcast_to(np.array([0.0, 0.0, camera["distance"]]), local_d.shape)
    return local_o @ rot.T, local_d @ rot.T


def coverage_mask(camera: Dict[str, Any]) -> np.ndarray:
    """``(H, W) bool``: pixels whose four corner rays all hit the unit sphere (full coverage)."""
    width, height = camera["resolution"]
    cx, cy = np.meshgrid(np.arange(width + 1, dtype=np.float64), np.arange(height + 1, dtype=np.float64))
    o, d = camera_rays(camera, cx, cy)
    # Distance^2 from the centre to the ray's line: |o|^2 - (o.d)^2 (d unit; camera outside the sphere).
    od = np.einsum("...k,...k->...", o, d)
    hit = (np.einsum("...k,...k->...", o, o) - od * od < 1.0) & (od < 0.0)
    return hit[:-1, :-1] & hit[:-1, 1:] & hit[1:, :-1] & hit[1:, 1:]


def sensor_dict(camera: Dict[str, Any]) -> dict:
    """Mitsuba sensor dictionary (box filter, float32 RGB film) for a camera description."""
    import mitsuba as mi

    width, height = camera["resolution"]
    film = {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
            "rfilter": {"type": "box"}}
    sensor = {"type": camera["type"], "film": film, "to_world": mi.ScalarTransform4f(camera["to_world"])}
    if camera["type"] == "perspective":
        sensor.update(fov=float(camera["fov"]), fov_axis="x", near_clip=1e-3, far_clip=1e4)
    else:
        sensor.update(near_clip=1e-3, far_clip=1e4)
    return sensor


def make_camera(camera: str = "orthographic", resolution: Union[int, Sequence[int]] = 256,
                radius_fraction: float = 0.45, fov: float = 30.0, distance: Optional[float] = None,
                camera_to_world: Any = None) -> Dict[str, Any]:
    """Describe a camera looking at the unit sphere at the origin (see the module docstring)."""
    import mitsuba as mi

    width, height = _resolution(resolution)
    rot = _rotation(camera_to_world)
    if not radius_fraction > 0.0:
        raise InputError("radius_fraction", f"must be positive, got {radius_fraction}")
    info: Dict[str, Any] = {"type": camera, "resolution": (width, height), "camera_to_world": rot}
    if camera == "orthographic":
        # Silhouette radius in pixels = radius_fraction * min(W, H); one pixel = 2 half / W world units.
        radius_px = radius_fraction * min(width, height)
        info.update(half_width=0.5 * width / radius_px, distance=ORTHO_DISTANCE, fov=None)
        scale = mi.ScalarTransform4f().scale([info["half_width"]] * 2 + [1.0])
    elif camera == "perspective":
        if not 0.0 < fov < 180.0:
            raise InputError("fov", f"must be in (0, 180) degrees, got {fov}")
        d = default_distance(fov, radius_fraction) if distance is None else float(distance)
        if d <= 1.0:
            raise InputError("distance", f"the camera must be outside the unit sphere, got {d}")
        info.update(fov=float(fov), distance=d)
        scale = mi.ScalarTransform4f()
    else:
        raise InputError("camera", f"unknown camera {camera!r}", "use 'orthographic' or 'perspective'")
    origin = rot @ np.array([0.0, 0.0, info["distance"]])
    up = rot @ np.array([0.0, 1.0, 0.0])
    look = mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=[0.0, 0.0, 0.0], up=up.tolist())
    info["to_world"] = np.array((look @ scale).matrix, np.float64)
    return info


def sphere_geometry(camera: Dict[str, Any], radius_fraction: float) -> Optional[SphereGeometry]:
    """The orthographic render's sphere in pixels (``None`` for perspective)."""
    if camera["type"] != "orthographic":
        return None
    width, height = camera["resolution"]
    return SphereGeometry(cx=0.5 * width, cy=0.5 * height, radius=radius_fraction * min(width, height),
                          camera_to_world=np.array(camera["camera_to_world"]))


# ------------------------------------------------------------------ scene

def sphere_scene_dict(bsdf: dict, probe: Any, camera: Dict[str, Any], normals: bool = True,
                      max_depth: int = 2, center: Sequence[float] = (0.0, 0.0, 0.0)) -> dict:
    """Scene dictionary: unit sphere, probe emitter, camera, ``path`` (inside ``aov`` when ``normals``).

    ``center`` moves the sphere (world units); the probe is at infinity, so
    this shifts the sphere in the image without changing its shading.
    """
    integrator = {"type": "path", "max_depth": max_depth, "hide_emitters": True}
    if normals:
        integrator = {"type": "aov", "aovs": "nn:sh_normal", "integrator": integrator}
    return {
        "type": "scene",
        "integrator": integrator,
        "sensor": sensor_dict(camera),
        "sphere": {"type": "sphere", "center": [float(c) for c in center], "radius": 1.0, "bsdf": bsdf},
        "probe": probe.emitter_dict(),
    }


def load_scene(scene: dict) -> Any:
    """``mi.load_dict`` that turns a plugin's InputError (wrapped by Mitsuba) back into one line."""
    import mitsuba as mi

    try:
        return mi.load_dict(scene)
    except RuntimeError as exc:
        marker = "InputError: "
        text = str(exc)
        if marker in text:
            raise InputError(None, text.rsplit(marker, 1)[1].strip().splitlines()[0]) from None
        raise


def render_sphere(bsdf: Any, probe: Any, resolution: Union[int, Sequence[int]] = 256, spp: int = 256,
                  camera: str = "orthographic", seed: int = 0, radius_fraction: float = 0.45,
                  fov: float = 30.0, distance: Optional[float] = None,
                  camera_to_world: Any = None) -> SphereRender:
    """Render a unit sphere with ``bsdf`` under ``probe``.

    Args:
        bsdf: a BSDF dictionary, or anything :func:`bsdf_dict` accepts.
        probe: a :class:`~mi_bivariate.probes.Probe` (anything with ``emitter_dict()``).
        resolution: image size, an int (square) or ``(W, H)``.
        spp: samples per pixel.
        camera: ``"orthographic"`` or ``"perspective"``.
        seed: sampler seed; the same inputs and seed give the identical image.
        radius_fraction: silhouette radius as a fraction of ``min(W, H)`` (orthographic),
            or of the image width (perspective, when ``distance`` is None).
        fov: horizontal field of view in degrees (perspective).
        distance: camera distance from the sphere centre (perspective).
        camera_to_world: ``(3, 3)`` rotation of the camera about the sphere's centre.
    """
    import mitsuba as mi

    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    if int(spp) < 1:
        raise InputError("spp", f"must be >= 1, got {spp}")
    bsdf = bsdf_dict(bsdf)
    cam = make_camera(camera, resolution, radius_fraction, fov, distance, camera_to_world)
    scene = load_scene(sphere_scene_dict(bsdf, probe, cam, normals=True))
    out = np.array(mi.render(scene, spp=int(spp), seed=int(seed)), dtype=np.float32)
    image = np.ascontiguousarray(out[..., :3])
    n = out[..., 3:6].astype(np.float64)
    mask = coverage_mask(cam)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(mask[..., None] & (length > 0.0), n / np.maximum(length, 1e-30), 0.0).astype(np.float32)
    return SphereRender(image=image, normals=n, mask=mask, geometry=sphere_geometry(cam, radius_fraction),
                        camera=cam, spp=int(spp), seed=int(seed))


def render_like(bsdf: Any, probe: Any, geometry: SphereGeometry, width: int, height: int, spp: int = 64,
                seed: int = 0) -> SphereRender:
    """Render the unit sphere exactly where ``geometry`` puts it in a ``width x height`` image.

    Used to re-render a recovered BRDF next to a user's photo: the orthographic
    camera gets the photo's scale (``geometry.radius`` pixels per unit) and
    pose, and the sphere is moved so its centre lands on ``(cx, cy)``.
    The returned ``mask`` marks pixels whose centre sees the sphere.
    """
    import mitsuba as mi

    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    cam = make_camera("orthographic", (width, height), radius_fraction=geometry.radius / min(width, height),
                      camera_to_world=geometry.camera_to_world)
    offset = np.array([(geometry.cx - 0.5 * width) / geometry.radius,
                       -(geometry.cy - 0.5 * height) / geometry.radius, 0.0])
    center = np.asarray(geometry.camera_to_world, np.float64) @ offset
    scene = load_scene(sphere_scene_dict(bsdf_dict(bsdf), probe, cam, normals=True, center=center))
    out = np.array(mi.render(scene, spp=int(spp), seed=int(seed)), dtype=np.float32)
    normals, mask = geometry.normals(width, height)
    return SphereRender(image=np.ascontiguousarray(out[..., :3]), normals=normals.astype(np.float32), mask=mask,
                        geometry=geometry, camera=cam, spp=int(spp), seed=int(seed))


# ----------------------------------------------------------------- output
# Previews and EXRs are written by mi_bivariate.images; re-exported here for convenience.
from mi_bivariate.images import tonemap, write_exr  # noqa: E402
from mi_bivariate.images import write_png as write_png_preview  # noqa: E402
