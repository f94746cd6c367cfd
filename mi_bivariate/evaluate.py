"""Batch evaluation: the paper's experiments over a set of materials (``mi-bivariate evaluate``).

Per material (a MERL ``.binary``, a MERL-NBRDF name or an analytic spec) and
per input probe:

1. render the input image of the full 3D BRDF with the ``merl`` plugin;
2. :func:`~mi_bivariate.recover.recover` the bivariate BRDF from it;
3. re-render the recovery (``bivariate`` plugin) under every novel probe next
   to the ground truth (``merl`` plugin) and the ideal bivariate reduction;
4. fit the parametric baselines (:mod:`mi_bivariate.baselines`) to the same
   observations through the same lighting matrix;
5. record the BRDF errors of :func:`mi_bivariate.metrics.brdf_errors` (Eq. 1,
   cosine-weighted, log-space) for the recovery, the bivariate floor and the
   baselines, image errors under each novel probe, the adequacy diagnostics
   and timings.

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
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.errors import InputError, InputWarning

PathLike = Union[str, os.PathLike]

#: Bumped when the protocol changes in a way that changes numbers (part of the config hash).
PROTOCOL_VERSION = 1
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

    @classmethod
    def quick(cls, shared_data: bool = True, **overrides) -> "EvalConfig":
        """Small sizes for the test suite and notebooks (seconds per material).

        Without the shared data (``shared_data=False``) the probes are synthetic.
        """
        base = dict(resolution=48, spp=16, novel_spp=8, n_normals=1000, n_dirs=3000, grid=(12, 12),
                    baseline_nfev=8, novel_probes=("pisa_256",))
        if not shared_data:
            base.update(input_probes=("synthetic:1", "synthetic:3"), novel_probes=("synthetic:7",))
        base.update(overrides)
        return cls(**base)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["input_probes"], d["novel_probes"] = list(self.input_probes), list(self.novel_probes)
        d["grid"], d["baselines"] = list(self.grid), list(self.baselines)
        return d

    def hash(self) -> str:
        """16 hex digits of SHA-256 over the canonical JSON of the config and protocol version."""
        text = json.dumps({"protocol": PROTOCOL_VERSION, "solver": _solver_identity(), **self.to_dict()},
                          sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _solver_identity() -> dict:
    """What else decides the numbers: the packaged prior's bytes and the default alpha.

    A finished material is only reused on resume when these are unchanged, so a
    re-learnt prior or a re-tuned alpha never mixes with old results.
    """
    from mi_bivariate import prior, solve

    digest = hashlib.sha256(Path(prior.DEFAULT_PRIOR_PATH).read_bytes()).hexdigest()[:16]
    return {"default_prior_sha256": digest, "default_alpha": solve.DEFAULT_ALPHA}


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
    """What a worker needs for one material (picklable)."""

    material: MaterialSpec
    config: EvalConfig
    data_dir: Optional[str] = None
    threads: Optional[int] = None


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


def evaluate_material(task: MaterialTask) -> Tuple[dict, Dict[str, np.ndarray]]:
    """Run the protocol of the module docstring for one material.

    Returns:
        ``(record, arrays)``: the JSON record (one line of ``results.jsonl``)
        and the artifact arrays (``materials/<slug>.npz``).
    """
    from mi_bivariate import baselines, metrics, render
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.recover import recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    cfg, data_dir = task.config, task.data_dir
    t_start = time.perf_counter()
    timings: Dict[str, float] = {}
    # Probes first: their EXR reads need worker threads (see _io_threads).
    inputs = [load_probe(p, data_dir) for p in cfg.input_probes]
    novels = [load_probe(p, data_dir) for p in cfg.novel_probes]
    if task.threads is not None:
        import drjit as dr

        dr.set_thread_count(int(task.threads))

    t0 = time.perf_counter()
    truth = load_truth(task.material, data_dir)
    n_t, n_s = cfg.grid
    floor = BivariateBRDF.reduce(truth, n_t=n_t, n_s=n_s)
    timings["truth"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    brdf_errors = metrics.BRDFErrors(truth)
    floor_errors = brdf_errors(floor)
    timings["brdf_errors"] = time.perf_counter() - t0

    arrays: Dict[str, np.ndarray] = {"floor": floor.table}
    arrays.update(_incident_curves(truth))
    truth_bsdf = render.bsdf_dict(truth)
    res = cfg.resolution

    t0 = time.perf_counter()
    truth_novel, floor_images = {}, {}
    floor_bsdf = render.bsdf_dict(floor)
    for k, (name, probe) in enumerate(zip(cfg.novel_probes, novels)):
        label = probe_label(name)
        shot = render.render_sphere(truth_bsdf, probe, resolution=res, spp=cfg.novel_spp, seed=cfg.seed + 1 + k)
        floor_shot = render.render_sphere(floor_bsdf, probe, resolution=res, spp=cfg.novel_spp,
                                          seed=cfg.seed + 1 + k)
        truth_novel[label] = shot
        floor_images[label] = _image_errors(floor_shot.image, shot.image, shot.mask)
        arrays[f"truth__{label}"] = _f16(shot.image)
        arrays[f"floor_render__{label}"] = _f16(floor_shot.image)
        arrays["mask"] = shot.mask
    timings["render_truth_novel"] = time.perf_counter() - t0

    per_input: Dict[str, dict] = {}
    for name, probe in zip(cfg.input_probes, inputs):
        label = probe_label(name)
        entry: Dict[str, Any] = {}
        t0 = time.perf_counter()
        shot = render.render_sphere(truth_bsdf, probe, resolution=res, spp=cfg.spp, seed=cfg.seed)
        t_render = time.perf_counter() - t0
        rec = recover(shot.image, probe, shot.geometry, n_normals=cfg.n_normals, n_dirs=cfg.n_dirs,
                      grid=cfg.grid, alpha=cfg.alpha, seed=cfg.seed, keep_inputs=False)
        entry["timings"] = {"render_input": t_render, **rec.timings}
        t0 = time.perf_counter()
        entry["recovered"] = brdf_errors(rec.brdf)
        entry["timings"]["brdf_errors"] = time.perf_counter() - t0
        entry["relative_residual"] = rec.relative_residual()
        entry["prior_winner"] = list(rec.solution.winner)
        entry["alpha"] = float(rec.solution.alpha)
        entry["observations"] = int(len(rec.observations.values))
        entry["adequacy"] = _adequacy_summary(rec.adequacy)
        arrays[f"input__{label}"] = _f16(shot.image)
        arrays[f"recovered__{label}"] = rec.brdf.table
        arrays[f"observation_map__{label}"] = np.asarray(rec.adequacy.observation_map, np.float32)

        t0 = time.perf_counter()
        images = {}
        rec_bsdf = render.bsdf_dict(rec.brdf)
        for k, novel_name in enumerate(cfg.novel_probes):
            nl = probe_label(novel_name)
            img = render.render_sphere(rec_bsdf, novels[k], resolution=res, spp=cfg.novel_spp,
                                       seed=cfg.seed + 1 + k).image
            images[nl] = _image_errors(img, truth_novel[nl].image, truth_novel[nl].mask)
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
            entry["baselines"][fam] = {**fit.summary(), "errors": brdf_errors(fit.brdf)}
            arrays[f"baseline__{label}__{fam}"] = fit.table.table
        entry["timings"]["baselines_errors"] = time.perf_counter() - t0
        del rec
        per_input[label] = entry

    timings["total"] = time.perf_counter() - t_start
    record = {
        "material": task.material.label,
        "kind": task.material.kind,
        "spec": task.material.spec,
        "slug": task.material.slug,
        "config_hash": cfg.hash(),
        "floor": floor_errors,
        "floor_images": floor_images,
        "inputs": per_input,
        "timings": timings,
        "threads": task.threads,
    }
    return record, arrays


# ------------------------------------------------------------------ results I/O

def read_records(path: PathLike, config_hash: Optional[str] = None) -> List[dict]:
    """Records of a ``results.jsonl`` (optionally only those with ``config_hash``).

    Lines that do not parse (a last line cut by an interruption) are skipped.
    """
    path = Path(path)
    if not path.is_file():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and (config_hash is None or rec.get("config_hash") == config_hash):
            records.append(rec)
    return records


def repair_results(path: PathLike) -> int:
    """Drop unparsable lines of a results file (atomically) so appends start on a fresh line.

    Returns the number of lines dropped. Every complete record is kept,
    whatever its configuration.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    raw = path.read_bytes()
    lines = raw.decode("utf-8", errors="replace").splitlines()
    good = []
    for line in lines:
        try:
            if isinstance(json.loads(line), dict):
                good.append(line)
        except json.JSONDecodeError:
            pass
    dropped = len(lines) - len(good)
    if dropped or (raw and not raw.endswith(b"\n")):
        with atomic_path(path) as tmp:
            tmp.write_text("".join(g + "\n" for g in good))
    return dropped


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


