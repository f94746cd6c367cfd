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

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import mitsuba as mi
import numpy as np

from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.geometry import Camera, SphereCamera, SphereGeometry, check_sphere
from mi_bivariate.limits import check_render_sizes, check_seed
from mi_bivariate.merl import MERLBRDF
from mi_bivariate.mesh import MeshShape, MeshView
from mi_bivariate.probes import Probe, check_probe, refuse_probe
from mi_bivariate.variants import ensure_variant


@dataclass
class SphereRender:
    """A rendered sphere.

    Attributes:
        image: ``(H, W, 3) float32`` linear RGB radiance (background 0).
        normals: ``(H, W, 3) float32`` unit world normals inside ``mask``, 0 elsewhere.
        mask: ``(H, W) bool`` pixels fully covered by the sphere.
        geometry: the sphere in pixels (orthographic camera), else ``None``.
        camera: the :class:`~mi_bivariate.geometry.SphereCamera` it was rendered from.
        spp, seed: sampling parameters of the render.
    """

    image: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    geometry: Optional[SphereGeometry]
    camera: Optional[SphereCamera] = None
    spp: int = 0
    seed: int = 0


# ------------------------------------------------------------------ BSDFs

def _merl_bitmap(table: np.ndarray):

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
    ensure_variant(vectorised=True)
    if isinstance(source, dict):
        if "type" not in source:
            raise InputError("bsdf", "a BSDF dictionary needs a 'type' entry")
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        suffix = path.suffix.lower()
        if not path.is_file():
            raise InputError(path, "BRDF file not found", "check the path")
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
    refuse_probe(source, "bsdf")
    if callable(getattr(source, "eval", None)):
        name = str(getattr(source, "name", type(source).__name__))
        merl = MERLBRDF.from_function(source.eval, name=name, dtype=np.float32)
        return {"type": "merl", "table": _merl_bitmap(merl.table), "interpolation": interpolation,
                "sampling": sampling}
    raise InputError("bsdf", f"cannot make a BSDF from a {type(source).__name__}",
                     "pass a BivariateBRDF, MERLBRDF, analytic BRDF, .npz/.binary path or a BSDF dict")


# ------------------------------------------------------------------ scene

def sphere_scene_dict(bsdf: dict, probe: Any, camera: SphereCamera, normals: bool = True,
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
        "sensor": camera.sensor_dict(),
        "sphere": {"type": "sphere", "center": [float(c) for c in center], "radius": 1.0, "bsdf": bsdf},
        "probe": probe.emitter_dict(),
    }


def _check_render_inputs(probe: Any, width: Any, height: Any, spp: Any, seed: Any, width_name: str = "width") -> int:
    """The checks every render's front door makes before building a scene: the probe's type, the
    image size and samples within :mod:`mi_bivariate.limits`, the seed an unsigned 32-bit integer
    (returned as an ``int``)."""
    check_probe(probe)
    check_render_sizes(width, spp, (width_name, "spp"), hint="lower spp or the image size", height=height)
    return check_seed(seed)


def load_scene(scene: dict) -> Any:
    """``mi.load_dict`` that turns a plugin's InputError (wrapped by Mitsuba) back into one line."""
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
    ensure_variant(vectorised=True)
    if np.ndim(resolution) == 0:
        seed = _check_render_inputs(probe, resolution, None, spp, seed, width_name="resolution")
        resolution = int(resolution)
    elif len(resolution) == 2:
        seed = _check_render_inputs(probe, resolution[0], resolution[1], spp, seed)
        resolution = (int(resolution[0]), int(resolution[1]))
    else:
        raise InputError("resolution", f"must be an int or (W, H), got {resolution!r}")
    bsdf = bsdf_dict(bsdf)
    cam = SphereCamera.create(camera, resolution, radius_fraction, fov, distance, camera_to_world)
    scene = load_scene(sphere_scene_dict(bsdf, probe, cam, normals=True))
    out = np.array(mi.render(scene, spp=int(spp), seed=int(seed)), dtype=np.float32)
    image = np.ascontiguousarray(out[..., :3])
    n = out[..., 3:6].astype(np.float64)
    mask = cam.coverage_mask()
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(mask[..., None] & (length > 0.0), n / np.maximum(length, 1e-30), 0.0).astype(np.float32)
    return SphereRender(image=image, normals=n, mask=mask, geometry=cam.sphere_geometry(radius_fraction),
                        camera=cam, spp=int(spp), seed=int(seed))


