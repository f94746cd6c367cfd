"""What each ``mi-bivariate`` subcommand does, after :mod:`mi_bivariate.cli` has parsed it.

One function per subcommand, ``cmd_<name>(args) -> exit status``, in
:data:`COMMANDS`. Each checks the user's numbers against the limits below
before anything is allocated, selects the Mitsuba variant (the CLI is a front
door) and raises :class:`~mi_bivariate.errors.InputError` for bad input, which
the CLI prints as one line. This module imports the whole pipeline; the CLI
loads it only to run a command, so ``mi-bivariate --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np
import scipy

from mi_bivariate import __version__, bivariate, demo
from mi_bivariate import evaluate as ev
from mi_bivariate import export, lighting, limits, merl
from mi_bivariate import recover as rec
from mi_bivariate import render, spherefit, synthesis, training_set
from mi_bivariate.atomic import atomic_paths, check_out_file, check_outputs, same_file
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Intrinsics
from mi_bivariate.images import load_image, load_mask, write_exr, write_png
from mi_bivariate.nbrdf import ALL_NBRDF_MATERIALS
from mi_bivariate.probes import check_lit
from mi_bivariate.solve import check_alpha
from mi_bivariate.sources import have_shared_data, input_files, load_brdf, load_probe
from mi_bivariate.threads import blas_threads, jit_threads, solve_thread_limit
from mi_bivariate.training_set import basis_path_for
from mi_bivariate.variants import ensure_variant

def _check_seed(seed: Optional[int]) -> None:
    if seed is not None:
        limits.check_seed(seed, "--seed")


def _check_grid(grid: Optional[Sequence[int]]) -> None:
    if grid is not None:
        limits.check_grid(grid, "--grid", ("--grid N_T", "--grid N_S"))


def _check_recovery_sizes(normals: Optional[int], dirs: Optional[int], grid: Optional[Sequence[int]]) -> None:
    """Limits on M, K and the grid, and on the lighting matrix and kernel they imply."""
    limits.check_recovery_sizes(normals, dirs, grid, ("--normals", "--dirs", "--grid"))
    if normals is not None and dirs is not None and grid is not None:
        lighting.check_kernel_lanes(normals, dirs, grid[0] * grid[1], "--dirs")


def _check_render_sizes(resolution: Optional[int], spp: Optional[int], flag: str = "--spp",
                        resolution_flag: str = "--resolution") -> None:
    limits.check_render_sizes(resolution, spp, (resolution_flag, flag))


#: ``recover --fov`` bounds (degrees): a photo's lens, from a long telephoto to a wide angle.
MIN_FOV, MAX_FOV = 1.0, 150.0


def _check_float(flag: str, value: Optional[float], lo: float, hi: float, lo_open: bool = False,
                 what: str = "a finite number") -> None:
    if value is None:
        return
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        if math.isinf(lo) and math.isinf(hi):
            bounds = ""
        elif math.isinf(hi):
            bounds = f" {'>' if lo_open else '>='} {lo:g}"
        else:
            bounds = f" in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise InputError(flag, f"must be {what}{bounds}, got {value}")


def _input_files(args: argparse.Namespace, *specs: Optional[str]) -> List[Path]:
    """The files the arguments read (inputs an output must not overwrite): files as given, a folder's
    MERL files, the shared files behind shared names, and a ``--prior`` file's basis prior beside it."""
    files = input_files(*specs, data_dir=getattr(args, "data", None))
    prior = getattr(args, "prior", None)
    if prior:
        files += input_files(prior, training_set.basis_path_for(prior))
    return files


def _check_out_file(out: Optional[str], example: str = "brdf.npz") -> None:
    """``--out`` naming a folder, an existing one or one written with a trailing separator (``o/new/``,
    which the path would otherwise read as the file ``o/new.npz``), is refused: the command writes files,
    not into a folder (``example``: a file name the command writes, for the hint)."""
    if out:
        check_out_file(out, "--out", example)


def _check_out_folder(out: Path, flag: str = "--out") -> None:
    """An output folder (given by ``flag``) must not be an existing file and must be creatable/writable."""
    if out.exists() and not out.is_dir():
        raise InputError(out, f"{flag} must be a folder, but this is a file", f"choose another {flag}")
    try:
        check_outputs([out / ".probe-write"], flag=flag)
    except InputError as exc:  # name the folder, not the file standing in for what it will hold
        raise InputError(out, exc.problem, exc.hint or f"choose another {flag}") from None


