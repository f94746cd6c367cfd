"""Multiple importance sampling of the light directions (the default ``"mis"`` sampling).

Three stratified strategies share the K directions of a row (:data:`MIS_FRACTIONS`):
uniform over the hemisphere (the paper's), the environment's own importance sampling
(Mitsuba's ``envmap.sample_direction``) and half vectors around the normal as dense as
the grid's t nodes (the specular peak); every direction is weighted by the balance
heuristic over all three densities (Veach's multi-sample estimator).

The environment's directions do not depend on the row, only on the lattice's shift: they
are sampled once per lighting matrix for :data:`ENV_SHIFTS` shifts
(:func:`environment_pool`), and each row reads the set of one shift (its own random pick)
instead of sampling the environment's hierarchy again. Each row's estimate is the same
stratified, unbiased estimator; the environment sampling, 58% of the kernels' time when done
per row, becomes a gather. The pooled directions cover the whole sphere, so most of them lie
below a given row's horizon (77% on the benchmark sphere under grace_latlong_1k); each shift's
points are stored along a Morton curve over their directions, so that the rows of a SIMD
packet (neighbours) reach such points together and jump over them
(:func:`~mi_bivariate.lighting.kernels.above_horizon`).

The heuristic's environment density is read from the radiance each lane looks up anyway,
``luminance(E) / Z`` (:class:`EnvironmentProxy`), not from a second map lookup
(``pdf_direction``): any stand-in that is positive only where the environment can be sampled
keeps the weights adding up to one (it is 0 next to a pole row far brighter than the next), and
this one is the true density up to the interpolation of ``sin theta`` between the map's rows
(``benchmarks/env_pool.py --compare density``: the same error to 0.01% on six materials). It
took the uniform and peak lanes' kernel from 0.58 to 0.38 s on the bench input.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any, Optional, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.common import LUMINANCE_WEIGHTS, luminance
from mi_bivariate.lighting.directions import _TWO_PI
from mi_bivariate.lighting.kernels import (RowInputs, _lattice_lanes, _launched, _occluded, _rgb_rows, _row_data,
                                          _splat, above_horizon, fibonacci_point, lattice_points, morton_key,
                                          splat_mode)

#: Light-direction sampling of :func:`lighting_matrix`: the fraction of the K
#: directions drawn by each strategy of the ``"mis"`` mixture (see :func:`_mis_chunk`).
MIS_FRACTIONS = {"uniform": 0.25, "environment": 0.5, "peak": 0.25}
#: The ``"peak"`` strategy draws half vectors with t = sqrt(2 theta_h / pi) uniform in
#: ``[0, PEAK_T_MAX]`` (theta_h up to 22.5 degrees): as dense as the st grid's t nodes.
PEAK_T_MAX = 0.5
SAMPLINGS = ("mis", "uniform")
#: Lattice shifts of the environment strategy's pooled directions (:func:`environment_pool`).
#: Rows pick one at random (:func:`_pool_slot`), so a given shift serves about 1/64 of the
#: rows, spread over the sphere (the pick is independent of the normal).
ENV_SHIFTS = 64
#: A pole row brighter than this many times the next row's texels gets a band without the proxy
#: (:class:`EnvironmentProxy`).
POLE_RATIO = 4.0
#: :func:`environment_proxy` per probe.
_PROXIES: "weakref.WeakKeyDictionary[Any, EnvironmentProxy]" = weakref.WeakKeyDictionary()
#: Bits per axis of the Morton curve that orders each pooled shift (:func:`environment_pool`):
#: keys of 16 bits, which numpy sorts by radix.
POOL_MORTON_BITS = 8
#: Floats per pooled direction: ``(d.x, d.y, d.z, pdf, radiance r, g, b, 0)``.
_POOL_FLOATS = 8
#: The largest pool :func:`~mi_bivariate.lighting.lighting_matrix` builds (bytes, per probe);
#: beyond it (K above ~2 million) the environment is sampled per row.
POOL_BYTES = 256 * 2**20


def pool_bytes(n_points: int) -> int:
    """Bytes of :func:`environment_pool` for ``n_points`` environment directions per row."""
    return int(n_points) * ENV_SHIFTS * _POOL_FLOATS * 4


def _pool_slot(shift: Any) -> Any:
    """The pooled shift (``mi.UInt32`` in ``[0, ENV_SHIFTS)``) a row reads, from its own random
    shift ``shift_1`` in [0, 1): the bits below its first 12 (``frac(4096 shift_1)``), so the
    pick is independent of where ``shift_1`` puts the row's uniform and peak lattices."""
    fine = shift * 4096.0
    return dr.minimum(mi.UInt32((fine - dr.floor(fine)) * ENV_SHIFTS), ENV_SHIFTS - 1)


