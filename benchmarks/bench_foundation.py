"""Foundation benchmark: MERL I/O, plugin render cost, importance-sampling quality.

Prints a Markdown report:

1. MERL ``.binary`` read time for a full-size (33 MB) file written to a temp dir.
2. Render time of a 256 x 256 sphere at 256 spp with the ``merl`` and
   ``bivariate`` plugins and with Mitsuba's built-in ``roughplastic``, under a
   shared probe (``grace_256``; a synthetic probe without the shared data).
   Target: each plugin within 1.5x of ``roughplastic``.
3. Relative noise of a glossy material rendered with the plugins' table
   sampling versus cosine-only sampling (``sampling="cosine"``), at equal spp:
   ``sqrt(mean_pixels var_seeds) / mean_pixels`` over the sphere's fully
   covered pixels.

Run: ``MI_BIVARIATE_DATA=../shared/data python benchmarks/bench_foundation.py``
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import numpy as np

ROUGHPLASTIC = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.05,
                "diffuse_reflectance": {"type": "rgb", "value": 0.5}}


def timed(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``repeats`` calls (seconds)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def load_probe():
    from mi_bivariate.probes import Probe, shared_probe
    from mi_bivariate.sources import synthetic_environment

    try:
        return shared_probe("grace_256"), "grace_256 (shared data)"
    except Exception:  # no shared data: the demo's procedural environment
        return Probe(synthetic_environment(seed=1), source="synthetic"), "synthetic environment (no shared data)"


def glossy_material():
    """A glossy MERL-grid material: NBRDF specular-white-phenolic, else a sharp GGX."""
    from mi_bivariate.analytic import CookTorranceGGX, to_merl

    try:
        from mi_bivariate.nbrdf import nbrdf_merl

        return nbrdf_merl("specular-white-phenolic"), "MERL-NBRDF specular-white-phenolic"
    except Exception:
        ggx = CookTorranceGGX(albedo_diffuse=0.1, specular=1.0, alpha=0.05, ior=1.5)
        return to_merl(ggx, dtype=np.float32), "GGX alpha=0.05 (no shared data)"


def bench_merl_read(repeats: int) -> Tuple[float, int]:
    from mi_bivariate.analytic import CookTorranceGGX, to_merl
    from mi_bivariate.merl import MERLBRDF

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ggx.binary"
        to_merl(CookTorranceGGX(albedo_diffuse=0.2, specular=1.0, alpha=0.2, ior=1.5)).write(path)
        size = path.stat().st_size
        MERLBRDF.read(path)  # warm the page cache: we time parsing, not the disk
        return timed(lambda: MERLBRDF.read(path), repeats), size


def render_fn(bsdf: dict, probe, resolution: int, spp: int) -> Callable[[int], np.ndarray]:
    """A function seed -> image for one scene (loaded once)."""
    import mitsuba as mi

    from mi_bivariate.geometry import SphereCamera
    from mi_bivariate.render import sphere_scene_dict

    camera = SphereCamera.create("orthographic", resolution)
    scene = mi.load_dict(sphere_scene_dict(bsdf, probe, camera, normals=False))
    mask = camera.coverage_mask()

    def render(seed: int) -> np.ndarray:
        return np.array(mi.render(scene, spp=spp, seed=seed), np.float64)[..., :3][mask]

    return render


def bench_render_times(probe, merl, repeats: int, resolution: int, spp: int) -> Dict[str, float]:
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.render import bsdf_dict

    biv = BivariateBRDF.reduce(merl)
    bsdfs = {
        "roughplastic (built-in)": ROUGHPLASTIC,
        "merl plugin (nearest)": bsdf_dict(merl, interpolation="nearest"),
        "merl plugin (linear)": bsdf_dict(merl, interpolation="linear"),
        "bivariate plugin (32x32)": bsdf_dict(biv),
    }
    renders = {name: render_fn(bsdf, probe, resolution, spp) for name, bsdf in bsdfs.items()}
    for render in renders.values():
        render(0)  # compile the kernels
    # Round-robin, so that load from other processes affects every BSDF alike.
    samples: Dict[str, List[float]] = {name: [] for name in renders}
    for repeat in range(repeats):
        for name, render in renders.items():
            samples[name].append(timed(lambda: render(1 + repeat), 1))
    return {name: statistics.median(t) for name, t in samples.items()}


def relative_noise(render: Callable[[int], np.ndarray], seeds: List[int]) -> float:
    images = np.stack([render(s) for s in seeds])  # (n_seeds, M, 3)
    return float(math.sqrt(images.var(axis=0, ddof=1).mean()) / images.mean())


def bench_noise(probe, merl, resolution: int, spp: int, n_seeds: int) -> Dict[str, Tuple[float, float]]:
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.render import bsdf_dict

    biv = BivariateBRDF.reduce(merl)
    seeds = list(range(10, 10 + n_seeds))
    out = {}
    for name, make in (("bivariate", lambda s: bsdf_dict(biv, sampling=s)),
                       ("merl (nearest)", lambda s: bsdf_dict(merl, interpolation="nearest", sampling=s))):
        out[name] = tuple(relative_noise(render_fn(make(sampling), probe, resolution, spp), seeds)
                          for sampling in ("table", "cosine"))
    # For scale: Mitsuba's own sampling of a comparably sharp built-in material.
    builtin = render_fn(ROUGHPLASTIC, probe, resolution, spp)
    out["roughplastic alpha=0.05 (built-in, for scale)"] = (relative_noise(builtin, seeds), float("nan"))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--noise-resolution", type=int, default=128)
    parser.add_argument("--noise-spp", type=int, default=64)
    parser.add_argument("--noise-seeds", type=int, default=4)
    parser.add_argument("--skip-timing", action="store_true", help="only the noise comparison")
    args = parser.parse_args()

    import mitsuba as mi

    from mi_bivariate.variants import ensure_variant

    variant = ensure_variant()
    probe, probe_name = load_probe()
    merl, material = glossy_material()

    noise = bench_noise(probe, merl, args.noise_resolution, args.noise_spp, args.noise_seeds)
    print(f"# Foundation benchmark ({variant}, Mitsuba {mi.__version__})\n")
    print(f"Probe: {probe_name}. Glossy material: {material}.\n")
    if not args.skip_timing:
        read_s, size = bench_merl_read(args.repeats)
        times = bench_render_times(probe, merl, args.repeats, args.resolution, args.spp)
        base = times["roughplastic (built-in)"]
        print("| measurement | value |\n| --- | --- |")
        print(f"| MERL .binary read ({size / 1e6:.1f} MB, median of {args.repeats}) | {read_s * 1e3:.0f} ms |")
        print(f"\n## Render time, {args.resolution}x{args.resolution} sphere, {args.spp} spp, path max_depth=2\n")
        print("| BSDF | time (s) | vs roughplastic |\n| --- | --- | --- |")
        for name, t in times.items():
            print(f"| {name} | {t:.2f} | {t / base:.2f}x |")
    print(f"\n## Relative noise, {args.noise_resolution}x{args.noise_resolution}, {args.noise_spp} spp, "
          f"{args.noise_seeds} seeds (std over seeds / mean)\n")
    print("| plugin | table sampling | cosine sampling | variance ratio (cosine / table) |\n| --- | --- | --- | --- |")
    for name, (table, cosine) in noise.items():
        if math.isnan(cosine):
            print(f"| {name} | {table:.4f} | | |")
        else:
            print(f"| {name} | {table:.4f} | {cosine:.4f} | {(cosine / table) ** 2:.1f}x |")


if __name__ == "__main__":
    main()
