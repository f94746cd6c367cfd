"""mi_bivariate.lighting: the lighting matrix of Eqs. 3-5 against independent truths.

- a plain numpy implementation (tests/reference_lighting.py) with the same directions;
- the furnace: constant radiance 1 and a Lambertian table give rho;
- Mitsuba itself: L @ f against a converged render of the ``bivariate`` plugin, with
  negative controls showing that a mirrored probe, a dropped cosine or a wrong 2 pi / K
  factor would be caught.
"""

from __future__ import annotations

import dataclasses
import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import assert_same_sums, suite_variant, sums_in_fixed_order
from reference_lighting import lighting_matrix_reference, mis_lighting_matrix_reference

from mi_bivariate import capture, lighting
from mi_bivariate.capture import Observations
from mi_bivariate.coordinates import grid_nodes, half_diff_from_dirs, half_diff_from_st
from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.limits import MAX_SEED
from mi_bivariate.probes import Probe
from mi_bivariate.threads import jit_threads


def synthetic_probe(height: int = 64, width: int = 128) -> Probe:
    """Smooth, coloured, non-symmetric environment with three bright blobs."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    uu, vv = np.meshgrid(u, v)
    data = 0.2 + 0.8 * np.stack([uu, 1.0 - vv, 0.5 + 0.5 * np.sin(2 * np.pi * uu)], axis=-1)
    for cu, cv, r, a in [(0.3, 0.35, 0.05, 30.0), (0.62, 0.2, 0.08, 10.0), (0.8, 0.6, 0.04, 20.0)]:
        blob = np.exp(-((uu - cu) ** 2 + (vv - cv) ** 2) / r**2)
        data = data + a * blob[..., None] * np.array([1.0, 0.7, 0.4])
    return Probe(data.astype(np.float32))


def random_observations(m: int, seed: int) -> Observations:
    """Random normals with random views in front of them (n . v >= 0.05), grazing included."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(m, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(np.sum(n * v, axis=1, keepdims=True) < 0, -v, v)
    v = v + 0.06 * n
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[0] = n[0]  # the view along the normal: no view/normal plane
    return Observations(n, v, np.zeros((m, 3), np.float32), np.zeros(m, np.int32))


def specular_table(n_t: int = 32, n_s: int = 32) -> np.ndarray:
    """Coloured diffuse + a theta_h lobe (0.15 rad) with a Schlick-like theta_d rise, 1/sr."""
    theta_h, theta_d = half_diff_from_st(grid_nodes(n_s)[None, :], grid_nodes(n_t)[:, None])
    fresnel = 0.04 + 0.96 * (1.0 - np.cos(theta_d)) ** 5
    lobe = np.exp(-(theta_h / 0.15) ** 2) * (1.0 + 3.0 * fresnel)
    return (np.array([0.15, 0.1, 0.05]) / np.pi + 0.8 * lobe[..., None]).astype(np.float32)


def apply(L: np.ndarray, table: np.ndarray) -> np.ndarray:
    return np.einsum("mnc,nc->mc", L, table.reshape(-1, 3).astype(np.float64))


# ------------------------------------------------------------ reference

def test_matches_numpy_reference():
    obs = random_observations(20, seed=3)
    probe = synthetic_probe().rotated(euler_deg=(10.0, 40.0, -25.0))
    fast = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=500, seed=7, sampling="uniform")
    slow = lighting_matrix_reference(obs, probe, n_t=8, n_s=8, n_dirs=500, seed=7)
    assert fast.shape == (20, 64, 3) and fast.dtype == np.float32
    assert np.abs(fast - slow).max() <= 1e-5 * np.abs(slow).max()
    # Not a vacuous match: the entries are spread over the grid.
    assert np.count_nonzero(slow.sum(axis=2) > 0) > 0.5 * slow[..., 0].size


def test_mis_matches_numpy_reference():
    """The default sampling against its plain numpy implementation (tests/reference_lighting.py: the
    same lattice points and pooled environment samples, everything else computed independently in
    float64), on a smooth probe and on one whose bright pole row gets a band without the proxy;
    grazing rows and the view along the normal included."""
    from mi_bivariate.lighting import mis

    obs = random_observations(20, seed=3)
    poles = np.full((32, 64, 3), 0.05, np.float32)
    poles[0], poles[1] = 100.0, 0.0
    # measured: 9e-7, and 1.3-2.8e-5 (a pole row 2000x the next: float32 directions against that gradient)
    for probe, tolerance in ((synthetic_probe().rotated(euler_deg=(10.0, 40.0, -25.0)), 1e-5),
                             (Probe(poles).rotated(euler_deg=(70.0, 0.0, 20.0)), 1e-4)):
        fast = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=7)
        slow = mis_lighting_matrix_reference(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=7)
        assert np.abs(fast - slow).max() <= tolerance * np.abs(slow).max()
        assert np.count_nonzero(slow.sum(axis=2) > 0) > 0.5 * slow[..., 0].size
    assert mis.environment_proxy(probe).has_bands
    # Not a vacuous match: another seed (another realisation of the estimator) differs.
    other = mis_lighting_matrix_reference(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=8)
    assert np.abs(other - slow).max() > 1e-2 * np.abs(slow).max()


def test_mis_rows_of_each_probe_match_the_numpy_reference():
    """A job of two images under two probes (a map and a turned copy of it): each image's rows equal the
    numpy reference with that probe and that probe's pooled environment directions (stream p for probe
    p, so that the two images do not share their lattices), and not the other probe's stream."""
    base = random_observations(10, seed=3)
    stacked = capture.stack([base, base], probe_index=[0, 1])
    probes = [synthetic_probe(), synthetic_probe().rotated(euler_deg=(0.0, 70.0, 0.0))]
    L = lighting.lighting_matrix(stacked, probes, n_t=8, n_s=8, n_dirs=600, seed=7)
    for p, rows in enumerate((np.arange(10), np.arange(10, 20))):
        slow = mis_lighting_matrix_reference(stacked, probes[p], n_t=8, n_s=8, n_dirs=600, seed=7, rows=rows,
                                             stream=p)
        assert np.abs(L[rows] - slow).max() <= 1e-5 * np.abs(slow).max(), p
    other = mis_lighting_matrix_reference(stacked, probes[1], n_t=8, n_s=8, n_dirs=600, seed=7, rows=rows, stream=0)
    assert np.abs(L[rows] - other).max() > 1e-2 * np.abs(other).max()


def test_light_directions_are_uniform_hemisphere_pairs():
    obs = random_observations(3, seed=1)
    offsets = lighting.hemisphere_offsets(3, seed=0)
    dirs, cos_u = lighting.light_directions(obs.normals, obs.views, 4000, offsets)
    assert dirs.shape == (3, 4000, 3)
    assert np.allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    assert np.allclose(np.einsum("mkc,mc->mk", dirs, obs.normals), cos_u)
    assert cos_u.min() >= 0.0
    # Uniform in solid angle: cos theta is uniform, mean cos = 1/2, mean cos^2 = 1/3.
    assert abs(cos_u.mean() - 0.5) < 1e-3 and abs((cos_u**2).mean() - 1 / 3) < 1e-3
    # Each half is mirrored across the view/normal plane: same Rusinkiewicz angles.
    x, y, wo = lighting.row_frames(obs.normals, obs.views)
    local = np.stack([np.einsum("mkc,mc->mk", dirs, a) for a in (x, y, obs.normals)], axis=-1)
    th, _, td, _ = half_diff_from_dirs(local, np.broadcast_to(wo[:, None], local.shape))
    assert np.allclose(th[:, :2000], th[:, 2000:], atol=1e-9)
    assert np.allclose(td[:, :2000], td[:, 2000:], atol=1e-9)


def test_an_odd_number_of_directions_is_rounded_up_to_mirrored_pairs():
    """As documented (light_directions): K is rounded up to even, K = 2 P mirrored pairs, so 399 directions
    are the 400 of the uniform lattice, bit for bit, and not the 398 that rounding down would give."""
    obs = random_observations(6, seed=2)
    offsets = lighting.hemisphere_offsets(6, seed=0)
    assert lighting.light_directions(obs.normals, obs.views, 399, offsets)[0].shape == (6, 400, 3)
    probe = synthetic_probe()
    odd, even = (lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=k, seed=1, sampling="uniform")
                 for k in (399, 400))
    assert odd.max() > 0.0
    assert_same_sums(odd, even)
    below = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=398, seed=1, sampling="uniform")
    assert not np.array_equal(below, even)


@pytest.mark.parametrize("sampling", ["mis", "uniform"])
def test_deterministic_and_chunking_invariant(sampling):
    # chunk=7: eight chunks, each copied into L while the next one's kernel runs (lighting._fill)
    obs = random_observations(50, seed=5)
    probe = synthetic_probe()
    a = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=2000, seed=1, sampling=sampling)
    b = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=2000, seed=1, chunk=7, sampling=sampling)
    c = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=2000, seed=2, sampling=sampling)
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6 * a.max())
    assert not np.allclose(a, c, rtol=1e-3, atol=0)


