"""What each change of the recovery brought (issue 9), measured on rows of the input view.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/ablation.py \
        --materials gold-metallic-paint2,red-specular-plastic,pink-fabric2,nickel,violet-acrylic,special-walnut-224,pvc,blue-metallic-paint2

Protocol (fast, row-level; the full image protocol is ``mi-bivariate evaluate``):
observations of a 128 px orthographic sphere (M = 1000 normals), the clean input
``I`` under grace_latlong_1k and the truth under each novel probe are the 3D
MERL-NBRDF table integrated over each row's hemisphere by the same MIS quadrature as
the lighting matrix (65536 directions, independent seed); the relit recovery is
``L_novel f`` (MIS, K = 32768) and the floor is ``L_novel f_exact`` (the exact Eq. 1
reduction on the same grid). The score is the median over materials of the median
over the novel probes of relight error / floor. Priors are leave-one-out
(:func:`mi_bivariate.training_set.learn_priors` without the material). Use training
materials (``mi_bivariate.nbrdf.NBRDF_TRAIN_MATERIALS``) to choose settings; the
development materials are for reporting.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from mi_bivariate import capture, lighting
from mi_bivariate import merl as merl_mod
from mi_bivariate import nbrdf, probes, solve, training_set
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.lighting import _row_packets, hemisphere_offsets
from mi_bivariate.lighting.mis import _mis_lanes
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant

NOVEL = ("grace_256", "pisa_256", "pedestrian_overpass_1k")
#: The 8 training materials of docs/recovery.md section 2 (and of its ablation table, section 7).
SECTION2_MATERIALS = ("gold-metallic-paint2", "red-specular-plastic", "pink-fabric2", "nickel", "violet-acrylic",
                      "special-walnut-224", "pvc", "blue-metallic-paint2")
#: (label, lighting sampling, model-error form, alpha, basis prior, how the prior variant is kept)
CONFIGS = (
    ("paper: uniform directions, unweighted, alpha 1e-2", "uniform", "constant", 1e-2, False, "residual"),
    ("+ MIS directions", "mis", "constant", 1e-2, False, "residual"),
    ("+ MIS, constant model error, alpha 0.1", "mis", "constant", 1e-1, False, "residual"),
    ("+ MIS, relative model error", "mis", "relative", 1e-2, False, "residual"),
    ("+ MIS, sqrt model error (default)", "mis", "sqrt", 1e-2, False, "residual"),
    ("+ basis prior (default), alpha fixed at 1e-2", "mis", "sqrt", 1e-2, True, "residual"),
    ("+ GCV alpha instead of 1e-2", "mis", "sqrt", "gcv", True, "residual"),
    ("+ discrepancy-principle alpha <= 1e-2 (default)", "mis", "sqrt", "discrepancy", True, "residual"),
    ("+ prior variant kept by the evidence (default)", "mis", "sqrt", "discrepancy", True, "evidence"),
)


def full_table(name: str) -> np.ndarray:
    """The NBRDF on every MERL node (also below the horizon, where the MLP is defined)."""
    model = nbrdf.load_nbrdf(name)
    th, td, pd = merl_mod.node_angles()
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    x = np.stack([np.sin(TH), np.zeros_like(TH), np.cos(TH), np.sin(TD) * np.cos(PD), np.sin(TD) * np.sin(PD),
                  np.cos(TD)], -1).reshape(-1, 6)
    return model.eval_inputs(x, np.float32).reshape(90, 90, 180, 3)


def sphere_rows(n_normals: int):
    """The row-level protocol's observations (a 128 px orthographic sphere) and grace_latlong_1k."""
    obs = capture.image_observations(np.ones((128, 128, 3), np.float32), SphereGeometry(64, 64, 60),
                                     n_normals=n_normals, seed=0, saturation=2.0)
    return obs, probes.shared_probe("grace_latlong_1k")


def merl_position(lx, ly, lz, sin_v, cos_v):
    """Texture coordinates on the MERL grid ``(phi_d, theta_d, theta_h)`` of lanes with light
    ``(lx, ly, lz)`` in the row frame whose view is ``(sin_v, 0, cos_v)`` (``mi.Point3f``)."""
    import drjit as dr
    import mitsuba as mi

    hx, hy, hz = lx + sin_v, ly, lz + cos_v
    hn = dr.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    th = dr.atan2(dr.sqrt(hx * hx + hy * hy), hz)
    sph, cph = dr.sincos(-dr.atan2(hy, hx))
    sth, cth = dr.sincos(-th)
    ax, ay, az = lx * cph - ly * sph, lx * sph + ly * cph, lz
    bx, by, bz = ax * cth + az * sth, ay, -ax * sth + az * cth
    td = dr.atan2(dr.sqrt(bx * bx + by * by), bz)
    pd = dr.atan2(by, bx)
    pd = dr.select(pd < 0, pd + math.pi, pd)
    return mi.Point3f((pd / math.pi * 180 + 0.5) / 180, (td * (2 / math.pi) * 90 + 0.5) / 90,
                      (dr.sqrt(dr.maximum(th, 0) * (2 / math.pi)) * 90 + 0.5) / 90)


