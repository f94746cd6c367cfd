"""mi_bivariate.capture: normals, views and pixel values from images of a known sphere."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from mi_bivariate import capture, limits
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Intrinsics, PerspectiveSphereGeometry, SphereGeometry


def sphere_image(size: int = 128, radius: float = 57.6, value: float = 0.5) -> tuple:
    """A shaded sphere (value * (0.2 + n_z), channels scaled 1 : 1.5 : 0.7) and its geometry."""
    geo = SphereGeometry(size / 2, size / 2, radius)
    normals, mask = geo.normals(size, size)
    shade = np.where(mask, value * (0.2 + normals[..., 2]), 0.0)
    image = (shade[..., None] * np.array([1.0, 1.5, 0.7])).astype(np.float32)
    return image, geo


def test_normals_match_render_aov():
    """Capture's analytic normals are the renderer's own shading normals at those pixels."""
    from mi_bivariate.render import render_sphere

    render = render_sphere({"type": "diffuse"}, _constant_probe(), resolution=96, spp=64)
    obs = capture.observations_from_sphere(render.image, render.geometry, n_normals=2000)
    rows, cols = obs.pixels.T
    assert render.mask[rows, cols].all()
    aov = render.normals[rows, cols].astype(np.float64)
    angle = np.degrees(np.arccos(np.clip(np.sum(aov * obs.normals, axis=1), -1, 1)))
    # The AOV averages the normals of 64 random points in the pixel; the capture
    # takes the centre. Jitter of the mean position: ~0.04 px, i.e. ~0.04 deg at
    # the centre of this 43 px sphere and 5x more near the 80 degree limit.
    assert np.median(angle) < 0.15 and angle.max() < 1.0
    assert np.allclose(obs.views, [0.0, 0.0, 1.0])
    # The normal-map path on the same AOVs picks (nearly) the same observations.
    nm = capture.observations_from_normal_map(render.image, render.normals, render.mask,
                                              np.array([0.0, 0.0, 1.0]), n_normals=2000)
    assert abs(len(nm) - len(obs)) < 0.1 * len(obs)
    assert np.allclose(nm.values, render.image[nm.pixels[:, 0], nm.pixels[:, 1]])


def _constant_probe():
    from mi_bivariate.probes import Probe

    return Probe.constant(1.0, 16)


def test_rotated_camera():
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # camera on +x
    image, geo = sphere_image()
    geo = SphereGeometry(geo.cx, geo.cy, geo.radius, camera_to_world=rot)
    obs = capture.observations_from_sphere(image, geo, n_normals=500)
    assert np.allclose(obs.views, [1.0, 0.0, 0.0])
    assert np.all(np.sum(obs.normals * obs.views, axis=1) >= math.cos(math.radians(80)) - 1e-9)
    # Image right is world -z for this camera: the right half of the image sees n.z < 0.
    right = obs.pixels[:, 1] + 0.5 > geo.cx + 2
    assert np.all(obs.normals[right, 2] < 0)


def test_normals_are_uniform_over_the_visible_cap():
    image, geo = sphere_image(size=256, radius=120.0)
    obs = capture.observations_from_sphere(image, geo, n_normals=8000)
    cos_max = math.cos(math.radians(80))
    cos_v = np.sum(obs.normals * obs.views, axis=1)
    assert cos_v.min() >= cos_max - 1e-9
    # Uniform in solid angle: cos(view angle) uniform on [cos 80deg, 1].
    hist, _ = np.histogram(cos_v, bins=10, range=(cos_max, 1.0))
    assert np.abs(hist / hist.mean() - 1.0).max() < 0.1, hist
    azimuth = np.arctan2(obs.normals[:, 1], obs.normals[:, 0])
    hist, _ = np.histogram(azimuth, bins=8, range=(-np.pi, np.pi))
    assert np.abs(hist / hist.mean() - 1.0).max() < 0.1, hist
    # The paper's numbers: 8000 over the hemisphere, those beyond 80 degrees dropped
    # (plus a few whose pixel's own normal is just past 80 degrees).
    assert 8000 * cos_max - 2 <= obs.dropped["view_angle"] <= 8000 * cos_max * 1.05
    assert len(obs) + sum(obs.dropped.values()) == 8000
    assert len(np.unique(obs.pixels, axis=0)) == len(obs)


def test_drop_counts_on_planted_pixels():
    image, geo = sphere_image()
    clean = capture.observations_from_sphere(image, geo, n_normals=3000, saturation=10.0)
    assert sum(clean.dropped[k] for k in ("nonfinite", "negative", "saturated")) == 0
    rows, cols = clean.pixels.T
    rng = np.random.default_rng(0)
    picks = rng.permutation(len(clean))
    planted = {"nonfinite": picks[:10], "negative": picks[10:17], "saturated": picks[17:30]}
    bad = image.copy()
    bad[rows[planted["nonfinite"][:5]], cols[planted["nonfinite"][:5]], 0] = np.nan
    bad[rows[planted["nonfinite"][5:]], cols[planted["nonfinite"][5:]], 2] = np.inf
    bad[rows[planted["negative"]], cols[planted["negative"]], 1] = -0.01
    bad[rows[planted["saturated"]], cols[planted["saturated"]], 1] = 10.0
    # Pixels the lattice does not pick do not count.
    _, mask = geo.normals(*image.shape[1::-1])
    unused = mask.copy()
    unused[rows, cols] = False
    bad[np.nonzero(unused)[0][:50], np.nonzero(unused)[1][:50]] = np.nan
    obs = capture.observations_from_sphere(bad, geo, n_normals=3000, saturation=10.0)
    for reason, idx in planted.items():
        assert obs.dropped[reason] == len(idx), reason
    assert len(obs) == len(clean) - 30
    assert np.all(np.isfinite(obs.values)) and obs.values.min() >= 0 and obs.values.max() < 10


def test_mask_and_silhouette():
    image, geo = sphere_image()
    mask = np.ones(image.shape[:2], bool)
    mask[:, :64] = False  # left half
    obs = capture.observations_from_sphere(image, geo, n_normals=2000, mask=mask)
    assert obs.dropped["outside_mask"] > 0.3 * len(obs)
    assert np.all(obs.pixels[:, 1] >= 64)
    # Every used pixel lies entirely inside the silhouette.
    centre = obs.pixels[:, ::-1] + 0.5 - [geo.cx, geo.cy]
    assert np.all(np.linalg.norm(centre, axis=1) + math.sqrt(0.5) < geo.radius)


def test_stack_and_probe_index():
    image, geo = sphere_image()
    a = capture.observations_from_sphere(image, geo, n_normals=500)
    b = capture.observations_from_sphere(image * 2, geo, n_normals=500, seed=1)
    s = capture.stack([a, b], probe_index=[0, 3])
    assert len(s) == len(a) + len(b)
    assert np.all(s.probe_index[:len(a)] == 0) and np.all(s.probe_index[len(a):] == 3)
    assert np.all(s.image_index[len(a):] == 1)
    assert s.dropped["view_angle"] == a.dropped["view_angle"] + b.dropped["view_angle"]
    assert np.allclose(s.values[len(a):], b.values)


def test_deterministic():
    image, geo = sphere_image()
    a = capture.observations_from_sphere(image, geo, n_normals=800, seed=4)
    b = capture.observations_from_sphere(image, geo, n_normals=800, seed=4)
    c = capture.observations_from_sphere(image, geo, n_normals=800, seed=5)
    assert np.array_equal(a.pixels, b.pixels)
    assert not np.array_equal(a.pixels, c.pixels)


def test_bad_input():
    image, geo = sphere_image()
    with pytest.raises(InputError, match="mask has shape"):
        capture.observations_from_sphere(image, geo, mask=np.ones((10, 10), bool))
    with pytest.raises(InputError, match="outside the"):
        capture.observations_from_sphere(image, SphereGeometry(500.0, 500.0, 20.0))
    with pytest.raises(InputError, match="RGB image"):
        capture.observations_from_sphere(image[..., 0], geo)
    with pytest.raises(InputError, match="black"):
        capture.observations_from_sphere(np.zeros_like(image), geo)
    with pytest.raises(InputError, match="no usable pixel"):
        capture.observations_from_sphere(np.full_like(image, np.nan), geo)
    with pytest.raises(InputError, match="radius"):
        capture.observations_from_sphere(image, SphereGeometry(64.0, 64.0, -3.0))
    with pytest.raises(InputError, match="normal map has shape"):
        capture.observations_from_normal_map(image, np.zeros((5, 5, 3)), np.ones((128, 128), bool), [0, 0, 1])
    with pytest.warns(InputWarning, match="only .* usable observations"):
        capture.observations_from_sphere(image, geo, n_normals=100)
    with pytest.warns(InputWarning, match="beyond the"):
        capture.observations_from_sphere(image, SphereGeometry(10.0, 64.0, 57.6))
    clipped = np.minimum(image * 4, 1.0)
    with pytest.warns(InputWarning, match="clipped"):
        capture.observations_from_sphere(clipped, geo)
    nans = image.copy()
    nans[::2] = np.nan
    with pytest.warns(InputWarning, match="unusable values"):
        capture.observations_from_sphere(nans, geo)


def test_every_geometry_gives_surface_maps_that_agree_with_its_own_model():
    """The Geometry interface: an orthographic sphere's maps are its normals and one view; a pinhole
    sphere's fully covered pixels lie inside its centre-covered ones and look back along the rays."""
    ortho = SphereGeometry(16.0, 15.0, 12.0)
    maps = ortho.surface_maps(32, 30)
    normals, mask = ortho.normals(32, 30)
    np.testing.assert_array_equal(maps.mask, mask)
    np.testing.assert_array_equal(maps.normals, normals)
    np.testing.assert_allclose(maps.views[mask], np.broadcast_to(ortho.view_direction(), (mask.sum(), 3)))
    assert np.all(maps.views[~mask] == 0) and maps.positions is None and ortho.occluder() is None
    persp = PerspectiveSphereGeometry(Intrinsics.from_fov(40, 30, 40.0), [0.2, -0.1, -4.0])
    full = persp.surface_maps(40, 30)
    _, _, centre = persp.normals_and_views(40, 30, coverage="centre")
    assert full.mask.sum() > 20 and np.all(centre[full.mask]) and full.mask.sum() < centre.sum()
    assert np.all(np.sum(full.normals[full.mask] * full.views[full.mask], axis=-1) > 0)