# --------------------------------------------------------------------------- info

def cmd_info(args: argparse.Namespace) -> int:
    variant = ensure_variant(args.variant)
    info: Dict[str, object] = {
        "mi_bivariate": __version__,
        "python": platform.python_version(),
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "variant": variant,
        "variants_available": [v for v in mi.variants() if v.endswith("_rgb")],
        "llvm_backend": bool(dr.has_backend(dr.JitBackend.LLVM)),
        "cuda_backend": bool(dr.has_backend(dr.JitBackend.CUDA)),  # the GPU
        "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH", "(search)"),
        "MI_BIVARIATE_DATA": os.environ.get("MI_BIVARIATE_DATA", "(unset)"),
        "cpu_count": os.cpu_count(),
    }
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        width = max(len(k) for k in info)
        for k, v in info.items():
            print(f"{k:<{width}}  {v}")
    return 0


# --------------------------------------------------------------------------- render

#: ``render`` says what it renders (on a terminal) from this many samples: ~10 s on two cores.
RENDER_NOTICE_SAMPLES = 2 ** 24


def cmd_render(args: argparse.Namespace) -> int:
    _check_render_sizes(args.resolution, args.spp)
    _check_seed(args.seed)
    _check_out_file(args.out, "render.exr")
    out = Path(args.out)
    args.source_names["merl table"] = str(args.brdf)  # an analytic spec's tabulated values
    _check_outputs_of(out, (".exr",), "render writes OpenEXR (and a PNG preview beside it)",
                      [out, out.with_suffix(".png")], _input_files(args, args.brdf, args.probe))
    ensure_variant(args.variant, vectorised=True)  # the plugins and the lighting matrix are JIT code
    brdf = load_brdf(args.brdf, args.data)
    probe = _load_turned_probe(args)
    samples = args.resolution ** 2 * args.spp
    if samples >= RENDER_NOTICE_SAMPLES and sys.stderr.isatty():  # one kernel: no progress to show, so say it
        print(f"rendering {args.resolution} x {args.resolution} px at {args.spp} spp ({samples / 1e6:.0f} M "
              "samples) ...", file=sys.stderr, flush=True)
    result = render.render_sphere(render.bsdf_dict(brdf), probe, resolution=args.resolution, spp=args.spp,
                                  camera=args.camera, seed=args.seed)
    bad = int(np.count_nonzero(~np.isfinite(result.image)))
    if bad:  # float32 radiance overflowed: a table or probe far beyond any physical scale
        raise InputError(f"{args.brdf} under {args.probe}", f"the render overflowed float32 in {bad} pixel values "
                         "(NaN or infinite)", "scale the BRDF or the probe down; nothing was written")
    if not np.any(result.image > 0.0):
        warnings.warn(f"{args.brdf}: the render is black: the BRDF reflects no light under {args.probe} (no pixel "
                      "is above 0)", InputWarning, stacklevel=2)
    with atomic_paths([out, out.with_suffix(".png")]) as (exr, png):
        write_exr(exr, result.image)
        write_png(png, result.image)
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


# --------------------------------------------------------------------------- reduce

def _check_outputs_of(out: Path, suffixes: Sequence[str], what: str, outputs: Sequence[Path],
                      inputs: Sequence[Path]) -> None:
    """A command's outputs checked in the order a user should hear of them: ``--out`` naming an input,
    then ``--out``'s type (``suffixes``, ``what`` it writes), then all ``outputs`` (written twice, not
    writable: :func:`~mi_bivariate.atomic.check_outputs`)."""
    check_outputs([out], inputs)
    if out.suffix.lower() not in suffixes:
        raise InputError(out, what, f"give --out a name ending in {[x for x in suffixes if x][0]}")
    check_outputs(outputs, inputs)


