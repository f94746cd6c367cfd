"""The camera noise model: estimation from one image against the noise that was added."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.noise import estimate_camera_noise
from mi_bivariate.recover import _estimate_noise


def add_camera_noise(image, a, b, seed):
    """Gaussian noise of variance a I + b, independent per pixel and channel (the model itself)."""
    rng = np.random.default_rng(seed)
    return image + np.sqrt(a * np.maximum(image, 0) + b) * rng.standard_normal(image.shape)


def _sphere_like(n: int = 256) -> tuple:
    y, x = np.mgrid[0:n, 0:n] + 0.5
    r2 = ((x - n / 2) ** 2 + (y - n / 2) ** 2) / (0.45 * n) ** 2
    mask = r2 < 1
    z = np.sqrt(np.clip(1 - r2, 0, 1))
    clean = 0.05 + 2.0 * z**3 + 0.5 * x / n  # smooth shading over a 40x range
    return np.repeat(clean[..., None], 3, axis=2), mask


@pytest.mark.parametrize("a,b", [(0.01, 1e-4), (0.0, 4e-4), (0.02, 0.0)])
def test_estimate_recovers_the_added_noise(a, b):
    clean, mask = _sphere_like()
    noisy = add_camera_noise(clean, a, b, seed=1)
    # Per-pixel channels carry independent noise; the estimator sees their mean (variance / 3).
    a_hat, b_hat = estimate_camera_noise(noisy, mask)
    level = np.median(clean[mask, 0])
    assert a_hat * level + b_hat == pytest.approx((a * level + b) / 3, rel=0.25)
    high = np.quantile(clean[mask, 0], 0.95)
    assert a_hat * high + b_hat == pytest.approx((a * high + b) / 3, rel=0.25)


def test_clean_image_has_almost_no_noise_and_bad_input_is_an_input_error():
    clean, mask = _sphere_like()
    a_hat, b_hat = estimate_camera_noise(clean, mask)
    assert a_hat * 2.0 + b_hat < 1e-5
    with pytest.raises(InputError):
        estimate_camera_noise(clean[:5, :5], mask[:5, :5])


def test_chi_square_quantile_matches_scipy_stats():
    import scipy.stats

    from mi_bivariate import noise

    assert noise._CHI2_QUANTILE == pytest.approx(float(scipy.stats.chi2.ppf(noise.QUANTILE, 1)), rel=1e-12)


def test_camera_noise_level_is_the_relative_noise_at_the_mean_signal():
    """``level`` is the noise's relative std at the image's mean signal: a flat image at ``v`` gets std
    ``level v sqrt(1 + READ_FRACTION^2)`` (shot noise ``level v``, read noise ``READ_FRACTION`` of it)."""
    from mi_bivariate.noise import READ_FRACTION, add_camera_noise

    v, level = 7.0, 0.02
    noisy = add_camera_noise(np.full((200, 200, 3), v, np.float32), level, seed=3).astype(np.float64)
    assert np.std(noisy) / v == pytest.approx(level * np.sqrt(1.0 + READ_FRACTION**2), rel=0.01)
    assert np.mean(noisy) == pytest.approx(v, rel=1e-3)


def test_noise_reference_is_the_objects_mean_and_every_lit_pixel_gets_noise():
    """``I_ref`` is the mean over the non-zero pixels (a black background does not dilute it), and a pixel
    with any non-zero channel is the object's: its black channels get noise too; black pixels stay black."""
    from mi_bivariate.noise import READ_FRACTION, add_camera_noise, noise_parameters

    image = np.zeros((40, 40, 3))
    image[10:30, 10:30] = [4.0, 0.0, 2.0]  # the object, one channel black; the rest background
    level = 0.05
    ref = 3.0  # mean of the non-zero values
    a, b = noise_parameters(image, level)
    assert a == pytest.approx(level**2 * ref, rel=1e-12)
    assert b == pytest.approx((READ_FRACTION * level * ref) ** 2, rel=1e-12)
    noisy = add_camera_noise(image, level, seed=1).astype(np.float64)
    np.testing.assert_array_equal(noisy[:10], 0.0)
    green = noisy[10:30, 10:30, 1]
    assert np.std(green) == pytest.approx(np.sqrt(b), rel=0.15)  # read noise alone where the signal is 0


