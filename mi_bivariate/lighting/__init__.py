"""The lighting matrix L of Eq. 5: pixel values are ``I = L f``.

A pixel that sees normal ``n`` from view ``v`` integrates the environment
over the normal's upper hemisphere (Eq. 3)::

    I(v, n) = int_Omega E(u) f(s(u, v), t(u, v)) cos(theta_u) du
            ~ sum_k w_k E(u_k) cos(theta_k) sum_{(i,j) in N_k} alpha^k_ij f_ij   (Eq. 4)

with ``K`` light directions ``u_k`` and their quadrature weights ``w_k``, ``E`` the
environment radiance looked up exactly as Mitsuba's ``envmap`` emitter does
(:meth:`Probe.eval_dr`), and ``alpha^k_ij`` the bilinear weights of the four st nodes
around ``(s, t)(u_k, v)``. Row ``m`` of ``L`` holds these weights for normal ``m``;
column ``it * n_s + is`` is st node ``(t_it, s_is)`` (the C order of a ``(n_t, n_s, 3)``
table); the last axis is the colour channel.

Light directions (``sampling``):

- ``"mis"`` (default, :mod:`.mis`): multiple importance sampling. The K directions of a
  row are split between three stratified strategies (uniform over the hemisphere, the
  environment's own importance sampling, half vectors around the specular peak) and
  weighted by the balance heuristic over all three densities. The environment's
  directions are sampled once per lighting matrix and shared by the rows
  (:func:`environment_pool`). At K = 8000 it predicts pixels more accurately than the
  paper's uniform lattice at K = 32000 (0.13-0.29% against 0.32-22.7% RMS, six
  materials under grace_latlong_1k; ``docs/recovery.md``, Round 9).
- ``"uniform"`` (the paper's, :func:`light_directions`): a spherical Fibonacci lattice,
  uniform in solid angle (``w_k = 2 pi / K``), on the half of the normal's hemisphere on
  one side of the view/normal plane, shifted per row by a seeded random offset (a
  Cranley-Patterson rotation, which decorrelates the quadrature error between rows),
  plus the mirror image of every direction across that plane. A direction and its
  mirror image have the same (s, t), the fold of Fig. 4: one lane computes their angles
  once and looks up the environment twice.

Layout: :mod:`.directions` (the lattice, numpy), :mod:`.kernels` (the Dr.Jit
kernels and the splat), :mod:`.mis` (the default sampling), :mod:`.gram` (Gram
matrices of L by row blocks that touch few nodes), this front door
(:func:`lighting_matrix`, :func:`texel_lighting_matrix`: input checks, chunking,
visibility).

Implementation: one fused Dr.Jit kernel per chunk of normals (directions,
envmap lookups, Rusinkiewicz angles, bilinear weights) scatters RGB padded
to a 4-wide packet into ``[rows, n_t * n_s, 4]`` (:mod:`.kernels`). On the
LLVM backend a lane per row loops over the row's directions, so every element
of L is summed by one lane in one order: L is the same bit for bit from run to
run and for any number of threads. On CUDA a lane per (row, direction) scatters
with atomics (``ReduceMode.Expand``, which Dr.Jit turns into atomics there), and
sums agree to float32 rounding. Directions below a row's horizon, which add nothing, are
jumped over where a whole SIMD packet (or warp) has them at once
(:func:`~mi_bivariate.lighting.kernels.above_horizon`: the environment's pooled
directions, stored so that neighbouring rows reach them together, and the texels).
Visibility (``occluder``): the paper assumes every light direction of the
normal's hemisphere reaches the surface, which holds for a convex object
only. Given the object as a Mitsuba scene, rows that know their surface
position (:attr:`Observations.positions`, e.g. ray-cast from a mesh) trace
a shadow ray per light direction inside the same kernel (``scene.ray_test``
from the point, offset along the geometric normal exactly as Mitsuba's
``spawn_ray`` does for a render's shadow rays), and blocked directions
contribute nothing. With ``max_depth=2`` renders (no interreflection) the
model is then exact for any shape.

Rows are ordered along a space-filling curve of their normals (a chunk's
rows are neighbours, and so are the rows of one SIMD packet on the CPU).
Each chunk's kernels are launched and the previous chunk is copied into L while
they run (:func:`_fill`).
Memory: the ``(M, n_t * n_s, 3) float32`` result (94 MB at M = 8000,
32 x 32) plus :data:`CHUNK_BYTES` for the running chunk's target, and the
previous chunk's target while it is copied; the kernel itself stores no
per-direction arrays.
"""

