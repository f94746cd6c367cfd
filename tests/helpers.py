"""Helpers shared by several test files (imported as ``from helpers import ...``; pytest puts
``tests/`` on the path, as for ``reference_solve`` and ``reference_lighting``)."""

from __future__ import annotations

import os
import subprocess
import time
from typing import Callable, Sequence, Tuple

import numpy as np

from mi_bivariate import metrics
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.evaluate.config import EvalConfig
from mi_bivariate.evaluate.renders import Renderer
from mi_bivariate.probes import Probe
from mi_bivariate.sources import load_probe, load_truth, resolve_materials
from mi_bivariate.variants import DEFAULT_VARIANT


def suite_variant() -> str:
    """The Mitsuba variant the suite runs under: ``$MI_BIVARIATE_VARIANT`` (``cuda_ad_rgb`` on a
    machine with a GPU: ``scripts/gpu_check.sh``) or the toolkit's default, ``llvm_ad_rgb``."""
    return os.environ.get("MI_BIVARIATE_VARIANT") or DEFAULT_VARIANT


def sums_in_fixed_order() -> bool:
    """Whether the lighting matrix's sums run in one order, so that two runs agree bit for bit: on
    the LLVM backend, for any number of Dr.Jit threads (a lane per row). Not on CUDA, whose scatter-adds are atomics that land
    in whatever order the GPU's threads reach them: there runs agree to float32 rounding only
    (measured on an H100: 2e-7 relative in one kernel's rows, 5e-7 in a recovered table)."""
    return not suite_variant().startswith("cuda")


def assert_same_sums(actual: np.ndarray, desired: np.ndarray, rel: float = 1e-5, err_msg: str = "") -> None:
    """``actual == desired`` bit for bit where :func:`sums_in_fixed_order`; under CUDA, to ``rel`` of
    the largest entry (the rounding of sums added in another order, not a looser model)."""
    if sums_in_fixed_order():
        np.testing.assert_array_equal(actual, desired, err_msg=err_msg)
    else:
        scale = float(np.max(np.abs(desired))) if np.size(desired) else 0.0
        np.testing.assert_allclose(actual, desired, rtol=0.0, atol=rel * scale, err_msg=err_msg)


def signal_when(argv: Sequence[str], ready: Callable[[subprocess.Popen], bool], signum: int, timeout: float = 60.0,
                poll: float = 0.005, **popen) -> Tuple[int, str]:
    """Start ``argv``, send it ``signum`` as soon as ``ready(process)`` holds (asked every ``poll`` s, for at
    most ``timeout`` s, while it runs) and wait for it to end: its exit status and standard error. The
    process is killed if it outlives the wait."""
    proc = subprocess.Popen(list(argv), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **popen)
    try:
        deadline = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < deadline:
            if ready(proc):
                proc.send_signal(signum)
                break
            time.sleep(poll)
        err = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, err


def sun_sky_probe() -> Probe:
    """Smooth sky gradient plus a small bright patch (a sun), 32 x 64: sharp and smooth lighting at once."""
    h, w = 32, 64
    y, x = np.mgrid[0:h, 0:w]
    data = np.stack([0.3 + 0.7 * (1 - y / h), 0.4 + 0.3 * x / w, 0.5 + 0.0 * x], -1)
    data[6:9, 20:23] = 40.0
    return Probe(data.astype(np.float32), source="synthetic")


def sky_probe(yaw_deg: float = 0.0, n_lights: int = 2) -> Probe:
    """A smooth sky with soft suns (64 x 128): strong directional light, cheap to integrate.

    ``n_lights`` > 2 adds smaller lamps spread over the sphere (seeded), so
    that the specular peak is observed from many normals.
    """
    h, w = 64, 128
    theta = (np.arange(h) + 0.5)[:, None] / h * np.pi
    phi = (np.arange(w) + 0.5)[None, :] / w * 2 * np.pi
    d = np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(phi), np.cos(theta) + 0 * phi,
                                     np.sin(theta) * np.sin(phi)), axis=-1)
    sky = np.clip(0.25 + 0.25 * d[..., 1:2], 0.05, None) * np.array([0.8, 0.9, 1.0])
    lights = [((0.5, 0.7, 0.5), 60.0, (1.0, 0.9, 0.7)), ((-0.8, 0.2, -0.3), 20.0, (0.6, 0.7, 1.0))]
    rng = np.random.default_rng(7)
    for _ in range(max(0, n_lights - 2)):
        lights.append((rng.normal(size=3), rng.uniform(5.0, 20.0), rng.uniform(0.5, 1.0, 3)))
    for direction, power, colour in lights:
        u = np.asarray(direction, float) / np.linalg.norm(direction)
        sky = sky + power * np.exp(-(1.0 - d @ u) / 0.01)[..., None] * np.asarray(colour)
    probe = Probe(sky.astype(np.float32), source="sky")
    return probe.rotated(euler_deg=(0, yaw_deg, 0)) if yaw_deg else probe


def independent_relight_floor(config: EvalConfig, material: str, probe_spec: str, seed: int,
                              resolution: int, grid: Tuple[int, int] = (8, 8)) -> float:
    """The relight floor recomputed outside the code under test: the truth and its exact reduction on
    ``grid`` rendered by the evaluation's renderer under ``probe_spec`` at ``seed``, and the
    reduction's relative RMS error (:func:`mi_bivariate.metrics.image_relative_rmse`)."""
    spec = resolve_materials([material])[0]
    truth = load_truth(spec)
    renderer, probe = Renderer(config, spec, cache_dir=None), load_probe(probe_spec)
    shot = renderer.render(truth, probe, probe_spec, resolution, seed, config.novel_spp)
    floor = renderer.render(BivariateBRDF.reduce(truth, n_t=grid[0], n_s=grid[1]), probe, probe_spec, resolution,
                            seed, config.novel_spp).image
    return metrics.image_relative_rmse(floor, shot.image, shot.mask)
