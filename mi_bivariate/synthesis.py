"""Analysis by synthesis: the bivariate table fitted by differentiable rendering.

The baseline against which the linear route (observations -> lighting matrix
-> constrained solve, :func:`mi_bivariate.recover.recover`) is measured. The
same ``(n_t, n_s, 3)`` table is optimised with ``mi.ad.Adam`` through the
``bivariate`` plugin and the ``prb`` integrator so that a render of the
sphere matches the input image:

- variable: ``log f`` (positivity without clamping; the step is relative);
- start: the Lambertian fit, the best constant table for the image
  (``f_c = <L 1, y> / ||L 1||^2`` per channel from the same lighting matrix
  the linear solve uses), like the solve's own start;
- loss: mean squared pixel error over the sphere relative to the image's
  mean square, plus ``smoothness`` times the mean squared first difference of
  ``log f`` along both st axes (the role of the solve's smoothness prior:
  cells the image barely constrains follow their neighbours instead of
  drifting on gradient noise);
- estimator: ``spp`` samples per pixel per iteration, a new seed per
  iteration, the table's own importance sampling (``sampling="table"``,
  rebuilt from the current table at every update), ``max_depth`` 2 (direct
  illumination by the probe, as in the image model).

The plugin's table gradients under ``prb`` with table importance sampling
are checked against central finite differences in ``tests/test_gradients.py``.

The linear route is measured at the configuration's sizes and on a ladder
of cheaper ones (:data:`LINEAR_LADDER`: fractions of the configuration's
sampled normals ``M`` and lighting directions ``K``; :data:`LADDER_GRIDS`:
the same and the configuration's own sizes on a coarser st grid, with priors
chosen on it; fixed in advance, the same for every material), so that both
routes have a curve of error against wall time and
"time to equal error" means, for each route, the least time at which it
reached that error (:func:`time_to_error`).

The input is path traced (the config's resolution and spp: a photo's noise and
pixel footprint, the forward model analysis by synthesis itself uses). Errors are
scored as the evaluation scores them: the relative RMSE of a render under a
novel probe by the evaluation's renderer (by default the converged quadrature of
:mod:`mi_bivariate.reference`, ~0.1% noise, measured and returned) against the
3D truth rendered the same way, beside the exact reduction's (the relight
floor), and the BRDF errors of :class:`mi_bivariate.metrics.BRDFErrors`. The
clock stops while errors are measured.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass, replace
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate import capture, metrics, render
from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.evaluate.config import EvalConfig
from mi_bivariate.evaluate.protocol import MaterialTask, choose_priors
from mi_bivariate.evaluate.renders import Renderer, Shot
from mi_bivariate.geometry import SphereCamera
from mi_bivariate.recover import Recovery, recover
from mi_bivariate.sources import MaterialSpec, load_probe, load_truth, probe_label, resolve_materials
from mi_bivariate.variants import ensure_variant

#: Cheaper linear routes measured beside the configuration's: fractions of its
#: ``(n_normals, n_dirs)`` (fixed in advance, the same for every material).
LINEAR_LADDER: Tuple[float, ...] = (1 / 8, 1 / 4, 1 / 2)

#: Smallest ``n_normals`` / ``n_dirs`` of a ladder rung.
LADDER_MIN = 250

#: Coarser st grids measured beside the configuration's: fractions of its sides (each rung of the
#: ladder and the configuration's own sizes again on each coarser grid; the solve's cost grows with
#: the cube of the node count, so a grid is the linear route's largest cost setting).
LADDER_GRIDS: Tuple[float, ...] = (1 / 2,)

#: Fewest nodes per side of a coarser ladder grid.
LADDER_GRID_MIN = 4

#: Timed stages of the linear route (:attr:`mi_bivariate.recover.Recovery.timings`).
LINEAR_STAGES = ("observations", "lighting matrix", "adequacy", "normal equations", "solve")


@dataclass(frozen=True)
class SynthesisSettings:
    """Settings of :func:`optimise_table` (one setting for every material: not tuned per material).

    Attributes:
        spp: samples per pixel of each iteration's render.
        learning_rate: Adam step on ``log f`` (a relative step of about this size per iteration).
        smoothness: weight of the ``log f`` first-difference penalty.
        sampling: the plugin's ``sampling`` property (``"table"`` or ``"cosine"``).
        max_depth: ``prb``'s path depth (2: direct illumination).
        log_bounds: ``log f`` is kept in this range (1/sr).
        seed: seed of the first iteration (iteration ``i`` uses ``seed + i``).
    """

    spp: int = 16
    learning_rate: float = 0.05
    smoothness: float = 1e-3
    sampling: str = "table"
    max_depth: int = 2
    log_bounds: tuple = (-14.0, 9.0)
    seed: int = 1000

    def __post_init__(self) -> None:
        """Refuse settings the optimiser cannot use (:class:`InputError`)."""
        def number(value: Any) -> bool:
            return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
                and math.isfinite(value)

        if not (isinstance(self.spp, (int, np.integer)) and self.spp >= 1):
            raise InputError("spp", f"must be a whole number >= 1 (samples per pixel per iteration), got {self.spp!r}")
        if not (number(self.learning_rate) and self.learning_rate > 0):
            raise InputError("learning_rate", f"must be a finite number > 0, got {self.learning_rate!r}")
        if not (number(self.smoothness) and self.smoothness >= 0):
            raise InputError("smoothness", f"must be a finite number >= 0, got {self.smoothness!r}")
        if self.sampling not in ("table", "cosine"):
            raise InputError("sampling", f"must be 'table' or 'cosine', got {self.sampling!r}")
        if not (isinstance(self.max_depth, (int, np.integer)) and (self.max_depth >= 2 or self.max_depth == -1)):
            raise InputError("max_depth", f"must be >= 2 (2: direct illumination; -1: unlimited), got "
                                          f"{self.max_depth!r}", "depth 1 renders no reflection, only the emitters")
        bounds = tuple(self.log_bounds)
        if not (len(bounds) == 2 and all(number(b) for b in bounds) and bounds[0] < bounds[1]):
            raise InputError("log_bounds", f"must be two finite numbers (low, high), low < high, "
                                           f"got {self.log_bounds!r}")


def lambertian_start(L: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The best constant BRDF per channel: ``<L 1, y> / ||L 1||^2``, ``(3,) float64`` in 1/sr (>= 0).

    Args:
        L: ``(M, N, 3)`` lighting matrix.
        values: ``(M, 3)`` observed pixels.
    """
    row_sums = np.asarray(L, np.float64).sum(axis=1)  # (M, 3): L applied to the all-ones table
    y = np.asarray(values, np.float64)
    num = np.einsum("mc,mc->c", row_sums, y)
    den = np.einsum("mc,mc->c", row_sums, row_sums)
    return np.maximum(np.divide(num, den, out=np.zeros(3), where=den > 0), 0.0)