def test_sphere_footprints_are_finer_than_the_footprint_angle():
    """Every pixel whose opposite corners' normals are more than ``footprint`` degrees apart (an angle
    taken between the corners, not through the centre as the code does) is split, and its neighbouring
    sub-pixel normals are then about ``footprint`` apart at most (1.02x measured; 1.6x if the split
    were half as fine)."""
    from mi_bivariate.capture import _sphere_footprints

    cx = cy = 32.0
    r, footprint = 30.0, 2.0
    yy, xx = np.mgrid[0:64, 0:64]
    inside = np.ones_like(xx, bool)
    for dx in (0, 1):
        for dy in (0, 1):
            inside &= (xx + dx - cx) ** 2 + (yy + dy - cy) ** 2 < r * r
    pixels = np.stack([yy[inside], xx[inside]], axis=1)
    normals, rows = _sphere_footprints(pixels, cx, cy, r, np.eye(3), footprint)

    def corner(dx, dy):
        x, y = (pixels[:, 1] + dx - cx) / r, -(pixels[:, 0] + dy - cy) / r
        return np.stack([x, y, np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))], axis=1)

    def angle(a, b):
        return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))

    diagonal = np.maximum(angle(corner(0, 0), corner(1, 1)), angle(corner(1, 0), corner(0, 1)))
    assert set(np.flatnonzero(diagonal > footprint)) <= set(np.unique(rows))
    worst = 0.0
    for row in np.unique(rows):
        sub = normals[rows == row]
        side = int(round(np.sqrt(len(sub))))
        grid = sub.reshape(side, side, 3)
        worst = max(worst, angle(grid[:, 1:], grid[:, :-1]).max(), angle(grid[1:], grid[:-1]).max())
    assert worst <= 1.2 * footprint, worst


