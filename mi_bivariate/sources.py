"""Names and paths to materials and probes: the one place the CLI, the demo, the
evaluation and prior learning turn what a user types into data.

A *BRDF spec* is one of

- a MERL ``.binary`` file (the full 3D table, :class:`~mi_bivariate.merl.MERLBRDF`);
- a bivariate ``.npz`` (:class:`~mi_bivariate.bivariate.BivariateBRDF`, :func:`load_brdf` only);
- a shared MERL-NBRDF material name (:data:`mi_bivariate.nbrdf.ALL_NBRDF_MATERIALS`,
  tabulated on the MERL grid; needs the shared data folder);
- an analytic spec such as ``ggx:alpha=0.1`` or a bare family name
  (:data:`ANALYTIC_NAMES`, :func:`mi_bivariate.analytic.analytic_from_spec`),
  tabulated on the MERL grid.

A *probe spec* is an environment map file (``.exr``, ``.hdr``, ``.pfm``), a
shared probe name (:data:`mi_bivariate.probes.SHARED_PROBES`) or
``synthetic:SEED`` (:func:`synthetic_environment`, for runs without the shared data).

Bad input raises :class:`~mi_bivariate.errors.InputError` naming the spec.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import drjit as dr
import numpy as np

from mi_bivariate import analytic, bivariate, limits, merl, nbrdf, probes
from mi_bivariate.common import PathLike, file_digest
from mi_bivariate.errors import InputError

#: Analytic families a spec may name without parameters (their class defaults).
ANALYTIC_NAMES: Tuple[str, ...] = ("lambertian", "ggx", "oren-nayar", "bivariate-lobe")
#: The analytic material of runs without the shared data (demo, ``evaluate --quick``):
#: Cook-Torrance/GGX with a coloured diffuse base, not bivariate.
DEFAULT_ANALYTIC = "ggx:diffuse=0.25,0.12,0.05,specular=0.6,alpha=0.12,ior=1.5"
#: Prefix of a synthetic probe spec (``synthetic:SEED``).
SYNTHETIC_PREFIX = "synthetic:"


def is_analytic_spec(spec: str) -> bool:
    """True when ``spec`` is meant as an analytic BRDF (``kind:params`` or a bare family name)."""
    return ":" in spec or spec in ANALYTIC_NAMES


def have_shared_data(data_dir: Optional[PathLike] = None) -> bool:
    """True when the shared data folder (probes and MERL-NBRDF fits) is available."""
    try:
        nbrdf.data_dir(data_dir)
        return True
    except InputError:
        return False


# ------------------------------------------------------------------ BRDFs

def load_brdf(spec: str, data_dir: Optional[PathLike] = None,
              dtype: Any = np.float64) -> Union["merl.MERLBRDF", "bivariate.BivariateBRDF"]:
    """A BRDF from a spec: a MERL ``.binary``, a bivariate ``.npz``, a MERL-NBRDF name or an analytic spec.

    Args:
        spec: the spec (see the module docstring).
        data_dir: the shared data folder (default ``$MI_BIVARIATE_DATA``), for MERL-NBRDF names.
        dtype: table dtype of an analytic spec tabulated on the MERL grid.

    Raises:
        InputError: a file of another type, or a spec that is none of these.
    """
    path = Path(spec)
    if path.suffix.lower() == ".binary":
        return merl.MERLBRDF.read(path)
    if path.suffix.lower() == ".npz":
        return bivariate.BivariateBRDF.load(path)
    if spec in nbrdf.ALL_NBRDF_MATERIALS:
        return nbrdf.nbrdf_merl(spec, data_dir=data_dir)
    if is_analytic_spec(spec):
        return analytic.to_merl(analytic.analytic_from_spec(spec), dtype=dtype)
    if path.exists():
        raise InputError(path, "unknown BRDF file type", "use a MERL .binary or a bivariate .npz")
    raise InputError(spec, "not a file, an NBRDF material name or an analytic spec",
                     f"NBRDF names: {', '.join(nbrdf.NBRDF_MATERIALS)}")


def merl_files(sources: Union[PathLike, Iterable[PathLike]]) -> List[PathLike]:
    """Expand folders among ``sources`` into their MERL ``.binary`` files (sorted); other items as given.

    Raises:
        InputError: a folder without ``.binary`` files.
    """
    if isinstance(sources, (str, os.PathLike)):
        sources = [sources]
    expanded: List[PathLike] = []
    for src in sources:
        path = Path(src)
        expanded.extend(merl.merl_files_in(path) if path.is_dir() else [src])
    return expanded


#: Keywords naming sets of shared MERL-NBRDF materials (:mod:`mi_bivariate.nbrdf`).
NBRDF_SETS: Dict[str, Tuple[str, ...]] = {
    "nbrdf": nbrdf.NBRDF_MATERIALS,             # the 23 development materials
    "nbrdf-train": nbrdf.NBRDF_TRAIN_MATERIALS,  # the 50 the priors and settings were learnt on
    "nbrdf-all": nbrdf.ALL_NBRDF_MATERIALS,      # all 73
}


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

    def source_digest(self) -> Optional[str]:
        """A ``"merl"`` material's :func:`~mi_bivariate.common.file_digest` (``None`` for the other kinds,
        which their name or spec determines): a result kept for a file's label is not reused once the file's
        content changes, or the label is given by another file."""
        return file_digest(self.spec) if self.kind == "merl" else None


def resolve_materials(items: Sequence[str], data_dir: Optional[PathLike] = None) -> List[MaterialSpec]:
    """Expand material arguments into :class:`MaterialSpec` s (duplicates dropped, order kept).

    Each item is a folder (its ``*.binary`` files, sorted), a MERL ``.binary``
    file, a keyword of :data:`NBRDF_SETS` (``nbrdf``: the 23 MERL-NBRDF development
    materials; ``nbrdf-train``: the 50 training ones; ``nbrdf-all``: all 73), a
    shared MERL-NBRDF name, or an analytic spec such as ``ggx:alpha=0.1``.

    Raises:
        InputError: an item that is none of these, an empty folder, or two different materials of one
            label (:func:`unique_materials`).
    """
    out: List[MaterialSpec] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            out += [MaterialSpec(f.stem, "merl", str(f)) for f in merl.merl_files_in(path)]
        elif path.suffix.lower() == ".binary":  # as load_brdf and render read it
            if not path.is_file():
                raise InputError(path, "MERL file not found", "check the path")
            out.append(MaterialSpec(path.stem, "merl", str(path)))
        elif item in NBRDF_SETS:
            out += [MaterialSpec(n, "nbrdf", n) for n in NBRDF_SETS[item]]
        elif item in nbrdf.ALL_NBRDF_MATERIALS:
            out.append(MaterialSpec(item, "nbrdf", item))
        elif is_analytic_spec(item):
            out.append(MaterialSpec(analytic.analytic_from_spec(item).name, "analytic", item))
        else:
            raise InputError(item, "not a folder, .binary file, MERL-NBRDF name or analytic spec",
                             f"MERL-NBRDF names: {', '.join(nbrdf.ALL_NBRDF_MATERIALS)}; or one of "
                             f"{', '.join(NBRDF_SETS)}")
    return unique_materials(out)


def unique_materials(specs: Sequence[MaterialSpec]) -> List[MaterialSpec]:
    """``specs`` with repeats of one material dropped (order kept).

    Results are kept by a material's label, so two *different* materials of one label (two MERL files of
    one name in two folders, a file named like a shared material) cannot both be evaluated: the second is
    refused, never silently dropped.

    Raises:
        InputError: two materials of one label.
    """
    def identity(m: MaterialSpec) -> Tuple[str, str]:  # a file by its real path; a name or spec by its label
        return (m.kind, os.path.realpath(m.spec) if m.kind == "merl" else m.label)

    first: Dict[str, MaterialSpec] = {}
    for m in specs:
        seen = first.setdefault(m.label, m)
        if identity(seen) != identity(m):
            raise InputError(m.spec, f"another material given is also named {m.label!r} ({seen.spec}); results "
                                     "are kept by name", "rename one of the files, or evaluate them in separate "
                                     "runs (another --out)")
    return list(first.values())


def load_truth(material: MaterialSpec, data_dir: Optional[PathLike] = None) -> "merl.MERLBRDF":
    """The material's 3D table (:class:`~mi_bivariate.merl.MERLBRDF`; analytic ones in float32)."""
    if material.kind == "merl":
        return merl.MERLBRDF.read(material.spec)
    if material.kind == "nbrdf":
        return nbrdf.nbrdf_merl(material.spec, data_dir=data_dir)
    truth = analytic.to_merl(analytic.analytic_from_spec(material.spec), dtype=np.float32)
    merl.check_reflects(truth.table, material.spec)  # its input photo would be black: nothing to recover
    return truth


