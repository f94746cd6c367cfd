"""The lighting matrix L of Eq. 5: pixel values are ``I = L f``.

A pixel that sees normal ``n`` from view ``v`` integrates the environment
over the normal's upper hemisphere (Eq. 3)::

    I(v, n) = int_Omega E(u) f(s(u, v), t(u, v)) cos(theta_u) du
            ~ 2 pi / K  sum_k E(u_k) cos(theta_k) sum_{(i,j) in N_k} alpha^k_ij f_ij   (Eq. 4)

with ``K`` light directions ``u_k`` uniformly distributed (in solid angle) on
the hemisphere, ``E`` the environment radiance looked up exactly as Mitsuba's
``envmap`` emitter does (:meth:`Probe.eval_dr`), and ``alpha^k_ij`` the
bilinear weights of the four st nodes around ``(s, t)(u_k, v)``. Directions
mirrored about the view/normal plane land on the same ``(s, t)``: the
hemisphere folds by itself. Row ``m`` of ``L`` holds these weights for normal
``m``; column ``it * n_s + is`` is st node ``(t_it, s_is)`` (the C order of a
``(n_t, n_s, 3)`` table); the last axis is the colour channel.

Light directions (:func:`light_directions`): a spherical Fibonacci lattice,
uniform in solid angle, on the half of the normal's hemisphere on one side of
the view/normal plane, shifted per row by a seeded random offset (a
Cranley-Patterson rotation, which decorrelates the quadrature error between
rows), plus the mirror image of every direction across that plane. A
direction and its mirror image have the same (s, t): the fold of Fig. 4.

Implementation: one fused Dr.Jit kernel per chunk of normals (directions,
two envmap lookups per mirrored pair, Rusinkiewicz angles, bilinear weights)
scatters RGB padded to a 4-wide packet into ``[rows, n_t * n_s, 4]`` with
``ReduceMode.Expand`` (per-thread copies of the target, no atomics; see the
field notes: ``Auto`` silently picks ``Local`` on big targets, 7x slower).
Visibility (``occluder``): the paper assumes every light direction of the
normal's hemisphere reaches the surface, which holds for a convex object
only. Given the object as a Mitsuba scene, rows that know their surface
position (:attr:`Observations.positions`, e.g. ray-cast from a mesh) trace
a shadow ray per light direction inside the same kernel (``scene.ray_test``
from the point, offset along the geometric normal exactly as Mitsuba's
``spawn_ray`` does for a render's shadow rays), and blocked directions
contribute nothing. With ``max_depth=2`` renders (no interreflection) the
model is then exact for any shape.

Rows are ordered along a space-filling curve of their normals and lanes run
over (direction, row), so consecutive lanes read nearby envmap texels and
splat into a cache-resident target. Memory: the ``(M, n_t * n_s, 3)
float32`` result (94 MB at M = 8000, 32 x 32) plus, per chunk, a
:data:`CHUNK_BYTES` target per thread and its packed copy; the kernel itself
stores no per-direction arrays. Measured at M = 8000, K = 32000: peak RSS
grows by ~200 MB. Accumulation order across threads varies, so results agree
between runs to float32 rounding (~1e-7 relative), not bit for bit.
"""

from __future__ import annotations

import math
import sys
from typing import Any, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.capture import Observations
from mi_bivariate.errors import InputError

#: Size of one chunk's scatter target (one thread's copy).
CHUNK_BYTES = 2 * 2**20

#: Show a progress bar when a job has more (normal, direction) pairs than this.
PROGRESS_PAIRS = 5 * 10**8

_TWO_PI = 2.0 * math.pi
# floor(2^32 / golden ratio): (k G mod 2^32) / 2^32 = frac(k / golden), exact in uint32.
_GOLDEN_U32 = 2654435769


def hemisphere_offsets(n_rows: int, seed: int = 0) -> np.ndarray:
    """Per-row Cranley-Patterson shifts of the direction lattice, ``(n_rows, 2) float32`` in [0, 1)."""
    return np.random.default_rng(seed).random((n_rows, 2), dtype=np.float32)


