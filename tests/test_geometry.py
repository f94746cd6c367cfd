"""The geometry's small pieces against closed forms (mi_bivariate.geometry): the rotation check, the
basis completing an axis, a sphere's normals just off its silhouette, the intrinsics' and the
perspective sphere's checks, the record a table keeps of its geometry, a perspective sphere's view
angles and a camera's field of view.

The rendered truths (Mitsuba's normals AOV and ray intersections) are in tests/test_spherefit.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate.errors import InputError
from mi_bivariate.geometry import (
    Camera,
    Intrinsics,
    PerspectiveSphereGeometry,
    SphereGeometry,
    check_rotation,
    orthonormal_pair,
)
from mi_bivariate.probes import rotation_matrix


def test_check_rotation_takes_rotations_and_refuses_the_rest():
    """A proper rotation (to rounding) passes as float64; a matrix 0.1% too long (it would stretch every
    normal it turns), a reflection, a non-finite or a non-3x3 one is refused, naming the source."""
    rot = rotation_matrix((10.0, -70.0, 33.0))
    np.testing.assert_array_equal(check_rotation(rot), rot)
    np.testing.assert_array_equal(check_rotation(None), np.eye(3))
    assert check_rotation(rot + 1e-9).dtype == np.float64
    for bad in (1.001 * rot, rot @ np.diag([1.0, 1.0, -1.0]), np.where(np.eye(3) > 0, np.nan, 0.0), np.eye(2),
                "eye"):
        with pytest.raises(InputError, match="^cam: camera_to_world is not a \\(3, 3\\) rotation matrix"):
            check_rotation(bad, "cam")


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0),
                                  (0.95, 0.3, -0.1), (0.2, -0.5, -0.8)])
def test_orthonormal_pair_completes_any_axis_to_a_right_handed_basis(axis):
    axis = np.array(axis) / np.linalg.norm(axis)
    e1, e2 = orthonormal_pair(axis)
    basis = np.stack([e1, e2, axis])
    np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(e1, e2), axis, atol=1e-12)


def test_normals_just_off_the_silhouette_are_held_on_the_rim():
    """Closed form: a position a distance rho > R from the centre in the image direction phi (y down) is
    pulled onto the rim, to the unit normal (cos phi, -sin phi, ~0) in the camera frame, turned by the
    camera's rotation; inside the silhouette nothing changes, and without onto_sphere the outside
    position gives the documented (x, y, 0), longer than 1."""
    rot = rotation_matrix((20.0, 35.0, -10.0))
    geometry = SphereGeometry(30.0, 22.0, 10.0, camera_to_world=rot)
    phi = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    rho = np.array([10.2, 11.0, 13.0] * 4)
    x, y = 30.0 + rho * np.cos(phi), 22.0 + rho * np.sin(phi)
    rim = np.stack([np.cos(phi), -np.sin(phi), np.zeros_like(phi)], axis=1) @ rot.T
    held = geometry.normals_at(x, y, onto_sphere=True)
    np.testing.assert_allclose(np.linalg.norm(held, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(held, rim, atol=2e-3)
    assert np.all(held @ geometry.view_direction() > 0.0)  # the visible hemisphere
    off = geometry.normals_at(x, y)
    np.testing.assert_allclose(off, np.stack([rho * np.cos(phi), -rho * np.sin(phi), np.zeros(12)], axis=1)
                               / 10.0 @ rot.T, atol=1e-12)
    inside_x, inside_y = np.array([30.0, 33.0, 24.5]), np.array([22.0, 17.0, 29.9])
    np.testing.assert_array_equal(geometry.normals_at(inside_x, inside_y, onto_sphere=True),
                                  geometry.normals_at(inside_x, inside_y))


@pytest.mark.parametrize("values", [(100.0, 0.0, 32.0, 24.0), (0.0, 100.0, 32.0, 24.0), (100.0, 100.0, np.nan, 24.0),
                                    (100.0, -100.0, 32.0, 24.0), (np.inf, 100.0, 32.0, 24.0)])
def test_intrinsics_refuse_a_focal_length_that_is_not_positive_or_a_point_not_finite(values):
    with pytest.raises(InputError, match="^intrinsics: the focal lengths must be finite and positive"):
        Intrinsics(*values)


def test_a_perspective_sphere_beside_the_camera_is_refused():
    """Centre on the camera's x axis (z = 0), outside the camera: half of it is behind the image plane and
    its silhouette is no ellipse; a visible sphere has centre[2] < 0."""
    k = Intrinsics.from_fov(64, 48, 40.0)
    with pytest.raises(InputError, match="radius 1\\) is not in front of the camera"):
        PerspectiveSphereGeometry(k, [3.0, 0.0, 0.0], 1.0)
    assert PerspectiveSphereGeometry(k, [3.0, 0.0, -1e-3], 1.0).distance == pytest.approx(3.0)


def test_a_camera_of_no_pixels_is_refused():
    for width, height in ((0, 16), (16, 0)):
        with pytest.raises(InputError, match="image size must be positive"):
            Camera(width, height, Intrinsics(10.0, 10.0, 8.0, 8.0))


def test_a_geometrys_record_holds_its_rotation_and_camera():
    """What a table records of its geometry tells two cameras apart: the (3, 3) rotation (9 numbers) and a
    perspective sphere's intrinsics and centre."""
    rot = rotation_matrix((0.0, 30.0, 0.0))
    assert SphereGeometry(30.0, 22.0, 10.0, camera_to_world=rot).record() == {
        "type": "SphereGeometry", "cx": 30.0, "cy": 22.0, "radius": 10.0, "camera_to_world": rot.tolist()}
    persp = PerspectiveSphereGeometry(Intrinsics(90.0, 110.0, 30.0, 22.0), [0.1, 0.2, -5.0], 0.5, rot)
    assert persp.record() == {"type": "PerspectiveSphereGeometry",
                              "intrinsics": {"fx": 90.0, "fy": 110.0, "cx": 30.0, "cy": 22.0},
                              "centre": [0.1, 0.2, -5.0], "radius": 0.5, "camera_to_world": rot.tolist()}