def test_estimate_holds_at_the_dark_and_bright_ends():
    """The fitted a I + b against the added noise (variance / 3: the channels' mean) at the 2% and 98%
    quantiles of the signal, where the read-noise floor and the shot noise dominate in turn."""
    clean, mask = _sphere_like()
    a, b = 0.01, 1e-4
    a_hat, b_hat = estimate_camera_noise(add_camera_noise(clean, a, b, seed=1), mask)
    for q in (0.02, 0.98):
        level = np.quantile(clean[mask, 0], q)
        assert a_hat * level + b_hat == pytest.approx((a * level + b) / 3, rel=0.15), q


def test_estimate_uses_only_second_differences_inside_the_mask():
    """A mask with holes every fourth row and column (masked-out highlights, say): pixels next to a hole
    have no second difference; the estimate is the added noise's."""
    clean, mask = _sphere_like()
    y, x = np.mgrid[0:256, 0:256]
    holes = mask & (x % 4 != 0) & (y % 4 != 0)
    a, b = 0.01, 1e-4
    a_hat, b_hat = estimate_camera_noise(add_camera_noise(clean, a, b, seed=2), holes)
    level = np.median(clean[holes, 0])
    assert a_hat * level + b_hat == pytest.approx((a * level + b) / 3, rel=0.25)


def _second_differences_by_loops(image, mask):
    """Every ``(centre, I[x-1] - 2 I[x] + I[x+1])`` along rows and columns whose three pixels are in the mask,
    by plain loops (a second implementation)."""
    pairs = []
    h, w = image.shape
    for y in range(h):
        for x in range(w):
            for dy, dx in ((1, 0), (0, 1)):
                y0, x0, y1, x1 = y - dy, x - dx, y + dy, x + dx
                if 0 <= y0 and 0 <= x0 and y1 < h and x1 < w and mask[y0, x0] and mask[y, x] and mask[y1, x1]:
                    pairs.append((image[y, x], image[y0, x0] - 2.0 * image[y, x] + image[y1, x1]))
    return sorted(pairs)


def test_second_differences_are_every_in_mask_triplet_along_rows_and_columns():
    """Against plain loops on a random image and mask: both axes, and only triplets whose three pixels (the
    centre too: a one-pixel hole splits a row) lie in the mask."""
    from mi_bivariate.noise import _second_differences

    rng = np.random.default_rng(4)
    image = rng.random((12, 13))
    mask = rng.random((12, 13)) < 0.8
    level, d = _second_differences(np.where(mask, image, 0.0), mask)
    want = _second_differences_by_loops(image, mask)
    assert len(want) > 40
    np.testing.assert_allclose(sorted(zip(level, d)), want, rtol=0, atol=1e-15)


def test_a_flat_noise_free_image_has_no_noise():
    """Every centre value equal: no signal dependence to fit and no noise, ``(0, 0)`` (not an error)."""
    assert estimate_camera_noise(np.full((40, 40), 0.7)) == (0.0, 0.0)


def test_too_few_pixels_are_refused_with_their_count():
    """Fewer than 100 second differences, or fewer than 20 in each intensity bin (up to ~240), is too few pixels
    for a per-intensity estimate, and says so (not that a varied image is "too uniform")."""
    rng = np.random.default_rng(0)
    ramp = np.linspace(1.0, 2.0, 300)[None, :] + 0.01 * rng.standard_normal((1, 300))
    with pytest.raises(InputError) as caught:
        estimate_camera_noise(ramp[:, :101])                 # a one-row strip: 99 triplets
    assert caught.value.problem == "only 99 usable pixels to estimate the noise from"
    with pytest.raises(InputError, match="only 198 usable pixels to estimate the noise from"):
        estimate_camera_noise(ramp[:, :200])                 # 12 bins of 16 or 17
    a_hat, b_hat = estimate_camera_noise(ramp)               # 298: bins of 24 or 25
    assert a_hat * 1.5 + b_hat == pytest.approx(1e-4, rel=0.5)


