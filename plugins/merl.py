"""The ``merl`` BSDF: an isotropic BRDF tabulated on the MERL grid.

Properties:
    filename: a MERL ``.binary`` file; or
    table: ``mi.Bitmap`` RGB float, H = 90 * 90 (theta_h major, then theta_d), W = 180
        (phi_d), values in 1/sr (:meth:`mi_bivariate.merl.MERLBRDF.to_bitmap`).
    interpolation: ``"nearest"`` (default; MERL's floor indexing) or ``"linear"``
        (trilinear between nodes, phi_d periodic with period pi, theta axes clamped).
    sampling: ``"table"`` (default) or ``"cosine"``.

Nodes (radians): theta_h_i = (i/90)^2 pi/2, theta_d_j = j/90 pi/2, phi_d_k = k/180 pi.
Missing samples (NaN or negative) and nodes whose configuration lies below the
horizon (which MERL never measures) are filled with the phi_d mean of the valid
nodes of the same (theta_h, theta_d), or 0 where there is none: lookups near
the horizon then continue the data instead of dropping to zero, and a
bivariate BRDF stored as a MERL table is reproduced exactly.

One-sided like ``diffuse``: zero when either direction is at or below the horizon (wrap it in
``twosided`` for both sides). A relative ``filename`` is read from the working directory, else found
as Mitsuba finds its files (beside the scene file being loaded).

Importance sampling uses the phi_d-averaged table (a 90 x 90 bivariate table).
Differentiable parameter: ``table`` (``mi.TensorXf``, ``(90, 90, 180, 3)``). A table set through
``mi.traverse`` is filled as above (the filled nodes get no gradient) and refused if it holds
infinities (the renders keep the last good table).
"""

from __future__ import annotations

import math
from typing import Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.coordinates import fold_phi_d, half_diff_from_dirs
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERLBRDF, geometric_mask
from mi_bivariate.plugins._tabulated import make_tabulated_bsdf_base

N_THETA_H, N_THETA_D, N_PHI_D = 90, 90, 180


