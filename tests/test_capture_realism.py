"""Realistic synthetic capture: perspective photos of MERL-NBRDF spheres through the photo path.

Each perturbation alone (sensor noise, a 2% radius error, a 5-degree probe yaw,
clipped highlights) and all together must be handled without crashing and
must not make the recovery better than the clean case; estimating the
probe's yaw first must win back most of what the misalignment cost.
Errors are novel-probe pixel errors predicted through Eq. 5 (see
:func:`novel_error`); the benchmark (``benchmarks/bench_beyond_sphere.py``)
reports Eq. 1 and rendered-image errors at full size.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mi_bivariate.capture import Observations, hemisphere_lattice
from mi_bivariate.errors import InputWarning
from mi_bivariate.geometry import Intrinsics
from mi_bivariate.lighting import lighting_matrix
from mi_bivariate.recover import recover_from_photo
from mi_bivariate.render import render_sphere
from mi_bivariate.spherefit import fit_sphere

RES, FOV = 96, 30.0
FAST = dict(n_normals=800, n_dirs=6000)


@pytest.fixture(scope="module")
def scene(data_dir):
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.nbrdf import nbrdf_merl
    from mi_bivariate.probes import shared_probe

    # Area-averaged probes: K = 8000 sampled directions resolve them (the full
    # grace_256 needs K ~ 32000: at 8000 even a diffuse sphere leaves a 20% residual).
    probe = shared_probe("grace_256", data_dir).downsampled(4)
    novel = shared_probe("uffizi_256", data_dir).downsampled(4)
    truth = nbrdf_merl("pink-jasper", data_dir)
    render = render_sphere(truth, probe, resolution=RES, spp=256, camera="perspective", fov=FOV, seed=5)
    n = hemisphere_lattice(800, seed=5)
    n = n[n[:, 2] > np.cos(np.radians(80))]
    obs = Observations(n, np.broadcast_to([0.0, 0.0, 1.0], n.shape).copy(), np.zeros((len(n), 3), np.float32),
                       np.zeros(len(n), np.int32))
    L_novel = lighting_matrix(obs, novel, n_dirs=8000)
    reference = np.einsum("mnc,nc->mc", L_novel, BivariateBRDF.reduce(truth).table.reshape(-1, 3))
    return probe, render, L_novel, reference


def novel_error(rec, L_novel: np.ndarray, reference: np.ndarray) -> float:
    """Relative RMS of a sphere's pixels under the novel probe, recovered table vs the truth's reduction."""
    predicted = np.einsum("mnc,nc->mc", L_novel, rec.brdf.table.reshape(-1, 3))
    return float(np.linalg.norm(predicted - reference) / np.linalg.norm(reference))


@pytest.mark.slow
def test_perturbations_degrade_gracefully(scene):
    probe, render, L_novel, reference = scene
    k = Intrinsics.from_fov(RES, RES, FOV)
    image = render.image
    region = render.mask
    rng = np.random.default_rng(0)
    mean = float(image[region].mean())
    noisy = np.maximum(image + rng.normal(size=image.shape) * np.sqrt(image * mean / 900 + (0.002 * mean) ** 2), 0)
    level = float(np.quantile(image[region].max(axis=1), 0.99))
    clipped = np.minimum(image, level)
    fit = fit_sphere(image, intrinsics=k, warn=False)
    assert fit.confident
    bigger = (fit.cx, fit.cy, 1.02 * fit.radius)
    turned = probe.rotated(euler_deg=(0, 5, 0))

    err = {}
    err["clean"] = novel_error(recover_from_photo(image, probe, intrinsics=k, **FAST), L_novel, reference)
    err["noise"] = novel_error(recover_from_photo(noisy.astype(np.float32), probe, intrinsics=k, **FAST),
                               L_novel, reference)
    # The radius error is measured against the true silhouette: the automatic fit
    # itself is ~0.8% small here (see test_fit_bias), which a +2% error would partly cancel.
    true_r = k.fx * np.tan(np.arcsin(1.0 / render.camera.distance))
    err["known"] = novel_error(recover_from_photo(image, probe, intrinsics=k, sphere=(48.0, 48.0, true_r), **FAST),
                               L_novel, reference)
    err["radius"] = novel_error(recover_from_photo(image, probe, intrinsics=k, sphere=(48.0, 48.0, 1.02 * true_r),
                                                   **FAST), L_novel, reference)
    err["yaw"] = novel_error(recover_from_photo(image, turned, intrinsics=k, **FAST), L_novel, reference)
    clipped_rec = recover_from_photo(clipped.astype(np.float32), probe, intrinsics=k, **FAST)
    err["clip"] = novel_error(clipped_rec, L_novel, reference)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        all_rec = recover_from_photo(np.minimum(noisy, level).astype(np.float32), turned, intrinsics=k,
                                     sphere=bigger, **FAST)
    err["all"] = novel_error(all_rec, L_novel, reference)
    aligned = recover_from_photo(image, turned, intrinsics=k, estimate_yaw=True,
                                 yaw_kwargs={"search_deg": (-20.0, 20.0), "coarse_step_deg": 10.0,
                                             "n_normals": 600}, **FAST)
    err["yaw estimated"] = novel_error(aligned, L_novel, reference)

    assert err["clean"] < 0.2 and err["known"] < 0.2, err
    # Clipping is detected (plateau at the maximum) and the clipped pixels dropped.
    assert clipped_rec.observations.dropped["saturated"] > 0
    for case in ("noise", "yaw", "clip", "all"):
        assert np.isfinite(err[case]) and err[case] >= 0.9 * err["clean"], (case, err)
    assert err["radius"] > err["known"], err
    assert err["yaw"] > err["clean"], err
    assert err["all"] > err["clean"], err
    # Estimating the yaw recovers most of the loss.
    assert abs(aligned.alignment.yaw_deg + 5.0) < 1.5, aligned.alignment.summary()
    assert err["yaw estimated"] - err["clean"] < 0.5 * (err["yaw"] - err["clean"]), err


def test_fit_bias(scene):
    """The automatic perspective fit's silhouette angle is close to the truth (documents its bias)."""
    _, render, _, _ = scene
    k = Intrinsics.from_fov(RES, RES, FOV)
    fit = fit_sphere(render.image, intrinsics=k, warn=False)
    true = np.arcsin(1.0 / render.camera.distance)
    # Measured: 13.448 vs 13.558 degrees (-0.8%) at 96 px, 512 spp.
    assert abs(fit.geometry.half_angle / true - 1.0) < 0.015
