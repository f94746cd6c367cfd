"""Passive reflectometry end to end: images of a known sphere under known probes -> BRDF.

This is the library's front door (``mi_bivariate.recover``). It chains the
pipeline stages in the paper's order:

observations (:mod:`capture`) -> lighting matrix L (:mod:`lighting`, Eqs. 3-5)
-> adequacy of the environment (:mod:`adequacy`, Sect. 3.1) -> constrained,
regularised solve (:mod:`solve`, Eq. 6 with the learnt :mod:`prior`)
-> :class:`~mi_bivariate.bivariate.BivariateBRDF`.
"""

from __future__ import annotations

import numbers
import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate import adequacy
from mi_bivariate import alignment as alignment_mod
from mi_bivariate import capture, lighting, limits
from mi_bivariate import prior as prior_mod
from mi_bivariate import solve as solve_mod
from mi_bivariate import sphere_refine, spherefit
from mi_bivariate.basis_prior import BasisPrior, default_basis_prior
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Geometry, PerspectiveSphereGeometry, SphereGeometry, check_sphere
from mi_bivariate.images import bounding_box
from mi_bivariate.noise import check_noise_model, estimate_camera_noise
from mi_bivariate.probes import Probe, check_lit, check_probe
from mi_bivariate.solve import IMAGE_WEIGHTS, cross_image_factors, solve_stages
from mi_bivariate.threads import blas_threads
from mi_bivariate.variants import ensure_variant


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
        sphere_fit: the silhouette fit (:func:`recover_from_photo`).
        alignment: the probe's estimated yaw (:func:`recover_from_photo` with ``estimate_yaw``).
        sphere_refinement: the sphere refined by shading (:func:`refine_sphere_and_recover`), or ``None``.
    """

    brdf: BivariateBRDF
    observations: capture.Observations
    lighting_matrix: np.ndarray
    solution: solve_mod.SolveResult
    adequacy: adequacy.AdequacyReport
    predicted: np.ndarray
    images: List[np.ndarray] = field(default_factory=list)
    geometries: List[Geometry] = field(default_factory=list)
    probes: List[Probe] = field(default_factory=list)
    timings: Dict[str, float] = field(default_factory=dict)
    sphere_fit: Optional[Any] = None
    alignment: Optional[Any] = None
    sphere_refinement: Optional[sphere_refine.SphereRefinement] = None

    def relative_residual(self) -> float:
        """``||I - L f|| / ||I||`` over all rows and channels (with several images, the brightest
        dominates it: :meth:`relative_residuals` gives each image's own)."""
        values = np.asarray(self.observations.values, np.float64)  # float32 squares overflow beyond ~1e19
        return float(np.linalg.norm(values - self.predicted) / max(np.linalg.norm(values), 1e-30))

    def relative_residuals(self) -> np.ndarray:
        """``(n_images,) float64``: ``||I_k - L_k f|| / ||I_k||`` over image ``k``'s rows and channels,
        each independent of the images' relative brightness."""
        values = np.asarray(self.observations.values, np.float64)
        index = self.observations.image_index
        index = np.zeros(len(values), np.int64) if index is None else np.asarray(index)
        residual = np.bincount(index, weights=np.sum((values - self.predicted) ** 2, axis=-1))
        signal = np.bincount(index, weights=np.sum(values ** 2, axis=-1))
        return np.sqrt(residual) / np.maximum(np.sqrt(signal), 1e-30)

    def _per_image_residuals(self) -> str:
        each = self.relative_residuals()
        return f" (per image: {', '.join(f'{r:.4f}' for r in each)})" if len(each) > 1 else ""

    def summary(self) -> str:
        obs = self.observations
        dropped = ", ".join(f"{k}: {v}" for k, v in obs.dropped.items() if v) or "none"
        winners = "/".join(self.solution.winner)
        stages = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items())
        refined = [self.sphere_refinement.summary()] if self.sphere_refinement is not None else []
        return "\n".join(refined + [
            f"observations: {len(obs.values)} normals (sampled normals dropped: {dropped})",
            f"lighting matrix: {self.lighting_matrix.shape[0]} x {self.lighting_matrix.shape[1]} x 3",
            f"adequacy: {self.adequacy.summary()}",
            f"solve: alpha ({self.solution.alpha_rule}) R/G/B "
            f"{' '.join(f'{a:.3g}' for a in self.solution.alphas)}, prior pair per channel {winners} "
            f"(by {self.solution.pair_rule}), "
            f"basis prior {'on' if self.brdf.provenance.get('basis_prior') else 'off'}, "
            f"relative residual {self.relative_residual():.4f}{self._per_image_residuals()}",
            f"confidence: the image measured {100 * float(np.mean(np.min(self.solution.measured, -1) > 0.5)):.0f}% "
            f"of the nodes (their uncertainty more than halved), the priors supplied the rest",
            f"timings: {stages}",
        ])


def _image_list(images: Any) -> List[np.ndarray]:
    """The images as a list: one array of ``ndim != 4`` is one image (checked with its name later),
    a 4-D array or a sequence is several."""
    if isinstance(images, np.ndarray):
        images = list(images) if images.ndim == 4 else [images]
    elif isinstance(images, (list, tuple)):
        images = list(images)
    else:
        raise InputError("images", f"expected an (H, W, 3) image or a list of them, got a {type(images).__name__}",
                         "read a file with mi_bivariate.images.load_image")
    if not images:
        raise InputError(None, "no images given")
    return images