def test_rim_pixels_mixed_with_the_background_are_never_used():
    """Up to the rim (max_view_angle 90): no used pixel reaches outside the silhouette (its centre plus
    half its diagonal inside the circle, the closed form of a square pixel inside a disc); the others
    are counted as silhouette drops."""
    image, geo = sphere_image()
    obs = capture.observations_from_sphere(image, geo, n_normals=20000, max_view_angle_deg=90.0)
    centre = obs.pixels[:, ::-1] + 0.5 - [geo.cx, geo.cy]
    assert np.all(np.linalg.norm(centre, axis=1) + math.sqrt(0.5) < geo.radius)
    assert obs.dropped["silhouette"] > 100


def test_normal_map_rows_face_their_own_view_within_the_limit():
    """A pinhole photo: each pixel has its own view. Every row's normal lies within max_view_angle of
    that pixel's own view (not just of the mean view the lattice is laid about)."""
    k = Intrinsics(120.0, 120.0, 64.0, 64.0)
    geo = PerspectiveSphereGeometry(k, [0.9, 0.5, -3.0], 1.0)
    normals, views, mask = geo.normals_and_views(128, 128, coverage="full")
    image = np.where(mask[..., None], 0.2 + normals[..., 2:], 0.0).repeat(3, axis=2).astype(np.float32)
    obs = capture.image_observations(image, geo, n_normals=4000, max_view_angle_deg=60.0)
    cos = np.sum(obs.normals * obs.views, axis=1)
    assert len(obs) > 500 and cos.min() >= math.cos(math.radians(60.0)) - 1e-9
    np.testing.assert_allclose(obs.views, views[obs.pixels[:, 0], obs.pixels[:, 1]])