@pytest.mark.parametrize("shape", [(500,), (4, 20, 20), (20, 20, 4), (20, 20, 1, 3)])
def test_an_image_of_another_shape_is_refused(shape):
    """(H, W) or (H, W, 3) only: a 1-D row of values or an RGBA image (whose alpha would be averaged into the
    signal) is an InputError, not a numpy traceback or a wrong estimate."""
    with pytest.raises(InputError, match="expected an \\(H, W\\) or \\(H, W, 3\\) image"):
        estimate_camera_noise(np.ones(shape))


def test_non_finite_pixels_inside_the_mask_are_left_out():
    """A NaN or an infinity inside the given mask counts as outside it: the same estimate as with those
    pixels masked out by the caller."""
    clean, mask = _sphere_like(96)
    noisy = add_camera_noise(clean, 0.01, 1e-4, seed=5)[..., 0]
    bad = noisy.copy()
    bad[40, 40], bad[50, 30], bad[30, 60] = np.nan, np.inf, -np.inf
    without = mask.copy()
    without[40, 40] = without[50, 30] = without[30, 60] = False
    assert estimate_camera_noise(bad, mask) == estimate_camera_noise(noisy, without)
    assert np.all(np.isfinite(estimate_camera_noise(bad)))   # no mask: every finite pixel


@pytest.mark.parametrize("seed", [1, 2])
def test_estimate_holds_across_a_high_dynamic_range(seed):
    """An HDR image (a smooth ramp over four decades, 1e-3 .. 10): the fitted a I + b against the added noise
    at the 2%, 50% and 98% quantiles. The per-bin variances differ by 1e4, so an unweighted fit would follow
    the bright bins' scatter and leave the read-noise floor free (3-6x off at the dark end, measured)."""
    n = 256
    y, x = np.mgrid[0:n, 0:n] + 0.5
    clean = 1e-3 * np.exp(np.log(1e4) * x / n) * (1 + 0.2 * np.sin(3 * y / n))
    a, b = 1e-4, 1e-8
    noisy = clean + np.sqrt(a * clean + b) * np.random.default_rng(seed).standard_normal(clean.shape)
    a_hat, b_hat = estimate_camera_noise(noisy)
    for q in (0.02, 0.5, 0.98):
        level = np.quantile(clean, q)
        assert a_hat * level + b_hat == pytest.approx(a * level + b, rel=0.2), q


def test_noise_models_accept_zero_and_refuse_what_is_not_finite_and_non_negative():
    """``(a, b)`` each a number or three, finite and >= 0: zero is a model (no read noise, or no shot noise),
    in either place and per channel; NaN, infinity or a negative value in either is refused; a per-channel
    array is the caller's no longer (a copy)."""
    from mi_bivariate.noise import check_noise_model

    for given in [(0.0, 1e-4), (1e-3, 0.0), (0.0, 0.0), ([1e-3, 0.0, 2e-3], [0.0, 1e-4, 0.0])]:
        a, b = check_noise_model(given)
        np.testing.assert_array_equal(a, given[0])
        np.testing.assert_array_equal(b, given[1])
    for bad in [np.nan, np.inf, -1e-6]:
        for given in [(bad, 1e-4), (1e-3, bad), ([1e-3, bad, 1e-3], 1e-4), (1e-3, [1e-4, 1e-4, bad])]:
            with pytest.raises(InputError, match="must be finite and >= 0"):
                check_noise_model(given, "noise")
    per_channel = np.array([1e-3, 2e-3, 3e-3])
    a, _ = check_noise_model((per_channel, 0.0))
    per_channel[:] = 1.0
    np.testing.assert_array_equal(a, [1e-3, 2e-3, 3e-3])


def test_camera_noise_level_must_be_finite():
    """An infinite noise level is refused (it made every object pixel infinite), as NaN and negative ones are."""
    from mi_bivariate.noise import add_camera_noise as camera_noise

    for level in (np.inf, np.nan, -0.01):
        with pytest.raises(InputError, match="noise level must be a finite number >= 0"):
            camera_noise(np.ones((8, 8, 3)), level)