def fill_missing(table: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid entries by the phi_d mean of the valid ones (0 where none).

    Args:
        table: ``(90, 90, 180, 3) float32``, 1/sr (anything where ``valid`` is False).
        valid: ``(90, 90, 180) bool``.

    Returns:
        ``(90, 90, 180, 3) float32`` with every entry finite and non-negative.
    """
    clean = np.where(valid[..., None], table, np.float32(0.0))
    count = valid.sum(axis=2, dtype=np.float32)[..., None]  # (90, 90, 1)
    mean = clean.sum(axis=2, dtype=np.float64) / np.maximum(count, 1.0)  # (90, 90, 3)
    return np.where(valid[..., None], clean, mean[:, :, None, :].astype(np.float32))


def valid_nodes(table: np.ndarray, source: str) -> np.ndarray:
    """``(90, 90, 180) bool``: the measured (finite, non-negative) nodes above the horizon of a
    ``(90, 90, 180, 3)`` MERL table (1/sr); refused when it holds infinities or no such node."""
    if table.shape != (N_THETA_H, N_THETA_D, N_PHI_D, 3):
        raise InputError(source, f"a MERL table must have shape (90, 90, 180, 3), got {table.shape}")
    if np.isinf(table).any():
        raise InputError(source, "MERL table holds infinite values",
                         "a BRDF whose values overflow float32 cannot be tabulated: an analytic lobe needs a "
                         "larger roughness, a file is corrupt")
    measured = (table >= 0.0).all(axis=-1)  # False for NaN (missing) and negative (missing) entries
    valid = measured & geometric_mask()
    if not valid.any():
        raise InputError(source, "MERL table has no valid (finite, non-negative, above-horizon) sample")
    return valid


def prepare_merl_table(table: np.ndarray, source: str) -> np.ndarray:
    """Validate a ``(90, 90, 180, 3)`` MERL table (1/sr) and fill its missing entries."""
    table = np.asarray(table, dtype=np.float32)
    return fill_missing(table, valid_nodes(table, source))


def make_merl_bsdf():
    """Build the ``merl`` BSDF class for the active variant."""
    TabulatedBSDF = make_tabulated_bsdf_base()

    class MERLBSDF(TabulatedBSDF):
        plugin_name = "merl"
        file_suffix = ".binary"
        interpolations = ("nearest", "linear")
        table_ndim = 4

        def read_file(self, filename: str) -> np.ndarray:
            return prepare_merl_table(MERLBRDF.read(filename).table, filename)

        def from_array(self, array: np.ndarray) -> np.ndarray:
            if array.shape != (N_THETA_H * N_THETA_D, N_PHI_D, 3):
                raise InputError("merl table", f"bitmap must be 8100 x 180 (H x W) RGB, got {array.shape}")
            return prepare_merl_table(array.reshape(N_THETA_H, N_THETA_D, N_PHI_D, 3), "merl table")

        def updated_table(self, table: mi.TensorXf) -> mi.TensorXf:
            """A table set through ``mi.traverse`` filled like the ``table`` property (missing and
            below-horizon nodes from the phi_d mean of the valid ones); the valid nodes keep their
            gradients, the filled ones have none. Refused (the renders keep the last good table) if it
            holds infinities. Each update reads the 4.4 M values back to fill them (~0.1 s on a CPU)."""
            host = dr.detach(table).numpy()
            valid = valid_nodes(host, self.plugin_name)
            filled = fill_missing(host, valid)
            if np.array_equal(filled, host):
                return table
            keep = mi.TensorXb(np.ascontiguousarray(np.broadcast_to(valid[..., None], host.shape)))
            return dr.select(keep, table, mi.TensorXf(filled))

        def valid_shape(self, shape: Tuple[int, ...]) -> bool:
            return shape == (N_THETA_H, N_THETA_D, N_PHI_D, 3)

        def profile_values(self, host: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
            nodes = np.arange(N_THETA_H) / N_THETA_H
            return host.mean(axis=2, dtype=np.float64), nodes, nodes

        def _coordinates(self, wi: mi.Vector3f, wo: mi.Vector3f) -> Tuple[mi.Float, mi.Float, mi.Float]:
            """Continuous node coordinates (node k at k) along theta_h, theta_d, phi_d."""
            theta_h, _, theta_d, phi_d = half_diff_from_dirs(wo, wi)  # light first, as MERL
            u_h = dr.sqrt(dr.maximum(theta_h, 0.0) * (2.0 / math.pi)) * N_THETA_H
            u_d = dr.maximum(theta_d, 0.0) * (2.0 / math.pi) * N_THETA_D
            u_p = fold_phi_d(phi_d) * (1.0 / math.pi) * N_PHI_D
            return u_h, u_d, u_p

        def _gather(self, i_h: mi.UInt32, i_d: mi.UInt32, i_p: mi.UInt32) -> mi.Color3f:
            return dr.gather(mi.Color3f, self.lookup.array, (i_h * N_THETA_D + i_d) * N_PHI_D + i_p)

        def _eval_brdf(self, wi: mi.Vector3f, wo: mi.Vector3f) -> mi.Color3f:
            u_h, u_d, u_p = self._coordinates(wi, wo)
            if self.interpolation == "nearest":
                i_h = dr.minimum(mi.UInt32(dr.floor(u_h)), N_THETA_H - 1)
                i_d = dr.minimum(mi.UInt32(dr.floor(u_d)), N_THETA_D - 1)
                i_p = dr.minimum(mi.UInt32(dr.floor(u_p)), N_PHI_D - 1)
                return self._gather(i_h, i_d, i_p)
            u_h = dr.clip(u_h, 0.0, N_THETA_H - 1)
            u_d = dr.clip(u_d, 0.0, N_THETA_D - 1)
            h0 = dr.minimum(mi.UInt32(dr.floor(u_h)), N_THETA_H - 2)
            d0 = dr.minimum(mi.UInt32(dr.floor(u_d)), N_THETA_D - 2)
            p_floor = dr.floor(u_p)
            p0 = dr.minimum(mi.UInt32(p_floor), N_PHI_D - 1)
            p1 = dr.select(p0 + 1 >= N_PHI_D, 0, p0 + 1)  # phi_d is periodic (period pi)
            wh, wd, wp = u_h - mi.Float(h0), u_d - mi.Float(d0), u_p - p_floor
            result = mi.Color3f(0.0)
            for dh, w_h in ((0, 1.0 - wh), (1, wh)):
                for dd, w_d in ((0, 1.0 - wd), (1, wd)):
                    lo = self._gather(h0 + dh, d0 + dd, p0)
                    hi = self._gather(h0 + dh, d0 + dd, p1)
                    result += (w_h * w_d) * dr.lerp(lo, hi, wp)
            return result

    return MERLBSDF
