"""Any known shape: a triangle mesh seen by a posed camera.

The paper measures a sphere; nothing in Eqs. 3-6 needs one. What the capture
step needs is, per pixel, the world normal it sees, the direction towards the
camera and (for visibility) the surface point. For a mesh these come from
Mitsuba itself: the mesh is loaded into a scene and the camera's pixel-centre
rays are intersected with ``scene.ray_intersect`` (vectorised over the
image). The normal is the shading normal ``si.sh_frame.n``, the one Mitsuba's
BSDFs use in a render: interpolated vertex normals when the mesh has them,
else the face normal (flat shading; warned about with ``normals="auto"``).

Self-occlusion: a non-convex object hides part of each normal's hemisphere
from the environment (the paper ignores it). :attr:`Observations.positions`
keeps each pixel's surface point so that
:func:`mi_bivariate.lighting.lighting_matrix` can trace shadow rays against
:meth:`MeshShape.scene` (``occluder=``).

Cameras (:class:`Camera`) follow :mod:`mi_bivariate.geometry`: camera frame x
right, y up, z towards the viewer, looking down -z; pixel (i, j) has its
centre at (i + 0.5, j + 0.5), image y down. A perspective camera has
:class:`~mi_bivariate.geometry.Intrinsics` in pixels; an orthographic one
uses the same class with ``fx, fy`` in pixels per world unit.

Pixel coverage: a pixel is used when the rays through its centre and its
four corners all hit the mesh on one continuous surface patch (corner
points close to the centre's tangent plane, normals within
:data:`PATCH_MAX_ANGLE_DEG`), so pixels that mix the object with the
background, or a near surface with a far one, are left out.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import mitsuba as mi
import numpy as np

from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Camera, Geometry, SurfaceMaps
from mi_bivariate.variants import ensure_variant

#: Mesh file types read through trimesh.
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
#: The shortest vertex normal taken as a direction (shorter: as none, in a file; refused, given directly).
MIN_NORMAL_LENGTH = 1e-12

#: A pixel's corner hits must have shading normals within this angle of its centre's.
PATCH_MAX_ANGLE_DEG = 30.0
#: ... and lie this close to the centre's tangent plane (relative to their distance).
PATCH_MAX_SLOPE = 0.35


# -------------------------------------------------------------------- mesh

def _trimesh_load(path: Path) -> Any:
    import trimesh

    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on foreign or corrupt files
        raise InputError(path, f"cannot read the mesh ({type(exc).__name__}: {str(exc).strip()[:200]})",
                         f"use one of {', '.join(MESH_SUFFIXES)}") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(path, "the file holds no triangle mesh")
    if not np.all(np.isfinite(loaded.vertices)):  # before trimesh's own processing trips over them
        raise InputError(path, "the mesh has non-finite vertex positions")
    return loaded


def _file_vertex_normals(path: Path, n_vertices: int) -> Tuple[Optional[np.ndarray], int]:
    """The vertex normals stored in a mesh file, or ``None``, and how many of its parts store none.

    trimesh reads them but drops them from the mesh it returns (its cache is
    invalidated on load), so the format loader is asked directly. A file of
    several parts (glTF primitives) where only some store normals gives the
    others' computed from their faces (:func:`_parts_vertex_normals`).
    """
    try:
        from trimesh.exchange.load import mesh_loaders

        kind = path.suffix.lower().lstrip(".")
        if kind not in mesh_loaders:
            return None, 0
        with open(path, "rb") as f:
            kwargs = mesh_loaders[kind](f, file_type=kind)
        placed = isinstance(kwargs, dict) and "geometry" in kwargs  # a scene graph (glTF): nodes place it
        if placed and isinstance(kwargs["geometry"], dict) and len(kwargs["geometry"]) > 1:
            return _parts_vertex_normals(path, kwargs["geometry"], n_vertices)
        if placed and isinstance(kwargs["geometry"], dict) and len(kwargs["geometry"]) == 1:
            kwargs = next(iter(kwargs["geometry"].values()))
        normals = _usable_normals(kwargs.get("vertex_normals") if isinstance(kwargs, dict) else None, n_vertices)
        if normals is None:  # unusable as a whole, as a part of several is (_parts_vertex_normals)
            return None, 0
        if placed:  # trimesh moved the vertices by the node's transform: the normals follow it
            transform = _node_transform(path)
            if transform is None:
                return None, 0
            normals = _placed_normals(normals, transform)
    except Exception:  # an unreadable normal block is the same as none
        return None, 0
    return normals, 0


def _usable_normals(normals: Any, n_vertices: int) -> Optional[np.ndarray]:
    """A file's stored vertex normals as ``(n_vertices, 3) float64``, or ``None`` where there are none or
    they are unusable: another shape, a NaN, or one shorter than :data:`MIN_NORMAL_LENGTH`."""
    if normals is None:
        return None
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != (n_vertices, 3) or not np.all(np.isfinite(normals)) \
            or not np.all(np.linalg.norm(normals, axis=1) >= MIN_NORMAL_LENGTH):
        return None
    return normals


def _placed_normals(normals: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Unit normals ``(V, 3)`` of vertices moved by the ``(4, 4)`` ``transform``: rows ``(M^-T n)^T``."""
    normals = normals @ np.linalg.inv(transform[:3, :3])
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