def test_texel_matrix_chunking_invariant():
    obs = random_observations(50, seed=6)
    probe = synthetic_probe()
    a = lighting.texel_lighting_matrix(obs, probe, n_t=8, n_s=8, downsample=2)
    b = lighting.texel_lighting_matrix(obs, probe, n_t=8, n_s=8, downsample=2, chunk=7)
    assert a.max() > 0.0 and np.allclose(a, b, rtol=1e-5, atol=1e-6 * a.max())


def test_texel_matrix_uses_each_rows_probe_and_the_documented_downsampling():
    """Stacked images under constant probes 1 and 3: L is linear in the radiance, so the second image's
    rows are 3 times the first's, and both integrate the furnace (rho / pi gives rho times the radiance).
    ``downsample`` takes the largest factor up to it that divides the width: 8 and 6 on a 128-wide map
    are the map area-downsampled by 8 and by 4 (Probe.downsampled) at one texel per light."""
    base = random_observations(30, seed=2)
    stacked = capture.stack([base, base], probe_index=[0, 1])
    L = lighting.texel_lighting_matrix(stacked, [Probe.constant(1.0, 32), Probe.constant(3.0, 32)], n_t=8, n_s=8,
                                       downsample=1)
    np.testing.assert_allclose(L[30:], 3.0 * L[:30], rtol=1e-5, atol=1e-6 * L.max())
    rho = np.array([0.2, 0.5, 0.9])
    predicted = apply(L, np.broadcast_to(rho / np.pi, (8, 8, 3)))
    assert np.abs(predicted[:30] / rho - 1.0).max() < 3e-2  # a 32 x 64 map: coarse hemisphere edge
    probe = synthetic_probe()
    assert probe.width == 128
    for downsample, factor in ((8, 8), (6, 4)):
        got = lighting.texel_lighting_matrix(base, probe, n_t=8, n_s=8, downsample=downsample)
        expected = lighting.texel_lighting_matrix(base, probe.downsampled(factor), n_t=8, n_s=8, downsample=1)
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7 * expected.max())
    assert not np.allclose(got, lighting.texel_lighting_matrix(base, probe, n_t=8, n_s=8, downsample=1),
                           rtol=1e-3, atol=0)


def test_views_near_the_normal_match_the_numpy_reference():
    """Views within a degree of their normal (the middle of a sphere photo): the row frame's x axis
    follows the view's projection down to 1e-6 of it, so the mirrored pairs share their st points
    exactly; the numpy reference (its own frames, each direction's own angles) agrees."""
    rng = np.random.default_rng(14)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tangent = np.cross(n, rng.normal(size=(5, 3)))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    angle = np.array([1e-4, 5e-4, 2e-3, 5e-3, 1.5e-2])[:, None]
    v = np.cos(angle) * n + np.sin(angle) * tangent
    obs = Observations(n, v, np.zeros((5, 3), np.float32), np.zeros(5, np.int32))
    probe = synthetic_probe().rotated(euler_deg=(10.0, 40.0, -25.0))
    fast = lighting.lighting_matrix(obs, probe, n_t=16, n_s=16, n_dirs=2000, seed=7, sampling="uniform")
    slow = lighting_matrix_reference(obs, probe, n_t=16, n_s=16, n_dirs=2000, seed=7)
    assert np.abs(fast - slow).max() <= 1e-5 * np.abs(slow).max()


@pytest.mark.parametrize("sampling", ["mis", "uniform", "texel"])
def test_rows_depend_on_the_directions_of_normals_and_views_only(sampling):
    """Normals and views are directions: scaled by 0.5 and 3 (as a user's unnormalised vectors) they give
    the same matrix (the row frames normalise both; a view left unnormalised moved its st points)."""
    obs = random_observations(12, seed=13)
    scaled = dataclasses.replace(obs, normals=0.5 * obs.normals, views=3.0 * obs.views)
    probe = synthetic_probe()

    def matrix(o):
        if sampling == "texel":
            return lighting.texel_lighting_matrix(o, probe, n_t=8, n_s=8, downsample=4)
        return lighting.lighting_matrix(o, probe, n_t=8, n_s=8, n_dirs=400, seed=2, sampling=sampling)

    expected = matrix(obs)
    assert expected.max() > 0.0
    np.testing.assert_allclose(matrix(scaled), expected, rtol=0, atol=1e-5 * expected.max())


def test_chunk_rows_keep_the_target_within_budget_for_any_thread_count():
    # One copy of a chunk's scatter target on either backend (a lane per row on LLVM, atomics on
    # CUDA), so the rows per chunk do not depend on Dr.Jit's threads.
    threads = dr.thread_count()
    try:
        for n in (1, 2, 8, 64):
            dr.set_thread_count(n)
            rows = lighting._chunk_rows(32 * 32, None)
            assert rows * 32 * 32 * 16 <= lighting.CHUNK_BYTES
            assert rows * 32 * 32 * 16 > lighting.CHUNK_BYTES // 2
            assert lighting._chunk_rows(64 * 64, None) == rows // 4
    finally:
        dr.set_thread_count(threads)


@pytest.mark.parametrize("sampling", ["mis", "uniform", "texel"])
def test_lighting_matrix_is_the_same_bit_for_bit_for_any_threads_and_chunks(sampling):
    # "Runs are deterministic for a given seed": on the LLVM backend each element of L is summed by
    # one lane in one order, so neither the thread pool's schedule nor the chunking changes a bit
    # (rows without pixel footprints: a footprint block's seed follows the chunk size).
    # (Before, per-thread copies summed in schedule order: ~7% of the entries moved from call to call.)
    if not sums_in_fixed_order():
        pytest.skip("CUDA sums with atomics: equal to float32 rounding, not bit for bit")
    obs = random_observations(300, seed=8)
    probe = synthetic_probe()

    def matrix(chunk=None):
        if sampling == "texel":
            return lighting.texel_lighting_matrix(obs, probe, n_t=16, n_s=16, downsample=2, chunk=chunk)
        return lighting.lighting_matrix(obs, probe, n_t=16, n_s=16, n_dirs=3000, seed=4, sampling=sampling,
                                        chunk=chunk)

    threads = dr.thread_count()
    try:
        a = matrix()
        again = matrix()
        chunked = matrix(chunk=37)
        dr.set_thread_count(1)
        one_thread = matrix()
        dr.set_thread_count(max(4, threads))
        four_threads = matrix()
    finally:
        dr.set_thread_count(threads)
    assert a.max() > 0.0
    for name, other in (("again", again), ("chunk 37", chunked), ("1 thread", one_thread),
                        ("4 threads", four_threads)):
        assert np.array_equal(a, other), name


def test_stacked_probes_use_their_own_probe():
    base = random_observations(30, seed=2)
    probes = [synthetic_probe(), Probe.constant([1.0, 2.0, 3.0], 16)]
    stacked = capture.stack([base, base], probe_index=[0, 1])
    L = lighting.lighting_matrix(stacked, probes, n_t=8, n_s=8, n_dirs=8000)
    alone = lighting.lighting_matrix(base, probes[1], n_t=8, n_s=8, n_dirs=8000)
    # Rows are seeded by position, so compare the totals (quadrature-level agreement:
    # MIS at K = 8000 has ~1e-3 per-row error on this smooth integrand).
    assert np.allclose(L[30:].sum(axis=1), alone.sum(axis=1), rtol=5e-3)
    assert not np.allclose(L[:30].sum(axis=1), alone.sum(axis=1), rtol=0.1)


# --------------------------------------------------------------- furnace

@pytest.mark.parametrize("method", ["sampled", "mis", "texel"])
def test_furnace(method):
    geo = capture.SphereGeometry(64.0, 64.0, 60.0)
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), geo, n_normals=400,
                                           saturation=2.0)
    probe = Probe.constant(1.0, 32)
    if method == "sampled":
        L = lighting.lighting_matrix(obs, probe, n_dirs=32000, sampling="uniform")
        tol = 2e-4
    elif method == "mis":
        L = lighting.lighting_matrix(obs, probe, n_dirs=32000, sampling="mis")
        tol = 3e-3  # three stratified strategies, each with a third of the directions
    else:
        L = lighting.texel_lighting_matrix(obs, probe, downsample=1)
        tol = 3e-2  # a 32 x 64 map: coarse hemisphere edge
    rho = np.array([0.2, 0.5, 0.9])
    table = np.broadcast_to(rho / np.pi, (32, 32, 3))
    assert np.abs(apply(L, table) / rho - 1.0).max() < tol


