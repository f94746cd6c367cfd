"""Rusinkiewicz half/difference angles and the paper's st map.

Every function here is written once and works on two kinds of input:

- numpy: directions are ``(..., 3)`` float arrays, angles are ``(...)`` arrays;
- Dr.Jit: directions are ``mi.Vector3f`` (or any Dr.Jit 3-vector), angles are
  ``mi.Float``; this is what the BSDF plugins and the lighting matrix use.

Conventions: all angles in radians; theta_h, theta_d in
[0, pi/2] for directions in the upper hemisphere; phi_h, phi_d in (-pi, pi] as
returned by ``atan2``; :func:`fold_phi_d` maps phi_d to [0, pi) as MERL does
(reciprocity makes an isotropic BRDF pi-periodic in phi_d).

Precision: theta_h and theta_d are computed with ``atan2`` of a sine and a
cosine, never ``acos``. In float32, ``acos(h.z)`` resolves only ~22 distinct
values of theta_h below 1.6e-3 rad, which smears the specular peak across
almost half a t-cell.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

PI = math.pi
HALF_PI = 0.5 * math.pi

#: Named regions of the (theta_h, theta_d) domain, ``(name, axis, low, high)`` in degrees: near the
#: specular peak, near retro-reflection and at grazing differences. Adequacy counts how well they
#: are lit; metrics splits the BRDF error by them.
ST_REGIONS: Tuple[Tuple[str, str, float, float], ...] = (
    ("specular", "theta_h", 0.0, 2.0),
    ("retro", "theta_d", 0.0, 10.0),
    ("grazing", "theta_d", 75.0, 90.0),
)

_NUMPY_OPS = SimpleNamespace(
    sqrt=np.sqrt,
    atan2=np.arctan2,
    sin=np.sin,
    cos=np.cos,
    abs=np.abs,
    maximum=np.maximum,
    where=np.where,
    floor=np.floor,
)


def _drjit_ops() -> SimpleNamespace:

    return SimpleNamespace(
        sqrt=dr.sqrt,
        atan2=dr.atan2,
        sin=dr.sin,
        cos=dr.cos,
        abs=dr.abs,
        maximum=dr.maximum,
        where=lambda c, a, b: dr.select(c, a, b),
        floor=dr.floor,
    )


def _is_drjit(x: Any) -> bool:
    mod = type(x).__module__
    return mod.startswith("drjit") or mod.startswith("mitsuba")


def _ops(x: Any) -> SimpleNamespace:
    return _drjit_ops() if _is_drjit(x) else _NUMPY_OPS


def _components(v: Any) -> Tuple[Any, Any, Any]:
    if _is_drjit(v):
        return v.x, v.y, v.z
    v = np.asarray(v)
    if v.shape[-1] != 3:
        raise ValueError(f"expected directions of shape (..., 3), got {v.shape}")
    return v[..., 0], v[..., 1], v[..., 2]


def _vector(like: Any, x: Any, y: Any, z: Any) -> Any:
    if _is_drjit(like):
        return type(like)(x, y, z)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def half_diff_from_dirs(wi: Any, wo: Any) -> Tuple[Any, Any, Any, Any]:
    """Rusinkiewicz angles of a direction pair in the local shading frame.

    Args:
        wi: incident (light) directions, unit, local frame (z = normal).
        wo: outgoing (view) directions, unit, local frame.

    Returns:
        ``(theta_h, phi_h, theta_d, phi_d)`` in radians. theta_d is the angle
        between wi and the half vector; phi_d is wi's azimuth in the frame of
        the half vector (Rusinkiewicz 1998).
    """
    op = _ops(wi)
    ix, iy, iz = _components(wi)
    ox, oy, oz = _components(wo)
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    norm = op.sqrt(hx * hx + hy * hy + hz * hz)
    norm = op.maximum(norm, 1e-30)
    hx, hy, hz = hx / norm, hy / norm, hz / norm

    rho = op.sqrt(hx * hx + hy * hy)
    theta_h = op.atan2(rho, hz)
    phi_h = op.atan2(hy, hx)
    # cos/sin of phi_h straight from h: no trigonometric round trip, and a
    # well-defined frame (phi_h = 0) when h is the normal.
    safe = rho > 1e-12
    inv_rho = 1.0 / op.maximum(rho, 1e-30)
    cp = op.where(safe, hx * inv_rho, 1.0)
    sp = op.where(safe, hy * inv_rho, 0.0)
    ct, st = hz, rho

    # d = R_y(-theta_h) R_z(-phi_h) wi
    ax = ix * cp + iy * sp
    ay = -ix * sp + iy * cp
    dx = ax * ct - iz * st
    dy = ay
    dz = ax * st + iz * ct

    theta_d = op.atan2(op.sqrt(dx * dx + dy * dy), dz)
    phi_d = op.atan2(dy, dx)
    return theta_h, phi_h, theta_d, phi_d


def dirs_from_half_diff(theta_h: Any, phi_h: Any, theta_d: Any, phi_d: Any) -> Tuple[Any, Any]:
    """Inverse of :func:`half_diff_from_dirs`.

    Returns:
        ``(wi, wo)``: numpy ``(..., 3)`` arrays, or ``mi.Vector3f`` for Dr.Jit
        input. Either may point below the horizon for invalid angle tuples.
    """
    op = _ops(theta_h)
    sd, cd = op.sin(theta_d), op.cos(theta_d)
    dx, dy, dz = sd * op.cos(phi_d), sd * op.sin(phi_d), cd
    st, ct = op.sin(theta_h), op.cos(theta_h)
    sp, cp = op.sin(phi_h), op.cos(phi_h)
    # wi = R_z(phi_h) R_y(theta_h) d
    bx = dx * ct + dz * st
    bz = -dx * st + dz * ct
    ix = bx * cp - dy * sp
    iy = bx * sp + dy * cp
    iz = bz
    hx, hy, hz = st * cp, st * sp, ct
    two_cos = 2.0 * (ix * hx + iy * hy + iz * hz)
    ox, oy, oz = two_cos * hx - ix, two_cos * hy - iy, two_cos * hz - iz
    like = _like_vector(theta_h)
    return _vector(like, ix, iy, iz), _vector(like, ox, oy, oz)


def _like_vector(x: Any) -> Any:
    if _is_drjit(x):

        return mi.Vector3f(0.0)
    return np.zeros(3)


def fold_phi_d(phi_d: Any) -> Any:
    """Map phi_d to [0, pi), using the reciprocity period of isotropic BRDFs."""
    op = _ops(phi_d)
    folded = phi_d - PI * op.floor(phi_d / PI)
    return op.where(folded >= PI, folded - PI, folded)


def st_from_half_diff(theta_h: Any, theta_d: Any) -> Tuple[Any, Any]:
    """The paper's st map: ``s = 2 theta_d / pi``, ``t = sqrt(2 theta_h / pi)``."""
    op = _ops(theta_h)
    s = theta_d * (2.0 / PI)
    t = op.sqrt(op.maximum(theta_h * (2.0 / PI), 0.0))
    return s, t


def half_diff_from_st(s: Any, t: Any) -> Tuple[Any, Any]:
    """Inverse st map: ``theta_h = pi t^2 / 2``, ``theta_d = pi s / 2``."""
    theta_h = t * t * HALF_PI
    theta_d = s * HALF_PI
    return theta_h, theta_d


def st_from_dirs(wi: Any, wo: Any) -> Tuple[Any, Any]:
    """st coordinates of a direction pair (local frame)."""
    theta_h, _, theta_d, _ = half_diff_from_dirs(wi, wo)
    return st_from_half_diff(theta_h, theta_d)


def grid_nodes(n: int) -> np.ndarray:
    """Node coordinates of an n-node st axis: ``i / (n - 1)``, ``(n,) float64``."""
    if n < 2:
        raise ValueError(f"an st axis needs at least 2 nodes, got {n}")
    return np.linspace(0.0, 1.0, n)
