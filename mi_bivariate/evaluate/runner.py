"""Running an evaluation: the front door :func:`run_evaluation`, in-process, in worker
processes or on a Dask cluster, resuming from ``results.jsonl``.

Materials run in parallel in worker processes (``jobs``; spawn context,
Dr.Jit threads per worker = cores // jobs) or on a Dask cluster. The Mitsuba
variant is selected once at each front door: :func:`run_evaluation` (and the
in-process tasks), :func:`_init_worker` (each worker process) and
:func:`_evaluate_on_dask_worker` (each Dask task). One run holds an output
folder at a time (:func:`_folder_lock`). Every random choice is seeded, so the
same command reproduces the same numbers.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import multiprocessing
import os
import shutil
import warnings
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import as_completed as cf_completed
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import mitsuba as mi
import numpy as np

from mi_bivariate import nbrdf, training_set
from mi_bivariate.atomic import atomic_path
from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError, InputWarning, Terminated
from mi_bivariate.evaluate.config import EvalConfig, shared_data_digest
from mi_bivariate.evaluate.protocol import MaterialTask, evaluate_material
from mi_bivariate.evaluate.results import (
    RESULTS_FILE,
    SUMMARY_FILE,
    append_record,
    artifact_path,
    make_figures,
    read_records,
    repair_results,
    same_data,
    save_artifacts,
    write_summary_csv,
)
from mi_bivariate.merl import MERLBRDF
from mi_bivariate.probes import check_lit
from mi_bivariate.process import die_with_parent
from mi_bivariate.sources import MaterialSpec, load_probe, resolve_materials, unique_materials
from mi_bivariate.threads import pin_process_threads
from mi_bivariate.variants import ensure_variant

#: Folder (under the output folder) of cached reference renders of truths and exact reductions.
REFERENCE_DIR = "references"
#: Held (``flock``) by the run using an output folder.
LOCK_FILE = ".evaluate.lock"


def threads_per_job(jobs: int) -> int:
    """Dr.Jit threads for each of ``jobs`` worker processes: the cores shared out, at least 1."""
    return max(1, (os.cpu_count() or 1) // max(1, jobs))


def _init_worker(variant: Optional[str], parent: Optional[int] = None, threads: Optional[int] = None) -> None:
    """Worker set-up: die with the parent (``PR_SET_PDEATHSIG`` on Linux and a
    watchdog thread polling ``os.getppid``), select the variant, and give this
    process ``threads`` BLAS/OpenMP threads and solve workers (its own setting:
    nothing to restore, the parent's environment is untouched)."""
    if parent is not None:
        die_with_parent(parent)
    if threads is not None:
        pin_process_threads(threads)
    ensure_variant(variant)


def _evaluate_on_dask_worker(task: MaterialTask, variant: str) -> Tuple[dict, Dict[str, np.ndarray]]:
    """A Dask worker's front door: select the parent's variant, then run the protocol."""
    ensure_variant(variant)
    return evaluate_material(task)


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
            variant = mi.variant()
            futures = {client.submit(_evaluate_on_dask_worker, t, variant, pure=False,
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
    with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_init_worker,
                             initargs=(mi.variant(), os.getpid(), tasks[0].threads or threads_per_job(jobs))) as pool:
        futures = {pool.submit(evaluate_material, t): t for t in tasks}
        try:
            for fut in cf_completed(futures):
                try:
                    yield futures[fut], fut.result()
                except Exception as exc:  # noqa: BLE001
                    yield futures[fut], exc
        except BaseException as exc:
            for fut in futures:
                fut.cancel()
            if isinstance(exc, Terminated):
                # SIGTERM to this process alone (``timeout``) would leave the pool's shutdown waiting for the
                # workers' materials to finish: end them now, as their death signal would (Ctrl-C reaches
                # them itself, and they clean up after it). Only this pool's processes.
                for worker in list(getattr(pool, "_processes", {}).values()):
                    worker.terminate()
            raise


def run_evaluation(materials: Sequence[Union[str, MaterialSpec]], out_dir: PathLike,
                   config: Optional[EvalConfig] = None, jobs: int = 1, dask: Any = None,
                   data_dir: Optional[PathLike] = None, progress: bool = True,
                   figures: bool = True, figure_formats: Sequence[str] = ("png",),
                   on_record: Optional[Callable[[dict], None]] = None,
                   threads: Optional[int] = None,
                   on_failure: Optional[Callable[[MaterialSpec, BaseException], None]] = None) -> List[dict]:
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
        on_failure: called with the material and its exception for each material that failed (it
            is also warned about, and the others go on; a rerun tries it again).
        threads: Dr.Jit threads per job (default: cores // jobs in worker
            processes; unchanged in-process and on Dask). On the CPU the numbers
            are bitwise reproducible for any number (the lighting matrix sums each
            entry in one order).

    Returns:
        All records of this configuration, in material order (a material that failed has none).

    Raises:
        InputError: bad settings, probes, prior or files (before any material runs), or every
            material failed with one (the first's).
    """
    ensure_variant()
    config = config or EvalConfig()
    config.validate()
    if jobs < 1:
        raise InputError("--jobs", f"must be >= 1, got {jobs}")
    specs = [m if isinstance(m, MaterialSpec) else None for m in materials]
    if any(s is None for s in specs):
        specs = resolve_materials([str(m) for m in materials if not isinstance(m, MaterialSpec)], data_dir) + \
            [m for m in materials if isinstance(m, MaterialSpec)]
    specs = unique_materials(specs)  # a material given twice once; two of one name refused
    if not specs:
        raise InputError("materials", "no materials given")
    # Fail early (in the parent, with a one-line error naming the file) on a missing, black or (an
    # input probe) partly dark probe, a missing data folder, an unusable prior, a damaged MERL file or
    # an unreachable scheduler: before the output folder exists, not once per material.
    for name in config.input_probes:
        parts = name.split("+")
        for part in parts:
            # One input probe is all its recovery's light: every channel must be lit (as `recover` asks);
            # the views of a multi-view input ("a+b") only need light between them.
            check_lit(load_probe(part, data_dir, cache=True), part, every_channel=len(parts) == 1)
    for name in config.novel_probes:
        check_lit(load_probe(name, data_dir, cache=True), name)
    if config.prior is not None:
        training_set.load_prior_files(config.prior)  # and the basis prior beside it, as each material loads them
    for m in specs:
        if m.kind == "merl":
            MERLBRDF.check_file(m.spec)
        elif m.kind == "nbrdf":  # the shared data folder and its weights file: every such material's problem
            nbrdf.check_weights(nbrdf.weights_path(m.spec, data_dir))
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "the output folder is a file", "choose another --out")
    if figures and (out / "figures").exists() and not (out / "figures").is_dir():
        raise InputError(out / "figures", "is a file, where the figures go",
                         "move it away, choose another --out, or pass --no-figures")
    client = _connect_dask(dask) if dask is not None else None
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out, f"cannot create the output folder ({exc.strerror or exc})") from None
    try:
        with _folder_lock(out):
            records = _run_locked(specs, out, config, jobs, client, data_dir, progress, figures,
                                  figure_formats, on_record, threads, created, on_failure)
    finally:
        if client is not None and client is not dask:
            client.close()
    return records


def _run_locked(specs: List[MaterialSpec], out: Path, config: EvalConfig, jobs: int, dask: Any,
                data_dir: Optional[PathLike], progress: bool, figures: bool, figure_formats: Sequence[str],
                on_record: Optional[Callable[[dict], None]], threads: Optional[int], created: bool,
                on_failure: Optional[Callable[[MaterialSpec, BaseException], None]] = None) -> List[dict]:
    """:func:`run_evaluation`'s work, in a folder it holds the lock of."""
    (out / "materials" / config.hash()).mkdir(parents=True, exist_ok=True)
    results = out / RESULTS_FILE
    repair_results(results)
    h = config.hash()
    # A MERL file's record counts as done only for the same bytes: its label (the file's stem) given by another
    # file, or by the same file since changed, is evaluated again (its new record, appended, is the one read).
    # Records written before the digest was kept have none: their MERL files are evaluated once more.
    digest = {m.label: m.source_digest() for m in specs}
    # A shared probe or MERL-NBRDF material counts as done only for the same shared files (another --data folder
    # may hold other bytes under the same names): results.same_data.
    first_of_kind = {m.kind: m for m in reversed(specs)}  # the digest depends on the kind only: read each file once
    by_kind = {kind: shared_data_digest(config, m, data_dir) for kind, m in first_of_kind.items()}
    shared = {m.label: by_kind[m.kind] for m in specs}

    def reusable(r: dict) -> bool:
        label = r["material"]
        return same_data(r, {"source_sha256": digest.get(label), "shared_data_sha256": shared.get(label)})

    done = {r["material"] for r in read_records(results, h) if reusable(r)}
    if threads is None and dask is None and jobs > 1:
        threads = threads_per_job(jobs)
    tasks = [MaterialTask(m, config, None if data_dir is None else str(data_dir), threads,
                          cache_dir=str(out / REFERENCE_DIR))
             for m in specs if m.label not in done]
    with atomic_path(out / "config.json") as tmp:
        tmp.write_text(json.dumps({"config_hash": h, **config.to_dict()}, indent=2))

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
                    if on_failure is not None:
                        on_failure(task.material, result)
                    continue
                record, arrays = result
                for message in record.get("warnings", ()):  # said here, whichever process evaluated it
                    warnings.warn(message, InputWarning, stacklevel=2)
                if digest[task.material.label] is not None:  # a MERL file: its bytes, and artifacts of their own
                    record["source_sha256"] = digest[task.material.label]
                    record["slug"] = f"{record['slug']}-{record['source_sha256'][:8]}"
                if shared[task.material.label] is not None:  # the shared files' bytes, and artifacts of their own
                    record["shared_data_sha256"] = shared[task.material.label]
                    record["slug"] = f"{record['slug']}-{record['shared_data_sha256'][:8]}"
                # Artifacts before the record: a record on disk always has its artifacts.
                save_artifacts(artifact_path(out, record), arrays)
                append_record(results, record)
                if on_record is not None:
                    on_record(record)
                bar.set_postfix_str(record["material"][:24])
        finally:
            bar.close()

    by_label = {r["material"]: r for r in read_records(results, h) if reusable(r)}
    records = [by_label[m.label] for m in specs if m.label in by_label]
    write_summary_csv(records, out / SUMMARY_FILE)
    if figures and records:
        make_figures(out, records, formats=figure_formats)
    if failures and not records:
        label, exc = failures[0]
        if created:  # nothing came of it: leave no folder behind
            shutil.rmtree(out, ignore_errors=True)
        if isinstance(exc, InputError):
            raise exc
        raise RuntimeError(f"every material failed; first: {label}: {type(exc).__name__}: {exc}") from exc
    return records
