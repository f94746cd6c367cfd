"""The ``mi-bivariate`` command.

Subcommands: ``info``, ``render``, ``reduce``, ``learn-prior``, ``recover``,
``recover-batch``, ``demo``, ``evaluate``. Every one has ``--help``. Problems with the
user's input end in a single line ``mi-bivariate: error: FILE: problem`` and exit status 2. A stop ends
in ``mi-bivariate: interrupted`` (or ``terminated``) with 130 (Ctrl-C) or 143 (SIGTERM); a standard output
whose reader has gone (``| head``), quietly with 141.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import math
import os
import select
import signal
import stat
import sys
import warnings
from typing import Dict, Optional, Sequence, Tuple

if __name__ == "__main__":  # ``python -m mi_bivariate.cli``: the console script's own start, before numpy loads
    from mi_bivariate.__main__ import main as _console_main  # imports this module again, by its name, and runs

    sys.exit(_console_main())

from mi_bivariate import __version__, process
from mi_bivariate.atomic import signals_deferred, stop_on_signal
from mi_bivariate.errors import InputError, Terminated, renamed
from mi_bivariate.report_worker import ReportWorker


class _HelpFormatter(argparse.HelpFormatter):
    """Help that states each option's default (unless its text already does, or there is none to state)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not action.option_strings or any(
                action.default is v for v in (None, False, argparse.SUPPRESS)):
            return text
        default = " ".join(map(str, action.default)) if isinstance(action.default, (tuple, list)) else "%(default)s"
        return f"{text} (default: {default})" if text else f"default: {default}"


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors as one line ``mi-bivariate: error: ... (see ... --help)``, exit status 2,
    and every option's default in its help."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"mi-bivariate: error: {message} (see '{self.prog} --help')\n")


def _parse_sphere(text: str):
    if text == "auto":
        return text
    try:
        cx, cy, r = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sphere expects CX,CY,R in pixels, got {text!r}")
    if not all(math.isfinite(v) for v in (cx, cy, r)):
        raise argparse.ArgumentTypeError(f"--sphere expects finite CX,CY,R in pixels, got {text!r}")
    if not r > 0:
        raise argparse.ArgumentTypeError(f"--sphere radius must be positive, got {r}")
    return cx, cy, r