def cmd_reduce(args: argparse.Namespace) -> int:
    _check_grid(args.grid)
    _check_out_file(args.out)
    if Path(args.merl).suffix.lower() != ".binary":
        raise InputError(args.merl, "is not a MERL .binary file", "give the 3D table to reduce as a .binary file")
    out = Path(args.out) if args.out else Path(args.merl).with_suffix(".npz")
    _check_outputs_of(out, (".npz",), "reduce writes a .npz table (and its .exr view beside it)",
                      [out, out.with_suffix(".exr")], _input_files(args, args.merl))
    source = merl.MERLBRDF.read(args.merl)  # refuses a table with no positive value
    if not args.out:  # X.npz beside X.binary may be the recovery that `recover --merl` wrote with it
        for existing in (out, out.with_suffix(".exr")):
            if existing.exists():
                raise InputError(existing, "exists already, and reduce would replace it (it writes beside its "
                                 "input unless --out says where)", "give --out to write elsewhere or to replace it")
    biv = bivariate.BivariateBRDF.reduce(source, n_t=args.grid[0], n_s=args.grid[1])
    exact = bivariate.exact_floor(source)
    grid = bivariate.reduction_error(source, biv)
    with atomic_paths([out, out.with_suffix(".exr")]) as (npz, exr):
        biv.save(npz)
        biv.save_exr(exr)
    print(f"exact floor (Eq. 1 of the exact phi_d average at MERL resolution, paper Fig. 3): {exact:.4f}")
    print(f"grid floor (Eq. 1 of the {biv.n_t}x{biv.n_s} table read back at MERL resolution): {grid:.4f}")
    print(f"wrote {out} and {out.with_suffix('.exr')}")
    return 0


# --------------------------------------------------------------------------- learn-prior

def cmd_learn_prior(args: argparse.Namespace) -> int:
    _check_grid(args.grid)
    _check_out_file(args.out, "prior.npz")
    for source in args.sources:
        if not Path(source).exists() and source not in ALL_NBRDF_MATERIALS:
            raise InputError(source, "no such file or folder, and not a MERL-NBRDF name",
                             "give MERL .binary files, folders of them, or shared MERL-NBRDF names")
    basis_out = training_set.basis_path_for(args.out)
    _check_outputs_of(Path(args.out), (".npz",), "learn-prior writes a .npz prior (and its basis beside it)",
                      [Path(args.out), basis_out], _input_files(args, *args.sources))
    smooth, basis = training_set.learn_priors_from_merl(args.sources, n_t=args.grid[0], n_s=args.grid[1],
                                                        data_dir=args.data, progress=sys.stderr.isatty())
    with atomic_paths([args.out, basis_out], suffixes=[".npz", ".npz"]) as (tmp_smooth, tmp_basis):
        smooth.save(tmp_smooth)
        basis.save(tmp_basis)
    print(f"wrote {args.out} (smoothness prior, {len(smooth.provenance['materials'])} materials) and "
          f"{basis_out} (basis prior, {basis.basis.shape[1]} components)")
    return 0


# --------------------------------------------------------------------------- recover

def _check_recover_args(args: argparse.Namespace) -> None:
    """The checks ``recover`` and ``recover-batch`` share, before anything is loaded."""
    if args.dirs is None:
        args.dirs = lighting.DEFAULT_DIRS
    _check_recovery_sizes(args.normals, args.dirs, args.grid)
    _check_seed(args.seed)
    _check_float("--max-view-angle", args.max_view_angle, 0.0, 90.0, lo_open=True)
    _check_float("--footprint", args.footprint, 0.0, 90.0, lo_open=True)
    _check_float("--saturation", args.saturation, 0.0, float("inf"), lo_open=True)
    _check_float("--fov", args.fov, MIN_FOV, MAX_FOV, what="a horizontal field of view (degrees)")
    if args.fov is not None:
        for flag, given in (("--footprint", args.footprint is not None), ("--report-render", args.report_render),
                            ("--refine-sphere", args.refine_sphere)):
            if given:
                raise InputError(flag, "models an orthographic view only", "leave it out with --fov")
    _check_alpha(args.alpha)
    _check_threads(args)


def _check_alpha(alpha) -> None:
    """``--alpha`` as the solve will check it, before any work (a rule name or a number in its range)."""
    try:
        check_alpha(alpha)
    except InputError as exc:
        raise InputError("--alpha", exc.problem, exc.hint) from None