# ------------------------------------------------------------------ probes

def synthetic_environment(height: int = 128, width: int = 256, seed: int = 0) -> np.ndarray:
    """A procedural lat-long environment ``(H, W, 3) float32``: sky, sun, ground and windows.

    Used when no real probe is available. It has a bright sun, a sky
    gradient, a darker ground and a few bright rectangular "windows" at
    random azimuths, so it is neither symmetric nor low-frequency.
    """
    rng = np.random.default_rng(seed)
    theta = (np.arange(height) + 0.5) / height * np.pi           # polar angle from +y
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    up = np.cos(th)
    sky = np.where(up[..., None] > 0, np.array([0.35, 0.5, 0.9]) * (0.4 + 0.6 * up[..., None]),
                   np.array([0.25, 0.2, 0.15]) * (0.5 + 0.5 * (-up[..., None])))
    sun_dir = np.array([np.sin(0.7) * np.cos(1.0), np.cos(0.7), np.sin(0.7) * np.sin(1.0)])
    dirs = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], axis=-1)
    cos_sun = dirs @ sun_dir
    env = sky + np.array([60.0, 55.0, 45.0]) * (cos_sun > np.cos(0.06))[..., None]
    env += np.array([2.0, 1.8, 1.5]) * np.exp((cos_sun - 1.0) / 0.02)[..., None]
    for _ in range(6):
        p0, t0 = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 1.6)
        dp, dt = rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4)
        inside = (np.abs(np.angle(np.exp(1j * (ph - p0)))) < dp) & (np.abs(th - t0) < dt)
        env[inside] += rng.uniform(2.0, 8.0) * rng.uniform(0.7, 1.0, size=3)
    return env.astype(np.float32)