def test_stacked_footprints_stay_with_their_rows():
    """Three observation sets of different sizes with pixel footprints: after stacking, each footprint
    normal still belongs to its row (within the footprint's spread of the row's centre normal)."""
    image, geo = sphere_image()
    parts = [capture.observations_from_sphere(image, geo, n_normals=n, max_view_angle_deg=88.0, footprint=1.0,
                                              seed=n) for n in (400, 700, 1200)]
    s = capture.stack(parts)
    assert len(s.footprint_rows) == sum(len(p.footprint_rows) for p in parts) > 100
    cos = np.sum(s.footprint_normals * s.normals[s.footprint_rows], axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max() < 15.0


def test_hemisphere_lattice_is_the_stated_closed_form():
    """``z_k = 1 - (k + 1/2) / n``, unit vectors, golden-angle azimuth steps (mod 2 pi) after a seeded offset."""
    n = 50
    lattice = capture.hemisphere_lattice(n, seed=3)
    np.testing.assert_allclose(lattice[:, 2], 1.0 - (np.arange(n) + 0.5) / n, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(lattice, axis=1), 1.0, rtol=1e-14)
    phi = np.arctan2(lattice[:, 1], lattice[:, 0])
    step = np.mod(np.diff(phi), 2.0 * np.pi)
    np.testing.assert_allclose(step, np.mod(2.0 * np.pi / ((1.0 + math.sqrt(5.0)) / 2.0), 2.0 * np.pi), atol=1e-12)


@pytest.mark.parametrize("axis", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.95, 0.3, 0.0],
                                  [0.3, -0.2, -2.0]])
def test_frame_about_an_axis_is_a_rotation_onto_it(axis):
    """Orthonormal, determinant +1 (a rotation, not a reflection), third column the unit axis: also for axes
    along or near x, where the first helper vector is (nearly) parallel."""
    from mi_bivariate.capture import _frame_about

    frame = _frame_about(np.array(axis))
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(frame[:, 2], np.array(axis) / np.linalg.norm(axis), atol=1e-15)