def _check_angle(name: str, value: Any) -> None:
    """An angle in degrees in ``(0, 90]``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 < value <= 90.0:
        raise InputError(name, f"must be an angle in (0, 90] degrees, got {value!r}")


def _as_list(value, n: int, name: str, argument: str) -> list:
    """One ``value`` per image: a list or tuple of ``n`` (else :class:`InputError` naming ``argument``), or one
    value for all."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise InputError(argument, f"{len(value)} {name} given for {n} images")
        return list(value)
    return [value] * n


def _geometry_list(geometry: Any, n: int) -> List[Geometry]:
    """One checked :class:`Geometry` per image (an orthographic sphere's numbers by
    :func:`~mi_bivariate.geometry.check_sphere`), else :class:`InputError` naming ``geometry``."""
    if isinstance(geometry, (list, tuple)) and geometry and all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) for v in geometry):
        raise InputError("geometry", f"expected a Geometry, got the numbers {tuple(geometry)!r}",
                         "give SphereGeometry(cx, cy, radius) in pixels (or a list of one Geometry per image)")
    geometries = _as_list(geometry, n, "geometries", "geometry")
    for k, geo in enumerate(geometries):
        source = "geometry" if n == 1 else f"geometry {k}"
        if isinstance(geo, SphereGeometry):
            check_sphere(geo, source)
        elif not isinstance(geo, Geometry):
            raise InputError(source, f"expected a Geometry, got a {type(geo).__name__}",
                             "use SphereGeometry, PerspectiveSphereGeometry or mesh.MeshView "
                             "(mi_bivariate.spherefit.fit_sphere(image).geometry fits a sphere)")
    return geometries


def _same_mask(a: Any, b: Any) -> bool:
    """Whether two entries of ``masks`` select the same pixels (anything but an array of numbers is not a mask:
    refused, naming it, where it is read). No mask and a mask of every pixel are the same: both leave every
    pixel usable."""
    a, b = (None if m is None else np.asarray(m) for m in (a, b))
    if any(m is not None and m.dtype.kind not in "biuf" for m in (a, b)):
        return False
    if a is None or b is None:
        return (a is None or bool(np.all(a))) and (b is None or bool(np.all(b)))
    return a.shape == b.shape and np.array_equal(a.astype(bool), b.astype(bool))


