"""The light directions of each row of the lighting matrix (numpy reference of the kernels).

A spherical Fibonacci lattice, uniform in solid angle, on the half of the normal's
hemisphere on one side of the view/normal plane, shifted per row by a seeded random
offset (a Cranley-Patterson rotation), plus the mirror image of every direction across
that plane (the fold of the paper's Fig. 4). The Dr.Jit kernels
(:mod:`mi_bivariate.lighting.kernels`) generate exactly these directions; the functions
here define them and serve as their numpy reference.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np

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