def _parse_path(text: str) -> str:
    """A path: any non-empty name (an empty ``--out`` has no file name to write; an empty ``--prior`` ended in
    a traceback, an empty ``--mask`` was taken as no mask)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a file or folder name, got an empty one")
    return text


def _parse_alpha(text: str):
    if text.strip().lower() in ("gcv", "discrepancy"):
        return text.strip().lower()
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, 'discrepancy' or 'gcv', got {text!r}") from None


def _parse_noise(text: str):
    value = text.strip().lower()
    if value in ("auto", "none"):
        return None if value == "none" else "auto"
    try:
        a, b = (float(v) for v in value.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto, none or A,B, got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b) and a >= 0 and b >= 0):
        raise argparse.ArgumentTypeError(f"A and B must be finite and >= 0, got {text!r}")
    return (a, b)


def _parse_rotation(text: str) -> Tuple[float, float, float]:
    try:
        angles = tuple(float(v) for v in text.split(","))
    except ValueError:
        angles = ()
    if len(angles) != 3 or not all(math.isfinite(v) for v in angles):
        raise argparse.ArgumentTypeError(f"expected three angles in degrees RX,RY,RZ, got {text!r}")
    if not all(-360.0 <= v <= 360.0 for v in angles):  # a turn more or less is the same rotation
        raise argparse.ArgumentTypeError(f"each angle must be in [-360, 360] degrees, got {text!r}")
    return angles


def _add_variant(p: argparse.ArgumentParser) -> None:
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb on a GPU (env MI_BIVARIATE_VARIANT)")


def _add_data(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=None,
                   help="shared data folder with probes/ and merl_nbrdf/ (default: $MI_BIVARIATE_DATA)")


def _add_probe_rotation(p: argparse.ArgumentParser, whose: str) -> None:
    p.add_argument("--probe-rotation", type=_parse_rotation, default=None, metavar="RX,RY,RZ",
                   help="turn the probe by these angles in degrees, about world x, then y, then z (after a shared "
                        f"probe's own rotation; world: y up, the camera on +z), for a probe stored in another "
                        f"orientation than {whose}; write a negative first angle as --probe-rotation=-90,0,0")


def _add_recover_options(p: argparse.ArgumentParser) -> None:
    """The options ``recover`` and ``recover-batch`` share."""
    p.add_argument("--probe", required=True, help="environment map file or shared probe name")
    _add_probe_rotation(p, "the photo's")
    p.add_argument("--sphere", default="auto", type=_parse_sphere, metavar="CX,CY,R",
                   help="sphere centre and radius in pixels (pixel centres at i+0.5, y down; write a negative "
                        "centre as --sphere=-10,32,40); default 'auto': fitted to the image (or --mask), with the "
                        "fit residual reported")
    p.add_argument("--refine-sphere", action="store_true",
                   help="then refine the sphere's centre and radius by the image's shading and recover again "
                        "(orthographic view only; 10-32 s): the silhouette fit of a glossy sphere can be "
                        "0.3-0.6 px off, which raised four metals' relight error by 25-85%% under grace; a "
                        "refinement that would move the outline more than 1 px, or whose recovery fits the image "
                        "worse, is not taken (a warning says so)")
    p.add_argument("--mask", type=_parse_path, default=None,
                   help="optional mask image, of the photo's size (pixels with a value > 0 in any colour channel "
                        "are usable, and where the file has alpha only the pixels with alpha > 0; 0, negative, "
                        "NaN and transparent ones are not)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="the photo's horizontal field of view for a pinhole camera with its principal point at "
                        "the image centre (default: an orthographic view, the paper's model)")
    p.add_argument("--merl", action="store_true", help="also write a MERL .binary")
    report = p.add_mutually_exclusive_group()
    report.add_argument("--no-report", action="store_true", help="skip the PNG report")
    report.add_argument("--report-render", action="store_true",
                        help="path-trace the report's re-render (seconds) instead of predicting it as L f")
    p.add_argument("--normals", type=int, default=8000, help="number of normals M")
    p.add_argument("--dirs", type=int, default=None, help="light directions per normal K (default 8000)")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"),
                   help="st grid (theta_h nodes, theta_d nodes); the packaged priors are learnt on 32 x 32 and "
                        "resampled to another grid, unless --prior names priors learnt on it")
    p.add_argument("--alpha", type=_parse_alpha, default=None,
                   help="smoothness weight: a number, or how to choose it: 'discrepancy' (default: the largest "
                        "weight, at most 1e-2, whose fit explains the image to within its expected error) or 'gcv'")
    p.add_argument("--pair-rule", choices=("evidence", "residual"), default="evidence",
                   help="which of the smoothness prior's two weight pairs each channel keeps: the one under which "
                        "the image is likelier (evidence, default) or the lower data residual (the paper's rule)")
    p.add_argument("--noise", type=_parse_noise, default="auto", metavar="auto|none|A,B",
                   help="camera noise, variance A*I+B in image units: estimated from the image (auto, default), "
                        "none (clean input) or given")
    p.add_argument("--prior", type=_parse_path, default=None, metavar="FILE",
                   help="smoothness prior from learn-prior (its _basis.npz beside it is the basis prior)")
    p.add_argument("--no-basis-prior", action="store_true", help="smoothness prior alone (the paper's Eq. 6)")
    p.add_argument("--sampling", choices=("mis", "uniform"), default="mis",
                   help="light directions of the lighting matrix (default mis)")
    p.add_argument("--max-view-angle", type=float, default=80.0, help="drop normals further from the view (deg)")
    p.add_argument("--footprint", type=float, default=None, metavar="DEG",
                   help="pixel-footprint model: rows whose pixel spans more than DEG degrees of normals average "
                        "sub-pixel normals (default: centre normals, the paper's model)")
    p.add_argument("--saturation", type=float, default=None, help="drop pixels with any channel >= this value")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the light directions' random shifts (runs are deterministic for a seed)")
    threads = p.add_mutually_exclusive_group()
    threads.add_argument("--threads", type=int, default=None,
                         help="Dr.Jit threads, and at most as many solve workers (default: all cores; on the CPU "
                              "the outputs are bit-identical for any number)")
    threads.add_argument("--deterministic", dest="threads", action="store_const", const=1,
                         help="same as --threads 1 (kept for scripts; on the CPU every thread count now "
                              "gives bit-identical outputs)")
    _add_variant(p)
    _add_data(p)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="mi-bivariate",
        description="Passive reflectometry for Mitsuba 3: recover a bivariate (theta_h, theta_d) BRDF "
                    "from an HDR image of a known sphere under a known light probe.")
    parser.add_argument("--version", action="version", version=f"mi-bivariate {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("info", help="versions, Mitsuba variant, LLVM and GPU availability")
    _add_variant(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    

    p = sub.add_parser("render", help="render a sphere of any BRDF under a probe (EXR + PNG preview)")
    p.add_argument("brdf", help="MERL .binary, bivariate .npz, MERL-NBRDF name, or analytic spec "
                                "(e.g. 'ggx:alpha=0.1')")
    p.add_argument("--probe", required=True, help="environment map file (.exr/.hdr/.pfm) or shared probe name")
    _add_probe_rotation(p, "the render's (give the angles given to recover)")
    p.add_argument("--out", type=_parse_path, default="render.exr",
                   help="output EXR (a PNG preview is written beside it)")
    p.add_argument("--resolution", type=int, default=256, help="image width and height in pixels")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel")
    p.add_argument("--camera", choices=("orthographic", "perspective"), default="orthographic",
                   help="camera model of the render (perspective: a 30 degree horizontal field of view; "
                        "recover such an image with --fov 30)")
    p.add_argument("--seed", type=int, default=0, help="seed of the render's samples")
    _add_variant(p)
    _add_data(p)
    

    p = sub.add_parser("reduce", help="reduce a MERL .binary to a bivariate table (prints the exact and grid floors)")
    p.add_argument("merl", help="MERL .binary file")
    p.add_argument("--out", type=_parse_path, default=None, help="output .npz (default: beside the input)")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"),
                   help="st grid size (theta_h nodes, theta_d nodes)")
    

    p = sub.add_parser("learn-prior", help="learn the smoothness prior from a set of MERL materials")
    p.add_argument("sources", nargs="+", help="folders of MERL .binary files, .binary files, or MERL-NBRDF names")
    p.add_argument("--out", type=_parse_path, default="prior.npz", help="output .npz")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"),
                   help="st grid the priors are learnt on (theta_h nodes, theta_d nodes; default 32 32)")
    _add_data(p)
    

    p = sub.add_parser("recover", help="recover a bivariate BRDF from an HDR image of a sphere under a known probe")
    p.add_argument("image", help="linear HDR image (.exr, .hdr/.rgbe/.pic, .pfm; an 8-bit .png/.jpg is read "
                                 "with a warning: not radiometric)")
    p.add_argument("--out", type=_parse_path, default="brdf.npz",
                   help="output .npz (EXR view and PNG report beside it)")
    _add_recover_options(p)

    p = sub.add_parser("recover-batch",
                       help="recover one BRDF from each of several photos under one probe, in one process",
                       description="recover on each photo in turn, in one process: the imports, the Mitsuba "
                                   "variant's start and the kernels' compilation are paid once (measured ~1.6x "
                                   "faster per photo than separate recover runs). --sphere and --mask apply to "
                                   "every photo. A photo whose file or sphere is the problem gets its one-line "
                                   "error and the others go on (exit status 2); a problem shared by every photo "
                                   "(an option, the probe, the priors) stops the batch.")
    p.add_argument("images", nargs="+", help="linear HDR images (as for recover), each of a sphere under --probe")
    p.add_argument("--out-dir", type=_parse_path, required=True,
                   help="output folder: STEM.npz per photo (its EXR view and PNG report beside it, and with "
                        "--merl its .binary)")
    _add_recover_options(p)

    p = sub.add_parser("demo", help="render a measured material, recover it, re-render it under a novel probe")
    p.add_argument("--out", type=_parse_path, default="out/demo", help="output folder")
    p.add_argument("--material", default=None,
                   help="MERL-NBRDF name, MERL .binary or analytic spec (default: gold-metallic-paint3; "
                        "an analytic material without shared data)")
    p.add_argument("--input-probe", default="grace_latlong_1k", help="probe lighting the input image")
    p.add_argument("--novel-probe", default="pisa_256", help="probe for the validation render")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel of every render")
    p.add_argument("--resolution", type=int, default=256, help="image width and height in pixels")
    p.add_argument("--seed", type=int, default=0, help="seed of every render and of the recovery")
    _add_variant(p)
    _add_data(p)
    
    p = sub.add_parser("evaluate", help="batch evaluation: recover many materials, re-render under novel probes, "
                                        "compare with the truth and parametric baselines",
                       description="batch evaluation: recover many materials, re-render them under novel probes, "
                                   "compare with the truth and parametric baselines. A material that fails gets "
                                   "a warning and the others go on: their results are written, and the command "
                                   "then ends with one error line naming the failed materials (exit status 2; a "
                                   "rerun tries only them). A problem shared by every material (an option, a "
                                   "probe, the prior) stops it before any work.")
    p.add_argument("materials", nargs="*",
                   help="folders of MERL .binary files, .binary files, MERL-NBRDF names, 'nbrdf' (the 23 "
                        "development materials), 'nbrdf-train' (the 50 training ones), 'nbrdf-all' (all 73) or "
                        "analytic specs (default: nbrdf; with --quick: two materials)")
    p.add_argument("--out", type=_parse_path, default="out/evaluate",
                   help="output folder (results.jsonl, summary.csv, figures/)")
    p.add_argument("--input-probes", nargs="+", default=None, metavar="PROBE",
                   help="probes lighting the input image (default: grace_latlong_1k uffizi_256)")
    p.add_argument("--novel-probes", nargs="+", default=None, metavar="PROBE",
                   help="probes of the validation renders (default: the other shared probes)")
    p.add_argument("--jobs", type=int, default=1, help="materials evaluated in parallel worker processes")
    p.add_argument("--dask", default=None, metavar="ADDRESS", help="send the materials to this Dask scheduler")
    p.add_argument("--threads", type=int, default=None,
                   help="Dr.Jit threads per job (default: cores // jobs)")
    p.add_argument("--quick", action="store_true",
                   help="a few materials at small sizes, seconds each: its sizes replace the defaults stated below "
                        "(48 px, 16 spp, 1000 normals, 3000 directions, a 12 x 12 grid, pisa_256 only, the "
                        "packaged priors; EvalConfig.quick); options given explicitly still apply")
    p.add_argument("--resolution", type=int, default=None, help="render width = height (default 128)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel of the input render (default 128)")
    p.add_argument("--novel-spp", type=int, default=None, help="samples per pixel of validation renders (default 64)")
    p.add_argument("--normals", type=int, default=None, help="normals M (default 8000)")
    p.add_argument("--dirs", type=int, default=None, help="light directions K (default 8000)")
    p.add_argument("--grid", type=int, nargs=2, default=None, metavar=("N_T", "N_S"),
                   help="st grid of the recovered tables (theta_h nodes, theta_d nodes; default 32 32)")
    p.add_argument("--alpha", type=_parse_alpha, default=None,
                   help="regularisation weight, or how to choose it: 'discrepancy' (default) or 'gcv'")
    p.add_argument("--baselines", nargs="*", default=None, metavar="MODEL",
                   help="parametric baselines to fit (default: ggx ward; none: skip)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the renders, the camera noise and the recovery (default: the config's, 0)")
    p.add_argument("--noise", type=float, default=None, metavar="LEVEL",
                   help="camera noise of the input images: variance a I + b with a relative standard deviation "
                        "LEVEL at the mean signal (mi_bivariate.noise; default 0 = clean)")
    p.add_argument("--renderer", choices=("reference", "path"), default=None,
                   help="renders that are scored: deterministic quadrature (default) or Mitsuba path tracing")
    p.add_argument("--novel-resolution", type=int, default=None,
                   help="width = height of the renders under the novel probes (default 64)")
    p.add_argument("--prior", default=None, metavar="FILE",
                   help="prior file for the recovery (default: for a shared MERL-NBRDF material, priors learnt "
                        "leave-one-out from the other 72, except with --quick; for any other, the packaged ones)")
    p.add_argument("--pdf", action="store_true", help="figures also as PDF")
    p.add_argument("--no-figures", action="store_true", help="skip the figures (tables and results only)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--abs", type=int, default=0, metavar="N",
                   help="also run analysis by synthesis (Adam + prb) on the first N materials (a rerun reports "
                        "those already run with this configuration from analysis_by_synthesis.jsonl)")
    p.add_argument("--abs-time-factor", type=float, default=10.0,
                   help="analysis by synthesis runs up to this many times the linear solve's time (both timed "
                        "after a warm-up, kernel compilation excluded)")
    _add_variant(p)
    _add_data(p)
    
    parser.command_parsers = sub.choices  # {command: its parser}, for errors pointing at the command's --help
    return parser


def _user_names(text: str, source_names: Dict[str, str]) -> str:
    """One line, its leading internal source name (``alpha``, ``image``) replaced by the user's file or option."""
    text = " ".join(text.split())
    return renamed(text, source_names) or text