from __future__ import annotations

import sys
from typing import Any, Callable, Iterable, List, Optional, Sequence, Tuple, Union

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.capture import Observations
from mi_bivariate.errors import InputError
from mi_bivariate.limits import (MAX_DIRS, MAX_KERNEL_LANES, MAX_LIGHTING_BYTES, MAX_SEED, check_grid, check_max,
                                 check_seed, whole_number)
from mi_bivariate.lighting.directions import direction_pairs, hemisphere_offsets, light_directions, row_frames
from mi_bivariate.lighting.kernels import (_lighting_target, _rgb_rows, _row_packets, _spatial_order, _texel_target,
                                          lane_per_row)
from mi_bivariate.lighting.mis import (
    ENV_SHIFTS,
    MIS_FRACTIONS,
    PEAK_T_MAX,
    POOL_BYTES,
    SAMPLINGS,
    _mis_target,
    environment_pool,
    pool_bytes,
    strategy_counts,
)
from mi_bivariate.probes import check_probe
from mi_bivariate.variants import ensure_variant

__all__ = ["CHUNK_BYTES", "ENV_SHIFTS", "MIS_FRACTIONS", "PEAK_T_MAX", "PROGRESS_PAIRS", "SAMPLINGS",
           "direction_pairs", "environment_pool", "hemisphere_offsets", "light_directions", "lighting_matrix",
           "row_frames", "strategy_counts", "texel_lighting_matrix"]

#: Memory for one chunk's scatter target, ``(rows, n_t * n_s, 4) float32``: 2048 rows at
#: 32 x 32. The kernels hold one copy of it on either backend (:mod:`.kernels`: a lane per row
#: on LLVM, atomics on CUDA); it sets how many kernels a matrix takes. Measured with the
#: per-thread copies of ``ReduceMode.Expand`` (``docs/recovery.md``, Speed, Round 16: 128-2048
#: rows) and with a lane per row (Round 21: 1024 against 2048 rows).
CHUNK_BYTES = 32 * 2**20

#: Show a progress bar when a job has more (normal, direction) pairs than this.
PROGRESS_PAIRS = 5 * 10**8


#: Light directions K per normal by default. With MIS, K = 8000 predicts pixels to ~0.1-0.3%
#: (well below the solve's 1% model error) and recovers the same tables as K = 32000 to ~1% in
#: relight error (8 materials, docs/recovery.md "Directions per normal"), at a quarter of the cost.
DEFAULT_DIRS = 8000

def _as_probe_list(probes: Any) -> List[Any]:
    if isinstance(probes, (list, tuple)):
        return list(probes)
    return [probes]


def check_kernel_lanes(n_rows: int, n_dirs: int, n_nodes: int, name: str = "n_dirs",
                       chunk: Optional[int] = None, texels: bool = False) -> None:
    """Refuse a lighting kernel of more than :data:`~mi_bivariate.limits.MAX_KERNEL_LANES` lanes
    (Dr.Jit indexes them with 32 bits), naming ``name``: rows of a chunk x direction pairs where a
    lane runs per (row, direction) (CUDA); a chunk's rows where a lane loops over its row's
    directions (:func:`~mi_bivariate.lighting.kernels.lane_per_row`, the CPU). With ``texels``,
    ``n_dirs`` counts a probe's texels (:func:`texel_lighting_matrix`: a lane per (row, texel))."""
    per_row = 1 if lane_per_row() else (int(n_dirs) if texels else direction_pairs(n_dirs))
    lanes = min(int(n_rows), _chunk_rows(n_nodes, chunk)) * per_row
    if lanes > MAX_KERNEL_LANES:
        raise InputError(name, f"{n_dirs} {'texels' if texels else 'directions'} with {n_nodes} grid nodes make a "
                         f"lighting kernel of {lanes} lanes, over the limit of {MAX_KERNEL_LANES}",
                         "downsample the probe more" if texels else "use fewer directions")


