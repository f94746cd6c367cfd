"""Measure the quadrature error of the reference renderer (mi_bivariate.reference).

Usage: python scripts/reference_noise.py [RESOLUTION] [FACTOR] [MATERIALS] [PROBES]
(defaults 64, 1, the six materials and three probes below)

MATERIALS, PROBES: comma-separated MERL-NBRDF and shared probe names.

For each material x probe: relative RMS difference of two seeds / sqrt 2 over the sphere
(``seed``), the difference against a render with 4x the directions (``vs 4x``), and the
CPU and wall seconds per render (one Dr.Jit thread). Directions = FACTOR x reference.DEFAULT_DIRECTIONS.
"""
import sys

import drjit as dr

from mi_bivariate import evaluate as ev
from mi_bivariate import nbrdf, reference
from mi_bivariate.variants import ensure_variant

MATERIALS = ("blue-acrylic", "gold-metallic-paint3", "specular-white-phenolic", "tungsten-carbide",
             "brass", "hematite")
PROBES = ("grace_latlong_1k", "pisa_256", "pedestrian_overpass_1k")

ensure_variant()
dr.set_thread_count(1)
res = int(sys.argv[1]) if len(sys.argv) > 1 else 64
factor = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
materials = sys.argv[3].split(",") if len(sys.argv) > 3 else MATERIALS
probes = sys.argv[4].split(",") if len(sys.argv) > 4 else PROBES
dirs = reference.scaled_directions(factor)
print(f"resolution {res}, directions {dirs} per pixel (cosine, lobe, environment)")
print("| material | probe | seed noise | vs 4x | CPU s / render | wall s / render |")
print("|---|---|---:|---:|---:|---:|")
for name in materials:
    truth = nbrdf.nbrdf_merl(name)
    for probe in probes:
        q = reference.quadrature_noise(truth, ev.load_probe(probe), res, dirs, reference_factor=4.0)
        print(f"| {name} | {probe} | {q['seed_rms']:.4f} | {q['vs_large']:.4f} | {q['cpu_seconds']:.1f} | "
              f"{q['seconds']:.1f} |", flush=True)