def render_like(bsdf: Any, probe: Any, geometry: SphereGeometry, width: int, height: int, spp: int = 64,
                seed: int = 0) -> SphereRender:
    """Render the unit sphere exactly where ``geometry`` puts it in a ``width x height`` image.

    Used to re-render a recovered BRDF next to a user's photo: the orthographic
    camera gets the photo's scale (``geometry.radius`` pixels per unit) and
    pose, and the sphere is moved so its centre lands on ``(cx, cy)``.
    The returned ``mask`` marks pixels whose centre sees the sphere.

    Raises:
        InputError: naming ``geometry`` if it is not a :class:`SphereGeometry` with a finite centre
            and a finite positive radius (:func:`~mi_bivariate.geometry.check_sphere`), or the
            argument that breaks a limit.
    """
    ensure_variant(vectorised=True)
    check_sphere(geometry, "geometry")
    seed = _check_render_inputs(probe, width, height, spp, seed)
    width, height = int(width), int(height)
    cam = SphereCamera.create("orthographic", (width, height), radius_fraction=geometry.radius / min(width, height),
                              camera_to_world=geometry.camera_to_world)
    offset = np.array([(geometry.cx - 0.5 * width) / geometry.radius,
                       -(geometry.cy - 0.5 * height) / geometry.radius, 0.0])
    center = np.asarray(geometry.camera_to_world, np.float64) @ offset
    scene = load_scene(sphere_scene_dict(bsdf_dict(bsdf), probe, cam, normals=True, center=center))
    out = np.array(mi.render(scene, spp=int(spp), seed=int(seed)), dtype=np.float32)
    normals, mask = geometry.normals(width, height)
    return SphereRender(image=np.ascontiguousarray(out[..., :3]), normals=normals.astype(np.float32), mask=mask,
                        geometry=geometry, camera=cam, spp=int(spp), seed=int(seed))


# --------------------------------------------------------------- meshes

def mesh_scene_dict(shape: MeshShape, bsdf: dict, probe: Any, camera: Camera, max_depth: int = 2) -> dict:
    """Scene dictionary: the mesh with ``bsdf``, the probe's envmap and the camera (``path`` integrator).

    ``max_depth=2`` is direct lighting with self-shadowing but no
    interreflection: the forward model of the lighting matrix with visibility.
    """
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth), "hide_emitters": True},
        "sensor": camera.sensor_dict(),
        "shape": shape.mitsuba_mesh(bsdf),
        "probe": probe.emitter_dict(),
    }


def render_mesh(bsdf: Any, probe: Any, view: MeshView, spp: int = 64, seed: int = 0,
                max_depth: int = 2) -> np.ndarray:
    """Render ``view.shape`` with ``bsdf`` (anything :func:`mi_bivariate.render.bsdf_dict` takes)
    under ``probe`` from ``view.camera``: ``(H, W, 3) float32`` linear RGB (background 0).

    Raises:
        InputError: naming ``view`` if it is not a :class:`~mi_bivariate.mesh.MeshView`.
    """
    ensure_variant(vectorised=True)
    if not isinstance(view, MeshView):
        raise InputError("view", f"expected a mi_bivariate.mesh.MeshView (a mesh and its camera), got a "
                         f"{type(view).__name__}", "render a sphere with render_sphere or render_like")
    seed = _check_render_inputs(probe, view.camera.width, view.camera.height, spp, seed)
    scene = load_scene(mesh_scene_dict(view.shape, bsdf_dict(bsdf), probe, view.camera, max_depth))
    out = np.array(mi.render(scene, spp=int(spp), seed=int(seed)), dtype=np.float32)
    return np.ascontiguousarray(out[..., :3])
