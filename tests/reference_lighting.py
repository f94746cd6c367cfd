"""Slow, plainly written numpy lighting matrices: the references for tests and the benchmark.

:func:`lighting_matrix_reference` is the paper's uniform quadrature
(``sampling="uniform"``), :func:`mis_lighting_matrix_reference` the default multiple
importance sampling (``sampling="mis"``, :mod:`mi_bivariate.lighting.mis`). Both use the
same lattice points as :func:`mi_bivariate.lighting.lighting_matrix` (and the MIS one
the same pooled environment samples, :func:`mi_bivariate.lighting.environment_pool`) but
compute everything else independently, in float64: directions from the lattice,
radiance through :meth:`Probe.eval` (numpy in, numpy out), the strategies' densities from
their definitions, Rusinkiewicz angles through
:func:`mi_bivariate.coordinates.half_diff_from_dirs` on local-frame vectors, and the
bilinear splat with ``np.add.at``.
"""

from __future__ import annotations

from typing import Any, Sequence, Union

import numpy as np

from mi_bivariate.capture import Observations
from mi_bivariate.common import luminance
from mi_bivariate.coordinates import half_diff_from_dirs, st_from_half_diff
from mi_bivariate.lighting import (
    ENV_SHIFTS,
    PEAK_T_MAX,
    direction_pairs,
    environment_pool,
    hemisphere_offsets,
    light_directions,
    row_frames,
    strategy_counts,
)
from mi_bivariate.lighting.directions import _half_lattice
from mi_bivariate.lighting.mis import environment_proxy


def _local_frames(n: np.ndarray) -> np.ndarray:
    """Any orthonormal frame about each normal (an isotropic BRDF does not care): ``(b, 3, 3)``, rows = axes."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tx = np.cross(helper, n)
    tx /= np.linalg.norm(tx, axis=1, keepdims=True)
    return np.stack([tx, np.cross(n, tx), n], axis=1)


def _splat(out: np.ndarray, start: int, n: np.ndarray, v: np.ndarray, dirs: np.ndarray, value: np.ndarray,
           n_t: int, n_s: int) -> None:
    """Add ``value`` ``(b, K, 3)`` of world light directions ``dirs`` ``(b, K, 3)`` into rows
    ``start..start + b`` of ``out``, bilinearly at their st points."""
    frame = _local_frames(n)
    wi = np.einsum("bij,bkj->bki", frame, dirs)
    wo = np.einsum("bij,bj->bi", frame, v)[:, None, :]
    theta_h, _, theta_d, _ = half_diff_from_dirs(wi, np.broadcast_to(wo, wi.shape))
    s, t = st_from_half_diff(theta_h, theta_d)
    fs, ft = np.clip(s, 0, 1) * (n_s - 1), np.clip(t, 0, 1) * (n_t - 1)
    i_s = np.minimum(np.floor(fs).astype(int), n_s - 2)
    i_t = np.minimum(np.floor(ft).astype(int), n_t - 2)
    ws, wt = fs - i_s, ft - i_t
    row_of = np.broadcast_to(np.arange(len(n))[:, None], i_s.shape) + start
    for di, dj, w in ((0, 0, (1 - wt) * (1 - ws)), (0, 1, (1 - wt) * ws),
                      (1, 0, wt * (1 - ws)), (1, 1, wt * ws)):
        col = (i_t + di) * n_s + (i_s + dj)
        np.add.at(out, (row_of.ravel(), col.ravel()), (value * w[..., None]).reshape(-1, 3))


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def lighting_matrix_reference(obs: Observations, probes: Union[Any, Sequence[Any]], n_t: int = 32,
                              n_s: int = 32, n_dirs: int = 32000, seed: int = 0,
                              rows: Any = None, block: int = 8, cosine: bool = True) -> np.ndarray:
    """Eq. 4 row by row with the uniform lattice: ``(len(rows), n_t * n_s, 3) float64``.

    Args:
        rows: optional subset of rows (indices into ``obs``), e.g. to time a
            part of a big job; the per-row shifts are those of the full job.
        block: rows per numpy step (bounds memory: ``block * K`` directions).
        cosine: include Eq. 3's ``cos theta_u`` (``False`` only for the
            negative controls of the model-agreement test).
    """
    probes = list(probes) if isinstance(probes, (list, tuple)) else [probes]
    rows = np.arange(len(obs)) if rows is None else np.asarray(rows)
    offsets = hemisphere_offsets(len(obs), seed)
    k_total = 2 * direction_pairs(n_dirs)
    out = np.zeros((len(rows), n_t * n_s, 3))
    for start in range(0, len(rows), block):
        sel = rows[start:start + block]
        n, v = _unit(obs.normals[sel]), _unit(obs.views[sel])
        dirs, cos_u = light_directions(n, v, n_dirs, offsets[sel])          # (b, K, 3), (b, K)
        radiance = np.empty(dirs.shape)
        for b, r in enumerate(sel):
            radiance[b] = probes[obs.probe_index[r]].eval(dirs[b])
        foreshortening = cos_u if cosine else np.ones_like(cos_u)
        value = radiance * (foreshortening * (2.0 * np.pi / k_total))[..., None]  # (b, K, 3)
        _splat(out, start, n, v, dirs, value, n_t, n_s)
    return out


def _lattice(n_points: int, shift_u: np.ndarray, shift_v: np.ndarray):
    """The Fibonacci lattice of ``n_points`` (:func:`~mi_bivariate.lighting.directions._half_lattice`)
    shifted by each row's ``(shift_u, shift_v)``: ``(b, n_points)`` twice, in [0, 1)."""
    u1, u2 = _half_lattice(n_points)
    return np.mod(u1 + shift_u[:, None], 1.0), np.mod(u2 + shift_v[:, None], 1.0)


