"""Rusinkiewicz angles and the st map against an independent construction by explicit rotations."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mi_bivariate.coordinates import (
    dirs_from_half_diff,
    fold_phi_d,
    grid_nodes,
    half_diff_from_dirs,
    half_diff_from_st,
    st_from_dirs,
    st_from_half_diff,
)

Z = np.array([0.0, 0.0, 1.0])


def about(axis, angle):
    """Rotations by ``angle (N,)`` about a coordinate axis."""
    return Rotation.from_euler(axis, np.asarray(angle, np.float64)[:, None])


def rotation_dirs(theta_h, phi_h, theta_d, phi_d):
    """wi, wo built as Rusinkiewicz (1998) defines them: rotate z, then mirror wi about h."""
    to_half = about("z", phi_h) * about("y", theta_h)
    h = to_half.apply(Z)
    wi = (to_half * about("z", phi_d) * about("y", theta_d)).apply(Z)
    wo = Rotation.from_rotvec(math.pi * h).apply(wi)  # half-turn about h
    return wi, wo


def random_angles(rng, n, theta_min=0.0):
    theta_h = rng.uniform(theta_min, 0.5 * math.pi, n)
    theta_d = rng.uniform(theta_min, 0.5 * math.pi, n)
    phi_h = rng.uniform(-math.pi, math.pi, n)
    phi_d = rng.uniform(-math.pi, math.pi, n)
    return theta_h, phi_h, theta_d, phi_d


def random_hemisphere(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v


def angle_diff(a, b):
    """Distance between angles on the circle."""
    return np.abs((a - b + math.pi) % (2.0 * math.pi) - math.pi)


def test_dirs_match_explicit_rotations():
    rng = np.random.default_rng(1)
    angles = random_angles(rng, 2000)
    wi_ref, wo_ref = rotation_dirs(*angles)
    wi, wo = dirs_from_half_diff(*angles)
    np.testing.assert_allclose(wi, wi_ref, atol=1e-12)
    np.testing.assert_allclose(wo, wo_ref, atol=1e-12)


def test_angles_match_explicit_rotations():
    rng = np.random.default_rng(2)
    theta_h, phi_h, theta_d, phi_d = random_angles(rng, 2000, theta_min=1e-2)
    wi, wo = rotation_dirs(theta_h, phi_h, theta_d, phi_d)
    th, ph, td, pd = half_diff_from_dirs(wi, wo)
    np.testing.assert_allclose(th, theta_h, atol=1e-12)
    np.testing.assert_allclose(td, theta_d, atol=1e-12)
    assert angle_diff(ph, phi_h).max() < 1e-10
    assert angle_diff(pd, phi_d).max() < 1e-10


def test_round_trip_from_directions():
    rng = np.random.default_rng(3)
    wi, wo = random_hemisphere(rng, 5000), random_hemisphere(rng, 5000)
    wi2, wo2 = dirs_from_half_diff(*half_diff_from_dirs(wi, wo))
    np.testing.assert_allclose(wi2, wi, atol=1e-12)
    np.testing.assert_allclose(wo2, wo, atol=1e-12)


def test_round_trip_from_angles():
    rng = np.random.default_rng(4)
    theta_h, phi_h, theta_d, phi_d = random_angles(rng, 5000, theta_min=1e-3)
    th, ph, td, pd = half_diff_from_dirs(*dirs_from_half_diff(theta_h, phi_h, theta_d, phi_d))
    np.testing.assert_allclose(th, theta_h, atol=1e-12)
    np.testing.assert_allclose(td, theta_d, atol=1e-12)
    assert angle_diff(ph, phi_h).max() < 1e-9
    assert angle_diff(pd, phi_d).max() < 1e-9


def test_reciprocity_swaps_phi_d_by_pi():
    rng = np.random.default_rng(5)
    wi, wo = random_hemisphere(rng, 1000), random_hemisphere(rng, 1000)
    th, _, td, pd = half_diff_from_dirs(wi, wo)
    th2, _, td2, pd2 = half_diff_from_dirs(wo, wi)
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-12)
    keep = td > 1e-3
    assert angle_diff(pd2[keep], pd[keep] + math.pi).max() < 1e-9
    # Folded, both land on the same point of the pi-periodic circle.
    assert angle_diff(2.0 * fold_phi_d(pd2[keep]), 2.0 * fold_phi_d(pd[keep])).max() < 1e-9


def test_numpy_and_drjit_agree():
    rng = np.random.default_rng(6)
    wi = random_hemisphere(rng, 4000).astype(np.float32)
    wo = random_hemisphere(rng, 4000).astype(np.float32)
    ref = half_diff_from_dirs(wi.astype(np.float64), wo.astype(np.float64))
    dr_out = half_diff_from_dirs(mi.Vector3f(wi.T), mi.Vector3f(wo.T))
    got = [np.array(a, np.float64) for a in dr_out]
    np.testing.assert_allclose(got[0], ref[0], atol=2e-6)
    np.testing.assert_allclose(got[2], ref[2], atol=2e-6)
    # Azimuths are ill-conditioned where their polar angle vanishes.
    keep_h, keep_d = ref[0] > 1e-2, ref[2] > 1e-2
    assert angle_diff(got[1][keep_h], ref[1][keep_h]).max() < 1e-3
    assert angle_diff(got[3][keep_d], ref[3][keep_d]).max() < 1e-3

    angles = random_angles(rng, 4000)
    wi_np, wo_np = dirs_from_half_diff(*angles)
    wi_dr, wo_dr = dirs_from_half_diff(*(mi.Float(a.astype(np.float32)) for a in angles))
    np.testing.assert_allclose(np.array(wi_dr).T, wi_np, atol=2e-6)
    np.testing.assert_allclose(np.array(wo_dr).T, wo_np, atol=2e-6)

    phi = rng.uniform(-10.0, 10.0, 1000).astype(np.float32)
    np.testing.assert_allclose(np.array(fold_phi_d(mi.Float(phi))), fold_phi_d(phi.astype(np.float64)), atol=1e-5)
    s_dr, t_dr = st_from_half_diff(mi.Float(angles[0].astype(np.float32)), mi.Float(angles[2].astype(np.float32)))
    s_np, t_np = st_from_half_diff(angles[0], angles[2])
    np.testing.assert_allclose(np.array(s_dr), s_np, atol=1e-6)
    np.testing.assert_allclose(np.array(t_dr), t_np, atol=1e-6)


@pytest.mark.parametrize("theta_h", [1e-5, 1e-4, 3e-4, 1e-3])
def test_float32_resolves_specular_peak(theta_h):
    rng = np.random.default_rng(7)
    n = 256
    theta_d = rng.uniform(0.0, 1.4, n)
    phi_h, phi_d = rng.uniform(-math.pi, math.pi, (2, n))
    wi, wo = rotation_dirs(np.full(n, theta_h), phi_h, theta_d, phi_d)
    wi32, wo32 = wi.astype(np.float32), wo.astype(np.float32)
    # Rounding the inputs to float32 moves h by ~1e-7 rad: that is the attainable accuracy.
    tol = 1e-6 + 2e-2 * theta_h

    th_np = half_diff_from_dirs(wi32, wo32)[0]
    assert th_np.dtype == np.float32
    assert np.abs(th_np - theta_h).max() < tol
    th_dr = np.array(half_diff_from_dirs(mi.Vector3f(wi32.T), mi.Vector3f(wo32.T))[0])
    assert np.abs(th_dr - theta_h).max() < tol

    # The test can fail: the naive acos of h.z cannot resolve these angles in float32.
    h = wi32 + wo32
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    naive = np.arccos(np.clip(h[:, 2], -1.0, 1.0))
    if theta_h <= 3e-4:
        assert np.abs(naive - theta_h).max() > tol


def test_fold_phi_d():
    rng = np.random.default_rng(8)
    phi = rng.uniform(-20.0, 20.0, 10000)
    folded = fold_phi_d(phi)
    assert folded.min() >= 0.0 and folded.max() < math.pi
    # Same point of the pi-periodic circle.
    assert angle_diff(2.0 * folded, 2.0 * phi).max() < 1e-9
    edge = fold_phi_d(np.array([0.0, math.pi, -math.pi, 2 * math.pi, -1e-18, math.pi / 2, -math.pi / 2]))
    np.testing.assert_allclose(edge, [0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2, math.pi / 2], atol=1e-15)
    assert np.all(edge < math.pi)


def test_st_map_and_inverse():
    theta_h = np.array([0.0, math.pi / 8, math.pi / 2])
    theta_d = np.array([0.0, math.pi / 4, math.pi / 2])
    s, t = st_from_half_diff(theta_h, theta_d)
    np.testing.assert_allclose(s, [0.0, 0.5, 1.0], atol=1e-15)
    np.testing.assert_allclose(t, [0.0, 0.5, 1.0], atol=1e-15)
    rng = np.random.default_rng(9)
    s, t = rng.uniform(0.0, 1.0, (2, 1000))
    theta_h, theta_d = half_diff_from_st(s, t)
    s2, t2 = st_from_half_diff(theta_h, theta_d)
    np.testing.assert_allclose(s2, s, atol=1e-14)
    np.testing.assert_allclose(t2, t, atol=1e-14)
    wi, wo = rotation_dirs(theta_h, rng.uniform(-3, 3, 1000), theta_d, rng.uniform(-3, 3, 1000))
    s3, t3 = st_from_dirs(wi, wo)
    np.testing.assert_allclose(s3, s, atol=1e-12)
    np.testing.assert_allclose(t3, t, atol=1e-7)


def test_grid_nodes():
    np.testing.assert_allclose(grid_nodes(5), [0.0, 0.25, 0.5, 0.75, 1.0])
    assert grid_nodes(32)[31] == 1.0 and len(grid_nodes(32)) == 32
    with pytest.raises(ValueError):
        grid_nodes(1)


def test_mirror_pairs_have_the_normal_as_half_vector():
    """wo = wi mirrored about the normal: h is exactly z, theta_h = 0, and in the frame phi_h = 0 the difference
    vector is wi itself (theta_d = wi's polar angle, phi_d its azimuth), the explicit construction's angles."""
    rng = np.random.default_rng(10)
    theta_d = rng.uniform(0.01, 0.5 * math.pi - 1e-3, 200)
    phi_d = rng.uniform(-math.pi + 1e-3, math.pi, 200)
    wi = np.stack([np.sin(theta_d) * np.cos(phi_d), np.sin(theta_d) * np.sin(phi_d), np.cos(theta_d)], -1)
    wo = wi * [-1.0, -1.0, 1.0]
    th, ph, td, pd = half_diff_from_dirs(wi, wo)
    assert np.all(th == 0.0) and np.all(ph == 0.0)
    np.testing.assert_allclose(td, theta_d, atol=1e-12)
    assert angle_diff(pd, phi_d).max() < 1e-12
    wi_ref, wo_ref = rotation_dirs(th, ph, td, pd)
    np.testing.assert_allclose(wi_ref, wi, atol=1e-12)
    np.testing.assert_allclose(wo_ref, wo, atol=1e-12)
    th32, _, td32, _ = (np.array(a, np.float64) for a in half_diff_from_dirs(mi.Vector3f(wi.T.astype(np.float32)),
                                                                             mi.Vector3f(wo.T.astype(np.float32))))
    assert np.all(th32 == 0.0)
    np.testing.assert_allclose(td32, theta_d, atol=2e-6)


@pytest.mark.parametrize("region", ["pole", "horizon"])
def test_angles_rebuild_the_directions_near_the_pole_and_the_horizon(region):
    """Against the explicit rotations (rotate by phi_h about z, theta_h about y, then phi_d, theta_d): half vectors
    within 1e-9..1e-2 rad of the normal, and both directions within 1e-12..1e-6 of the horizon. The angles
    rebuild the directions, and swapping wi and wo (reciprocity) keeps theta_h and theta_d."""
    rng = np.random.default_rng(11)
    n = 400
    if region == "pole":
        theta_h = 10.0 ** rng.uniform(-9.0, -2.0, n)
        theta_d = rng.uniform(0.05, 1.5, n)
        wi, wo = rotation_dirs(theta_h, rng.uniform(-math.pi, math.pi, n), theta_d, rng.uniform(-math.pi, math.pi, n))
    else:
        def grazing():
            z = 10.0 ** rng.uniform(-12.0, -6.0, n)
            phi = rng.uniform(-math.pi, math.pi, n)
            r = np.sqrt(1.0 - z * z)
            return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
        wi, wo = grazing(), grazing()
    th, ph, td, pd = half_diff_from_dirs(wi, wo)
    if region == "pole":
        np.testing.assert_allclose(th, theta_h, atol=2e-14)  # ~eps: the rounding of wi and wo
        np.testing.assert_allclose(td, theta_d, atol=1e-12)
    assert np.all((th >= 0) & (th <= 0.5 * math.pi)) and np.all((td >= 0) & (td <= 0.5 * math.pi))
    wi_ref, wo_ref = rotation_dirs(th, ph, td, pd)
    np.testing.assert_allclose(wi_ref, wi, atol=1e-9)
    np.testing.assert_allclose(wo_ref, wo, atol=1e-9)
    th2, _, td2, _ = half_diff_from_dirs(wo, wi)
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-12)


def test_directions_must_have_three_components():
    """A (..., 4) or (..., 2) array is refused, not read as its first three components."""
    for shape in ((5, 4), (5, 2)):
        with pytest.raises(ValueError, match="shape"):
            half_diff_from_dirs(np.ones(shape), np.ones(shape))
