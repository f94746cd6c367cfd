"""The per-material protocol of an evaluation, as named steps (:func:`evaluate_material`).

For one material and every input probe: render the input image of the 3D
truth, recover the bivariate table from it, score the table against the truth
(BRDF errors over all and over the observed cells, the floors), relight it
under the novel probes next to the truth and the exact reduction, and fit the
parametric baselines to the same observations. Every step is a function of
this module; :func:`evaluate_material` runs them in order.

The caller has selected the Mitsuba variant (the runner's front doors, see
:mod:`mi_bivariate.evaluate.runner`).
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate import adequacy, baselines, bivariate, metrics, training_set
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputWarning, renamed
from mi_bivariate.evaluate.config import EvalConfig
from mi_bivariate.evaluate.renders import Renderer, Shot, plugin
from mi_bivariate.noise import add_camera_noise
from mi_bivariate.prior import Prior, default_prior
from mi_bivariate.probes import Probe
from mi_bivariate.recover import Recovery, recover
from mi_bivariate.report import incident_plane
from mi_bivariate.sources import MaterialSpec, input_label, load_probe, load_truth, probe_label
from mi_bivariate.threads import jit_threads

#: View angles (degrees) of the stored incident-plane curves (Fig. 6).
INCIDENT_VIEWS = (30.0, 60.0)
#: Seed offset of the input noise (``EvalConfig.noise``): view ``k`` of an input (``"a+b"``) gets the noise of
#: seed ``seed + (k + 1) * NOISE_SEED_OFFSET``, so the views' noises are independent (one seed once gave every
#: view the same draws).
NOISE_SEED_OFFSET = 7919
#: Seed offset of the second render of the truth under each novel probe, which measures the reference's own
#: noise (:func:`render_novel_truths`).
REFERENCE_NOISE_SEED_OFFSET = 104729

Arrays = Dict[str, np.ndarray]


@dataclass
class MaterialTask:
    """What a worker needs for one material (picklable).

    ``cache_dir``: folder of cached reference renders (:data:`~mi_bivariate.evaluate.runner.REFERENCE_DIR`);
    ``None``: no cache.
    """

    material: MaterialSpec
    config: EvalConfig
    data_dir: Optional[str] = None
    threads: Optional[int] = None
    cache_dir: Optional[str] = None


@dataclass
class _Truth:
    """The material's 3D table, its exact reduction on the grid, and what is scored against them."""

    brdf: Any
    floor: BivariateBRDF
    exact: np.ndarray  #: (90, 90, 3) float64, 1/sr: the exact phi_d average at the MERL nodes (Eq. 1's f_bar)
    errors: metrics.BRDFErrors
    floor_errors: dict
    floor_values: dict


@dataclass
class _Novel:
    """Renders of the truth and of the reduction under the novel probes (keyed by probe label)."""

    truth: Dict[str, Shot]
    floor: Dict[str, np.ndarray]
    floor_images: Dict[str, dict]
    noise: Dict[str, float]  #: the truth render's own noise: two seeds' relative RMS difference / sqrt 2


def _f16(image: np.ndarray) -> np.ndarray:
    return np.asarray(np.minimum(image, 6.0e4), np.float16)


def _adequacy_summary(report: Any) -> dict:
    return {
        "adequate": bool(report.adequate),
        "reasons": list(report.reasons),
        "rank_fraction": float(report.rank_fraction),
        "numerical_rank": int(report.numerical_rank),
        "effective_rank": float(report.effective_rank),
        "condition_number": float(report.condition_number),
        "unobserved_nodes": int(report.unobserved_nodes),
        "regions": {k: {kk: float(vv) for kk, vv in v.items()} for k, v in report.regions.items()},
        "detail": [float(d) for d in report.detail],
    }