def _peak_density(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Solid-angle density of the peak strategy at local directions ``wi`` (view ``wo``), from its
    definition: ``t = sqrt(2 theta_h / pi)`` uniform on ``[0, T]``, ``phi_h`` uniform, then the
    Jacobian ``1 / (4 v . h)`` of the mirror map."""
    h = _unit(wi + wo)
    theta_h = np.arctan2(np.hypot(h[..., 0], h[..., 1]), h[..., 2])
    t = np.sqrt(2.0 * theta_h / np.pi)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_h = 1.0 / (PEAK_T_MAX * (np.pi * t) * (2.0 * np.pi) * np.sin(theta_h))
        p = p_h / (4.0 * np.sum(wo * h, axis=-1))
    return np.where((t < PEAK_T_MAX) & (theta_h > 0) & (np.sum(wo * h, axis=-1) > 0), p, 0.0)


def mis_lighting_matrix_reference(obs: Observations, probe: Any, n_t: int = 32, n_s: int = 32,
                                  n_dirs: int = 8000, seed: int = 0, rows: Any = None,
                                  block: int = 8, stream: int = 0) -> np.ndarray:
    """Eq. 4 row by row with the default ``"mis"`` sampling: ``(len(rows), n_t * n_s, 3) float64``.

    One probe for the rows computed, whose pool is ``stream`` (a ``lighting_matrix`` job draws probe
    ``p``'s pool from stream ``p``: pass ``rows`` with ``obs.probe_index == p``). Per row: the
    three strategies' directions (the environment's from the pool entry of the row's slot), every direction
    weighted by ``cos theta / sum_j K_j q_j(d)`` with ``q_j`` the uniform density
    ``1 / (2 pi)``, the peak density (:func:`_peak_density`) and the environment proxy
    ``luminance(E(d)) / Z`` (0 in a pole band), the environment's directions times their
    ``q / p_env``. ``rows`` and ``block`` as :func:`lighting_matrix_reference`.
    """
    rows = np.arange(len(obs)) if rows is None else np.asarray(rows)
    offsets = hemisphere_offsets(len(obs), seed)
    counts = strategy_counts(n_dirs)
    n_env = counts["environment"]
    pool = np.array(environment_pool(probe, n_env, seed, stream=stream)).reshape(ENV_SHIFTS, n_env, 8)
    env = environment_proxy(probe)
    z = float(np.sum(luminance(probe.data) * probe.solid_angles()))
    axis = np.asarray(env.axis)
    out = np.zeros((len(rows), n_t * n_s, 3))
    for start in range(0, len(rows), block):
        sel = rows[start:start + block]
        n, v = _unit(obs.normals[sel]), _unit(obs.views[sel])
        x, y, wo = row_frames(n, v)
        shift_u, shift_v = offsets[sel, 0].astype(np.float64), offsets[sel, 1].astype(np.float64)
        # uniform: cos theta = u1, phi = 2 pi u2
        u1, u2 = _lattice(counts["uniform"], shift_u, shift_v)
        r = np.sqrt(np.clip(1.0 - u1 * u1, 0.0, None))
        uniform = np.stack([r * np.cos(2.0 * np.pi * u2), r * np.sin(2.0 * np.pi * u2), u1], axis=-1)
        # peak: theta_h = (pi / 2) (T u1)^2, phi_h = 2 pi u2, the view mirrored about h
        u1, u2 = _lattice(counts["peak"], shift_u, shift_v)
        theta_h = 0.5 * np.pi * (PEAK_T_MAX * u1) ** 2
        h = np.stack([np.sin(theta_h) * np.cos(2.0 * np.pi * u2), np.sin(theta_h) * np.sin(2.0 * np.pi * u2),
                      np.cos(theta_h)], axis=-1)
        peak = 2.0 * np.sum(h * wo[:, None, :], axis=-1, keepdims=True) * h - wo[:, None, :]
        local = np.concatenate([uniform, peak], axis=1)
        world = x[:, None, :] * local[..., :1] + y[:, None, :] * local[..., 1:2] + n[:, None, :] * local[..., 2:]
        # environment: the pool entry of the row's slot, frac(4096 shift_1) in 64 slots
        fine = offsets[sel, 0].astype(np.float64) * 4096.0
        slot = np.minimum(((fine - np.floor(fine)) * ENV_SHIFTS).astype(int), ENV_SHIFTS - 1)
        pooled = pool[slot]                                                   # (b, K_e, 8)
        env_world, env_pdf = _unit(pooled[..., :3].astype(np.float64)), pooled[..., 3].astype(np.float64)
        dirs = np.concatenate([world, env_world], axis=1)                     # (b, K, 3)
        is_env = np.arange(dirs.shape[1]) >= world.shape[1]
        cos_u = np.einsum("bkj,bj->bk", dirs, n)
        radiance = np.stack([probe.eval(d) for d in dirs]).astype(np.float64)
        proxy = luminance(radiance) / z
        along = dirs @ axis
        proxy = np.where((along > env.cos_top) | (-along > env.cos_bottom), 0.0, proxy)
        wi = np.stack([np.einsum("bkj,bj->bk", dirs, a) for a in (x, y, n)], axis=-1)
        density = (counts["uniform"] / (2.0 * np.pi) + counts["peak"] * _peak_density(wi, wo[:, None, :])
                   + n_env * proxy)
        ratio = np.ones_like(proxy)
        ratio[:, is_env] = np.divide(proxy[:, is_env], env_pdf, out=np.zeros_like(env_pdf), where=env_pdf > 0)
        lit = (cos_u > 0) & (density > 0)
        weight = np.where(lit, cos_u * ratio / np.where(lit, density, 1.0), 0.0)
        _splat(out, start, n, v, dirs, radiance * weight[..., None], n_t, n_s)
    return out
