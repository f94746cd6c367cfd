"""Can a material's phi_d shape be predicted from its bivariate table? (issue 9's Eq. 1 target)

    MI_BIVARIATE_DATA=../shared/data python benchmarks/phi_d_predictability.py [--components 3,8] [--features 3,8]

``docs/recovery.md`` section 4d: the phi_d shape ``s = f / f_bar`` of the material itself, put
into the lighting matrix, brings Eq. 1 on observed cells from 1.88 to 1.18 times the floor, and
3 known principal-component coefficients of it to 1.55; fitted from the image they are
identified on half of the materials only. A cheaper route would predict the coefficients from
what the solve already has, the bivariate table, by a regression learnt on measured materials.
This measures whether that could work, with the truth tables (the best case: a recovered table
is noisier).

Shapes as ``eq1_phi_d.py`` makes them (:func:`eq1_phi_d.phi_d_shape`, mean over RGB, the MERL grid
subsampled 2 x 2 x 4), principal components learnt on the 50 training materials. Features: the
first principal components of ``log(1 + 100 f_bar)`` (mean RGB, the same subsampling in
``theta_h, theta_d``) of the training materials, standardised; coefficients by ridge regression
on the 50 training materials, for each ridge weight. Scored on the 23 development materials,
which neither the components nor the regression saw: the fraction of each material's shape
variance about the training mean that its own ``K`` coefficients explain (the bound) and that
the predicted ones explain (1 is all, 0 no better than the mean shape, below 0 worse).
"""

from __future__ import annotations

import argparse

import numpy as np
from eq1_phi_d import _subsampled, phi_d_shape

from mi_bivariate import nbrdf
from mi_bivariate.bivariate import phi_d_average

RIDGE = (0.1, 1.0, 10.0, 100.0)


def _features(name: str) -> np.ndarray:
    f_bar = phi_d_average(nbrdf.nbrdf_merl(name)).mean(-1)
    return np.log1p(100.0 * np.maximum(f_bar, 0.0))[::2, ::2].ravel()


def _principal(x: np.ndarray, k: int):
    mean = x.mean(0)
    _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
    return mean, vt[:k]


def _explained(shape: np.ndarray, mean: np.ndarray, components: np.ndarray, coeffs: np.ndarray) -> float:
    about = shape - mean
    return 1.0 - float(np.sum((about - coeffs @ components) ** 2) / np.sum(about ** 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--components", default="3,8", help="shape components K (comma-separated)")
    parser.add_argument("--features", default="3,8", help="feature components (comma-separated)")
    args = parser.parse_args()
    train, dev = list(nbrdf.NBRDF_TRAIN_MATERIALS), list(nbrdf.NBRDF_MATERIALS)
    shapes = {n: _subsampled(phi_d_shape(n)).ravel() for n in train + dev}
    features = {n: _features(n) for n in train + dev}
    s_train = np.array([shapes[n] for n in train])
    x_train = np.array([features[n] for n in train])
    print("| shape components K | feature components | ridge | explained by own K coefficients, median (min) "
          "| explained by predicted coefficients, median (min) | correlation of predicted and own "
          "coefficients, median over components |")
    print("|---:|---:|---:|---|---|---:|")
    for k in (int(v) for v in args.components.split(",")):
        mean, components = _principal(s_train, k)
        c_train = (s_train - mean) @ components.T
        own = {n: (shapes[n] - mean) @ components.T for n in dev}
        bound = [_explained(shapes[n], mean, components, own[n]) for n in dev]
        for kf in (int(v) for v in args.features.split(",")):
            f_mean, f_components = _principal(x_train, kf)
            z_train = (x_train - f_mean) @ f_components.T
            spread = z_train.std(0) + 1e-12
            design = np.c_[z_train / spread, np.ones(len(train))]
            for ridge in RIDGE:
                penalty = ridge * np.eye(design.shape[1])
                penalty[-1, -1] = 0.0                      # the intercept is not penalised
                weights = np.linalg.solve(design.T @ design + penalty, design.T @ c_train)
                predicted = {n: np.r_[((features[n] - f_mean) @ f_components.T) / spread, 1.0] @ weights
                             for n in dev}
                got = [_explained(shapes[n], mean, components, predicted[n]) for n in dev]
                corr = np.median([np.corrcoef([predicted[n][j] for n in dev], [own[n][j] for n in dev])[0, 1]
                                  for j in range(k)])
                print(f"| {k} | {kf} | {ridge:g} | {np.median(bound):.2f} ({np.min(bound):.2f}) | "
                      f"{np.median(got):.2f} ({np.min(got):.2f}) | {corr:.2f} |", flush=True)


if __name__ == "__main__":
    main()