def _antialiased_sphere(size, cx, cy, r, ss=4, background=None):
    """A shaded sphere as a camera sees it: each pixel the mean of ``ss x ss`` samples (so rim pixels mix
    with the background: black, or ``background`` ``(size, size)`` constant over each pixel),
    ``(size, size)``."""
    o = (np.arange(size * ss) + 0.5) / ss
    x, y = np.meshgrid(o, o)
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / r**2
    behind = 0.0 if background is None else np.repeat(np.repeat(background, ss, axis=0), ss, axis=1)
    shade = np.where(r2 < 1, 0.3 + 2.0 * (1 - r2) + 0.3 * (x - cx) / r, behind)
    return shade.reshape(size, ss, size, ss).mean(axis=(1, 3))


def test_recover_auto_noise_is_each_channels_own_also_on_a_sphere_the_frame_cuts():
    """``recover(noise="auto")``'s per-channel estimate (recover._estimate_noise: lit pixels eroded by 2) on an
    antialiased sphere that the image frame cuts on two sides (the erosion leaves the frame's own rows and
    columns alone; there the sphere is cut, not mixed with the background): each channel's fitted
    ``a I + b`` against its own added noise at the lit pixels' median and 95% quantile."""
    shade = _antialiased_sphere(128, cx=40.0, cy=50.0, r=70.0)
    lit = shade > 0
    assert lit[0].any() and lit[:, 0].any()                    # the sphere reaches the frame
    clean = shade[..., None] * np.array([1.0, 0.7, 0.4])
    a, b = np.array([0.02, 0.005, 0.01]), np.array([1e-5, 4e-4, 1e-4])
    noisy = np.where(lit[..., None], add_camera_noise(clean, a, b, seed=3), 0.0)
    a_hat, b_hat = _estimate_noise(noisy, SphereGeometry(40.0, 50.0, 70.0), "image")
    for q in (0.5, 0.95):
        level = np.quantile(clean[lit], q, axis=0)
        np.testing.assert_allclose(a_hat * level + b_hat, a * level + b, rtol=0.25, err_msg=str(q))


def test_recover_auto_noise_leaves_a_lit_textured_background_out():
    """A photo's background is lit and has detail of its own (here a random texture of 0.2-2.2, as bright as
    the sphere), which the second differences would read as noise: ``recover(noise="auto")`` estimates over
    the pixels the geometry puts on the object (and their antialiased rim), so each channel's ``a I + b`` is
    the one a black background gives, its own added noise. Over the whole frame it was 5-6x too high."""
    shade = _antialiased_sphere(128, cx=64.0, cy=60.0, r=40.0)
    lit = shade > 0
    colour = np.array([1.0, 0.7, 0.4])
    clean = shade[..., None] * colour
    texture = np.random.default_rng(4).uniform(0.2, 2.2, (128, 128))
    photo = _antialiased_sphere(128, cx=64.0, cy=60.0, r=40.0, background=texture)[..., None] * colour
    a, b = np.array([0.02, 0.005, 0.01]), np.array([1e-5, 4e-4, 1e-4])
    a_hat, b_hat = _estimate_noise(add_camera_noise(photo, a, b, seed=5), SphereGeometry(64.0, 60.0, 40.0), "image")
    for q in (0.5, 0.95):
        level = np.quantile(clean[lit], q, axis=0)
        np.testing.assert_allclose(a_hat * level + b_hat, a * level + b, rtol=0.25, err_msg=str(q))