def optimise_table(image: np.ndarray, mask: np.ndarray, probe: Any, start: np.ndarray,
                   settings: SynthesisSettings = SynthesisSettings(), budget_s: float = 60.0,
                   max_iterations: int = 100000, eval_every: int = 10,
                   on_checkpoint: Optional[Callable[[int, float, float, np.ndarray], bool]] = None) -> Dict[str, Any]:
    """Fit a bivariate table to one image of the unit sphere by Adam through ``prb``.

    Args:
        image: ``(R, R, 3)`` linear input render (orthographic camera of
            :func:`mi_bivariate.render.render_sphere`, radius fraction 0.45).
        mask: ``(R, R) bool`` sphere pixels.
        probe: the :class:`~mi_bivariate.probes.Probe` lighting the image.
        start: ``(n_t, n_s, 3)`` positive starting table (1/sr).
        settings: see :class:`SynthesisSettings`.
        budget_s: optimisation wall time (the clock excludes checkpoints).
        max_iterations: iteration cap.
        eval_every: call ``on_checkpoint`` every this many iterations (and at the end).
        on_checkpoint: ``(iteration, clock_s, loss, table) -> stop?``; its time is not counted.

    Returns:
        ``{"iterations", "time_s", "losses" (per iteration), "table" (final, (n_t, n_s, 3))}``.

    Raises:
        InputError: an image that is not a square RGB image, a mask of another size or without a
        usable sphere pixel, a sphere that is black, ``eval_every`` < 1. Sphere pixels holding NaN or
        infinities are left out of the loss (as the linear route leaves them out), with a warning.
    """
    image, mask = _checked_image_mask(image, mask)
    if int(eval_every) < 1:
        raise InputError("eval_every", f"must be at least 1 (iterations between checkpoints), got {eval_every!r}")
    start = np.ascontiguousarray(np.maximum(np.asarray(start, np.float32), 1e-6))
    res = image.shape[0]
    cam = SphereCamera.create("orthographic", res, radius_fraction=0.45)
    scene_dict = render.sphere_scene_dict({"type": "bivariate", "table": mi.Bitmap(start),
                                           "sampling": settings.sampling}, probe, cam, normals=False)
    scene_dict["integrator"] = {"type": "prb", "max_depth": settings.max_depth, "hide_emitters": True}
    scene = render.load_scene(scene_dict)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("bsdf.table"))
    params.keep(key)

    m3 = np.repeat(mask[..., None], 3, axis=2)
    weight = mi.TensorXf(m3.astype(np.float32))
    reference = mi.TensorXf(np.where(m3, image, 0.0).astype(np.float32))
    norm = float(np.mean(np.asarray(image, np.float64)[mask] ** 2)) * float(m3.sum())
    n_t, n_s = start.shape[:2]
    n_diff = float(3 * ((n_t - 1) * n_s + n_t * (n_s - 1)))
    lo, hi = settings.log_bounds

    opt = mi.ad.Adam(lr=settings.learning_rate)
    opt["log_table"] = mi.TensorXf(np.log(start))
    losses: List[float] = []
    clock = 0.0
    it = 0

    def table_now() -> np.ndarray:
        return np.exp(np.asarray(opt["log_table"].numpy(), np.float64))

    while it < max_iterations:
        t0 = time.perf_counter()
        log_table = opt["log_table"]
        params[key] = dr.exp(log_table)
        params.update()
        rendered = mi.render(scene, params, spp=settings.spp, seed=settings.seed + it)
        data = dr.sum((rendered - reference) ** 2 * weight, axis=None) / norm
        loss = data
        if settings.smoothness > 0.0:
            g = log_table
            dt = g[1:, :, :] - g[:-1, :, :]
            ds = g[:, 1:, :] - g[:, :-1, :]
            loss = data + settings.smoothness * (dr.sum(dt * dt, axis=None) + dr.sum(ds * ds, axis=None)) / n_diff
        dr.backward(loss)
        grad = dr.grad(opt["log_table"])
        # A path through a degenerate configuration can give a NaN; drop it rather than poison the table.
        dr.set_grad(opt["log_table"], dr.select(dr.isfinite(grad), grad, 0.0))
        opt.step()
        opt["log_table"] = dr.clip(opt["log_table"], lo, hi)
        dr.eval(opt["log_table"])
        losses.append(float(data.array[0]))
        clock += time.perf_counter() - t0
        it += 1
        done = clock >= budget_s or it >= max_iterations
        if on_checkpoint is not None and (it % eval_every == 0 or done):
            if on_checkpoint(it, clock, losses[-1], table_now()):
                break
        if done:
            break
    return {"iterations": it, "time_s": clock, "losses": losses, "table": table_now()}