def _parts_vertex_normals(path: Path, parts: Dict[str, Any], n_vertices: int) -> Tuple[Optional[np.ndarray], int]:
    """The vertex normals of a file of several parts, in the order of the mesh ``trimesh.load(force="mesh")``
    makes of it (its scene's geometry nodes, each part moved by its node), and the number of parts that
    store none: those get the smooth normals trimesh computes from their own faces as placed (as
    ``normals="vertex"`` does for a whole mesh; one Mitsuba mesh has vertex normals everywhere or nowhere). ``(None, 0)`` when no part stores normals, or the parts do not
    add up to the mesh's ``n_vertices``."""
    import trimesh

    scene = trimesh.load(str(path), force="scene", process=False)
    normals, stored, computed = [], 0, 0
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        if not isinstance(geometry, trimesh.Trimesh):  # as to_mesh: only triangle meshes are kept
            continue
        transform = np.asarray(transform, dtype=np.float64)
        part = parts.get(name)
        own = _usable_normals(part.get("vertex_normals") if isinstance(part, dict) else None, len(geometry.vertices))
        if own is not None:
            normals.append(_placed_normals(own, transform))
            stored += 1
        else:
            placed = geometry.copy()
            placed.apply_transform(transform)
            normals.append(np.asarray(placed.vertex_normals, dtype=np.float64))
            computed += 1
    if stored == 0 or sum(len(n) for n in normals) != n_vertices:
        return None, 0
    return np.concatenate(normals), computed


def _node_transform(path: Path) -> Optional[np.ndarray]:
    """The ``(4, 4)`` transform by which a scene file's one placed geometry reaches the world (what
    ``trimesh.load(force="mesh")`` applied to its vertices), or ``None`` if it is placed more than once."""
    import trimesh

    scene = trimesh.load(str(path), force="scene", process=False)
    nodes = [node for names in scene.graph.geometry_nodes.values() for node in names]
    if len(nodes) != 1:
        return None
    return np.asarray(scene.graph[nodes[0]][0], dtype=np.float64)


#: File vertex normals further than this (median angle, degrees) from the outward normals of a closed
#: mesh's faces are refused: they belong to another placement of the mesh or point inwards.
MAX_NORMAL_DISAGREEMENT_DEG = 60.0