def _check_threads(args: argparse.Namespace, jobs: int = 1, local: bool = True) -> None:
    """``--threads`` from 1 to 1024, and, for threads on this machine (``local``), at most its CPUs shared
    by ``jobs`` processes: beyond them Dr.Jit gains nothing and the threads only contend (measured on 2
    cores, when each thread still held a copy of the lighting matrix's chunk: 64 threads took the
    lighting matrix from 1 s to 20 s), so more are lowered to that count, with a warning."""
    if args.threads is None:
        return
    if not 1 <= args.threads <= 1024:
        raise InputError("--threads", f"must be from 1 to 1024, got {args.threads}")
    if not local:
        return
    cpus = os.cpu_count() or 1
    share = max(1, cpus // max(1, jobs))
    if args.threads > share:
        per_job = f" shared by {jobs} jobs" if jobs > 1 else ""
        warnings.warn(f"--threads: {args.threads} is more than this machine's {cpus} CPU(s){per_job}; using {share}",
                      InputWarning, stacklevel=2)
        args.threads = share


def _recover_priors(args: argparse.Namespace) -> tuple:
    """``(smoothness prior or None, basis prior or "default" or None)`` as ``--prior`` and ``--no-basis-prior`` say."""
    smooth_prior, basis_prior = None, "default"
    args.source_names.update({"alpha": "--alpha", "noise": "--noise"})
    if args.prior is not None:
        args.source_names["basis_prior"] = str(basis_path_for(args.prior))
        smooth_prior, basis_prior = training_set.load_prior_files(args.prior, basis=not args.no_basis_prior)
    return smooth_prior, None if args.no_basis_prior else basis_prior


def _recover_image(args: argparse.Namespace, image_path: str, probe, priors: tuple, out: Path) -> tuple:
    """One photo of ``recover`` / ``recover-batch``: fit its sphere, recover, write its outputs.

    Returns ``(Recovery, paths written)``. Raises InputError naming the user's files.
    """
    args.source_names["image"] = str(image_path)  # "lighting matrix L": the command set it
    image = load_image(image_path)
    mask = load_mask(args.mask, image.shape) if args.mask else None
    sphere = None if args.sphere in (None, "auto") else args.sphere
    intrinsics = None if args.fov is None else Intrinsics.from_fov(image.shape[1], image.shape[0], args.fov)
    fit = spherefit.fit_sphere(image, mask, sphere=sphere, intrinsics=intrinsics, source=str(image_path))
    print(fit.summary())
    try:
        # No BLAS oversubscription on a shared machine; --threads also caps the solve's workers.
        with blas_threads(), solve_thread_limit(args.threads):
            options = dict(masks=mask, n_normals=args.normals, n_dirs=args.dirs, grid=tuple(args.grid),
                           alpha=args.alpha, pair_rule=args.pair_rule, seed=args.seed,
                           max_view_angle_deg=args.max_view_angle, footprint=args.footprint,
                           saturation=args.saturation, noise=args.noise, sampling=args.sampling, prior=priors[0],
                           basis_prior=priors[1])
            with warnings.catch_warnings(record=True) as said:
                warnings.simplefilter("always")
                result = rec.recover(image, probe, fit.geometry, **options)
            _warn_again(said)
            if args.refine_sphere:
                print(f"refining the sphere by the image's shading (relative residual {result.relative_residual():.4f} "
                      "under the fitted sphere) ...", flush=True)
                with warnings.catch_warnings(record=True) as said_again:
                    warnings.simplefilter("always")
                    result = rec.refine_sphere_and_recover(image, probe, result, **options)
                _warn_again(said_again, already=said)  # the second recovery's repeats of the first's are not said twice
    except InputError as exc:
        # The library names its arguments ("image", "lighting matrix L"); name the user's files. The noise
        # check measures this photo's own rows (its own estimate with --noise auto): a problem of the photo.
        names = {"image": image_path, "lighting matrix L": args.probe, "noise": image_path}
        if exc.source in names:
            raise InputError(names[exc.source], exc.problem, exc.hint) from None
        raise
    result.brdf.provenance["photos"] = [str(image_path)]
    args.source_names["out"] = str(out)  # what write_outputs' warnings call "out"
    paths = export.write_outputs(result, out, merl=args.merl, report=not args.no_report,
                                 report_render=args.report_render, report_worker=getattr(args, "report_worker", None))
    return result, paths


def _warning_key(w: warnings.WarningMessage) -> tuple:
    """A warning's category and text with its numbers blanked (a second recovery's "explains 47%" repeats "45%")."""
    return w.category, re.sub(r"[-+]?\d[\d.e+-]*", "#", str(w.message))


def _warn_again(records: Sequence[warnings.WarningMessage], already: Sequence[warnings.WarningMessage] = ()) -> None:
    """Issue recorded warnings again (through the caller's filters), but not those ``already`` said."""
    seen = {_warning_key(w) for w in already}
    for w in records:
        if _warning_key(w) not in seen:
            seen.add(_warning_key(w))
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)