@contextlib.contextmanager
def _io_threads() -> Iterator[None]:
    """At least 2 Dr.Jit threads while Mitsuba reads or writes images.

    Measured with Mitsuba 3.9.1: ``mi.Bitmap`` EXR reading and writing never
    return when ``dr.set_thread_count(1)`` is in force (the OpenEXR tasks
    wait on a pool without workers).
    """
    n = dr.thread_count()
    if n < 2:
        dr.set_thread_count(2)
    try:
        yield
    finally:
        if n < 2:
            dr.set_thread_count(n)


#: Probes kept by :func:`load_probe` with ``cache``, by :func:`_probe_key`.
_PROBE_CACHE: Dict[Tuple[Any, ...], "probes.Probe"] = {}


def input_files(*specs: Optional[PathLike], data_dir: Optional[PathLike] = None) -> List[Path]:
    """The files that specs of probes, materials or MERL folders read (for the check that no output
    overwrites an input): a file as given, a folder's MERL ``.binary`` files, and the shared file
    behind a shared probe name or a MERL-NBRDF name. Specs that name nothing on disk (analytic,
    ``synthetic:SEED``, a shared name without the data folder) contribute nothing.
    """
    files: List[Path] = []
    for spec in specs:
        if spec is None or not str(spec):
            continue
        path, name = Path(spec), str(spec)
        try:
            if path.is_dir():
                files += [Path(f) for f in merl.merl_files_in(path)]
            elif path.is_file():
                files.append(path)
            elif name in nbrdf.ALL_NBRDF_MATERIALS:
                files.append(nbrdf.weights_path(name, data_dir))
            elif name in probes.SHARED_PROBES:
                files.append(probes.shared_probe_path(name, data_dir))
        except InputError:  # not resolvable: the command's own loading reports it
            continue
    return files