def test_a_perspective_spheres_view_angles_follow_the_law_of_sines():
    """Closed form, float64: a pixel whose ray makes the angle beta with the ray to the centre (distance D)
    meets a sphere of radius r where the normal makes the angle gamma with the view, sin(gamma) =
    D sin(beta) / r (the triangle camera, centre, hit point), to 1e-11 up to the silhouette (grazing pixels
    included; measured 1e-13, and 3e-8 with the ray-sphere discriminant alone rounded to float32)."""
    k = Intrinsics(120.0, 120.0, 32.0, 30.0)
    geometry = PerspectiveSphereGeometry(k, [0.4, -0.3, -6.0], 0.9)
    normals, views, mask = geometry.normals_and_views(64, 60)
    rays = k.rays(*np.meshgrid(np.arange(64) + 0.5, np.arange(60) + 0.5))[mask]
    sin_beta = np.linalg.norm(np.cross(rays, geometry.centre / geometry.distance), axis=1)
    expected = np.sqrt(np.clip(1.0 - (geometry.distance * sin_beta / geometry.radius) ** 2, 0.0, None))
    assert mask.sum() > 200
    np.testing.assert_allclose(np.sum(normals[mask] * views[mask], axis=1), expected, rtol=0.0, atol=1e-11)


def test_a_wide_cameras_sensor_has_the_horizontal_field_of_view():
    """Camera.look_at(fov_deg=40) of a 64 x 32 image renders through Mitsuba's sensor with a 40 degree
    horizontal field of view (fov_axis "x"): 2 atan(W / 2 / fx), not the height's."""
    camera = Camera.look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), width=64, height=32, fov_deg=40.0)
    sensor = camera.sensor_dict()
    assert sensor["fov_axis"] == "x" and sensor["fov"] == pytest.approx(40.0, abs=1e-9)
    assert (sensor["film"]["width"], sensor["film"]["height"]) == (64, 32)