def _load_turned_probe(args: argparse.Namespace, every_channel: bool = False):
    """``--probe``, turned by ``--probe-rotation`` when given; refused when black (or, with
    ``every_channel``, as a recovery needs, black in any colour channel)."""
    probe = load_probe(args.probe, args.data)
    check_lit(probe, args.probe, every_channel=every_channel)
    if args.probe_rotation is not None:
        probe = probe.rotated(euler_deg=args.probe_rotation)
    return probe


def cmd_recover(args: argparse.Namespace) -> int:
    _check_recover_args(args)
    _check_out_file(args.out)
    _check_outputs_of(Path(args.out), ("", ".npz"), "recover writes a .npz table (and its .exr view and report "
                      "beside it)", export.output_paths(args.out, merl=args.merl, report=not args.no_report),
                      _input_files(args, args.image, args.probe, args.mask))
    args.source_names["lighting matrix L"] = str(args.probe)
    ensure_variant(args.variant, vectorised=True)  # the plugins and the lighting matrix are JIT code
    with jit_threads(args.threads):
        probe = _load_turned_probe(args, every_channel=True)
        result, paths = _recover_image(args, args.image, probe, _recover_priors(args), Path(args.out))
    print(result.summary())
    for p in paths:
        print(f"wrote {p}")
    return 0