def _warning_formatter(source_names: Dict[str, str]):
    """``warnings.formatwarning`` printing one line, with internal source names replaced by the user's files."""
    def format_warning(message, category, filename, lineno, line=None) -> str:
        return f"mi-bivariate: warning: {_user_names(str(message), source_names)}\n"

    return format_warning


def main(argv: Optional[Sequence[str]] = None, *, own_process: bool = False) -> int:
    """Run one ``mi-bivariate`` command; returns the exit status (2 for bad input).

    ``own_process``: the process exists for this command alone (:func:`run`). Everything the
    pipeline imports then lives until the process ends, so it is frozen out of Python's cyclic
    garbage collector once loaded (:func:`gc.freeze`): each full collection, during the run and
    several times while the interpreter shuts down, would otherwise walk those ~7 x 10^4 objects
    (~40 ms each time). Measured on ``recover --no-report``, 10 fresh processes per side alternating
    with the code before (``benchmarks/ab_revision.py REV --stages end-to-end,solve``, 2 cores):
    2.30 -> 2.03 s median, with the unchanged solve as control at 1.07x, so a gain of ~6-13%.
    The collector is also off while the pipeline loads: the ~170 collections it ran during the
    imports (one of them full) walked the growing heap for nothing: 0.09-0.19 s of collector time in
    one ``recover --no-report`` process, 0.01-0.02 s without them (two processes each, load 9-15).
    The modules that scipy's loading imports for nothing (numpy's ``f2py``, ``testing``, ``ma`` and
    ``polynomial``; ``scipy.special``) are deferred to their first use
    (:func:`mi_bivariate.process.defer_unused_modules`: ~0.09 s and ~0.04 s), as is Dr.Jit's rewrite of
    the functions Mitsuba's import decorates with ``@dr.syntax`` (:func:`~mi_bivariate.process.syntax_on_first_call`,
    ~0.02 s; a variant's start, ~0.1 s more, defers it in any process); scipy's parse of the docstrings
    it extends at import is skipped for the whole command (:func:`~mi_bivariate.process.plain_scipy_docstrings`,
    ~0.05 s of a ``recover``, ``scipy.ndimage``'s included); memory the command frees is
    kept for its next arrays instead of going back to the system
    (:func:`~mi_bivariate.process.keep_freed_memory`, for :data:`KEEP_FREED_MEMORY_COMMANDS`), and
    the process's memory is not put on transparent huge pages
    (:func:`~mi_bivariate.process.no_huge_pages`; an evaluation's worker processes inherit it).
    ``recover`` and ``recover-batch`` with their report draw it in a process started here, which loads
    matplotlib on the core the command's first second leaves idle (:func:`_report_worker_pays`).
    Tests and notebooks calling :func:`main` keep the default, which leaves the collector as it is.
    """
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the command's own parser: its --help lists what it takes
        parser.command_parsers[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    args.source_names = {}  # filled by commands that know which user file an internal name stands for
    formatwarning = warnings.formatwarning  # restored on return: a notebook calling main keeps its own
    warnings.formatwarning = _warning_formatter(args.source_names)
    replaced: Dict[int, object] = {}
    worker: Optional[ReportWorker] = None
    try:
        with contextlib.ExitStack() as blocks:
            if own_process:
                if args.command in KEEP_FREED_MEMORY_COMMANDS:
                    process.keep_freed_memory()  # first: before any thread allocates (see its notes)
                process.no_huge_pages()
                replaced = _stop_on_signals()
                gc.disable()  # until the freeze: no collection walks what the imports build (see above)
                if _report_worker_pays(args):
                    args.report_worker = worker = ReportWorker()  # loads matplotlib while the pipeline loads
            try:
                if own_process:
                    process.defer_unused_modules()
                    blocks.enter_context(process.plain_scipy_docstrings())  # the command's own imports too
                # A stop raised inside Dr.Jit's or Mitsuba's start aborted or crashed the process.
                with signals_deferred(), process.syntax_on_first_call() if own_process else contextlib.nullcontext():
                    commands = importlib.import_module("mi_bivariate.commands")  # the pipeline, loaded only to run
            finally:
                if own_process:
                    gc.freeze()
                    gc.enable()
            try:
                return int(commands.COMMANDS[args.command](args) or 0)
            finally:
                if worker is not None:  # here, so that a stop while it ends is said as any other
                    worker.close()
    except InputError as exc:
        # The library's own parameter ("noise", "basis_prior") named as the user gave it; a file the
        # user named so (a photo called "noise") is left alone. Messages without a source may begin
        # with the internal name ("merl table: ...").
        if exc.source is None:
            text = _user_names(str(exc), args.source_names)
        else:
            source = None if os.path.exists(exc.source) else args.source_names.get(exc.source)
            text = str(InputError(source, exc.problem, exc.hint)) if source else str(exc)
        print(f"mi-bivariate: error: {' '.join(text.split())}", file=sys.stderr)
        return 2
    except OSError as exc:
        if isinstance(exc, BrokenPipeError) and _stdout_reader_gone():
            return STATUS_READER_GONE  # ``mi-bivariate ... | head``: nothing to say, and nowhere to say it
        # A file the checks could not foresee (vanished, unreadable, a full disk).
        name = exc.filename if exc.filename is not None else args.command
        print(f"mi-bivariate: error: {name}: {exc.strerror or exc} (check the path, permissions and free space)",
              file=sys.stderr)
        return 2
    except MemoryError:
        print(f"mi-bivariate: error: {args.command}: out of memory (use smaller sizes)", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM as Terminated
        return _stopped(exc)
    except RuntimeError as exc:  # Dr.Jit wraps what a Python plugin raised inside a render
        cause = _interruption(exc)
        if cause is None:
            raise
        return _stopped(cause)
    finally:
        if worker is not None:
            worker.close()
        warnings.formatwarning = formatwarning
        for signum, handler in replaced.items():
            signal.signal(signum, handler)


#: Exit status of a command whose standard output's reader has gone: what a shell reports for a process
#: stopped by SIGPIPE (128 + 13), as the command line's other stops (130 for Ctrl-C, 143 for SIGTERM).
STATUS_READER_GONE = 128 + int(getattr(signal, "SIGPIPE", 13))


def _stdout_reader_gone() -> bool:
    """Whether standard output is a pipe or socket whose reader has gone (``mi-bivariate recover ... | head
    -1``; the kernel then reports an error or hang-up on the write end). If so, standard output is pointed at
    ``os.devnull``, so that the interpreter's last flush does not fail again, and the command ends with
    :data:`STATUS_READER_GONE` and no message, as a Unix tool stopped by SIGPIPE does (Python ignores SIGPIPE),
    not as a file's problem (status 2). Its outputs are written if the pipe broke after them (the summary is
    printed last). A broken pipe elsewhere (a worker's) is not this."""
    try:
        fd = sys.stdout.fileno()
        mode = os.fstat(fd).st_mode
        if not (stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)):
            return False
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if not any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0)):
            return False
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, fd)
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no descriptor (a notebook's stream), no poll (Windows)
        return False
    return True


#: The commands that write a recovery report (unless ``--no-report``).
REPORT_COMMANDS = ("recover", "recover-batch")


def _report_worker_pays(args: argparse.Namespace) -> bool:
    """Whether the command's report is drawn in a :class:`~mi_bivariate.report_worker.ReportWorker`: a
    report command with its report, and a second core for the worker (not ``--threads 1``).

    Measured (docs/recovery.md Round 37; 2026-12-07, the 2-core AMD EPYC VM, fresh processes, the same
    PNG byte for byte): what the report adds to ``recover`` was 0.69 s against 1.03 s without the worker in
    an alternating A/B run of the final code (0.54-1.07 s against 0.99-1.37 s over five runs of its versions),
    and 0.76-0.87 s in three ``bench_speed.py`` runs (target 1 s). The worker
    costs 0.1-0.5 s more CPU than drawing here (its own imports), so on a machine with no idle core it
    would cost time: hence a second core and not ``--threads 1``.
    """
    if args.command not in REPORT_COMMANDS or args.no_report or args.threads == 1 or os.name != "posix":
        return False
    return process.usable_cores() >= 2


#: The commands whose process keeps freed memory: those it was measured on (one photo, or a batch
#: of photos, each process short). ``evaluate`` (hours in one process with ``--jobs 1``), ``render``
#: and ``demo`` keep glibc's defaults.
KEEP_FREED_MEMORY_COMMANDS = ("recover", "recover-batch")


def _interruption(exc: BaseException) -> Optional[KeyboardInterrupt]:
    """The Ctrl-C or SIGTERM behind ``exc`` (among its causes and contexts), if any."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _stopped(exc: KeyboardInterrupt) -> int:
    """One line and the shell's status for a command stopped by SIGTERM (143) or Ctrl-C (130)."""
    if isinstance(exc, Terminated):
        print("mi-bivariate: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    print("mi-bivariate: interrupted", file=sys.stderr)
    return 130


def _stop_on_signals() -> Dict[int, object]:
    """SIGTERM and SIGINT stop the command as exceptions (:class:`~mi_bivariate.errors.Terminated`,
    ``KeyboardInterrupt``) that wait for the few steps of an output's writing that must not be cut
    (:func:`mi_bivariate.atomic.stop_on_signal`); where this process was started with a signal ignored
    or handled otherwise, that is left as it is. Returns the handlers replaced, to put back."""
    replaced = {}
    for signum, stop, default in ((signal.SIGTERM, Terminated, signal.SIG_DFL),
                                  (signal.SIGINT, KeyboardInterrupt, signal.default_int_handler)):
        if signal.getsignal(signum) is default:
            replaced[signum] = default
            signal.signal(signum, stop_on_signal(stop))
    return replaced


def run() -> int:
    """What the console script ``mi-bivariate``, ``python -m mi_bivariate`` and ``python -m mi_bivariate.cli``
    run (behind :func:`mi_bivariate.__main__.main`'s guard for a Ctrl-C while this module loads, and after its
    BLAS setting): :func:`main` with ``sys.argv`` in a process of its own.

    While the command runs, SIGTERM stops it as Ctrl-C does (:class:`~mi_bivariate.errors.Terminated`; exit
    status 143) instead of ending the process where it stands, which left an output's temporary file
    (``recover --merl``'s 35 MB ``.NAME.XXXX.binary``) behind (:func:`_stop_on_signals`).

    What the command left alive (for ``recover``, the report's matplotlib) is frozen too before the
    interpreter shuts down, whose collections would walk it once more (measured: shutdown 0.15-0.23 ->
    0.05 s after ``recover`` with its report).
    """
    status = main(own_process=True)
    gc.freeze()
    return status