def environment_pool(probe: Any, n_points: int, seed: int = 0, stream: int = 0) -> Any:
    """The environment strategy's directions for :data:`ENV_SHIFTS` lattice shifts (``mi.Float``).

    For shift ``q`` (drawn from ``seed`` and ``stream``: one stream per probe, so two images
    under rotated copies of one map do not share their lattices) and lattice point ``k`` of
    ``n_points``, the
    Fibonacci point shifted by ``q`` (as :func:`~mi_bivariate.lighting.kernels.lattice_points`
    shifts a row's) through ``envmap.sample_direction``: the world direction, its solid-angle
    density and the radiance there (``weight * pdf``), :data:`_POOL_FLOATS` floats per point.

    Shift ``q``'s points fill entries ``q * n_points`` to ``(q + 1) * n_points - 1`` along a Morton
    curve over their directions (:func:`~mi_bivariate.lighting.kernels.morton_key`), not in lattice
    order: the same set, so each row's estimate is unchanged but for the order of its sum. Each
    shift's points follow the environment's density, so the j-th points of two shifts lie near one
    another; the rows of a SIMD packet, neighbours that each read their own shift's j-th point at
    step j, then find it below all their horizons together far more often (74% of the packets'
    environment steps on the benchmark sphere under grace_latlong_1k, 14% in lattice order), and
    skip it (:func:`_mis_target`).
    """
    rng = np.random.default_rng([int(seed), int(stream), 0x5EED])
    shifts = mi.Float(rng.random((ENV_SHIFTS, 2), dtype=np.float32).reshape(-1))
    idx = dr.arange(mi.UInt32, int(n_points) * ENV_SHIFTS)
    q = idx // int(n_points)
    k = idx - q * int(n_points)
    u1, u2 = fibonacci_point(k, n_points, dr.gather(mi.Float, shifts, 2 * q),
                              dr.gather(mi.Float, shifts, 2 * q + 1))
    ds, weight = probe.emitter().sample_direction(dr.zeros(mi.Interaction3f), mi.Point2f(u1, u2))
    radiance = weight * ds.pdf
    head = mi.Vector4f(ds.d.x, ds.d.y, ds.d.z, ds.pdf)
    tail = mi.Vector4f(radiance[0], radiance[1], radiance[2], 0.0)
    key = morton_key(ds.d, POOL_MORTON_BITS)
    dr.eval(head, tail, key)  # one kernel
    # Each shift's points along the curve (a stable radix sort of 16-bit keys): entry q * n_points + j
    # holds point j of shift q in that order, lattice point order[q, j] (a gather, not the scatter of
    # the inverse permutation, which cost numpy 10 ms).
    n = int(n_points)
    order = np.argsort(key.numpy().astype(np.uint16).reshape(ENV_SHIFTS, n), axis=1, kind="stable")
    order += np.arange(0, ENV_SHIFTS * n, n, dtype=order.dtype)[:, None]
    source = mi.UInt32(order.reshape(-1).astype(np.uint32))
    entry = dr.arange(mi.UInt32, n * ENV_SHIFTS)
    pool = dr.zeros(mi.Float, n * ENV_SHIFTS * _POOL_FLOATS)
    dr.scatter(pool, dr.gather(mi.Vector4f, head, source), 2 * entry)
    dr.scatter(pool, dr.gather(mi.Vector4f, tail, source), 2 * entry + 1)
    dr.eval(pool)
    return pool


def _pooled_sample(pool: Any, r: RowInputs, k: Any, n_points: int) -> Tuple[Any, Any, Any]:
    """Point ``k`` of a row's pooled shift (:func:`environment_pool`; the shift :func:`_pool_slot`
    picks from the row's own ``shift_1``): the world direction ``d``, its density ``p_env`` and the
    radiance there (``mi.Color3f``)."""
    entry = _pool_slot(r.shift_1) * n_points + k
    head = dr.gather(mi.Vector4f, pool, 2 * entry)
    tail = dr.gather(mi.Vector4f, pool, 2 * entry + 1)
    return mi.Vector3f(head.x, head.y, head.z), head.w, mi.Color3f(tail.x, tail.y, tail.z)


