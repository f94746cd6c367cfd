"""How far Eq. 1 on observed cells falls if the lighting matrix models phi_d (issue 9's Eq. 1 target).

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/eq1_phi_d.py \
        alum-bronze,black-fabric,red-phenolic,white-paint,gold-metallic-paint3,pink-jasper \
        [--fit 3 [--projection]] [--relight]

The bivariate model treats each pixel as seeing the phi_d average of the BRDF. A real
material varies with phi_d, so a table fitted to the pixels absorbs that variation
(docs/recovery.md section 4d). This diagnostic puts a phi_d shape
``s(theta_h, theta_d, phi_d) = f / f_bar`` (mean 1 over the valid phi_d of each node)
into the lighting matrix, weighting each light direction by the shape at its
Rusinkiewicz angles, and solves for the bivariate table as ``recover`` does
(``solve_stages``: discrepancy alpha, basis prior, evidence). Shapes compared:

- ``plain``: none (a shape of 1: the product's estimator, sampled like the others, per row);
- ``oracle``: the material's own shape (the best any phi_d model could do);
- ``mean``: the mean shape of the 50 training materials;
- ``pcaK``: the material's own shape projected onto the mean plus the first K principal
  components of the training materials' shapes (luminance, MERL grid subsampled 2 x 2 x 4):
  the best a K-parameter model could do if its coefficients were known;
- ``fitK`` (with ``--fit K``): the K coefficients fitted from the image, alternating with the
  table solve (4 rounds): given the table, the coefficients by least squares on the rows
  (relative weights); given the coefficients, the table with the shaped matrix (linear in
  the coefficients: the matrices of the mean shape and of each component, combined).

- ``--projection``: the ``K`` coefficients fitted jointly with the table instead, by variable
  projection (:func:`projected`).
- ``--relight``: each table also relit under ``ablation.py``'s three novel probes (same view),
  the median over probes of its relative RMS error against the 3D truth divided by the exact
  reduction's (the bivariate model renders the table, whatever shape fitted it).

Row level as in ``eq1_alpha.py``: 3000 normals of a 128 px sphere, clean input under
grace_latlong_1k rendered from the 3D table by the MIS quadrature (65536 directions,
independent seed), K = 8000, 32 x 32, leave-one-out priors. Prints Eq. 1 over observed
cells / the exact floor (Eq. 1 of the phi_d average over all cells: the ratio issue 9 scores),
and over all cells; the grid floor (the 32 x 32 table's) beside it. Before 2026-12-06 the ratios'
denominator was the grid floor, labelled "exact floor" (an audit found it; ``docs/recovery.md``
section 4d rescales the tables measured before).
Development materials only (the shapes and priors never saw them); it chooses nothing.
"""

from __future__ import annotations

import argparse

import drjit as dr
import mitsuba as mi
import numpy as np
from ablation import NOVEL, full_table, material_rows, merl_position, rel, render_rows
from eq1_alpha import row_setup

from mi_bivariate import lighting, nbrdf, probes, solve, training_set
from mi_bivariate.bivariate import BivariateBRDF, phi_d_average
from mi_bivariate.lighting import _row_packets, hemisphere_offsets
from mi_bivariate.lighting.kernels import _splat
from mi_bivariate.lighting.mis import _mis_lanes
from mi_bivariate.metrics import BRDFErrors
from mi_bivariate.solve import solve_stages
from mi_bivariate.variants import ensure_variant

#: MERL-grid subsampling of the shapes for the principal components (theta_h, theta_d, phi_d).
STEP = (2, 2, 4)
COMPONENTS = (1, 3, 8)


