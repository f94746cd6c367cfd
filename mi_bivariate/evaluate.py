"""Batch evaluation: the paper's experiments over a set of materials (``mi-bivariate evaluate``).

Per material (a MERL ``.binary``, a MERL-NBRDF name or an analytic spec) and
per input probe:

1. render the input image of the full 3D BRDF (``merl`` plugin, trilinear)
   with the converged reference renderer (:mod:`mi_bivariate.reference`,
   deterministic hemisphere quadrature; ``renderer="path"`` path-traces
   instead), clean unless ``noise`` adds the camera noise of
   :mod:`mi_bivariate.noise`;
2. :func:`~mi_bivariate.recover.recover` the bivariate BRDF from it;
3. render under every novel probe, with the *same* renderer and the same
   quadrature seed: the recovery (``bivariate`` plugin), the exact reduction's
   ``n_t x n_s`` table and the 3D truth; the *relight floor* is the reduction's
   image error against the truth, and the recovery's error is reported with
   its ratio to that floor (:func:`mi_bivariate.metrics.relight_errors`);
4. fit the parametric baselines (:mod:`mi_bivariate.baselines`) to the same
   observations through the same lighting matrix;
5. record the BRDF errors of :class:`mi_bivariate.metrics.BRDFErrors` (Eq. 1
   over all cells, over the cells the input observes
   (:func:`mi_bivariate.adequacy.observed_nodes` and
   :func:`mi_bivariate.metrics.observed_cells`) and over f > 1e-3;
   cosine-weighted; log-space; per region) for the recovery, the grid table
   and the baselines; the *exact floor* and the *grid floor*
   (:func:`mi_bivariate.bivariate.floors`); the adequacy diagnostics and
   timings.

Reference renders of the truth and of the reduction's table depend on the
material and the probe only, not on the solver: they are cached in
``references/`` (one ``.npz`` per material, probe and render settings), so a
rerun after a solver change renders only the recoveries.

Results are one JSON line per finished material in ``results.jsonl``,
appended, flushed and fsynced by the parent process only, so an interrupted
run loses nothing that finished; a rerun skips the materials already there
with the same configuration hash (:meth:`EvalConfig.hash`) and tolerates a
truncated last line. Small per-material artifacts (tables, float16 renders,
incident-plane curves of the truth) go to ``materials/<config hash>/<slug>.npz`` so that
:func:`make_figures` needs no recomputation. ``summary.csv`` is written
(atomically) at the end.

Materials run in parallel in worker processes (``jobs``; spawn context,
Dr.Jit threads per worker = cores // jobs) or on a Dask cluster. Every random
choice is seeded, so the same command reproduces the same numbers.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import re
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.common import PathLike


#: Bumped when the protocol changes in a way that changes numbers (part of the config hash).
PROTOCOL_VERSION = 3
DEFAULT_INPUT_PROBES: Tuple[str, ...] = ("grace_latlong_1k", "uffizi_256")
DEFAULT_NOVEL_PROBES: Tuple[str, ...] = ("grace_256", "pisa_256", "venice_sunset_1k",
                                         "pedestrian_overpass_1k", "royal_esplanade_1k")
#: Materials of ``--quick`` with the shared data (else analytic ones, see :func:`quick_materials`).
QUICK_NBRDF = ("gold-metallic-paint3", "blue-acrylic")
QUICK_ANALYTIC = ("ggx:diffuse=0.25,0.12,0.05,specular=0.6,alpha=0.12,ior=1.5",
                  "oren-nayar:albedo=0.6,0.4,0.3,sigma=0.4")
#: View angles (degrees) of the stored incident-plane curves (Fig. 6).
INCIDENT_VIEWS = (30.0, 60.0)
RESULTS_FILE = "results.jsonl"
SUMMARY_FILE = "summary.csv"
#: Folder (under the output folder) of cached reference renders of truths and exact reductions.
REFERENCE_DIR = "references"
#: Seed offset of the input noise (``EvalConfig.noise``).
NOISE_SEED_OFFSET = 7919


@dataclass(frozen=True)
class EvalConfig:
    """Everything that decides the numbers of an evaluation (hashed for resume).

    Attributes:
        input_probes: probes lighting the input image (shared names or files).
        novel_probes: probes of the validation renders.
        resolution: image width = height of every render (pixels).
        spp: samples per pixel of the input renders.
        novel_spp: samples per pixel of the validation renders.
        n_normals, n_dirs, grid, alpha: recovery settings (:func:`~mi_bivariate.recover.recover`).
        baselines: parametric families to fit (:data:`mi_bivariate.baselines.FAMILIES`).
        baseline_nfev: least-squares evaluations of a baseline's final run.
        seed: seeds renders (input: seed, novel probe k: seed + 1 + k) and recovery.
        renderer: ``"reference"`` (deterministic quadrature, :mod:`mi_bivariate.reference`;
            ``spp`` and ``novel_spp`` unused) or ``"path"`` (Mitsuba path tracing at ``spp`` /
            ``novel_spp``; noisy, for comparison).
        novel_resolution: image width = height of the renders under the novel probes.
        reference_directions: directions per pixel of the reference renderer (cosine, lobe,
            environment; :data:`mi_bivariate.reference.DEFAULT_DIRECTIONS`).
        noise: camera noise level of the input images (:func:`mi_bivariate.noise.add_camera_noise`:
            relative standard deviation at the mean signal; 0 = clean).
        prior: a prior file (:meth:`mi_bivariate.prior.Prior.load`) passed to ``recover``
            (``None``: the packaged default, or leave-one-out priors, see below).
        leave_one_out: for a shared MERL-NBRDF material and ``prior=None``, learn both
            priors (smoothness and basis) from the other 72 shared materials, so that no
            number comes from a prior that saw the material
            (:func:`mi_bivariate.training_set.leave_one_out_priors`).

    An input probe spec ``"a+b"`` renders the material under both probes and recovers
    from the two images together (several images, one solve).
    """

    input_probes: Tuple[str, ...] = DEFAULT_INPUT_PROBES
    novel_probes: Tuple[str, ...] = DEFAULT_NOVEL_PROBES
    resolution: int = 128
    spp: int = 128
    novel_spp: int = 64
    n_normals: int = 8000
    n_dirs: int = 32000
    grid: Tuple[int, int] = (32, 32)
    alpha: Optional[float] = None
    baselines: Tuple[str, ...] = ("ggx", "ward")
    baseline_nfev: int = 40
    seed: int = 0
    renderer: str = "reference"
    novel_resolution: int = 64
    reference_directions: Tuple[int, int, int] = (1024, 2048, 3072)
    noise: float = 0.0
    prior: Optional[str] = None
    leave_one_out: bool = True

    @classmethod
    def quick(cls, shared_data: bool = True, **overrides) -> "EvalConfig":
        """Small sizes for the test suite and notebooks (seconds per material).

        Without the shared data (``shared_data=False``) the probes are synthetic.
        """
        base = dict(resolution=48, spp=16, novel_spp=8, n_normals=1000, n_dirs=3000, grid=(12, 12),
                    baseline_nfev=8, novel_probes=("pisa_256",), novel_resolution=32,
                    reference_directions=(256, 512, 256), leave_one_out=False)
        if not shared_data:
            base.update(input_probes=("synthetic:1", "synthetic:3"), novel_probes=("synthetic:7",))
        base.update(overrides)
        return cls(**base)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["input_probes"], d["novel_probes"] = list(self.input_probes), list(self.novel_probes)
        d["grid"], d["baselines"] = list(self.grid), list(self.baselines)
        d["reference_directions"] = list(self.reference_directions)
        return d

    def validate(self) -> None:
        """Raise :class:`InputError` for settings no run can use (before any work starts)."""
        if self.renderer not in ("reference", "path"):
            raise InputError("renderer", f"unknown renderer {self.renderer!r}", "use 'reference' or 'path'")
        if not (math.isfinite(self.noise) and self.noise >= 0.0):
            raise InputError("--noise", f"noise level must be a finite number >= 0, got {self.noise}")
        if self.prior is not None and not Path(self.prior).is_file():
            raise InputError(self.prior, "prior file not found")
        if int(self.novel_resolution) < 4:
            raise InputError("--novel-resolution", f"must be >= 4 pixels, got {self.novel_resolution}")
        if len(self.reference_directions) != 3 or min(self.reference_directions) < 0:
            raise InputError("reference_directions", "need 3 non-negative counts (cosine, lobe, environment)")

    def hash(self) -> str:
        """16 hex digits of SHA-256 over the canonical JSON of the config and protocol version."""
        extra = {} if self.prior is None else {"prior_sha256": _file_digest(self.prior)}   # bytes, not name
        text = json.dumps({"protocol": PROTOCOL_VERSION, "solver": _solver_identity(), **self.to_dict(), **extra},
                          sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _file_digest(path: PathLike) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        return "missing"


def _solver_identity() -> dict:
    """What else decides the numbers: the packaged prior's bytes and the default alpha.

    A finished material is only reused on resume when these are unchanged, so a
    re-learnt prior or a re-tuned alpha never mixes with old results.
    """
    from mi_bivariate import prior, solve

    from mi_bivariate import basis_prior

    digest = hashlib.sha256(Path(prior.DEFAULT_PRIOR_PATH).read_bytes()).hexdigest()[:16]
    basis = _file_digest(basis_prior.DEFAULT_BASIS_PRIOR_PATH)
    return {"default_prior_sha256": digest, "default_basis_prior_sha256": basis,
            "default_alpha": solve.DEFAULT_ALPHA, "solver": "mis+noise-aware+basis v1"}


# ------------------------------------------------------------------ materials

@dataclass(frozen=True)
class MaterialSpec:
    """One material: ``kind`` is ``"merl"`` (a .binary path), ``"nbrdf"`` or ``"analytic"``."""

    label: str
    kind: str
    spec: str

    @property
    def slug(self) -> str:
        """File-name-safe form of the label (artifacts)."""
        slug = re.sub(r"[^A-Za-z0-9._-]+", "_", self.label).strip("_")
        if len(slug) > 60 or slug != self.label:
            slug = slug[:48] + "-" + hashlib.sha1(self.label.encode()).hexdigest()[:8]
        return slug


def resolve_materials(items: Sequence[str], data_dir: Optional[PathLike] = None) -> List[MaterialSpec]:
    """Expand material arguments into :class:`MaterialSpec` s (duplicates dropped, order kept).

    Each item is a folder (its ``*.binary`` files, sorted), a MERL ``.binary``
    file, ``nbrdf`` (all 23 MERL-NBRDF materials), a MERL-NBRDF name, or an
    analytic spec such as ``ggx:alpha=0.1`` (:func:`~mi_bivariate.analytic.analytic_from_spec`).

    Raises:
        InputError: an item that is none of these, or an empty folder.
    """
    from mi_bivariate import analytic, nbrdf
    from mi_bivariate.merl import merl_files_in

    out: List[MaterialSpec] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            out += [MaterialSpec(f.stem, "merl", str(f)) for f in merl_files_in(path)]
        elif path.suffix == ".binary":
            if not path.is_file():
                raise InputError(path, "MERL file not found")
            out.append(MaterialSpec(path.stem, "merl", str(path)))
        elif item == "nbrdf":
            out += [MaterialSpec(n, "nbrdf", n) for n in nbrdf.NBRDF_MATERIALS]
        elif item in nbrdf.NBRDF_MATERIALS:
            out.append(MaterialSpec(item, "nbrdf", item))
        elif ":" in item or item in ("lambertian", "ggx", "oren-nayar", "bivariate-lobe"):
            out.append(MaterialSpec(analytic.analytic_from_spec(item).name, "analytic", item))
        else:
            raise InputError(item, "not a folder, .binary file, MERL-NBRDF name or analytic spec",
                             f"MERL-NBRDF names: {', '.join(nbrdf.NBRDF_MATERIALS)}; or 'nbrdf' for all")
    seen, unique = set(), []
    for m in out:
        if m.label not in seen:
            seen.add(m.label)
            unique.append(m)
    return unique


def quick_materials(data_dir: Optional[PathLike] = None) -> List[str]:
    """``--quick`` materials: two MERL-NBRDF ones with the shared data, else two analytic ones."""
    return list(QUICK_NBRDF) if have_shared_data(data_dir) else list(QUICK_ANALYTIC)


def load_truth(material: MaterialSpec, data_dir: Optional[PathLike] = None):
    """The material's 3D table (:class:`~mi_bivariate.merl.MERLBRDF`)."""
    from mi_bivariate import analytic, merl, nbrdf

    if material.kind == "merl":
        return merl.MERLBRDF.read(material.spec)
    if material.kind == "nbrdf":
        return nbrdf.nbrdf_merl(material.spec, data_dir=data_dir)
    return analytic.to_merl(analytic.analytic_from_spec(material.spec), dtype=np.float32)


