"""Converged reference images: deterministic per-pixel hemisphere quadrature.

Every image used to *score* a recovery (ground truth, validation, the relit
recovery, the input of the accuracy tables) comes from this renderer, not
from a path tracer: at 64-256 spp a path-traced sphere under a probe with
small bright sources has 2-7% per-pixel noise, which swamps a 1% floor.

A pixel that sees normal ``n`` from view ``v`` (the sphere, orthographic
camera, no interreflection: what :func:`mi_bivariate.render.render_sphere`
renders with ``max_depth=2``) has the radiance::

    I(n, v) = int_{H(n)} E(u) f(u, v) cos(theta_u) du
            ~ sum_j sum_{i < N_j} E(u_ij) [f cos](u_ij, v) / sum_k N_k p_k(u_ij)

a multi-sample estimator with the balance heuristic (Veach 1997, Sect. 9.2)
over three strategies, each with a fixed number of directions per pixel:

- ``cosine``: cosine-weighted hemisphere directions (diffuse part);
- ``lobe``: half vectors from the BSDF's own tabulated theta_h density (the
  plugins' :class:`~plugins._tabulated.HalfVectorSampler`: the table's glossy
  excess, so the directions concentrate where the lobe is, however sharp),
  reflected about the view;
- ``environment``: the ``envmap`` emitter's own importance sampling (its
  luminance-weighted hierarchical warp), for small bright sources such as the
  sun.

Each strategy maps a 2D rank-1 lattice (``((i + 1/2) / N, frac(i / golden))``,
the Fibonacci lattice of :mod:`mi_bivariate.lighting`) shifted per pixel by
a seeded Cranley-Patterson rotation, so the result is deterministic for a
seed, and two seeds give two independent estimates (how the quadrature error
is measured: :func:`quadrature_noise`). The BRDF is the *same Mitsuba plugin
object* a render uses (``merl`` with trilinear interpolation for 3D tables,
``bivariate`` for st tables: :func:`mi_bivariate.render.bsdf_dict`), and the
environment is looked up by the probe's ``envmap`` emitter
(:meth:`~mi_bivariate.probes.Probe.eval_dr`), so truth, exact reduction and
recovery go through identical code, which agrees with a Mitsuba render of the
same BSDF to the render's noise (tested).

The image is of pixel *centres* (``subpixels=1``): each pixel is the
radiance at its centre's normal, the model the recovery's lighting matrix
assumes. ``subpixels=s`` averages an ``s x s`` grid inside each pixel (the
box filter of Mitsuba's film), for comparisons with path-traced images.

Cost (measured, 2-core VM shared with other jobs, one Dr.Jit thread): see
:data:`DEFAULT_DIRECTIONS` and ``docs/results.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Dict, Sequence, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate import metrics
from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereCamera
from mi_bivariate.lighting.kernels import fibonacci_point
from mi_bivariate.render import SphereRender, bsdf_dict
from mi_bivariate.variants import ensure_variant

#: Directions per pixel and strategy (cosine, lobe, environment) by default.
DEFAULT_DIRECTIONS: Tuple[int, int, int] = (1024, 2048, 3072)
#: Radius of the sphere's silhouette as a fraction of the image size (as render_sphere's default).
RADIUS_FRACTION = 0.45
#: Lanes (pixel x direction) per Dr.Jit kernel launch.
CHUNK_LANES = 1 << 22
STRATEGIES = ("cosine", "lobe", "environment")
#: Bumped when the renderer's numbers change (part of the evaluation's cache keys).
REFERENCE_VERSION = 1


@dataclass
class ReferenceRender(SphereRender):
    """A :class:`~mi_bivariate.render.SphereRender` made by :func:`render_reference`.

    Attributes (besides the base class's; ``spp`` is the total directions per pixel):
        directions: directions per pixel for each of :data:`STRATEGIES`.
        subpixels: sub-pixel grid per axis.
        seconds: wall time of the quadrature.
        cpu_seconds: CPU time of the process meanwhile (all threads; the fair cost on a shared machine).
    """

    directions: Tuple[int, int, int] = DEFAULT_DIRECTIONS
    subpixels: int = 1
    seconds: float = 0.0
    cpu_seconds: float = 0.0


def pixel_rays(resolution: int, subpixels: int = 1, radius_fraction: float = RADIUS_FRACTION
               ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Any, dict]:
    """Normals of the sphere's pixels (orthographic camera of :func:`~mi_bivariate.render.render_sphere`).

    Returns:
        ``(normals (P, s*s, 3), pixels (P, 2) int [row, col], mask (H, W) bool, geometry, camera)``:
        the world normals at the ``s x s`` sub-pixel centres of every pixel whose
        centre lies inside the silhouette (sub-pixels outside the sphere get the
        normal pushed onto the silhouette), and the fully covered pixel mask.
    """
    cam = SphereCamera.create("orthographic", int(resolution), radius_fraction=radius_fraction)
    geometry = cam.sphere_geometry(radius_fraction)
    width, height = cam.resolution
    _, centre_inside = geometry.normals(width, height)
    rows, cols = np.nonzero(centre_inside)
    s = int(subpixels)
    offs = (np.arange(s) + 0.5) / s - 0.5
    ox, oy = np.meshgrid(offs, offs)
    x = (cols[:, None] + 0.5 + ox.reshape(1, -1) - geometry.cx) / geometry.radius
    y = -(rows[:, None] + 0.5 + oy.reshape(1, -1) - geometry.cy) / geometry.radius
    r = np.sqrt(x * x + y * y)
    scale = np.where(r > 1.0 - 1e-6, (1.0 - 1e-6) / np.maximum(r, 1e-30), 1.0)
    x, y = x * scale, y * scale
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    n_cam = np.stack([x, y, z], axis=-1)
    normals = n_cam @ np.asarray(geometry.camera_to_world, np.float64).T
    mask = cam.coverage_mask() & centre_inside
    return normals, np.stack([rows, cols], axis=1), mask, geometry, cam


def _lattice(i: Any, n: int, shift_u: Any, shift_v: Any) -> Tuple[Any, Any]:
    """Point ``i`` of the ``n``-point Fibonacci lattice, Cranley-Patterson shifted (Dr.Jit), in [0, 1)."""
    u, v = fibonacci_point(i, n, shift_u, shift_v)
    # Keep both strictly inside [0, 1): warps divide by (1 - u) near 1.
    return dr.minimum(u, 0.99999994), dr.minimum(v, 0.99999994)


def _chunk(bsdf: Any, emitter: Any, probe: Any, data: np.ndarray, directions: Tuple[int, int, int]
           ) -> np.ndarray:
    """Radiance of one chunk of sample points: ``(m, 3) float64``.

    ``data`` holds per point ``[n (3), v (3), shifts (3 strategies x 2)]``.
    """
    m = len(data)
    buf = mi.Float(np.ascontiguousarray(data, np.float32).reshape(-1))
    stride = data.shape[1]
    total = np.zeros((m, 3), np.float64)
    n_all = [int(k) for k in directions]
    ctx = mi.BSDFContext()
    for strategy, n_j in enumerate(n_all):
        if n_j == 0:
            continue
        idx = dr.arange(mi.UInt32, m * n_j)
        point = idx // n_j
        i = idx - point * n_j

        def g(c: int) -> Any:
            return dr.gather(mi.Float, buf, point * stride + c)

        normal = mi.Vector3f(g(0), g(1), g(2))
        view = mi.Vector3f(g(3), g(4), g(5))
        u, v = _lattice(i, n_j, g(6 + 2 * strategy), g(7 + 2 * strategy))
        frame = mi.Frame3f(normal)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = frame
        si.n = normal
        si.wi = frame.to_local(view)
        it = dr.zeros(mi.Interaction3f)
        if strategy == 0:
            wo = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u, v))
            world = frame.to_world(wo)
        elif strategy == 1:
            x = bsdf.sampler.distribution.sample(u)
            cos_h = 1.0 - x
            sin_h = dr.safe_sqrt(x * (2.0 - x))
            sin_phi, cos_phi = dr.sincos(dr.two_pi * v)
            h = mi.Vector3f(sin_h * cos_phi, sin_h * sin_phi, cos_h)
            wo = mi.reflect(si.wi, h)
            world = frame.to_world(wo)
        else:
            ds, _ = emitter.sample_direction(it, mi.Point2f(u, v))
            world = ds.d
            wo = frame.to_local(world)
        wo = dr.normalize(wo)
        cos_o = mi.Frame3f.cos_theta(wo)
        # Densities of this direction under every strategy (solid angle).
        p_cos = dr.maximum(cos_o, 0.0) * dr.inv_pi
        hv = dr.normalize(si.wi + wo)
        rho2 = hv.x * hv.x + hv.y * hv.y
        xh = rho2 / (1.0 + hv.z)
        up = (cos_o > 0.0) & (hv.z > 0.0)
        p_h = bsdf.sampler.distribution.eval_pdf_normalized(xh, up) * dr.inv_two_pi
        dot = dr.abs(dr.dot(wo, hv))
        p_lobe = dr.select(up & (dot > 0.0), p_h / (4.0 * dr.maximum(dot, 1e-30)), 0.0)
        ds_eval = dr.zeros(mi.DirectionSample3f)
        ds_eval.d = world
        p_env = emitter.pdf_direction(it, ds_eval)
        denom = n_all[0] * p_cos + n_all[1] * p_lobe + n_all[2] * p_env
        value = bsdf.eval(ctx, si, wo) * probe.eval_dr(world)
        ok = (cos_o > 0.0) & (denom > 0.0)
        contrib = dr.select(ok, value / dr.maximum(denom, 1e-30), 0.0)
        # One kernel for all three channels: evaluating the sums one at a time would re-run the
        # whole trace (sampling, BSDF, envmap) per channel.
        sums = [dr.block_sum(mi.Float64(contrib[c]), n_j) for c in range(3)]
        dr.eval(*sums)
        for c in range(3):
            total[:, c] += np.asarray(sums[c].numpy(), np.float64)
    return total


def render_reference(bsdf: Any, probe: Any, resolution: int = 64, seed: int = 0,
                     directions: Sequence[int] = DEFAULT_DIRECTIONS, subpixels: int = 1,
                     radius_fraction: float = RADIUS_FRACTION) -> ReferenceRender:
    """Render the sphere of :func:`~mi_bivariate.render.render_sphere` by hemisphere quadrature.

    Args:
        bsdf: anything :func:`mi_bivariate.render.bsdf_dict` accepts (a
            :class:`~mi_bivariate.merl.MERLBRDF` renders with the ``merl``
            plugin's trilinear lookup; a :class:`~mi_bivariate.bivariate.BivariateBRDF`
            with the ``bivariate`` plugin), or a loaded plugin object.
        probe: a :class:`~mi_bivariate.probes.Probe`.
        resolution: image width = height (pixels).
        seed: seeds the per-pixel Cranley-Patterson shifts (independent estimates per seed).
        directions: directions per pixel for the cosine, lobe and environment strategies.
        subpixels: ``s``: average an ``s x s`` grid of sub-pixel normals (box filter).

    Returns:
        A :class:`ReferenceRender`: ``image (H, W, 3) float32`` (0 outside the
        pixels whose centre lies on the sphere), ``normals``, ``mask`` (pixels
        fully covered, as ``render_sphere``), ``geometry``.
    """
    ensure_variant(vectorised=True)
    directions = tuple(int(k) for k in directions)
    if len(directions) != 3 or min(directions) < 0 or sum(directions) == 0:
        raise InputError("directions", f"need 3 non-negative counts (cosine, lobe, environment), got {directions}")
    if int(resolution) < 2 or int(subpixels) < 1:
        raise InputError("resolution", f"resolution must be >= 2 and subpixels >= 1, got {resolution}, {subpixels}")
    t0, cpu0 = time.perf_counter(), time.process_time()
    plugin = bsdf if hasattr(bsdf, "sampler") else mi.load_dict(bsdf_dict(bsdf))
    emitter = probe.emitter()
    normals, pixels, mask, geometry, cam = pixel_rays(resolution, subpixels, radius_fraction)
    p, s2 = normals.shape[:2]
    view = np.asarray(geometry.view_direction(), np.float64)
    shifts = np.random.default_rng(int(seed)).random((p, 6))
    data = np.empty((p, s2, 12), np.float64)
    data[..., 0:3] = normals
    data[..., 3:6] = view
    data[..., 6:12] = shifts[:, None, :]     # one shift per pixel, shared by its sub-pixels
    data = data.reshape(p * s2, 12)
    per_point = max(1, CHUNK_LANES // max(directions))
    out = np.empty((p * s2, 3), np.float64)
    for start in range(0, len(data), per_point):
        out[start:start + per_point] = _chunk(plugin, emitter, probe, data[start:start + per_point], directions)
    radiance = out.reshape(p, s2, 3).mean(axis=1)
    height = width = int(resolution)
    image = np.zeros((height, width, 3), np.float32)
    image[pixels[:, 0], pixels[:, 1]] = radiance
    normal_image = np.zeros((height, width, 3), np.float32)
    centre = normals[:, (s2 - 1) // 2] if s2 % 2 else normals.mean(axis=1)
    normal_image[pixels[:, 0], pixels[:, 1]] = centre / np.linalg.norm(centre, axis=1, keepdims=True)
    dr.eval()
    return ReferenceRender(image=image, normals=normal_image, mask=mask, geometry=geometry, camera=cam,
                           spp=sum(directions), seed=int(seed), directions=directions, subpixels=int(subpixels),
                           seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - cpu0)


def scaled_directions(factor: float, base: Sequence[int] = DEFAULT_DIRECTIONS) -> Tuple[int, int, int]:
    """``base`` directions times ``factor`` (at least 1 where base is non-zero)."""
    return tuple(max(1, int(round(k * factor))) if k else 0 for k in base)


def quadrature_noise(bsdf: Any, probe: Any, resolution: int = 64, directions: Sequence[int] = DEFAULT_DIRECTIONS,
                     seeds: Tuple[int, int] = (0, 1), reference_factor: float = 0.0) -> Dict[str, float]:
    """Measured quadrature error of :func:`render_reference` over the sphere.

    ``seed_rms``: relative RMS difference of two seeds' images over the mask,
    divided by sqrt 2 (the per-image noise, if the seeds are independent).
    With ``reference_factor > 1``, ``vs_large``: the relative RMS
    difference of the first image against one with ``reference_factor`` x
    the directions (includes any bias the two seeds share). ``seconds``: one
    render's wall time, ``cpu_seconds`` its CPU time.
    """
    ensure_variant(vectorised=True)
    plugin = bsdf if hasattr(bsdf, "sampler") else mi.load_dict(bsdf_dict(bsdf))
    a = render_reference(plugin, probe, resolution, seeds[0], directions)
    b = render_reference(plugin, probe, resolution, seeds[1], directions)
    out = {"seed_rms": metrics.seed_noise(b.image, a.image, a.mask),
           "seconds": a.seconds, "cpu_seconds": a.cpu_seconds, "directions": list(a.directions),
           "resolution": int(resolution)}
    if reference_factor > 1.0:
        big = render_reference(plugin, probe, resolution, seeds[0] + 1000,
                               scaled_directions(reference_factor, directions))
        out["vs_large"] = metrics.image_relative_rmse(a.image, big.image, a.mask)
        out["large_seconds"] = big.seconds
    return out
