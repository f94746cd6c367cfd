"""What decides an evaluation's numbers: :class:`EvalConfig`, its hash, and the solver's identity.

A finished material is reused on resume only when the hash of its
configuration (:meth:`EvalConfig.hash`) is unchanged; the hash covers the
settings, :data:`PROTOCOL_VERSION` and the solver's identity (the packaged
priors' bytes and the default alpha), so a re-learnt prior or a re-tuned
alpha never mixes with old results. The shared probes and MERL-NBRDF weights
enter it by name only: each record keeps :func:`shared_data_digest` beside it,
so that another shared data folder (``--data``) holding other bytes under the
same names is evaluated again.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

from mi_bivariate import basis_prior, nbrdf, prior, probes, solve, training_set
from mi_bivariate.baselines import FAMILIES
from mi_bivariate.common import PathLike, file_digest
from mi_bivariate.errors import InputError
from mi_bivariate.lighting import DEFAULT_DIRS
from mi_bivariate.sources import DEFAULT_ANALYTIC, MaterialSpec, have_shared_data, input_label

#: Bumped when the protocol changes in a way that changes numbers (part of the config hash).
PROTOCOL_VERSION = 3
DEFAULT_INPUT_PROBES: Tuple[str, ...] = ("grace_latlong_1k", "uffizi_256")
DEFAULT_NOVEL_PROBES: Tuple[str, ...] = ("grace_256", "pisa_256", "venice_sunset_1k",
                                         "pedestrian_overpass_1k", "royal_esplanade_1k")
#: Materials of ``--quick`` with the shared data (else analytic ones, see :func:`quick_materials`).
QUICK_NBRDF = ("gold-metallic-paint3", "blue-acrylic")
QUICK_ANALYTIC = (DEFAULT_ANALYTIC, "oren-nayar:albedo=0.6,0.4,0.3,sigma=0.4")
#: The largest input noise level (a relative standard deviation of 100% at the mean signal: beyond it
#: the image is noise; the accuracy curve runs 0-0.05).
MAX_NOISE = 1.0


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
        prior: a prior file (:meth:`mi_bivariate.prior.Prior.load`) passed to ``recover``, with the
            basis prior ``learn-prior`` wrote beside it (``<stem>_basis.npz``), or no basis prior
            where there is none, as ``recover --prior`` does (``None``: the packaged default, or
            leave-one-out priors, see below).
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
    n_dirs: int = DEFAULT_DIRS
    grid: Tuple[int, int] = (32, 32)
    alpha: Union[None, float, str] = None
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
        if not (math.isfinite(self.noise) and 0.0 <= self.noise <= MAX_NOISE):
            raise InputError("--noise", f"noise level must be a number from 0 to {MAX_NOISE:g} (a relative standard "
                                        f"deviation at the mean signal), got {self.noise}")
        if self.prior is not None and Path(self.prior).is_dir():  # as recover --prior says it
            raise InputError(self.prior, "not a file", "give the path of a .npz file, not of a folder")
        if self.prior is not None and not Path(self.prior).is_file():
            raise InputError(self.prior, "prior file not found", "check the path")
        if int(self.novel_resolution) < 4:
            raise InputError("--novel-resolution", f"must be >= 4 pixels, got {self.novel_resolution}")
        if len(self.reference_directions) != 3 or min(self.reference_directions) < 0:
            raise InputError("reference_directions", "need 3 non-negative counts (cosine, lobe, environment)")
        unknown = [b for b in self.baselines if b not in FAMILIES]
        if unknown:
            raise InputError("--baselines", f"unknown baseline model {unknown[0]!r}",
                             f"use {' '.join(FAMILIES)}, or none")
        if self.alpha is not None:
            solve.check_alpha(self.alpha)
        # Results are kept by a probe's label (its file's stem): two probes of one label would overwrite each other.
        for flag, names in (("--input-probes", self.input_probes), ("--novel-probes", self.novel_probes)):
            first: dict = {}
            for name in names:
                label = input_label(name)
                if label in first:
                    raise InputError(name, f"{flag} names two probes {label!r} ({first[label]} and {name}); results "
                                           "are kept by name", "give each probe once, or rename a file")
                first[label] = name

    def novel_seed(self, probe: str) -> int:
        """The render seed of novel probe ``probe``: ``seed + 1 + k`` for the ``k``-th of
        :attr:`novel_probes` (``seed + 1`` for a probe not in the list)."""
        probes = list(self.novel_probes)
        return int(self.seed) + 1 + (probes.index(probe) if probe in probes else 0)

    def hash(self) -> str:
        """16 hex digits of SHA-256 over the canonical JSON of the config and protocol version (and the bytes of
        a prior file and of probe files: a result is not reused once the file it came from changed)."""
        extra = {} if self.prior is None else {  # bytes, not names; "missing" for no basis prior beside it
            "prior_sha256": file_digest(self.prior),
            "basis_prior_sha256": file_digest(training_set.basis_path_for(self.prior))}
        files = {part: file_digest(part) for name in (*self.input_probes, *self.novel_probes)
                 for part in name.split("+") if Path(part).suffix}  # a probe file by its bytes, as a MERL file
        if files:
            extra["probe_files_sha256"] = files
        if self.noise > 0.0 and any("+" in name for name in self.input_probes):
            extra["noise_per_view"] = True  # the views' noises made independent: such results are not reused
        text = json.dumps({"protocol": PROTOCOL_VERSION, "solver": _solver_identity(), **self.to_dict(), **extra},
                          sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _solver_identity() -> dict:
    """What else decides the numbers: the packaged prior's bytes and the default alpha.

    A finished material is only reused on resume when these are unchanged, so a
    re-learnt prior or a re-tuned alpha never mixes with old results.
    """
    return {"default_prior_sha256": file_digest(prior.DEFAULT_PRIOR_PATH),
            "default_basis_prior_sha256": file_digest(basis_prior.DEFAULT_BASIS_PRIOR_PATH),
            "default_alpha": solve.DEFAULT_ALPHA_RULE, "discrepancy_target": solve.DISCREPANCY_TARGET,
            "solver": "mis+noise-aware+basis v2"}


def shared_data_digest(config: EvalConfig, material: MaterialSpec,
                       data_dir: Optional[PathLike] = None) -> Optional[str]:
    """16 hex digits of SHA-256 over the bytes of the shared data folder's files that ``material``'s evaluation
    under ``config`` reads: the shared probes ``config`` names (``pisa_256``: ``<data>/probes/pisa_256.hdr``) and,
    for a MERL-NBRDF material, the weights files (its own and, for leave-one-out priors, the others').

    The config hash names the probes only (a digest there would change every old folder's hash): a record keeps
    this digest beside it, and a rerun with another ``--data`` reuses it only for the same bytes. ``None`` where
    the evaluation reads no shared file (analytic materials and MERL files under synthetic or file probes) or no
    shared data folder is found.
    """
    names = sorted({part for name in (*config.input_probes, *config.novel_probes) for part in name.split("+")
                    if part in probes.SHARED_PROBES})
    try:
        root = nbrdf.data_dir(data_dir)
        files = {name: file_digest(probes.shared_probe_path(name, root)) for name in names}
    except InputError:
        return None
    if material.kind == "nbrdf":
        files.update({str(rel): file_digest(root / rel) for rel in (nbrdf.NBRDF_FILE, nbrdf.NBRDF_TRAIN_FILE)})
    if not files:
        return None
    return hashlib.sha256(json.dumps(files, sort_keys=True).encode()).hexdigest()[:16]


def quick_materials(data_dir: Optional[PathLike] = None) -> List[str]:
    """``--quick`` materials: two MERL-NBRDF ones with the shared data, else two analytic ones."""
    return list(QUICK_NBRDF) if have_shared_data(data_dir) else list(QUICK_ANALYTIC)