def _check_inputs(obs: Observations, probes: List[Any], n_t: Any, n_s: Any, n_dirs: Any = 2, seed: Any = 0,
                  chunk: Any = None) -> Tuple[int, int, int, int, Optional[int]]:
    """The front doors' arguments checked, each refusal an :class:`InputError` naming the argument:
    ``(n_t, n_s, n_dirs, seed, chunk)`` as ``int`` (``chunk`` may stay ``None``)."""
    if not isinstance(obs, Observations):
        raise InputError("obs", f"must be Observations, got a {type(obs).__name__}",
                         "build them from an image with mi_bivariate.capture.image_observations")
    n_t, n_s = check_grid((n_t, n_s), axis_names=("n_t", "n_s"))
    n_dirs = whole_number("n_dirs", n_dirs)
    if n_dirs < 2:
        raise InputError("n_dirs", f"must be at least 2, got {n_dirs}")
    check_max("n_dirs", n_dirs, MAX_DIRS)
    seed = check_seed(seed)
    if chunk is not None:
        chunk = whole_number("chunk", chunk)
        if chunk < 1:
            raise InputError("chunk", f"must be at least 1 row, got {chunk}")
    if len(obs) == 0:
        raise InputError("obs", "no observations")
    size = len(obs) * n_t * n_s * 3 * 4
    if size > MAX_LIGHTING_BYTES:
        raise InputError("obs", f"the lighting matrix of {len(obs)} rows x {n_t * n_s} nodes would take "
                         f"{size / 2**30:.1f} GiB, over the limit of {MAX_LIGHTING_BYTES / 2**30:.0f} GiB",
                         "use fewer normals or a smaller grid")
    if not probes:
        raise InputError("probes", "no probe given")
    for k, probe in enumerate(probes):
        check_probe(probe, "probes" if len(probes) == 1 else f"probes[{k}]")
    low, top = int(obs.probe_index.min()), int(obs.probe_index.max())
    if top >= len(probes) or low < 0:
        bad = low if low < 0 else top  # the index out of range, not a valid largest one
        raise InputError("probes", f"the observations refer to probe {bad} but {len(probes)} probe(s) were given")
    if not (np.all(np.isfinite(obs.normals)) and np.all(np.isfinite(obs.views))):
        raise InputError("obs", "the observations have non-finite normals or views")
    if np.any(np.sum(obs.normals * obs.views, axis=1) <= 0.0):
        raise InputError("obs", "some observed normals face away from their view (n . v <= 0)")
    if obs.positions is not None and obs.geometric_normals is not None:
        g = obs.geometric_normals[np.all(np.isfinite(obs.positions), axis=1)]
        if not (np.all(np.isfinite(g)) and np.all(np.linalg.norm(g, axis=1) > 0.0)):
            raise InputError("obs", "some rows with a surface position have a zero or non-finite geometric "
                             "normal (their shadow rays' offset)", "give each such row its face normal, or "
                             "geometric_normals=None (the shading normals stand in)")
    return n_t, n_s, n_dirs, seed, chunk