def load_probe(spec: str, data_dir: Optional[PathLike] = None, cache: bool = False) -> "probes.Probe":
    """A probe by file path, shared name or ``synthetic:SEED``.

    A path to a shared probe's own file (in ``data_dir``, ``$MI_BIVARIATE_DATA``, or a shared data
    folder: ``probes/`` beside ``merl_nbrdf/``) is that shared probe, with its rotation
    (``grace_latlong_1k``: :data:`~mi_bivariate.probes.GRACE_LATLONG_ROTATION`); any other file is
    read as is. ``synthetic:SEED`` is :func:`synthetic_environment` (a 128 x 256 sky with
    sun and windows), for runs without the shared data. With ``cache`` the
    probe is kept for the rest of the process, keyed by the spec and the file it resolves to (its real
    path, size and modification time, and the shared probe it is): batch runs load each probe once, and
    another data folder (``data_dir`` or ``$MI_BIVARIATE_DATA``) or a file rewritten since is read afresh.

    Raises:
        InputError: an unreadable file, an unknown shared name, a bad seed.
    """
    seed: Optional[int] = None
    path: Optional[Path] = None
    name: Optional[str] = None
    if spec.startswith(SYNTHETIC_PREFIX):
        try:
            seed = int(spec[len(SYNTHETIC_PREFIX):])
        except ValueError:
            seed = None
        if seed is None or not 0 <= seed <= limits.MAX_SEED:  # numpy refuses a negative seed with a traceback
            raise InputError(spec, f"synthetic probe seed must be an integer from 0 to {limits.MAX_SEED}")
    elif Path(spec).suffix:
        path = Path(spec)
        name = _shared_probe_name(path, data_dir)
    else:
        path, name = probes.shared_probe_path(spec, data_dir), spec
    key = _probe_key(spec, path, name) if cache else None
    if key is not None and key in _PROBE_CACHE:
        return _PROBE_CACHE[key]
    with _io_threads():
        if path is None:
            probe = probes.Probe(synthetic_environment(seed=seed), source=spec)
        else:
            probe = probes.Probe.load(path, rotation=None if name is None else probes.shared_rotation(name))
    if key is not None:
        _PROBE_CACHE[key] = probe
    return probe


def _probe_key(spec: str, path: Optional[Path], name: Optional[str]) -> Optional[Tuple[Any, ...]]:
    """The cache key of a probe: the spec, and for a file its real path, size and modification time (ns)
    and the shared probe it is (which sets its rotation); ``None`` (not cached) for a file that cannot be
    seen (its load reports it)."""
    if path is None:
        return (spec,)
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return (spec, os.path.realpath(path), stat.st_size, stat.st_mtime_ns, name)


def _shared_probe_name(path: Path, data_dir: Optional[PathLike]) -> Optional[str]:
    """The shared probe whose file ``path`` is (the same file on disk, through any symbolic links),
    else ``None``."""
    path = Path(os.path.realpath(path))  # a link to a shared probe's file is that file
    if path.stem not in probes.SHARED_PROBES or not path.is_file():
        return None
    folders = [data_dir, os.environ.get("MI_BIVARIATE_DATA")]
    if path.parent.name == "probes" and (path.parent.parent / "merl_nbrdf").is_dir():
        folders.append(path.parent)
    for folder in folders:
        if not folder:
            continue
        try:
            if os.path.samefile(path, probes.shared_probe_path(path.stem, folder)):
                return path.stem
        except (InputError, OSError):
            continue
    return None


def probe_label(spec: str) -> str:
    """Short name of a probe spec (file stem)."""
    return Path(spec).stem if Path(spec).suffix else spec


def input_label(name: str) -> str:
    """Short name of an evaluation input, one probe or several joined by ``+`` (each by :func:`probe_label`)."""
    return "+".join(probe_label(p) for p in name.split("+"))