def test_each_value_is_the_image_at_its_own_normal():
    """A sphere shaded by its normal's y and x (0.5 + 0.3 n_y + 0.1 n_x: not symmetric top to bottom or left to
    right): every row's value is that function of its own normal (image y points down, world y up)."""
    geo = SphereGeometry(64.0, 60.0, 50.0)
    normals, mask = geo.normals(128, 128)
    shade = np.where(mask, 0.5 + 0.3 * normals[..., 1] + 0.1 * normals[..., 0], 0.0)
    obs = capture.observations_from_sphere(np.repeat(shade[..., None], 3, axis=2).astype(np.float32), geo,
                                           n_normals=1500)
    assert len(obs) > 1000
    np.testing.assert_allclose(obs.values[:, 1], 0.5 + 0.3 * obs.normals[:, 1] + 0.1 * obs.normals[:, 0], rtol=1e-6)


def test_a_sphere_past_the_bottom_right_edges_drops_the_normals_beyond_them():
    """Lattice normals that project beyond the last row or column are counted as ``outside_image`` (the
    orthographic projection ``x = cx + r n_x``, ``y = cy - r n_y``, by hand), never indexed into the image."""
    image, _ = sphere_image()
    geo = SphereGeometry(100.0, 110.0, 40.0)
    with pytest.warns(InputWarning, match="beyond the"):
        obs = capture.observations_from_sphere(image, geo, n_normals=3000)
    lattice = capture.hemisphere_lattice(3000, 0)
    lattice = lattice[lattice[:, 2] >= math.cos(math.radians(80.0))]
    cols, rows = np.floor(100.0 + 40.0 * lattice[:, 0]), np.floor(110.0 - 40.0 * lattice[:, 1])
    assert obs.dropped["outside_image"] == np.count_nonzero((cols >= 128) | (rows >= 128)) > 100
    assert obs.pixels[:, 0].max() < 128 and obs.pixels[:, 1].max() < 128


@pytest.mark.parametrize("centre", [(64.0, -30.0), (64.0, 160.0), (-30.0, 64.0), (160.0, 64.0)])
def test_a_sphere_wholly_off_any_side_is_refused_and_one_across_any_side_warns(centre):
    image, _ = sphere_image()
    with pytest.raises(InputError, match="lies outside the 128x128 image"):
        capture.observations_from_sphere(image, SphereGeometry(*centre, 20.0))
    across = [c if abs(c - 64.0) < 1 else (0.0 if c < 0 else 128.0) for c in centre]   # centre on that edge
    with pytest.warns(InputWarning, match="extends beyond the 128x128 image"):
        capture.observations_from_sphere(image, SphereGeometry(*across, 20.0), n_normals=2000)


def test_pixel_value_limits_are_inclusive():
    """The largest accepted value is MAX_RADIANCE itself and the smallest largest value MIN_RADIANCE itself
    (float64 input, compared before the float32 cast); twice the one and half the other are refused, whatever
    non-finite value lies beside them (left out of the brightest), and for a negative value of that size."""
    image = np.zeros((4, 4, 3))
    for top, ok in ((limits.MAX_RADIANCE, True), (2.0 * limits.MAX_RADIANCE, False), (limits.MIN_RADIANCE, True),
                    (0.5 * limits.MIN_RADIANCE, False)):
        for spoiled in (None, np.nan, np.inf, -np.inf):  # non-finite values are no one's brightest value
            image[1, 1, 1] = top
            image[2, 3, 0] = 0.0 if spoiled is None else spoiled
            if ok:
                capture.check_image(image)
            else:
                with pytest.raises(InputError, match="too (large|small) for float32"):
                    capture.check_image(image)
        image[1, 1, 1] = -top  # the brightest magnitude, a negative value's too
        if ok:
            capture.check_image(image)
        else:
            with pytest.raises(InputError, match="too (large|small) for float32"):
                capture.check_image(image)
        image[...] = 0.0


def test_clipping_warnings_count_pixels_clipped_in_any_channel():
    """16 sphere pixels at the image maximum warn that it looks clipped (15 do not; a sphere of ~5000 pixels,
    whose 0.2% is fewer), also when only the red channel reaches it (a red highlight)."""
    image, geo = sphere_image(radius=40.0)
    _, mask = geo.normals(128, 128)
    rows, cols = np.nonzero(mask)
    for count, warns in ((16, True), (15, False)):
        clipped = image.copy()
        clipped[rows[:count], cols[:count], 0] = 5.0             # red only; green and blue stay below
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            capture.observations_from_sphere(clipped, geo, n_normals=1000)
        assert any("looks clipped" in str(w.message) for w in seen) is warns, count


