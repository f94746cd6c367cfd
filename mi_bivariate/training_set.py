"""The measured materials priors learn from, and leave-one-out priors for scoring.

The shared data holds 73 MERL-NBRDF materials (23 development, 50 training; see
:mod:`mi_bivariate.nbrdf`). Both priors of the solve, the smoothness weights of Eq. 6
(:class:`mi_bivariate.prior.Prior`) and the table basis
(:class:`mi_bivariate.basis_prior.BasisPrior`), are learnt from their exact bivariate
reductions (Eq. 1). A number reported on a shared material must come from priors
that never saw it: :func:`leave_one_out_priors`.

Reductions take ~1 s per material; they are cached (``.npz`` keyed by the
shared files' contents and the grid) in ``$MI_BIVARIATE_CACHE`` or
``~/.cache/mi_bivariate``.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import Any, Dict, Iterable, Optional, Sequence, Tuple, Union

import numpy as np

from . import coordinates
from .atomic import atomic_path
from .basis_prior import BasisPrior
from .bivariate import BivariateBRDF
from .common import PathLike
from .errors import InputError
from .merl import MERLBRDF
from .nbrdf import ALL_NBRDF_MATERIALS, NBRDF_FILE, NBRDF_TRAIN_FILE
from .nbrdf import data_dir as nbrdf_data_dir
from .nbrdf import nbrdf_merl
from .npzio import read_npz
from .prior import Prior
from .sources import merl_files


def cache_dir() -> Path:
    """Where derived data is cached: ``$MI_BIVARIATE_CACHE`` or ``~/.cache/mi_bivariate``."""
    value = os.environ.get("MI_BIVARIATE_CACHE")
    return Path(value) if value else Path.home() / ".cache" / "mi_bivariate"


def _data_digest(root: Path) -> str:
    h = hashlib.sha256()
    for rel in (NBRDF_FILE, NBRDF_TRAIN_FILE):
        path = root / rel
        if path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def reduced_tables(n_t: int = 32, n_s: int = 32, names: Sequence[str] = ALL_NBRDF_MATERIALS,
                   data_dir: Optional[PathLike] = None, cache: bool = True,
                   progress: bool = False) -> Dict[str, np.ndarray]:
    """Exact Eq. 1 reductions of shared MERL-NBRDF materials, ``{name: (n_t, n_s, 3) float64}`` (1/sr)."""
    root = nbrdf_data_dir(data_dir)
    code = _code_digest(BivariateBRDF, MERLBRDF, nbrdf_merl, coordinates)  # the reduction and what it reads
    path = cache_dir() / f"nbrdf_reductions_{_data_digest(root)}_{code}_{int(n_t)}x{int(n_s)}.npz"
    stored = _cached_tables(path, (int(n_t), int(n_s), 3)) if cache else {}
    missing = [n for n in names if n not in stored]
    if missing:
        iterator = missing
        if progress:
            from tqdm import tqdm

            iterator = tqdm(missing, desc="reducing materials", unit="material")
        for name in iterator:
            stored[name] = BivariateBRDF.reduce(nbrdf_merl(name, root), n_t=n_t, n_s=n_s).table.astype(np.float64)
        if cache:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_path(path, suffix=".npz") as tmp:
                    with open(tmp, "wb") as fh:
                        np.savez(fh, **stored)
            except (OSError, InputError):  # (atomic_path names an unwritable folder with an InputError)
                pass  # a read-only home only costs time
    return {n: stored[n] for n in names}


def _cached_tables(path: Path, shape: Tuple[int, int, int]) -> Dict[str, np.ndarray]:
    """The reductions cached in ``path``, those of the expected ``shape`` and finite; nothing where the
    file is missing or cannot be read (cut short, not a zip: they are reduced again)."""
    if not path.is_file():
        return {}
    try:
        stored = read_npz(path, "reductions cache", text=())
    except InputError:  # any damage costs time only
        return {}
    return {k: np.asarray(v, np.float64) for k, v in stored.items()
            if v.shape == shape and v.dtype.kind == "f" and np.all(np.isfinite(v))}


def learn_priors(tables: Dict[str, np.ndarray], exclude: Sequence[str] = (),
                 provenance: Optional[dict] = None) -> Tuple[Prior, BasisPrior]:
    """Both priors from ``tables`` without the materials in ``exclude`` (one name may be a string)."""
    exclude = (exclude,) if isinstance(exclude, str) else exclude
    kept = {k: v for k, v in tables.items() if k not in set(exclude)}
    if len(kept) < 3:
        raise InputError("prior training set", f"has {len(kept)} materials", "give at least 3")
    prov = {"excluded": sorted(exclude), **(provenance or {})}
    return Prior.learn(kept), BasisPrior.learn(kept, provenance=prov)


def _code_digest(*objects: Any) -> str:
    """A digest of the source files of ``objects`` (modules, or what they define): a cache entry is
    stale when they change."""
    h = hashlib.sha256()
    for item in objects:
        path = getattr(item, "__file__", None) or sys.modules[item.__module__].__file__
        h.update(Path(path).read_bytes())
    return h.hexdigest()[:12]


def _tables_digest(tables: Dict[str, np.ndarray]) -> str:
    """A digest of training tables (names, shapes and values): what the priors are learnt from."""
    h = hashlib.sha256()
    for name in sorted(tables):
        table = np.ascontiguousarray(tables[name], np.float64)
        h.update(name.encode() + b"\0" + repr(table.shape).encode() + b"\0")  # same bytes on another grid differ
        h.update(table.tobytes())
    return h.hexdigest()[:16]


def leave_one_out_priors(material: str, n_t: int = 32, n_s: int = 32,
                         data_dir: Optional[PathLike] = None, cache: bool = True) -> Tuple[Prior, BasisPrior]:
    """Priors learnt from every shared MERL-NBRDF material except ``material``.

    For a material outside the shared set this is simply all 73. With ``cache`` the pair is kept
    in :func:`cache_dir`, keyed by the training tables themselves (their names and values: the
    shared data and the reduction's code) and the code that learns the priors (learning the basis
    prior takes ~5-10 s on two cores: its leave-one-material-out residuals).
    """
    tables = reduced_tables(n_t, n_s, data_dir=data_dir)
    kept = {k: v for k, v in tables.items() if k != material}
    excluded = (material,) if material in tables else ()
    stem = cache_dir() / f"loo_priors_{_tables_digest(kept)}_{_code_digest(Prior, BasisPrior, learn_priors)}"
    paths = (stem.with_name(stem.name + "_smooth.npz"), stem.with_name(stem.name + "_basis.npz"))
    if cache and all(p.is_file() for p in paths):
        try:
            return Prior.load(paths[0]), BasisPrior.load(paths[1])
        except InputError:
            pass  # a damaged cache entry is learnt again
    priors = learn_priors(tables, exclude=excluded, provenance={"training": "shared MERL-NBRDF, leave-one-out"})
    if cache:
        try:
            paths[0].parent.mkdir(parents=True, exist_ok=True)
            for prior, path in zip(priors, paths):
                with atomic_path(path, suffix=".npz") as tmp:
                    prior.save(tmp)
        except (OSError, InputError):  # (atomic_path names an unwritable folder with an InputError)
            pass  # a read-only home only costs time
    return priors


def tables_from_sources(sources: Union[PathLike, Iterable[PathLike]], n_t: int = 32, n_s: int = 32,
                        data_dir: Optional[PathLike] = None,
                        progress: bool = False) -> Tuple[Dict[str, np.ndarray], Dict[str, str]]:
    """Reduce MERL materials to ``(n_t, n_s, 3)`` tables: a folder of ``.binary`` files, files,
    or MERL-NBRDF names (:data:`mi_bivariate.nbrdf.ALL_NBRDF_MATERIALS`); ``progress``: tqdm bars
    over the materials reduced.

    Returns:
        ``({name: table}, {name: where it came from})``.
    """
    tables: Dict[str, np.ndarray] = {}
    origin: Dict[str, str] = {}
    names = [str(s) for s in merl_files(sources) if str(s) in ALL_NBRDF_MATERIALS and not Path(s).is_file()]
    shared = reduced_tables(n_t, n_s, names, data_dir, progress=progress) if names else {}
    files = merl_files(sources)
    if progress and any(Path(src).is_file() for src in files):
        from tqdm import tqdm

        files = tqdm(files, desc="reducing MERL files", unit="material")
    for src in files:
        path = Path(src)
        if path.is_file():
            merl = MERLBRDF.read(path)
            name, where = (merl.name or path.stem), f"MERL file {path.name}"
            table = BivariateBRDF.reduce(merl, n_t=n_t, n_s=n_s).table.astype(np.float64)
        elif str(src) in shared:
            name, where, table = str(src), "MERL-NBRDF (Sztrajman et al. 2021 neural fit)", shared[str(src)]
        else:
            raise InputError(src, "not a MERL .binary file, a directory of them, or a MERL-NBRDF name",
                             "see mi_bivariate.nbrdf.ALL_NBRDF_MATERIALS for the names")
        if name in tables:
            raise InputError(src, f"material {name!r} given twice", "give each material once")
        tables[name], origin[name] = table, where
    if not tables:
        raise InputError("prior training set", "is empty")
    return tables, origin


def learn_prior_from_merl(sources: Union[PathLike, Iterable[PathLike]], n_t: int = 32, n_s: int = 32,
                          data_dir: Optional[PathLike] = None, **learn_kwargs) -> Prior:
    """The smoothness prior (:meth:`Prior.learn`) from MERL sources (see :func:`tables_from_sources`)."""
    tables, origin = tables_from_sources(sources, n_t, n_s, data_dir)
    return Prior.learn(tables, sources=origin, **learn_kwargs)


def learn_priors_from_merl(sources: Union[PathLike, Iterable[PathLike]], n_t: int = 32, n_s: int = 32,
                           data_dir: Optional[PathLike] = None, progress: bool = False) -> Tuple[Prior, BasisPrior]:
    """Both priors from MERL sources, each material reduced once (``progress``: bars while reducing)."""
    tables, origin = tables_from_sources(sources, n_t, n_s, data_dir, progress)
    return Prior.learn(tables, sources=origin), BasisPrior.learn(tables, provenance={"sources": origin})


def basis_path_for(prior_path: PathLike) -> Path:
    """Where ``learn-prior`` writes the basis prior beside a smoothness prior file: ``<stem>_basis.npz``.
    Raises :class:`InputError` for a path without a file name (``.``, ``/``), which no prior file has."""
    path = Path(prior_path)
    if not path.name:
        raise InputError(prior_path, "not a file", "give the path of a .npz file, not of a folder")
    return path.with_name(path.stem + "_basis.npz")


def load_prior_files(prior_path: PathLike, basis: bool = True) -> Tuple[Prior, Optional[BasisPrior]]:
    """The priors ``learn-prior`` wrote to ``prior_path``: the smoothness prior there and the basis prior
    beside it (:func:`basis_path_for`), or ``None`` where there is none (a recovery then uses no basis
    prior: never the packaged one, which saw every shared material) or ``basis`` is false (``recover
    --no-basis-prior``: that file is not read). What ``recover --prior`` and ``evaluate --prior`` load
    alike. Raises :class:`InputError` naming the file that cannot be used."""
    basis_file = basis_path_for(prior_path)
    return Prior.load(prior_path), BasisPrior.load(basis_file) if basis and basis_file.is_file() else None