def test_mis_is_unbiased_and_far_less_noisy_on_sharp_light_and_lobes():
    """Small bright sources and a sharp lobe: MIS agrees with uniform sampling at large K
    (no bias) and its two-seed difference is far smaller at equal K."""
    rng = np.random.default_rng(0)
    data = np.full((64, 128, 3), 0.05, np.float32)
    for _ in range(4):  # four 1-texel "windows" 1e4 brighter than the rest
        data[rng.integers(5, 30), rng.integers(0, 128)] = 500.0
    probe = Probe(data)
    geo = capture.SphereGeometry(64.0, 64.0, 60.0)
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), geo, n_normals=150,
                                           saturation=2.0)
    theta_h, _ = half_diff_from_st(grid_nodes(32)[None, :], grid_nodes(32)[:, None])
    lobe = np.broadcast_to(0.02 + 30.0 * np.exp(-(theta_h / 0.03) ** 2), (32, 32))
    table = lobe[..., None] * np.ones(3)

    def predict(sampling, k, seed):
        return apply(lighting.lighting_matrix(obs, probe, n_dirs=k, seed=seed, sampling=sampling), table)

    def rel(a, b):
        return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))

    mis = [predict("mis", 16000, s) for s in (1, 2)]
    uni = [predict("uniform", 16000, s) for s in (1, 2)]
    assert rel(mis[0], mis[1]) < 0.1 * rel(uni[0], uni[1])
    reference = predict("uniform", 1_000_000, 3)
    assert abs(mis[0].sum() / reference.sum() - 1) < 0.02
    assert rel(mis[0], reference) < rel(uni[0], reference)


def test_peak_lanes_weigh_at_most_their_own_strategy_allows():
    """A peak lane's balance weight is ``cos / sum_j K_j p_j``, so at most ``cos / (K_p p_peak)`` with
    ``p_peak`` the closed form at the lane's own sampled ``t = T u1`` (float64 here). A lattice point
    that wraps to ``u1 = 0`` in float32 (here made exact: 1024 peak points, shift 0.5 / 1024) is the
    mirror direction itself, where ``p_peak`` is infinite: its weight must be 0. Rebuilding the half
    vector from ``l + v`` found no component off the normal there and read ``p_peak = 0``: the lane
    got a uniform direction's weight at a sharp table's peak (spikes of up to 9.6% RMS in a
    tungsten-carbide prediction under uffizi_256, ``benchmarks/dirs_noise.py``)."""
    from mi_bivariate.lighting import kernels, mis

    obs = random_observations(6, seed=4)
    offsets = lighting.hemisphere_offsets(len(obs), seed=2)
    offsets[:3, 0] = 0.5 / 1024  # rows 0-2: lattice point 1023 lands on u1 = 1.0, which wraps to 0
    data = kernels._row_data(kernels._row_packets(obs.normals, obs.views, offsets))
    counts = mis.strategy_counts(4096)
    assert counts["peak"] == 1024
    probe = synthetic_probe()
    row, k, r, u1, u2 = kernels._lattice_lanes(data, len(obs), counts["peak"])
    lanes = mis._mis_lanes(data, len(obs), probe, "peak", counts)
    lz, weight = lanes[3].numpy().astype(np.float64), lanes[5].numpy().astype(np.float64)
    u1, sin_v, cos_v = (np.asarray(a.numpy(), np.float64) for a in (u1, r.sin_v, r.cos_v))
    assert np.count_nonzero(u1 == 0.0) == 3
    t = mis.PEAK_T_MAX * u1
    theta_h = 0.5 * np.pi * t**2
    v_dot_h = sin_v * np.sin(theta_h) * np.cos(2 * np.pi * u2.numpy()) + cos_v * np.cos(theta_h)
    with np.errstate(divide="ignore"):
        p_peak = 1.0 / (mis.PEAK_T_MAX * np.pi * t * 2 * np.pi * np.sin(theta_h) * 4 * v_dot_h)
    lit = (lz > 0) & (v_dot_h > 0)
    assert np.all(weight[~lit] == 0.0)
    bound = lz[lit] / (counts["peak"] * p_peak[lit])  # 0 where p_peak is infinite
    assert np.all(weight[lit] <= bound * (1 + 1e-4))
    assert np.all(weight[u1 == 0.0] == 0.0)
    # Not vacuous: away from the mirror direction the other strategies share the weight.
    far = lit & (u1 > 0.5)
    assert np.median(weight[far] * counts["peak"] * p_peak[far] / lz[far]) < 0.9


def test_pooled_environment_directions_are_the_per_row_estimator():
    """lighting_matrix reads the environment strategy's directions from a pool sampled once per
    lattice shift (lighting.mis.environment_pool). Per row it is the estimator of sampling the
    environment per row (_mis_chunk without a pool): with sharp light and a sharp lobe the two
    agree to their own seed-to-seed noise, both agree with a 10^6-direction uniform reference,
    and the pool is a function of the seed."""
    from mi_bivariate.lighting import kernels, mis

    rng = np.random.default_rng(5)
    data = np.full((64, 128, 3), 0.05, np.float32)
    for _ in range(4):
        data[rng.integers(5, 30), rng.integers(0, 128)] = 500.0
    probe = Probe(data)
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), capture.SphereGeometry(64.0, 64.0, 60.0),
                                           n_normals=150, saturation=2.0)
    theta_h, _ = half_diff_from_st(grid_nodes(32)[None, :], grid_nodes(32)[:, None])
    table = np.broadcast_to(0.02 + 30.0 * np.exp(-(theta_h / 0.03) ** 2), (32, 32))[..., None] * np.ones(3)

    def per_row(seed):
        packets = kernels._row_packets(obs.normals, obs.views, lighting.hemisphere_offsets(len(obs), seed))
        return apply(np.array(mis._mis_chunk(packets, probe, 32, 32, 16000)), table)

    def rel(a, b):
        return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))

    pooled = [apply(lighting.lighting_matrix(obs, probe, n_dirs=16000, seed=s), table) for s in (1, 2)]
    rows = [per_row(s) for s in (1, 2)]
    noise = rel(rows[0], rows[1])
    assert rel(pooled[0], pooled[1]) < 2.0 * noise
    assert rel(pooled[0], rows[0]) < 2.0 * noise
    reference = apply(lighting.lighting_matrix(obs, probe, n_dirs=1_000_000, seed=3, sampling="uniform"), table)
    for estimate in pooled + rows:  # measured: within 0.07% (a 5% error in the pool's radiance: 2%)
        assert abs(estimate.sum() / reference.sum() - 1) < 0.003
    a, b = (np.array(mis.environment_pool(probe, 100, seed)) for seed in (4, 4))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, np.array(mis.environment_pool(probe, 100, 5)))
    assert a.size == 100 * mis.ENV_SHIFTS * 8 and np.all(np.isfinite(a))


def test_environment_density_proxy_keeps_the_estimator_unbiased(monkeypatch):
    """The balance heuristic reads the environment's density as luminance(E) / Z (lighting.mis,
    EnvironmentProxy) rather than Mitsuba's pdf_direction. Any positive proxy keeps the estimator
    unbiased: with Z off by 20x either way every estimate still matches a 10^6-direction uniform
    reference (a lane that dropped its own q / p factor would not); with the true Z the noise is that
    of the exact density's heuristic (env_density="exact")."""
    from mi_bivariate.lighting import kernels, mis

    rng = np.random.default_rng(7)
    data = np.full((64, 128, 3), 0.05, np.float32)
    for _ in range(4):
        data[rng.integers(5, 30), rng.integers(0, 128)] = 500.0
    data[40:44, 60:70] = (30.0, 2.0, 0.5)  # a coloured source
    probe = Probe(data)
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), capture.SphereGeometry(64.0, 64.0, 60.0),
                                           n_normals=150, saturation=2.0)
    theta_h, _ = half_diff_from_st(grid_nodes(32)[None, :], grid_nodes(32)[:, None])
    table = np.broadcast_to(0.02 + 30.0 * np.exp(-(theta_h / 0.03) ** 2), (32, 32))[..., None] * np.ones(3)
    reference = apply(lighting.lighting_matrix(obs, probe, n_dirs=1_000_000, seed=3, sampling="uniform"), table)

    def rows(seed, **kwargs):
        packets = kernels._row_packets(obs.normals, obs.views, lighting.hemisphere_offsets(len(obs), seed))
        return apply(np.array(mis._mis_chunk(packets, probe, 32, 32, 16000, **kwargs)), table)

    def rel(a, b):
        return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))

    import mitsuba as mi

    # The weights only change the variance (any positive proxy is unbiased): Mitsuba's own are checked here.
    assert np.allclose(mis.LUMINANCE_WEIGHTS, [mi.luminance(mi.Color3f(*map(float, e)))[0] for e in np.eye(3)],
                       atol=1e-6)
    env = mis.environment_proxy(probe)
    scale = env.scale
    np.testing.assert_allclose(scale, np.sum((data.astype(float) @ mis.LUMINANCE_WEIGHTS) * probe.solid_angles()))
    exact = [rows(s, env_density="exact") for s in (1, 2)]
    proxy = [rows(s) for s in (1, 2)]
    assert rel(proxy[0], proxy[1]) < 1.3 * rel(exact[0], exact[1])
    for estimate in exact + proxy:  # measured: within 0.03% (dropping the lanes' q / p below: 0.3%)
        assert abs(estimate.sum() / reference.sum() - 1) < 0.002
    for factor in (0.05, 20.0):
        off = dataclasses.replace(env, scale=scale * factor)
        monkeypatch.setattr(mis, "environment_proxy", lambda _probe, off=off: off)
        for seed in (1, 2):  # measured: within 0.05%; without the environment lanes' q / p: 83% off
            assert abs(rows(seed).sum() / reference.sum() - 1) < 0.003, factor
    with pytest.raises(ValueError, match="env_density"):
        rows(1, env_density="other")