def _checked_image_mask(image: Any, mask: Any) -> Tuple[np.ndarray, np.ndarray]:
    """``(R, R, 3) float32`` image and ``(R, R) bool`` mask of its usable sphere pixels (non-finite ones
    dropped, with an :class:`InputWarning`), else :class:`InputError`."""
    image = capture.check_image(image, "image")
    if image.shape[0] != image.shape[1]:
        raise InputError("image", f"expected a square image of the sphere, got {image.shape[0]}x{image.shape[1]}",
                         "the orthographic camera of render.render_sphere renders R x R pixels")
    if mask is None:
        raise InputError("mask", "a mask of the sphere's pixels is needed",
                         "e.g. the mask of render.render_sphere's shot")
    mask = capture.check_mask(mask, image.shape[:2], "mask")
    finite = np.all(np.isfinite(image), axis=-1)
    dropped = int(np.count_nonzero(mask & ~finite))
    if dropped:
        warnings.warn(f"image: {dropped} sphere pixel(s) hold NaN or infinite values; left out of the loss",
                      InputWarning, stacklevel=3)
    mask = mask & finite
    if not mask.any():
        raise InputError("mask", "no sphere pixel to fit (the mask, less non-finite pixels, is empty)")
    if not np.any(image[mask] != 0.0):
        raise InputError("image", "the image is black on the sphere (every masked pixel is 0)",
                         "check the exposure and the mask")
    return image, mask