def _chunk_rows(n_nodes: int, chunk: Optional[int]) -> int:
    if chunk is not None:
        return max(1, int(chunk))
    # 16 B per node and row of the scatter target (one copy: see CHUNK_BYTES).
    return max(16, CHUNK_BYTES // (n_nodes * 16))


def _fill(L: np.ndarray, chunks: Iterable[Tuple[np.ndarray, Any]]) -> None:
    """Copy launched chunks ``(rows, target)`` into ``L[rows]`` (in place), each while the next
    chunk's kernel runs: the copy (and the first touch of L's pages, 0.05-0.2 s of a
    94 MB matrix on the benchmark machine) overlaps the kernels instead of following them."""
    ready = None
    for rows, target in chunks:
        if ready is not None:
            L[ready[0]] = ready[1]
        ready = rows, _rgb_rows(target, len(rows), L.shape[1])
    if ready is not None:
        L[ready[0]] = ready[1]


def _occluder_scene(occluder: Any) -> Any:
    """A ``mi.Scene`` from a scene or an object with a ``scene()`` method (e.g. a mesh shape)."""
    if occluder is None or isinstance(occluder, mi.Scene):
        return occluder
    if callable(getattr(occluder, "scene", None)):
        return occluder.scene()
    raise InputError("occluder", f"must be a Mitsuba scene or have a scene() method, got {type(occluder).__name__}")


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
        raise InputError("occluder", f"the observations come from image {top} but {len(per_image)} occluder(s) were given")
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
                    n_dirs: int = DEFAULT_DIRS, seed: int = 0, chunk: Optional[int] = None,
                    progress: Optional[bool] = None, occluder: Any = None,
                    sampling: str = "mis") -> np.ndarray:
    """The lighting matrix of Eqs. 4-5.

    Args:
        obs: observations (normals, views, which probe lit each row).
        probes: a :class:`~mi_bivariate.probes.Probe` or a list indexed by
            ``obs.probe_index``.
        n_t, n_s: st grid size.
        n_dirs: light directions K per normal.
        seed: seeds the per-row shifts of the direction lattice (and, with ``"mis"``, the
            :data:`ENV_SHIFTS` shifts of the environment's pooled directions).
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
            K = 32768 predicts pixels with 10-50% per-pixel quadrature noise,
            which the solve then fits; see ``docs/recovery.md``.

    Returns:
        ``(M, n_t * n_s, 3) float32``; column ``it * n_s + is``.
    """
    ensure_variant(vectorised=True)
    probes = _as_probe_list(probes)
    n_t, n_s, n_dirs, seed, chunk = _check_inputs(obs, probes, n_t, n_s, n_dirs, seed, chunk)
    check_kernel_lanes(len(obs), n_dirs, n_t * n_s, chunk=chunk)
    if sampling not in SAMPLINGS:
        raise InputError("sampling", f"unknown sampling {sampling!r}", f"use one of {', '.join(SAMPLINGS)}")
    target_fn = _mis_target if sampling == "mis" else _lighting_target
    m_total, n_nodes = len(obs), n_t * n_s
    scenes, scene_of_row = _occluder_per_row(obs, occluder)
    if scenes and not obs.has_positions:
        raise InputError("occluder", "an occluder was given but the observations have no surface positions",
                         "build them from a mesh (mi_bivariate.mesh) or pass positions to "
                         "observations_from_normal_map")
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(m_total, seed),
                           obs.positions, obs.geometric_normals)
    rows_per_chunk = _chunk_rows(n_nodes, chunk)

    jobs = []
    order = _spatial_order(obs.normals)
    order = order[np.isin(order, _centre_rows(obs))] if obs.has_footprints else order
    for p in np.unique(obs.probe_index):
        for o in np.unique(scene_of_row):
            rows = order[(obs.probe_index[order] == p) & (scene_of_row[order] == o)]
            jobs += [(int(p), int(o), rows[i:i + rows_per_chunk]) for i in range(0, len(rows), rows_per_chunk)]
    if progress is None:
        progress = len(jobs) > 1 and m_total * n_dirs > PROGRESS_PAIRS and sys.stderr.isatty()
    if progress:
        from tqdm import tqdm

        jobs = tqdm(jobs, desc="lighting matrix", unit="chunk")

    n_env = strategy_counts(n_dirs).get("environment", 0) if sampling == "mis" else 0
    pooled = n_env > 0 and pool_bytes(n_env) <= POOL_BYTES

    def chunks():
        pool, pool_of = None, None
        for p, o, rows in jobs:  # grouped by probe: one probe's pool is held at a time
            extra = {}
            if pooled:
                if pool_of != p:  # the environment's directions, sampled once per probe (lighting.mis)
                    pool, pool_of = None, p
                    pool = environment_pool(probes[p], n_env, seed, stream=p)
                extra = {"pool": pool}
            yield rows, target_fn(packets[rows], probes[p], n_t, n_s, n_dirs, scenes[o] if o >= 0 else None, **extra)

    L = np.empty((m_total, n_nodes, 3), dtype=np.float32)
    _fill(L, chunks())
    if obs.has_footprints:
        # Block b's seed: seed + 1 + b, wrapped into the seeds' range (a seed near MAX_SEED is valid too).
        _footprint_rows(L, obs, n_nodes, chunk, lambda sub, b: lighting_matrix(
            sub, probes, n_t=n_t, n_s=n_s, n_dirs=n_dirs, seed=(seed + 1 + b) % (MAX_SEED + 1), chunk=chunk,
            progress=False, sampling=sampling))
    return L