def test_environment_density_proxy_is_unbiased_at_the_poles():
    """Mitsuba weighs the map's rows by sin theta, 0 on the pole rows: between a bright pole row and a
    black next row the environment is never sampled although the radiance is not 0. The proxy is 0
    there (lighting.mis.EnvironmentProxy), so the uniform and peak lanes carry it: the estimate matches a
    10^6-direction uniform reference, also with the map turned (a proxy positive there: -44%)."""
    from mi_bivariate.lighting import mis

    data = np.full((64, 128, 3), 0.05, np.float32)
    data[0] = data[-1] = 100.0
    data[1] = data[-2] = 0.0
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), capture.SphereGeometry(64.0, 64.0, 60.0),
                                           n_normals=150, saturation=2.0)
    for probe in (Probe(data), Probe(data).rotated(euler_deg=(0.0, 0.0, 90.0))):
        env = mis.environment_proxy(probe)
        np.testing.assert_allclose(env.axis, probe.to_world[:3, 1], atol=1e-12)
        assert env.cos_top == env.cos_bottom and math.cos(math.pi / 63) > env.cos_top > math.cos(1.05 * math.pi / 63)
        reference = lighting.lighting_matrix(obs, probe, n_dirs=1_000_000, seed=3, sampling="uniform").sum()
        estimate = lighting.lighting_matrix(obs, probe, n_dirs=16000, seed=1).sum()
        assert abs(estimate / reference - 1) < 0.02, estimate / reference
    # A smooth map (every shared probe) needs no band: the kernel is the plain proxy's.
    smooth = data.copy()
    smooth[1] = smooth[-2] = 60.0
    assert not mis.environment_proxy(Probe(smooth)).has_bands


def test_polar_bands_of_the_shared_probes(data_dir_optional):
    """The default input probe's pole rows match their neighbours: its lighting matrices use the plain
    proxy everywhere. grace_256's last-but-one row has black texels below a lit pole row: its bottom
    band gets no proxy (lighting.mis.EnvironmentProxy), the case the test above builds."""
    from mi_bivariate.lighting import mis
    from mi_bivariate.probes import SHARED_PROBES, shared_probe

    if data_dir_optional is None:
        pytest.skip("needs the shared probes (MI_BIVARIATE_DATA)")
    bands = {}
    for name in SHARED_PROBES:
        env = mis.environment_proxy(shared_probe(name, data_dir_optional))
        bands[name] = (env.cos_top, env.cos_bottom)
    assert bands["grace_latlong_1k"] == (2.0, 2.0)
    assert bands["grace_256"][0] == 2.0 and bands["grace_256"][1] < 1.0
    assert sum(b != (2.0, 2.0) for b in bands.values()) == 1, bands


def test_rows_pick_their_pooled_shift_from_bits_independent_of_their_lattice_shift():
    """The pooled environment set a row reads depends on frac(4096 shift_1) only, not on the
    first bits of shift_1 that place its uniform and peak lattices: three rows with one normal,
    (a) and (c) sharing the pooled slot but not the first bits, (a) and (b) the reverse."""
    from mi_bivariate.lighting import kernels, mis

    probe = synthetic_probe()
    normal, view = np.array([[0.3, 0.2, 0.93]]), np.array([[0.0, 0.0, 1.0]])
    shifts = np.array([[0.25 + 0.1 / 4096, 0.5], [0.25 + 0.6 / 4096, 0.5], [0.75 + 0.1 / 4096, 0.5]], np.float32)
    fine = np.float64(shifts[:, 0]) * 4096
    slots = np.minimum(((fine - np.floor(fine)) * mis.ENV_SHIFTS).astype(int), mis.ENV_SHIFTS - 1)
    assert slots[0] == slots[2] != slots[1] and int(64 * shifts[0, 0]) == int(64 * shifts[1, 0])
    packets = kernels._row_packets(np.repeat(normal, 3, 0), np.repeat(view, 3, 0), shifts)
    only_environment = {"environment": 1.0}
    pool = mis.environment_pool(probe, 400, seed=2)
    rows = np.array(mis._mis_chunk(packets, probe, 8, 8, 400, fractions=only_environment, pool=pool))
    np.testing.assert_allclose(rows[0], rows[2], rtol=1e-6, atol=1e-7 * rows.max())
    assert np.abs(rows[0] - rows[1]).max() > 1e-3 * rows.max()
    # Another probe stream draws other shifts.
    assert not np.array_equal(np.array(pool), np.array(mis.environment_pool(probe, 400, seed=2, stream=1)))


def test_pool_too_big_falls_back_to_per_row_sampling(monkeypatch):
    """Past lighting.mis.POOL_BYTES the environment is sampled per row: lighting_matrix then
    equals the per-row sampler (chunked differently, so up to float summation order)."""
    from mi_bivariate.lighting import kernels, mis

    obs = random_observations(30, seed=4)
    probe = synthetic_probe()
    monkeypatch.setattr(lighting, "POOL_BYTES", 0)
    got = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=6)
    packets = kernels._row_packets(obs.normals, obs.views, lighting.hemisphere_offsets(len(obs), 6))
    expected = np.array(mis._mis_chunk(packets, probe, 8, 8, 600))
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6 * expected.max())
    monkeypatch.undo()
    pooled = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=6)
    assert np.abs(pooled - expected).max() > 1e-4 * expected.max()  # the pool is another realisation


# ----------------------------------------------------- texel quadrature

def test_texel_quadrature_accuracy():
    """Texel quadrature (every texel of a 64 x 128 probe one light) against the sampled L,
    on a smooth and a sharp table (numbers for a real probe: benchmarks/bench_recovery.py)."""
    geo = capture.SphereGeometry(64.0, 64.0, 60.0)
    obs = capture.observations_from_sphere(np.ones((128, 128, 3), np.float32), geo, n_normals=400,
                                           saturation=2.0)
    probe = synthetic_probe()
    sampled = lighting.lighting_matrix(obs, probe, n_dirs=64000)
    texel = lighting.texel_lighting_matrix(obs, probe, downsample=1)
    for table, tol in ((np.broadcast_to(np.array([0.3, 0.2, 0.1]) / np.pi, (32, 32, 3)), 0.02),
                       (specular_table(), 0.08)):
        a, b = apply(sampled, table), apply(texel, table)
        assert np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(a**2)) < tol


# -------------------------------------------------------- bad input

def test_bad_input():
    obs = random_observations(5, seed=0)
    with pytest.raises(InputError, match="probe 1"):
        lighting.lighting_matrix(obs.with_probe_index(1), [synthetic_probe()])
    back = Observations(obs.normals, -obs.views, obs.values, obs.probe_index)
    with pytest.raises(InputError, match="face away"):
        lighting.lighting_matrix(back, synthetic_probe())
    with pytest.raises(InputError, match="too small"):
        lighting.lighting_matrix(obs, synthetic_probe(), n_t=1)


def _edge_on(obs: Observations) -> Observations:
    """``obs`` with row 2 seen exactly edge-on (n . v = 0: a view along a tangent)."""
    normals, views = obs.normals.copy(), obs.views.copy()
    normals[2], views[2] = (0.0, 0.0, 1.0), (0.6, 0.8, 0.0)
    return dataclasses.replace(obs, normals=normals, views=views)


def _with_nan(obs: Observations, name: str) -> Observations:
    value = getattr(obs, name).copy()
    value[3, 1] = np.nan
    return dataclasses.replace(obs, **{name: value})