def time_to_error(points: Sequence[dict], target: float) -> Optional[dict]:
    """The fastest of ``points`` whose ``"relight"`` error is at most ``target``.

    Args:
        points: dicts with ``"time_s"`` (s) and ``"relight"`` (relative RMSE).
        target: the error to reach.

    Returns:
        That point, or ``None`` when none reaches ``target``.
    """
    reached = [p for p in points if p["relight"] <= target]
    return min(reached, key=lambda p: p["time_s"]) if reached else None


def ladder_sizes(n_normals: int, n_dirs: int, fractions: Sequence[float] = LINEAR_LADDER) -> List[Tuple[int, int]]:
    """The ladder's ``(n_normals, n_dirs)`` rungs below ``(n_normals, n_dirs)``, smallest first.

    Each rung is ``fraction`` x both sizes, at least :data:`LADDER_MIN`;
    rungs equal to each other or to the configuration itself are dropped.
    """
    rungs = {(max(LADDER_MIN, round(n_normals * f)), max(LADDER_MIN, round(n_dirs * f))) for f in fractions}
    rungs.discard((n_normals, n_dirs))
    return sorted(r for r in rungs if r[0] <= n_normals and r[1] <= n_dirs)


def ladder_grids(grid: Tuple[int, int], fractions: Sequence[float] = LADDER_GRIDS) -> List[Tuple[int, int]]:
    """The ladder's coarser st grids below ``grid``, finest first: each side x ``fraction``, at least
    :data:`LADDER_GRID_MIN`; grids that are not coarser than ``grid`` on both sides are dropped."""
    n_t, n_s = grid
    grids = {(max(LADDER_GRID_MIN, round(n_t * f)), max(LADDER_GRID_MIN, round(n_s * f))) for f in fractions}
    return sorted((g for g in grids if g[0] <= n_t and g[1] <= n_s and g != (n_t, n_s)), reverse=True)


def ladder_rungs(n_normals: int, n_dirs: int, grid: Tuple[int, int], fractions: Sequence[float] = LINEAR_LADDER,
                 grid_fractions: Sequence[float] = LADDER_GRIDS) -> List[Tuple[int, int, Tuple[int, int]]]:
    """Every ``(n_normals, n_dirs, grid)`` rung of the ladder: :func:`ladder_sizes` on ``grid``, then,
    on each of :func:`ladder_grids`, the same sizes and the configuration's own."""
    sizes = ladder_sizes(n_normals, n_dirs, fractions)
    rungs = [(m, k, tuple(grid)) for m, k in sizes]
    for g in ladder_grids(grid, grid_fractions):
        rungs += [(m, k, g) for m, k in [*sizes, (n_normals, n_dirs)]]
    return rungs


