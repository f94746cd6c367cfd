"""Low-parameter baselines fitted with the same forward model as the bivariate recovery.

The paper argues that a non-parametric bivariate table beats low-parameter
models for measured materials. To test that claim with the same data, each
baseline here is fitted to the *same* observations ``I (M, 3)`` through the
*same* lighting matrix ``L (M, n_t * n_s, 3)`` (Eqs. 2-5):

    I_c ~= L_c f_c(x),    f(x) = kd / pi + ks * lobe(theta_h, theta_d; u)

where ``f(x)`` is the model's **bivariate table**: the parametric BRDF
tabulated on the st nodes by averaging over phi_d exactly as
:meth:`~mi_bivariate.bivariate.BivariateBRDF.reduce` does for any 3D BRDF
(``n_phi`` samples of phi_d in [0, pi), configurations above the horizon,
nodes clamped at s, t <= 89/90). This is an approximation: the lighting
matrix can only see a BRDF through its bivariate projection, so a model's
phi_d dependence (Fresnel is a function of theta_d, but the microfacet
shadowing G and Ward's ``1/sqrt(cos_i cos_o)`` are not) is averaged away in
the fit, exactly as the bivariate recovery averages it away. The fitted
parameters are then evaluated as the **full 3D model** on the MERL grid to
compare with the 3D truth (:func:`mi_bivariate.metrics.brdf_errors`).

Models (``FAMILIES``):

- ``"ggx"``: Lambertian + Cook-Torrance microfacet lobe with GGX D, Smith G
  and dielectric Fresnel (:class:`~mi_bivariate.analytic.CookTorranceGGX`);
  parameters kd (RGB albedo), ks (RGB), alpha (GGX roughness), ior.
- ``"ward"``: Lambertian + isotropic Ward lobe (:class:`WardIsotropic`);
  parameters kd (RGB albedo), ks (RGB), alpha (RMS slope).

The fit is non-linear least squares (``scipy.optimize.least_squares``,
trust-region reflective) in transformed parameters that keep every value
physical: ``kd = exp(x)``, ``ks = exp(x)``, ``alpha = exp(u)``,
``ior = 1 + exp(u)``. Residuals are per channel relative to ``||I_c||`` so
that each channel counts equally. Several starts (one per initial alpha);
each start's kd, ks come from a non-negative linear solve at that alpha.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Sequence, Tuple

import numpy as np

from mi_bivariate.analytic import AnalyticBRDF, CookTorranceGGX, _fmt, _rgb
from mi_bivariate.bivariate import _ST_MAX, BivariateBRDF, _fill_nearest
from mi_bivariate.coordinates import dirs_from_half_diff, grid_nodes, half_diff_from_st
from mi_bivariate.errors import InputError
from mi_bivariate.merl import above_horizon


class WardIsotropic(AnalyticBRDF):
    """Lambertian + isotropic Ward (1992) lobe.

    ``f = albedo / pi + specular * exp(-tan^2(theta_h) / alpha^2) / (4 pi alpha^2 sqrt(cos_i cos_o))``.
    Not bivariate: ``cos_i cos_o`` depends on phi_d.
    """

    kind = "ward"

    def __init__(self, albedo_diffuse=0.0, specular=1.0, alpha: float = 0.1):
        self.albedo_diffuse = _rgb(albedo_diffuse, "diffuse")
        self.specular = _rgb(specular, "specular")
        self.alpha = float(alpha)
        if not (self.alpha > 0.0 and math.isfinite(self.alpha)):
            raise ValueError(f"alpha must be positive, got {alpha!r}")

    def _params(self):
        return {"diffuse": self.albedo_diffuse, "specular": self.specular, "alpha": np.array([self.alpha])}

    @property
    def name(self) -> str:
        return "ward:" + ",".join(f"{k}={_fmt(v)}" for k, v in self._params().items())

    def _value(self, wi, wo):
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        cos_h2 = h[..., 2] ** 2
        tan_h2 = np.maximum(1.0 - cos_h2, 0.0) / cos_h2
        a2 = self.alpha * self.alpha
        lobe = np.exp(-tan_h2 / a2) / (4.0 * math.pi * a2 * np.sqrt(wi[..., 2] * wo[..., 2]))
        return self.albedo_diffuse / math.pi + lobe[..., None] * self.specular


@dataclass(frozen=True)
class Family:
    """A parametric model family: Lambertian + ``ks`` x a unit lobe with non-linear parameters ``u``.

    Attributes:
        name: ``"ggx"`` or ``"ward"``.
        nonlinear: names of the lobe's parameters.
        to_params: transformed ``u`` -> physical lobe parameters (dict).
        make: ``(kd (3,), ks (3,), lobe params) -> AnalyticBRDF`` (the 3D model).
        starts: initial ``u`` vectors (one fit per start).
    """

    name: str
    nonlinear: Tuple[str, ...]
    to_params: Callable[[np.ndarray], Dict[str, float]]
    make: Callable[..., AnalyticBRDF]
    starts: Tuple[Tuple[float, ...], ...]


def _ggx_params(u: np.ndarray) -> Dict[str, float]:
    # alpha in (1e-3, 3): narrower lobes fall between the st nodes anyway.
    return {"alpha": float(np.clip(np.exp(u[0]), 1e-3, 3.0)), "ior": float(1.0 + np.clip(np.exp(u[1]), 1e-3, 20.0))}


def _ward_params(u: np.ndarray) -> Dict[str, float]:
    return {"alpha": float(np.clip(np.exp(u[0]), 1e-3, 3.0))}


FAMILIES: Dict[str, Family] = {
    "ggx": Family("ggx", ("alpha", "ior"), _ggx_params,
                  lambda kd, ks, p: CookTorranceGGX(kd, ks, alpha=p["alpha"], ior=p["ior"]),
                  tuple((math.log(a), math.log(0.5)) for a in (0.03, 0.1, 0.3))),
    "ward": Family("ward", ("alpha",), _ward_params,
                   lambda kd, ks, p: WardIsotropic(kd, ks, alpha=p["alpha"]),
                   tuple((math.log(a),) for a in (0.03, 0.1, 0.3))),
}


class PhiAverager:
    """Eq. 1 phi_d averages of a BRDF at the st nodes, with the directions precomputed.

    Produces the same table as ``BivariateBRDF.reduce(brdf, n_t, n_s, n_phi)``
    for an analytic BRDF (same node clamping at 89/90, same horizon test,
    same nearest-node fill), but reuses the direction pairs across the many
    model evaluations of a fit.
    """

    def __init__(self, n_t: int = 32, n_s: int = 32, n_phi: int = 45):
        t_nodes, s_nodes = grid_nodes(n_t), grid_nodes(n_s)
        theta_h, _ = half_diff_from_st(0.0, np.minimum(t_nodes, _ST_MAX))
        _, theta_d = half_diff_from_st(np.minimum(s_nodes, _ST_MAX), 0.0)
        phi_d = np.arange(n_phi) * (math.pi / n_phi)
        th, td, pd = np.broadcast_arrays(theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :])
        self.shape = (n_t, n_s)
        self.valid = above_horizon(th, td, pd)
        self.count = self.valid.sum(axis=2)
        wi, wo = dirs_from_half_diff(th, np.zeros_like(th), td, pd)
        self.wi, self.wo = wi[self.valid], wo[self.valid]

    def average(self, brdf: AnalyticBRDF) -> np.ndarray:
        """``(n_t, n_s, 3)`` float64 phi_d mean of ``brdf`` (1/sr)."""
        values = np.zeros(self.valid.shape + (3,))
        v = brdf.eval_dirs(self.wi, self.wo)
        v = np.where(np.isfinite(v), v, np.nan)
        values[self.valid] = np.nan_to_num(v, nan=0.0)
        finite = np.zeros(self.valid.shape + (3,), bool)
        finite[self.valid] = np.isfinite(v)
        with np.errstate(invalid="ignore", divide="ignore"):
            table = values.sum(axis=2) / finite.sum(axis=2)
        return _fill_nearest(table, source=getattr(brdf, "name", "model"))


@dataclass
class BaselineFit:
    """A fitted parametric baseline.

    Attributes:
        family: model family name.
        params: ``kd`` (RGB albedo), ``ks`` (RGB), and the lobe's parameters.
        brdf: the full 3D model with those parameters (``eval(theta_h, theta_d, phi_d)``).
        table: its phi_d-averaged bivariate table (what the fit saw through L).
        relative_residual: ``||I - L f|| / ||I||`` over all rows and channels.
        starts: final cost of every start; ``nfev``: model evaluations in total.
        time_s: wall time of the fit.
    """

    family: str
    params: Dict[str, object]
    brdf: AnalyticBRDF
    table: BivariateBRDF
    relative_residual: float
    starts: List[float] = field(default_factory=list)
    nfev: int = 0
    time_s: float = 0.0

    def summary(self) -> dict:
        """JSON-friendly parameters and fit statistics."""
        params = {k: (np.round(np.asarray(v, float), 6).tolist() if np.ndim(v) else round(float(v), 6))
                  for k, v in self.params.items()}
        return {"family": self.family, "params": params, "relative_residual": self.relative_residual,
                "start_costs": self.starts, "nfev": self.nfev, "time_s": round(self.time_s, 3)}


def _check_inputs(L: np.ndarray, I: np.ndarray, n_t: int, n_s: int) -> Tuple[np.ndarray, np.ndarray]:
    L = np.asarray(L, np.float32)
    I = np.asarray(I, np.float64)
    if L.ndim != 3 or L.shape[1] != n_t * n_s or L.shape[2] != 3:
        raise InputError("lighting matrix", f"expected shape (M, {n_t * n_s}, 3), got {L.shape}")
    if I.shape != (L.shape[0], 3):
        raise InputError("observations", f"expected shape ({L.shape[0]}, 3), got {I.shape}")
    if not np.all(np.isfinite(I)):
        raise InputError("observations", "contain non-finite values")
    return L, I


def fit_baseline(family: str, L: np.ndarray, I: np.ndarray, grid: Tuple[int, int] = (32, 32),
                 n_phi: int = 45, max_nfev: int = 40, start_nfev: int = 6, starts: int | None = None,
                 averager: PhiAverager | None = None) -> BaselineFit:
    """Fit a parametric model to observations through the lighting matrix.

    Args:
        family: a key of :data:`FAMILIES`.
        L: ``(M, n_t * n_s, 3)`` lighting matrix (column ``it * n_s + is``).
        I: ``(M, 3)`` observed pixel values.
        grid: ``(n_t, n_s)`` of L's table.
        n_phi: phi_d samples of the bivariate tabulation.
        max_nfev: least-squares evaluations of the final run.
        start_nfev: evaluations per start before the best start is continued.
        starts: use only the first ``starts`` initial alphas (default all).

    Returns:
        The best start's :class:`BaselineFit`.
    """
    if family not in FAMILIES:
        raise InputError(family, "unknown baseline model", f"use one of {', '.join(FAMILIES)}")
    fam = FAMILIES[family]
    n_t, n_s = (int(g) for g in grid)
    L, I = _check_inputs(L, I, n_t, n_s)
    averager = averager or PhiAverager(n_t, n_s, n_phi)
    t_start = time.perf_counter()
    M = L.shape[0]
    norm = np.maximum(np.linalg.norm(I, axis=0), 1e-30)                  # (3,) per-channel scale
    # L applied to the Lambertian table 1/pi: (M, 3).
    a = L.sum(axis=1, dtype=np.float64) / math.pi
    # Per channel (3, M, N), C-contiguous: L_c @ table is then one BLAS gemv.
    L_c = np.ascontiguousarray(L.transpose(2, 0, 1))
    n_u = len(fam.nonlinear)
    calls = {"n": 0}

    def lobe_response(u: np.ndarray) -> np.ndarray:
        """``L_c @ lobe(u)`` for a unit lobe: ``(M, 3)``."""
        calls["n"] += 1
        lobe = fam.make(np.zeros(3), np.ones(3), fam.to_params(u))
        table = averager.average(lobe)[..., 0].reshape(-1).astype(np.float32)
        return (L_c @ table).T.astype(np.float64)

    def split(x: np.ndarray):
        # Clipped so that a wild trust-region step cannot overflow exp.
        return np.exp(np.clip(x[:3], -40.0, 10.0)), np.exp(np.clip(x[3:6], -40.0, 10.0)), x[6:]

    cache: Dict[bytes, np.ndarray] = {}

    def response(u: np.ndarray) -> np.ndarray:
        key = np.asarray(u, np.float64).tobytes()
        if key not in cache:
            if len(cache) > 8:
                cache.clear()
            cache[key] = lobe_response(u)
        return cache[key]

    def residual(x: np.ndarray) -> np.ndarray:
        kd, ks, u = split(x)
        pred = kd * a + ks * response(u)
        return ((pred - I) / norm).T.reshape(-1)                         # channel-major (3 M,)

    def jacobian(x: np.ndarray) -> np.ndarray:
        kd, ks, u = split(x)
        b = response(u)
        J = np.zeros((3 * M, 6 + n_u))
        for c in range(3):
            rows = slice(c * M, (c + 1) * M)
            J[rows, c] = kd[c] * a[:, c] / norm[c]                       # d/d log kd_c
            J[rows, 3 + c] = ks[c] * b[:, c] / norm[c]                   # d/d log ks_c
        for k in range(n_u):                                             # forward differences in u
            du = np.zeros(n_u)
            du[k] = 1e-4
            db = response(u + du) - b
            J[:, 6 + k] = (ks * db / 1e-4 / norm).T.reshape(-1)
        return J

    from scipy.optimize import least_squares, nnls

    # Every start gets a few iterations; the best one then runs to convergence.
    trials = []
    for u0 in fam.starts[:starts]:
        u0 = np.asarray(u0, np.float64)
        b0 = response(u0)
        x0 = np.empty(6 + n_u)
        for c in range(3):
            # Linear kd, ks at this lobe shape: the start is already a least-squares fit.
            coef, _ = nnls(np.stack([a[:, c], b0[:, c]], axis=1) / norm[c], I[:, c] / norm[c])
            floor = 1e-6 * max(coef.max(), 1e-3)
            x0[c], x0[3 + c] = np.log(max(coef[0], floor)), np.log(max(coef[1], floor))
        x0[6:] = u0
        trials.append(least_squares(residual, x0, jac=jacobian, method="trf", max_nfev=start_nfev,
                                    x_scale="jac"))
    costs = [float(t.cost) for t in trials]
    best = trials[int(np.argmin(costs))]
    best = least_squares(residual, best.x, jac=jacobian, method="trf", max_nfev=max_nfev, x_scale="jac")
    kd, ks, u = split(best.x)
    lobe_params = fam.to_params(u)
    brdf = fam.make(kd, ks, lobe_params)
    table = averager.average(brdf)
    pred = kd * a + ks * response(u)
    rel = float(np.linalg.norm(pred - I) / max(np.linalg.norm(I), 1e-30))
    params: Dict[str, object] = {"kd": kd, "ks": ks, **lobe_params}
    return BaselineFit(family=family, params=params, brdf=brdf,
                       table=BivariateBRDF(np.maximum(table, 0.0), provenance={
                           "method": f"parametric baseline {family} (phi_d-averaged)", "model": brdf.name}),
                       relative_residual=rel, starts=costs, nfev=calls["n"],
                       time_s=time.perf_counter() - t_start)


def fit_baselines(L: np.ndarray, I: np.ndarray, grid: Tuple[int, int] = (32, 32),
                  families: Sequence[str] = ("ggx", "ward"), **kwargs) -> Dict[str, BaselineFit]:
    """:func:`fit_baseline` for several families, sharing the direction tables."""
    n_t, n_s = (int(g) for g in grid)
    averager = PhiAverager(n_t, n_s, kwargs.pop("n_phi", 45))
    return {f: fit_baseline(f, L, I, grid=grid, averager=averager, **kwargs) for f in families}