@pytest.mark.parametrize("front_door", ["lighting_matrix", "texel_lighting_matrix"])
@pytest.mark.parametrize("make, match", [
    (lambda o: dataclasses.replace(o, probe_index=np.array([0, 0, -1, 1, 0], np.int32)),
     r"^probes: the observations refer to probe -1 but 2 probe\(s\) were given"),
    (lambda o: _with_nan(o, "normals"), "^obs: the observations have non-finite normals or views"),
    (lambda o: _with_nan(o, "views"), "^obs: the observations have non-finite normals or views"),
    (_edge_on, r"^obs: some observed normals face away from their view \(n \. v <= 0\)"),
], ids=["negative probe index", "NaN normal", "NaN view", "edge-on view"])
def test_front_doors_refuse_rows_they_cannot_light(front_door, make, match):
    """Rows no lighting matrix can hold are refused, each with its one InputError, before any kernel: a
    negative probe index (numpy would silently light the row with the last probe; the message named the
    largest index, a valid one), a NaN normal or view (a NaN row, then a NaN table), a view at n . v = 0
    exactly (documented as refused: <= 0)."""
    obs = random_observations(5, seed=0)
    probes = [synthetic_probe(), Probe.constant(1.0, 16)]
    with pytest.raises(InputError, match=match):
        getattr(lighting, front_door)(make(obs), probes, n_t=4, n_s=4)


def test_lighting_matrix_size_limit_is_the_matrix_it_would_allocate(monkeypatch):
    """The refusal of a too-big lighting matrix counts the bytes of the (M, N, 3) float32 it returns:
    a limit of exactly L.nbytes is met, one byte less is refused (a limit counted at 2 bytes a value
    would let twice the memory through)."""
    obs = random_observations(5, seed=0)
    L = lighting.texel_lighting_matrix(obs, Probe.constant(1.0, 16), n_t=4, n_s=4)
    for front_door in (lighting.lighting_matrix, lighting.texel_lighting_matrix):
        monkeypatch.setattr(lighting, "MAX_LIGHTING_BYTES", L.nbytes)
        assert front_door(obs, Probe.constant(1.0, 16), n_t=4, n_s=4).nbytes == L.nbytes
        monkeypatch.setattr(lighting, "MAX_LIGHTING_BYTES", L.nbytes - 1)
        with pytest.raises(InputError, match=r"^obs: the lighting matrix of 5 rows x 16 nodes would take"):
            front_door(obs, Probe.constant(1.0, 16), n_t=4, n_s=4)


@pytest.mark.parametrize("kwargs, named", [
    ({"seed": -1}, "seed"), ({"seed": 1.5}, "seed"), ({"seed": 2**40}, "seed"),
    ({"n_t": 32.5}, "n_t"), ({"n_s": "8"}, "n_s"), ({"n_dirs": 300.7}, "n_dirs"), ({"n_dirs": 1}, "n_dirs"),
    ({"chunk": 0}, "chunk"), ({"chunk": 2.5}, "chunk"), ({"sampling": "bad"}, "sampling"),
    ({"occluder": "scene.xml"}, "occluder")])
def test_front_door_names_the_bad_argument(kwargs, named):
    """lighting_matrix refuses each bad argument before any work with an InputError that names it
    (no numpy or Dr.Jit error from deep inside, no silent rounding of 300.7 directions)."""
    obs = random_observations(5, seed=0)
    with pytest.raises(InputError, match=f"^{named}: "):
        lighting.lighting_matrix(obs, synthetic_probe(), **{"n_dirs": 300, **kwargs})


@pytest.mark.parametrize("front_door", ["lighting_matrix", "texel_lighting_matrix"])
def test_front_doors_refuse_what_is_not_observations(front_door):
    image = np.ones((16, 16, 3), np.float32)
    with pytest.raises(InputError, match="^obs: must be Observations"):
        getattr(lighting, front_door)(image, synthetic_probe())
    with pytest.raises(InputError, match="^downsample: "):
        lighting.texel_lighting_matrix(random_observations(5, seed=0), synthetic_probe(), downsample=0)


# ------------------------------------------------------- model agreement

def test_model_agreement_with_mitsuba(data_dir_optional):
    """L @ f matches a converged render of the bivariate plugin, to the Monte Carlo noise.

    Pins envmap orientation, frames, the cosine and the 2 pi / K normalisation at once;
    the negative controls show each would be caught."""
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.render import render_sphere

    if data_dir_optional is not None:
        from mi_bivariate.probes import shared_probe

        probe = shared_probe("grace_latlong_1k", data_dir_optional)
    else:
        probe = synthetic_probe()
    table = specular_table()
    renders = [render_sphere(BivariateBRDF(table), probe, resolution=96, spp=256, seed=s) for s in (1, 2)]
    image = 0.5 * (renders[0].image + renders[1].image)
    obs = capture.observations_from_sphere(image, renders[0].geometry, n_normals=1000, max_view_angle_deg=70)
    rows, cols = obs.pixels.T
    noise = 0.5 * (renders[0].image - renders[1].image)[rows, cols]  # std of the two-render mean
    noise_rms = np.sqrt(np.mean(noise**2))

    L = lighting.lighting_matrix(obs, probe, n_dirs=32000)
    predicted = apply(L, table)

    def rms_error(p: np.ndarray) -> float:
        return float(np.sqrt(np.mean((obs.values - p) ** 2)))

    error = rms_error(predicted)
    assert error < 1.5 * noise_rms, (error, noise_rms)
    assert abs(obs.values.sum() / predicted.sum() - 1.0) < 0.01

    # Negative controls. A mirrored environment (orientation wrong):
    mirrored = Probe(np.ascontiguousarray(probe.data[:, ::-1]), probe.to_world)
    assert rms_error(apply(lighting.lighting_matrix(obs, mirrored, n_dirs=32000), table)) > 8 * error
    # A wrong normalisation (e.g. 2 pi / K off by 5%) shows in the total:
    assert abs(obs.values.sum() / (1.05 * predicted).sum() - 1.0) > 0.03
    # A dropped cosine (reference implementation without it, on a subset of rows):
    sub = np.arange(0, len(obs), 10)
    with_cos = lighting_matrix_reference(obs, probe, n_dirs=8000, rows=sub)
    without = lighting_matrix_reference(obs, probe, n_dirs=8000, rows=sub, cosine=False)
    err_with = np.sqrt(np.mean((obs.values[sub] - apply(with_cos, table)) ** 2))
    err_without = np.sqrt(np.mean((obs.values[sub] - apply(without, table)) ** 2))
    assert err_without > 5 * err_with


def _sphere_scene(centre, radius):
    return mi.load_dict({"type": "scene", "ball": {"type": "sphere", "center": list(centre), "radius": radius}})


@pytest.mark.parametrize("sampling", ["mis", "uniform"])
def test_occluders_follow_their_images_and_skip_rows_without_positions(sampling):
    """Closed forms of visibility: a tiny ball far away blocks (essentially) nothing, a ball that encloses
    the surface points blocks every shadow ray. With the occluders [far, enclosing, far] per image, the
    rows of images 0 and 2 equal the unoccluded rows, those of image 1 are 0, except image 1's rows
    without a surface position (NaN), which trace no shadow rays and equal their unoccluded rows."""
    rng = np.random.default_rng(11)
    base = random_observations(24, seed=6)
    positions = rng.uniform(-0.5, 0.5, size=(24, 3))
    positions[[9, 13]] = np.nan
    obs = dataclasses.replace(base, image_index=np.repeat(np.arange(3, dtype=np.int32), 8), positions=positions)
    far, enclosing = _sphere_scene((100.0, 100.0, 100.0), 0.01), _sphere_scene((0.0, 0.0, 0.0), 5.0)
    probe = synthetic_probe()
    kwargs = dict(n_t=8, n_s=8, n_dirs=400, seed=1, sampling=sampling)
    free = lighting.lighting_matrix(obs, probe, **kwargs)
    L = lighting.lighting_matrix(obs, probe, occluder=[far, enclosing, far], **kwargs)
    assert free.max() > 0.0
    lit = np.r_[np.arange(8), 9, 13, np.arange(16, 24)]
    np.testing.assert_allclose(L[lit], free[lit], rtol=1e-6, atol=1e-7 * free.max())
    shadowed = np.setdiff1d(np.arange(8, 16), [9, 13])
    assert np.all(L[shadowed] == 0.0)


def test_shadow_rays_leave_from_the_geometric_normal_side():
    """A plane cannot shadow a point on itself: each shadow ray leaves from the side of the face its
    direction points to (offset along the geometric normal, as Mitsuba's spawn_ray), so rows on a
    rectangle whose shading normals lean 40 degrees from its face are not darkened by it. Offset along the
    shading normal, the rays of the wedge between the two horizons would start above the face and hit it."""
    rng = np.random.default_rng(12)
    m = 16
    lean = np.radians(40.0)
    azimuth = rng.uniform(0.0, 2.0 * np.pi, m)
    normals = np.stack([np.sin(lean) * np.cos(azimuth), np.sin(lean) * np.sin(azimuth), np.full(m, np.cos(lean))], -1)
    positions = np.c_[rng.uniform(-0.5, 0.5, size=(m, 2)), np.zeros(m)]
    geometric = np.tile([0.0, 0.0, 1.0], (m, 1))
    obs = Observations(normals, normals.copy(), np.zeros((m, 3), np.float32), np.zeros(m, np.int32),
                       positions=positions, geometric_normals=geometric)
    plane = mi.load_dict({"type": "scene", "face": {"type": "rectangle",
                                                    "to_world": mi.ScalarTransform4f().scale([10.0, 10.0, 1.0])}})
    probe = synthetic_probe()
    kwargs = dict(n_t=8, n_s=8, n_dirs=400, seed=2, sampling="uniform")
    free = lighting.lighting_matrix(obs, probe, **kwargs)
    L = lighting.lighting_matrix(obs, probe, occluder=plane, **kwargs)
    assert free.max() > 0.0
    np.testing.assert_allclose(L, free, rtol=1e-6, atol=1e-7 * free.max())


