"""Passive reflectometry end to end: images of a known sphere under known probes -> BRDF.

This is the library's front door (``mi_bivariate.recover``). It chains the
pipeline stages in the paper's order:

observations (:mod:`capture`) -> lighting matrix L (:mod:`lighting`, Eqs. 3-5)
-> adequacy of the environment (:mod:`adequacy`, Sect. 3.1) -> constrained,
regularised solve (:mod:`solve`, Eq. 6 with the learnt :mod:`prior`)
-> :class:`~mi_bivariate.bivariate.BivariateBRDF`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate import adequacy, capture, lighting, prior as prior_mod, solve as solve_mod
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.images import load_image, load_mask
from mi_bivariate.probes import Probe

PathLike = Union[str, os.PathLike]


@dataclass
class Recovery:
    """A recovered BRDF and everything needed to judge it.

    Attributes:
        brdf: the recovered bivariate BRDF (1/sr).
        observations: the stacked observations (M rows).
        lighting_matrix: ``(M, n_t * n_s, 3) float32``, Eq. 5's L.
        solution: the solver's report (residuals, winning prior per channel).
        adequacy: rank/condition/coverage of L and its warnings.
        predicted: ``(M, 3)`` model prediction ``L @ f`` at the observations.
        images, geometries, probes: the inputs, kept for reports.
        timings: seconds per stage.
    """

    brdf: BivariateBRDF
    observations: capture.Observations
    lighting_matrix: np.ndarray
    solution: solve_mod.SolveResult
    adequacy: adequacy.AdequacyReport
    predicted: np.ndarray
    images: List[np.ndarray] = field(default_factory=list)
    geometries: List[SphereGeometry] = field(default_factory=list)
    probes: List[Probe] = field(default_factory=list)
    timings: Dict[str, float] = field(default_factory=dict)
    sphere_fit: Optional[Any] = None
    alignment: Optional[Any] = None

    def relative_residual(self) -> float:
        """``||I - L f|| / ||I||`` over all rows and channels."""
        values = self.observations.values
        return float(np.linalg.norm(values - self.predicted) / max(np.linalg.norm(values), 1e-30))

    def summary(self) -> str:
        obs = self.observations
        dropped = ", ".join(f"{k}: {v}" for k, v in obs.dropped.items() if v) or "none"
        winners = "/".join(self.solution.winner)
        stages = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items())
        return "\n".join([
            f"observations: {len(obs.values)} normals (dropped pixels: {dropped})",
            f"lighting matrix: {self.lighting_matrix.shape[0]} x {self.lighting_matrix.shape[1]} x 3",
            f"adequacy: {self.adequacy.summary()}",
            f"solve: alpha {self.solution.alpha:g}, prior pair per channel (R/G/B) {winners}, "
            f"relative residual {self.relative_residual():.4f}",
            f"timings: {stages}",
        ])


def _as_list(value, n: int, name: str) -> list:
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise InputError(None, f"{len(value)} {name} given for {n} images")
        return list(value)
    return [value] * n


def recover(images: Union[np.ndarray, Sequence[np.ndarray]],
            probe: Union[Probe, Sequence[Probe]],
            geometry: Union[SphereGeometry, Sequence[SphereGeometry]],
            *,
            masks: Optional[Union[np.ndarray, Sequence[Optional[np.ndarray]]]] = None,
            n_normals: int = 8000,
            n_dirs: int = 32000,
            grid: Tuple[int, int] = (32, 32),
            alpha: Optional[float] = None,
            prior: Optional[prior_mod.Prior] = None,
            max_view_angle_deg: float = 80.0,
            saturation: Optional[float] = None,
            seed: int = 0,
            keep_inputs: bool = True,
            visibility: bool = True) -> Recovery:
    """Recover a bivariate BRDF from HDR images of a sphere under known probes.

    Args:
        images: one ``(H, W, 3)`` linear image or a list of them (other views
            or other probes; all rows stack into one system).
        probe: the probe lighting each image (one for all, or one per image),
            in Mitsuba's envmap frame (y up).
        geometry: what each image shows: a sphere (:class:`SphereGeometry`,
            :class:`PerspectiveSphereGeometry`, pixels and camera pose; see
            :mod:`geometry`) or a known mesh with its camera
            (:class:`mi_bivariate.mesh.MeshView`). Poses may differ per image.
        masks: optional ``(H, W) bool`` usable-pixel masks.
        n_normals: normals M per image (uniform over the visible hemisphere).
        n_dirs: light directions K per normal.
        grid: st grid ``(n_t, n_s)``.
        alpha: regularisation weight (default: :data:`solve.DEFAULT_ALPHA`).
        prior: smoothness prior (default: the packaged one, resampled to ``grid``).
        max_view_angle_deg: drop normals further than this from the view.
        saturation: drop pixels with any channel at or above this value.
        seed: seeds normal selection and light directions.
        visibility: for mesh views, trace shadow rays against the mesh so
            that directions it blocks itself contribute nothing (the paper
            ignores this; it matters for non-convex shapes).
    """
    if isinstance(images, np.ndarray) and images.ndim == 3:
        images = [images]
    images = list(images)
    if not images:
        raise InputError(None, "no images given")
    n = len(images)
    probe_list = _as_list(probe, n, "probes")
    geometries = _as_list(geometry, n, "geometries")
    mask_list = _as_list(masks, n, "masks")
    n_t, n_s = (int(g) for g in grid)
    if n_t < 2 or n_s < 2:
        raise InputError("grid", f"{n_t}x{n_s} is too small", "each st axis needs at least 2 nodes")
    if alpha is not None and not (np.isfinite(alpha) and alpha >= 0):
        raise InputError("alpha", f"must be a finite number >= 0, got {alpha}")

    timings: Dict[str, float] = {}
    t0 = time.perf_counter()
    parts = []
    for k, (image, geo, mask) in enumerate(zip(images, geometries, mask_list)):
        obs = capture.image_observations(image, geo, n_normals=n_normals, max_view_angle_deg=max_view_angle_deg,
                                 saturation=saturation, mask=mask, seed=seed + k,
                                 source=f"image {k}" if n > 1 else "image")
        parts.append(obs.with_probe_index(k))
    observations = capture.stack(parts)
    timings["observations"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    occluders = [geo.occluder() if visibility and callable(getattr(geo, "occluder", None)) else None
                 for geo in geometries]
    L = lighting.lighting_matrix(observations, probe_list, n_t=n_t, n_s=n_s, n_dirs=n_dirs, seed=seed,
                                 occluder=occluders if any(o is not None for o in occluders) else None)
    timings["lighting matrix"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    report = adequacy.analyse(L, n_t=n_t, n_s=n_s, probes=probe_list, warn=True)
    timings["adequacy"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if prior is None:
        prior = prior_mod.default_prior()
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    solution = solve_mod.solve(L, observations.values, prior, alpha=alpha)
    timings["solve"] = time.perf_counter() - t0

    table = solution.table
    predicted = np.einsum("mnc,nc->mc", L, table.reshape(n_t * n_s, 3), optimize=True)
    brdf = BivariateBRDF(table, provenance={
        "method": "passive reflectometry (Romeiro et al. 2008), mi_bivariate.recover",
        "images": n, "normals": int(len(observations.values)), "light_directions": int(n_dirs),
        "alpha": float(solution.alpha), "prior_winner": list(solution.winner), "seed": int(seed),
        "probes": [getattr(p, "source", "?") for p in probe_list],
        "visibility": bool(any(o is not None for o in occluders)),
    })
    return Recovery(brdf=brdf, observations=observations, lighting_matrix=L, solution=solution,
                    adequacy=report, predicted=predicted,
                    images=images if keep_inputs else [], geometries=geometries,
                    probes=probe_list, timings=timings)


def _auto_saturation(image: np.ndarray, region: Optional[np.ndarray]) -> Optional[float]:
    """The clipping level of an image whose highlights sit on a plateau at its maximum, else ``None``."""
    values = np.asarray(image, np.float64)
    values = values[region] if region is not None else values.reshape(-1, 3)
    values = values[np.all(np.isfinite(values), axis=1)]
    if len(values) == 0:
        return None
    peak = float(values.max())
    at_peak = int(np.count_nonzero(np.any(values >= peak, axis=1)))
    if peak > 0.0 and at_peak >= max(4, int(0.002 * len(values))):
        return peak
    return None


def recover_from_photo(image: np.ndarray, probe: Probe, *, intrinsics: Any = None,
                       sphere: Optional[Sequence[float]] = None, mask: Optional[np.ndarray] = None,
                       camera_to_world: Any = None, saturation: Union[None, float, str] = "auto",
                       estimate_yaw: bool = False, yaw_kwargs: Optional[dict] = None,
                       source: str = "image", **kwargs) -> Recovery:
    """Recover a BRDF from one photograph of a sphere, finding the sphere automatically.

    The photo path: :func:`mi_bivariate.spherefit.fit_sphere` (orthographic,
    or perspective with ``intrinsics``) -> per-pixel normals and views ->
    observations -> lighting matrix -> solve (:func:`recover`).

    Args:
        image: ``(H, W, 3)`` linear HDR photo.
        probe: the environment, in Mitsuba's envmap frame (y up).
        intrinsics: ``(fx, fy, cx, cy)`` pixels or :class:`~mi_bivariate.geometry.Intrinsics`
            (pinhole model); ``None``: orthographic.
        sphere: explicit ``(cx, cy, r)`` in pixels instead of the fit.
        mask: optional ``(H, W) bool`` user mask of the sphere.
        camera_to_world: ``(3, 3)`` camera rotation in the probe's frame.
        saturation: drop pixels at or above this value; ``"auto"``: the
            image's maximum when highlights sit on a plateau there (clipped).
        estimate_yaw: first estimate the probe's rotation about the vertical
            (:func:`mi_bivariate.alignment.estimate_yaw`) and recover under
            the aligned probe (the main error source for captured data).
        yaw_kwargs: options for :func:`~mi_bivariate.alignment.estimate_yaw`.
        kwargs: passed to :func:`recover`.

    Returns:
        The :class:`Recovery`, with ``sphere_fit`` (and ``alignment``) set.
    """
    from mi_bivariate import spherefit

    fit = spherefit.fit_sphere(image, mask, sphere=sphere, intrinsics=intrinsics,
                               camera_to_world=camera_to_world, source=source)
    if isinstance(saturation, str):
        if saturation != "auto":
            raise InputError("saturation", f"must be a number, None or 'auto', got {saturation!r}")
        region = fit.region if fit.region is not None else None
        saturation = _auto_saturation(image, region)
    alignment = None
    if estimate_yaw:
        from mi_bivariate import alignment as alignment_mod

        alignment = alignment_mod.estimate_yaw(image, probe, fit.geometry, saturation=saturation,
                                               **(yaw_kwargs or {}))
        probe = alignment.probe
    result = recover(image, probe, fit.geometry, saturation=saturation, **kwargs)
    result.sphere_fit = fit
    result.alignment = alignment
    return result


def recover_from_files(image_paths: Sequence[PathLike], probe: Union[Probe, Sequence[Probe]],
                       geometry: Union[SphereGeometry, Sequence[SphereGeometry]],
                       mask: Optional[PathLike] = None, **kwargs) -> Recovery:
    """:func:`recover` on image files (EXR/HDR/PFM); ``mask`` applies to every image."""
    images = [load_image(p) for p in image_paths]
    masks = None
    if mask is not None:
        masks = [load_mask(mask, img.shape) for img in images]
    return recover(images, probe, geometry, masks=masks, **kwargs)


def write_outputs(result: Recovery, out: PathLike, merl: bool = False, report: bool = True,
                  report_render: bool = False) -> List[Path]:
    """Write the table (``.npz``), its EXR view, optionally a MERL ``.binary`` and a PNG report.

    The report's re-render is the model's prediction ``L f`` unless ``report_render``
    asks for a path-traced one (:func:`mi_bivariate.report.write_recovery_report`).

    Every file is written atomically; returns the paths written.
    """
    out = Path(out)
    if out.suffix != ".npz":
        out = out.with_suffix(".npz")
    written = [out]
    result.brdf.save(out)
    exr = out.with_suffix(".exr")
    result.brdf.save_exr(exr)
    written.append(exr)
    if merl:
        binary = out.with_suffix(".binary")
        result.brdf.to_merl().write(binary)
        written.append(binary)
    if report:
        from mi_bivariate import report as report_mod

        png = out.with_name(out.stem + "_report.png")
        report_mod.write_recovery_report(result, png, path_trace=report_render)
        written.append(png)
    return written
