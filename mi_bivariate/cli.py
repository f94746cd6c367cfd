"""The ``mi-bivariate`` command.

Subcommands: ``info``, ``render``, ``reduce``, ``learn-prior``, ``recover``,
``demo``. Every one has ``--help``. Problems with the user's input end in a
single line ``mi-bivariate: error: FILE: problem`` and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

from mi_bivariate.errors import InputError, InputWarning


def _parse_sphere(text: str):
    if text == "auto":
        return text
    try:
        cx, cy, r = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sphere expects CX,CY,R in pixels, got {text!r}")
    if not r > 0:
        raise argparse.ArgumentTypeError(f"--sphere radius must be positive, got {r}")
    return cx, cy, r


def _add_variant(p: argparse.ArgumentParser) -> None:
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (llvm_ad_rgb default, cuda_ad_rgb on a GPU; env MI_BIVARIATE_VARIANT)")


def _add_data(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", default=None,
                   help="shared data folder with probes/ and merl_nbrdf/ (default: $MI_BIVARIATE_DATA)")


# --------------------------------------------------------------------------- info

def cmd_info(args: argparse.Namespace) -> int:
    import platform

    import drjit as dr
    import mitsuba as mi
    import numpy as np
    import scipy

    from mi_bivariate import __version__
    from mi_bivariate.variants import ensure_variant

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
        "cuda_backend (GPU)": bool(dr.has_backend(dr.JitBackend.CUDA)),
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

def _load_brdf_source(spec: str, data: Optional[str], interpolation: str = "nearest"):
    """A BRDF from a CLI spec: a MERL .binary, a bivariate .npz, an NBRDF name or an analytic spec."""
    from mi_bivariate import analytic, bivariate, merl, nbrdf

    path = Path(spec)
    if path.suffix == ".binary":
        return merl.MERLBRDF.read(path)
    if path.suffix == ".npz":
        return bivariate.BivariateBRDF.load(path)
    if spec in nbrdf.NBRDF_MATERIALS:
        return nbrdf.nbrdf_merl(spec, data_dir=data)
    if ":" in spec or spec in ("lambertian", "ggx", "oren-nayar", "bivariate-lobe"):
        return analytic.to_merl(analytic.analytic_from_spec(spec))
    if path.exists():
        raise InputError(path, "unknown BRDF file type", "use a MERL .binary or a bivariate .npz")
    raise InputError(spec, "not a file, an NBRDF material name or an analytic spec",
                     f"NBRDF names: {', '.join(nbrdf.NBRDF_MATERIALS)}")


def _load_probe(spec: str, data: Optional[str]):
    from mi_bivariate import probes

    path = Path(spec)
    if path.suffix:
        return probes.Probe.load(path)
    return probes.shared_probe(spec, data_dir=data)


def cmd_render(args: argparse.Namespace) -> int:
    from mi_bivariate import render
    from mi_bivariate.variants import ensure_variant

    ensure_variant(args.variant)
    brdf = _load_brdf_source(args.brdf, args.data)
    probe = _load_probe(args.probe, args.data)
    result = render.render_sphere(render.bsdf_dict(brdf), probe, resolution=args.resolution, spp=args.spp,
                                  camera=args.camera, seed=args.seed)
    out = Path(args.out)
    render.write_exr(out, result.image)
    render.write_png_preview(out.with_suffix(".png"), result.image)
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


# --------------------------------------------------------------------------- reduce

def cmd_reduce(args: argparse.Namespace) -> int:
    from mi_bivariate import bivariate, merl

    source = merl.MERLBRDF.read(args.merl)
    biv = bivariate.BivariateBRDF.reduce(source, n_t=args.grid[0], n_s=args.grid[1])
    error = bivariate.reduction_error(source, biv)
    out = Path(args.out) if args.out else Path(args.merl).with_suffix(".npz")
    biv.save(out)
    biv.save_exr(out.with_suffix(".exr"))
    print(f"Eq. 1 relative RMS error of the bivariate reduction: {error:.4f}")
    print(f"wrote {out} and {out.with_suffix('.exr')}")
    return 0


# --------------------------------------------------------------------------- learn-prior

def cmd_learn_prior(args: argparse.Namespace) -> int:
    from mi_bivariate import prior

    learnt = prior.learn_prior_from_merl(args.sources, n_t=args.grid[0], n_s=args.grid[1], data_dir=args.data)
    learnt.save(args.out)
    print(f"wrote {args.out}")
    return 0


# --------------------------------------------------------------------------- recover

def cmd_recover(args: argparse.Namespace) -> int:
    from mi_bivariate import recover as rec
    from mi_bivariate import spherefit
    from mi_bivariate.images import load_image, load_mask
    from mi_bivariate.threads import blas_threads
    from mi_bivariate.variants import ensure_variant

    ensure_variant(args.variant)
    probe = _load_probe(args.probe, args.data)
    image = load_image(args.image)
    mask = load_mask(args.mask, image.shape) if args.mask else None
    sphere = None if args.sphere in (None, "auto") else args.sphere
    fit = spherefit.fit_sphere(image, mask, sphere=sphere, source=str(args.image))
    print(fit.summary())
    with blas_threads():  # no BLAS oversubscription on a shared machine (mi_bivariate.threads)
        result = rec.recover(
            image, probe, fit.geometry, masks=mask, n_normals=args.normals, n_dirs=args.dirs,
            grid=tuple(args.grid), alpha=args.alpha, seed=args.seed, max_view_angle_deg=args.max_view_angle,
            saturation=args.saturation)
    paths = rec.write_outputs(result, args.out, merl=args.merl, report=not args.no_report,
                              report_render=args.report_render)
    print(result.summary())
    for p in paths:
        print(f"wrote {p}")
    return 0


# --------------------------------------------------------------------------- demo

def cmd_demo(args: argparse.Namespace) -> int:
    from mi_bivariate import demo
    from mi_bivariate.variants import ensure_variant

    ensure_variant(args.variant)
    return demo.run_demo(out_dir=Path(args.out), material=args.material, input_probe=args.input_probe,
                         novel_probe=args.novel_probe, data_dir=args.data, spp=args.spp, seed=args.seed,
                         resolution=args.resolution)


# --------------------------------------------------------------------------- evaluate

def cmd_evaluate(args: argparse.Namespace) -> int:
    from mi_bivariate import evaluate as ev
    from mi_bivariate.variants import ensure_variant

    ensure_variant(args.variant)
    data = args.data
    materials = list(args.materials) or (ev.quick_materials(data) if args.quick else ["nbrdf"])
    overrides = {k: v for k, v in {
        "input_probes": tuple(args.input_probes) if args.input_probes else None,
        "novel_probes": tuple(args.novel_probes) if args.novel_probes else None,
        "resolution": args.resolution, "spp": args.spp, "novel_spp": args.novel_spp,
        "n_normals": args.normals, "n_dirs": args.dirs, "grid": tuple(args.grid) if args.grid else None,
        "alpha": args.alpha, "seed": args.seed,
        "baselines": tuple(args.baselines) if args.baselines is not None else None,
    }.items() if v is not None}
    config = (ev.EvalConfig.quick(shared_data=ev.have_shared_data(data), **overrides) if args.quick
              else ev.EvalConfig(**overrides))
    formats = ("png", "pdf") if args.pdf else ("png",)
    records = ev.run_evaluation(materials, args.out, config=config, jobs=args.jobs, dask=args.dask,
                                data_dir=data, progress=not args.no_progress, figures=not args.no_figures,
                                figure_formats=formats, threads=args.threads)
    print(ev.format_summary(records))
    if args.abs:
        import json

        out = Path(args.out) / "analysis_by_synthesis.jsonl"
        for record in records[:args.abs]:
            result = ev.analysis_by_synthesis(record["spec"], config.input_probes[0], config=config, data_dir=data,
                                              time_factor=args.abs_time_factor)
            ev.append_record(out, result)
            a, lin = result["abs"], result["linear"]
            print(f"analysis by synthesis, {record['material']}: linear solve Eq. 1 {lin['eq1']:.4g} in "
                  f"{lin['time_s']:.1f} s; Adam+prb {a['final']['eq1']:.4g} after {a['time_s']:.1f} s "
                  f"({a['iterations']} iterations){' (reached)' if a['reached_linear_eq1'] else ''}")
    print(f"results: {Path(args.out) / ev.RESULTS_FILE}, {Path(args.out) / ev.SUMMARY_FILE}"
          + ("" if args.no_figures else f", figures in {Path(args.out) / 'figures'}"))
    return 0


# --------------------------------------------------------------------------- parser

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mi-bivariate",
        description="Passive reflectometry for Mitsuba 3: recover a bivariate (theta_h, theta_d) BRDF "
                    "from an HDR image of a known sphere under a known light probe.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("info", help="versions, Mitsuba variant, LLVM and GPU availability")
    _add_variant(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("render", help="render a sphere of any BRDF under a probe (EXR + PNG preview)")
    p.add_argument("brdf", help="MERL .binary, bivariate .npz, MERL-NBRDF name, or analytic spec "
                                "(e.g. 'ggx:alpha=0.1')")
    p.add_argument("--probe", required=True, help="environment map file (.exr/.hdr/.pfm) or shared probe name")
    p.add_argument("--out", default="render.exr", help="output EXR (a PNG preview is written beside it)")
    p.add_argument("--resolution", type=int, default=256, help="image width and height in pixels")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel")
    p.add_argument("--camera", choices=("orthographic", "perspective"), default="orthographic")
    p.add_argument("--seed", type=int, default=0)
    _add_variant(p)
    _add_data(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("reduce", help="reduce a MERL .binary to a bivariate table (prints the Eq. 1 error)")
    p.add_argument("merl", help="MERL .binary file")
    p.add_argument("--out", default=None, help="output .npz (default: beside the input)")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"),
                   help="st grid size (theta_h nodes, theta_d nodes)")
    p.set_defaults(func=cmd_reduce)

    p = sub.add_parser("learn-prior", help="learn the smoothness prior from a set of MERL materials")
    p.add_argument("sources", nargs="+", help="folders of MERL .binary files, .binary files, or MERL-NBRDF names")
    p.add_argument("--out", default="prior.npz", help="output .npz")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"))
    _add_data(p)
    p.set_defaults(func=cmd_learn_prior)

    p = sub.add_parser("recover", help="recover a bivariate BRDF from an HDR image of a sphere under a known probe")
    p.add_argument("image", help="linear HDR image (.exr/.hdr/.pfm)")
    p.add_argument("--probe", required=True, help="environment map file or shared probe name")
    p.add_argument("--sphere", default="auto", type=_parse_sphere, metavar="CX,CY,R",
                   help="sphere centre and radius in pixels (pixel centres at i+0.5, y down); "
                        "default 'auto': fitted to the image (or --mask), with the fit residual reported")
    p.add_argument("--mask", default=None, help="optional mask image (non-zero = usable)")
    p.add_argument("--out", default="brdf.npz", help="output .npz (EXR view and PNG report beside it)")
    p.add_argument("--merl", action="store_true", help="also write a MERL .binary")
    p.add_argument("--no-report", action="store_true", help="skip the PNG report")
    p.add_argument("--report-render", action="store_true",
                   help="path-trace the report's re-render (seconds) instead of predicting it as L f")
    p.add_argument("--normals", type=int, default=8000, help="number of normals M")
    p.add_argument("--dirs", type=int, default=32000, help="light directions per normal K")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 32), metavar=("N_T", "N_S"))
    p.add_argument("--alpha", type=float, default=None, help="regularisation weight (default: the documented one)")
    p.add_argument("--max-view-angle", type=float, default=80.0, help="drop normals further from the view (deg)")
    p.add_argument("--saturation", type=float, default=None, help="drop pixels with any channel >= this value")
    p.add_argument("--seed", type=int, default=0)
    _add_variant(p)
    _add_data(p)
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("demo", help="render a measured material, recover it, re-render it under a novel probe")
    p.add_argument("--out", default="out/demo", help="output folder")
    p.add_argument("--material", default=None, help="MERL-NBRDF name (default: gold-metallic-paint3; "
                                                    "an analytic material without shared data)")
    p.add_argument("--input-probe", default="grace_latlong_1k", help="probe lighting the input image")
    p.add_argument("--novel-probe", default="pisa_256", help="probe for the validation render")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel of every render")
    p.add_argument("--resolution", type=int, default=256, help="image width and height in pixels")
    p.add_argument("--seed", type=int, default=0)
    _add_variant(p)
    _add_data(p)
    p.set_defaults(func=cmd_demo)
    p = sub.add_parser("evaluate", help="batch evaluation: recover many materials, re-render under novel probes, "
                                        "compare with the truth and parametric baselines")
    p.add_argument("materials", nargs="*",
                   help="folders of MERL .binary files, .binary files, MERL-NBRDF names, 'nbrdf' (all 23) or "
                        "analytic specs (default: nbrdf; with --quick: two materials)")
    p.add_argument("--out", default="out/evaluate", help="output folder (results.jsonl, summary.csv, figures/)")
    p.add_argument("--input-probes", nargs="+", default=None, metavar="PROBE",
                   help="probes lighting the input image (default: grace_latlong_1k uffizi_256)")
    p.add_argument("--novel-probes", nargs="+", default=None, metavar="PROBE",
                   help="probes of the validation renders (default: the other shared probes)")
    p.add_argument("--jobs", type=int, default=1, help="materials evaluated in parallel worker processes")
    p.add_argument("--dask", default=None, metavar="ADDRESS", help="send the materials to this Dask scheduler")
    p.add_argument("--threads", type=int, default=None,
                   help="Dr.Jit threads per job (default: cores // jobs; 1 makes numbers bitwise reproducible)")
    p.add_argument("--quick", action="store_true", help="a few materials at small sizes (seconds each)")
    p.add_argument("--resolution", type=int, default=None, help="render width = height (default 128)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel of the input render (default 128)")
    p.add_argument("--novel-spp", type=int, default=None, help="samples per pixel of validation renders (default 64)")
    p.add_argument("--normals", type=int, default=None, help="normals M (default 8000)")
    p.add_argument("--dirs", type=int, default=None, help="light directions K (default 32000)")
    p.add_argument("--grid", type=int, nargs=2, default=None, metavar=("N_T", "N_S"))
    p.add_argument("--alpha", type=float, default=None, help="regularisation weight")
    p.add_argument("--baselines", nargs="*", default=None, metavar="MODEL",
                   help="parametric baselines to fit (default: ggx ward; none: skip)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--pdf", action="store_true", help="figures also as PDF")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--abs", type=int, default=0, metavar="N",
                   help="also run analysis by synthesis (Adam + prb) on the first N materials")
    p.add_argument("--abs-time-factor", type=float, default=10.0,
                   help="analysis by synthesis runs up to this many times the linear solve's time")
    _add_variant(p)
    _add_data(p)
    p.set_defaults(func=cmd_evaluate)
    return parser


def _format_warning(message, category, filename, lineno, line=None) -> str:
    return f"mi-bivariate: warning: {message}\n"


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.formatwarning = _format_warning
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"mi-bivariate: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mi-bivariate: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