def _coordinate_system(n: np.ndarray) -> np.ndarray:
    """A unit tangent of each unit normal, ``(m, 3)`` (Duff et al. 2017, as ``mi.coordinate_system``)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    return np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=-1)


def row_frames(normals: np.ndarray, views: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The local frame of each row, aligned with its view/normal plane.

    Returns:
        ``(x, y, wo)``: unit tangent ``x`` ``(m, 3)`` along the view's
        projection on the tangent plane (any tangent when the view is the
        normal), ``y = n x x`` ``(m, 3)``, and the local view ``wo`` ``(m, 3)``
        ``= (sin theta_v, 0, cos theta_v)``. float64.
    """
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    v = views / np.linalg.norm(views, axis=1, keepdims=True)
    cos_v = np.sum(n * v, axis=1)
    x = v - cos_v[:, None] * n
    length = np.linalg.norm(x, axis=1)
    along_view = length > 1e-6
    x = np.where(along_view[:, None], x / np.maximum(length, 1e-30)[:, None], _coordinate_system(n))
    y = np.cross(n, x)
    wo = np.stack([np.sum(v * x, axis=1), np.zeros(len(n)), cos_v], axis=-1)
    return x, y, wo


def direction_pairs(n_dirs: int) -> int:
    """Number of mirrored direction pairs for ``n_dirs`` light directions (K = 2 pairs)."""
    return max(1, (int(n_dirs) + 1) // 2)


def _half_lattice(n_pairs: int) -> Tuple[np.ndarray, np.ndarray]:
    """Unshifted Fibonacci lattice ``(u1, u2)`` of the half hemisphere, ``(n_pairs,) float64`` each.

    ``u2 = frac(k / golden)`` is computed as ``(k * G mod 2^32) / 2^32`` in
    exact uint32 arithmetic, as the Dr.Jit kernel does.
    """
    k = np.arange(n_pairs, dtype=np.uint64)
    u1 = (k + 0.5) / n_pairs
    u2 = ((k * _GOLDEN_U32) % 2**32).astype(np.float32).astype(np.float64) * 2.0**-32
    return u1, u2


def light_directions(normals: np.ndarray, views: np.ndarray, n_dirs: int,
                     offsets: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The light directions of each row (numpy, float64; what the Dr.Jit kernel uses).

    A spherical Fibonacci lattice on the half hemisphere ``phi in [0, pi)`` of
    the row frame (:func:`row_frames`): ``cos theta_k = frac((k + 1/2) / P +
    a)``, ``phi_k = pi frac(k / golden + b)`` for ``k < P`` pairs, with the
    row's Cranley-Patterson shift ``(a, b)``; each direction is paired with its
    mirror image across the view/normal plane (``phi -> -phi``). Both land on
    the same st point (the fold), so the kernel computes their angles once.
    The lattice is stratified in ``cos theta`` (P levels) and near-isotropic
    everywhere, also around the normal; uniform in solid angle, each of the
    ``K = 2 P`` directions has weight ``2 pi / K``.

    Args:
        normals, views: ``(m, 3)`` unit world vectors.
        n_dirs: K (rounded up to even, :func:`direction_pairs`).
        offsets: ``(m, 2)`` from :func:`hemisphere_offsets`.

    Returns:
        ``(m, K, 3)`` unit world directions towards the light (the lattice
        half first, then the mirrors in the same order) and ``(m, K)`` ``cos theta_u``.
    """
    u1, u2 = _half_lattice(direction_pairs(n_dirs))
    u1 = np.mod(u1 + offsets[:, :1].astype(np.float64), 1.0)
    u2 = np.mod(u2 + offsets[:, 1:].astype(np.float64), 1.0)
    r = np.sqrt(np.clip(1.0 - u1 * u1, 0.0, None))
    phi = math.pi * u2
    lx, ly, lz = r * np.cos(phi), r * np.sin(phi), u1
    lx, ly, lz = (np.concatenate([lx, lx], axis=1), np.concatenate([ly, -ly], axis=1),
                  np.concatenate([lz, lz], axis=1))
    x, y, _ = row_frames(normals, views)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    world = [x[:, c, None] * lx + y[:, c, None] * ly + n[:, c, None] * lz for c in range(3)]
    return np.stack(world, axis=-1), lz


def _as_probe_list(probes: Any) -> List[Any]:
    if isinstance(probes, (list, tuple)):
        return list(probes)
    return [probes]


def _check_inputs(obs: Observations, probes: List[Any], n_t: int, n_s: int, n_dirs: int) -> None:
    if n_t < 2 or n_s < 2:
        raise InputError(None, f"st grid {n_t}x{n_s} is too small", "each axis needs at least 2 nodes")
    if n_dirs < 2:
        raise InputError(None, f"n_dirs must be at least 2, got {n_dirs}")
    if len(obs) == 0:
        raise InputError(None, "no observations")
    if not probes:
        raise InputError(None, "no probe given")
    top = int(obs.probe_index.max())
    if top >= len(probes) or int(obs.probe_index.min()) < 0:
        raise InputError(None, f"observations refer to probe {top} but {len(probes)} probe(s) were given")
    if not (np.all(np.isfinite(obs.normals)) and np.all(np.isfinite(obs.views))):
        raise InputError(None, "observations have non-finite normals or views")
    if np.any(np.sum(obs.normals * obs.views, axis=1) <= 0.0):
        raise InputError(None, "some observed normals face away from their view (n . v <= 0)")


def _chunk_rows(n_nodes: int, chunk: Optional[int]) -> int:
    if chunk is not None:
        return max(1, int(chunk))
    # Each thread's copy of the scatter target (16 B per node and row) should
    # stay in a 2 MB L2 cache.
    return max(16, CHUNK_BYTES // (n_nodes * 16))


#: 4-wide float32 packets per row in the kernels' input (see :func:`_row_packets`).
_PACKETS = 5


def _row_packets(normals: np.ndarray, views: np.ndarray, offsets: np.ndarray,
                 positions: Optional[np.ndarray] = None,
                 geometric_normals: Optional[np.ndarray] = None) -> np.ndarray:
    """Per-row kernel inputs, 20 float32 per row (five 4-wide packets):
    ``[x, sin theta_v | y, cos theta_v | n, shift_1 | shift_2, p | n_g, shadow]``
    with ``p`` the surface position, ``n_g`` the geometric normal and
    ``shadow`` 1 where the row traces shadow rays (finite position), else 0."""
    x, y, wo = row_frames(normals, views)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    out = np.zeros((len(n), 4 * _PACKETS), dtype=np.float32)
    out[:, 0:3], out[:, 3] = x, wo[:, 0]
    out[:, 4:7], out[:, 7] = y, wo[:, 2]
    out[:, 8:11], out[:, 11] = n, offsets[:, 0]
    out[:, 12] = offsets[:, 1]
    out[:, 16:19] = n
    if positions is not None:
        known = np.all(np.isfinite(positions), axis=1)
        out[known, 13:16] = positions[known]
        out[known, 19] = 1.0
        if geometric_normals is not None:
            out[known, 16:19] = geometric_normals[known]
    return out


def _spatial_order(normals: np.ndarray, bits: int = 10) -> np.ndarray:
    """Row order along a Morton curve over the octahedral map of the normals."""
    n = normals / np.abs(normals).sum(axis=1, keepdims=True)
    oct_xy = np.where(n[:, 2:] >= 0.0, n[:, :2], (1.0 - np.abs(n[:, ::-1][:, 1:])) * np.sign(n[:, :2]))
    q = np.clip((oct_xy + 1.0) * 0.5 * (2**bits - 1), 0, 2**bits - 1).astype(np.uint64)
    key = np.zeros(len(n), dtype=np.uint64)
    for b in range(bits):
        key |= ((q[:, 0] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b)
        key |= ((q[:, 1] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b + 1)
    return np.argsort(key, kind="stable")


def _lattice_lanes(data: Any, m: int, n_points: int):
    """One lane per (lattice point, row) of a chunk of ``m`` rows: the row frame and the
    row's Cranley-Patterson-shifted Fibonacci lattice point ``(u1, u2)`` in [0, 1)^2.

    Lane order: lattice point, then row. The chunk's rows are neighbouring normals
    (:func:`_spatial_order`), so consecutive lanes read nearby envmap texels and splat
    into a small, cache-resident part of the target.

    Returns:
        ``(row, x_axis, y_axis, normal, sin_v, cos_v, u1, u2, p3)`` with ``p3`` the row's
        fourth packet (shift, surface position).
    """
    import drjit as dr
    import mitsuba as mi

    idx = dr.arange(mi.UInt32, m * n_points)
    k = idx // m
    row = idx - k * m
    p0, p1, p2, p3 = (dr.gather(mi.Vector4f, data, row * _PACKETS + q) for q in range(4))
    x_axis, y_axis = mi.Vector3f(p0.x, p0.y, p0.z), mi.Vector3f(p1.x, p1.y, p1.z)
    normal = mi.Vector3f(p2.x, p2.y, p2.z)
    u1 = mi.Float(k) * (1.0 / n_points) + (0.5 / n_points) + p2.w
    u1 = u1 - dr.floor(u1)
    u2 = mi.Float(k * _GOLDEN_U32) * 2.0**-32 + p3.x
    u2 = u2 - dr.floor(u2)
    return row, x_axis, y_axis, normal, p0.w, p1.w, u1, u2, p3


def _lighting_chunk(packets: np.ndarray, probe: Any, n_t: int, n_s: int, n_dirs: int,
                    occluder: Any = None) -> np.ndarray:
    """Rows of L for one chunk: one fused kernel, ``(m, n_t * n_s, 3) float32``.

    One lane per mirrored direction pair: two envmap lookups (and, with an
    ``occluder`` scene, two shadow rays), one set of Rusinkiewicz angles and
    one bilinear splat.
    """
    import drjit as dr
    import mitsuba as mi

    m = len(packets)
    n_pairs = direction_pairs(n_dirs)
    data = mi.Float(packets.reshape(-1))
    # Shifted Fibonacci lattice (see light_directions()).
    row, x_axis, y_axis, normal, sin_v, cos_v, u1, u2, p3 = _lattice_lanes(data, m, n_pairs)
    r = dr.safe_sqrt(1.0 - u1 * u1)
    sin_phi, cos_phi = dr.sincos(math.pi * u2)
    lx, ly, lz = r * cos_phi, r * sin_phi, u1

    base = x_axis * lx + normal * lz
    d_plus, d_minus = base + y_axis * ly, base - y_axis * ly
    if occluder is None:
        radiance = probe.eval_dr(d_plus) + probe.eval_dr(d_minus)
    else:
        p4 = dr.gather(mi.Vector4f, data, row * _PACKETS + 4)
        shadow = p4.w > 0.5
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p = mi.Point3f(p3.y, p3.z, p3.w)
        si.n = mi.Normal3f(p4.x, p4.y, p4.z)
        # spawn_ray offsets along the geometric normal on the side of the
        # direction, as a render's shadow rays do: a direction above the
        # shading horizon but below the face goes into the object.
        lit_plus = ~(shadow & occluder.ray_test(si.spawn_ray(d_plus), active=shadow))
        lit_minus = ~(shadow & occluder.ray_test(si.spawn_ray(d_minus), active=shadow))
        radiance = dr.select(lit_plus, probe.eval_dr(d_plus), 0.0) + \
            dr.select(lit_minus, probe.eval_dr(d_minus), 0.0)
    weight = lz * (_TWO_PI / (2 * n_pairs))
    return _splat(m, row, lx, ly, lz, sin_v, cos_v, radiance * weight, n_t, n_s)


#: Light-direction sampling of :func:`lighting_matrix`: the fraction of the K
#: directions drawn by each strategy of the ``"mis"`` mixture (see :func:`_mis_chunk`).
MIS_FRACTIONS = {"uniform": 0.25, "environment": 0.5, "peak": 0.25}
#: The ``"peak"`` strategy draws half vectors with t = sqrt(2 theta_h / pi) uniform in
#: ``[0, PEAK_T_MAX]`` (theta_h up to 22.5 degrees): as dense as the st grid's t nodes.
PEAK_T_MAX = 0.5
SAMPLINGS = ("mis", "uniform")


def strategy_counts(n_dirs: int, fractions: Optional[dict] = None) -> dict:
    """Directions per strategy of the ``"mis"`` sampling (they add up to ``n_dirs``)."""
    fractions = MIS_FRACTIONS if fractions is None else fractions
    names = [k for k in ("uniform", "environment", "peak") if fractions.get(k, 0.0) > 0.0]
    total = sum(fractions[k] for k in names)
    counts = {k: max(1, int(round(n_dirs * fractions[k] / total))) for k in names}
    counts[names[0]] += max(0, int(n_dirs) - sum(counts.values()))
    return counts


def _peak_pdf(lx: Any, ly: Any, lz: Any, sin_v: Any, cos_v: Any) -> Any:
    """Solid-angle density of the ``"peak"`` strategy at local light direction ``l``.

    Half vectors ``h`` have ``t = sqrt(2 theta_h / pi)`` uniform on ``[0, T]`` and
    ``phi_h`` uniform: ``p(h) = 1 / (T pi t 2 pi sin theta_h)``; the light is ``h``'s
    mirror of the view, ``p(l) = p(h) / (4 (v . h))``.
    """
    import drjit as dr

    hx, hy, hz = lx + sin_v, ly, lz + cos_v
    norm = dr.sqrt(hx * hx + hy * hy + hz * hz)
    sin_h = dr.sqrt(hx * hx + hy * hy) / norm
    theta_h = dr.atan2(sin_h, hz / norm)
    t = dr.sqrt(theta_h * (2.0 / math.pi))
    v_dot_h = (sin_v * hx + cos_v * hz) / norm
    pdf = 1.0 / (PEAK_T_MAX * math.pi * t * _TWO_PI * sin_h * 4.0 * v_dot_h)
    return dr.select((t < PEAK_T_MAX) & (sin_h > 0.0) & (v_dot_h > 0.0), pdf, 0.0)


def _mis_lanes(data: Any, m: int, probe: Any, strategy: str, counts: dict, seed_shift: Any = None):
    """The lanes of one sampling strategy for ``m`` rows: ``(row, lx, ly, lz, d, weight)``.

    ``d`` is the world light direction, ``(lx, ly, lz)`` its row-frame coordinates and
    ``weight = cos theta_u / sum_j K_j p_j(u)`` the balance-heuristic weight of the
    mixture (Veach's multi-sample estimator), 0 below the horizon. Each strategy
    draws a shifted Fibonacci lattice (per-row Cranley-Patterson shift), so every
    strategy is stratified.
    """
    import drjit as dr
    import mitsuba as mi

    row, x_axis, y_axis, normal, sin_v, cos_v, u1, u2, _ = _lattice_lanes(data, m, counts[strategy])
    emitter = probe.emitter()
    it = dr.zeros(mi.Interaction3f)
    if strategy == "uniform":
        r = dr.safe_sqrt(1.0 - u1 * u1)
        sin_phi, cos_phi = dr.sincos(_TWO_PI * u2)
        lx, ly, lz = r * cos_phi, r * sin_phi, u1
        d = x_axis * lx + y_axis * ly + normal * lz
    elif strategy == "environment":
        ds, _ = emitter.sample_direction(it, mi.Point2f(u1, u2))
        d = ds.d
        lx, ly, lz = dr.dot(d, x_axis), dr.dot(d, y_axis), dr.dot(d, normal)
    elif strategy == "peak":
        theta_h = (0.5 * math.pi) * dr.square(PEAK_T_MAX * u1)
        sin_h, cos_h = dr.sincos(theta_h)
        sin_p, cos_p = dr.sincos(_TWO_PI * u2)
        hx, hy, hz = sin_h * cos_p, sin_h * sin_p, cos_h
        v_dot_h = sin_v * hx + cos_v * hz
        lx, ly, lz = 2.0 * v_dot_h * hx - sin_v, 2.0 * v_dot_h * hy, 2.0 * v_dot_h * hz - cos_v
        d = x_axis * lx + y_axis * ly + normal * lz
    else:
        raise ValueError(strategy)
    density = mi.Float(0.0)
    if counts.get("uniform"):
        density += counts["uniform"] * (1.0 / _TWO_PI)
    if counts.get("environment"):
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = d
        density += counts["environment"] * emitter.pdf_direction(it, ds)
    if counts.get("peak"):
        density += counts["peak"] * _peak_pdf(lx, ly, lz, sin_v, cos_v)
    above = (lz > 0.0) & (density > 0.0)
    weight = dr.select(above, lz / density, 0.0)
    return row, lx, ly, lz, d, weight, sin_v, cos_v, above


def _mis_chunk(packets: np.ndarray, probe: Any, n_t: int, n_s: int, n_dirs: int,
               occluder: Any = None, fractions: Optional[dict] = None) -> np.ndarray:
    """Rows of L for one chunk by multiple importance sampling, ``(m, n_t * n_s, 3) float32``.

    Three stratified strategies share the K directions (:data:`MIS_FRACTIONS`):
    uniform over the hemisphere (the paper's), the environment's own
    importance sampling (Mitsuba's ``envmap.sample_direction``, luminance
    times sin theta: the small bright sources of a real probe), and half
    vectors around the normal as dense as the grid's t nodes (the specular
    peak, where a sharp table varies fastest). Every direction is weighted by
    the balance heuristic over all three densities, so the estimator stays
    unbiased for any table and its variance is that of the best strategy for
    each part of the integrand.
    """
    import drjit as dr
    import mitsuba as mi

    m = len(packets)
    counts = strategy_counts(n_dirs, fractions)
    data = mi.Float(packets.reshape(-1))
    target = dr.zeros(mi.Float, m * n_t * n_s * 4)
    for strategy in counts:
        row, lx, ly, lz, d, weight, sin_v, cos_v, above = _mis_lanes(data, m, probe, strategy, counts)
        radiance = probe.eval_dr(d)
        if occluder is not None:
            p3 = dr.gather(mi.Vector4f, data, row * _PACKETS + 3)
            p4 = dr.gather(mi.Vector4f, data, row * _PACKETS + 4)
            shadow = p4.w > 0.5
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.p = mi.Point3f(p3.y, p3.z, p3.w)
            si.n = mi.Normal3f(p4.x, p4.y, p4.z)
            lit = ~(shadow & occluder.ray_test(si.spawn_ray(d), active=shadow & above))
            radiance = dr.select(lit, radiance, 0.0)
        _splat(m, row, lx, ly, lz, sin_v, cos_v, radiance * weight, n_t, n_s, active=above, target=target)
    out = target.numpy().reshape(m, n_t * n_s, 4)
    return np.ascontiguousarray(out[:, :, :3])


def _splat(m: int, row: Any, lx: Any, ly: Any, lz: Any, sin_v: Any, cos_v: Any, value: Any,
           n_t: int, n_s: int, active: Any = True, target: Any = None) -> Optional[np.ndarray]:
    """Bilinear splat of ``value`` (``mi.Color3f``) at the st point of each lane.

    ``(lx, ly, lz)`` is the light direction in the row frame, whose view is
    ``wo = (sin_v, 0, cos_v)``. Returns ``(m, n_t * n_s, 3) float32``, or
    accumulates into ``target`` (``m * n_t * n_s * 4`` floats) and returns ``None``.
    """
    import drjit as dr
    import mitsuba as mi

    # Rusinkiewicz angles; theta_d is half the angle between wi and wo. atan2
    # of a sine and a cosine keeps float32 precision at the specular peak,
    # where acos would smear theta_h over half a t-cell (see coordinates.py).
    hx, hz = lx + sin_v, lz + cos_v
    theta_h = dr.atan2(dr.sqrt(hx * hx + ly * ly), hz)
    dot = lx * sin_v + lz * cos_v
    cx, cy, cz = ly * cos_v, lz * sin_v - lx * cos_v, ly * sin_v
    theta_d = 0.5 * dr.atan2(dr.sqrt(cx * cx + cy * cy + cz * cz), dot)
    s = theta_d * (2.0 / math.pi)
    t = dr.sqrt(theta_h * (2.0 / math.pi))

    fs = dr.clip(s, 0.0, 1.0) * (n_s - 1)
    ft = dr.clip(t, 0.0, 1.0) * (n_t - 1)
    i_s = dr.minimum(mi.UInt32(fs), n_s - 2)
    i_t = dr.minimum(mi.UInt32(ft), n_t - 2)
    ws = fs - mi.Float(i_s)
    wt = ft - mi.Float(i_t)

    n_nodes = n_t * n_s
    rgb = mi.Vector4f(value[0], value[1], value[2], 0.0)
    given = target is not None
    if not given:
        target = dr.zeros(mi.Float, m * n_nodes * 4)
    node = row * n_nodes + i_t * n_s + i_s
    # 4-wide packets with ReduceMode.Expand: per-thread copies of the target,
    # no atomics (Auto silently picks Local for big targets: 7x slower).
    for offset, w in ((0, (1.0 - wt) * (1.0 - ws)), (1, (1.0 - wt) * ws),
                      (n_s, wt * (1.0 - ws)), (n_s + 1, wt * ws)):
        dr.scatter_reduce(dr.ReduceOp.Add, target, rgb * w, node + offset, active=active,
                          mode=dr.ReduceMode.Expand)
    if given:
        return None
    out = target.numpy().reshape(m, n_nodes, 4)
    return np.ascontiguousarray(out[:, :, :3])


def _texel_chunk(packets: np.ndarray, texels: Tuple[Any, Any, int], n_t: int, n_s: int) -> np.ndarray:
    """Rows of the texel-quadrature L for one chunk, ``(m, n_t * n_s, 3) float32``."""
    import drjit as dr
    import mitsuba as mi

    directions, radiance_weight, n_texels = texels
    m = len(packets)
    data = mi.Float(packets.reshape(-1))
    idx = dr.arange(mi.UInt32, m * n_texels)
    texel = idx // m
    row = idx - texel * m
    p0, p1, p2 = (dr.gather(mi.Vector4f, data, row * _PACKETS + q) for q in range(3))
    d = dr.gather(mi.Vector3f, directions, texel)
    lx = p0.x * d.x + p0.y * d.y + p0.z * d.z
    ly = p1.x * d.x + p1.y * d.y + p1.z * d.z
    lz = p2.x * d.x + p2.y * d.y + p2.z * d.z
    value = dr.gather(mi.Color3f, radiance_weight, texel) * lz
    return _splat(m, row, lx, ly, lz, p0.w, p1.w, value, n_t, n_s, active=lz > 0.0)


def _occluder_scene(occluder: Any) -> Any:
    """A ``mi.Scene`` from a scene or an object with a ``scene()`` method (e.g. a mesh shape)."""
    import mitsuba as mi

    if occluder is None or isinstance(occluder, mi.Scene):
        return occluder
    if callable(getattr(occluder, "scene", None)):
        return occluder.scene()
    raise InputError(None, f"occluder must be a Mitsuba scene or have a scene() method, got {type(occluder).__name__}")


def _occluder_per_row(obs: Observations, occluder: Any) -> Tuple[List[Any], np.ndarray]:
    """Distinct occluder scenes and, per row, the index of its scene (-1: no shadow rays).

    ``occluder`` is one scene (or ``scene()`` owner) for every row, or a
    sequence indexed by :attr:`Observations.image_index` (``None`` entries:
    no visibility for that image's rows).
    """
    m = len(obs)
    if occluder is None:
        return [], np.full(m, -1, dtype=np.int64)
    per_image = list(occluder) if isinstance(occluder, (list, tuple)) else None
    if per_image is None:
        return [_occluder_scene(occluder)], np.zeros(m, dtype=np.int64)
    top = int(obs.image_index.max())
    if top >= len(per_image):
        raise InputError(None, f"observations come from image {top} but {len(per_image)} occluder(s) were given")
    scenes: List[Any] = []
    index_of_image = []
    for item in per_image:
        scene = _occluder_scene(item)
        if scene is None:
            index_of_image.append(-1)
            continue
        known = [i for i, s in enumerate(scenes) if s is scene]
        if not known:
            scenes.append(scene)
        index_of_image.append(known[0] if known else len(scenes) - 1)
    return scenes, np.asarray(index_of_image, dtype=np.int64)[obs.image_index]


def lighting_matrix(obs: Observations, probes: Union[Any, Sequence[Any]], n_t: int = 32, n_s: int = 32,
                    n_dirs: int = 32000, seed: int = 0, chunk: Optional[int] = None,
                    progress: Optional[bool] = None, occluder: Any = None,
                    sampling: str = "mis") -> np.ndarray:
    """The lighting matrix of Eqs. 4-5.

    Args:
        obs: observations (normals, views, which probe lit each row).
        probes: a :class:`~mi_bivariate.probes.Probe` or a list indexed by
            ``obs.probe_index``.
        n_t, n_s: st grid size.
        n_dirs: light directions K per normal.
        seed: seeds the per-row shifts of the direction lattice.
        chunk: normals per kernel (default: sized to :data:`CHUNK_BYTES`).
        progress: show a tqdm bar over chunks (default: for big jobs on a tty).
        occluder: the observed object for visibility: a ``mi.Scene`` (or an
            object with ``scene()``, such as :class:`mi_bivariate.mesh.MeshShape`),
            or a sequence of them (or ``None``) indexed by ``obs.image_index``.
            Rows with a finite :attr:`Observations.positions` then get a shadow
            ray per light direction; blocked directions contribute nothing.
            ``None`` (default): every direction of the hemisphere is lit
            (the paper's model; exact for convex objects).
        sampling: how the K directions are drawn. ``"mis"`` (default):
            a balance-heuristic mixture of uniform, environment and
            specular-peak sampling (:func:`_mis_chunk`); ``"uniform"``: the
            paper's uniform hemisphere lattice in mirrored pairs
            (:func:`light_directions`). Under a real probe with small bright
            sources (grace_latlong_1k) and a glossy table, ``"uniform"`` at
            K = 32768 predicts pixels with 10-15% per-pixel quadrature noise,
            which the solve then fits; see ``docs/recovery.md``.

    Returns:
        ``(M, n_t * n_s, 3) float32``; column ``it * n_s + is``.
    """
    from mi_bivariate.variants import ensure_variant

    ensure_variant(vectorised=True)
    probes = _as_probe_list(probes)
    _check_inputs(obs, probes, n_t, n_s, n_dirs)
    if sampling not in SAMPLINGS:
        raise InputError(None, f"unknown sampling {sampling!r}", f"use one of {', '.join(SAMPLINGS)}")
    chunk_fn = _mis_chunk if sampling == "mis" else _lighting_chunk
    m_total, n_nodes = len(obs), n_t * n_s
    scenes, scene_of_row = _occluder_per_row(obs, occluder)
    if scenes and not obs.has_positions:
        raise InputError(None, "an occluder was given but the observations have no surface positions",
                         "build them from a mesh (mi_bivariate.mesh) or pass positions to "
                         "observations_from_normal_map")
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(m_total, seed),
                           obs.positions, obs.geometric_normals)
    rows_per_chunk = _chunk_rows(n_nodes, chunk)

    jobs = []
    order = _spatial_order(obs.normals)
    for p in np.unique(obs.probe_index):
        for o in np.unique(scene_of_row):
            rows = order[(obs.probe_index[order] == p) & (scene_of_row[order] == o)]
            jobs += [(int(p), int(o), rows[i:i + rows_per_chunk]) for i in range(0, len(rows), rows_per_chunk)]
    if progress is None:
        progress = len(jobs) > 1 and m_total * n_dirs > PROGRESS_PAIRS and sys.stderr.isatty()
    if progress:
        from tqdm import tqdm

        jobs = tqdm(jobs, desc="lighting matrix", unit="chunk")

    L = np.empty((m_total, n_nodes, 3), dtype=np.float32)
    for p, o, rows in jobs:
        L[rows] = chunk_fn(packets[rows], probes[p], n_t, n_s, n_dirs, scenes[o] if o >= 0 else None)
    return L


def texel_lighting_matrix(obs: Observations, probes: Union[Any, Sequence[Any]], n_t: int = 32,
                          n_s: int = 32, downsample: int = 8, chunk: Optional[int] = None) -> np.ndarray:
    """The lighting matrix by environment-texel quadrature.

    Every texel of the probe, area-downsampled by ``downsample``
    (:meth:`Probe.downsampled`; the largest factor up to ``downsample`` that
    divides the width), is one light direction (its Mitsuba texel
    position) with its solid angle and stored radiance; a row sums the
    texels in its normal's upper hemisphere. Deterministic and faster than
    :func:`lighting_matrix` for coarse maps, but it smooths the environment
    and samples the hemisphere unevenly, so sharp lobes suffer. Measured
    (``benchmarks/bench_recovery.py``, grace_latlong_1k, per-pixel relative
    RMS of ``L @ f`` against sampled K = 128000): a 128 x 64 texel map gives
    9e-4 on a diffuse table and 2.5e-2 on a 0.05 rad lobe (sampled K = 32000:
    4e-3 and 2e-2) at 0.3x the time; 64 x 32 texels: 1.8e-3 and 1.4e-1.

    Returns:
        ``(M, n_t * n_s, 3) float32``, laid out as :func:`lighting_matrix`.
    """
    import mitsuba as mi

    from mi_bivariate.variants import ensure_variant

    ensure_variant(vectorised=True)
    probes = _as_probe_list(probes)
    _check_inputs(obs, probes, n_t, n_s, 2)
    if downsample < 1:
        raise InputError(None, f"downsample must be >= 1, got {downsample}")
    m_total, n_nodes = len(obs), n_t * n_s
    packets = _row_packets(obs.normals, obs.views, np.zeros((m_total, 2), dtype=np.float32))
    rows_per_chunk = _chunk_rows(n_nodes, chunk)
    order = _spatial_order(obs.normals)
    L = np.empty((m_total, n_nodes, 3), dtype=np.float32)
    for p in np.unique(obs.probe_index):
        probe = probes[int(p)]
        factor = max(f for f in range(1, downsample + 1) if probe.width % f == 0)
        coarse = probe.downsampled(factor)
        directions, solid_angle = coarse.texel_directions()
        radiance = coarse.data.reshape(-1, 3).astype(np.float64) * solid_angle[:, None]
        texels = (mi.Vector3f(*directions.astype(np.float32).T),
                  mi.Color3f(*radiance.astype(np.float32).T), len(solid_angle))
        rows = order[obs.probe_index[order] == p]
        for i in range(0, len(rows), rows_per_chunk):
            sel = rows[i:i + rows_per_chunk]
            L[sel] = _texel_chunk(packets[sel], texels, n_t, n_s)
    return L