# --------------------------------------------------------------------- probes

_PROBE_CACHE: Dict[Tuple[str, str], Any] = {}


@contextlib.contextmanager
def _io_threads() -> Iterator[None]:
    """At least 2 Dr.Jit threads while Mitsuba reads or writes images.

    Measured with Mitsuba 3.9.1: ``mi.Bitmap`` EXR reading and writing never
    return when ``dr.set_thread_count(1)`` is in force (the OpenEXR tasks
    wait on a pool without workers).
    """
    import drjit as dr

    n = dr.thread_count()
    if n < 2:
        dr.set_thread_count(2)
    try:
        yield
    finally:
        if n < 2:
            dr.set_thread_count(n)


def load_probe(spec: str, data_dir: Optional[PathLike] = None):
    """A probe by shared name, file path, or ``synthetic:SEED`` (cached per process).

    ``synthetic:SEED`` is :func:`mi_bivariate.demo.synthetic_environment` (a
    128 x 256 sky with sun and windows), for runs without the shared data.
    """
    from mi_bivariate import probes

    key = (spec, str(data_dir))
    if key not in _PROBE_CACHE:
        with _io_threads():
            path = Path(spec)
            if spec.startswith("synthetic:"):
                from mi_bivariate.demo import synthetic_environment

                try:
                    seed = int(spec.split(":", 1)[1])
                except ValueError:
                    raise InputError(spec, "synthetic probe seed must be an integer") from None
                _PROBE_CACHE[key] = probes.Probe(synthetic_environment(seed=seed), source=spec)
            elif path.suffix:
                _PROBE_CACHE[key] = probes.Probe.load(path)
            else:
                _PROBE_CACHE[key] = probes.shared_probe(spec, data_dir=data_dir)
    return _PROBE_CACHE[key]


