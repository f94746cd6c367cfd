"""Is it the tails or the level? A path-traced photo's Monte Carlo noise against Gaussian noise of
the same local variance, and what an image-space despike does (docs/recovery.md section 5).

For each material, a 128 px sphere under grace_latlong_1k is path traced at ``--spp`` (default
64) and at 1024 spp (the clean input). Four inputs are recovered with leave-one-out priors and
``recover``'s defaults, under the exact sphere, and relit under pisa_256 by the reference
quadrature (128 px; relative RMS against the truth's render there; printed beside them: the relight
floor, the 32 x 32 reduction's error rendered the same way, and the scoring renders' own noise, the
truth's render against a second seed over sqrt 2):

- ``clean``: the 1024-spp render;
- ``monte carlo``: the ``--spp`` render (heavy-tailed per-pixel noise: its kurtosis is printed);
- ``gaussian, same variance``: the clean render plus Gaussian noise whose per-pixel variance is
  the Monte Carlo error's, averaged over 9 x 9 pixels (the same level, Gaussian tails);
- ``despiked``: the Monte Carlo render with every pixel that departs from its 3 x 3 median by
  more than 6 robust deviations (1.4826 times the 5 x 5 median of the absolute departures)
  replaced by that median; the count of replaced pixels is printed for it and for the clean image.

It decides whether a robust data term (or a despike before the solve) is worth building: if the
Gaussian input recovers no better than the Monte Carlo one, the tails are not what costs.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/mc_noise.py \\
        [--materials gold-metallic-paint3 red-phenolic nickel] [--spp 64]
"""

from __future__ import annotations

import argparse
import warnings
from typing import Sequence, Tuple

import numpy as np
from scipy import ndimage

from _machine import machine  # benchmarks/_machine.py

MATERIALS = ("gold-metallic-paint3", "red-phenolic", "nickel")
#: Robust deviations beyond which a pixel counts as a spike.
SPIKE_DEVIATIONS = 6.0


def despike(image: np.ndarray, mask: np.ndarray) -> Tuple[np.ndarray, int]:
    """``image`` with its spikes (see the module doc) replaced by their 3 x 3 medians, and their count."""
    lum = image.mean(-1)
    departure = lum - ndimage.median_filter(lum, size=3)
    scale = 1.4826 * ndimage.median_filter(np.abs(departure), size=5) + 1e-3 * np.median(lum[mask])
    spike = mask & (np.abs(departure) > SPIKE_DEVIATIONS * scale)
    out = image.copy()
    for c in range(3):
        out[..., c] = np.where(spike, ndimage.median_filter(image[..., c], size=3), image[..., c])
    return out, int(spike.sum())


def main(argv: Sequence[str] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS))
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args(argv)

    from mi_bivariate import metrics, nbrdf, probes, reference, render, training_set
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.recover import recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    warnings.simplefilter("ignore")
    print(f"Machine: {machine()}\n")
    print(f"| material | {args.spp}-spp relative noise, median / 99th pct | kurtosis | clean | monte carlo "
          "| gaussian, same variance | despiked | relight floor | scoring noise | spikes found: monte carlo / clean |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    grace, pisa = probes.shared_probe("grace_latlong_1k"), probes.shared_probe("pisa_256")
    for material in args.materials:
        truth = nbrdf.nbrdf_merl(material)
        priors = dict(zip(("prior", "basis_prior"), training_set.leave_one_out_priors(material)))
        want = reference.render_reference(truth, pisa, resolution=128, seed=1)
        again = reference.render_reference(truth, pisa, resolution=128, seed=2)
        scoring_noise = metrics.image_relative_rmse(again.image, want.image, want.mask) / np.sqrt(2.0)
        reduced = reference.render_reference(BivariateBRDF.reduce(truth, 32, 32), pisa, resolution=128, seed=1)
        floor = metrics.image_relative_rmse(reduced.image, want.image, want.mask)
        clean = render.render_sphere(render.bsdf_dict(truth), grace, resolution=128, spp=1024, seed=5)
        noisy = render.render_sphere(render.bsdf_dict(truth), grace, resolution=128, spp=args.spp, seed=0)
        mask = clean.mask
        error = noisy.image - clean.image
        variance = np.stack([ndimage.uniform_filter(error[..., c] ** 2, 9) for c in range(3)], -1)
        gaussian = clean.image + (np.random.default_rng(3).standard_normal(clean.image.shape)
                                  * np.sqrt(variance)).astype(np.float32)
        relative = error[mask] / np.maximum(clean.image[mask], 1e-3 * clean.image[mask].max())
        kurtosis = float(np.mean(relative**4) / np.mean(relative**2) ** 2)
        despiked, spikes = despike(noisy.image, mask)
        clean_spikes = despike(clean.image, mask)[1]
        relit = []
        for image in (clean.image, noisy.image, gaussian, despiked):
            result = recover(image, grace, clean.geometry, seed=0, **priors)
            got = reference.render_reference(result.brdf, pisa, resolution=128, seed=1)
            relit.append(metrics.image_relative_rmse(got.image, want.image, want.mask))
        print(f"| {material} | {np.median(np.abs(relative)):.3f} / {np.percentile(np.abs(relative), 99):.3f} "
              f"| {kurtosis:.1f} | " + " | ".join(f"{v:.4f}" for v in relit)
              + f" | {floor:.4f} | {scoring_noise:.4f} | {spikes} / {clean_spikes} |",
              flush=True)


if __name__ == "__main__":
    main()