def test_recover_auto_noise_leaves_out_what_the_users_mask_leaves_out():
    """A label on the sphere (a random texture of 0.2-2.2, as bright as the sphere), masked out by the user:
    ``recover(noise="auto")`` estimated the noise over every pixel the geometry puts on the object, mask or
    not, so the label's own detail read as noise (1.5-1.8x the added noise at the median level). Now the
    estimate keeps to the mask: each channel's ``a I + b`` is its own added noise."""
    from mi_bivariate.probes import Probe
    from mi_bivariate.recover import recover

    shade = _antialiased_sphere(96, cx=48.0, cy=48.0, r=40.0)
    mask = np.ones(shade.shape, bool)
    mask[20:60, 45:80] = False                                   # the label, wholly on the sphere
    photo = np.where(mask, shade, np.random.default_rng(6).uniform(0.2, 2.2, shade.shape))
    colour = np.array([1.0, 0.7, 0.4])
    a, b = np.array([0.02, 0.005, 0.01]), np.array([1e-5, 4e-4, 1e-4])
    noisy = add_camera_noise(photo[..., None] * colour, a, b, seed=7).astype(np.float32)
    sphere = SphereGeometry(48.0, 48.0, 40.0)
    result = recover(noisy, Probe.constant([1.0, 0.9, 0.8], res=16), sphere, masks=mask, noise="auto",
                     n_normals=200, n_dirs=400, grid=(8, 8), basis_prior=None)
    a_hat, b_hat = (np.asarray(v) for v in result.brdf.provenance["noise"][0])
    unmasked_a, unmasked_b = _estimate_noise(noisy, sphere, "image")  # the texture counted: the old estimate
    clean = shade[..., None] * colour
    for q in (0.5, 0.95):
        level = np.quantile(clean[(shade > 0) & mask], q, axis=0)
        np.testing.assert_allclose(a_hat * level + b_hat, a * level + b, rtol=0.25, err_msg=str(q))
    level = np.quantile(clean[(shade > 0) & mask], 0.5, axis=0)
    assert np.all(unmasked_a * level + unmasked_b > 1.4 * (a * level + b))  # the label does read as noise


def test_nonnegative_fit_is_scipy_nnls():
    """A second implementation: ``scipy.optimize.nnls`` on two-unknown problems whose solution lies on
    each face of the constraints (both free, the slope at zero, the offset at zero, both at zero),
    on a zero column, and on the estimate's own kind of design (bin levels and weights)."""
    from scipy.optimize import nnls

    from mi_bivariate.noise import nonnegative_fit

    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 2.0, 12)
    ones = np.ones_like(x)
    cases = [(np.stack([x, ones], 1), 0.3 * x + 0.1),          # both free
             (np.stack([x, ones], 1), -0.3 * x + 0.5),         # slope at zero
             (np.stack([x, ones], 1), 0.4 * x - 0.2),          # offset at zero
             (np.stack([x, ones], 1), -0.4 * x - 0.2),         # both at zero
             (np.stack([np.zeros_like(x), ones], 1), x),        # a zero column
             (np.stack([x, x], 1), 0.5 * x)]                    # collinear columns
    for _ in range(200):
        w = rng.uniform(0.1, 10.0, 12)
        cases.append((np.stack([rng.uniform(0, 3, 12), ones], 1) * w[:, None], rng.normal(0.0, 1.0, 12) * w))
    for scale in (1e-20, 1e20):  # an image's scale: the columns differ by it (both faces active and not)
        w = rng.uniform(0.5, 2.0, 12) / scale**2
        for slope, offset in ((0.01, 1e-3), (0.01, -1e-3)):
            variance = (slope * x + offset) * scale**2 * (1 + 0.05 * rng.standard_normal(12))
            cases.append((np.stack([x * scale, ones], 1) * w[:, None], variance * w))
    w = np.where(np.arange(12) < 6, 1e300, 1.0)  # the estimate's weight of a bin of no noise (variance 1e-300)
    cases.append((np.stack([x, ones], 1) * w[:, None], (0.3 * x + 1e-3) * w * 1e-300))
    for design, target in cases:
        ours = np.array(nonnegative_fit(design, target))
        theirs, _ = nnls(design, target)
        assert np.all(ours >= 0) and np.all(np.isfinite(ours))
        scale = np.max(np.abs(design), axis=0)
        scale = np.where(scale > 0, scale, 1.0)  # the columns by their size: the estimate's differ by 1e20
        residual, best = (np.linalg.norm((design / scale) @ (sol * scale) - target) for sol in (ours, theirs))
        assert residual <= best * (1 + 1e-9) + 1e-14 * np.max(np.abs(target))
        if np.linalg.matrix_rank(design / scale) == 2:  # unique solution
            np.testing.assert_allclose(ours * scale, theirs * scale, rtol=1e-7, atol=1e-12 * np.max(np.abs(theirs * scale)))