def phi_d_shape(name: str) -> np.ndarray:
    """``f / f_bar`` on the MERL grid, ``(90, 90, 180, 3) float32``; 1 where invalid or f_bar ~ 0."""
    merl = nbrdf.nbrdf_merl(name)
    f_bar = phi_d_average(merl)[:, :, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        shape = merl.table / f_bar
    keep = merl.valid_mask()[..., None] & np.isfinite(shape) & (f_bar > 1e-6)
    return np.clip(np.where(keep, shape, 1.0), 0.0, 50.0).astype(np.float32)


def shaped_lighting_matrix(obs, probe, shape: np.ndarray, n_dirs: int = 8000, seed: int = 0,
                           chunk: int = 256, n_t: int = 32, n_s: int = 32) -> np.ndarray:
    """The MIS lighting matrix with each direction weighted by ``shape`` (a (.., .., .., 3) MERL-layout grid)."""
    tex = mi.Texture3f(mi.TensorXf(np.ascontiguousarray(shape)), filter_mode=dr.FilterMode.Linear,
                       wrap_mode=dr.WrapMode.Clamp)
    packets = _row_packets(obs.normals, obs.views, hemisphere_offsets(len(obs), seed))
    counts = lighting.strategy_counts(n_dirs)
    n_nodes = n_t * n_s
    out = np.empty((len(obs), n_nodes, 3), np.float32)
    for c0 in range(0, len(obs), chunk):
        m = len(packets[c0:c0 + chunk])
        data = mi.Float(packets[c0:c0 + chunk].reshape(-1))
        target = dr.zeros(mi.Float, m * n_nodes * 4)
        for strategy in counts:
            lanes = _mis_lanes(data, m, probe, strategy, counts)
            row, lx, ly, lz, d, weight, sin_v, cos_v, above, radiance = lanes
            radiance = radiance * weight
            pos = merl_position(lx, ly, lz, sin_v, cos_v)
            s = tex.eval(pos)
            value = mi.Color3f(radiance[0] * s[0], radiance[1] * s[1], radiance[2] * s[2])
            _splat(m, row, lx, ly, lz, sin_v, cos_v, value, n_t, n_s, active=above, target=target)
        out[c0:c0 + m] = target.numpy().reshape(m, n_nodes, 4)[:, :, :3]
    return out


def _subsampled(shape: np.ndarray) -> np.ndarray:
    return shape[::STEP[0], ::STEP[1], ::STEP[2]].mean(-1)


FIT_ROUNDS = 4


def fitted(pixels, plain, prior, basis, base, parts, errors, observed, floor):
    """Eq. 1 ratios over the rounds of fitting the coefficients of ``parts`` (the matrices of the
    components, :func:`component_matrices`) with the table; ``base``: the mean shape's matrix."""
    k = len(parts)
    weight = 1.0 / (0.01 * pixels + 1e-3 * pixels.mean(0))
    result = solve_stages(solve.prepare_data_term(plain, pixels), prior, None, basis)
    out = []
    for _ in range(FIT_ROUNDS):
        f = result.table.reshape(-1, 3).astype(np.float32)
        design = np.stack([np.einsum("mnc,nc->mc", p, f) for p in parts], -1) * weight[..., None]
        target = (pixels - np.einsum("mnc,nc->mc", base, f)) * weight
        coeffs = np.linalg.lstsq(design.reshape(-1, k), target.reshape(-1), rcond=None)[0]
        L = base + sum(c * p for c, p in zip(coeffs, parts))
        result = solve_stages(solve.prepare_data_term(L, pixels), prior, None, basis)
        out.append(errors(BivariateBRDF(result.table), observed_nodes=observed)["eq1_observed"] / floor)
    return out, coeffs


def component_matrices(obs, grace, components, k, as_rgb):
    """The lighting matrices of the first ``k`` principal components of the shapes (a component is
    a signed direction in shape space: not clipped like a shape)."""
    return [shaped_lighting_matrix(obs, grace, as_rgb(components[j], clip=False)) for j in range(k)]


def projected(pixels, plain, prior, basis, base, parts, scale, errors, observed, floor,
              max_evaluations: int = 80):
    """Eq. 1 ratio with ``k`` shape coefficients fitted jointly with the table, by variable projection.

    The table is eliminated: for coefficients ``c`` the smoothness-prior solve at the plain
    solve's alpha and pairs gives the table ``f(c)`` and its penalised objective
    ``Phi(c) = sum_k data_k + alpha prior_k`` (rows weighted by the plain image's sigma,
    fixed across ``c``), and Nelder-Mead minimises ``Phi`` over ``c`` in units of the training
    coefficients' spread (``scale``), from 0 (the mean shape). The table at the best ``c``
    is then solved as ``recover`` does (both stages).
    """
    from scipy.optimize import minimize

    k = len(parts)
    sigma = solve.row_sigma(pixels)
    first = solve_stages(solve.prepare_data_term(plain, pixels, sigma), prior, None, basis)
    pairs = tuple(sorted(set(first.winner)))

    def matrix(z):
        return base + sum(zj * sj * p for zj, sj, p in zip(z, scale, parts))

    def objective(z):
        result = solve.solve_prepared(solve.prepare_data_term(matrix(z), pixels, sigma), prior, first.alphas,
                                      pairs=pairs, winner=first.winner)
        kept = [result.pairs[w] for w in result.winner]
        return float(sum(p.data_term[c] + a * p.prior_term[c] for c, (p, a) in enumerate(zip(kept, first.alphas))))

    best = minimize(objective, np.zeros(k), method="Nelder-Mead",
                    options={"maxfev": max_evaluations, "initial_simplex": np.vstack([np.zeros(k), np.eye(k)]),
                             "xatol": 0.05, "fatol": 1e-6})
    result = solve_stages(solve.prepare_data_term(matrix(best.x), pixels), prior, None, basis)
    ratio = errors(BivariateBRDF(result.table), observed_nodes=observed)["eq1_observed"] / floor
    return ratio, best.x * scale[:k], best.nfev, objective(np.zeros(k)), best.fun, result.table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("materials", help="comma-separated MERL-NBRDF development names")
    parser.add_argument("--fit", type=int, default=0, metavar="K", help="fit K shape coefficients from the image")
    parser.add_argument("--projection", action="store_true", help="with --fit: by variable projection")
    parser.add_argument("--relight", action="store_true", help="also relight each table under the novel probes")
    args = parser.parse_args()
    projection, relight, fit = args.projection, args.relight, args.fit
    ensure_variant()
    obs, grace, _, observed, tables = row_setup()
    # Every column through the same per-row sampler (the product's lighting matrix pools the
    # environment's directions: another realisation of the quadrature).
    plain = shaped_lighting_matrix(obs, grace, np.ones((2, 2, 2, 3), np.float32))
    train = np.array([_subsampled(phi_d_shape(n)).ravel() - 1.0 for n in nbrdf.NBRDF_TRAIN_MATERIALS])
    mean = train.mean(0)
    _, sv, components = np.linalg.svd(train - mean, full_matrices=False)
    energy = np.cumsum(sv**2) / np.sum(sv**2)
    print("training shapes: energy about the mean in the first " +
          ", ".join(f"{k}: {energy[k - 1]:.2f}" for k in COMPONENTS), flush=True)
    grid = _subsampled(np.zeros((90, 90, 180, 1))).shape
    def as_rgb(s, clip=True):
        s = np.clip(s, 0, 50) if clip else s
        return np.repeat(s.reshape(grid)[..., None], 3, -1).astype(np.float32)

    mean_matrix = shaped_lighting_matrix(obs, grace, as_rgb(1.0 + mean))
    parts = component_matrices(obs, grace, components, fit, as_rgb) if fit else []
    if relight:  # the tables relit under ablation.py's novel probes, against the 3D truth, per exact floor
        novel = {p: probes.shared_probe(p) for p in NOVEL}
        L_novel = {p: lighting.lighting_matrix(obs, novel[p], n_dirs=32768, seed=5) for p in NOVEL}
    for name in args.materials.split(","):
        truth = nbrdf.nbrdf_merl(name)
        errors = BRDFErrors(truth)
        floor = errors(phi_d_average(truth))["eq1"]  # the exact floor (paper Fig. 3)
        grid_floor = errors(BivariateBRDF(tables[name]))["eq1"]
        prior, basis = training_set.learn_priors(tables, exclude=(name,))
        pixels = render_rows(obs, grace, full_table(name))
        own = phi_d_shape(name)
        matrices = {"plain": plain, "oracle": shaped_lighting_matrix(obs, grace, own), "mean": mean_matrix}
        centred = _subsampled(own).ravel() - 1.0 - mean
        for k in COMPONENTS:
            coeffs = components[:k] @ centred
            matrices[f"pca{k}"] = shaped_lighting_matrix(obs, grace, as_rgb(1.0 + mean + coeffs @ components[:k]))
        cells = [f"{name}: exact floor {floor:.3f} (grid floor {grid_floor:.3f})"]
        if relight:
            _, _, _, truth, floors, _ = material_rows(name, obs, grace, novel, L_novel, tables)

            def relit_ratio(table):
                f = np.asarray(table, np.float64).reshape(-1, 3)
                return float(np.median([rel(np.einsum("mnc,nc->mc", L_novel[p], f), truth[p]) / fl
                                        for p, fl in zip(NOVEL, floors)]))
        for tag, L in matrices.items():
            table = solve_stages(solve.prepare_data_term(L, pixels), prior, None, basis).table
            e = errors(BivariateBRDF(table), observed_nodes=observed)
            cells.append(f"{tag} {e['eq1_observed'] / floor:.2f}x (all cells {e['eq1'] / floor:.2f}x"
                         + (f", relight / floor {relit_ratio(table):.3f})" if relight else ")"))
        if fit and projection:
            ratio, coeffs, nfev, phi0, phi, table = projected(pixels, plain, prior, basis, mean_matrix, parts,
                                                              sv / np.sqrt(len(train)), errors, observed, floor)
            cells.append(f"fit{fit} by projection {ratio:.2f}x ({nfev} solves, Phi {phi0:.4g} -> {phi:.4g}; "
                         + (f"relight / floor {relit_ratio(table):.3f}; " if relight else "")
                         + f"coefficients {np.round(coeffs, 2).tolist()}, own "
                         f"{np.round(components[:fit] @ centred, 2).tolist()})")
        elif fit:
            rounds, coeffs = fitted(pixels, plain, prior, basis, mean_matrix, parts, errors, observed, floor)
            cells.append(f"fit{fit} by round " + " ".join(f"{r:.2f}x" for r in rounds) +
                         f" (coefficients {np.round(coeffs, 2).tolist()}, own "
                         f"{np.round(components[:fit] @ centred, 2).tolist()})")
        print(" | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