def strategy_counts(n_dirs: int, fractions: Optional[dict] = None) -> dict:
    """Directions per strategy of the ``"mis"`` sampling: each strategy's share of ``n_dirs`` rounded
    (at least 1), the first strategy topped up to ``n_dirs``. Rounding can give one more than ``n_dirs``
    in total (3 of 8 values of ``n_dirs``; two more for ``n_dirs`` = 1); the estimator stays unbiased."""
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
    mirror of the view, ``p(l) = p(h) / (4 (v . h))``. Written with the unnormalised half
    vector ``l + v`` and theta_h exactly as :func:`~mi_bivariate.lighting.kernels._splat`
    computes them, so that Dr.Jit traces those operations once per lane (its common
    subexpressions are merged: 300 -> 275 operations per environment lane).
    """
    hx, hz = lx + sin_v, lz + cos_v
    sin_h = dr.sqrt(hx * hx + ly * ly)           # |h| sin theta_h
    theta_h = dr.atan2(sin_h, hz)
    t = dr.sqrt(theta_h * (2.0 / math.pi))
    v_dot_h = sin_v * hx + cos_v * hz            # |h| (v . h)
    pdf = (hx * hx + ly * ly + hz * hz) / ((PEAK_T_MAX * math.pi * _TWO_PI * 4.0) * t * sin_h * v_dot_h)
    return dr.select((t < PEAK_T_MAX) & (sin_h > 0.0) & (v_dot_h > 0.0), pdf, 0.0)


@dataclass(frozen=True)
class EnvironmentProxy:
    """What the balance heuristic needs of a probe to read the environment's density from the
    radiance (:func:`_mis_lane`): ``q(d) = luminance(E(d)) / scale``, and 0 in the polar bands.

    ``scale`` is ``Z``, the integral of the luminance over the sphere (sr times radiance; 0 for a
    black probe, whose lanes all add 0). ``axis`` is the world direction of the map's first row
    (its local ``+y``, theta = 0). Mitsuba weighs the rows by ``sin theta``, 0 on the two pole
    rows, so between a pole row and the next (``theta < pi / (H - 1)``) its sampling density
    follows the next row alone while the radiance also has the pole row's: a pole row far brighter
    (more than :data:`POLE_RATIO` times) than the next row's texels below it would make
    ``q / p_env`` large there, and unbounded where those are black (``q > 0 = p_env``, a bias).
    For such a pole the band (widened by 1%) gets ``q = 0``: ``d . axis > cos_top``
    (``-d . axis > cos_bottom``); otherwise the cosine is 2 (no band).
    """

    scale: float
    axis: Tuple[float, float, float]
    cos_top: float
    cos_bottom: float

    @property
    def inverse_scale(self) -> float:
        """``1 / scale``, 0 for a black probe (no proxy density)."""
        return 1.0 / self.scale if math.isfinite(self.scale) and self.scale > 0.0 else 0.0

    @property
    def has_bands(self) -> bool:
        """Whether either pole has a band (else the kernels skip the test)."""
        return self.cos_top <= 1.0 or self.cos_bottom <= 1.0


def environment_proxy(probe: Any) -> EnvironmentProxy:
    """The probe's :class:`EnvironmentProxy` (cached per probe)."""
    cached = _PROXIES.get(probe)
    if cached is None:
        lum = luminance(probe.data)

        def needs_band(pole: np.ndarray, nxt: np.ndarray) -> bool:
            # each pair of neighbouring columns (wrapping): the bilinear footprint of a direction
            hi = np.maximum(pole, np.roll(pole, -1))
            lo = np.minimum(nxt, np.roll(nxt, -1))
            return bool(np.any(hi > POLE_RATIO * lo))

        axis = np.asarray(probe.to_world, dtype=np.float64)[:3, 1]
        axis = axis / np.linalg.norm(axis)
        height = lum.shape[0]
        band = float(math.cos(min(0.5 * math.pi, 1.01 * math.pi / max(1, height - 1))))
        cached = EnvironmentProxy(
            scale=float(np.sum(lum * probe.solid_angles())),
            axis=(float(axis[0]), float(axis[1]), float(axis[2])),
            cos_top=band if height < 3 or needs_band(lum[0], lum[1]) else 2.0,
            cos_bottom=band if height < 3 or needs_band(lum[-1], lum[-2]) else 2.0)
        _PROXIES[probe] = cached
    return cached