def _same_pixels(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two checked images hold the same pixels (NaN as NaN); a strided sample first rejects most
    different photos without a full pass."""
    if a is b:
        return True
    if a.shape != b.shape:
        return False
    a, b = np.asarray(a), np.asarray(b)
    return np.array_equal(a[::7, ::7], b[::7, ::7], equal_nan=True) and np.array_equal(a, b, equal_nan=True)


def _refuse_repeated_images(images: Sequence[np.ndarray], geometries: Sequence[Geometry], masks: Sequence[Any]) -> None:
    """:class:`InputError` naming ``images`` when one entry repeats another: the same pixels, the same object
    (the same geometry object, or spheres of equal numbers) and the same mask. Its rows would count twice, as
    if the photo's noise were smaller than it is (the table then leans on it over the priors), and
    ``image_weights="cross"`` would weigh the photo against itself. The same photo with another sphere
    (two spheres in one photo) or a mask selecting other pixels is not a repeat. The pixels are compared
    only for entries of one geometry and mask (a single photo's are not read: no cost on the usual
    recovery)."""
    for k in range(1, len(images)):
        geometry = geometries[k]
        for j in range(k):
            other = geometries[j]
            same_object = other is geometry or (
                isinstance(geometry, (SphereGeometry, PerspectiveSphereGeometry))
                and type(other) is type(geometry) and other.record() == geometry.record())
            if same_object and _same_mask(masks[j], masks[k]) and _same_pixels(images[j], images[k]):
                raise InputError("images", f"image {k} repeats image {j} (the same pixels, object and mask): its "
                                 "pixels would count twice, as if the photo's noise were smaller than it is",
                                 "give each photo once; a photo of two spheres: one geometry each")


def recover(images: Union[np.ndarray, Sequence[np.ndarray]],
            probe: Union[Probe, Sequence[Probe]],
            geometry: Union[Geometry, Sequence[Geometry]],
            *,
            masks: Optional[Union[np.ndarray, Sequence[Optional[np.ndarray]]]] = None,
            n_normals: int = 8000,
            n_dirs: int = lighting.DEFAULT_DIRS,
            grid: Tuple[int, int] = (32, 32),
            alpha: Union[None, float, str] = None,
            pair_rule: str = solve_mod.DEFAULT_PAIR_RULE,
            image_weights: str = "cross",
            prior: Optional[prior_mod.Prior] = None,
            basis_prior: Union[BasisPrior, None, str] = "default",
            noise: Any = "auto",
            sampling: str = "mis",
            max_view_angle_deg: float = 80.0,
            footprint: Optional[float] = None,
            saturation: Optional[float] = None,
            seed: int = 0,
            keep_inputs: bool = True,
            visibility: bool = True) -> Recovery:
    """Recover a bivariate BRDF from HDR images of a sphere under known probes.

    Args:
        images: one ``(H, W, 3)`` linear image or a list of them (other views
            or other probes; all rows stack into one system). A photo given twice with the
            same geometry and mask is refused (its pixels would count twice).
        probe: the probe lighting each image (one for all, or one per image),
            in Mitsuba's envmap frame (y up).
        geometry: what each image shows, a :class:`~mi_bivariate.geometry.Geometry`:
            a sphere (:class:`SphereGeometry`, :class:`PerspectiveSphereGeometry`,
            pixels and camera pose) or a known mesh with its camera
            (:class:`mi_bivariate.mesh.MeshView`). Poses may differ per image.
        masks: optional ``(H, W) bool`` usable-pixel masks (one for all images, or one or ``None`` per
            image): the rows and the ``"auto"`` noise estimate use only their pixels.
        n_normals: normals M per image (uniform over the visible hemisphere).
        n_dirs: light directions K per normal (:data:`lighting.DEFAULT_DIRS`).
        grid: st grid ``(n_t, n_s)``.
        alpha: how the smoothness prior's weight is chosen: ``"discrepancy"`` (default), one
            alpha for the three channels by the discrepancy principle
            (:mod:`mi_bivariate.solve.discrepancy`: the largest alpha, at most
            :data:`solve.DEFAULT_ALPHA`, whose fit explains the image to within its expected
            error); ``"gcv"``, per channel by generalised cross-validation (:func:`solve.gcv_curve`;
            measured to over-fit clean images, see docs/recovery.md); or a number (every channel).
            The second stage (basis prior) keeps the first stage's alphas.
        pair_rule: which of the smoothness prior's two weight pairs each channel keeps:
            ``"evidence"`` (default; the pair under which the image is likelier,
            :mod:`mi_bivariate.solve.evidence`) or ``"residual"`` (the paper's: the lower
            data residual). The second stage keeps the first stage's pairs.
        image_weights: with several images, how their rows are weighted beyond each image's
            own scale and noise: ``"cross"`` (default; :func:`cross_image_factors`: an image
            whose table alone predicts the other images worse counts less) or ``"equal"``.
        prior: smoothness prior (default: the packaged one, resampled to ``grid``).
        basis_prior: the data-driven table prior (:mod:`mi_bivariate.basis_prior`):
            ``"default"`` the packaged one (learnt from the 73 shared MERL-NBRDF
            materials on 32 x 32, resampled to ``grid`` as the smoothness prior is), a
            :class:`BasisPrior` (on ``grid``), or
            ``None`` for the smoothness prior alone. With it the solve runs twice:
            the first estimate and its per-node confidence give the basis prior's
            prediction, which then joins Eq. 6 as a per-node Gaussian.
        noise: the camera's noise, variance ``a I + b`` in each image's units:
            ``(a, b)`` for every image (``a`` and ``b`` each a number or three, R, G, B),
            a list with one ``(a, b)`` or ``None`` per image, ``"auto"`` (default: estimated from each image's
            object, its lit pixels that ``geometry`` puts on the object and its mask keeps, less a 2 px rim, by
            :func:`noise.estimate_camera_noise`; ~0 for a clean rendering), or
            ``None`` (clean input; only the model error counts, see
            :func:`solve.row_sigma`). Measured on a 256-spp Mitsuba render of a
            Lambertian sphere under grace: median node error 1.0% with ``"auto"``,
            3.0% with ``None``.
        sampling: light-direction sampling of the lighting matrix
            (:func:`lighting.lighting_matrix`: ``"mis"`` or ``"uniform"``).
        max_view_angle_deg: drop normals further than this from the view.
        footprint: the pixel-footprint model for orthographic spheres
            (:func:`capture.observations_from_sphere`): ``None`` (default, the
            paper's centre normals) or the largest normal spread, degrees, one
            sub-pixel sample stands for (e.g. ``2.0``, with
            ``max_view_angle_deg`` up to 88; see ``benchmarks/bench_footprint.py``).
        saturation: drop pixels with any channel at or above this value.
        seed: seeds normal selection and light directions.
        visibility: for mesh views, trace shadow rays against the mesh so
            that directions it blocks itself contribute nothing (the paper
            ignores this; it matters for non-convex shapes).
    """
    ensure_variant(vectorised=True)  # a front door: the lighting matrix needs a JIT variant
    images = _image_list(images)
    n = len(images)
    # shapes and number types before the noise estimate reads the pixels
    images = [capture.check_image(image, f"image {k}" if n > 1 else "image") for k, image in enumerate(images)]
    probe_list = _as_list(probe, n, "probes", "probe")
    geometries = _geometry_list(geometry, n)
    mask_list = _as_list(masks, n, "masks", "masks")
    # their shapes before the noise estimate reads them
    mask_list = [capture.check_mask(mask, image.shape[:2], f"image {k}" if n > 1 else "image")
                 for k, (mask, image) in enumerate(zip(mask_list, images))]
    _refuse_repeated_images(images, geometries, mask_list)
    n_t, n_s = limits.check_grid(grid)
    limits.check_recovery_sizes(n_normals, n_dirs, (n_t, n_s))
    n_normals, n_dirs, seed = int(n_normals), int(n_dirs), limits.check_seed(seed)
    if prior is not None and not isinstance(prior, prior_mod.Prior):
        raise InputError("prior", f"expected a mi_bivariate.prior.Prior or None, got a {type(prior).__name__}",
                         "load one with Prior.load(path); a BasisPrior goes to basis_prior")
    _check_angle("max_view_angle_deg", max_view_angle_deg)
    if footprint is not None:
        _check_angle("footprint", footprint)
    if saturation is not None and not (isinstance(saturation, numbers.Real) and not isinstance(saturation, bool)
                                       and saturation > 0.0):
        raise InputError("saturation", f"must be a positive number or None, got {saturation!r}")
    given = solve_mod.check_alpha(alpha)  # fail before the lighting matrix
    if not isinstance(given, str) and np.any(given == 0.0):
        warnings.warn("alpha 0: no smoothness prior, so the nodes the image barely constrains are free, and the "
                      "table can reach absurd values there (measured: 4e19 1/sr on a 64 px sphere); use the "
                      "default ('discrepancy') or a small alpha such as 1e-4", InputWarning, stacklevel=2)
    solve_mod.check_pair_rule(pair_rule)
    basis = _basis_prior(basis_prior, n_t, n_s)  # its type and grid checked before the lighting matrix
    if image_weights not in IMAGE_WEIGHTS:
        raise InputError("image_weights", f"unknown rule {image_weights!r}", f"use one of {', '.join(IMAGE_WEIGHTS)}")
    for k, item in enumerate(probe_list):  # before any work: a wrong object or a black probe
        source = "probe" if n == 1 else f"probe {k}"
        check_lit(check_probe(item, source), source)
    noise_models = _noise_list(noise, images, geometries, mask_list)  # its form checked, "auto" estimated, before work

    timings: Dict[str, float] = {}
    t0 = time.perf_counter()
    parts = []
    for k, (image, geo, mask) in enumerate(zip(images, geometries, mask_list)):
        obs = capture.image_observations(image, geo, n_normals=n_normals, max_view_angle_deg=max_view_angle_deg,
                                         saturation=saturation, mask=mask, seed=seed + k, footprint=footprint,
                                         source=f"image {k}" if n > 1 else "image")
        parts.append(obs.with_probe_index(k))
        _check_grey_photo(obs.values, probe_list[k], f"image {k}" if n > 1 else "image")
    observations = capture.stack(parts)
    timings["observations"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    occluders = [geo.occluder() if visibility else None for geo in geometries]
    L = lighting.lighting_matrix(observations, probe_list, n_t=n_t, n_s=n_s, n_dirs=n_dirs, seed=seed,
                                 occluder=occluders if any(o is not None for o in occluders) else None,
                                 sampling=sampling)
    timings["lighting matrix"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    report = adequacy.analyse(L, n_t=n_t, n_s=n_s, probes=probe_list, warn=True)
    timings["adequacy"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if prior is None:
        prior = prior_mod.default_prior()
    if (prior.n_t, prior.n_s) != (n_t, n_s):
        prior = prior.resampled(n_t, n_s)
    with blas_threads():  # no BLAS oversubscription on a shared machine (mi_bivariate.threads)
        sigma = solve_mod.row_sigma(observations.values, observations.image_index, noise=noise_models)
        _check_noise_against_signal(sigma, observations.values)
        row_noise = sigma
        factors = np.ones(n)
        if image_weights == "cross" and n > 1:
            t1 = time.perf_counter()
            found = cross_image_factors(L, observations.values, observations.image_index, sigma, prior, alpha,
                                        basis, pair_rule)
            factors[: len(found)] = found
            sigma = sigma * factors[observations.image_index][:, None]
            timings["image weights"] = time.perf_counter() - t1
            t0 += timings["image weights"]
        data = solve_mod.prepare_data_term(L, observations.values, sigma)
        limits.check_table_level(data.level, "image" if n == 1 else "images")
        timings["normal equations"] = time.perf_counter() - t0
        solution = solve_stages(data, prior, alpha, basis, pair_rule)
        timings["solve"] = time.perf_counter() - t0 - timings["normal equations"]
        table = solution.table
        predicted = solution.predicted  # L f, as the solve computed it for its residuals (its last stage's)
    _check_explained(observations.values, predicted, row_noise, observations.image_index, n)
    level = np.where(data.level > 0, data.level, 1.0)
    confidence = {
        "measured": solution.measured,
        "resolution": solution.resolution,
        "posterior_std": solution.posterior_std,
        "observation_weight": (np.stack([np.diag(g) for g in data.gram], axis=-1) * level**2).reshape(n_t, n_s, 3),
    }
    brdf = BivariateBRDF(table, confidence=confidence, provenance={
        "method": "passive reflectometry (Romeiro et al. 2008), mi_bivariate.recover",
        "images": n, "normals": int(len(observations.values)), "light_directions": int(n_dirs),
        "sampling": sampling, "alpha": [float(a) for a in solution.alphas], "alpha_rule": solution.alpha_rule,
        "prior_winner": list(solution.winner), "prior_pair_rule": solution.pair_rule, "seed": int(seed),
        "image_weights": image_weights, "image_sigma_factors": [float(v) for v in factors],
        "basis_prior": None if basis is None else {"materials": len(basis.materials),
                                                    "components": int(basis.basis.shape[1]),
                                                    "grid": [basis.n_t, basis.n_s],
                                                    "resampled_from": basis.provenance.get("resampled_from")},
        "noise": None if noise_models is None else [None if v is None else [np.asarray(x).tolist() for x in v]
                                                    for v in noise_models],
        "geometries": [g.record() if hasattr(g, "record") else {"type": type(g).__name__} for g in geometries],
        "probes": [getattr(p, "source", "?") for p in probe_list],
        "probe_to_world": [np.asarray(getattr(p, "to_world", np.eye(4))).tolist() for p in probe_list],
        "visibility": bool(any(o is not None for o in occluders)),
        "confidence": "measured: 1 - posterior variance / the priors' own variance (1: the image set the "
                      "node, 0: the priors did); resolution: diag of the model resolution matrix; "
                      "posterior_std: 1/sr; observation_weight: diag(L^T W L) times the table level^2",
    })
    return Recovery(brdf=brdf, observations=observations, lighting_matrix=L, solution=solution,
                    adequacy=report, predicted=predicted,
                    images=[np.array(image, copy=True) for image in images] if keep_inputs else [],
                    geometries=geometries,
                    probes=probe_list, timings=timings)


def _basis_prior(value: Union[BasisPrior, None, str], n_t: int, n_s: int) -> Optional[BasisPrior]:
    if value is None or isinstance(value, BasisPrior):
        if value is not None and (value.n_t, value.n_s) != (n_t, n_s):
            raise InputError("basis_prior", f"is learnt on a {value.n_t} x {value.n_s} grid, the recovery "
                             f"uses {n_t} x {n_s}", "learn one on this grid (mi-bivariate learn-prior --grid), or "
                             "recover without it (basis_prior=None; recover --no-basis-prior)")
        return value
    if value != "default":
        raise InputError("basis_prior", f"must be 'default', None or a BasisPrior, got {value!r}")
    packaged = default_basis_prior()
    return None if packaged is None else packaged.resampled(n_t, n_s)


#: How far (4-neighbour pixel steps) the noise estimate reaches beyond the pixels on the object: its
#: antialiased rim (a render's pixel filter spreads it ~1-2 px), not the background.
NOISE_MARGIN_PX = 2
#: ... and the estimate's region eroded by this many pixels (see :func:`_estimate_noise`).
NOISE_EROSION_PX = 2

#: The largest median ratio of a row's noise to its value that a recovery accepts: beyond it the
#: image says nothing the priors do not (and the normal equations lose the data term).
MAX_NOISE_TO_SIGNAL = 10.0


def _check_noise_against_signal(sigma: np.ndarray, values: np.ndarray) -> None:
    """Refuse a noise model that swamps the image (``sigma``, ``values``: ``(M, 3)``): in every channel
    with signal, the median over its lit rows of noise / value is above :data:`MAX_NOISE_TO_SIGNAL`.
    Dark rows and channels without signal (a red material's G and B) do not count."""
    ratios = [float(np.median(sigma[lit, c] / values[lit, c]))
              for c in range(values.shape[1]) for lit in [values[:, c] > 0.0] if np.any(lit)]
    if ratios and min(ratios) > MAX_NOISE_TO_SIGNAL:
        raise InputError("noise", f"the rows' noise is {min(ratios):.3g} times their value (the median over lit "
                                  "rows, in the channel where it is smallest): the image would carry no information",
                         "check the noise model (--noise A,B): variance a I + b, with I a pixel value in the "
                         "image's units")


#: The least fraction of an image's variation about its mean (per channel) that the recovered table must
#: explain, ``1 - ||I - L f||^2 / ||I - mean(I)||^2``, before the recovery warns that the probe, the camera
#: or the sphere may not match the photo. Measured (64 px spheres, 64 spp, a Lambertian and a glossy lobe,
#: under grace_latlong_1k and a synthetic sky): 0.89-0.96 with the right probe; with the probe upside down
#: -1.5 to -0.3, turned 90 degrees about the vertical 0.31-0.56.
MIN_EXPLAINED = 0.5
#: The fit check leaves out this fraction of an image's rows, those of the largest residuals: one
#: Monte Carlo firefly row (a residual of 5.6 where the median pixel is 0.009, a 64 px sphere at
#: 16 spp) made a self-consistent render "explain 48%" of itself. A probe that does not match
#: misfits most rows, not 1%.
EXPLAINED_TRIM = 0.01


def _check_explained(values: np.ndarray, predicted: np.ndarray, sigma: np.ndarray, image_index: np.ndarray,
                     n_images: int) -> None:
    """Warn for each image whose rows (but the :data:`EXPLAINED_TRIM` of the largest residuals) the recovered
    table explains less than :data:`MIN_EXPLAINED` of,
    unless its residual is within four times its noise (``sum r^2 <= 16 sum sigma^2``): a noise estimate
    can be several times low (Monte Carlo noise, docs/recovery.md section 5), and a fit that close to
    it says nothing about the probe (measured: a 24 px, 4 spp sphere under a uniform probe, 2.7 sigma).

    ``values``, ``predicted``, ``sigma``: ``(M, 3)`` rows in image units; ``image_index``: ``(M,)``.
    """
    for k in range(n_images):
        rows = np.flatnonzero(image_index == k)
        if not len(rows):
            continue
        row_residual = np.sum((np.asarray(values[rows], np.float64) - predicted[rows]) ** 2, axis=1)
        if len(rows) >= 1.0 / EXPLAINED_TRIM:  # leave out the rows of the largest residuals
            rows = rows[row_residual <= np.quantile(row_residual, 1.0 - EXPLAINED_TRIM)]
        v = np.asarray(values[rows], np.float64)
        residual = float(np.sum((v - predicted[rows]) ** 2))
        if residual <= 16.0 * float(np.sum(np.square(sigma[rows], dtype=np.float64))):
            continue
        spread = float(np.sum((v - v.mean(axis=0)) ** 2))
        explained = 1.0 - residual / spread if spread > 0.0 else -np.inf
        if explained >= MIN_EXPLAINED:
            continue
        rel = np.sqrt(residual / max(float(np.sum(v * v)), 1e-300))
        source = f"image {k}" if n_images > 1 else "image"
        warnings.warn(f"{source}: the recovered table explains {100.0 * max(explained, 0.0):.0f}% of the image's "
                      f"variation (relative residual {rel:.2f}): the probe, the camera or the sphere may not match "
                      f"the photo (check the probe's orientation: a shared probe carries its rotation, another "
                      f"file is read as stored, --probe-rotation or Probe.rotated turns it; --fov for a perspective "
                      f"photo; --sphere)",
                      InputWarning, stacklevel=3)


#: A probe whose mean colour's channels differ by more than this ratio is coloured (:func:`_check_grey_photo`).
GREY_PROBE_RATIO = 1.05


def _check_grey_photo(values: np.ndarray, probe: Probe, source: str) -> None:
    """Warn when a grey photo (``values``: ``(M, 3)`` rows with R = G = B, e.g. a one-channel EXR) is lit
    by a coloured probe: each channel's table is then fitted to light of another colour than the pixels
    show, and the recovered colour is the probe's inverse, not the material's."""
    if not len(values) or np.any(values[:, 0] != values[:, 1]) or np.any(values[:, 0] != values[:, 2]):
        return
    mean = np.asarray(probe.mean_radiance(), np.float64)
    if mean.min() > 0.0 and mean.max() <= GREY_PROBE_RATIO * mean.min():
        return
    warnings.warn(f"{source}: the photo is grey (R = G = B on the object) but the probe is coloured (mean RGB "
                  f"{', '.join(f'{v:.3g}' for v in mean)}): the recovered table's colour will be the probe's "
                  "inverse, not the material's (give an RGB photo, or a grey probe for a grey photo)",
                  InputWarning, stacklevel=3)


def _noise_list(noise: Any, images: Sequence[np.ndarray], geometries: Sequence[Geometry],
                masks: Sequence[Optional[np.ndarray]]) -> Optional[list]:
    """Per-image ``(a, b)`` (or None) from ``"auto"`` (estimated on each image's object, within its checked
    ``(H, W) bool`` mask or ``None``), one pair, a list, or None."""
    n = len(images)
    if noise is None:
        return None
    if isinstance(noise, str):
        if noise != "auto":
            raise InputError("noise", f"must be 'auto', (a, b), a list or None, got {noise!r}")
        return [_estimate_noise(img, geo, f"image {k}" if n > 1 else "image", mask)
                for k, (img, geo, mask) in enumerate(zip(images, geometries, masks))]
    if isinstance(noise, numbers.Real) or (isinstance(noise, np.ndarray) and noise.ndim == 0):
        raise InputError("noise", f"got one number ({float(noise):g}); give the pair (a, b) of the variance a I + b",
                         "e.g. noise=(0, sigma**2) for a constant sigma")
    if not isinstance(noise, (list, tuple, np.ndarray)):
        raise InputError("noise", f"must be 'auto', (a, b), a list or None, got a {type(noise).__name__}",
                         "e.g. noise=(0, sigma**2) for a constant sigma, or one (a, b) or None per image")
    if _one_noise_model(noise):
        return [check_noise_model(noise, "noise")] * n
    items = list(noise)
    if len(items) != n:
        raise InputError("noise", f"{len(items)} noise models given for {n} images",
                         "give one (a, b) for every image, or a list of one (a, b) or None per image")
    return [None if v is None else check_noise_model(v, f"noise[{k}]" if n > 1 else "noise")
            for k, v in enumerate(items)]


def _one_noise_model(noise: Sequence) -> bool:
    """Whether ``noise`` reads as one ``(a, b)`` for every image (two numbers, or two ``(R, G, B)``), not as
    a list of one model (a pair) or ``None`` per image."""
    def entry(v: Any) -> bool:
        try:
            shape = np.shape(v)
        except ValueError:  # ragged
            return False
        return v is not None and (shape == () or shape == (3,))
    return len(noise) == 2 and all(entry(v) for v in noise)


def _estimate_noise(image: np.ndarray, geometry: Geometry, source: str,
                    mask: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Per-channel ``(a, b)`` of one image (see :mod:`noise`) over the object's lit interior: the lit pixels
    within :data:`NOISE_MARGIN_PX` of the pixels ``geometry`` puts on the object (so its antialiased rim, but
    no lit or textured background, whose own detail would read as noise) and inside the user's ``mask``
    (``(H, W) bool``, checked; ``None``: every pixel), eroded by 2 px (the rim's pixels mix object and
    background, and the mask's edge pixels may mix in what it leaves out: a label, another object's
    highlight)."""
    from scipy import ndimage  # as the sphere fit, which a recovery from a photo has run already

    # All of it within the object's box, widened by what the dilation and the erosion reach (and a pixel):
    # beyond it the region is empty, and a photo's frame may be mostly background.
    height, width = image.shape[:2]
    on_object = geometry.object_mask(width, height, source)
    reach = NOISE_MARGIN_PX + NOISE_EROSION_PX + 1
    rows, cols = bounding_box(on_object)
    rows = slice(max(rows.start - reach, 0), min(rows.stop + reach, height))
    cols = slice(max(cols.start - reach, 0), min(cols.stop + reach, width))
    crop, on_object = image[rows, cols], on_object[rows, cols]
    lit = np.ones(crop.shape[:2], dtype=bool)
    with np.errstate(invalid="ignore"):
        for c in range(3):  # finite and positive in every channel
            lit &= (crop[..., c] > 0) & (crop[..., c] < np.inf)
    near = ndimage.binary_dilation(on_object, iterations=NOISE_MARGIN_PX)  # 4-neighbour steps
    # The frame's own rows and columns are left as they are: there the object is cut, not mixed.
    interior = np.zeros_like(lit)
    interior[max(1 - rows.start, 0):height - 1 - rows.start, max(1 - cols.start, 0):width - 1 - cols.start] = True
    region = lit & near if mask is None else lit & near & mask[rows, cols]
    inner = ndimage.binary_erosion(region, iterations=NOISE_EROSION_PX, border_value=1,
                                   mask=None if interior.all() else interior)  # (the masked erosion is 1.7x slower)
    try:
        pairs = [estimate_camera_noise(crop[..., c], inner, source) for c in range(3)]
    except InputError as exc:
        warnings.warn(f"{source}: {exc.problem}; assuming a clean image (only the model error)",
                      InputWarning, stacklevel=3)
        return None
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


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


def refine_sphere_and_recover(image: np.ndarray, probe: Probe, first: Recovery, **kwargs) -> Recovery:
    """Refine ``first``'s sphere by the image's shading, then recover again under the refined sphere.

    The silhouette fit of a glossy sphere can be 0.3-0.6 px off (its rim darkens); the centre
    and radius under which the bivariate model explains the image best are found by
    :func:`mi_bivariate.sphere_refine.refine_sphere`, with ``first``'s alpha and prior variant
    per channel and its camera-noise model, and the table recovered again under them. Measured
    on 8 materials under grace_latlong_1k (256 px, leave-one-out priors, docs/recovery.md section
    9): median relight error 1.17x the exact geometry's with the silhouette fit, 1.01x refined.
    Costs 10-32 s on two cores.

    A minimum found more than :data:`mi_bivariate.sphere_refine.MAX_SHIFT_PX` from the starting
    outline is not taken, nor is a sphere too small to refine, nor one whose recovery fits the
    image worse than ``first`` by more than :data:`~mi_bivariate.sphere_refine.MAX_RESIDUAL_RISE`
    (relative residual over the pixels both use): it warns and returns ``first`` (sphere and
    table), with the refinement recorded in its provenance. The user's normals,
    directions and footprint do not apply to the refinement (M 2000, K 2000, centre normals, view
    angles up to :data:`~mi_bivariate.sphere_refine.MAX_VIEW_ANGLE_DEG` or the user's, if lower).

    Args:
        image: the ``(H, W, 3)`` image ``first`` was recovered from (one image, orthographic sphere).
        probe: its probe.
        first: the recovery under the starting sphere.
        kwargs: :func:`recover`'s options, the same as ``first``'s.

    Returns:
        The new :class:`Recovery`, with ``sphere_refinement`` set and recorded in the table's provenance.
    """
    if len(first.geometries) != 1:
        raise InputError(None, "refining the sphere needs a recovery from one image")
    mask = kwargs.get("masks")
    try:
        refinement = sphere_refine.refine_sphere(
            image, probe, first.geometries[0], alphas=first.solution.alphas, winner=first.solution.winner,
            prior=kwargs.get("prior"), grid=kwargs.get("grid", (32, 32)), saturation=kwargs.get("saturation"),
            mask=mask[0] if isinstance(mask, (list, tuple)) else mask, seed=kwargs.get("seed", 0),
            sampling=kwargs.get("sampling", "mis"), noise=(first.brdf.provenance.get("noise") or [None])[0],
            max_view_angle_deg=min(sphere_refine.MAX_VIEW_ANGLE_DEG, kwargs.get("max_view_angle_deg", 80.0)))
    except InputError as exc:  # the first recovery stands
        warnings.warn(f"image: sphere not refined: {exc.problem}; kept the fitted sphere", InputWarning, stacklevel=2)
        first.brdf.provenance["sphere_refinement"] = {"accepted": False, "status": exc.problem}
        return first
    if refinement.accepted:
        t0 = time.perf_counter()
        result = recover(image, probe, refinement.geometry, **kwargs)
        before, after = _residuals_on_common_pixels(first, result)
        if after > sphere_refine.MAX_RESIDUAL_RISE * before:  # the objective led astray: the first recovery stands
            refinement = replace(refinement, accepted=False, geometry=refinement.start, reason=(
                f"the recovery under the refined sphere fits the image worse (relative residual {after:.4f} "
                f"against {before:.4f} on the pixels both use)"))
            first.timings = {"refined recovery (given up)": time.perf_counter() - t0, **first.timings}
    if not refinement.accepted:
        warnings.warn(f"image: {refinement.rejection()}", InputWarning, stacklevel=2)  # the summary has the numbers
        result = first  # its table stands; the refinement is recorded on it
    result.sphere_refinement = refinement
    result.timings = {"sphere refinement": refinement.seconds, **result.timings}
    start, end, found = refinement.start, refinement.geometry, refinement.found
    result.brdf.provenance["sphere_refinement"] = {
        "start": [start.cx, start.cy, start.radius], "refined": [end.cx, end.cy, end.radius],
        "found": [found.cx, found.cy, found.radius], "accepted": refinement.accepted, "status": refinement.status,
        "cost": [refinement.cost_start, refinement.cost], "evaluations": refinement.evaluations,
        "rejection": refinement.rejection()}
    return result


def _residuals_on_common_pixels(a: Recovery, b: Recovery) -> Tuple[float, float]:
    """``||I - L f|| / ||I||`` of two recoveries of one image over the pixels both observe (each under
    its own sphere: their lattices and dropped rims differ)."""
    width = 1 + int(max(a.observations.pixels[:, 1].max(), b.observations.pixels[:, 1].max()))
    keys = [o.pixels[:, 0].astype(np.int64) * width + o.pixels[:, 1] for o in (a.observations, b.observations)]
    _, ia, ib = np.intersect1d(keys[0], keys[1], assume_unique=True, return_indices=True)
    out = []
    for rec, rows in ((a, ia), (b, ib)):
        values = np.asarray(rec.observations.values, np.float64)[rows]
        out.append(float(np.linalg.norm(values - rec.predicted[rows]) / max(np.linalg.norm(values), 1e-30)))
    return out[0], out[1]


def recover_from_photo(image: np.ndarray, probe: Probe, *, intrinsics: Any = None,
                       sphere: Optional[Sequence[float]] = None, mask: Optional[np.ndarray] = None,
                       camera_to_world: Any = None, saturation: Union[None, float, str] = "auto",
                       estimate_yaw: bool = False, yaw_kwargs: Optional[dict] = None,
                       refine_sphere: bool = False, source: str = "image", **kwargs) -> Recovery:
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
        mask: optional ``(H, W) bool`` user mask of the sphere: the fit, the yaw estimate and the
            recovery use its pixels only.
        camera_to_world: ``(3, 3)`` camera rotation in the probe's frame.
        saturation: drop pixels at or above this value; ``"auto"``: the
            image's maximum when highlights sit on a plateau there (clipped).
        estimate_yaw: first estimate the probe's rotation about the vertical
            (:func:`mi_bivariate.alignment.estimate_yaw`) and recover under
            the aligned probe (the main error source for captured data).
        yaw_kwargs: options for :func:`~mi_bivariate.alignment.estimate_yaw`.
        refine_sphere: then refine the sphere by the image's shading and recover again
            (:func:`refine_sphere_and_recover`; orthographic only, 10-32 s).
        kwargs: passed to :func:`recover`.

    Returns:
        The :class:`Recovery`, with ``sphere_fit`` (and ``alignment``) set.
    """
    if refine_sphere and intrinsics is not None:
        raise InputError(source, "refine_sphere models an orthographic view only", "leave it out with intrinsics")
    if mask is not None and kwargs.get("masks") is not None:
        raise InputError("masks", "both mask and masks are given", "give the sphere's mask once, as mask")
    image = capture.check_image(image, source)  # before the sphere fit and the saturation level read its pixels
    fit = spherefit.fit_sphere(image, mask, sphere=sphere, intrinsics=intrinsics,
                               camera_to_world=camera_to_world, source=source)
    if isinstance(saturation, str):
        if saturation != "auto":
            raise InputError("saturation", f"must be a number, None or 'auto', got {saturation!r}")
        region = fit.region if fit.region is not None else None
        saturation = _auto_saturation(image, region)
    alignment = None
    if estimate_yaw:
        alignment = alignment_mod.estimate_yaw(image, probe, fit.geometry,
                                               **{"saturation": saturation, "mask": mask, **(yaw_kwargs or {})})
        probe = alignment.probe
    if mask is not None:  # the user's mask limits the recovery's pixels too, not only the fit's
        kwargs["masks"] = mask
    result = recover(image, probe, fit.geometry, saturation=saturation, **kwargs)
    if refine_sphere:
        result = refine_sphere_and_recover(image, probe, result, saturation=saturation, **kwargs)
    result.sphere_fit = fit
    result.alignment = alignment
    return result