class MeshShape:
    """A triangle mesh of known shape, in world units.

    Attributes:
        vertices: ``(V, 3) float64``.
        faces: ``(F, 3) int64`` vertex indices, counter-clockwise seen from outside.
        vertex_normals: ``(V, 3) float64`` unit shading normals, or ``None``
            (face normals: flat shading).
        source: the file (or a description) for messages.
        watertight: whether the surface is closed (visibility is exact
            only then; light can leak through holes otherwise).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, vertex_normals: Optional[np.ndarray] = None,
                 source: str = "mesh", watertight: Optional[bool] = None):
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
            raise InputError(source, f"a mesh needs (V >= 3, 3) vertices, got shape {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1:
            raise InputError(source, f"a mesh needs (F >= 1, 3) triangle faces, got shape {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= len(vertices):
            raise InputError(source, "face indices must be integers in [0, V)")
        if not np.all(np.isfinite(vertices)):
            raise InputError(source, "the mesh has non-finite vertex positions")
        if vertex_normals is not None:
            vertex_normals = np.asarray(vertex_normals, dtype=np.float64)
            length = np.linalg.norm(vertex_normals, axis=1, keepdims=True)
            if vertex_normals.shape != vertices.shape or not np.all(np.isfinite(vertex_normals)) \
                    or np.any(length < MIN_NORMAL_LENGTH):
                raise InputError(source, "vertex normals must be finite, non-zero and one per vertex")
            vertex_normals = vertex_normals / length
        self.vertices = vertices
        self.faces = faces.astype(np.int64)
        self.vertex_normals = vertex_normals
        self.source = str(source)
        self.watertight = bool(watertight) if watertight is not None else self._is_watertight()
        self._scenes: Dict[str, Any] = {}

    def __repr__(self) -> str:
        shading = "vertex normals" if self.vertex_normals is not None else "face normals"
        return (f"MeshShape({self.source!r}, {len(self.vertices)} vertices, {len(self.faces)} faces, "
                f"{shading}, {'watertight' if self.watertight else 'open'})")

    def _is_watertight(self) -> bool:
        import trimesh

        # Merge duplicate vertices first: STL stores every triangle separately.
        return bool(trimesh.Trimesh(self.vertices, self.faces, process=True).is_watertight)

    @classmethod
    def load(cls, source: Union[PathLike, Any], normals: str = "auto") -> "MeshShape":
        """A mesh from a file trimesh reads (OBJ, PLY, STL, GLB, ...) or a ``trimesh.Trimesh``.

        Args:
            normals: ``"auto"``: the file's vertex normals when it has them
                (a NaN or zero-length one makes them unusable: as none),
                else face normals with an :class:`InputWarning`; ``"vertex"``:
                the file's, else smooth angle-weighted ones computed from the
                faces; ``"face"``: face normals (flat shading). In a file of
                several parts (glTF primitives) of which only some store
                normals, the others' are computed from their faces, with an
                :class:`InputWarning` (one mesh has vertex normals everywhere
                or nowhere).

        Raises:
            InputError: unreadable file, no triangles, non-finite vertices.

        Warns:
            InputWarning: no vertex normals (``"auto"``), parts without them
                beside parts with them, a surface that is not closed
                (visibility leaks through holes), faces wound inwards.
        """
        import trimesh

        if normals not in ("auto", "vertex", "face"):
            raise InputError("normals", f"must be 'auto', 'vertex' or 'face', got {normals!r}")
        if isinstance(source, trimesh.Trimesh):
            mesh, name = source, "trimesh mesh"
            # A Trimesh whose normals were set explicitly keeps them in its cache.
            stored = np.asarray(mesh._cache["vertex_normals"]) if "vertex_normals" in mesh._cache else None
            computed_parts = 0
        else:
            path = Path(source)
            if not path.is_file():
                raise InputError(path, "mesh file not found")
            if path.suffix.lower() not in MESH_SUFFIXES:
                raise InputError(path, f"unknown mesh file type {path.suffix!r}", f"use one of {', '.join(MESH_SUFFIXES)}")
            mesh, name = _trimesh_load(path), str(path)
            stored, computed_parts = _file_vertex_normals(path, len(mesh.vertices))
            if stored is not None and normals != "face" and mesh.is_watertight:  # (a closed surface has an outside)
                # The area-weighted normals of the faces as placed, turned outwards (faces wound inwards
                # have a negative volume; the shading normals of such a file may still point out).
                outward = np.asarray(mesh.vertex_normals) * (-1.0 if float(mesh.volume) < 0.0 else 1.0)
                # Directions only: a file's normals need not be unit length (MeshShape normalises them).
                unit = stored / np.maximum(np.linalg.norm(stored, axis=1, keepdims=True), 1e-300)
                angle = np.degrees(np.arccos(np.clip(np.sum(unit * outward, axis=1), -1.0, 1.0)))
                if float(np.median(angle)) > MAX_NORMAL_DISAGREEMENT_DEG:
                    raise InputError(name, f"the file's vertex normals are {np.median(angle):.0f} deg (median) "
                                     "from the outward normals of its faces", "fix or drop them, or load it with "
                                     "normals='face'")
            if stored is None:
                # Nothing to keep in step with the file's vertex order: weld duplicates
                # (STL repeats every corner) so computed vertex normals are smooth.
                mesh.merge_vertices()
        if len(mesh.faces) == 0 or len(mesh.vertices) < 3:
            raise InputError(name, "the mesh has no triangles")
        if not np.all(np.isfinite(mesh.vertices)):
            raise InputError(name, "the mesh has non-finite vertex positions")
        # Degenerate (zero-area) faces have no normal; Mitsuba would shade them with NaN.
        area = np.asarray(mesh.area_faces)
        keep = area > 1e-14 * max(float(area.max()), 1e-300)
        faces = np.asarray(mesh.faces)[keep]
        if len(faces) == 0:
            raise InputError(name, "every face of the mesh is degenerate (zero area)")

        vertex_normals = None
        if stored is not None and normals != "face" and computed_parts:
            warnings.warn(f"{name}: {computed_parts} of the file's parts store no vertex normals; theirs are "
                          "computed from their faces (smooth shading, as the parts with normals)",
                          InputWarning, stacklevel=2)
        if normals == "vertex":
            vertex_normals = stored if stored is not None else np.asarray(mesh.vertex_normals)
        elif normals == "auto":
            if stored is None:
                warnings.warn(f"{name}: the mesh has no vertex normals; using face normals (flat shading). "
                              "Pass normals='vertex' to smooth them", InputWarning, stacklevel=2)
            vertex_normals = stored
        shape = cls(mesh.vertices, faces, vertex_normals, source=name)
        if not shape.watertight:
            warnings.warn(f"{name}: the mesh is not watertight (open edges); shadow rays can leak through "
                          "its holes, so visibility is only approximate", InputWarning, stacklevel=2)
        elif float(trimesh.Trimesh(shape.vertices, shape.faces, process=False).volume) < 0.0:
            warnings.warn(f"{name}: the faces are wound inwards (negative volume); their geometric normals "
                          "point into the object. Fix with trimesh.repair.fix_normals", InputWarning, stacklevel=2)
        return shape

    @property
    def diagonal(self) -> float:
        """Length of the bounding box diagonal (world units)."""
        return float(np.linalg.norm(self.vertices.max(axis=0) - self.vertices.min(axis=0)))

    def mitsuba_mesh(self, bsdf: Optional[dict] = None) -> Any:
        """The mesh as a ``mi.Mesh`` (with ``bsdf``, a BSDF dictionary, when given)."""
        ensure_variant()  # a user's script may reach here before anything chose a variant
        props = mi.Properties()
        if bsdf is not None:
            props["bsdf"] = mi.load_dict(bsdf)
        has_normals = self.vertex_normals is not None
        mesh = mi.Mesh(Path(self.source).stem or "mesh", len(self.vertices), len(self.faces), props=props,
                       has_vertex_normals=has_normals)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(self.vertices.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(self.faces.astype(np.uint32).ravel())
        if has_normals:
            params["vertex_normals"] = mi.Float(self.vertex_normals.astype(np.float32).ravel())
        params.update()
        return mesh

    def scene(self) -> Any:
        """A ``mi.Scene`` holding only this mesh (for ray casts and shadow rays), cached per variant."""
        variant = ensure_variant(vectorised=True)  # the ray casts are vectorised over pixels
        if variant not in self._scenes:
            self._scenes[variant] = mi.load_dict({"type": "scene", "shape": self.mitsuba_mesh()})
        return self._scenes[variant]


# ----------------------------------------------------------- ray casting

def _cast(scene: Any, origins: np.ndarray, directions: np.ndarray) -> Tuple[np.ndarray, ...]:
    """Intersect rays ``(N, 3)``: ``valid (N,)``, ``p``, ``sh_n``, ``n`` ``(N, 3)`` float64."""
    ray = mi.Ray3f(mi.Point3f(origins.astype(np.float32).T), mi.Vector3f(directions.astype(np.float32).T))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    p = np.array(si.p, dtype=np.float64).T
    sh_n = np.array(si.sh_frame.n, dtype=np.float64).T
    n = np.array(si.n, dtype=np.float64).T
    return valid, p, sh_n, n


def surface_maps(shape: MeshShape, camera: Camera) -> SurfaceMaps:
    """Ray-cast ``shape`` from ``camera`` at pixel centres and corners.

    Raises:
        InputError: the camera sees no part of the mesh.
    """
    scene = shape.scene()
    w, h = camera.width, camera.height
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    o, d = camera.rays(x, y)
    valid, p, sh_n, n = _cast(scene, o.reshape(-1, 3), d.reshape(-1, 3))
    if not valid.any():
        raise InputError(shape.source, "the camera sees no part of the mesh",
                         "check the camera position, direction and field of view")
    sh_n /= np.maximum(np.linalg.norm(sh_n, axis=1, keepdims=True), 1e-30)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)

    # Corner rays: the same patch must cover the whole pixel.
    cx, cy = np.meshgrid(np.arange(w + 1, dtype=np.float64), np.arange(h + 1, dtype=np.float64))
    co, cd = camera.rays(cx, cy)
    c_valid, c_p, c_n, _ = _cast(scene, co.reshape(-1, 3), cd.reshape(-1, 3))
    c_valid, c_p, c_n = c_valid.reshape(h + 1, w + 1), c_p.reshape(h + 1, w + 1, 3), c_n.reshape(h + 1, w + 1, 3)
    c_n /= np.maximum(np.linalg.norm(c_n, axis=-1, keepdims=True), 1e-30)
    valid, p, sh_n, n = valid.reshape(h, w), p.reshape(h, w, 3), sh_n.reshape(h, w, 3), n.reshape(h, w, 3)
    mask = valid.copy()
    cos_max = math.cos(math.radians(PATCH_MAX_ANGLE_DEG))
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        cv = c_valid[dy:dy + h, dx:dx + w]
        cp = c_p[dy:dy + h, dx:dx + w]
        cn = c_n[dy:dy + h, dx:dx + w]
        offset = cp - p
        dist = np.linalg.norm(offset, axis=-1)
        with np.errstate(invalid="ignore"):
            flat = np.abs(np.sum(offset * sh_n, axis=-1)) <= PATCH_MAX_SLOPE * dist + 1e-9
            mask &= cv & flat & (np.sum(cn * sh_n, axis=-1) >= cos_max)

    views = np.where(valid[..., None], -d, 0.0)
    nan = np.where(valid[..., None], 0.0, np.nan)
    return SurfaceMaps(normals=np.where(valid[..., None], sh_n, 0.0), views=views, positions=p + nan,
                       geometric_normals=np.where(valid[..., None], n, 0.0), hit=valid, mask=mask)


@dataclass(frozen=True)
class MeshView(Geometry):
    """A mesh seen by a posed camera: the :class:`~mi_bivariate.geometry.Geometry` of an image of a known shape.

    Usable wherever :func:`mi_bivariate.recover.recover` takes a geometry.
    """

    shape: MeshShape
    camera: Camera

    def __post_init__(self) -> None:
        if not isinstance(self.shape, MeshShape):
            raise InputError("geometry", f"MeshView needs a MeshShape, got a {type(self.shape).__name__}",
                             "load the mesh with mi_bivariate.mesh.MeshShape.load(path)")
        if not isinstance(self.camera, Camera):
            raise InputError("geometry", f"MeshView needs a Camera, got a {type(self.camera).__name__}",
                             "e.g. mi_bivariate.geometry.Camera.look_at(...)")

    no_pixels = "no pixel sees the mesh cleanly (all are silhouette or masked pixels)"
    no_pixels_hint = "use a larger image or move the camera closer"

    def surface(self) -> SurfaceMaps:
        """:func:`surface_maps` (cached)."""
        cache = self.__dict__.get("_surface")
        if cache is None:
            cache = surface_maps(self.shape, self.camera)
            object.__setattr__(self, "_surface", cache)
        return cache

    def surface_maps(self, width: int, height: int, source: str = "image") -> SurfaceMaps:
        """:meth:`surface` for an image of the camera's size (``InputError`` otherwise)."""
        cam = self.camera
        if (height, width) != (cam.height, cam.width):
            raise InputError(source, f"image is {width}x{height} but the camera is {cam.width}x{cam.height}",
                             "give the camera the image's size")
        return self.surface()

    def occluder(self) -> MeshShape:
        """The object that casts shadows on itself (for ``lighting_matrix(occluder=...)``)."""
        return self.shape