def _normals_and_views(count: int, spread: float, seed: int):
    """``count`` random unit normals and unit views about them (``spread``: the views' scatter; a view that
    would graze or face away is the normal itself): ``((count, 3), (count, 3))``."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = n + spread * rng.normal(size=(count, 3))
    v = np.where(np.sum(n * v, axis=1, keepdims=True) < 0.1, n, v)
    return n, v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("sampling", ["mis", "uniform"])
def test_a_convex_object_does_not_shadow_itself(sampling):
    """Rows on the surface of the occluder itself, a ball, with positions and no geometric normals (their
    shading normals stand in): no light direction of a normal's hemisphere re-enters a convex object, so
    the matrix equals the unoccluded one. Shadow rays that left the surface without spawn_ray's offset
    hit the ball they start on."""
    n, v = _normals_and_views(16, spread=0.8, seed=15)
    obs = Observations(n, v, np.zeros((16, 3), np.float32), np.zeros(16, np.int32), positions=0.7 * n)
    probe = synthetic_probe()
    kwargs = dict(n_t=8, n_s=8, n_dirs=400, seed=3, sampling=sampling)
    free = lighting.lighting_matrix(obs, probe, **kwargs)
    L = lighting.lighting_matrix(obs, probe, occluder=_sphere_scene((0.0, 0.0, 0.0), 0.7), **kwargs)
    assert free.max() > 0.0
    np.testing.assert_allclose(L, free, rtol=1e-6, atol=1e-7 * free.max())


def test_geometric_normals_are_directions_and_a_zero_or_nan_one_is_refused():
    """The shadow rays leave a row's position offset along its geometric normal (spawn_ray: the normal times
    an epsilon), and the kernels took the geometric normals as given while they normalise the shading ones:
    a zero one left the ray on the ball it starts from (the rows of a convex ball came out shadowed by
    it), a NaN one started it at NaN. Now such rows are refused, and any other length is a direction: rows
    on the ball with geometric normals 3 n give the matrix of n, which is the unoccluded one."""
    n, v = _normals_and_views(12, spread=0.5, seed=16)
    ball, probe = _sphere_scene((0.0, 0.0, 0.0), 0.7), synthetic_probe()
    kwargs = dict(n_t=8, n_s=8, n_dirs=200, seed=4, sampling="uniform")

    def rows(geometric):
        return Observations(n, v, np.zeros((12, 3), np.float32), np.zeros(12, np.int32), positions=0.7 * n,
                            geometric_normals=geometric)

    free = lighting.lighting_matrix(rows(n), probe, **kwargs)
    unit = lighting.lighting_matrix(rows(n), probe, occluder=ball, **kwargs)
    np.testing.assert_allclose(unit, free, rtol=1e-6, atol=1e-7 * free.max())
    np.testing.assert_array_equal(lighting.lighting_matrix(rows(3.0 * n), probe, occluder=ball, **kwargs), unit)
    for bad in (0.0, np.nan):
        geometric = n.copy()
        geometric[5] = bad
        with pytest.raises(InputError, match="zero or non-finite geometric normal") as info:
            lighting.lighting_matrix(rows(geometric), probe, occluder=ball, **kwargs)
        assert info.value.source == "obs"


@pytest.fixture(scope="module")
def data_dir_optional():
    """The shared data folder when MI_BIVARIATE_DATA is set, else None (synthetic probe)."""
    value = os.environ.get("MI_BIVARIATE_DATA")
    return value if value and os.path.isdir(value) else None


# ------------------------------------------------------------ pixel footprints

def test_footprint_model_predicts_area_integrated_pixels():
    """A small sphere (24 px image, radius 10.8 px: a pixel spans 5-15 degrees of normals) imaged like a
    camera (the reference renderer averaging 8 x 8 sub-pixel centres, an independent implementation):
    the pixel-footprint model predicts every pixel to the quadrature noise, the centre normal does not."""
    import mitsuba as mi

    from mi_bivariate import reference, render
    from mi_bivariate.bivariate import BivariateBRDF

    table = specular_table()
    probe = synthetic_probe()
    plugin = mi.load_dict(render.bsdf_dict(BivariateBRDF(table)))
    shot = reference.render_reference(plugin, probe, resolution=24, seed=0, subpixels=8,
                                      directions=reference.scaled_directions(0.2))
    kwargs = dict(n_normals=4000, max_view_angle_deg=88.0, seed=0)
    centre = capture.observations_from_sphere(shot.image, shot.geometry, **kwargs)
    fp = capture.observations_from_sphere(shot.image, shot.geometry, footprint=1.0, **kwargs)
    np.testing.assert_array_equal(centre.pixels, fp.pixels)
    assert len(centre) > 250 and len(np.unique(fp.footprint_rows)) == len(fp)

    def error(obs: Observations) -> float:
        pred = apply(lighting.lighting_matrix(obs, probe, n_dirs=16384, seed=1), table)
        return float(np.sqrt(np.mean((pred - obs.values) ** 2) / np.mean(obs.values.astype(float) ** 2)))

    err_centre, err_fp = error(centre), error(fp)
    assert err_fp < 0.002 and err_fp < 0.1 * err_centre, (err_fp, err_centre)  # measured 0.0004 vs 0.0195


def test_footprints_follow_subset_and_stack():
    geo = SphereGeometry(32.0, 32.0, 28.0)
    image = np.ones((64, 64, 3), np.float32)
    obs = capture.observations_from_sphere(image, geo, n_normals=3000, max_view_angle_deg=88.0, footprint=2.0)
    rows = np.unique(obs.footprint_rows)
    keep = np.zeros(len(obs), bool)
    keep[rows[::2]] = True
    keep[:10] = True
    sub = obs.subset(keep)
    old_of_new = np.flatnonzero(keep)
    for r in np.unique(sub.footprint_rows):
        np.testing.assert_array_equal(sub.footprint_normals[sub.footprint_rows == r],
                                      obs.footprint_normals[obs.footprint_rows == old_of_new[r]])
    both = capture.stack([obs, sub])
    assert len(both.footprint_rows) == len(obs.footprint_rows) + len(sub.footprint_rows)
    np.testing.assert_array_equal(both.footprint_rows[len(obs.footprint_rows):], sub.footprint_rows + len(obs))
    # the sub-pixel normals of a pixel average to (about) its centre normal
    r = rows[-1]
    mean = obs.footprint_normals[obs.footprint_rows == r].mean(axis=0)
    assert np.degrees(np.arccos(np.dot(mean / np.linalg.norm(mean), obs.normals[r]))) < 2.0


def test_footprint_rows_are_means_of_their_sub_rows_in_both_quadratures():
    """Each footprint row of L equals the mean of the rows its sub-pixel normals get on their own
    (with the texel quadrature, which is deterministic), and centre rows are untouched."""
    geo = SphereGeometry(20.0, 20.0, 17.0)
    obs = capture.observations_from_sphere(np.ones((40, 40, 3), np.float32), geo, n_normals=800,
                                           max_view_angle_deg=85.0, footprint=6.0)
    probe = synthetic_probe()
    L = lighting.texel_lighting_matrix(obs, probe, n_t=8, n_s=8)
    plain = lighting.texel_lighting_matrix(capture.Observations(obs.normals, obs.views, obs.values,
                                                                obs.probe_index), probe, n_t=8, n_s=8)
    fp = np.unique(obs.footprint_rows)
    centre = np.setdiff1d(np.arange(len(obs)), fp)
    assert len(fp) > 10 and len(centre) > 10
    np.testing.assert_allclose(L[centre], plain[centre], rtol=1e-5, atol=1e-7)  # float32 order of other chunks
    sub = capture.Observations(obs.footprint_normals, obs.views[obs.footprint_rows], obs.values[obs.footprint_rows],
                               obs.probe_index[obs.footprint_rows])
    L_sub = lighting.texel_lighting_matrix(sub, probe, n_t=8, n_s=8)
    for r in fp[:: max(1, len(fp) // 20)]:
        np.testing.assert_allclose(L[r], L_sub[obs.footprint_rows == r].mean(axis=0), rtol=1e-5, atol=1e-7)
    assert np.abs(L[fp] - plain[fp]).max() > 1e-3 * np.abs(plain[fp]).max()   # footprints change them
    L_mis = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=2000)
    assert np.all(np.isfinite(L_mis)) and np.all(L_mis >= 0)


@pytest.mark.parametrize("seed", [MAX_SEED - 1, MAX_SEED])
def test_footprint_rows_take_any_valid_seed(seed):
    """The footprint blocks draw their directions from seed + 1 + block, wrapped into the seeds' range: a
    valid seed near MAX_SEED is taken (it was refused as "seed: must be an integer from 0 to 4294967295,
    got 4294967296"), and every row, footprint ones included, still integrates the furnace: a Lambertian
    table rho / pi under constant radiance 1 gives rho."""
    geo = SphereGeometry(20.0, 20.0, 17.0)
    obs = capture.observations_from_sphere(np.full((40, 40, 3), 0.5, np.float32), geo, n_normals=800,
                                           max_view_angle_deg=85.0, footprint=6.0)
    assert len(np.unique(obs.footprint_rows)) > 10
    rho = np.array([0.2, 0.5, 0.9])
    L = lighting.lighting_matrix(obs, Probe.constant(1.0, 16), n_t=8, n_s=8, n_dirs=2000, seed=seed, chunk=8,
                                 sampling="uniform")
    assert np.abs(apply(L, np.broadcast_to(rho / np.pi, (8, 8, 3))) / rho - 1.0).max() < 1e-3


def test_mis_masked_lookups_change_no_bit(monkeypatch):
    """The MIS kernels read no texels for directions below the horizon (masked lookups): their rows
    equal, bit for bit (to float32 rounding under CUDA's atomics), those with every
    direction looked up."""
    from mi_bivariate.lighting import kernels, mis

    obs = random_observations(40, seed=8)
    probe = synthetic_probe()
    packets = kernels._row_packets(obs.normals, obs.views, lighting.hemisphere_offsets(len(obs), 3))
    looked_up = Probe.eval_dr
    with jit_threads(1):  # one accumulation order under CUDA too (its atomics still vary)
        got = np.array(mis._mis_chunk(packets, probe, 8, 8, 600))
        monkeypatch.setattr(Probe, "eval_dr", lambda self, d, active=True: looked_up(self, d))
        expected = np.array(mis._mis_chunk(packets, probe, 8, 8, 600))
    assert np.any(got > 0)
    assert_same_sums(got, expected)


@pytest.mark.parametrize("sampling", ["mis", "texel"])
def test_skipping_directions_below_the_horizon_changes_no_bit(monkeypatch, sampling):
    """The kernels jump over a lane's work where its light direction is below the horizon
    (kernels.above_horizon: the pooled environment directions, the texels); the matrix equals, bit
    for bit, the one with every lane's work run (where such lanes add 0 through their masks).
    The same skip with a wrong test (the horizon at cos 0.1) changes it."""
    from mi_bivariate.lighting import kernels, mis

    obs = random_observations(64, seed=9)
    probe = synthetic_probe()

    def matrix():
        with jit_threads(1):  # one accumulation order under CUDA too (its atomics still vary)
            if sampling == "texel":
                return lighting.texel_lighting_matrix(obs, probe, n_t=8, n_s=8, downsample=4)
            return lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=800, seed=3)

    skipped = matrix()
    for module in (kernels, mis):
        monkeypatch.setattr(module, "above_horizon", lambda lz, work: work())
    assert_same_sums(skipped, matrix())
    for module in (kernels, mis):
        monkeypatch.setattr(module, "above_horizon", lambda lz, work: dr.if_stmt(
            args=(), cond=lz > 0.1, true_fn=work, false_fn=lambda: None))
    assert np.abs(matrix() - skipped).max() > 1e-3 * np.abs(skipped).max()


@pytest.mark.parametrize("bits", [8, 10, 16])
def test_morton_key_interleaves_the_octahedral_cells(bits):
    """kernels.morton_key against a plain numpy version (bit by bit interleaving of the octahedral
    map's cell indices); zero and non-finite vectors get the key of the map's centre."""
    from mi_bivariate.lighting import kernels

    d = np.random.default_rng(bits).normal(size=(20000, 3)).astype(np.float32)
    d[:3] = [[0, 0, 1], [0, 0, -1], [1, -1, 0]]
    n = d / np.abs(d).sum(axis=1, keepdims=True)
    sign = np.where(n[:, :2] >= 0, 1.0, -1.0).astype(np.float32)
    oct_xy = np.where(n[:, 2:] >= 0, n[:, :2], (1 - np.abs(n[:, ::-1][:, 1:])) * sign)
    scale = 2**bits - 1
    q = np.clip((oct_xy + 1) * np.float32(0.5 * scale), 0, scale).astype(np.uint64)
    expected = np.zeros(len(d), np.uint64)
    for b in range(bits):
        expected |= ((q[:, 0] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b)
        expected |= ((q[:, 1] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b + 1)
    got = np.array(kernels.morton_key(mi.Vector3f(np.ascontiguousarray(d.T)), bits)).astype(np.uint64)
    assert np.mean(got == expected) > 0.999   # a cell boundary may round the other way in float32
    assert got.max() < 2 ** (2 * bits)
    odd = kernels.morton_key(mi.Vector3f([0.0, np.nan, np.inf], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]), bits)
    centre = kernels.morton_key(mi.Vector3f([0.0], [0.0], [1e-30]), bits)
    assert np.all(np.array(odd) == np.array(centre)[0])


def test_environment_pool_holds_each_shift_along_a_morton_curve(monkeypatch):
    """Each shift of the pool holds the points of its lattice (the same set, by value, as in lattice
    order), ordered along the Morton curve of their directions, so the k-th points of the shifts lie
    near one another (what lets a packet of neighbouring rows skip them together)."""
    from mi_bivariate.lighting import kernels, mis

    probe = synthetic_probe()
    n = 300
    pool = np.array(mis.environment_pool(probe, n, seed=6)).reshape(mis.ENV_SHIFTS, n, 8)
    monkeypatch.setattr(mis, "morton_key", lambda d, bits: dr.zeros(mi.UInt32, dr.width(d)))  # lattice order
    lattice = np.array(mis.environment_pool(probe, n, seed=6)).reshape(mis.ENV_SHIFTS, n, 8)
    assert not np.array_equal(pool, lattice)
    for q in range(mis.ENV_SHIFTS):
        np.testing.assert_array_equal(np.unique(pool[q], axis=0), np.unique(lattice[q], axis=0))
        key = kernels.morton_key(mi.Vector3f(np.ascontiguousarray(pool[q, :, :3].T)), mis.POOL_MORTON_BITS)
        assert np.all(np.diff(np.array(key).astype(np.int64)) >= 0)
    spread = np.degrees(np.arccos(np.clip(np.sum(pool[0, :, :3] * pool[1, :, :3], axis=1), -1, 1)))
    spread_lattice = np.degrees(np.arccos(np.clip(np.sum(lattice[0, :, :3] * lattice[1, :, :3], axis=1), -1, 1)))
    assert np.median(spread) < 0.25 * np.median(spread_lattice)


def test_weighted_gram_by_row_blocks_matches_dense_product():
    """lighting.gram.weighted_gram (blocks of rows, touched columns only) equals A^T A and A^T y."""
    from mi_bivariate.lighting import gram

    rng = np.random.default_rng(12)
    m, n = 301, 50
    L = rng.random((m, n, 3)).astype(np.float32)
    L *= (np.abs(np.arange(n)[None, :] - np.linspace(0, n, m)[:, None]) < 9)[:, :, None]
    L[100:140] = 0.0  # a block with no signal
    w, y = rng.random(m) + 0.5, rng.random(m)
    channel = L[:, :, 1]  # a strided view, as the solve passes it
    a = channel.astype(np.float64) * w[:, None]
    for block_rows in (1, 16, 128, 10_000):
        g, rhs = gram.weighted_gram(channel, w, y, block_rows=block_rows)
        np.testing.assert_allclose(g, a.T @ a, rtol=1e-13, atol=1e-13 * np.abs(a.T @ a).max())
        np.testing.assert_array_equal(g, g.T)
        np.testing.assert_allclose(rhs, a.T @ y, rtol=1e-13, atol=1e-13)
    assert gram.weighted_gram(channel, w)[1] is None
    np.testing.assert_array_equal(gram.touched_columns(L[100:140]), [])


def test_touched_columns_of_rgb_rows_include_columns_lit_in_one_channel():
    """A column is touched where any of its entries, in any channel, is non-zero (a node that a
    coloured source reaches in red only still enters the luminance Gram matrix; a mutant asking for
    every channel dropped it), also through the adequacy's blocked statistics."""
    from mi_bivariate import adequacy
    from mi_bivariate.lighting import gram

    rng = np.random.default_rng(4)
    block = rng.random((6, 40, 3)) * (rng.random((6, 40, 3)) < 0.15)
    expected = np.flatnonzero(np.any(block != 0.0, axis=(0, 2)))
    assert np.any(np.sum(np.any(block != 0.0, axis=0), axis=1) == 1)  # columns lit in a single channel
    np.testing.assert_array_equal(gram.touched_columns(block), expected)
    np.testing.assert_array_equal(gram.touched_columns(block[..., 0]), np.flatnonzero(np.any(block[..., 0], axis=0)))
    lum = block @ np.asarray(adequacy.LUMINANCE_WEIGHTS, np.float64)
    got, _ = adequacy._luminance_statistics(block.astype(np.float32), block_rows=4)
    np.testing.assert_allclose(got, lum.T @ lum, rtol=1e-6, atol=1e-12)


def test_kernel_lane_limit_follows_the_layout(monkeypatch):
    """Dr.Jit indexes a kernel's lanes with 32 bits. A lane per (row, direction) (CUDA) makes
    rows x direction pairs lanes, refused above MAX_KERNEL_LANES before any work; a lane per row
    (the CPU) makes a chunk's rows, whatever K."""
    from mi_bivariate.lighting import kernels
    from mi_bivariate.limits import MAX_KERNEL_LANES

    rows = lighting._chunk_rows(32 * 32, None)
    too_many = 2 * (MAX_KERNEL_LANES // rows + 1)  # directions: pairs x rows just over the limit
    monkeypatch.setattr(kernels, "lane_per_row", lambda: False)
    monkeypatch.setattr(lighting, "lane_per_row", lambda: False)
    lighting.check_kernel_lanes(8000, too_many - 4, 32 * 32)
    with pytest.raises(InputError, match="--dirs.*lanes"):
        lighting.check_kernel_lanes(8000, too_many, 32 * 32, "--dirs")
    monkeypatch.setattr(lighting, "lane_per_row", lambda: True)
    lighting.check_kernel_lanes(8000, too_many, 32 * 32, "--dirs")


def test_kernel_lane_limit_counts_the_rows_a_small_job_has(monkeypatch):
    """With a lane per (row, direction) (CUDA), a job of fewer rows than a chunk makes rows x pairs lanes:
    100 rows at the most directions allowed (MAX_DIRS: 5 * 10^6 pairs, 5 * 10^8 lanes) go ahead, 1000
    rows (5 * 10^9) are refused. Counting a whole chunk's rows refused the small job too."""
    from mi_bivariate.lighting import kernels
    from mi_bivariate.limits import MAX_DIRS, MAX_KERNEL_LANES

    monkeypatch.setattr(kernels, "lane_per_row", lambda: False)
    monkeypatch.setattr(lighting, "lane_per_row", lambda: False)
    assert lighting._chunk_rows(32 * 32, None) * lighting.direction_pairs(MAX_DIRS) > MAX_KERNEL_LANES
    lighting.check_kernel_lanes(100, MAX_DIRS, 32 * 32)
    with pytest.raises(InputError, match="^n_dirs: 10000000 directions with 1024 grid nodes make a lighting kernel "
                                         "of 5000000000 lanes"):
        lighting.check_kernel_lanes(1000, MAX_DIRS, 32 * 32)


def test_occluders_refuse_what_they_cannot_shadow():
    """An occluder list shorter than the images, or an occluder for observations without surface positions
    (no shadow ray can start: the occluder would be ignored without a word), is refused naming it."""
    obs = dataclasses.replace(random_observations(6, seed=0), image_index=np.repeat(np.arange(2, dtype=np.int32), 3),
                              positions=np.zeros((6, 3)))
    ball = _sphere_scene((0.0, 0.0, 0.0), 5.0)
    with pytest.raises(InputError, match=r"^occluder: the observations come from image 1 but 1 occluder\(s\) were "
                                         r"given"):
        lighting.lighting_matrix(obs, synthetic_probe(), n_t=4, n_s=4, n_dirs=50, occluder=[ball])
    no_positions = dataclasses.replace(obs, positions=None)
    for occluder in (ball, [ball, None]):
        with pytest.raises(InputError, match="^occluder: an occluder was given but the observations have no "
                                             "surface positions"):
            lighting.lighting_matrix(no_positions, synthetic_probe(), n_t=4, n_s=4, n_dirs=50, occluder=occluder)


def test_texel_kernel_lane_limit_follows_the_layout(monkeypatch):
    """The texel quadrature runs a lane per (row, texel) on CUDA: a 2k probe (2048 x 1024 texels) at
    downsample=1 with a chunk of 2048 rows makes 2^32 lanes, refused naming downsample before any kernel
    (it once launched them); downsample=2 (2^30 lanes) goes ahead. A lane per row (the CPU) makes a chunk's
    rows, whatever the texels."""
    from mi_bivariate.lighting import kernels

    class Launched(Exception):
        pass

    def launched(packets, texels, n_t, n_s):
        raise Launched(len(packets) * texels[2])

    obs = random_observations(2 * lighting._chunk_rows(32 * 32, None), seed=1)
    probe = Probe.constant(1.0, 2048)
    monkeypatch.setattr(lighting, "_texel_target", launched)
    monkeypatch.setattr(kernels, "lane_per_row", lambda: False)
    monkeypatch.setattr(lighting, "lane_per_row", lambda: False)
    with pytest.raises(InputError, match=r"^downsample: 2097152 texels with 1024 grid nodes make a lighting kernel "
                                         r"of 4294967296 lanes, over the limit of 2147483648"):
        lighting.texel_lighting_matrix(obs, probe, downsample=1)
    with pytest.raises(Launched, match="^1073741824$"):
        lighting.texel_lighting_matrix(obs, probe, downsample=2)
    monkeypatch.setattr(lighting, "lane_per_row", lambda: True)
    lighting.check_kernel_lanes(len(obs), 2048 * 1024, 32 * 32, "downsample", texels=True)


@pytest.mark.parametrize("flag", ["SymbolicLoops", "SymbolicConditionals"])
def test_lighting_loops_stay_symbolic_whatever_the_jit_flag(flag):
    """A lane per row loops over its directions symbolically (one kernel per chunk), and skips the
    directions below its horizon with a symbolic conditional, even where a user turned Dr.Jit's
    symbolic loops or conditionals off: an evaluated loop would launch a kernel per direction."""
    if not sums_in_fixed_order():
        pytest.skip("CUDA runs a lane per (row, direction): no loop")
    obs = random_observations(50, seed=3)
    probe = synthetic_probe()
    expected = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=7)
    history = dr.flag(dr.JitFlag.KernelHistory)
    symbolic = dr.flag(getattr(dr.JitFlag, flag))
    try:
        dr.set_flag(getattr(dr.JitFlag, flag), False)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        got = lighting.lighting_matrix(obs, probe, n_t=8, n_s=8, n_dirs=600, seed=7)
        launched = len(dr.kernel_history())
    finally:
        dr.set_flag(getattr(dr.JitFlag, flag), symbolic)
        dr.set_flag(dr.JitFlag.KernelHistory, history)
    assert np.array_equal(got, expected)
    assert launched < 20, launched


@pytest.mark.parametrize("sampling", ["mis", "uniform", "texel"])
def test_both_lane_layouts_give_the_same_matrix(monkeypatch, sampling):
    """The CPU's lane per row (a loop over the row's directions) and CUDA's lane per (row, direction)
    are one estimator: the same terms, summed in another order. Run here on the CPU, so that a
    change to either layout is caught without a GPU."""
    from mi_bivariate.lighting import kernels

    obs = random_observations(120, seed=5)
    probe = synthetic_probe().rotated(euler_deg=(0.0, 30.0, 10.0))

    def matrix():
        if sampling == "texel":
            return lighting.texel_lighting_matrix(obs, probe, n_t=12, n_s=12, downsample=2)
        return lighting.lighting_matrix(obs, probe, n_t=12, n_s=12, n_dirs=2400, seed=3, sampling=sampling)

    monkeypatch.setattr(kernels, "lane_per_row", lambda: True)
    per_row = matrix()
    monkeypatch.setattr(kernels, "lane_per_row", lambda: False)
    per_direction = matrix()
    assert per_row.max() > 0.0
    np.testing.assert_allclose(per_direction, per_row, rtol=0.0, atol=2e-6 * per_row.max())


def test_strategy_counts_round_each_share_and_top_up_the_first():
    """As documented: each share of n_dirs rounded (at least 1), the first strategy topped up; the total
    is n_dirs or one more (two more for n_dirs = 1)."""
    from mi_bivariate.lighting.mis import MIS_FRACTIONS, strategy_counts

    assert strategy_counts(8000) == {"uniform": 2000, "environment": 4000, "peak": 2000}
    for n in range(1, 3000):
        counts = strategy_counts(n)
        assert list(counts) == [k for k in ("uniform", "environment", "peak") if MIS_FRACTIONS[k] > 0]
        assert all(c >= 1 for c in counts.values())
        assert counts["environment"] == max(1, round(n * MIS_FRACTIONS["environment"]))
        assert 0 <= sum(counts.values()) - n <= (2 if n == 1 else 1)
