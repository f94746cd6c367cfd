"""The ``bivariate`` BSDF: an isotropic BRDF f(theta_h, theta_d) given by a table.

Properties:
    filename: a ``.npz`` written by :meth:`mi_bivariate.bivariate.BivariateBRDF.save`; or
    table: ``mi.Bitmap`` RGB float, H = n_t rows (theta_h), W = n_s columns (theta_d),
        values in 1/sr (:meth:`BivariateBRDF.to_bitmap`).
    sampling: ``"table"`` (default; cosine + tabulated half-vector mixture) or
        ``"cosine"`` (cosine-hemisphere only, for comparisons).
    interpolation: ``"linear"``, the only mode (accepted so that one scene file can
        serve both plugins).

The table's nodes sit at ``s, t = i / (n - 1)`` of the paper's st map
(``s = 2 theta_d / pi``, ``t = sqrt(2 theta_h / pi)``); values are bilinear in
(s, t) between nodes and clamped outside. One-sided like ``diffuse``: zero when
either direction is at or below the horizon (wrap it in ``twosided`` for both sides).
A relative ``filename`` is read from the working directory, else found as Mitsuba finds its files
(beside the scene file being loaded).

Differentiable parameter: ``table`` (``mi.TensorXf``, ``(n_t, n_s, 3)``); it may change the grid. A
table set through ``mi.traverse`` is refused if it holds NaN or infinities (the renders keep the last
good table), and its negative values are rendered as 0 with a warning (optimise its logarithm, as
:mod:`mi_bivariate.synthesis` does).
"""

from __future__ import annotations

from typing import Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.bivariate import BivariateBRDF, validate_table
from mi_bivariate.coordinates import st_from_dirs
from mi_bivariate.plugins._tabulated import make_tabulated_bsdf_base


def make_bivariate_bsdf():
    """Build the ``bivariate`` BSDF class for the active variant."""
    TabulatedBSDF = make_tabulated_bsdf_base()

    class BivariateBSDF(TabulatedBSDF):
        plugin_name = "bivariate"
        file_suffix = ".npz"
        interpolations = ("linear",)  # bilinear in (s, t); accepted so one scene file serves both plugins

        def read_file(self, filename: str) -> np.ndarray:
            return validate_table(BivariateBRDF.load(filename).table, filename)

        def from_array(self, array: np.ndarray) -> np.ndarray:
            return validate_table(array, "bivariate table")

        def valid_shape(self, shape: Tuple[int, ...]) -> bool:
            return shape[0] >= 2 and shape[1] >= 2

        def profile_values(self, host: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
            self.n_t, self.n_s = host.shape[:2]  # the grid follows the table (it may change via traverse)
            return host, np.linspace(0.0, 1.0, self.n_t), np.linspace(0.0, 1.0, self.n_s)

        def _eval_brdf(self, wi: mi.Vector3f, wo: mi.Vector3f) -> mi.Color3f:
            # Rusinkiewicz angles with the light direction first, as MERL does.
            s, t = st_from_dirs(wo, wi)
            u = dr.clip(s, 0.0, 1.0) * (self.n_s - 1)
            v = dr.clip(t, 0.0, 1.0) * (self.n_t - 1)
            i0 = dr.minimum(mi.UInt32(dr.floor(u)), self.n_s - 2)
            j0 = dr.minimum(mi.UInt32(dr.floor(v)), self.n_t - 2)
            fu = u - mi.Float(i0)
            fv = v - mi.Float(j0)
            base = j0 * self.n_s + i0
            flat = self.lookup.array
            c00 = dr.gather(mi.Color3f, flat, base)
            c01 = dr.gather(mi.Color3f, flat, base + 1)
            c10 = dr.gather(mi.Color3f, flat, base + self.n_s)
            c11 = dr.gather(mi.Color3f, flat, base + self.n_s + 1)
            return dr.lerp(dr.lerp(c00, c01, fu), dr.lerp(c10, c11, fu), fv)

    return BivariateBSDF