def test_sphere_normals_are_its_normals_at_each_pixel_centre_inside_the_silhouette():
    """``SphereGeometry.normals`` (computed inside the silhouette only) against ``normals_at`` over the whole
    frame, masked: the same values bit for bit, for a rotated camera and a sphere the frame cuts; its
    ``object_mask`` (computed without the normals) is the pixel centres inside the circle, and a geometry
    without its own ``object_mask`` (perspective) gets its surface maps' mask from the base class."""
    rot = rotation_matrix([17.0, -11.0, 63.0])
    for geometry, (w, h) in ((SphereGeometry(60.3, 41.7, 35.2, rot), (120, 90)),
                             (SphereGeometry(10.5, 80.25, 40.0), (97, 64))):
        xx, yy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        inside = ((xx - geometry.cx) / geometry.radius) ** 2 + ((yy - geometry.cy) / geometry.radius) ** 2 < 1.0
        want = np.where(inside[..., None], geometry.normals_at(xx, yy), 0.0)
        normals, mask = geometry.normals(w, h)
        np.testing.assert_array_equal(mask, inside)
        np.testing.assert_array_equal(normals, want)
        np.testing.assert_array_equal(geometry.object_mask(w, h), inside)
    perspective = PerspectiveSphereGeometry(Intrinsics(90.0, 110.0, 60.0, 45.0), [0.1, 0.2, -5.0], 0.5, rot)
    mask = perspective.object_mask(120, 90)
    assert 100 < np.count_nonzero(mask) < 120 * 90
    np.testing.assert_array_equal(mask, perspective.surface_maps(120, 90).mask)


def test_a_spheres_box_holds_every_pixel_of_its_mask():
    """``images.circle_box`` of a sphere (found from the circle, without the mask) holds every pixel of
    ``object_mask``, within the frame, for spheres inside, cut by or beyond the frame, of either sign of
    radius, and is at most two pixels wider on each side than their bounding box where the centre lies in the
    frame. ``object_mask``, computed in that box by rows, is the whole frame's formula."""
    from mi_bivariate.images import bounding_box, circle_box

    rng = np.random.default_rng(4)
    for k in range(500):
        width, height = (int(v) for v in rng.integers(1, 60 if k % 2 else 700, 2))
        radius = float(rng.choice([rng.uniform(0.01, 400.0), 1e-7, 1e6])) * (-1.0 if k % 5 == 0 else 1.0)
        geometry = SphereGeometry(float(rng.uniform(-30, width + 30)), float(rng.uniform(-30, height + 30)), radius)
        xx, yy = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        inside = ((xx - geometry.cx) / geometry.radius) ** 2 + ((yy - geometry.cy) / geometry.radius) ** 2 < 1.0
        np.testing.assert_array_equal(geometry.object_mask(width, height), inside)
        rows, cols = circle_box((height, width), geometry.cx, geometry.cy, geometry.radius)
        assert 0 <= rows.start <= rows.stop <= height and 0 <= cols.start <= cols.stop <= width
        assert np.count_nonzero(inside[rows, cols]) == np.count_nonzero(inside)
        if 0 <= geometry.cx <= width and 0 <= geometry.cy <= height and inside.any():  # else the circle's box is
            tight_rows, tight_cols = bounding_box(inside)                             # wider than its pixels'
            assert tight_rows.start - rows.start <= 2 and rows.stop - tight_rows.stop <= 2
            assert tight_cols.start - cols.start <= 2 and cols.stop - tight_cols.stop <= 2
    assert bounding_box(np.zeros((4, 5), bool)) == (slice(0, 0), slice(0, 0))