def _local_direction(strategy: str, u1: Any, u2: Any, sin_v: Any, cos_v: Any) -> Tuple[Any, Any, Any, Any]:
    """The row-frame light direction ``(lx, ly, lz)`` of the uniform or peak strategy at lattice point
    ``(u1, u2)``, and the peak strategy's own solid-angle density there (``None`` for the uniform
    strategy, whose constant density :func:`_row_frame_density` adds).

    The peak strategy's density is the closed form at the sampled ``t = T u1`` and ``theta_h``, not
    :func:`_peak_pdf` at ``l`` (what the other strategies' lanes read). A lattice point within a
    float32 ulp of ``u1 = 1`` wraps to ``u1 = 0`` (:func:`~mi_bivariate.lighting.kernels.fibonacci_point`;
    3 lanes of 2443 rows at K = 10000, seed 1, on the benchmark sphere): its light is the mirror direction
    itself, where the density is infinite and the lane weighs 0. Rebuilt from ``l + v``, its half
    vector had no component off the normal and :func:`_peak_pdf` read 0: the lane took a uniform
    direction's weight at a sharp table's peak (``benchmarks/dirs_noise.py``: tungsten-carbide under
    uffizi_256 predicted with 0.94-9.6% RMS error at 3 of 4 seeds of K = 10000, 0.12-0.14% after). Near
    the mirror direction the rebuilt ``theta_h`` is also round-off (~1e-7 rad), so :func:`_peak_pdf`
    was up to 1e4 times the true density there (weights of ~1e-12: harmless, and gone with it).
    """
    azimuth = _TWO_PI * u2
    if strategy == "uniform":
        r = dr.safe_sqrt(1.0 - u1 * u1)
        sin_phi, cos_phi = dr.sincos(azimuth)
        return r * cos_phi, r * sin_phi, u1, None
    if strategy == "peak":
        t = PEAK_T_MAX * u1
        theta_h = (0.5 * math.pi) * dr.square(t)
        sin_h, cos_h = dr.sincos(theta_h)
        sin_p, cos_p = dr.sincos(azimuth)
        hx, hy, hz = sin_h * cos_p, sin_h * sin_p, cos_h
        v_dot_h = sin_v * hx + cos_v * hz
        # p(h) = 1 / (T pi t 2 pi sin theta_h), times the mirror map's Jacobian 1 / (4 v . h); infinite
        # at t = 0 exactly (the lane then weighs 0), 0 where the mirrored light is below the surface.
        pdf = dr.select(v_dot_h > 0.0, 1.0 / ((PEAK_T_MAX * math.pi * _TWO_PI * 4.0) * t * sin_h * v_dot_h), 0.0)
        return 2.0 * v_dot_h * hx - sin_v, 2.0 * v_dot_h * hy, 2.0 * v_dot_h * hz - cos_v, pdf
    raise ValueError(strategy)


def _row_frame_density(counts: dict, lx: Any, ly: Any, lz: Any, sin_v: Any, cos_v: Any,
                        own_peak: Any = None) -> Any:
    """``K_u p_u + K_p p_peak`` at a row-frame direction: the part of the balance heuristic's
    denominator that does not depend on the environment. ``own_peak``: the peak density of a peak
    lane, known from its sample (:func:`_local_direction`), instead of :func:`_peak_pdf` at ``l``."""
    density = mi.Float(0.0)
    if counts.get("uniform"):
        density += counts["uniform"] * (1.0 / _TWO_PI)
    if counts.get("peak"):
        density += counts["peak"] * (_peak_pdf(lx, ly, lz, sin_v, cos_v) if own_peak is None else own_peak)
    return density


def _environment_density(counts: dict, probe: Any, d: Any, radiance: Any, horizon: Any, own: Any,
                         env_density: str) -> Any:
    """``q(d)``, the environment's density as the balance heuristic reads it (``None`` without an
    environment strategy): the proxy ``luminance(E(d)) / Z`` from the radiance (:class:`EnvironmentProxy`),
    or with ``env_density="exact"`` Mitsuba's ``pdf_direction`` (``own``, the lane's sampled density,
    where it is known)."""
    if not counts.get("environment"):
        return None
    if env_density == "proxy":
        env = environment_proxy(probe)
        w = LUMINANCE_WEIGHTS * env.inverse_scale
        proxy = float(w[0]) * radiance[0] + float(w[1]) * radiance[1] + float(w[2]) * radiance[2]
        if env.has_bands:  # a pole row far brighter than the next (grace_256's bottom)
            along = d.x * env.axis[0] + d.y * env.axis[1] + d.z * env.axis[2]
            proxy = dr.select((along > env.cos_top) | (-along > env.cos_bottom), 0.0, proxy)
        return proxy
    if env_density == "exact":
        if own is not None:
            return own
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = d
        return probe.emitter().pdf_direction(dr.zeros(mi.Interaction3f), ds, horizon)
    raise ValueError(f"env_density must be 'proxy' or 'exact', not {env_density!r}")