def _init_worker(variant: Optional[str]) -> None:
    from mi_bivariate.variants import ensure_variant

    ensure_variant(variant)


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
        from distributed import Client, as_completed

        client = dask if isinstance(dask, Client) else Client(dask)
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
                                   initializer=_init_worker, initargs=(mi.variant(),))
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
    if jobs < 1:
        raise InputError("--jobs", f"must be >= 1, got {jobs}")
    specs = [m if isinstance(m, MaterialSpec) else None for m in materials]
    if any(s is None for s in specs):
        specs = resolve_materials([str(m) for m in materials if not isinstance(m, MaterialSpec)], data_dir) + \
            [m for m in materials if isinstance(m, MaterialSpec)]
    if not specs:
        raise InputError("materials", "no materials given")
    # Fail early (in the parent, with a one-line error) on a missing probe or data folder.
    for p in tuple(config.input_probes) + tuple(config.novel_probes):
        load_probe(p, data_dir)
    out = Path(out_dir)
    (out / "materials" / config.hash()).mkdir(parents=True, exist_ok=True)
    results = out / RESULTS_FILE
    repair_results(results)
    h = config.hash()
    done = {r["material"] for r in read_records(results, h)}
    if threads is None and dask is None and jobs > 1:
        threads = threads_per_job(jobs)
    tasks = [MaterialTask(m, config, None if data_dir is None else str(data_dir), threads)
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
        for key, label in (("floor_log", "floor log"), ("recovered_log", "recovered log"),
                           ("ggx_log", "GGX log"), ("ward_log", "Ward log"),
                           ("recovered_eq1_min", "recovered Eq.1>1e-3"), ("image_rel_rmse_mean", "image RMSE")):
            vals = [r[key] for r in sel if key in r and math.isfinite(r[key])]
            if vals:
                parts.append(f"{label} {np.median(vals):.3f}")
        lines.append(f"  input {probe}: median " + ", ".join(parts))
    return "\n".join(lines)