def test_a_large_objects_estimate_samples_evenly_spaced_rows_and_columns():
    """An object of 1.6 M pixels gives ~3.3 M second differences; the estimate takes every 7th row and column
    (``MAX_SECOND_DIFFERENCES``) and lands within 3% of the estimate from all of them, which itself holds
    the added noise to 25% (as on smaller images), at the median and the bright end. The thinned
    differences are exactly the full set's along those rows and columns."""
    from mi_bivariate import noise
    from mi_bivariate.noise import _second_differences

    clean, mask = _sphere_like(1600)
    a, b = 0.01, 1e-4
    noisy = add_camera_noise(clean, a, b, seed=2)[..., 0]
    step = -(-2 * np.count_nonzero(mask) // noise.MAX_SECOND_DIFFERENCES)
    assert step == 7
    steps = []

    def recorded(image, m, step=1):
        steps.append(step)
        return _second_differences(image, m, step)

    noise._second_differences = recorded
    try:
        thinned = estimate_camera_noise(noisy, mask)
    finally:
        noise._second_differences = _second_differences
    assert steps == [7]
    saved = noise.MAX_SECOND_DIFFERENCES
    try:
        noise.MAX_SECOND_DIFFERENCES = 10**12
        full = estimate_camera_noise(noisy, mask)
    finally:
        noise.MAX_SECOND_DIFFERENCES = saved
    for level in (np.median(clean[mask, 0]), np.quantile(clean[mask, 0], 0.95)):
        assert thinned[0] * level + thinned[1] == pytest.approx(full[0] * level + full[1], rel=0.03)
        assert thinned[0] * level + thinned[1] == pytest.approx(a * level + b, rel=0.25)
    image = np.where(mask, noisy, 0.0)
    level, d = _second_differences(image, mask, step=step)
    want_rows = _second_differences(image[::step], mask[::step])  # along the rows: within rows 0, 7, 14, ...
    want_cols = _second_differences(image[:, ::step], mask[:, ::step])
    n_cols = np.count_nonzero(mask[:-2, ::step] & mask[1:-1, ::step] & mask[2:, ::step])  # down the columns first
    np.testing.assert_array_equal(d[:n_cols], want_cols[1][:n_cols])
    n_rows = np.count_nonzero(mask[::step, :-2] & mask[::step, 1:-1] & mask[::step, 2:])
    np.testing.assert_array_equal(np.sort(d[n_cols:]), np.sort(want_rows[1][len(want_rows[1]) - n_rows:]))
    assert len(d) == n_cols + n_rows


def test_thinning_keeps_every_phase_of_a_bayer_patterned_noise():
    """Noise whose level alternates with the pixel's row and column parity (a demosaiced photo's Bayer
    pattern): a 1000 x 1000 ramp needs a step of 4 by count, made odd (5), so the thinned rows and columns
    take every phase and the estimate stays within 5% of the full one (with step 4 it was 0.56x; a
    helper's review)."""
    from mi_bivariate import noise

    y, x = np.mgrid[0:1000, 0:1000]
    clean = 0.2 + 0.8 * (x + y) / 2000.0
    sigma = np.array([[0.004, 0.008], [0.008, 0.016]])[y % 2, x % 2]
    image = clean + sigma * np.random.default_rng(0).standard_normal(clean.shape)
    thinned = estimate_camera_noise(image)
    saved = noise.MAX_SECOND_DIFFERENCES
    try:
        noise.MAX_SECOND_DIFFERENCES = 10**12
        full = estimate_camera_noise(image)
    finally:
        noise.MAX_SECOND_DIFFERENCES = saved
    assert thinned[0] * 0.6 + thinned[1] == pytest.approx(full[0] * 0.6 + full[1], rel=0.05)


def test_the_estimate_does_not_depend_on_where_the_object_sits_in_the_frame():
    """The estimate works in its mask's box, and a large object's thinned rows and columns are counted from
    the mask's first row and column: the same object placed elsewhere in a larger frame (offsets that are
    not multiples of the step, a lit background around it) gives the same ``(a, b)``, bit for bit, thinned
    (step 7) or not, float32 or float64; a mask of another shape than the image is refused."""
    for n, dtype in ((1600, np.float32), (256, np.float64)):
        clean, mask = _sphere_like(n)
        noisy = add_camera_noise(clean, 0.01, 1e-4, seed=3)[..., 0].astype(dtype)
        alone = estimate_camera_noise(noisy, mask)
        for dy, dx in ((3, 5), (11, 2)):
            frame = np.full((n + 20, n + 30), 7.0, dtype)
            frame[dy:dy + n, dx:dx + n] = noisy
            placed = np.zeros(frame.shape, bool)
            placed[dy:dy + n, dx:dx + n] = mask
            assert estimate_camera_noise(frame, placed) == alone
    with pytest.raises(InputError, match="mask has shape"):
        estimate_camera_noise(noisy, mask[:-1])


def test_the_noise_estimate_in_the_objects_box_is_the_whole_frames():
    """``recover``'s noise estimate (``_estimate_noise``: the lit pixels near the object, within the user's
    mask, eroded; each channel's estimate) is found in the object's box, widened by what the dilation and
    erosion reach: the same ``(a, b)``, bit for bit, as the whole frame's computation written out here, for a
    sphere inside the frame and one the frame cuts (its edge rows are left uneroded), with and without a
    user's mask, and a black hole and a NaN on the object."""
    from scipy import ndimage

    def whole_frame(image, geometry, mask):
        lit = np.all(np.isfinite(image), axis=2) & np.all(image > 0, axis=2)
        near = ndimage.binary_dilation(geometry.object_mask(image.shape[1], image.shape[0]), iterations=2)
        interior = np.zeros_like(lit)
        interior[1:-1, 1:-1] = True
        region = lit & near if mask is None else lit & near & mask
        inner = ndimage.binary_erosion(region, iterations=2, border_value=1, mask=interior)
        pairs = [estimate_camera_noise(image[..., c], inner) for c in range(3)]
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    clean, _ = _sphere_like(200)
    image = np.full((240, 260, 3), 0.3)
    image[20:220, 30:230] = clean
    image = add_camera_noise(image, 0.01, 1e-4, seed=4).astype(np.float32)
    image[100:104, 100:110] = 0.0
    image[60, 140, 1] = np.nan
    user = np.ones(image.shape[:2], bool)
    user[:, 150:] = False
    for geometry in (SphereGeometry(130.2, 120.4, 90.0), SphereGeometry(10.3, 120.4, 90.0),
                     SphereGeometry(130.2, 236.0, 90.0)):
        for mask in (None, user):
            got, want = _estimate_noise(image, geometry, "image", mask), whole_frame(image, geometry, mask)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def test_the_noise_estimate_asks_a_perspective_sphere_for_its_pixels_once(monkeypatch):
    """A geometry whose mask costs its surface maps (a perspective sphere: normals and views of the whole
    frame) is asked once by ``recover``'s noise estimate (a helper's review found the first box version
    asking twice: 2.4 -> 4.1 s on a 2048 px photo)."""
    from mi_bivariate.geometry import Intrinsics, PerspectiveSphereGeometry

    geometry = PerspectiveSphereGeometry(Intrinsics(300.0, 300.0, 100.0, 90.0), [0.0, 0.0, -5.0], 1.0)
    calls = []
    maps = PerspectiveSphereGeometry.surface_maps
    monkeypatch.setattr(PerspectiveSphereGeometry, "surface_maps",
                        lambda self, *args, **kwargs: calls.append(1) or maps(self, *args, **kwargs))
    clean, _ = _sphere_like(200)
    image = add_camera_noise(np.pad(clean, ((0, 0), (0, 0), (0, 0))), 0.01, 1e-4, seed=5).astype(np.float32)
    a, b = _estimate_noise(image, geometry, "image")
    assert len(calls) == 1 and np.all(np.isfinite(a)) and np.all(np.isfinite(b))