def linear_run(shot: Any, probe: Any, config: EvalConfig, n_normals: int, n_dirs: int,
               repeats: int, quiet: bool = False, priors: Tuple[Any, Any] = (None, "default")
               ) -> Tuple[Recovery, dict]:
    """The linear route (:func:`~mi_bivariate.recover.recover`) at ``n_normals`` x ``n_dirs`` on
    ``config.grid``, timed ``repeats`` times in this process (``quiet``: without its input warnings,
    e.g. a ladder rung's "few usable observations", which is the benchmark's choice, not the user's input), with
    ``priors`` = ``(prior, basis_prior)`` as :func:`~mi_bivariate.recover.recover` takes them.

    Returns:
        The last :class:`~mi_bivariate.recover.Recovery` and a point: ``n_normals``, ``n_dirs``,
        ``grid`` (``[n_t, n_s]``), ``time_s`` (median over the runs of the :data:`LINEAR_STAGES` summed,
        s), ``times_s`` (those sums, one per run), ``stage_runs`` (each run's stages, s) and ``stages`` (median of
        each stage over the runs, s; their sum need not be ``time_s`` on a loaded machine).
    """
    runs: List[Dict[str, float]] = []
    for _ in range(max(1, int(repeats))):
        with warnings.catch_warnings():
            if quiet:
                warnings.simplefilter("ignore", InputWarning)
            rec = recover(shot.image, probe, shot.geometry, n_normals=n_normals, n_dirs=n_dirs, grid=config.grid,
                          alpha=config.alpha, prior=priors[0], basis_prior=priors[1], seed=config.seed,
                          keep_inputs=False)
        runs.append({stage: float(rec.timings.get(stage, 0.0)) for stage in LINEAR_STAGES})
    times = [sum(r.values()) for r in runs]
    return rec, {"n_normals": int(n_normals), "n_dirs": int(n_dirs), "grid": [int(n) for n in config.grid],
                 "time_s": float(np.median(times)),
                 "times_s": times, "stage_runs": runs,
                 "stages": {k: float(np.median([r[k] for r in runs])) for k in LINEAR_STAGES}}


def rung_label(point: dict) -> str:
    """A linear point's sizes for people: ``"M 1000, K 1000, 16 x 16"`` (records without a grid: no grid)."""
    grid = f", {point['grid'][0]} x {point['grid'][1]}" if point.get("grid") else ""
    return f"M {point['n_normals']}, K {point['n_dirs']}{grid}"


def linear_reaches(points: Sequence[dict], best_relight: float,
                   best_time_s: float) -> Tuple[Optional[dict], Optional[float]]:
    """The fastest linear run at least as good as AbS's best relight error, and AbS's time to that
    best over that run's time (``None``, ``None`` when no run reaches it; the ratio ``None`` when
    ``best_time_s`` is 0: AbS's best is its start, which has no time of its own to compare)."""
    fastest = time_to_error(points, best_relight)
    if fastest is None or fastest["time_s"] <= 0 or best_time_s <= 0:
        return fastest, None
    return fastest, best_time_s / fastest["time_s"]


def relight_error(table_or_brdf: Any, renderer: Renderer, probe: Any, probe_spec: str, truth: Shot,
                  seed: int) -> float:
    """Relative RMSE of ``table_or_brdf`` (an ``(n_t, n_s, 3)`` table or a BRDF) rendered under
    ``probe`` by the evaluation's ``renderer`` at ``truth``'s resolution, against ``truth``."""
    return metrics.image_relative_rmse(relit(table_or_brdf, renderer, probe, probe_spec, truth, seed),
                                       truth.image, truth.mask)


def render_noise(table_or_brdf: Any, renderer: Renderer, probe: Any, probe_spec: str, truth: Shot,
                 seeds: Tuple[int, int]) -> float:
    """One render's own noise: the relative RMSE between renders of ``table_or_brdf`` at the two
    ``seeds`` (``truth``'s resolution and mask), over sqrt 2."""
    a, b = (relit(table_or_brdf, renderer, probe, probe_spec, truth, seed) for seed in seeds)
    return metrics.image_relative_rmse(a, b, truth.mask) / np.sqrt(2.0)