def _image_errors(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> dict:
    return {"rel_rmse": metrics.image_relative_rmse(image, reference, mask),
            "psnr": metrics.image_psnr(image, reference, mask)}


def _incident_curves(truth: Any) -> Arrays:
    out = {}
    for view in INCIDENT_VIEWS:
        theta_in, theta_h, theta_d, phi_d = incident_plane(view)
        out[f"incident__{view:g}__truth"] = truth.eval(theta_h, theta_d, phi_d, interpolation="linear")
        out["incident__theta_in"] = theta_in
    return out


# ------------------------------------------------------------------ the steps

def load_probes(cfg: EvalConfig, data_dir: Optional[str]) -> Tuple[List[List[Probe]], List[Probe]]:
    """The input probes (a list per input spec ``"a+b"``) and the novel probes, cached per process.

    Loaded first: their EXR reads need worker threads (:func:`mi_bivariate.sources.load_probe`).
    """
    inputs = [[load_probe(p, data_dir, cache=True) for p in name.split("+")] for name in cfg.input_probes]
    novels = [load_probe(p, data_dir, cache=True) for p in cfg.novel_probes]
    return inputs, novels


def choose_priors(task: MaterialTask) -> Tuple[Optional[Prior], Any, str]:
    """``(smoothness prior, basis prior, where they came from)`` for the recovery.

    A prior file when the config names one (with the basis prior ``learn-prior`` wrote beside it, or
    none: as ``recover --prior`` loads them, :func:`~mi_bivariate.training_set.load_prior_files`); else,
    for a shared MERL-NBRDF material with ``leave_one_out``, priors learnt without it; else the packaged ones.
    """
    cfg = task.config
    if cfg.prior is not None:
        prior, basis_prior = training_set.load_prior_files(cfg.prior)
        beside = training_set.basis_path_for(cfg.prior)
        name = _shared_name(task.material)
        saw = [str(p) for p, learnt in ((cfg.prior, prior), (beside, basis_prior))
               if learnt is not None and name in learnt.provenance.get("materials", ())]
        if saw:  # a score must come from priors that never saw the material
            warnings.warn(f"{task.material.label}: {' and '.join(saw)} learnt from {_this(task.material)}: its "
                          "scores are not leave-one-out (learn the priors without it, or leave --prior out for "
                          "leave-one-out priors of the shared materials)", InputWarning, stacklevel=2)
        return prior, basis_prior, (f"files {cfg.prior} and {beside}" if basis_prior is not None
                                    else f"file {cfg.prior} (no basis prior: no {beside.name} beside it)")
    if cfg.leave_one_out and task.material.kind == "nbrdf":
        prior, basis_prior = training_set.leave_one_out_priors(task.material.spec, *cfg.grid, data_dir=task.data_dir)
        return prior, basis_prior, f"leave-one-out: the other {len(basis_prior.materials)} shared MERL-NBRDF materials"
    name = _shared_name(task.material)
    if name is not None and name in _packaged_materials():
        cure = (f"evaluate it by its shared name, {name}, for leave-one-out priors" if task.material.kind == "merl"
                else "leave-one-out priors are the full configuration's; --quick and leave_one_out=False use "
                     "the packaged ones")
        warnings.warn(f"{task.material.label}: the packaged priors were learnt from {_this(task.material)}: its "
                      f"scores are not leave-one-out ({cure})", InputWarning, stacklevel=2)
    return None, "default", "packaged (73 shared MERL-NBRDF materials)"


def _shared_name(material: MaterialSpec) -> Optional[str]:
    """The shared-material name a prior's provenance would list ``material`` under: a MERL-NBRDF material's
    own, a MERL file's stem (``brass.binary``: 'brass'), ``None`` for an analytic one."""
    return {"nbrdf": material.spec, "merl": Path(material.spec).stem}.get(material.kind)


def _this(material: MaterialSpec) -> str:
    return (f"a shared material named {_shared_name(material)!r} (if this file is that material)"
            if material.kind == "merl" else "this material")


@functools.lru_cache(maxsize=1)
def _packaged_materials() -> frozenset:
    """The materials the packaged priors were learnt from (read once per process)."""
    return frozenset(default_prior().provenance.get("materials", ()))


def load_truth_and_floor(task: MaterialTask, timings: Dict[str, float]) -> _Truth:
    """The 3D truth, its exact reduction, the floors and the floor's BRDF errors (timed)."""
    n_t, n_s = task.config.grid
    t0 = time.perf_counter()
    truth = load_truth(task.material, task.data_dir)
    floor = BivariateBRDF.reduce(truth, n_t=n_t, n_s=n_s)
    timings["truth"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    floor_values = bivariate.floors(truth, n_t, n_s)
    errors = metrics.BRDFErrors(truth)
    floor_errors = errors(floor)
    timings["brdf_errors"] = time.perf_counter() - t0
    return _Truth(truth, floor, bivariate.phi_d_average(truth), errors, floor_errors, floor_values)


def render_novel_truths(renderer: Renderer, cfg: EvalConfig, novels: List[Probe], truth_bsdf: Any,
                        floor_bsdf: Any, arrays: Arrays) -> _Novel:
    """The truth and the exact reduction rendered under every novel probe (:meth:`EvalConfig.novel_seed`), the
    reduction's image errors (the relight floor), and the truth render's noise, measured by a second render of
    another seed (:data:`REFERENCE_NOISE_SEED_OFFSET`; cached as the first is):
    :func:`mi_bivariate.metrics.seed_noise`."""
    grid_key = f"grid_table_{cfg.grid[0]}x{cfg.grid[1]}"
    novel = _Novel({}, {}, {}, {})
    for name, probe in zip(cfg.novel_probes, novels):
        label = probe_label(name)
        seed = cfg.novel_seed(name)
        shot = renderer.render(truth_bsdf, probe, name, cfg.novel_resolution, seed, cfg.novel_spp, cache_key="truth")
        floor_shot = renderer.render(floor_bsdf, probe, name, cfg.novel_resolution, seed, cfg.novel_spp,
                                     cache_key=grid_key)
        novel.truth[label] = shot
        novel.floor[label] = floor_shot.image
        novel.floor_images[label] = _image_errors(floor_shot.image, shot.image, shot.mask)
        again = renderer.render(truth_bsdf, probe, name, cfg.novel_resolution, seed + REFERENCE_NOISE_SEED_OFFSET,
                                cfg.novel_spp, cache_key="truth")
        novel.noise[label] = metrics.seed_noise(shot.image, again.image, shot.mask)
        arrays[f"truth__{label}"] = _f16(shot.image)
        arrays[f"floor_render__{label}"] = _f16(floor_shot.image)
        arrays["mask"] = shot.mask
    return novel


def render_inputs(renderer: Renderer, cfg: EvalConfig, name: str, probe_list: List[Probe],
                  truth_bsdf: Any) -> Tuple[List[np.ndarray], list]:
    """The input images of one input spec (one per ``+`` part), with camera noise if configured."""
    images, geometries = [], []
    for k, (part, probe) in enumerate(zip(name.split("+"), probe_list)):
        shot = renderer.render(truth_bsdf, probe, part, cfg.resolution, cfg.seed, cfg.spp, cache_key="truth")
        image = shot.image
        if cfg.noise > 0.0:  # each view its own draws (the first as a single input's)
            image = add_camera_noise(image, cfg.noise, seed=cfg.seed + (k + 1) * NOISE_SEED_OFFSET)
        images.append(image)
        geometries.append(shot.geometry)
    return images, geometries


def score_recovery(rec: Recovery, truth: _Truth, grid: Tuple[int, int]) -> Tuple[dict, np.ndarray]:
    """BRDF errors of the recovered table over all cells, the observed cells and the confident ones.

    Returns:
        ``(entry fields, observed node mask (n_t, n_s))``.
    """
    n_t, n_s = grid
    effective, signal = adequacy.node_observation_strength(rec.lighting_matrix, n_t, n_s)
    observed = (effective >= adequacy.OBSERVED_MIN_EFFECTIVE) & (signal >= adequacy.OBSERVED_MIN_SIGNAL)
    entry: Dict[str, Any] = {}
    entry["observed"] = {"nodes": int(observed.sum()), "node_fraction": float(observed.mean()),
                         "min_effective": adequacy.OBSERVED_MIN_EFFECTIVE,
                         "min_signal": adequacy.OBSERVED_MIN_SIGNAL}
    entry["recovered"] = truth.errors(rec.brdf, observed_nodes=observed)
    # The recovery's own per-node confidence: nodes whose uncertainty the image more than halved.
    confident = np.min(rec.solution.measured, axis=-1) > 0.5
    entry["confident"] = {"nodes": int(confident.sum()), "node_fraction": float(confident.mean()),
                          "eq1": truth.errors(rec.brdf, observed_nodes=confident)["eq1_observed"],
                          "floor_eq1": truth.errors(truth.floor, observed_nodes=confident)["eq1_observed"],
                          "exact_floor_eq1": truth.errors(truth.exact, observed_nodes=confident)["eq1_observed"]}
    # Both floors over the same observed cells (the like-for-like denominators of Eq. 1 there).
    entry["grid_floor_observed"] = truth.errors(truth.floor, observed_nodes=observed)["eq1_observed"]
    entry["exact_floor_observed"] = truth.errors(truth.exact, observed_nodes=observed)["eq1_observed"]
    return entry, observed


def describe_recovery(rec: Recovery) -> dict:
    """The solve's own diagnostics: residual, prior choice, alpha, noise model, adequacy."""
    return {"relative_residual": rec.relative_residual(),
            "prior_winner": list(rec.solution.winner),
            "alpha": float(rec.solution.alpha),
            "alphas": [float(a) for a in rec.solution.alphas],
            "alpha_rule": rec.solution.alpha_rule,
            "noise_model": rec.brdf.provenance.get("noise"),
            "observations": int(len(rec.observations.values)),
            "adequacy": _adequacy_summary(rec.adequacy)}


def relight(renderer: Renderer, cfg: EvalConfig, rec: Recovery, novels: List[Probe], novel: _Novel,
            label: str, arrays: Arrays) -> Dict[str, dict]:
    """The recovery rendered under every novel probe, scored against the truth and the relight floor."""
    images = {}
    rec_bsdf = plugin(rec.brdf, cfg.renderer)
    for k, novel_name in enumerate(cfg.novel_probes):
        nl = probe_label(novel_name)
        img = renderer.render(rec_bsdf, novels[k], novel_name, cfg.novel_resolution, cfg.novel_seed(novel_name),
                              cfg.novel_spp).image
        images[nl] = metrics.relight_errors(img, novel.floor[nl], novel.truth[nl].image, novel.truth[nl].mask,
                                            novel.noise[nl])
        arrays[f"recovered_render__{label}__{nl}"] = _f16(img)
    return images


def fit_baselines(rec: Recovery, cfg: EvalConfig, truth: _Truth, observed: np.ndarray, label: str,
                  arrays: Arrays, timings: Dict[str, float]) -> dict:
    """Parametric fits to the recovery's observations through its lighting matrix, and their BRDF errors."""
    t0 = time.perf_counter()
    fits = baselines.fit_baselines(rec.lighting_matrix, rec.observations.values, grid=cfg.grid,
                                   families=cfg.baselines, max_nfev=cfg.baseline_nfev)
    timings["baselines_fit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = {}
    for fam, fit in fits.items():
        out[fam] = {**fit.summary(), "errors": truth.errors(fit.brdf, observed_nodes=observed)}
        arrays[f"baseline__{label}__{fam}"] = fit.table.table
    timings["baselines_errors"] = time.perf_counter() - t0
    return out


def evaluate_input(task: MaterialTask, name: str, probe_list: List[Probe], novels: List[Probe], truth: _Truth,
                   novel: _Novel, renderer: Renderer, truth_bsdf: Any, priors: Tuple[Any, Any, str],
                   arrays: Arrays) -> Tuple[str, dict]:
    """Every step for one input probe spec: render, recover, score, relight, baselines.

    Returns:
        ``(input label, its entry of the record's "inputs")``.
    """
    cfg = task.config
    prior, basis_prior, prior_source = priors
    label = input_label(name)
    t0 = time.perf_counter()
    images, geometries = render_inputs(renderer, cfg, name, probe_list, truth_bsdf)
    t_render = time.perf_counter() - t0
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        rec = recover(images, probe_list, geometries, n_normals=cfg.n_normals, n_dirs=cfg.n_dirs,
                      grid=cfg.grid, alpha=cfg.alpha, prior=prior, basis_prior=basis_prior, seed=cfg.seed,
                      keep_inputs=False)
    for w in said:  # "image: ..." is this material's render under this input's probe
        warnings.warn(_named(str(w.message), task.material.label, name.split("+"))
                      if issubclass(w.category, InputWarning) else w.message, w.category, stacklevel=2)
    entry: Dict[str, Any] = {"prior": prior_source, "timings": {"render_input": t_render, **rec.timings}}
    t0 = time.perf_counter()
    scores, observed = score_recovery(rec, truth, cfg.grid)
    entry.update(scores)
    entry["timings"]["brdf_errors"] = time.perf_counter() - t0
    entry.update(describe_recovery(rec))
    arrays[f"input__{label}"] = _f16(images[0])
    arrays[f"recovered__{label}"] = rec.brdf.table
    arrays[f"observation_map__{label}"] = np.asarray(rec.adequacy.observation_map, np.float32)
    arrays[f"observed_nodes__{label}"] = observed

    t0 = time.perf_counter()
    entry["images"] = relight(renderer, cfg, rec, novels, novel, label, arrays)
    entry["timings"]["render_novel"] = time.perf_counter() - t0
    entry["baselines"] = fit_baselines(rec, cfg, truth, observed, label, arrays, entry["timings"])
    return label, entry


def evaluate_material(task: MaterialTask) -> Tuple[dict, Arrays]:
    """Run the protocol (:mod:`mi_bivariate.evaluate`) for one material.

    Returns:
        ``(record, arrays)``: the JSON record (one line of ``results.jsonl``)
        and the artifact arrays (``materials/<config hash>/<slug>.npz``).
    """
    cfg = task.config
    cfg.validate()
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    timings: Dict[str, float] = {}
    inputs, novels = load_probes(cfg, task.data_dir)
    # The toolkit's warnings go into the record, each once, named after the material, and the process that
    # writes the records says them (run_evaluation): a worker process would print them in Python's own
    # two-line form, under no material's name. A failed material's warnings are said at once: they may
    # explain the failure.
    label = task.material.label
    said: List[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            priors = choose_priors(task)
            with jit_threads(task.threads):
                record, arrays = _evaluate_material(task, inputs, novels, priors, timings, t_start, cpu_start)
    except BaseException:
        for message in _input_warnings(said, label):
            warnings.warn(message, InputWarning, stacklevel=2)
        _say_others(said)
        raise
    record["warnings"] = _input_warnings(said, label)
    _say_others(said)
    return record, arrays


#: The registry of :func:`_say_others`: Python's once per place filter, across materials.
_SAID: Dict[Any, Any] = {}


def _input_warnings(said: Sequence[warnings.WarningMessage], material: str) -> List[str]:
    """The toolkit's warnings among ``said``, each once, named after ``material``."""
    return list(dict.fromkeys(
        str(w.message) if str(w.message).startswith(f"{material} ") or str(w.message).startswith(f"{material}:")
        else f"{material}: {w.message}" for w in said if issubclass(w.category, InputWarning)))


def _say_others(said: Sequence[warnings.WarningMessage]) -> None:
    """Warn again the other warnings among ``said`` (numpy's, the libraries'), under the filters in force and
    once per place (their record kept every repeat)."""
    for w in said:
        if not issubclass(w.category, InputWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, registry=_SAID)


def _named(message: str, material: str, probes: Sequence[str]) -> str:
    """A recovery's warning about ``"image"`` (``"image k"`` of several) as about ``material`` under the
    probe (``probes[k]``) that lit that image."""
    names = {"image": f"{material} under {probes[0]}"} if probes else {}
    names.update({f"image {k}": f"{material} under {probe}" for k, probe in enumerate(probes)})
    return renamed(message, names) or f"{material} under {'+'.join(probes)}: {message}"


def _evaluate_material(task: MaterialTask, inputs: List[List[Probe]], novels: List[Probe], priors: Any,
                       timings: Dict[str, float], t_start: float, cpu_start: float) -> Tuple[dict, Arrays]:
    cfg = task.config
    truth = load_truth_and_floor(task, timings)
    arrays: Arrays = {"floor": truth.floor.table}
    arrays.update(_incident_curves(truth.brdf))
    renderer = Renderer(cfg, task.material, task.cache_dir, truth=truth.brdf)
    truth_bsdf = plugin(truth.brdf, cfg.renderer)
    floor_bsdf = plugin(truth.floor, cfg.renderer)

    t0 = time.perf_counter()
    novel = render_novel_truths(renderer, cfg, novels, truth_bsdf, floor_bsdf, arrays)
    timings["render_truth_novel"] = time.perf_counter() - t0

    per_input: Dict[str, dict] = {}
    for name, probe_list in zip(cfg.input_probes, inputs):
        label, entry = evaluate_input(task, name, probe_list, novels, truth, novel, renderer, truth_bsdf, priors,
                                      arrays)
        per_input[label] = entry

    # Render counts go with the timings: a cache hit changes the work, not the numbers.
    timings["render_seconds"] = renderer.seconds
    timings["renders_rendered"] = float(renderer.renders)
    timings["renders_from_cache"] = float(renderer.cached)
    timings["total"] = time.perf_counter() - t_start
    # CPU seconds of this process (all its threads): the fair cost on a machine shared with other jobs.
    timings["cpu_total"] = time.process_time() - cpu_start
    record = {
        "material": task.material.label,
        "kind": task.material.kind,
        "spec": task.material.spec,
        "slug": task.material.slug,
        "config_hash": cfg.hash(),
        "floor": truth.floor_errors,
        "floors": truth.floor_values,
        "floor_images": novel.floor_images,
        "relight_floor": {k: v["rel_rmse"] for k, v in novel.floor_images.items()},
        "reference_noise": novel.noise,
        "inputs": per_input,
        "renderer": cfg.renderer,
        "timings": timings,
        "threads": task.threads,
    }
    return record, arrays