def _mis_lanes(data: Any, m: int, probe: Any, strategy: str, counts: dict,
               pool: Any = None, env_density: str = "proxy"):
    """The lanes of one sampling strategy for ``m`` rows, one lane per (row, light direction), row then
    direction: ``(row, lx, ly, lz, d, weight, sin_v, cos_v, above, radiance)``
    (:func:`_mis_lane`; the layout the benchmarks take apart).
    """
    row, k, r, u1, u2 = _lattice_lanes(data, m, counts[strategy])
    return (row,) + _mis_lane(k, r, u1, u2, probe, strategy, counts, pool, env_density)


def _mis_lane(k: Any, r: RowInputs, u1: Any, u2: Any, probe: Any, strategy: str, counts: dict,
              pool: Any = None, env_density: str = "proxy"):
    """One light direction of one sampling strategy per lane, lattice point ``k`` (``(u1, u2)``) of a row
    with inputs ``r``: ``(lx, ly, lz, d, weight, sin_v, cos_v, above, radiance)``.

    ``d`` is the world light direction, ``(lx, ly, lz)`` its row-frame coordinates and
    ``weight`` the multi-sample balance-heuristic weight of the lane (Veach's estimator),
    0 below the horizon: a lane adds ``weight * radiance * f``. Each strategy draws a shifted
    Fibonacci lattice (per-row Cranley-Patterson shift), so every strategy is stratified.

    The heuristic's environment density is the proxy ``q(d) = luminance(E(d)) / Z``
    (:class:`EnvironmentProxy`), read from the radiance each lane looks up anyway, instead of
    Mitsuba's ``pdf_direction`` (a second map lookup per uniform and peak lane). With
    ``p_j`` each strategy's true density, ``q_j = p_j`` for the uniform and peak ones and
    ``Q = sum_j K_j q_j``, a lane of strategy ``i`` weighs ``cos theta (q_i / p_i) / Q``:
    the weights ``K_j q_j / Q`` add up to one wherever the integrand is non-zero, so the
    estimator stays unbiased provided ``q > 0`` only where the environment can be sampled
    (``p_env > 0``). Mitsuba weighs the map's rows by ``sin theta``, which is 0 on the two pole
    rows: between a pole row and the next, ``p_env`` can be 0 where ``E`` is not. Where a pole
    row is far brighter than the next (among the shared probes, grace_256's bottom), ``q = 0``
    in that band: the uniform and peak lanes carry those directions alone.
    Elsewhere ``q`` is the environment's density up to the interpolation of ``sin theta``
    between the rows (``benchmarks/env_pool.py`` measures the variance).

    ``env_density="exact"`` uses Mitsuba's ``pdf_direction`` instead (``q = p_env``: the
    plain balance heuristic; the estimator before the proxy, kept to compare against).

    ``radiance`` is the radiance at ``d`` (``mi.Color3f``, 0 below the horizon). With a
    ``pool`` (:func:`environment_pool`), the environment's lanes read the directions, true
    densities and radiances of the row's pooled shift.
    """
    x_axis, y_axis, normal, sin_v, cos_v = r.x_axis, r.y_axis, r.normal, r.sin_v, r.cos_v
    own = None  # the environment lanes' true density p_env
    own_peak = None  # the peak lanes' own density
    if strategy == "environment" and pool is not None:
        d, own, radiance = _pooled_sample(pool, r, k, counts[strategy])
        lx, ly, lz = dr.dot(d, x_axis), dr.dot(d, y_axis), dr.dot(d, normal)
    elif strategy == "environment":
        ds, _ = probe.emitter().sample_direction(dr.zeros(mi.Interaction3f), mi.Point2f(u1, u2))
        d, own = ds.d, ds.pdf
        lx, ly, lz = dr.dot(d, x_axis), dr.dot(d, y_axis), dr.dot(d, normal)
    else:
        lx, ly, lz, own_peak = _local_direction(strategy, u1, u2, sin_v, cos_v)
        d = x_axis * lx + y_axis * ly + normal * lz
    horizon = lz > 0.0
    if strategy != "environment" or pool is None:
        radiance = probe.eval_dr(d, horizon)  # below the horizon: 0, no texels read
    else:
        radiance = dr.select(horizon, radiance, 0.0)
    density = _row_frame_density(counts, lx, ly, lz, sin_v, cos_v, own_peak=own_peak)
    proxy = _environment_density(counts, probe, d, radiance, horizon, own, env_density)
    if proxy is not None:
        density += counts["environment"] * proxy
    above = horizon & (density > 0.0)
    if own is not None and env_density == "proxy":  # with q = p_env the ratio is 1
        # A sampled direction has p_env > 0 up to float32 round-off (a zero-density lane adds nothing).
        cosine = dr.select(own > 0.0, lz * proxy / own, 0.0)
    else:
        cosine = lz
    weight = dr.select(above, cosine / density, 0.0)
    return lx, ly, lz, d, weight, sin_v, cos_v, above, radiance