def test_unusable_values_warn_above_five_percent_and_few_rows_below_256():
    """Of the sampled sphere pixels: 10% non-finite warn (more than 5%), 4% do not; fewer than 256 usable rows
    warn, 256 or more do not."""
    image, geo = sphere_image()
    clean = capture.observations_from_sphere(image, geo, n_normals=3000)
    rows, cols = clean.pixels.T
    for share, warns in ((0.10, True), (0.04, False)):
        bad = image.copy()
        k = int(share * len(clean))
        bad[rows[:k], cols[:k], 2] = np.nan
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            capture.observations_from_sphere(bad, geo, n_normals=3000)
        assert any("unusable values" in str(w.message) for w in seen) is warns, share
    sizes = []
    for n_normals in (300, 400):                           # 241 and 329 usable rows
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            sizes.append(len(capture.observations_from_sphere(image, geo, n_normals=n_normals)))
        assert any("usable observations" in str(w.message) for w in seen) is (sizes[-1] < 256), sizes
    assert sizes[0] < 256 <= sizes[1]


def test_a_sphere_whose_only_light_is_in_dropped_pixels_is_black():
    """Positive values only in pixels that are dropped (saturated) leave a black sphere: refused."""
    image, geo = sphere_image()
    obs = capture.observations_from_sphere(image, geo, n_normals=1000)
    dark = np.zeros_like(image)
    dark[obs.pixels[::2, 0], obs.pixels[::2, 1]] = 10.0
    with pytest.raises(InputError, match="black on the object"):
        capture.observations_from_sphere(dark, geo, n_normals=1000, saturation=5.0)


def test_an_object_placed_where_the_photo_is_dark_is_not_called_a_black_image():
    """Every pixel where the sphere is placed is 0, while the photo has light elsewhere (a helper's perspective
    sphere far too large for its image): the error says where the object is placed is the problem, not that
    the image is black."""
    image, geo = sphere_image()
    elsewhere = np.zeros_like(image)
    elsewhere[:3, :3] = 1.0  # a lit corner outside the sphere
    assert not capture.observations_from_sphere(image, geo, n_normals=200).pixels[:, 0].min() < 3
    with pytest.raises(InputError, match="no positive pixel value where the object is placed, though the photo has "
                                         "light elsewhere .check where the object is"):
        capture.observations_from_sphere(elsewhere, geo, n_normals=1000)
    with pytest.raises(InputError, match="black on the object"):  # nothing lit anywhere: black, as before
        capture.observations_from_sphere(np.zeros_like(image), geo, n_normals=1000)


def test_a_subset_in_another_order_keeps_each_footprint_with_its_row():
    """``subset`` with rows in another order (a permutation): the footprint normals follow their rows and stay
    ascending by row."""
    image, geo = sphere_image()
    obs = capture.observations_from_sphere(image, geo, n_normals=600, max_view_angle_deg=88.0, footprint=1.0)
    order = np.random.default_rng(1).permutation(len(obs))
    sub = obs.subset(order)
    assert len(sub.footprint_rows) == len(obs.footprint_rows) > 50 and np.all(np.diff(sub.footprint_rows) >= 0)
    for new in np.unique(sub.footprint_rows)[:20]:
        np.testing.assert_array_equal(sub.footprint_normals[sub.footprint_rows == new],
                                      obs.footprint_normals[obs.footprint_rows == order[new]])


