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
either direction is at or below the horizon.

Differentiable parameter: ``table`` (``mi.TensorXf``, ``(n_t, n_s, 3)``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mi_bivariate.bivariate import validate_table
from mi_bivariate.errors import InputError

from ._tabulated import half_vector_profile, luminance, make_tabulated_bsdf_base


def bitmap_to_array(bitmap: Any, source: str) -> np.ndarray:
    """A ``mi.Bitmap`` as a ``(H, W, 3) float32`` array (InputError if not RGB)."""
    import mitsuba as mi

    if not isinstance(bitmap, mi.Bitmap):
        raise InputError(source, f"'table' must be a mitsuba.Bitmap, got {type(bitmap).__name__}",
                         "numpy arrays cannot be passed to Python plugins; use mi.Bitmap(array)")
    array = np.array(bitmap, dtype=np.float32, copy=True)
    if array.ndim == 2:
        array = array[..., None]
    if array.shape[-1] != 3:
        raise InputError(source, f"'table' bitmap must be RGB, got {array.shape[-1]} channel(s)")
    return array


def load_bivariate_table(props: Any) -> np.ndarray:
    """The ``(n_t, n_s, 3) float32`` table named by a plugin's properties."""
    if "filename" in props:
        from mi_bivariate.bivariate import BivariateBRDF

        filename = str(props["filename"])
        table = BivariateBRDF.load(filename).table
        return validate_table(table, filename)
    if "table" in props:
        return validate_table(bitmap_to_array(props["table"], "bivariate table"), "bivariate table")
    raise InputError("bivariate", "the BSDF needs a 'filename' (.npz) or a 'table' (mi.Bitmap) property")


def make_bivariate_bsdf():
    """Build the ``bivariate`` BSDF class for the active variant."""
    import drjit as dr
    import mitsuba as mi

    from mi_bivariate.coordinates import st_from_dirs

    TabulatedBSDF = make_tabulated_bsdf_base()

    class BivariateBSDF(TabulatedBSDF):
        plugin_name = "bivariate"

        def __init__(self, props: mi.Properties):
            TabulatedBSDF.__init__(self, props)
            interpolation = props.get("interpolation", "linear")
            if interpolation != "linear":
                raise InputError("bivariate", f"interpolation must be 'linear' (bilinear in s, t), "
                                              f"got {interpolation!r}")
            self.table = mi.TensorXf(load_bivariate_table(props))
            self._rebuild()

        def _rebuild(self) -> None:
            shape = tuple(self.table.shape)
            if len(shape) != 3 or shape[2] != 3 or shape[0] < 2 or shape[1] < 2:
                raise ValueError(f"bivariate: table must have shape (n_t, n_s, 3), got {shape}")
            self.n_t, self.n_s = int(shape[0]), int(shape[1])
            host = np.asarray(dr.detach(self.table).numpy(), np.float64)
            profile = half_vector_profile(luminance(host), np.linspace(0.0, 1.0, self.n_t),
                                          np.linspace(0.0, 1.0, self.n_s),
                                          cosine_only=self.sampling == "cosine")
            self._set_profile(profile)

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
            flat = self.table.array
            c00 = dr.gather(mi.Color3f, flat, base)
            c01 = dr.gather(mi.Color3f, flat, base + 1)
            c10 = dr.gather(mi.Color3f, flat, base + self.n_s)
            c11 = dr.gather(mi.Color3f, flat, base + self.n_s + 1)
            return dr.lerp(dr.lerp(c00, c01, fu), dr.lerp(c10, c11, fu), fv)

        def traverse(self, callback: mi.TraversalCallback) -> None:
            callback.put("table", self.table, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: list[str]) -> None:
            self._rebuild()

        def to_string(self) -> str:
            return (f"BivariateBSDF[n_t={self.n_t}, n_s={self.n_s}, sampling={self.sampling!r}, "
                    f"p_cosine={self.sampler.cosine_weight:.3f}]")

    return BivariateBSDF