def _mis_chunk(packets: np.ndarray, probe: Any, n_t: int, n_s: int, n_dirs: int, **kwargs: Any) -> np.ndarray:
    """Rows of L for one chunk by multiple importance sampling, ``(m, n_t * n_s, 3) float32``
    (:func:`_mis_target`, awaited)."""
    return _rgb_rows(_mis_target(packets, probe, n_t, n_s, n_dirs, **kwargs), len(packets), n_t * n_s)


def _mis_target(packets: np.ndarray, probe: Any, n_t: int, n_s: int, n_dirs: int,
                occluder: Any = None, fractions: Optional[dict] = None, pool: Any = None,
                env_density: str = "proxy") -> Any:
    """Rows of L for one chunk by multiple importance sampling: the chunk's 4-wide target with
    its kernels launched (:func:`~mi_bivariate.lighting.kernels._launched`;
    :func:`~mi_bivariate.lighting.kernels._rgb_rows` reads it).

    Three stratified strategies share the K directions (:data:`MIS_FRACTIONS`):
    uniform over the hemisphere (the paper's), the environment's own
    importance sampling (Mitsuba's ``envmap.sample_direction``, luminance
    times sin theta: the small bright sources of a real probe), and half
    vectors around the normal as dense as the grid's t nodes (the specular
    peak, where a sharp table varies fastest). Every direction is weighted by
    the balance heuristic over all three densities, so the estimator stays
    unbiased for any table and its variance is that of the best strategy for
    each part of the integrand. ``pool``: the environment's pooled directions
    (:func:`environment_pool`, as :func:`~mi_bivariate.lighting.lighting_matrix` passes them);
    ``None``: sampled per row.
    """
    if env_density not in ("proxy", "exact"):  # checked here: an error inside the loop's tracing is wrapped
        raise ValueError(f"env_density must be 'proxy' or 'exact', not {env_density!r}")
    m = len(packets)
    counts = strategy_counts(n_dirs, fractions)
    data = _row_data(packets)
    target = dr.zeros(mi.Float, m * n_t * n_s * 4)
    mode = splat_mode()
    probe.emitter()  # built before the loops: a symbolic loop may not create the map's arrays
    for strategy in counts:  # one loop (or set of lanes) per strategy, all in one kernel
        def lane(row: Any, k: Any, r: RowInputs, u1: Any, u2: Any, strategy: str = strategy) -> None:
            lx, ly, lz, d, weight, sin_v, cos_v, active, radiance = _mis_lane(
                k, r, u1, u2, probe, strategy, counts, pool=pool, env_density=env_density)
            if occluder is not None:  # blocked directions contribute nothing (their weight needs the radiance)
                radiance = dr.select(_occluded(data, row, d, active, occluder), 0.0, radiance)
            _splat(m, row, lx, ly, lz, sin_v, cos_v, radiance * weight, n_t, n_s, active=active, target=target,
                   mode=mode)

        body = lane
        if strategy == "environment" and pool is not None:
            # The pooled directions cover the whole sphere, most of them below a given row's horizon;
            # sorted (environment_pool), a packet of neighbouring rows skips them together.
            def body(row: Any, k: Any, r: RowInputs, u1: Any, u2: Any, lane: Any = lane) -> None:
                d, _, _ = _pooled_sample(pool, r, k, counts["environment"])
                above_horizon(dr.dot(d, r.normal), lambda: lane(row, k, r, u1, u2))

        lattice_points(data, m, counts[strategy], body)
    return _launched(target)
