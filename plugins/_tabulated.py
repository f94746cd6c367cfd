"""Shared machinery of the tabulated BSDF plugins: half-vector importance sampling.

Both plugins (``bivariate`` and ``merl``) sample a mixture of two strategies:

- cosine-weighted hemisphere sampling, which covers the diffuse part and every
  direction the other strategy misses;
- half-vector sampling from a tabulated 1D density over theta_h derived from
  the table's glossy excess over its typical level (phi_h uniform), followed
  by a mirror reflection of the view direction about the half vector.

The theta_h density is parameterised by ``x = 1 - cos(theta_h)`` so that the
solid angle of half vectors is ``d omega_h = dx dphi_h``: the density per
steradian is ``p_x(x) / (2 pi)`` without a ``1 / sin(theta_h)`` singularity at
the specular peak. Its nodes follow the st map's t axis (``theta_h = pi t^2 /
2``), which puts most of them near the peak where sharp lobes need them. The
mixture pdf of an outgoing direction ``wo`` given ``wi`` is::

    p(wo) = p_c cos(theta_o) / pi + (1 - p_c) p_h(h) / (4 |wo . h|)

The numpy half (:func:`half_vector_profile`) runs once per table change; the
Dr.Jit half (:class:`HalfVectorSampler`) runs inside renders and is written
for symbolic evaluation (no host round trips), so it works unchanged on the
``llvm_ad_rgb`` and ``cuda_ad_rgb`` variants.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from typing import Any, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.common import luminance
from mi_bivariate.errors import InputError, InputWarning

#: Luminance weights (Rec. 709) used to turn RGB tables into one density.

#: Mixture weight of cosine sampling is clamped to this range, so neither
#: strategy is ever switched off (robust to tables that are mostly one or
#: the other but not quite).
COSINE_WEIGHT_RANGE = (0.1, 0.9)

#: Number of fine sub-intervals per table t-interval in the theta_h density.
UPSAMPLE = 8


@dataclass(frozen=True)
class HalfVectorProfile:
    """Host-side description of the sampling mixture.

    Attributes:
        x_nodes: ``(K,) float64`` strictly increasing nodes of ``x = 1 - cos(theta_h)``
            in [0, 1].
        density: ``(K,) float64`` unnormalised, non-negative density over x at the nodes
            (piecewise linear in between); all zero means "no glossy part".
        cosine_weight: probability ``p_c`` of choosing cosine sampling.
    """

    x_nodes: np.ndarray
    density: np.ndarray
    cosine_weight: float


def x_from_theta_h(theta_h: np.ndarray) -> np.ndarray:
    """``1 - cos(theta_h)`` computed as ``2 sin^2(theta_h / 2)`` (no cancellation)."""
    return 2.0 * np.sin(0.5 * theta_h) ** 2


def half_vector_profile(luminance: np.ndarray, t_nodes: np.ndarray, s_nodes: np.ndarray,
                        cosine_only: bool = False) -> HalfVectorProfile:
    """Build the sampling mixture from a bivariate luminance table.

    Args:
        luminance: ``(n_t, n_s)`` non-negative BRDF luminance in 1/sr on the st grid
            (rows theta_h, columns theta_d); missing entries already replaced.
        t_nodes: ``(n_t,)`` t coordinates of the rows (``theta_h = pi t^2 / 2``).
        s_nodes: ``(n_s,)`` s coordinates of the columns (``theta_d = pi s / 2``).
        cosine_only: force ``p_c = 1`` (pure cosine sampling; for comparisons).

    Returns:
        The mixture description: a theta_h density proportional to the glossy
        excess ``e(theta_h) cos(theta_h)`` (``e`` = the theta_d-averaged profile
        above its median) and ``p_c`` from the ratio of the two parts' albedos
        at normal incidence.
    """
    luminance = np.nan_to_num(np.asarray(luminance, dtype=np.float64), nan=0.0, posinf=0.0)
    luminance = np.clip(luminance, 0.0, None)
    theta_d = 0.5 * math.pi * np.asarray(s_nodes, dtype=np.float64)
    # Down-weight grazing theta_d, where Fresnel and missing data inflate values
    # that few directions see.
    w = np.cos(np.clip(theta_d, 0.0, 0.5 * math.pi)) + 1e-3
    profile = luminance @ w / w.sum()  # (n_t,)
    # The lobe is what rises above the profile's typical (median) level. The
    # minimum would count a gentle slope across the whole hemisphere as
    # "glossy" and spread the half-vector samples thin; for a near-mirror
    # material (specular-white-phenolic under grace_256) the median halves
    # the image variance. Whatever lies below is left to cosine sampling.
    diffuse = float(np.median(profile))
    excess = np.clip(profile - diffuse, 0.0, None)

    # Fine grid in t (the table is piecewise linear in t), extended to the
    # horizon so that every half vector of the upper hemisphere has support.
    t_nodes = np.asarray(t_nodes, dtype=np.float64)
    n_fine = UPSAMPLE * (len(t_nodes) - 1) + 1
    t_fine = np.linspace(0.0, 1.0, n_fine)
    e_fine = np.interp(t_fine, t_nodes, excess)
    theta_h = 0.5 * math.pi * t_fine * t_fine
    x = x_from_theta_h(theta_h)
    density = e_fine * np.cos(theta_h)
    # float32 must still see strictly increasing nodes near the peak.
    keep = np.concatenate([[True], np.diff(x.astype(np.float32)) > 0])
    x, density = x[keep], density[keep]

    albedo_diffuse = math.pi * diffuse
    # Glossy albedo at normal incidence: f cos(theta_o) d omega_o
    # = e(theta_h) cos(2 theta_h) 4 cos(theta_h) d omega_h, with d omega_h = 2 pi dx.
    integrand = e_fine * np.clip(np.cos(2.0 * theta_h), 0.0, None) * 4.0 * np.cos(theta_h)
    x_all = x_from_theta_h(theta_h)
    albedo_glossy = 2.0 * math.pi * float(np.sum(0.5 * (integrand[1:] + integrand[:-1]) * np.diff(x_all)))
    if cosine_only:
        p_c = 1.0
    elif albedo_glossy <= 0.0 or not np.any(density > 0):
        p_c = COSINE_WEIGHT_RANGE[1]
    else:
        p_c = float(np.clip(albedo_diffuse / (albedo_diffuse + albedo_glossy), *COSINE_WEIGHT_RANGE))
    if not np.any(density > 0):
        density = np.ones_like(x)  # unused weight, but keep a valid distribution
    return HalfVectorProfile(x_nodes=x, density=density, cosine_weight=p_c)


class HalfVectorSampler:
    """Dr.Jit side of the mixture: sample and evaluate directions (local frame).

    Construct after ``mi.set_variant``; holds a ``mi.IrregularContinuousDistribution``
    over ``x = 1 - cos(theta_h)``.
    """

    def __init__(self, profile: HalfVectorProfile):

        self.cosine_weight = float(profile.cosine_weight)
        # p_c and 1 - p_c as opaque variables, not literals: p_c follows the table, and a literal changed
        # by each update of an optimisation made every iteration compile its kernels anew (measured in
        # synthesis.optimise_table on blue-acrylic: 2 kernels an iteration, 0.35 -> 1.7 s, once p_c left its clamp).
        self._p_cosine = dr.opaque(mi.Float, self.cosine_weight)
        self._p_half = dr.opaque(mi.Float, 1.0 - self.cosine_weight)
        self.distribution = mi.IrregularContinuousDistribution(
            mi.Float(profile.x_nodes.astype(np.float32)), mi.Float(profile.density.astype(np.float32)))

    def sample(self, wi, sample1, sample2) -> Tuple[object, object]:
        """Sample an outgoing direction.

        Args:
            wi: ``mi.Vector3f`` view direction, local frame.
            sample1: ``mi.Float`` uniform variate choosing the strategy.
            sample2: ``mi.Point2f`` uniform variates for the direction.

        Returns:
            ``(wo: mi.Vector3f, cosine: mi.Bool)``: the direction (may lie below
            the horizon when the reflection does) and which strategy produced it.
        """
        cosine = sample1 < self._p_cosine
        wo_cosine = mi.warp.square_to_cosine_hemisphere(sample2)

        x = self.distribution.sample(sample2.x)
        cos_h = 1.0 - x
        sin_h = dr.safe_sqrt(x * (2.0 - x))
        sin_phi, cos_phi = dr.sincos(dr.two_pi * sample2.y)
        h = mi.Vector3f(sin_h * cos_phi, sin_h * sin_phi, cos_h)
        wo_half = mi.reflect(wi, h)  # 2 (wi . h) h - wi
        return dr.select(cosine, wo_cosine, wo_half), cosine

    def pdf(self, wi, wo):
        """Mixture density of ``wo`` (solid angle, local frame) given ``wi``: ``mi.Float``.

        Zero when either direction is at or below the horizon.
        """
        cos_o = mi.Frame3f.cos_theta(wo)
        valid = (mi.Frame3f.cos_theta(wi) > 0.0) & (cos_o > 0.0)
        h = dr.normalize(wi + wo)
        # 1 - h.z without cancellation near the peak: rho^2 / (1 + h.z).
        rho2 = h.x * h.x + h.y * h.y
        x = rho2 / (1.0 + h.z)
        p_h = self.distribution.eval_pdf_normalized(x, valid) * dr.inv_two_pi
        dot = dr.abs(dr.dot(wo, h))
        p_half = dr.select(dot > 0.0, p_h / (4.0 * dot), 0.0)
        p = self._p_cosine * cos_o * dr.inv_pi + self._p_half * p_half
        return dr.select(valid, p, 0.0)


def make_tabulated_bsdf_base():
    """Build the common ``mi.BSDF`` subclass for the active variant.

    The base reads the shared properties (``sampling``, ``interpolation``,
    ``filename`` / ``table``), exposes ``table`` as the differentiable
    parameter and rebuilds the sampler when it changes. A plugin writes only
    what is its own:

    - ``plugin_name``, ``file_suffix``, ``interpolations`` (accepted modes,
      default first) and ``table_ndim`` (the table tensor's rank, channels last);
    - ``read_file(filename) -> ndarray`` and ``from_array(array) -> ndarray``
      (the ``filename`` and ``table`` properties; raise ``InputError``);
    - ``profile_values(host) -> (values, theta_h_nodes, theta_d_nodes)`` for the
      half-vector density;
    - ``_eval_brdf(wi, wo) -> mi.Color3f`` (the value in 1/sr, no cosine, of ``self.lookup``: the
      table as the renders use it);
    - optionally ``updated_table(table) -> mi.TensorXf``: a table set through ``mi.traverse`` made
      what the renders use (checked, filled; gradients kept), ``self.lookup``.

    Defined in a function because ``mi.BSDF`` only exists once a variant is set.
    """
    class TabulatedBSDF(mi.BSDF):
        """One-sided reflection BSDF given by a table; mixture importance sampling."""

        plugin_name = "tabulated"
        file_suffix = ""
        interpolations: Tuple[str, ...] = ("linear",)
        table_ndim = 3

        def __init__(self, props: mi.Properties):
            mi.BSDF.__init__(self, props)
            if not dr.is_jit_v(mi.Float):  # the table lookups and samplers are written for wide arrays
                raise InputError(self.plugin_name, f"the plugin needs a JIT variant, not {mi.variant()}",
                                 "use llvm_ad_rgb or cuda_ad_rgb: mi.set_variant or "
                                 "mi_bivariate.variants.ensure_variant")
            sampling = props.get("sampling", "table")
            if sampling not in ("table", "cosine"):
                raise InputError(self.plugin_name, f"sampling must be 'table' or 'cosine', got {sampling!r}")
            self.sampling = sampling
            interpolation = props.get("interpolation", self.interpolations[0])
            if interpolation not in self.interpolations:
                raise InputError(self.plugin_name, f"interpolation must be "
                                 f"{' or '.join(repr(m) for m in self.interpolations)}, got {interpolation!r}")
            self.interpolation = interpolation
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags
            self.sampler: HalfVectorSampler | None = None
            if "filename" in props:
                table = self.read_file(resolve_path(str(props["filename"])))
            elif "table" in props:
                table = self.from_array(bitmap_to_array(props["table"], f"{self.plugin_name} table"))
            else:
                raise InputError(self.plugin_name, f"the BSDF needs a 'filename' ({self.file_suffix}) or a 'table' "
                                                  "(mi.Bitmap) property")
            self.table = mi.TensorXf(table)  # the parameter: mi.traverse writes into this object in place
            # What eval reads, the table as the renders use it: another handle on the same values, so that
            # an update refused by updated_table leaves the renders with the last good table.
            self.lookup = mi.TensorXf(self.table)
            self._rebuild()

        def _check_shape(self) -> None:
            shape = tuple(self.table.shape)
            if len(shape) != self.table_ndim or shape[-1] != 3 or not self.valid_shape(shape):
                raise InputError(self.plugin_name, f"table has shape {shape}, which this plugin cannot use")

        def _rebuild(self) -> None:
            """Check the table's shape and rebuild the sampler from the table the renders use."""
            self._check_shape()
            values, theta_h_nodes, theta_d_nodes = self.profile_values(dr.detach(self.lookup).numpy())
            self.sampler = HalfVectorSampler(half_vector_profile(luminance(values), theta_h_nodes, theta_d_nodes,
                                                                 cosine_only=self.sampling == "cosine"))

        def valid_shape(self, shape: Tuple[int, ...]) -> bool:
            return True

        def traverse(self, callback: mi.TraversalCallback) -> None:
            callback.put("table", self.table, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys: list) -> None:
            self._check_shape()
            self.lookup = mi.TensorXf(self.updated_table(self.table))  # a handle of its own (see __init__)
            self._rebuild()

        def updated_table(self, table: mi.TensorXf) -> mi.TensorXf:
            """A table set through ``mi.traverse`` as the renders use it (gradients kept). Here: refused
            (the renders keep the last good table) unless finite; negative values rendered as 0, with a
            warning (a reflectance cannot be negative; their nodes get no gradient)."""
            host = dr.detach(table).numpy()
            if not np.all(np.isfinite(host)):
                raise InputError(self.plugin_name, "the table set through mi.traverse holds NaN or infinite values",
                                 "set a finite table; until then the renders keep the last good one")
            if np.any(host < 0.0):
                warnings.warn(f"{self.plugin_name}: the table set through mi.traverse has negative values (min "
                              f"{host.min():g} 1/sr), rendered as 0 (optimise its logarithm, or clamp it)",
                              InputWarning, stacklevel=2)
                return dr.maximum(table, 0.0)
            return table

        def _enabled(self, ctx: mi.BSDFContext) -> bool:
            return ctx.is_enabled(mi.BSDFFlags.GlossyReflection) or ctx.is_enabled(mi.BSDFFlags.DiffuseReflection)

        def _eval_cos(self, si: mi.SurfaceInteraction3f, wo: mi.Vector3f, active) -> mi.Color3f:
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            active = active & (cos_i > 0.0) & (cos_o > 0.0)
            value = self._eval_brdf(si.wi, wo) * cos_o
            return dr.select(active, value, 0.0)

        def eval(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Color3f(0.0)
            return self._eval_cos(si, wo, active)

        def pdf(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Float(0.0)
            return dr.select(active, self.sampler.pdf(si.wi, wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Color3f(0.0), mi.Float(0.0)
            return self._eval_cos(si, wo, active), dr.select(active, self.sampler.pdf(si.wi, wo), 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = dr.zeros(mi.BSDFSample3f)
            if not self._enabled(ctx):
                return bs, mi.Color3f(0.0)
            wo, cosine = self.sampler.sample(si.wi, sample1, sample2)
            pdf = self.sampler.pdf(si.wi, wo)
            active = active & (pdf > 0.0)
            bs.wo = wo
            bs.pdf = dr.select(active, pdf, 0.0)
            bs.eta = 1.0
            bs.sampled_type = dr.select(cosine, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                                        mi.UInt32(+mi.BSDFFlags.GlossyReflection))
            bs.sampled_component = mi.UInt32(0)
            value = self._eval_cos(si, wo, active)
            weight = dr.select(active, value / dr.maximum(pdf, 1e-30), 0.0)
            return bs, weight

        def to_string(self) -> str:
            return (f"{type(self).__name__}[shape={tuple(self.table.shape)}, interpolation={self.interpolation!r}, "
                    f"sampling={self.sampling!r}, p_cosine={self.sampler.cosine_weight:.3f}]")

    return TabulatedBSDF


def resolve_path(filename: str) -> str:
    """Where a ``filename`` property's file is: as given when it exists from the working directory,
    else through Mitsuba's file resolver (beside the scene file being loaded, as the built-in plugins
    find theirs). The working directory first: the resolver's copy of it dates from Mitsuba's import."""
    if os.path.exists(filename):
        return filename
    return str(mi.file_resolver().resolve(filename))


def bitmap_to_array(bitmap: Any, source: str) -> np.ndarray:
    """A ``mi.Bitmap`` as a ``(H, W, 3) float32`` array (InputError if not RGB)."""
    if not isinstance(bitmap, mi.Bitmap):
        raise InputError(source, f"'table' must be a mitsuba.Bitmap, got {type(bitmap).__name__}",
                         "numpy arrays cannot be passed to Python plugins; use mi.Bitmap(array)")
    array = np.array(bitmap, dtype=np.float32, copy=True)
    if array.ndim == 2:
        array = array[..., None]
    if array.shape[-1] != 3:
        raise InputError(source, f"'table' bitmap must be RGB, got {array.shape[-1]} channel(s)")
    return array