def cmd_recover_batch(args: argparse.Namespace) -> int:
    """``recover`` on each photo in turn, in one process: the imports, the variant's start and the
    kernels' compilation are paid once.

    A photo whose own file or sphere is the problem gets its one-line error, and the others go on (the
    exit status is then 2). A problem shared by every photo (an option, the probe, the priors) stops
    the batch at the first photo it shows in, with one line; so does anything unexpected. Photos
    finished before are kept (each one's outputs are written all or none).
    """
    _check_recover_args(args)
    out_dir = Path(args.out_dir)
    _check_out_folder(out_dir, "--out-dir")
    outs = [out_dir / (Path(image).stem + ".npz") for image in args.images]
    first_of: Dict[Path, str] = {}
    for image, out in zip(args.images, outs):
        if out in first_of:
            if same_file(Path(image), Path(first_of[out])):
                raise InputError(image, "is given twice", "give each photo once")
            raise InputError(image, f"writes {out}, as {first_of[out]} does",
                             "rename one of them, or recover them in separate batches")
        first_of[out] = image
    outputs = [p for out in outs for p in export.output_paths(out, merl=args.merl, report=not args.no_report)]
    check_outputs(outputs, _input_files(args, *args.images, args.probe, args.mask), flag="--out-dir")
    args.source_names["lighting matrix L"] = str(args.probe)
    ensure_variant(args.variant, vectorised=True)  # the plugins and the lighting matrix are JIT code
    failed: List[str] = []
    with jit_threads(args.threads):
        probe = _load_turned_probe(args, every_channel=True)
        priors = _recover_priors(args)
        for k, (image, out) in enumerate(zip(args.images, outs), 1):
            t0 = time.perf_counter()
            try:
                with warnings.catch_warnings():  # each photo's warnings shown, not only the first photo's
                    result, paths = _recover_image(args, image, probe, priors, out)
            except OSError as exc:  # a file the checks could not foresee (vanished, unreadable)
                name = exc.filename if exc.filename is not None else image
                print(f"mi-bivariate: error: {name}: {exc.strerror or exc} (check the path, permissions and "
                      "free space)", file=sys.stderr)
                failed.append(image)
                continue
            except InputError as exc:
                if not any(_same_path(exc.source, p) for p in (image, args.mask)):  # every photo's: stop here
                    done = k - 1 - len(failed)
                    if done or failed:
                        said = f"{done} of {len(args.images)} photos recovered before this error"
                        raise InputError(exc.source, exc.problem, f"{exc.hint}; {said}" if exc.hint else said) \
                            from None
                    raise
                print(f"mi-bivariate: error: {exc}", file=sys.stderr)
                failed.append(image)
                continue
            print(f"[{k}/{len(args.images)}] {image}: relative residual {result.relative_residual():.4f}, "
                  f"{time.perf_counter() - t0:.1f} s; wrote {', '.join(str(p) for p in paths)}", flush=True)
    print(f"recovered {len(args.images) - len(failed)} of {len(args.images)} photos"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 2 if failed else 0


def _same_path(a: Optional[str], b: Optional[str]) -> bool:
    """Whether two path names name one file (``./x.exr`` and ``x.exr``, ``a//b`` and ``a/b``, links)."""
    return a is not None and b is not None and same_file(a, b)


# --------------------------------------------------------------------------- demo

def cmd_demo(args: argparse.Namespace) -> int:
    _check_render_sizes(args.resolution, args.spp)
    _check_seed(args.seed)
    _check_out_folder(Path(args.out))
    check_outputs([Path(args.out) / name for name in demo.OUTPUTS],
                  _input_files(args, args.material, args.input_probe, args.novel_probe))
    ensure_variant(args.variant, vectorised=True)  # the plugins and the lighting matrix are JIT code
    args.source_names["image"] = "the demo's input render"  # what the recovery's warnings call "image"
    return demo.run_demo(out_dir=Path(args.out), material=args.material, input_probe=args.input_probe,
                         novel_probe=args.novel_probe, data_dir=args.data, spp=args.spp, seed=args.seed,
                         resolution=args.resolution)


# --------------------------------------------------------------------------- evaluate

def cmd_evaluate(args: argparse.Namespace) -> int:
    """The paper's evaluation over the materials given (:func:`mi_bivariate.evaluate.run_evaluation`).

    As in ``recover-batch``, a material that fails (a refused file, a failed recovery) gets its warning
    and the others go on: their results, summary and figures are written, and the command then ends
    with one error line naming the failed materials and exit status 2 (a rerun tries only them). A
    problem shared by every material (an option, a probe, the prior) stops it before any work.
    """
    def given(value, default):  # 0 is a value to check, not "unset"
        return default if value is None else value

    # An option not given takes the run's own default: --quick's sizes (EvalConfig.quick), else the full ones.
    base = ev.EvalConfig.quick(shared_data=have_shared_data(args.data)) if args.quick else ev.EvalConfig()
    _check_recovery_sizes(given(args.normals, base.n_normals), given(args.dirs, base.n_dirs),
                          given(args.grid, base.grid))
    _check_render_sizes(given(args.resolution, base.resolution), args.spp)
    _check_render_sizes(given(args.novel_resolution, base.novel_resolution), args.novel_spp, flag="--novel-spp",
                        resolution_flag="--novel-resolution")
    _check_seed(args.seed)
    _check_alpha(args.alpha)
    _check_float("--abs-time-factor", args.abs_time_factor, 0.0, 1e6, lo_open=True)
    if args.abs < 0:
        raise InputError("--abs", f"must be >= 0 (the number of materials), got {args.abs}")
    if not 1 <= args.jobs <= 256:
        raise InputError("--jobs", f"must be from 1 to 256, got {args.jobs}")
    _check_threads(args, jobs=args.jobs, local=args.dask is None)  # with --dask they run on the cluster's machines
    _check_out_folder(Path(args.out))
    ensure_variant(args.variant, vectorised=True)  # the plugins and the lighting matrix are JIT code
    data = args.data
    materials = list(args.materials) or (ev.quick_materials(data) if args.quick else ["nbrdf"])
    overrides = {k: v for k, v in {
        "input_probes": tuple(args.input_probes) if args.input_probes else None,
        "novel_probes": tuple(args.novel_probes) if args.novel_probes else None,
        "resolution": args.resolution, "spp": args.spp, "novel_spp": args.novel_spp,
        "n_normals": args.normals, "n_dirs": args.dirs, "grid": tuple(args.grid) if args.grid else None,
        "alpha": args.alpha, "seed": args.seed,
        "baselines": None if args.baselines is None else tuple(b for b in args.baselines if b.lower() != "none"),
        "noise": args.noise, "renderer": args.renderer, "novel_resolution": args.novel_resolution,
        "prior": args.prior,
    }.items() if v is not None}
    config = (ev.EvalConfig.quick(shared_data=have_shared_data(data), **overrides) if args.quick
              else ev.EvalConfig(**overrides))
    formats = ("png", "pdf") if args.pdf else ("png",)
    failed: List[str] = []  # the materials as the user named them (a MERL file's path)
    records = ev.run_evaluation(materials, args.out, config=config, jobs=args.jobs, dask=args.dask,
                                data_dir=data, progress=not args.no_progress, figures=not args.no_figures,
                                figure_formats=formats, threads=args.threads,
                                on_failure=lambda material, exc: failed.append(material.spec))
    print(ev.format_summary(records))
    if args.abs:
        out = Path(args.out) / "analysis_by_synthesis.jsonl"
        # A rerun resumes, as the evaluation does: a material already run with this configuration,
        # input probe and time factor, from the same bytes (ev.same_data, with the digests its evaluation
        # record keeps), is reported from its record, not run (and appended) again.
        done: Dict[tuple, List[dict]] = {}
        for r in ev.read_records(out):
            if r["config_hash"] == config.hash():
                done.setdefault((r["material"], r.get("input_probe"), r.get("time_factor")), []).append(r)
        input_label = ev.probe_label(config.input_probes[0])
        for record in records[:args.abs]:
            digests = {k: record[k] for k in ev.DATA_DIGESTS if record.get(k) is not None}
            same = [r for r in done.get((record["material"], input_label, args.abs_time_factor), [])
                    if ev.same_data(r, digests)]
            result = same[-1] if same else None
            if result is None:
                result = synthesis.analysis_by_synthesis(record["spec"], config.input_probes[0], config=config,
                                                         data_dir=data, time_factor=args.abs_time_factor)
                result["time_factor"] = args.abs_time_factor
                result.update(digests)
                ev.append_record(out, result)
            else:
                print(f"analysis by synthesis, {record['material']}: from {out} (an earlier run with this "
                      f"configuration; delete its line to run it again)")
            a, lin = result["abs"], result["linear"]
            fastest, speedup = result["linear_to_abs_best"], result["ladder_speedup"]
            reaches = ("; AbS never reached the linear relight error" if not a["reached_linear_relight"] else
                       f"; AbS reached the linear relight error at {a['time_to_linear_relight_s']:.3g} s")
            faster = (f"; the fastest linear run as good as AbS's best took {fastest['time_s']:.3g} s "
                      f"({synthesis.rung_label(fastest)}: {speedup:.0f}x faster)"
                      if fastest is not None and speedup is not None else "")
            print(f"analysis by synthesis, {record['material']}: linear solve Eq. 1 {lin['eq1']:.4g}, relight "
                  f"{lin['relight']:.4g} (floor {result['relight_floor']:.4g}) in {lin['time_s']:.3g} s; Adam+prb "
                  f"Eq. 1 {a['final']['eq1']:.4g}, best relight {a['best_relight']:.4g} at "
                  f"{a['best_relight_time_s']:.3g} s of {a['time_s']:.3g} s ({a['iterations']} iterations)"
                  f"{reaches}{faster}")
    print(f"results: {Path(args.out) / ev.RESULTS_FILE}, {Path(args.out) / ev.SUMMARY_FILE}"
          + ("" if args.no_figures else f", figures in {Path(args.out) / 'figures'}"))
    if failed:  # as recover-batch: the others' results are written, the run still says it failed
        print(f"mi-bivariate: error: {', '.join(failed)}: evaluation failed for {len(failed)} of "
              f"{len(failed) + len(records)} materials (the warnings above say why; fix or drop "
              f"{'it' if len(failed) == 1 else 'them'} and rerun: finished materials are kept)", file=sys.stderr)
        return 2
    return 0


# --------------------------------------------------------------------------- parser


#: Subcommand name -> function.
COMMANDS = {"info": cmd_info, "render": cmd_render, "reduce": cmd_reduce, "learn-prior": cmd_learn_prior,
            "recover": cmd_recover, "recover-batch": cmd_recover_batch, "demo": cmd_demo, "evaluate": cmd_evaluate}