def _user_normal_map(size: int = 64) -> tuple:
    """A shaded sphere with a user's normal map of it, broken in three known blocks inside its mask: zero
    normals (64 pixels), zero geometric normals (16) and unknown positions (8). Returns
    ``(image, normals, mask, positions, geometric_normals, broken)``, ``broken`` the blocks' ``(H, W) bool``."""
    image, geo = sphere_image(size, radius=0.45 * size)
    normals, mask = geo.normals(size, size)
    positions = np.where(mask[..., None], normals, 0.0)        # a unit sphere at the origin
    geometric = normals.copy()
    broken = np.zeros(mask.shape, bool)
    for (rows, cols), (array, value) in zip(
            [((28, 36), (28, 36)), ((20, 24), (40, 44)), ((40, 42), (20, 24))],
            [(normals, 0.0), (geometric, 0.0), (positions, np.nan)]):
        array[rows[0]:rows[1], cols[0]:cols[1]] = value
        broken[rows[0]:rows[1], cols[0]:cols[1]] = True
    assert mask[broken].all()
    return image, normals, mask, positions, geometric, broken


def test_a_normal_maps_unusable_pixels_in_its_mask_are_left_out_with_a_warning():
    """A user's normal map with zero normals, zero geometric normals or unknown positions inside its mask:
    those pixels were left out without a word, and a zero geometric normal was kept as the row's (a shadow ray
    without spawn_ray's offset). Now each such pixel is left out, counted per cause in one InputWarning, and
    every row's normal and geometric normal is a unit vector at a finite position; a map with no usable
    normal in its mask is refused."""
    image, normals, mask, positions, geometric, broken = _user_normal_map()
    with pytest.warns(InputWarning, match=f"88 of {mask.sum()} pixels in the mask are not used: 64 without a "
                                          r"usable normal .*, 8 without a usable position .*, 16 without a "
                                          "usable geometric normal"):
        obs = capture.observations_from_normal_map(image, normals, mask, [0.0, 0.0, 1.0], n_normals=1000,
                                                   positions=positions, geometric_normals=geometric)
    rows, cols = obs.pixels.T
    assert len(obs) > 300 and mask[rows, cols].all() and not broken[rows, cols].any()
    np.testing.assert_allclose(np.linalg.norm(obs.normals, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(obs.geometric_normals, axis=1), 1.0, rtol=1e-12)
    assert np.all(np.isfinite(obs.positions))
    with warnings.catch_warnings():
        warnings.simplefilter("error")                               # a sound map says nothing
        capture.observations_from_normal_map(image, 3.0 * normals, mask & ~broken,
                                             [0.0, 0.0, 1.0], n_normals=1000, positions=positions,
                                             geometric_normals=3.0 * geometric)
    with pytest.raises(InputError, match="the mask selects no pixel with a valid normal"):
        capture.observations_from_normal_map(image, np.zeros_like(normals), mask, [0.0, 0.0, 1.0])


def test_recover_through_a_users_geometry_leaves_its_broken_normals_out():
    """A normal map reaches a recovery as a user's :class:`Geometry` (its ``surface_maps``): its broken pixels
    warn and add no row. The command line takes no normal map: its spheres' normals are computed (an
    orthographic sphere's by the lattice; ``--fov``'s perspective sphere's map, which says nothing)."""
    from mi_bivariate.geometry import Geometry, SurfaceMaps
    from mi_bivariate.recover import recover

    image, normals, mask, positions, geometric, broken = _user_normal_map()
    perspective = PerspectiveSphereGeometry(Intrinsics(60.0, 60.0, 32.0, 32.0), [0.2, 0.1, -3.0], 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        capture.image_observations(image, perspective, n_normals=1000)

    class UserNormalMap(Geometry):
        def surface_maps(self, width, height, source="image"):
            return SurfaceMaps(normals=normals, views=np.broadcast_to([0.0, 0.0, 1.0], normals.shape).copy(),
                               mask=mask, positions=positions, geometric_normals=geometric)

    with pytest.warns(InputWarning, match="88 of .* pixels in the mask are not used"):
        result = recover(image, _constant_probe(), UserNormalMap(), n_normals=400, n_dirs=400, grid=(8, 8),
                         basis_prior=None, noise="auto")
    rows, cols = result.observations.pixels.T
    assert not broken[rows, cols].any() and np.all(np.isfinite(result.observations.normals))
    assert np.all(np.isfinite(result.brdf.table))
