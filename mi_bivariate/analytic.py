"""Closed-form isotropic BRDFs, for tests, round trips and the CLI.

Every model evaluates in 1/sr, RGB, numpy float64, and has two entry points:

- ``eval_dirs(wi, wo) -> (..., 3)``: unit directions ``(..., 3)`` in the local
  shading frame (z = normal); 0 where either direction is at or below the
  horizon;
- ``eval(theta_h, theta_d, phi_d) -> (..., 3)``: Rusinkiewicz angles (radians),
  i.e. ``eval_dirs`` of the pair built with phi_h = 0 (isotropy).

:class:`Lambertian` and :class:`BivariateLobe` are bivariate (functions of
theta_h, theta_d alone); :class:`CookTorranceGGX` and :class:`OrenNayar` are
not. :func:`analytic_from_spec` parses the CLI spelling, e.g.
``"ggx:alpha=0.1,specular=0.5,diffuse=0.2,0.1,0.05"``; :func:`to_merl`
tabulates any model on the MERL grid.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.coordinates import dirs_from_half_diff, half_diff_from_dirs
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERLBRDF

RGBLike = Union[float, Sequence[float], np.ndarray]


def _rgb(value: RGBLike, what: str) -> np.ndarray:
    rgb = np.asarray(value, np.float64).reshape(-1)
    if rgb.size == 1:
        rgb = np.repeat(rgb, 3)
    if rgb.size != 3 or not np.all(np.isfinite(rgb)) or np.any(rgb < 0.0):
        raise ValueError(f"{what} must be one or three finite non-negative values, got {value!r}")
    return rgb


def _fmt(values: np.ndarray) -> str:
    values = np.atleast_1d(values)
    if values.size == 3 and np.all(values == values[0]):
        values = values[:1]
    return ",".join(f"{v:g}" for v in values)


class AnalyticBRDF:
    """Base class: subclasses define ``_value(wi, wo)`` for directions above the horizon."""

    kind = "analytic"

    def _params(self) -> Dict[str, np.ndarray]:
        raise NotImplementedError

    @property
    def name(self) -> str:
        """A spec string that :func:`analytic_from_spec` parses back to this model."""
        return f"{self.kind}:" + ",".join(f"{k}={_fmt(v)}" for k, v in self._params().items())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    def _value(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def eval_dirs(self, wi, wo) -> np.ndarray:
        """BRDF of unit local-frame direction pairs ``(..., 3)`` -> ``(..., 3)`` 1/sr."""
        wi, wo = np.broadcast_arrays(np.asarray(wi, np.float64), np.asarray(wo, np.float64))
        up = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            value = self._value(wi, wo)
        return np.where(up[..., None], value, 0.0)

    def eval(self, theta_h, theta_d, phi_d) -> np.ndarray:
        """BRDF at Rusinkiewicz angles (radians, broadcast) -> ``(..., 3)`` 1/sr."""
        theta_h, theta_d, phi_d = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d)))
        wi, wo = dirs_from_half_diff(theta_h, np.zeros_like(theta_h), theta_d, phi_d)
        return self.eval_dirs(wi, wo)


class Lambertian(AnalyticBRDF):
    """``f = albedo / pi``."""

    kind = "lambertian"

    def __init__(self, albedo: RGBLike = 0.5):
        self.albedo = _rgb(albedo, "albedo")

    def _params(self):
        return {"albedo": self.albedo}

    def _value(self, wi, wo):
        return np.broadcast_to(self.albedo / math.pi, wi.shape[:-1] + (3,))


def fresnel_dielectric(cos_theta: np.ndarray, ior: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric (``ior > 1``) seen from outside."""
    c = np.clip(cos_theta, 0.0, 1.0)
    g = np.sqrt(ior * ior - 1.0 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


class CookTorranceGGX(AnalyticBRDF):
    """Diffuse + Cook-Torrance microfacet specular: GGX D, separable Smith G, dielectric Fresnel.

    ``f = diffuse / pi + specular * F(theta_d) D(theta_h) G1(wi) G1(wo) / (4 cos_i cos_o)``.
    ``ior=None`` drops the Fresnel factor (F = 1, for white-furnace checks). The
    specular term is Mitsuba's ``roughconductor`` (GGX, ``sample_visible``
    irrelevant for ``eval``) with a real index of refraction. Not bivariate: G
    depends on phi_d.
    """

    kind = "ggx"

    def __init__(self, albedo_diffuse: RGBLike = 0.0, specular: RGBLike = 1.0, alpha: float = 0.1,
                 ior: float | None = 1.5):
        self.albedo_diffuse = _rgb(albedo_diffuse, "diffuse")
        self.specular = _rgb(specular, "specular")
        self.alpha = float(alpha)
        if not (self.alpha > 0.0 and math.isfinite(self.alpha)):
            raise ValueError(f"alpha must be positive, got {alpha!r}")
        if ior is not None and not float(ior) > 1.0:
            raise ValueError(f"ior must be > 1, got {ior!r}")
        self.ior = None if ior is None else float(ior)

    def _params(self):
        params = {"diffuse": self.albedo_diffuse, "specular": self.specular, "alpha": np.array([self.alpha])}
        if self.ior is not None:
            params["ior"] = np.array([self.ior])
        return params

    def distribution(self, cos_theta_h: np.ndarray) -> np.ndarray:
        """GGX normal distribution D (1/sr), normalised so that ``int D cos dw = 1``."""
        a2 = self.alpha * self.alpha
        c2 = cos_theta_h * cos_theta_h
        return a2 / (math.pi * (c2 * (a2 - 1.0) + 1.0) ** 2)

    def smith_g1(self, w: np.ndarray, h: np.ndarray) -> np.ndarray:
        """GGX Smith shadowing of direction w for microfacet normal h."""
        cos2 = w[..., 2] ** 2
        tan2 = np.maximum(1.0 - cos2, 0.0) / cos2
        g1 = 2.0 / (1.0 + np.sqrt(1.0 + self.alpha * self.alpha * tan2))
        return np.where(np.sum(w * h, axis=-1) * w[..., 2] > 0.0, g1, 0.0)

    def _value(self, wi, wo):
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        cos_d = np.sum(wi * h, axis=-1)
        fresnel = 1.0 if self.ior is None else fresnel_dielectric(cos_d, self.ior)
        spec = (fresnel * self.distribution(h[..., 2]) * self.smith_g1(wi, h) * self.smith_g1(wo, h)
                / (4.0 * wi[..., 2] * wo[..., 2]))
        return self.albedo_diffuse / math.pi + spec[..., None] * self.specular


class OrenNayar(AnalyticBRDF):
    """Oren-Nayar (1994) qualitative rough-diffuse model: back-scattering (retro-reflection).

    ``f = albedo / pi * (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta))``,
    ``alpha = max(theta_i, theta_o)``, ``beta = min(theta_i, theta_o)``,
    ``A = 1 - 0.5 s^2 / (s^2 + 0.33)``, ``B = 0.45 s^2 / (s^2 + 0.09)``,
    ``s = sigma`` (facet slope standard deviation, radians). ``sigma = 0`` is Lambertian.
    """

    kind = "oren-nayar"

    def __init__(self, albedo: RGBLike = 0.5, sigma: float = 0.3):
        self.albedo = _rgb(albedo, "albedo")
        self.sigma = float(sigma)
        if not (self.sigma >= 0.0 and math.isfinite(self.sigma)):
            raise ValueError(f"sigma must be >= 0 (radians), got {sigma!r}")

    def _params(self):
        return {"albedo": self.albedo, "sigma": np.array([self.sigma])}

    def _value(self, wi, wo):
        s2 = self.sigma * self.sigma
        a = 1.0 - 0.5 * s2 / (s2 + 0.33)
        b = 0.45 * s2 / (s2 + 0.09)
        sin_i = np.hypot(wi[..., 0], wi[..., 1])
        sin_o = np.hypot(wo[..., 0], wo[..., 1])
        denom = sin_i * sin_o
        cos_dphi = np.where(denom > 1e-12, (wi[..., 0] * wo[..., 0] + wi[..., 1] * wo[..., 1])
                            / np.maximum(denom, 1e-12), 0.0)
        # sin(alpha) tan(beta): alpha has the larger sine, beta the larger cosine.
        sin_alpha_tan_beta = np.maximum(sin_i, sin_o) * np.minimum(sin_i, sin_o) / np.maximum(wi[..., 2], wo[..., 2])
        factor = a + b * np.maximum(cos_dphi, 0.0) * sin_alpha_tan_beta
        return factor[..., None] * (self.albedo / math.pi)


class BivariateLobe(AnalyticBRDF):
    """A bivariate test BRDF: a function of (theta_h, theta_d) only.

    ``f = diffuse / pi + specular * exp(-(theta_h / width)^2) * (f0 + (1 - f0)(1 - cos theta_d)^5)``:
    a sharp half-vector lobe (``width`` radians) with a Schlick-like theta_d term
    that brightens towards grazing, as Fresnel does.
    """

    kind = "bivariate-lobe"

    def __init__(self, diffuse: RGBLike = 0.2, specular: RGBLike = 5.0, width: float = 0.1, f0: float = 0.25):
        self.diffuse = _rgb(diffuse, "diffuse")
        self.specular = _rgb(specular, "specular")
        self.width = float(width)
        self.f0 = float(f0)
        if not (self.width > 0.0 and math.isfinite(self.width)):
            raise ValueError(f"width must be positive (radians), got {width!r}")
        if not 0.0 <= self.f0 <= 1.0:
            raise ValueError(f"f0 must be in [0, 1], got {f0!r}")

    def _params(self):
        return {"diffuse": self.diffuse, "specular": self.specular, "width": np.array([self.width]),
                "f0": np.array([self.f0])}

    def eval_half_diff(self, theta_h, theta_d) -> np.ndarray:
        """The closed form at (theta_h, theta_d) (radians, broadcast) -> ``(..., 3)`` 1/sr, no horizon test."""
        theta_h, theta_d = np.broadcast_arrays(np.asarray(theta_h, np.float64), np.asarray(theta_d, np.float64))
        lobe = np.exp(-(theta_h / self.width) ** 2) * (self.f0 + (1.0 - self.f0) * (1.0 - np.cos(theta_d)) ** 5)
        return self.diffuse / math.pi + lobe[..., None] * self.specular

    def _value(self, wi, wo):
        theta_h, _, theta_d, _ = half_diff_from_dirs(wi, wo)
        return self.eval_half_diff(theta_h, theta_d)


_MODELS: Dict[str, Tuple[type, Dict[str, Tuple[str, bool]]]] = {
    # spec name -> (class, {spec key: (constructor argument, is RGB)})
    "lambertian": (Lambertian, {"albedo": ("albedo", True)}),
    "ggx": (CookTorranceGGX, {"diffuse": ("albedo_diffuse", True), "specular": ("specular", True),
                              "alpha": ("alpha", False), "ior": ("ior", False)}),
    "oren-nayar": (OrenNayar, {"albedo": ("albedo", True), "sigma": ("sigma", False)}),
    "bivariate-lobe": (BivariateLobe, {"diffuse": ("diffuse", True), "specular": ("specular", True),
                                       "width": ("width", False), "f0": ("f0", False)}),
}
#: The largest size of a spec's parameter: far beyond any physical albedo, roughness or index, and
#: small enough that a table of it renders and solves in float32.
MAX_PARAMETER = 1e6
_ALIASES = {"diffuse": "lambertian", "cook-torrance": "ggx", "orennayar": "oren-nayar", "lobe": "bivariate-lobe"}


def analytic_from_spec(spec: str) -> AnalyticBRDF:
    """Parse ``"kind:key=v[,v,v],key=v..."`` into an analytic BRDF.

    Kinds and keys (RGB keys take one or three values; angles in radians):
    ``lambertian: albedo``; ``ggx: diffuse, specular, alpha, ior``;
    ``oren-nayar: albedo, sigma``; ``bivariate-lobe: diffuse, specular, width, f0``.
    Omitted keys take the class defaults.

    Raises:
        InputError: unknown kind or key, or a malformed value (names the spec).
    """
    kind, _, body = spec.strip().partition(":")
    kind = _ALIASES.get(kind.strip().lower(), kind.strip().lower())
    if kind not in _MODELS:
        raise InputError(spec, f"unknown analytic BRDF {kind!r}", f"use one of {', '.join(_MODELS)}")
    cls, keys = _MODELS[kind]
    values: Dict[str, list] = {}
    current = None
    for token in filter(None, (t.strip() for t in body.split(","))):
        if "=" in token:
            current, _, token = (p.strip() for p in token.partition("="))
            if current not in keys:
                raise InputError(spec, f"unknown parameter {current!r} for {kind}", f"valid: {', '.join(keys)}")
            if current in values:
                raise InputError(spec, f"parameter {current!r} given twice", "give each parameter once")
            values[current] = []
        elif current is None:
            raise InputError(spec, f"value {token!r} has no parameter name", "write key=value")
        try:
            value = float(token)
        except ValueError:
            raise InputError(spec, f"{current}: {token!r} is not a number", f"write {current}=NUMBER") from None
        if not (math.isfinite(value) and abs(value) <= MAX_PARAMETER):
            raise InputError(spec, f"{current}: {token!r} is out of range (finite, at most {MAX_PARAMETER:g} in size)",
                             f"give {current} a value in that range")
        values[current].append(value)
    kwargs = {}
    for key, vals in values.items():
        arg, is_rgb = keys[key]
        if len(vals) not in ((1, 3) if is_rgb else (1,)):
            raise InputError(spec, f"{key} takes {'1 or 3 values' if is_rgb else 'one value'}, got {len(vals)}",
                             f"write {key}=V" + (f" or {key}=R,G,B" if is_rgb else ""))
        kwargs[arg] = vals if is_rgb else vals[0]
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise InputError(spec, str(e), "change the value it names") from None


def to_merl(brdf: Union[AnalyticBRDF, Callable], name: str | None = None, dtype=np.float64) -> MERLBRDF:
    """Tabulate an analytic BRDF (or any object with ``eval(theta_h, theta_d, phi_d)``) on the MERL grid.

    Below-horizon configurations are stored as missing (NaN), like real MERL data.
    """
    fn = brdf.eval if hasattr(brdf, "eval") else brdf
    return MERLBRDF.from_function(fn, name=name or getattr(brdf, "name", "analytic"), dtype=dtype)