def have_shared_data(data_dir: Optional[PathLike] = None) -> bool:
    """True when the shared data folder (probes and MERL-NBRDF fits) is available."""
    from mi_bivariate import nbrdf

    try:
        nbrdf.data_dir(data_dir)
        return True
    except InputError:
        return False


def probe_label(spec: str) -> str:
    """Short name of a probe spec (file stem)."""
    return Path(spec).stem if Path(spec).suffix else spec


# --------------------------------------------------------------- one material

@dataclass
class MaterialTask:
    """What a worker needs for one material (picklable).

    ``cache_dir``: folder of cached reference renders (:data:`REFERENCE_DIR`); ``None``: no cache.
    """

    material: MaterialSpec
    config: EvalConfig
    data_dir: Optional[str] = None
    threads: Optional[int] = None
    cache_dir: Optional[str] = None


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
    from mi_bivariate import metrics

    return {"rel_rmse": metrics.image_relative_rmse(image, reference, mask),
            "psnr": metrics.image_psnr(image, reference, mask)}


def _incident_curves(truth: Any) -> Dict[str, np.ndarray]:
    from mi_bivariate.report import incident_plane

    out = {}
    for view in INCIDENT_VIEWS:
        theta_in, theta_h, theta_d, phi_d = incident_plane(view)
        out[f"incident__{view:g}__truth"] = truth.eval(theta_h, theta_d, phi_d, interpolation="linear")
        out["incident__theta_in"] = theta_in
    return out


@dataclass
class _Shot:
    """A rendered sphere as the protocol uses it."""

    image: np.ndarray
    mask: np.ndarray
    geometry: Any


class _Renderer:
    """The protocol's renders: one renderer for every image that is scored, with a cache.

    Renders of the truth and of the exact reduction (``cache_key`` given)
    are cached as ``<cache_dir>/<key hash>.npz`` (image, mask, geometry).
    """

    def __init__(self, cfg: EvalConfig, material: MaterialSpec, cache_dir: Optional[str]):
        self.cfg = cfg
        self.cache_dir = Path(cache_dir) if cache_dir else None
        identity = {"label": material.label, "kind": material.kind, "spec": material.spec}
        if material.kind == "merl":
            try:
                st = os.stat(material.spec)
                identity["file"] = [st.st_size, st.st_mtime_ns]
            except OSError:
                pass
        self.identity = identity
        self.seconds = 0.0
        self.renders = 0
        self.cached = 0

    def _settings(self, resolution: int, seed: int, spp: int) -> dict:
        from mi_bivariate import reference

        if self.cfg.renderer == "reference":
            return {"renderer": "reference", "version": reference.REFERENCE_VERSION, "resolution": int(resolution),
                    "seed": int(seed), "directions": list(self.cfg.reference_directions)}
        return {"renderer": "path", "resolution": int(resolution), "seed": int(seed), "spp": int(spp)}

    def render(self, bsdf: Any, probe: Any, probe_spec: str, resolution: int, seed: int, spp: int,
               cache_key: Optional[str] = None) -> _Shot:
        """Render ``bsdf`` (a plugin object or anything render.bsdf_dict takes) under ``probe``."""
        from mi_bivariate import reference, render
        from mi_bivariate.geometry import SphereGeometry

        settings = self._settings(resolution, seed, spp)
        path = None
        if cache_key is not None and self.cache_dir is not None:
            key = json.dumps({"material": self.identity, "what": cache_key, "probe": probe_spec,
                              "probe_sha": _probe_digest(probe), **settings}, sort_keys=True)
            path = self.cache_dir / f"{hashlib.sha256(key.encode()).hexdigest()[:24]}.npz"
            if path.is_file():
                try:
                    with np.load(path, allow_pickle=False) as npz:
                        g = npz["geometry"]
                        shot = _Shot(np.asarray(npz["image"], np.float32), np.asarray(npz["mask"], bool),
                                     SphereGeometry(float(g[0]), float(g[1]), float(g[2]),
                                                    np.asarray(npz["camera_to_world"], np.float64)))
                    self.cached += 1
                    return shot
                except (OSError, ValueError, KeyError, EOFError):
                    pass                               # unreadable: render again and overwrite
        t0 = time.perf_counter()
        if self.cfg.renderer == "reference":
            out = reference.render_reference(bsdf, probe, resolution=resolution, seed=seed,
                                             directions=self.cfg.reference_directions)
        else:
            source = render.bsdf_dict(bsdf) if not hasattr(bsdf, "sampler") else bsdf
            out = render.render_sphere(source, probe, resolution=resolution, spp=spp, seed=seed)
        self.seconds += time.perf_counter() - t0
        self.renders += 1
        shot = _Shot(np.asarray(out.image, np.float32), np.asarray(out.mask, bool), out.geometry)
        if path is not None:
            g = shot.geometry
            with contextlib.suppress(OSError):
                path.parent.mkdir(parents=True, exist_ok=True)
                save_artifacts(path, {"image": shot.image, "mask": shot.mask,
                                      "geometry": np.array([g.cx, g.cy, g.radius]),
                                      "camera_to_world": np.asarray(g.camera_to_world, np.float64)})
        return shot


