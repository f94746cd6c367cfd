"""The Dr.Jit kernels of the lighting matrix: one fused kernel per chunk of rows.

Per (row, lattice point) the light direction(s), the envmap lookup(s), the Rusinkiewicz
angles and a bilinear splat of RGB, padded to a 4-wide packet, into ``[rows, n_t * n_s, 4]``.
:func:`lattice_points` runs a per-point body over a chunk's rows in one of two layouts:

- **LLVM (CPU): one lane per row**, a loop over the row's lattice points. Each element of
  the target is written by one lane, in lattice order, so the sums do not depend on how
  Dr.Jit's threads share the work: the matrix is the same bit for bit from run to run and
  for any thread count, and the splat needs no atomics and no per-thread copies
  (``ReduceMode.NoConflicts``).
- **CUDA: one lane per (row, lattice point)**, as a GPU needs many threads; the splat uses
  ``ReduceMode.Expand`` (atomics there), so sums agree between runs to float32 rounding.

The ``*_target`` functions return that target with its kernel launched and not awaited (on the
LLVM backend Dr.Jit runs it on its thread pool while Python goes on); :func:`_rgb_rows` is its
``(m, n_t * n_s, 3)`` RGB view (not copied), which :func:`mi_bivariate.lighting.lighting_matrix`
copies into L while the next chunk's kernel runs.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple, Optional, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.lighting.directions import _GOLDEN_U32, _TWO_PI, direction_pairs, row_frames

#: 4-wide float32 packets per row in the kernels' input (see :func:`_row_packets`).
_PACKETS = 5


def _row_packets(normals: np.ndarray, views: np.ndarray, offsets: np.ndarray,
                 positions: Optional[np.ndarray] = None,
                 geometric_normals: Optional[np.ndarray] = None) -> np.ndarray:
    """Per-row kernel inputs, 20 float32 per row (five 4-wide packets):
    ``[x, sin theta_v | y, cos theta_v | n, shift_1 | shift_2, p | n_g, shadow]``
    with ``p`` the surface position, ``n_g`` the unit geometric normal (``geometric_normals`` normalised,
    as the shading ``normals`` are: spawn_ray's offset scales with its length) and ``shadow`` 1 where the
    row traces shadow rays (finite position), else 0."""
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
            g = geometric_normals[known]
            out[known, 16:19] = g / np.linalg.norm(g, axis=1, keepdims=True)
    return out


def _row_data(packets: np.ndarray) -> Any:
    """The kernels' per-row input (``mi.Float``, :func:`_row_packets` flattened) in 64-byte aligned memory.

    Dr.Jit reads a 4-wide packet (``dr.gather(mi.Vector4f, ...)``) with one vector load per lane
    only from aligned memory; from a numpy buffer that is not (numpy aligns to 16 bytes) it falls
    back to one gather per component, 4x the gathers (``docs/recovery.md``, Speed, Round 11: ~7% of
    the MIS matrix's time). On the LLVM backend ``mi.Float`` maps the numpy memory without a copy
    and holds a reference to the array (and so to its buffer) while it lives; CUDA copies it.
    """
    flat = np.ravel(packets).astype(np.float32, copy=False)
    buffer = np.empty(flat.size + 16, dtype=np.float32)
    start = (-buffer.ctypes.data % 64) // 4
    aligned = buffer[start:start + flat.size]
    aligned[:] = flat
    return mi.Float(aligned)


#: Bits per axis of the rows' Morton curve (:func:`_spatial_order`).
ROW_MORTON_BITS = 10


def _spread_bits(q: Any) -> Any:
    """The low 16 bits of ``q`` (``mi.UInt32``) moved to the even bit positions."""
    q = (q | (q << 8)) & 0x00FF00FF
    q = (q | (q << 4)) & 0x0F0F0F0F
    q = (q | (q << 2)) & 0x33333333
    return (q | (q << 1)) & 0x55555555


def morton_key(d: Any, bits: int) -> Any:
    """Position of each direction ``d`` (``mi.Vector3f``, any length) along a Morton curve over the
    octahedral map of the sphere, ``bits`` (at most 16) per axis: ``mi.UInt32`` below
    ``2 ** (2 * bits)``. Directions with near keys are near on the sphere (up to the curve's jumps);
    a zero or non-finite vector gets the key of the map's centre."""
    length = dr.abs(d.x) + dr.abs(d.y) + dr.abs(d.z)
    usable = dr.isfinite(length) & (length > 0.0)
    x, y, z = (dr.select(usable, c / length, 0.0) for c in (d.x, d.y, d.z))
    lower = z < 0.0  # the lower hemisphere folded over the octahedron's faces
    ox = dr.select(lower, (1.0 - dr.abs(y)) * dr.sign(x), x)
    oy = dr.select(lower, (1.0 - dr.abs(x)) * dr.sign(y), y)
    scale = float(2**bits - 1)
    qx = mi.UInt32(dr.clip((ox + 1.0) * (0.5 * scale), 0.0, scale))
    qy = mi.UInt32(dr.clip((oy + 1.0) * (0.5 * scale), 0.0, scale))
    return _spread_bits(qx) | (_spread_bits(qy) << 1)


def _spatial_order(normals: np.ndarray) -> np.ndarray:
    """Row order along a Morton curve over the octahedral map of the normals (:func:`morton_key`)."""
    n = np.asarray(normals, dtype=np.float32)
    return np.argsort(morton_key(mi.Vector3f(np.ascontiguousarray(n.T)), ROW_MORTON_BITS).numpy(), kind="stable")


def fibonacci_point(k: Any, n_points: int, shift_u: Any, shift_v: Any) -> Tuple[Any, Any]:
    """Point ``k`` (``mi.UInt32``) of the ``n_points`` Fibonacci lattice in [0, 1)^2, Cranley-Patterson
    shifted by ``(shift_u, shift_v)``: ``(u1, u2)`` (``mi.Float``; the numpy reference is
    :func:`mi_bivariate.lighting.directions.light_directions`)."""
    u1 = mi.Float(k) * (1.0 / n_points) + (0.5 / n_points) + shift_u
    u2 = mi.Float(k * _GOLDEN_U32) * 2.0**-32 + shift_v
    return u1 - dr.floor(u1), u2 - dr.floor(u2)


class RowInputs(NamedTuple):
    """A row's kernel inputs (:func:`_row_packets`), per lane: its frame (``x_axis``, ``y_axis``,
    ``normal``: ``mi.Vector3f``), the view ``(sin_v, 0, cos_v)`` in that frame and its two
    Cranley-Patterson shifts."""

    x_axis: Any
    y_axis: Any
    normal: Any
    sin_v: Any
    cos_v: Any
    shift_1: Any
    shift_2: Any


def row_inputs(data: Any, row: Any) -> RowInputs:
    """The :class:`RowInputs` of rows ``row`` (``mi.UInt32``) from the kernels' input ``data`` (:func:`_row_data`)."""
    p0, p1, p2, p3 = (dr.gather(mi.Vector4f, data, row * _PACKETS + q) for q in range(4))
    return RowInputs(mi.Vector3f(p0.x, p0.y, p0.z), mi.Vector3f(p1.x, p1.y, p1.z), mi.Vector3f(p2.x, p2.y, p2.z),
                     p0.w, p1.w, p2.w, p3.x)


def lane_per_row() -> bool:
    """Whether the kernels run one lane per row with a loop over its lattice points (the LLVM
    backend: bit-reproducible sums), rather than one lane per (row, point) (CUDA)."""
    return not (mi.variant() or "").startswith("cuda")


def splat_mode() -> Any:
    """The ``dr.ReduceMode`` of :func:`_splat` in the layout of :func:`lane_per_row`: ``NoConflicts``
    with a lane per row (no two lanes write one row), else ``Expand``."""
    return dr.ReduceMode.NoConflicts if lane_per_row() else dr.ReduceMode.Expand


def lattice_points(data: Any, m: int, n_points: int,
                   body: Callable[[Any, Any, RowInputs, Any, Any], None]) -> None:
    """Call ``body(row, k, inputs, u1, u2)`` for every row of a chunk of ``m`` rows and every point
    ``k`` of its ``n_points`` lattice, ``(u1, u2)`` the row's Cranley-Patterson-shifted Fibonacci
    point (:func:`fibonacci_point`) and ``inputs`` the row's :class:`RowInputs`.

    With :func:`lane_per_row`, one lane per row gathers its inputs once and loops over ``k``
    (``dr.while_loop``, traced once: ``body`` runs in a symbolic loop and may scatter, as with
    :func:`splat_mode`, but not read what it scatters, nor create arrays that outlive the loop:
    build a probe's emitter before). Dr.Jit then splits a kernel into at most one block per SIMD
    packet of rows (16 rows with AVX-512): a chunk of 2048 rows keeps up to 128 threads busy, a
    matrix of 100 rows only 7. Otherwise (CUDA) one lane per (row, point), row then point: a row's
    lanes are contiguous (``docs/recovery.md``, Speed, Round 16).
    """
    if lane_per_row():
        row = dr.arange(mi.UInt32, m)
        inputs = row_inputs(data, row)

        def step(k: Any) -> Tuple[Any]:
            u1, u2 = fibonacci_point(k, n_points, inputs.shift_1, inputs.shift_2)
            body(row, k, inputs, u1, u2)
            return (k + 1,)

        # Symbolic whatever dr.JitFlag.SymbolicLoops says: an evaluated loop would launch a kernel per point.
        dr.while_loop(state=(dr.zeros(mi.UInt32, m),), cond=lambda k: k < n_points, body=step, mode="symbolic",
                      label="lattice_points")
        return
    body(*_lattice_lanes(data, m, n_points))


def _lattice_lanes(data: Any, m: int, n_points: int) -> Tuple[Any, Any, RowInputs, Any, Any]:
    """One lane per (row, lattice point) of a chunk of ``m`` rows, row then point:
    ``(row, k, inputs, u1, u2)`` as :func:`lattice_points` passes them to its body (its CUDA
    layout; also for the benchmarks that take lanes apart)."""
    idx = dr.arange(mi.UInt32, m * n_points)
    row = idx // n_points
    k = idx - row * n_points
    inputs = row_inputs(data, row)
    u1, u2 = fibonacci_point(k, n_points, inputs.shift_1, inputs.shift_2)
    return row, k, inputs, u1, u2


def _occluded(data: Any, row: Any, d: Any, active: Any, occluder: Any) -> Any:
    """Whether the shadow ray of each lane's direction ``d`` hits the ``occluder`` scene (``mi.Bool``;
    rows without a surface position trace none): from the row's surface position, offset along its
    geometric normal as Mitsuba's ``spawn_ray`` does for a render's shadow rays."""
    p3 = dr.gather(mi.Vector4f, data, row * _PACKETS + 3)
    p4 = dr.gather(mi.Vector4f, data, row * _PACKETS + 4)
    shadow = p4.w > 0.5
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.p = mi.Point3f(p3.y, p3.z, p3.w)
    si.n = mi.Normal3f(p4.x, p4.y, p4.z)
    return shadow & occluder.ray_test(si.spawn_ray(d), active=shadow & active)


def _nothing() -> None:
    return None


def above_horizon(lz: Any, work: Callable[[], None]) -> None:
    """``work()``, a lane's work that adds nothing where its light direction is below the horizon
    (``lz <= 0``, the direction's cosine to the normal), run only where ``lz > 0``. ``work`` reads
    the lane's variables from its enclosing scope and writes only by scattering.

    A symbolic ``dr.if_stmt``: a SIMD packet of rows (LLVM, :func:`lattice_points`) or a GPU warp
    whose lanes are all below the horizon jumps over it. What it computes is unchanged (such lanes
    add 0); it saves time where neighbouring lanes look at near directions at once. Symbolic
    whatever ``dr.JitFlag.SymbolicConditionals`` says (as :func:`lattice_points`' loop): evaluated,
    it would split the kernel.
    """
    dr.if_stmt(args=(), cond=lz > 0.0, true_fn=work, false_fn=_nothing, mode="symbolic", label="above_horizon")


def _launched(target: Any) -> Any:
    """``target`` with its kernel launched (``dr.eval``; on the LLVM backend it runs
    asynchronously until something reads the data)."""
    dr.eval(target)
    return target


def _rgb_rows(target: Any, m: int, n_nodes: int) -> np.ndarray:
    """The ``(m, n_nodes, 3) float32`` RGB view of a chunk's 4-wide target (waits for its kernel;
    a view of Dr.Jit's memory on the LLVM backend, not a copy)."""
    return target.numpy().reshape(m, n_nodes, 4)[:, :, :3]


def _lighting_target(packets: np.ndarray, probe: Any, n_t: int, n_s: int, n_dirs: int,
                     occluder: Any = None) -> Any:
    """Rows of L for one chunk by the uniform lattice: one fused kernel, launched
    (:func:`_launched`; :func:`_rgb_rows` reads it).

    One lattice point per mirrored direction pair: two envmap lookups (and, with an
    ``occluder`` scene, two shadow rays), one set of Rusinkiewicz angles and
    one bilinear splat.
    """
    m = len(packets)
    n_pairs = direction_pairs(n_dirs)
    data = _row_data(packets)
    target = dr.zeros(mi.Float, m * n_t * n_s * 4)
    mode = splat_mode()
    probe.emitter()  # built before the loop: a symbolic loop may not create the map's arrays

    def body(row: Any, k: Any, r: RowInputs, u1: Any, u2: Any) -> None:
        # Shifted Fibonacci lattice (see light_directions()).
        radius = dr.safe_sqrt(1.0 - u1 * u1)
        sin_phi, cos_phi = dr.sincos(math.pi * u2)
        lx, ly, lz = radius * cos_phi, radius * sin_phi, u1
        base = r.x_axis * lx + r.normal * lz
        d_plus, d_minus = base + r.y_axis * ly, base - r.y_axis * ly
        if occluder is None:
            radiance = probe.eval_dr(d_plus) + probe.eval_dr(d_minus)
        else:
            # spawn_ray offsets along the geometric normal on the side of the
            # direction, as a render's shadow rays do: a direction above the
            # shading horizon but below the face goes into the object.
            lit_plus = ~_occluded(data, row, d_plus, True, occluder)
            lit_minus = ~_occluded(data, row, d_minus, True, occluder)
            radiance = probe.eval_dr(d_plus, lit_plus) + probe.eval_dr(d_minus, lit_minus)  # 0 where blocked
        weight = lz * (_TWO_PI / (2 * n_pairs))
        _splat(m, row, lx, ly, lz, r.sin_v, r.cos_v, radiance * weight, n_t, n_s, target=target, mode=mode)

    lattice_points(data, m, n_pairs, body)
    return _launched(target)


def _splat(m: int, row: Any, lx: Any, ly: Any, lz: Any, sin_v: Any, cos_v: Any, value: Any,
           n_t: int, n_s: int, active: Any = True, target: Any = None,
           mode: Any = dr.ReduceMode.Expand) -> Optional[np.ndarray]:
    """Bilinear splat of ``value`` (``mi.Color3f``) at the st point of each lane.

    ``(lx, ly, lz)`` is the light direction in the row frame, whose view is
    ``wo = (sin_v, 0, cos_v)``. Returns ``(m, n_t * n_s, 3) float32``, or
    accumulates into ``target`` (``m * n_t * n_s * 4`` floats) and returns ``None``.
    ``mode``: the scatter's ``dr.ReduceMode`` (:func:`splat_mode` in :func:`lattice_points`).
    """
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
    # 4-wide packets. NoConflicts (CPU): a lane per row, no two lanes write one element, a plain
    # read-add-write. Expand (CUDA, a lane per (row, direction)): Dr.Jit's atomics there; on
    # the CPU it would be per-thread copies, and Auto silently picks Local for big targets, 7x slower.
    for offset, w in ((0, (1.0 - wt) * (1.0 - ws)), (1, (1.0 - wt) * ws),
                      (n_s, wt * (1.0 - ws)), (n_s + 1, wt * ws)):
        dr.scatter_reduce(dr.ReduceOp.Add, target, rgb * w, node + offset, active=active, mode=mode)
    if given:
        return None
    return _rgb_rows(target, m, n_nodes)  # a view: the caller copies it into L once


def _texel_target(packets: np.ndarray, texels: Tuple[Any, Any, int], n_t: int, n_s: int) -> Any:
    """Rows of the texel-quadrature L for one chunk, launched (:func:`_launched`; :func:`_rgb_rows`
    reads it). The texels take the place of the lattice points (:func:`lattice_points`; the rows'
    shifts are unused)."""
    directions, radiance_weight, n_texels = texels
    m = len(packets)
    data = _row_data(packets)
    target = dr.zeros(mi.Float, m * n_t * n_s * 4)
    mode = splat_mode()

    def lit(row: Any, texel: Any, r: RowInputs, d: Any, lz: Any) -> None:
        lx = r.x_axis.x * d.x + r.x_axis.y * d.y + r.x_axis.z * d.z
        ly = r.y_axis.x * d.x + r.y_axis.y * d.y + r.y_axis.z * d.z
        value = dr.gather(mi.Color3f, radiance_weight, texel) * lz
        _splat(m, row, lx, ly, lz, r.sin_v, r.cos_v, value, n_t, n_s, active=lz > 0.0, target=target, mode=mode)

    def body(row: Any, texel: Any, r: RowInputs, u1: Any, u2: Any) -> None:
        d = dr.gather(mi.Vector3f, directions, texel)
        lz = r.normal.x * d.x + r.normal.y * d.y + r.normal.z * d.z
        # every row reads texel k at step k: a packet skips together
        above_horizon(lz, lambda: lit(row, texel, r, d, lz))

    lattice_points(data, m, n_texels, body)
    return _launched(target)