def relit(table_or_brdf: Any, renderer: Renderer, probe: Any, probe_spec: str, truth: Shot, seed: int) -> np.ndarray:
    """``table_or_brdf`` rendered under ``probe`` as ``truth`` was: ``(H, W, 3) float32``."""
    brdf = bivariate_brdf(table_or_brdf) if isinstance(table_or_brdf, np.ndarray) else table_or_brdf
    return renderer.render(brdf, probe, probe_spec, truth.image.shape[0], seed, renderer.cfg.novel_spp).image


def analysis_by_synthesis(material: Any, input_probe: str = "grace_latlong_1k", config: Any = None,
                          data_dir: Optional[PathLike] = None, time_factor: float = 10.0,
                          spp: Optional[int] = None, learning_rate: Optional[float] = None,
                          eval_every: int = 10, max_iterations: int = 100000,
                          novel_probe: Optional[str] = None, settings: Optional[SynthesisSettings] = None,
                          budget_s: Optional[float] = None,
                          linear_ladder: Sequence[float] = LINEAR_LADDER, ladder_repeats: int = 3,
                          ladder_grid_fractions: Sequence[float] = LADDER_GRIDS) -> dict:
    """The linear solve and analysis by synthesis on the same image, errors against wall time.

    The input image is path traced (config resolution, spp and seed) and the
    table recovered with the config's normals, directions, grid and alpha, and
    the priors the evaluation would use (:func:`~mi_bivariate.evaluate.protocol.choose_priors`:
    for a shared material with ``config.leave_one_out``, learnt without it). Then :func:`optimise_table` starts from
    the Lambertian fit and runs for ``budget_s`` (default ``time_factor`` x
    the linear route's time: observations + lighting matrix + adequacy +
    solve). Every ``eval_every`` iterations the table's relight error under
    ``novel_probe`` and its BRDF errors are measured (clock paused).

    ``novel_probe`` (default: the config's first novel probe) is rendered at
    the seed the evaluation gives it (:meth:`EvalConfig.novel_seed`).

    The linear route is timed after one warm-up run, ``ladder_repeats`` times
    (median) at the config's sizes and at each of the cheaper rungs of
    :func:`ladder_rungs` (``linear_ladder``: fractions of ``config.n_normals``
    and ``config.n_dirs``; ``ladder_grid_fractions``: coarser grids, fractions of
    ``config.grid``'s sides, each with the priors the evaluation would choose on
    it; ``()`` for none), all relit the same way. AbS (on ``config.grid``) is
    timed alike: after one untimed warm-up iteration (its kernels compiled;
    measured: 2.4-5 s with a cold Dr.Jit kernel cache, against 0.6 s an iteration).

    Returns:
        A JSON-friendly dict: ``linear`` (a :func:`linear_run` point with
        the BRDF errors and ``relight``, at the configuration's sizes),
        ``linear_ladder`` (the same per rung), ``relight_floor`` (the exact
        reduction's relight error), ``relight_noise`` (one render's own
        relative RMS noise, :func:`render_noise`, of the truth, the linear
        table and AbS's best table),
        ``scoring`` (the renderer's settings), ``abs``
        (iterations, time, settings, best and final
        errors, when the linear errors were first reached), ``speedup`` (AbS
        time to its best relight error / the linear route's time at the
        configuration's sizes, when that is at least as good; ``None`` when AbS's best is its start),
        ``ladder_speedup`` (the same over the fastest linear run, ladder
        included, that reaches AbS's best) and ``trace``.
    """
    ensure_variant(vectorised=True)
    config = config or EvalConfig()
    settings = settings or SynthesisSettings()
    overrides = {k: v for k, v in (("spp", spp), ("learning_rate", learning_rate)) if v is not None}
    if overrides:
        settings = SynthesisSettings(**{**asdict(settings), **overrides})
    spec = material if isinstance(material, MaterialSpec) else resolve_materials([material], data_dir)[0]
    truth = load_truth(spec, data_dir)
    probe = load_probe(input_probe, data_dir, cache=True)
    novel_probe = novel_probe or config.novel_probes[0]
    novel = load_probe(novel_probe, data_dir, cache=True)
    shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=config.resolution, spp=config.spp,
                                seed=config.seed)
    # Scored as the evaluation scores (its renderer: by default the converged quadrature of
    # mi_bivariate.reference), at its novel resolution and the seed it gives this probe.
    renderer = Renderer(config, spec, cache_dir=None)
    relight_seed = config.novel_seed(novel_probe)
    truth_novel = renderer.render(truth, novel, novel_probe, config.novel_resolution, relight_seed, config.novel_spp)

    def relight(table_or_brdf: Any) -> float:
        return relight_error(table_or_brdf, renderer, novel, novel_probe, truth_novel, relight_seed)

    def noise(table_or_brdf: Any) -> float:
        return render_noise(table_or_brdf, renderer, novel, novel_probe, truth_novel,
                            (relight_seed + 101, relight_seed + 102))

    n_t, n_s = config.grid
    relight_floor = relight(BivariateBRDF.reduce(truth, n_t=n_t, n_s=n_s))

    # The evaluation's priors (leave-one-out for a shared material): no score from a prior that saw it.
    own_grid = tuple(config.grid)

    def on_grid(grid: Tuple[int, int]) -> EvalConfig:
        return config if tuple(grid) == own_grid else replace(config, grid=tuple(grid))

    def grid_priors(grid: Tuple[int, int]) -> Tuple[Any, Any, str]:
        chosen = choose_priors(MaterialTask(spec, on_grid(grid), None if data_dir is None else str(data_dir)))
        basis = chosen[1]
        if isinstance(basis, BasisPrior) and (basis.n_t, basis.n_s) != tuple(grid):
            basis = basis.resampled(*grid)      # a prior file learnt on the configuration's grid
        return chosen[0], basis, chosen[2]

    prior, basis_prior, prior_source = grid_priors(config.grid)
    priors = (prior, basis_prior)
    # Every linear point is timed alike: after one warm-up run in this process, the median of
    # ladder_repeats runs.
    linear_run(shot, probe, config, config.n_normals, config.n_dirs, 1, priors=priors)
    rec, linear = linear_run(shot, probe, config, config.n_normals, config.n_dirs, ladder_repeats, priors=priors)
    linear_s = linear["time_s"]
    brdf_errors = metrics.BRDFErrors(truth)
    linear_errors = {k: v for k, v in brdf_errors(rec.brdf).items() if k != "eq1_rgb"}
    linear_relight = relight(rec.brdf)
    relight_noise = {"truth": noise(truth), "linear_table": noise(rec.brdf)}

    lam = lambertian_start(rec.lighting_matrix, rec.observations.values)
    start = np.broadcast_to(np.maximum(lam, 1e-4), (n_t, n_s, 3)).astype(np.float32)
    del rec

    ladder: List[dict] = []
    rung_priors = {own_grid: (prior, basis_prior, prior_source)}
    for m, k, grid in ladder_rungs(config.n_normals, config.n_dirs, config.grid, linear_ladder,
                                   ladder_grid_fractions):
        if grid not in rung_priors:
            rung_priors[grid] = grid_priors(grid)
            # A warm-up on each new grid (its kernels compiled), as at the configuration's sizes.
            linear_run(shot, probe, on_grid(grid), m, k, 1, quiet=True, priors=rung_priors[grid][:2])
        chosen = rung_priors[grid]
        rung, point = linear_run(shot, probe, on_grid(grid), m, k, ladder_repeats, quiet=True, priors=chosen[:2])
        ladder.append({**point, "relight": relight(rung.brdf), **({"prior": chosen[2]} if grid != own_grid else {})})
        del rung

    trace: List[dict] = []
    best_table: Dict[str, Any] = {}

    def checkpoint(it: int, clock: float, loss: float, table: np.ndarray) -> bool:
        brdf = bivariate_brdf(table)
        e = brdf_errors(brdf)
        trace.append({"iteration": it, "time_s": clock, "loss": loss,
                      "relight": relight(brdf),
                      **{k: e[k] for k in ("eq1", "eq1_min", "log", "cosine")}})
        if trace[-1]["relight"] < best_table.get("relight", np.inf):
            best_table.update(relight=trace[-1]["relight"], table=np.array(table, copy=True))
        return False

    budget = float(budget_s) if budget_s is not None else time_factor * linear_s
    start_relight = relight(start)
    best_table.update(relight=start_relight, table=start)
    e0 = brdf_errors(bivariate_brdf(start))
    trace.append({"iteration": 0, "time_s": 0.0, "loss": None, "relight": start_relight,
                  **{k: e0[k] for k in ("eq1", "eq1_min", "log", "cosine")}})
    # As the linear route: a warm-up first, so that neither clock counts kernel compilation.
    optimise_table(shot.image, shot.mask, probe, start, settings, budget_s=0.0, max_iterations=1)
    run = optimise_table(shot.image, shot.mask, probe, start, settings, budget_s=budget,
                         max_iterations=max_iterations, eval_every=eval_every, on_checkpoint=checkpoint)

    best = min(trace, key=lambda r: r["relight"])
    first = lambda key, target: next((r["time_s"] for r in trace if r[key] <= target), None)  # noqa: E731
    reached_eq1 = first("eq1", linear_errors["eq1"])
    reached_log = first("log", linear_errors["log"])
    reached_relight = first("relight", linear_relight)
    # AbS's best at its start (time 0): it never improved, and there is no time to compare (not "0x").
    speedup = (best["time_s"] / linear_s if linear_relight <= best["relight"] and linear_s > 0 and best["time_s"] > 0
               else None)
    linear = {**linear, "relight": linear_relight}
    fastest, ladder_speedup = linear_reaches(ladder + [linear], best["relight"], best["time_s"])
    if best_table["relight"] != best["relight"]:
        raise RuntimeError("analysis_by_synthesis: the best table kept is not the trace's best")
    relight_noise["abs_best_table"] = noise(best_table["table"])
    last = trace[-1]
    return {"material": spec.label, "input_probe": probe_label(input_probe), "novel_probe": probe_label(novel_probe),
            "config_hash": config.hash(),
            "linear": {**linear, **linear_errors, "prior": prior_source},
            "linear_ladder": ladder,
            "relight_floor": relight_floor,
            "relight_noise": relight_noise,
            "scoring": {"renderer": config.renderer, "resolution": config.novel_resolution,
                        **({"directions": list(config.reference_directions)} if config.renderer == "reference"
                           else {"spp": config.novel_spp})},
            "abs": {"iterations": run["iterations"], "time_s": run["time_s"], "budget_s": budget,
                    "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(settings).items()},
                    "spp": settings.spp, "learning_rate": settings.learning_rate,
                    "start_relight": start_relight,
                    "best_relight": best["relight"], "best_relight_time_s": best["time_s"],
                    "best_relight_iteration": best["iteration"],
                    "reached_linear_eq1": reached_eq1 is not None, "time_to_linear_eq1_s": reached_eq1,
                    "reached_linear_log": reached_log is not None, "time_to_linear_log_s": reached_log,
                    "reached_linear_relight": reached_relight is not None,
                    "time_to_linear_relight_s": reached_relight,
                    "loss_first": run["losses"][0] if run["losses"] else None,
                    "loss_last": float(np.mean(run["losses"][-10:])) if run["losses"] else None,
                    "final": {k: last.get(k) for k in ("eq1", "eq1_min", "log", "cosine", "relight")}},
            "speedup": speedup,
            "ladder_speedup": ladder_speedup,
            "linear_to_abs_best": fastest,
            "trace": trace}


def bivariate_brdf(table: np.ndarray) -> Any:
    """A :class:`~mi_bivariate.bivariate.BivariateBRDF` of a (clipped, NaN-free) table."""
    return BivariateBRDF(np.maximum(np.nan_to_num(np.asarray(table, np.float64), nan=0.0), 0.0))
