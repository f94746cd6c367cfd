"""The camera noise model: estimation from one image against the noise that was added."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate.errors import InputError
from mi_bivariate.noise import estimate_camera_noise


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