def render_rows(obs, probe, table: np.ndarray, n_dirs: int = 65536, seed: int = 77, chunk: int = 512):
    """Row values of a 3D MERL-grid table by the lighting matrix's MIS quadrature, ``(M, 3)``."""
    import drjit as dr
    import mitsuba as mi

    tex = mi.Texture3f(mi.TensorXf(np.ascontiguousarray(table)), filter_mode=dr.FilterMode.Linear,
                       wrap_mode=dr.WrapMode.Clamp)
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(len(obs), seed))
    counts = lighting.strategy_counts(n_dirs)
    out = np.empty((len(obs), 3), np.float32)
    for c0 in range(0, len(obs), chunk):
        pk = packets[c0:c0 + chunk]
        m = len(pk)
        data = mi.Float(pk.reshape(-1))
        target = dr.zeros(mi.Float, m * 4)
        for strategy in counts:
            lanes = _mis_lanes(data, m, probe, strategy, counts)
            row, lx, ly, lz, d, weight, sin_v, cos_v, above, radiance = lanes
            rad = radiance * weight
            pos = merl_position(lx, ly, lz, sin_v, cos_v)
            f = tex.eval(pos)
            dr.scatter_reduce(dr.ReduceOp.Add, target, mi.Vector4f(f[0] * rad[0], f[1] * rad[1], f[2] * rad[2], 0),
                              row, active=above, mode=dr.ReduceMode.Expand)
        out[c0:c0 + m] = target.numpy().reshape(m, 4)[:, :3]
    return out


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def material_rows(name: str, obs, grace, novel: dict, L_novel: dict, tables: dict):
    """One material under the protocol: ``(prior, basis, pixels, truth, floors, exact)`` with
    leave-one-out priors, the input rows under grace, the truth rows under each novel probe,
    the exact reduction's relight error there and the reduction itself ``(N, 3)``."""
    prior, basis = training_set.learn_priors(tables, exclude=(name,))
    table3d = full_table(name)
    pixels = render_rows(obs, grace, table3d)
    truth = {p: render_rows(obs, novel[p], table3d) for p in novel}
    exact = tables[name].reshape(-1, 3)
    floors = np.array([rel(np.einsum("mnc,nc->mc", L_novel[p], exact), truth[p]) for p in novel])
    return prior, basis, pixels, truth, floors, exact


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", default=",".join(SECTION2_MATERIALS),
                        help="comma-separated MERL-NBRDF names (default: the 8 training materials of "
                             "docs/recovery.md section 2, named in this docstring)")
    parser.add_argument("--normals", type=int, default=1000)
    args = parser.parse_args()
    ensure_variant()
    obs, grace = sphere_rows(args.normals)
    novel = {p: probes.shared_probe(p) for p in NOVEL}
    L_in = {s: lighting.lighting_matrix(obs, grace, n_dirs=32768, sampling=s) for s in ("uniform", "mis")}
    L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=5) for p in NOVEL}
    tables = training_set.reduced_tables(32, 32)
    scores = {c[0]: [] for c in CONFIGS}
    for name in args.materials.split(","):
        t0 = time.perf_counter()
        prior, basis, I, truth, floors, _ = material_rows(name, obs, grace, novel, L_novel, tables)
        for label, sampling, form, alpha, use_basis, pair_rule in CONFIGS:
            data = solve.prepare_data_term(L_in[sampling], I, solve.row_sigma(I, form=form))
            r = solve_stages(data, prior, alpha, basis if use_basis else None, pair_rule)  # as recover() does
            f = r.table.reshape(-1, 3)
            errors = np.array([rel(np.einsum("mnc,nc->mc", L_novel[p], f), truth[p]) for p in NOVEL])
            scores[label].append(float(np.median(errors / floors)))
        print(f"{name}: floors {np.round(floors, 4).tolist()} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print("\n| change | median relight / floor | worst |\n|---|---|---|")
    for label, values in scores.items():
        print(f"| {label} | {np.median(values):.2f} | {np.max(values):.2f} |")


if __name__ == "__main__":
    main()