def _centre_rows(obs: Observations) -> np.ndarray:
    """The rows modelled by their centre normal alone (the others are footprint means)."""
    keep = np.ones(len(obs), dtype=bool)
    if obs.has_footprints:
        keep[obs.footprint_rows] = False
    return np.flatnonzero(keep)


def _footprint_rows(L: np.ndarray, obs: Observations, n_nodes: int, chunk: Optional[int],
                    rows_of: Callable[[Observations, int], np.ndarray]) -> None:
    """Fill the rows that have a pixel footprint with the mean of their footprint normals' rows (in place).

    The footprint normals (:attr:`Observations.footprint_normals`) become rows
    of their own, with their pixel's view and probe (footprints are made for
    convex spheres: no positions, no shadow rays), in blocks of whole pixels so
    that memory stays at about one block's ``(P, N, 3)``. ``rows_of(sub, block)``
    computes a block's rows with the caller's quadrature.
    """
    rows = obs.footprint_rows
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])   # first footprint normal of each pixel
    counts = np.diff(np.r_[starts, len(rows)]).astype(np.float32)
    block = starts // max(1, _chunk_rows(n_nodes, chunk) * 4)     # a pixel goes wholly to one block
    for b in np.unique(block):
        pix = np.flatnonzero(block == b)
        lo, hi = starts[pix[0]], starts[pix[-1]] + int(counts[pix[-1]])
        owner = rows[lo:hi]
        sub = Observations(normals=obs.footprint_normals[lo:hi], views=obs.views[owner],
                           values=obs.values[owner], probe_index=obs.probe_index[owner])
        L[rows[starts[pix]]] = np.add.reduceat(rows_of(sub, int(b)), starts[pix] - lo, axis=0) / counts[pix, None, None]


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
    ensure_variant(vectorised=True)
    probes = _as_probe_list(probes)
    n_t, n_s, _, _, chunk = _check_inputs(obs, probes, n_t, n_s, chunk=chunk)
    downsample = whole_number("downsample", downsample)
    if downsample < 1:
        raise InputError("downsample", f"must be at least 1, got {downsample}")
    m_total, n_nodes = len(obs), n_t * n_s
    packets = _row_packets(obs.normals, obs.views, np.zeros((m_total, 2), dtype=np.float32))
    rows_per_chunk = _chunk_rows(n_nodes, chunk)
    order = _spatial_order(obs.normals)
    order = order[np.isin(order, _centre_rows(obs))] if obs.has_footprints else order
    coarse_of = {}
    for p in np.unique(obs.probe_index):  # every probe's kernels checked before the first runs
        probe = probes[int(p)]
        factor = max(f for f in range(1, downsample + 1) if probe.width % f == 0)
        coarse_of[int(p)] = coarse = probe.downsampled(factor)
        check_kernel_lanes(int(np.count_nonzero(obs.probe_index == p)), coarse.width * coarse.height, n_nodes,
                           "downsample", chunk, texels=True)

    def chunks():
        for p in np.unique(obs.probe_index):
            coarse = coarse_of[int(p)]
            directions, solid_angle = coarse.texel_directions()
            radiance = coarse.data.reshape(-1, 3).astype(np.float64) * solid_angle[:, None]
            texels = (mi.Vector3f(*directions.astype(np.float32).T),
                      mi.Color3f(*radiance.astype(np.float32).T), len(solid_angle))
            rows = order[obs.probe_index[order] == p]
            for i in range(0, len(rows), rows_per_chunk):
                sel = rows[i:i + rows_per_chunk]
                yield sel, _texel_target(packets[sel], texels, n_t, n_s)

    L = np.empty((m_total, n_nodes, 3), dtype=np.float32)
    _fill(L, chunks())
    if obs.has_footprints:
        _footprint_rows(L, obs, n_nodes, chunk, lambda sub, b: texel_lighting_matrix(
            sub, probes, n_t=n_t, n_s=n_s, downsample=downsample, chunk=chunk))
    return L