def _probe_digest(probe: Any) -> str:
    """Identity of a probe's pixels and orientation (cache keys)."""
    digest = getattr(probe, "_mi_bivariate_digest", None)
    if digest is None:
        h = hashlib.sha256(np.ascontiguousarray(probe.data).tobytes())
        h.update(np.ascontiguousarray(probe.to_world, np.float64).tobytes())
        digest = h.hexdigest()[:16]
        with contextlib.suppress(AttributeError, TypeError):
            object.__setattr__(probe, "_mi_bivariate_digest", digest)
    return digest


def _plugin(source: Any, renderer: str) -> Any:
    """A loaded BSDF plugin (reference renderer: built once, used for every probe) or a BSDF dict."""
    import mitsuba as mi

    from mi_bivariate import render

    bsdf = render.bsdf_dict(source)
    return mi.load_dict(bsdf) if renderer == "reference" else bsdf


def evaluate_material(task: MaterialTask) -> Tuple[dict, Dict[str, np.ndarray]]:
    """Run the protocol of the module docstring for one material.

    Returns:
        ``(record, arrays)``: the JSON record (one line of ``results.jsonl``)
        and the artifact arrays (``materials/<slug>.npz``).
    """
    from mi_bivariate import adequacy, baselines, bivariate, metrics
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.noise import add_camera_noise
    from mi_bivariate.recover import recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    cfg, data_dir = task.config, task.data_dir
    cfg.validate()
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    timings: Dict[str, float] = {}
    # Probes first: their EXR reads need worker threads (see _io_threads).
    inputs = [[load_probe(p, data_dir) for p in name.split("+")] for name in cfg.input_probes]
    novels = [load_probe(p, data_dir) for p in cfg.novel_probes]
    prior, basis_prior, prior_source = None, "default", "packaged (73 shared MERL-NBRDF materials)"
    if cfg.prior is not None:
        from mi_bivariate.prior import Prior

        prior, prior_source = Prior.load(cfg.prior), f"file {cfg.prior}"
    elif cfg.leave_one_out and task.material.kind == "nbrdf":
        from mi_bivariate import training_set

        prior, basis_prior = training_set.leave_one_out_priors(task.material.spec, *cfg.grid, data_dir=data_dir)
        prior_source = f"leave-one-out: the other {len(basis_prior.materials)} shared MERL-NBRDF materials"
    if task.threads is not None:
        import drjit as dr

        dr.set_thread_count(int(task.threads))

    t0 = time.perf_counter()
    truth = load_truth(task.material, data_dir)
    n_t, n_s = cfg.grid
    floor = BivariateBRDF.reduce(truth, n_t=n_t, n_s=n_s)
    timings["truth"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    floor_values = bivariate.floors(truth, n_t, n_s)
    brdf_errors = metrics.BRDFErrors(truth)
    floor_errors = brdf_errors(floor)
    timings["brdf_errors"] = time.perf_counter() - t0

    arrays: Dict[str, np.ndarray] = {"floor": floor.table}
    arrays.update(_incident_curves(truth))
    renderer = _Renderer(cfg, task.material, task.cache_dir)
    truth_bsdf = _plugin(truth, cfg.renderer)
    floor_bsdf = _plugin(floor, cfg.renderer)
    res, res_novel = cfg.resolution, cfg.novel_resolution
    grid_key = f"grid_table_{n_t}x{n_s}"

    t0 = time.perf_counter()
    truth_novel: Dict[str, _Shot] = {}
    floor_novel: Dict[str, np.ndarray] = {}
    floor_images: Dict[str, dict] = {}
    for k, (name, probe) in enumerate(zip(cfg.novel_probes, novels)):
        label = probe_label(name)
        seed = cfg.seed + 1 + k
        shot = renderer.render(truth_bsdf, probe, name, res_novel, seed, cfg.novel_spp, cache_key="truth")
        floor_shot = renderer.render(floor_bsdf, probe, name, res_novel, seed, cfg.novel_spp, cache_key=grid_key)
        truth_novel[label] = shot
        floor_novel[label] = floor_shot.image
        floor_images[label] = _image_errors(floor_shot.image, shot.image, shot.mask)
        arrays[f"truth__{label}"] = _f16(shot.image)
        arrays[f"floor_render__{label}"] = _f16(floor_shot.image)
        arrays["mask"] = shot.mask
    timings["render_truth_novel"] = time.perf_counter() - t0

    per_input: Dict[str, dict] = {}
    for name, probe_list in zip(cfg.input_probes, inputs):
        label = "+".join(probe_label(p) for p in name.split("+"))
        entry: Dict[str, Any] = {}
        t0 = time.perf_counter()
        images, geometries = [], []
        for part, probe in zip(name.split("+"), probe_list):
            shot = renderer.render(truth_bsdf, probe, part, res, cfg.seed, cfg.spp, cache_key="truth")
            image = shot.image
            if cfg.noise > 0.0:
                image = add_camera_noise(image, cfg.noise, seed=cfg.seed + NOISE_SEED_OFFSET)
            images.append(image)
            geometries.append(shot.geometry)
        t_render = time.perf_counter() - t0
        rec = recover(images, probe_list, geometries, n_normals=cfg.n_normals, n_dirs=cfg.n_dirs,
                      grid=cfg.grid, alpha=cfg.alpha, prior=prior, basis_prior=basis_prior, seed=cfg.seed,
                      keep_inputs=False)
        image = images[0]
        entry["prior"] = prior_source
        entry["timings"] = {"render_input": t_render, **rec.timings}
        t0 = time.perf_counter()
        effective, signal = adequacy.node_observation_strength(rec.lighting_matrix, n_t, n_s)
        observed = (effective >= adequacy.OBSERVED_MIN_EFFECTIVE) & (signal >= adequacy.OBSERVED_MIN_SIGNAL)
        entry["observed"] = {"nodes": int(observed.sum()), "node_fraction": float(observed.mean()),
                             "min_effective": adequacy.OBSERVED_MIN_EFFECTIVE,
                             "min_signal": adequacy.OBSERVED_MIN_SIGNAL}
        entry["recovered"] = brdf_errors(rec.brdf, observed_nodes=observed)
        # The recovery's own per-node confidence: nodes whose uncertainty the image more than halved.
        confident = np.min(rec.solution.measured, axis=-1) > 0.5
        entry["confident"] = {"nodes": int(confident.sum()), "node_fraction": float(confident.mean()),
                              "eq1": brdf_errors(rec.brdf, observed_nodes=confident)["eq1_observed"],
                              "floor_eq1": brdf_errors(floor, observed_nodes=confident)["eq1_observed"]}
        entry["grid_floor_observed"] = brdf_errors(floor, observed_nodes=observed)["eq1_observed"]
        entry["timings"]["brdf_errors"] = time.perf_counter() - t0
        entry["relative_residual"] = rec.relative_residual()
        entry["prior_winner"] = list(rec.solution.winner)
        entry["alpha"] = float(rec.solution.alpha)
        entry["noise_model"] = rec.brdf.provenance.get("noise")
        entry["observations"] = int(len(rec.observations.values))
        entry["adequacy"] = _adequacy_summary(rec.adequacy)
        arrays[f"input__{label}"] = _f16(image)
        arrays[f"recovered__{label}"] = rec.brdf.table
        arrays[f"observation_map__{label}"] = np.asarray(rec.adequacy.observation_map, np.float32)
        arrays[f"observed_nodes__{label}"] = observed

        t0 = time.perf_counter()
        images = {}
        rec_bsdf = _plugin(rec.brdf, cfg.renderer)
        for k, novel_name in enumerate(cfg.novel_probes):
            nl = probe_label(novel_name)
            img = renderer.render(rec_bsdf, novels[k], novel_name, res_novel, cfg.seed + 1 + k, cfg.novel_spp).image
            images[nl] = metrics.relight_errors(img, floor_novel[nl], truth_novel[nl].image, truth_novel[nl].mask)
            arrays[f"recovered_render__{label}__{nl}"] = _f16(img)
        entry["images"] = images
        entry["timings"]["render_novel"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        fits = baselines.fit_baselines(rec.lighting_matrix, rec.observations.values, grid=cfg.grid,
                                       families=cfg.baselines, max_nfev=cfg.baseline_nfev)
        entry["timings"]["baselines_fit"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        entry["baselines"] = {}
        for fam, fit in fits.items():
            entry["baselines"][fam] = {**fit.summary(), "errors": brdf_errors(fit.brdf, observed_nodes=observed)}
            arrays[f"baseline__{label}__{fam}"] = fit.table.table
        entry["timings"]["baselines_errors"] = time.perf_counter() - t0
        del rec
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
        "floor": floor_errors,
        "floors": floor_values,
        "floor_images": floor_images,
        "relight_floor": {k: v["rel_rmse"] for k, v in floor_images.items()},
        "inputs": per_input,
        "renderer": cfg.renderer,
        "timings": timings,
        "threads": task.threads,
    }
    return record, arrays


# ------------------------------------------------------------------ results I/O

#: Damaged lines of ``results.jsonl`` are moved here (and their materials recomputed).
REJECTED_FILE = "results.rejected.jsonl"
#: Held (``flock``) by the run using an output folder.
LOCK_FILE = ".evaluate.lock"


def _parse_record(line: bytes) -> Optional[dict]:
    """A results line as a record, or ``None`` if damaged (not UTF-8, not JSON, not a record)."""
    try:
        rec = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("material"), str) \
            or not isinstance(rec.get("config_hash"), str):
        return None
    return rec


def read_records(path: PathLike, config_hash: Optional[str] = None) -> List[dict]:
    """Records of a ``results.jsonl`` (optionally only those with ``config_hash``).

    Damaged lines (a last line cut by an interruption, bytes that are not
    UTF-8, invalid JSON, a record without ``material`` or ``config_hash``) are
    skipped; :func:`repair_results` sets them aside.
    """
    path = Path(path)
    if not path.is_file():
        return []
    records = []
    for line in path.read_bytes().splitlines():
        rec = _parse_record(line)
        if rec is not None and (config_hash is None or rec.get("config_hash") == config_hash):
            records.append(rec)
    return records


def repair_results(path: PathLike) -> int:
    """Set damaged lines of a results file aside so that their materials are recomputed.

    Damaged lines (see :func:`read_records`) are appended, as they were, to
    ``results.rejected.jsonl`` beside it, and the results file is rewritten
    (atomically) with the good lines only, ending in a newline. Returns the
    number of lines set aside. Every complete record is kept, whatever its
    configuration.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    raw = path.read_bytes()
    lines = [line for line in raw.splitlines() if line.strip()]
    good = [line for line in lines if _parse_record(line) is not None]
    bad = [line for line in lines if _parse_record(line) is None]
    if bad:
        rejected = path.with_name(REJECTED_FILE)
        with open(rejected, "ab") as f:
            f.write(b"".join(line + b"\n" for line in bad))
            f.flush()
            os.fsync(f.fileno())
        warnings.warn(f"{path}: {len(bad)} damaged line(s) set aside in {rejected}; their materials are "
                      "recomputed", InputWarning, stacklevel=2)
    if bad or (raw and not raw.endswith(b"\n")) or len(lines) != len(raw.splitlines()):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"".join(line + b"\n" for line in good))
    return len(bad)


def append_record(path: PathLike, record: dict) -> None:
    """Append one JSON line, flushed and fsynced (the only writer is the parent process)."""
    line = json.dumps(record, sort_keys=True)
    with open(path, "a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def save_artifacts(path: PathLike, arrays: Dict[str, np.ndarray]) -> None:
    """Write a material's artifact arrays as a compressed ``.npz`` (atomic)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def artifact_path(out_dir: PathLike, record_or_slug: Union[dict, str], config_hash: Optional[str] = None) -> Path:
    """``out_dir/materials/<config hash>/<slug>.npz``: one folder per configuration, so a
    rerun with another configuration never overwrites the artifacts of recorded results."""
    if isinstance(record_or_slug, dict):
        slug, config_hash = record_or_slug["slug"], record_or_slug["config_hash"]
    else:
        slug = record_or_slug
    return Path(out_dir) / "materials" / str(config_hash) / f"{slug}.npz"


def load_artifacts(path: PathLike) -> Dict[str, np.ndarray]:
    """Read a material's artifacts (all arrays into memory)."""
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def summary_rows(records: Sequence[dict]) -> List[dict]:
    """One flat row per (material, input probe): the numbers of ``summary.csv``."""
    rows = []
    for r in records:
        for probe, e in r["inputs"].items():
            row = {"material": r["material"], "input_probe": probe}
            for key in ("eq1", "eq1_min", "cosine", "log"):
                row[f"floor_{key}"] = r["floor"][key]
                row[f"recovered_{key}"] = e["recovered"][key]
                for fam, b in e.get("baselines", {}).items():
                    row[f"{fam}_{key}"] = b["errors"][key]
            rmse = [v["rel_rmse"] for v in e["images"].values()]
            psnr = [v["psnr"] for v in e["images"].values() if math.isfinite(v["psnr"])]
            floor_rmse = [v["rel_rmse"] for v in r["floor_images"].values()]
            row["image_rel_rmse_mean"] = float(np.mean(rmse)) if rmse else float("nan")
            row["image_psnr_mean"] = float(np.mean(psnr)) if psnr else float("nan")
            row["floor_image_rel_rmse_mean"] = float(np.mean(floor_rmse)) if floor_rmse else float("nan")
            for key in ("exact_floor", "grid_floor", "exact_floor_min", "grid_floor_min"):
                if key in r.get("floors", {}):
                    row[key] = r["floors"][key]
            if "eq1_observed" in e["recovered"]:
                row["recovered_eq1_observed"] = e["recovered"]["eq1_observed"]
                row["grid_floor_observed"] = e.get("grid_floor_observed", float("nan"))
                row["observed_fraction"] = e["recovered"]["observed_fraction"]
            for region, v in e["recovered"].get("regions", {}).items():
                row[f"recovered_eq1_{region}"] = v["eq1"]
                row[f"recovered_share_{region}"] = v["share"]
            ratios = [v["ratio"] for v in e["images"].values() if "ratio" in v]
            if ratios:
                row["relight_rmse_median"] = float(np.median(rmse))
                row["relight_floor_median"] = float(np.median([v["floor"] for v in e["images"].values()]))
                row["relight_ratio_median"] = float(np.median(ratios))
                for novel, v in e["images"].items():
                    row[f"relight_{novel}"] = v["rel_rmse"]
                    row[f"relight_floor_{novel}"] = v["floor"]
            row["relative_residual"] = e["relative_residual"]
            row["rank_fraction"] = e["adequacy"]["rank_fraction"]
            row["adequate"] = e["adequacy"]["adequate"]
            row["recover_s"] = sum(v for k, v in e["timings"].items()
                                   if k in ("observations", "lighting matrix", "adequacy", "solve"))
            row["material_total_s"] = r["timings"]["total"]
            rows.append(row)
    return rows


def write_summary_csv(records: Sequence[dict], path: PathLike) -> Path:
    """``summary.csv`` from :func:`summary_rows` (atomic)."""
    rows = summary_rows(records)
    keys: List[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return path


# ------------------------------------------------------------------ execution

def threads_per_job(jobs: int) -> int:
    """Dr.Jit threads for each of ``jobs`` worker processes: the cores shared out, at least 1."""
    return max(1, (os.cpu_count() or 1) // max(1, jobs))


def _watch_parent(parent: int, interval: float = 0.5) -> None:
    """Exit this process as soon as ``parent`` is no longer its parent (it died)."""
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(interval)
        os._exit(1)

    threading.Thread(target=watch, name="mi-bivariate-parent-watch", daemon=True).start()


def _init_worker(variant: Optional[str], parent: Optional[int] = None) -> None:
    """Worker set-up: die with the parent (``PR_SET_PDEATHSIG`` on Linux and a
    watchdog thread polling ``os.getppid``), then select the variant."""
    if parent is not None:
        if sys.platform.startswith("linux"):
            import ctypes
            import signal

            with contextlib.suppress(OSError, AttributeError):
                libc = ctypes.CDLL(None, use_errno=True)
                libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent:      # the parent died before the signal was armed
            os._exit(1)
        _watch_parent(parent)
    from mi_bivariate.variants import ensure_variant

    ensure_variant(variant)


def _connect_dask(address: Any) -> Any:
    """A ``distributed.Client`` for ``address`` (a client is returned as is); InputError if unreachable."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError("--dask", "the 'distributed' package is not installed",
                         "pip install distributed, or run without --dask") from None
    if isinstance(address, Client):
        return address
    try:
        return Client(address, timeout="5s")
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        text = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise InputError("--dask", f"cannot reach a Dask scheduler at {address!r} ({text})",
                         "start the scheduler or check the address") from None


@contextlib.contextmanager
def _folder_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``out/.evaluate.lock`` (released when the process ends, even killed).

    Raises:
        InputError: another run holds it.
    """
    import fcntl

    path = out / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
            raise InputError(out, f"another evaluate run (pid {holder}) is using this folder",
                             "wait for it to finish, or use another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def _blas_threads(n: int) -> Iterator[None]:
    """Environment for spawned workers: BLAS/OpenMP pools of ``n`` threads (restored afterwards)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: str(n) for k in keys})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _run_tasks(tasks: List[MaterialTask], jobs: int, dask: Any) -> Iterator[Tuple[MaterialTask, Any]]:
    """Yield ``(task, (record, arrays))`` or ``(task, exception)`` as tasks finish.

    In-process, in a spawn-context process pool, or on Dask. A task's
    exception is yielded, not raised, so one bad material does not stop the
    batch; ``KeyboardInterrupt`` still does.
    """
    if dask is not None:
        from distributed import as_completed

        client = _connect_dask(dask)
        try:
            futures = {client.submit(evaluate_material, t, pure=False,
                                     key=f"mi-bivariate-{t.material.slug}-{t.config.hash()}"): t for t in tasks}
            for fut in as_completed(list(futures)):
                try:
                    yield futures[fut], fut.result()
                except Exception as exc:  # noqa: BLE001 (reported per material)
                    yield futures[fut], exc
        finally:
            if client is not dask:
                client.close()
        return
    if jobs <= 1:
        for t in tasks:
            try:
                result = evaluate_material(t)
            except Exception as exc:  # noqa: BLE001
                result = exc
            yield t, result
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed as cf_completed

    import mitsuba as mi

    with _blas_threads(tasks[0].threads or threads_per_job(jobs)):
        pool = ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_worker, initargs=(mi.variant(), os.getpid()))
    with pool:
        futures = {pool.submit(evaluate_material, t): t for t in tasks}
        try:
            for fut in cf_completed(futures):
                try:
                    yield futures[fut], fut.result()
                except Exception as exc:  # noqa: BLE001
                    yield futures[fut], exc
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise


def run_evaluation(materials: Sequence[Union[str, MaterialSpec]], out_dir: PathLike,
                   config: Optional[EvalConfig] = None, jobs: int = 1, dask: Any = None,
                   data_dir: Optional[PathLike] = None, progress: bool = True,
                   figures: bool = True, figure_formats: Sequence[str] = ("png",),
                   on_record: Optional[Callable[[dict], None]] = None,
                   threads: Optional[int] = None) -> List[dict]:
    """Evaluate materials, resuming from ``out_dir/results.jsonl``.

    Args:
        materials: material specs (see :func:`resolve_materials`) or :class:`MaterialSpec` s.
        out_dir: output folder (``results.jsonl``, ``summary.csv``, ``materials/``, ``figures/``).
        config: the protocol settings (default :class:`EvalConfig`).
        jobs: worker processes (1: in this process).
        dask: a ``distributed.Client`` or a scheduler address; overrides ``jobs``.
        data_dir: shared data folder (default ``$MI_BIVARIATE_DATA``).
        progress: show a tqdm progress bar.
        figures: draw the figures at the end (:func:`make_figures`).
        on_record: called with each new record after it is safely on disk.
        threads: Dr.Jit threads per job (default: cores // jobs in worker
            processes; unchanged in-process and on Dask). Numbers are bitwise
            reproducible only with 1 thread per job: with more, the lighting
            matrix's parallel scatter-add sums in a varying order (~1e-6 relative).

    Returns:
        All records of this configuration, in material order.
    """
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    config = config or EvalConfig()
    config.validate()
    if jobs < 1:
        raise InputError("--jobs", f"must be >= 1, got {jobs}")
    specs = [m if isinstance(m, MaterialSpec) else None for m in materials]
    if any(s is None for s in specs):
        specs = resolve_materials([str(m) for m in materials if not isinstance(m, MaterialSpec)], data_dir) + \
            [m for m in materials if isinstance(m, MaterialSpec)]
    if not specs:
        raise InputError("materials", "no materials given")
    # Fail early (in the parent, with a one-line error) on a missing probe or data folder,
    # a damaged MERL file or an unreachable scheduler: before the output folder exists.
    for p in tuple(config.input_probes) + tuple(config.novel_probes):
        for part in p.split("+"):
            load_probe(part, data_dir)
    from mi_bivariate.merl import MERLBRDF

    for m in specs:
        if m.kind == "merl":
            MERLBRDF.check_file(m.spec)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "the output folder is a file", "choose another --out")
    client = _connect_dask(dask) if dask is not None else None
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out, f"cannot create the output folder ({exc.strerror or exc})") from None
    try:
        with _folder_lock(out):
            records = _run_locked(specs, out, config, jobs, client, data_dir, progress, figures,
                                  figure_formats, on_record, threads, created)
    finally:
        if client is not None and client is not dask:
            client.close()
    return records


def _run_locked(specs: List[MaterialSpec], out: Path, config: EvalConfig, jobs: int, dask: Any,
                data_dir: Optional[PathLike], progress: bool, figures: bool, figure_formats: Sequence[str],
                on_record: Optional[Callable[[dict], None]], threads: Optional[int], created: bool) -> List[dict]:
    """:func:`run_evaluation`'s work, in a folder it holds the lock of."""
    (out / "materials" / config.hash()).mkdir(parents=True, exist_ok=True)
    results = out / RESULTS_FILE
    repair_results(results)
    h = config.hash()
    done = {r["material"] for r in read_records(results, h)}
    if threads is None and dask is None and jobs > 1:
        threads = threads_per_job(jobs)
    tasks = [MaterialTask(m, config, None if data_dir is None else str(data_dir), threads,
                          cache_dir=str(out / REFERENCE_DIR))
             for m in specs if m.label not in done]
    with atomic_path(out / "config.json") as tmp:
        tmp.write_text(json.dumps({"config_hash": h, **config.to_dict()}, indent=2))

    import drjit as dr

    parent_threads = dr.thread_count()
    failures: List[Tuple[str, BaseException]] = []
    if tasks:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(specs), initial=len(specs) - len(tasks), desc="materials", unit="material",
                   disable=not progress)
        try:
            for task, result in _run_tasks(tasks, jobs, dask):
                bar.update(1)
                if isinstance(result, BaseException):
                    # Not a record: a rerun tries this material again.
                    failures.append((task.material.label, result))
                    warnings.warn(f"{task.material.label}: evaluation failed: {type(result).__name__}: {result}",
                                  InputWarning, stacklevel=2)
                    continue
                record, arrays = result
                # Artifacts before the record: a record on disk always has its artifacts.
                save_artifacts(artifact_path(out, record), arrays)
                append_record(results, record)
                if on_record is not None:
                    on_record(record)
                bar.set_postfix_str(record["material"][:24])
        finally:
            bar.close()
            dr.set_thread_count(parent_threads)      # in-process tasks may have changed it

    by_label = {r["material"]: r for r in read_records(results, h)}
    records = [by_label[m.label] for m in specs if m.label in by_label]
    write_summary_csv(records, out / SUMMARY_FILE)
    if figures and records:
        make_figures(out, records, formats=figure_formats)
    if failures and not records:
        label, exc = failures[0]
        if created:  # nothing came of it: leave no folder behind
            import shutil

            shutil.rmtree(out, ignore_errors=True)
        if isinstance(exc, InputError):
            raise exc
        raise RuntimeError(f"every material failed; first: {label}: {type(exc).__name__}: {exc}") from exc
    return records


# ------------------------------------------------------------------- figures

def make_figures(out_dir: PathLike, records: Optional[Sequence[dict]] = None,
                 formats: Sequence[str] = ("png",), fig_dir: Optional[PathLike] = None,
                 dpi: int = 100) -> List[Path]:
    """Draw the evaluation figures from ``results.jsonl`` and the artifacts (no recomputation).

    Figures (in ``out_dir/figures`` unless ``fig_dir``): ``fig3_reduction``,
    ``fig5_validation``, ``fig6_incident``, ``fig6_errors``, ``fig7_environment``,
    ``tables``, ``baselines``; one file per format in ``formats`` (png, pdf).
    """
    from mi_bivariate import report

    out = Path(out_dir)
    if records is None:
        config = json.loads((out / "config.json").read_text())
        records = read_records(out / RESULTS_FILE, config["config_hash"])
    records = list(records)
    if not records:
        return []
    fig_dir = Path(fig_dir) if fig_dir is not None else out / "figures"
    arts = {r["material"]: load_artifacts(artifact_path(out, r)) for r in records}
    written: List[Path] = []

    def save(fig: Any, stem: str) -> None:
        written.extend(report.save_figure_formats(fig, fig_dir / stem, formats, dpi=dpi))

    probes_in = list(records[0]["inputs"])
    novel = list(records[0]["floor_images"])
    save(report.plot_reduction_ranking(records, arts, novel[0]), "fig3_reduction")
    # Fig. 5: the median material by recovered error under the first input probe.
    order = sorted(records, key=lambda r: r["inputs"][probes_in[0]]["recovered"]["log"])
    example = order[len(order) // 2]
    save(report.plot_validation(example, arts[example["material"]], probes_in[0], novel[0]), "fig5_validation")
    save(report.plot_incident_planes(example, arts[example["material"]], probes_in), "fig6_incident")
    save(report.plot_error_curves(records), "fig6_errors")
    save(report.plot_environment_dependence(example, arts[example["material"]], probes_in), "fig7_environment")
    save(report.plot_table_gallery(records, arts, probes_in), "tables")
    save(report.plot_baselines(records, probes_in[0]), "baselines")
    return written


# ------------------------------------------------------- analysis by synthesis

def analysis_by_synthesis(material: Union[str, MaterialSpec], input_probe: str = DEFAULT_INPUT_PROBES[0],
                          config: Optional[EvalConfig] = None, data_dir: Optional[PathLike] = None,
                          time_factor: float = 10.0, **kwargs: Any) -> dict:
    """The linear solve against differentiable rendering on one material: see
    :func:`mi_bivariate.synthesis.analysis_by_synthesis` (this is a thin wrapper)."""
    from mi_bivariate import synthesis

    return synthesis.analysis_by_synthesis(material, input_probe, config=config, data_dir=data_dir,
                                           time_factor=time_factor, **kwargs)


# ------------------------------------------------------------------ reporting

def _fmt(v: Any, digits: int = 3) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, (int, float)) and not math.isfinite(v):
        return "inf" if v > 0 else ("nan" if v != v else "-inf")
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) >= 1e3 or abs(v) < 1e-2 else f"{v:.{digits}f}"
    return str(v)


#: The results page's per-material table (:func:`markdown_table`): floors, where the image looks, relighting.
HEADLINE_COLUMNS = (("material", "material"), ("input_probe", "input"),
                    ("exact_floor", "exact floor"), ("grid_floor", "grid floor"),
                    ("recovered_eq1", "rec. Eq.1"), ("recovered_eq1_observed", "rec. Eq.1 obs."),
                    ("grid_floor_observed", "grid floor obs."), ("observed_fraction", "obs. cells"),
                    ("recovered_eq1_min", "rec. Eq.1>1e-3"), ("recovered_cosine", "rec. cos"),
                    ("recovered_log", "rec. log"),
                    ("recovered_eq1_specular", "Eq.1 spec."), ("recovered_eq1_retro", "Eq.1 retro"),
                    ("recovered_eq1_grazing", "Eq.1 grazing"), ("recovered_eq1_rest", "Eq.1 rest"),
                    ("relight_rmse_median", "relight"), ("relight_floor_median", "relight floor"),
                    ("relight_ratio_median", "ratio"))

SUMMARY_COLUMNS = (("material", "material"), ("input_probe", "input"),
                   ("floor_log", "floor log"), ("recovered_log", "rec. log"),
                   ("ggx_log", "GGX log"), ("ward_log", "Ward log"),
                   ("floor_eq1", "floor Eq.1"), ("recovered_eq1", "rec. Eq.1"),
                   ("floor_eq1_min", "floor Eq.1>1e-3"), ("recovered_eq1_min", "rec. Eq.1>1e-3"),
                   ("ggx_eq1_min", "GGX Eq.1>1e-3"), ("ward_eq1_min", "Ward Eq.1>1e-3"),
                   ("floor_cosine", "floor cos"), ("recovered_cosine", "rec. cos"),
                   ("image_rel_rmse_mean", "img RMSE"), ("floor_image_rel_rmse_mean", "floor img RMSE"),
                   ("image_psnr_mean", "PSNR dB"), ("rank_fraction", "rank"))


def markdown_table(records: Sequence[dict], columns: Sequence[Tuple[str, str]] = SUMMARY_COLUMNS) -> str:
    """The summary rows as a Markdown table (columns absent from every row are left out)."""
    rows = summary_rows(records)
    cols = [(k, h) for k, h in columns if any(k in r for r in rows)]
    lines = ["| " + " | ".join(h for _, h in cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(k, "")) for k, _ in cols) + " |" for r in rows]
    return "\n".join(lines)


def format_summary(records: Sequence[dict]) -> str:
    """A short plain-text summary: medians over materials per input probe, and the slowest stage."""
    rows = summary_rows(records)
    if not rows:
        return "no results"
    lines = [f"{len(records)} materials"]
    for probe in dict.fromkeys(r["input_probe"] for r in rows):
        sel = [r for r in rows if r["input_probe"] == probe]
        parts = []
        for key, label in (("exact_floor", "exact floor"), ("grid_floor", "grid floor"),
                           ("recovered_eq1_observed", "recovered Eq.1 observed"),
                           ("recovered_log", "recovered log"), ("ggx_log", "GGX log"), ("ward_log", "Ward log"),
                           ("recovered_eq1_min", "recovered Eq.1>1e-3"),
                           ("relight_rmse_median", "relight"), ("relight_floor_median", "relight floor"),
                           ("relight_ratio_median", "relight/floor")):
            vals = [r[key] for r in sel if key in r and math.isfinite(r[key])]
            if vals:
                parts.append(f"{label} {np.median(vals):.3f}")
        lines.append(f"  input {probe}: median " + ", ".join(parts))
    return "\n".join(lines)
