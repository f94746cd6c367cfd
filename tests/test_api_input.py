"""The library's front doors refuse bad input as the CLI does: an :class:`InputError` naming the
argument, before any work, not a traceback from deep inside Dr.Jit or numpy (a review of the Python
API as a researcher uses it, 2026-12-06)."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from mi_bivariate import capture, metrics, recover as recover_mod, render
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.geometry import Intrinsics, PerspectiveSphereGeometry, SphereGeometry
from mi_bivariate.probes import Probe
from mi_bivariate.prior import default_prior
from mi_bivariate.recover import recover

IMAGE = np.full((48, 48, 3), 0.5, np.float32)
SPHERE = SphereGeometry(24.0, 24.0, 20.0)
SMALL = dict(n_normals=200, n_dirs=400, grid=(8, 8), basis_prior=None, noise=None)


@pytest.fixture
def probe() -> Probe:
    return Probe.constant([1.0, 0.9, 0.8], res=16)


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if a recovery gets as far as reading its image's pixels."""
    def refuse(*args, **kwargs):
        raise AssertionError("the recovery started work before refusing its arguments")

    monkeypatch.setattr(capture, "image_observations", refuse)


# ------------------------------------------------------------------ the table

def test_a_table_is_a_checked_copy_and_save_writes_no_file_load_refuses(tmp_path):
    """Before, the table shared the caller's array: a NaN put there afterwards was saved, and load refused
    the file."""
    values = np.ones((8, 8, 3), np.float32)
    confidence = np.zeros((8, 8, 3))
    brdf = BivariateBRDF(values, confidence={"measured": confidence})
    values[0, 0, 0], confidence[0, 0, 0] = np.nan, np.nan
    assert np.all(np.isfinite(brdf.table)) and np.all(np.isfinite(brdf.confidence["measured"]))
    brdf.save(tmp_path / "t.npz")
    np.testing.assert_array_equal(BivariateBRDF.load(tmp_path / "t.npz").table, np.ones((8, 8, 3)))
    brdf.table[0, 0, 0] = -1.0
    with pytest.raises(InputError, match="negative values") as info:
        brdf.save(tmp_path / "u.npz")
    assert info.value.source == str(tmp_path / "u.npz") and not (tmp_path / "u.npz").exists()
    brdf.table[0, 0, 0] = 1.0
    brdf.confidence["measured"][0, 0, 0] = np.nan
    with pytest.raises(InputError, match="confidence map 'measured' must be finite"):
        brdf.save(tmp_path / "u.npz")
    brdf.confidence["measured"][0, 0, 0] = 0.0
    brdf.table = np.ones((4, 4, 3), np.float32)  # another grid than the confidence maps'
    with pytest.raises(InputError, match=r"confidence map 'measured' must be finite and shaped \(4, 4, 3\)"):
        brdf.save(tmp_path / "u.npz")
    assert not (tmp_path / "u.npz").exists()


def test_table_lookup_of_nan_angles_is_nan():
    brdf = BivariateBRDF(np.ones((8, 8, 3)))
    value = brdf.eval(np.array([np.nan, 0.2]), 0.3)
    assert np.all(np.isnan(value[0])) and np.allclose(value[1], 1.0)


def test_reduce_refuses_a_probe_and_a_grid_of_fractions(probe):
    with pytest.raises(InputError, match="got a Probe where a BRDF goes"):
        BivariateBRDF.reduce(probe, 8, 8)
    with pytest.raises(InputError, match="must be a whole number"):
        BivariateBRDF.reduce(BivariateBRDF(np.ones((8, 8, 3))), 8.5, 8)


def test_plugins_refuse_a_scalar_variant_in_one_line(tmp_path):
    """The plugins are written for wide arrays: under scalar_rgb they said a 30-line TypeError; now the
    plugin's own error says which variants to use."""
    BivariateBRDF(np.ones((8, 8, 3))).save(tmp_path / "t.npz")
    code = textwrap.dedent(f"""
        import mitsuba as mi
        from mi_bivariate.variants import ensure_variant
        ensure_variant("scalar_rgb")
        try:
            mi.load_dict({{"type": "bivariate", "filename": {str(tmp_path / "t.npz")!r}}})
        except RuntimeError as exc:
            print("refused:", "needs a JIT variant" in str(exc), "Traceback" in str(exc).split("InputError")[-1])
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "refused: True False" in out.stdout, out.stdout + out.stderr[-2000:]


# ------------------------------------------------------------------ recover

@pytest.mark.parametrize("kwargs, name, problem", [
    (dict(n_normals=10**9), "n_normals", "over the limit"),
    (dict(n_dirs=10**10), "n_dirs", "over the limit"),
    (dict(grid=(300, 300)), "grid n_t", "over the limit"),
    (dict(grid=(64, 128)), "grid", "nodes is over the limit"),
    (dict(grid=8), "grid", "must be two node counts"),
    (dict(grid=(8,)), "grid", "must be two node counts"),
    (dict(grid=(8.7, 8)), "grid n_t", "must be a whole number"),
    (dict(n_normals=2.5), "n_normals", "must be a whole number"),
    (dict(seed=-1), "seed", "must be an integer from 0"),
    (dict(seed=1.5), "seed", "must be an integer from 0"),
    (dict(seed=None), "seed", "must be an integer from 0"),
    (dict(prior="foo"), "prior", "expected a mi_bivariate.prior.Prior"),
    (dict(max_view_angle_deg=float("nan")), "max_view_angle_deg", "must be an angle in (0, 90]"),
    (dict(max_view_angle_deg=95.0), "max_view_angle_deg", "must be an angle in (0, 90]"),
    (dict(footprint=-1.0), "footprint", "must be an angle in (0, 90]"),
    (dict(saturation=float("nan")), "saturation", "must be a positive number"),
    (dict(saturation=True), "saturation", "must be a positive number"),  # not read as 1.0
    (dict(saturation=0.0), "saturation", "must be a positive number"),
    (dict(pair_rule="bad"), "pair_rule", "unknown rule 'bad'"),      # before: after the lighting matrix
    (dict(basis_prior="x"), "basis_prior", "must be 'default', None or a BasisPrior"),  # the same
], ids=lambda v: v if isinstance(v, str) else None)
def test_recover_refuses_bad_arguments_before_any_work(probe, no_work, kwargs, name, problem):
    with pytest.raises(InputError) as info:
        recover(IMAGE, probe, SPHERE, **{**SMALL, **kwargs})
    assert info.value.source == name and problem in info.value.problem, str(info.value)


@pytest.mark.parametrize("bad", ["grace_256", np.ones((8, 16, 3)), None])
def test_recover_refuses_what_is_not_a_probe_before_any_work(no_work, bad):
    with pytest.raises(InputError, match="expected a mi_bivariate.probes.Probe") as info:
        recover(IMAGE, bad, SPHERE, **SMALL)
    assert info.value.source == "probe"


def test_recover_refuses_a_black_probe_before_any_work(no_work):
    with pytest.raises(InputError, match="probe is black"):
        recover(IMAGE, Probe.constant(0.0, res=16), SPHERE, **SMALL)


@pytest.mark.parametrize("bad", [[[0.5, 0.5, 0.5], [0.5, 0.5]], np.full((4, 4, 3), "grey")],
                         ids=["ragged lists", "words"])
@pytest.mark.parametrize("front_door", ["fit_sphere", "image_observations", "check_image", "write_exr", "write_png"])
def test_front_doors_name_an_image_numpy_cannot_read_as_one_array(tmp_path, front_door, bad):
    """Nested lists of unequal lengths (or words) given as an image: before, numpy's own ValueError ("setting
    an array element with a sequence ... inhomogeneous shape") escaped from the sphere fit, the image's
    observations and the EXR/PNG writers before their checks; now an InputError naming the image (or the
    file), as for a wrong shape, and no file written."""
    from mi_bivariate import images, spherefit

    out = tmp_path / "out.exr"
    calls = {"fit_sphere": lambda: spherefit.fit_sphere(bad),
             "image_observations": lambda: capture.image_observations(bad, SphereGeometry(8, 8, 6)),
             "check_image": lambda: capture.check_image(bad),
             "write_exr": lambda: images.write_exr(out, bad),
             "write_png": lambda: images.write_png(out.with_suffix(".png"), bad)}
    with pytest.raises(InputError) as info:
        calls[front_door]()
    if front_door in ("write_exr", "write_png"):
        assert info.value.source.startswith(str(tmp_path)) and not list(tmp_path.iterdir())
    else:
        assert info.value.source == "image"
    assert "dtype" in info.value.problem or "not one array of real numbers" in info.value.problem, str(info.value)


def test_a_grey_two_dimensional_image_is_named_as_one_image(probe):
    with pytest.raises(InputError, match=r"expected an \(H, W, 3\) RGB image, got shape \(48, 48\)") as info:
        recover(IMAGE[..., 0], probe, SPHERE, **SMALL)
    assert info.value.source == "image"


@pytest.mark.parametrize("masks, source", [(np.ones((10, 10), bool), "image"),
                                           ([None, np.ones((48, 47), bool)], "image 1")], ids=["one", "second"])
def test_a_mask_of_another_size_is_refused_before_the_noise_estimate(probe, no_work, monkeypatch, masks, source):
    """``noise="auto"`` reads each image's mask; its shape is checked before (before, the estimate ran on the
    whole image and the mask was refused only when the observations were built)."""
    def refuse(*args, **kwargs):
        raise AssertionError("the noise estimate ran before the masks were checked")

    monkeypatch.setattr(recover_mod, "_estimate_noise", refuse)
    images = IMAGE if source == "image" else [IMAGE, 2.0 * IMAGE]
    with pytest.raises(InputError, match=r"mask has shape \(\d+, \d+\) but the image is 48x48") as info:
        recover(images, probe, SPHERE, **{**SMALL, "noise": "auto", "masks": masks})
    assert info.value.source == source


@pytest.mark.parametrize("image", [IMAGE[..., 0], IMAGE[..., :2]], ids=["grey", "two-channel"])
def test_an_image_that_is_not_rgb_is_refused_before_the_noise_estimate(probe, no_work, image):
    """Before, the default ``noise="auto"`` estimated the noise on the raw array first and crashed in numpy
    (AxisError, IndexError); ``recover_from_photo`` crashed reading its saturation level."""
    with pytest.raises(InputError, match=r"expected an \(H, W, 3\) RGB image") as info:
        recover(image, probe, SPHERE, **{**SMALL, "noise": "auto"})
    assert info.value.source == "image"
    with pytest.raises(InputError, match=r"expected an \(H, W, 3\) RGB image") as info:
        recover_mod.recover_from_photo(image, probe, **{**SMALL, "noise": "auto"})
    assert info.value.source == "image"
    with pytest.raises(InputError, match=r"expected an \(H, W, 3\) RGB image") as info:
        recover([IMAGE, image], probe, SPHERE, **SMALL)
    assert info.value.source == "image 1"


@pytest.mark.parametrize("geometry, problem", [
    ((24.0, 24.0, 20.0), "expected a Geometry, got the numbers"),    # before: "3 geometries given", no name
    (None, "expected a Geometry, got a NoneType"),
    (SphereGeometry("24", 24.0, 20.0), "centre and radius must be numbers"),  # before: numpy UFuncTypeError
    (SphereGeometry(24.0, 24.0, float("nan")), "invalid sphere"),
    ([SPHERE, SPHERE], "2 geometries given for 1 images"),
], ids=["numbers", "None", "string centre", "NaN radius", "two for one image"])
def test_recover_names_a_bad_geometry_before_any_work(probe, no_work, geometry, problem):
    with pytest.raises(InputError) as info:
        recover(IMAGE, probe, geometry, **SMALL)
    assert info.value.source == "geometry" and problem in info.value.problem, str(info.value)


def test_a_basis_prior_on_another_grid_is_refused_before_any_work(probe, no_work):
    from mi_bivariate.basis_prior import default_basis_prior

    basis = default_basis_prior()
    if basis is None:
        pytest.skip("no packaged basis prior")
    with pytest.raises(InputError, match="is learnt on a 32 x 32 grid") as info:
        recover(IMAGE, probe, SPHERE, **{**SMALL, "basis_prior": basis})  # SMALL's grid is 8 x 8
    assert info.value.source == "basis_prior"


def test_noise_as_one_number_is_refused_and_as_an_array_pair_accepted(probe, monkeypatch):
    with monkeypatch.context() as patched:  # refused before any work
        patched.setattr(capture, "image_observations", lambda *a, **k: pytest.fail("work started"))
        with pytest.raises(InputError, match=r"give the pair \(a, b\)"):
            recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": 0.01})
        with pytest.raises(InputError, match="3 noise models given for 1 images"):
            recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": [None, None, None]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        pair = recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": np.array([1e-4, 1e-6])})
        listed = recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": (1e-4, 1e-6)})
    # the same noise model (two Dr.Jit threads add the lighting matrix's sums in either order: 1e-7)
    assert pair.brdf.provenance["noise"] == listed.brdf.provenance["noise"]
    np.testing.assert_allclose(pair.brdf.table, listed.brdf.table, rtol=1e-4, atol=1e-6 * listed.brdf.table.max())



def test_a_malformed_noise_model_is_refused_naming_noise_before_any_work(probe, no_work):
    """Before, a model in a per-image list was read only inside the solve, after the lighting matrix: a
    string or three entries there raised a bare ValueError from numpy ("could not convert string to
    float", "too many values to unpack"), as did two strings for one image; a non-iterable a TypeError."""
    two = [IMAGE, IMAGE * np.float32(0.9)]
    for noise, source in [(("a", "b"), "noise"), ({"a": 1}, "noise"), (object(), "noise"),
                          ([(1e-4, 1e-6, 0.0), None], "noise[0]"), ([None, "auto"], "noise[1]"),
                          ([1e-4, (0.0, 1e-6)], "noise[0]"), ([([1e-4] * 2, [1e-6] * 3), None], "noise[0]"),
                          ([None, (-1.0, 0.0)], "noise[1]"), ([(np.nan, 0.0), None], "noise[0]"),
                          ([np.array(1e-4), None], "noise[0]")]:  # a 0-d array: was len()'s TypeError
        with pytest.raises(InputError) as info:
            recover(two, probe, [SPHERE, SPHERE], **{**SMALL, "noise": noise})
        assert info.value.source == source, (noise, str(info.value))


def test_one_per_channel_noise_model_is_every_images(probe):
    """``(a, b)`` of three (R, G, B) each, as an "auto" estimate records them, is one model for every
    image (before: "2 noise models given for 1 images")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        rgb = recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": ([1e-4] * 3, [1e-6] * 3)})
        pair = recover(IMAGE, probe, SPHERE, **{**SMALL, "noise": (1e-4, 1e-6)})
    # each recorded as given: a pair of numbers as [a, b], as it was before the check was shared (the
    # shared check had made it [[a, a, a], [b, b, b]] in every brdf.npz of recover --noise A,B)
    assert pair.brdf.provenance["noise"] == [[1e-4, 1e-6]]
    assert rgb.brdf.provenance["noise"] == [[[1e-4] * 3, [1e-6] * 3]]
    np.testing.assert_allclose(rgb.brdf.table, pair.brdf.table, rtol=1e-4, atol=1e-6 * pair.brdf.table.max())


def test_the_same_photo_twice_is_refused_before_any_work(probe, no_work):
    """Before, a photo given twice (a copy, another dtype, one mask for both) counted twice: with all its
    pixels in both (a 64 px sphere, n_dirs 2000), the table moved by 19% (noise "auto") and 48% (None) of
    its peak from the photo's alone, the photo's weight doubled against the priors'; with fewer normals
    (1500), each copy saw another lattice and image_weights="cross" weighed the photo against itself
    (sigma factor 34.6 on one copy with noise None)."""
    photo = IMAGE * np.linspace(0.5, 1.0, 48, dtype=np.float32)[:, None, None]
    mask = np.ones((48, 48), bool)
    half = mask.copy()
    half[24:] = False
    for images, geometries, masks in [([photo, photo], SPHERE, None),
                                      ([photo, photo.astype(np.float64)], [SPHERE, SphereGeometry(24.0, 24.0, 20.0)],
                                       None),
                                      (np.stack([photo, IMAGE, photo]), SPHERE, half),
                                      ([photo, photo], SPHERE, [mask, None])]:  # every pixel, as without a mask
        with pytest.raises(InputError, match="repeats image 0") as info:
            recover(images, probe, geometries, **{**SMALL, "masks": masks})
        assert info.value.source == "images" and "give each photo once" in str(info.value)
    # the same photo of two spheres, or under two masks selecting other pixels, is two sets of pixels: it goes
    # on to the work (a mask of every pixel beside no mask was called "two masks" here: the same rows twice)
    for geometries, masks in [([SPHERE, SphereGeometry(20.0, 24.0, 10.0)], None), (SPHERE, [half, None])]:
        with pytest.raises(AssertionError, match="started work"):
            recover([photo, photo], probe, geometries, **{**SMALL, "masks": masks})

def test_the_repeat_check_reads_no_pixels_of_a_single_photo_or_of_two_objects():
    """The repeat check hashed every photo's pixels (blake2b of a copy) on every recovery, one photo included:
    0.1 s for a 2048 x 2048 photo and 0.7 s for 24 Mpx, on a recovery of 1.7-3.3 s, for a check that cannot
    find anything there. Pixels are now compared only between entries of one geometry and mask."""
    class Unread:  # an image whose pixels must not be read
        shape, dtype = (48, 48, 3), np.dtype(np.float32)

        def __array__(self, *args, **kwargs):
            raise AssertionError("pixels read")

    recover_mod._refuse_repeated_images([Unread()], [SPHERE], [None])
    recover_mod._refuse_repeated_images([Unread(), Unread()], [SPHERE, SphereGeometry(20.0, 24.0, 10.0)], [None, None])
    recover_mod._refuse_repeated_images([Unread(), Unread()], [SPHERE, SPHERE], [None, np.eye(48, dtype=bool)])
    photo = np.full((48, 48, 3), 0.5, np.float32)
    photo[3, 5] = np.nan  # a NaN pixel repeats as itself
    with pytest.raises(InputError, match="image 1 repeats image 0"):
        recover_mod._refuse_repeated_images([photo, photo.copy()], [SPHERE, SphereGeometry(24.0, 24.0, 20.0)],
                                            [None, None])
    other = photo.copy()
    other[40, 40] = 0.25  # off the sample's stride: found by the full comparison
    recover_mod._refuse_repeated_images([photo, other], [SPHERE, SPHERE], [None, None])


def test_images_are_checked_for_their_number_type(probe):
    with pytest.raises(InputError, match="expected real numbers"):
        recover(IMAGE.astype(np.complex64), probe, SPHERE, **SMALL)
    for scale in (np.float64(1e300), np.float32(1e37)):  # beyond float32; within it, but the sums overflow
        with pytest.raises(InputError, match="too large for float32 and the solve's sums"):
            recover(IMAGE * scale, probe, SPHERE, **SMALL)
    with pytest.raises(InputError, match="too small for float32 and the solve's sums"):
        recover(IMAGE * np.float32(1e-30), probe, SPHERE, **SMALL)
    with warnings.catch_warnings():  # within the limits, the recovery is linear in the image
        warnings.simplefilter("ignore", InputWarning)
        tables = [recover(IMAGE * np.float32(s), probe, SPHERE, **SMALL).brdf.table / s for s in (1.0, 1e-18)]
    np.testing.assert_allclose(tables[1], tables[0], rtol=0, atol=1e-5 * tables[0].max())
    with pytest.warns(InputWarning, match=r"the image holds integers \(uint8\)"):
        recover(np.full((48, 48, 3), 128, np.uint8), probe, SPHERE, **SMALL)


def test_a_recovery_keeps_copies_of_its_images(probe):
    image = IMAGE.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        result = recover(image, probe, SPHERE, **SMALL)
    image[:] = 0.0
    np.testing.assert_array_equal(result.images[0], IMAGE)


def test_the_fit_check_leaves_out_a_firefly_row_but_not_a_mismatch():
    """One row with a Monte Carlo firefly's residual (600x the median pixel) no longer makes a perfect fit
    "explain" under half of the image; a fit that misses every row still warns."""
    rng = np.random.default_rng(0)
    values = rng.uniform(0.005, 0.015, (2000, 3))
    sigma = np.full_like(values, 1e-5)
    index = np.zeros(2000, dtype=np.int64)
    fitted = values.copy()
    values_with_firefly = values.copy()
    values_with_firefly[7] = 6.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        recover_mod._check_explained(values_with_firefly, fitted, sigma, index, 1)
    # the same firefly, unchecked, explains almost nothing: the trim is what keeps quiet
    assert 1.0 - np.sum((values_with_firefly - fitted) ** 2) / np.sum(
        (values_with_firefly - values_with_firefly.mean(0)) ** 2) < 0.01
    with pytest.warns(InputWarning, match="the recovered table explains"):
        recover_mod._check_explained(values, rng.permutation(values), sigma, index, 1)


def test_a_smoothness_prior_is_still_accepted(probe):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        result = recover(IMAGE, probe, SPHERE, **{**SMALL, "prior": default_prior()})
    assert result.brdf.table.shape == (8, 8, 3)


# ------------------------------------------------------------------ render

@pytest.mark.parametrize("call, name, problem", [
    (lambda p: render.render_sphere(p, p, resolution=16, spp=1), "bsdf", "got a Probe where a BRDF goes"),
    (lambda p: render.render_sphere({"type": "diffuse"}, "grace_256", resolution=16, spp=1), "probe",
     "expected a mi_bivariate.probes.Probe"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=100000, spp=1), "resolution",
     "over the limit"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=(16, 1), spp=1), "height",
     "must be at least 2 pixels"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=16, spp=10**9), "spp", "over the limit"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=16, spp=1, seed=-1), "seed",
     "must be an integer from 0"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=16, spp=1, seed=2**40), "seed",
     "must be an integer from 0"),
    (lambda p: render.render_like({"type": "diffuse"}, p, SPHERE, 48, 48, spp=0), "spp", "must be at least 1"),
    (lambda p: render.render_like({"type": "diffuse"}, p, SPHERE, 0, 48, spp=4), "width",
     "must be at least 2 pixels"),
    (lambda p: render.render_sphere({"type": "diffuse"}, p, resolution=16, spp=1, seed=np.array([3])), "seed",
     "must be an integer from 0"),
], ids=["probe as BRDF", "name as probe", "huge resolution", "one-pixel height", "huge spp", "negative seed",
        "40-bit seed", "render_like spp 0", "render_like width 0", "seed array"])
def test_renders_refuse_bad_arguments(probe, call, name, problem):
    with pytest.raises(InputError) as info:
        call(probe)
    assert info.value.source == name and problem in info.value.problem, str(info.value)


def test_renders_take_whole_numbers_in_any_numeric_type(probe):
    """Sizes and seeds that are whole numbers in another type (16.0, numpy integers, a 0-d array) render as
    their ints did before the checks, bit for bit."""
    diffuse = {"type": "diffuse"}
    want = render.render_sphere(diffuse, probe, resolution=16, spp=2, seed=3)
    for resolution, seed in ((16.0, 3.0), (np.int64(16), np.uint32(3)), ((16, np.float64(16.0)), np.array(3))):
        got = render.render_sphere(diffuse, probe, resolution=resolution, spp=2, seed=seed)
        np.testing.assert_array_equal(got.image, want.image)
    like = render.render_like(diffuse, probe, SPHERE, 48.0, np.int32(48), spp=2, seed=np.int16(1))
    assert like.image.shape == (48, 48, 3) and like.seed == 1


# ------------------------------------------------------------------ metrics

def test_image_metrics_check_shapes_and_masks():
    a = np.ones((8, 8, 3))
    with pytest.raises(ValueError, match="image shapes differ"):
        metrics.image_psnr(a[..., :1], a)
    for bad, match in ((np.ones((8, 8)), "mask must be boolean"), (np.ones((4, 4), bool), "does not fit"),
                       (np.zeros((8, 8), bool), "selects no pixel")):
        for metric in (metrics.image_psnr, metrics.image_relative_rmse):
            with pytest.raises(ValueError, match=match):
                metric(a, a, bad)
    assert metrics.image_relative_rmse(a * 1.1, a, np.ones((8, 8), bool)) == pytest.approx(0.1)


def test_brdf_errors_say_which_argument_is_the_truth(probe):
    table = BivariateBRDF(np.ones((8, 8, 3)))
    with pytest.raises(TypeError, match="the truth must be a 3D MERLBRDF"):
        metrics.brdf_errors(table, table)


def test_the_scores_refuse_a_probe_as_the_estimate(probe):
    """A probe has an ``eval`` (radiance), which the scores' duck typing would take for a BRDF's."""
    from mi_bivariate.merl import MERLBRDF

    truth = MERLBRDF.from_function(lambda th, td, pd: np.full(np.shape(th) + (3,), 0.2), name="flat")
    with pytest.raises(InputError, match="estimate: got a Probe where a BRDF goes"):
        metrics.brdf_errors(truth, probe)
    with pytest.raises(InputError, match="estimate: got a Probe where a BRDF goes"):
        metrics.estimate_on_merl_grid(probe)


@pytest.mark.parametrize("make, problem", [
    (lambda k: PerspectiveSphereGeometry(k, [0.0, 0.0, -4.0], 1.0, np.diag([-1.0, 1.0, 1.0])), "rotation"),
    (lambda k: PerspectiveSphereGeometry((-k.fx, k.fy, k.cx, k.cy), [0.0, 0.0, -4.0]), "focal lengths"),
    (lambda k: PerspectiveSphereGeometry(k, [0.0, -4.0]), "3 finite numbers"),
    (lambda k: PerspectiveSphereGeometry((50.0, 50.0, 16.0), [0.0, 0.0, -4.0]), "(fx, fy, cx, cy)"),
    (lambda k: PerspectiveSphereGeometry(k, [0.0, 0.0, -4.0], -1.0), "finite positive"),
    (lambda k: PerspectiveSphereGeometry(k, [0.0, 0.0, 4.0]), "sphere (centre (0, 0, 4), radius 1) is not in front of the camera"),
    (lambda k: PerspectiveSphereGeometry(k, [0.0, 0.0, -0.5]), "not in front of the camera"),
], ids=["mirror", "negative fx", "2-vector centre", "3 intrinsics", "negative radius", "behind", "around"])
def test_a_perspective_sphere_is_checked_when_made(make, problem):
    """A mirrored camera or a negative focal length recovered a wrong table with no error; a malformed
    centre or intrinsics raised numpy's ValueError."""
    with pytest.raises(InputError, match=re.escape(problem)):
        make(Intrinsics.from_fov(64, 64, 30.0))


def test_a_mesh_view_is_checked_when_made():
    import trimesh

    from mi_bivariate.geometry import Camera
    from mi_bivariate.mesh import MeshShape, MeshView

    with pytest.raises(InputError, match="needs a MeshShape"):
        MeshView("torus.obj", Camera.look_at([0, 0, 3], [0, 0, 0], width=8, height=8))
    with pytest.raises(InputError, match="needs a Camera"):
        MeshView(MeshShape.load(trimesh.creation.icosphere()), None)


@pytest.mark.parametrize("kwargs, name", [
    ({"probe": None}, "probe"),
    ({"search_deg": (-np.inf, np.inf)}, "search_deg"),
    ({"search_deg": 5.0}, "search_deg"),
    ({"search_deg": (10.0, 10.0)}, "search_deg"),
    ({"coarse_step_deg": "5"}, "coarse_step_deg"),
    ({"coarse_step_deg": 0.0}, "coarse_step_deg"),
    ({"coarse_step_deg": 120.0}, "coarse_step_deg"),
    ({"texel_width": 0}, "texel_width"),
    ({"texel_width": 1}, "texel_width"),
    ({"tol_deg": float("nan")}, "tol_deg"),
    ({"tol_deg": 0.0}, "tol_deg"),
    ({"alpha": -1.0}, "alpha"),
    ({"n_normals": 0}, "n_normals"),
    ({"alpha": "discrepancy"}, "alpha"),
    ({"seed": -1}, "seed"),
])
def test_estimate_yaw_refuses_bad_arguments_before_any_work(probe, no_work, kwargs, name):
    from mi_bivariate.alignment import estimate_yaw

    args = {"probe": probe, **kwargs}
    with pytest.raises(InputError) as info:
        estimate_yaw(IMAGE, args.pop("probe"), SPHERE, **args)
    assert info.value.source == name, str(info.value)


def test_recover_from_photo_keeps_to_the_users_mask(probe, monkeypatch):
    """``mask=`` limits the recovery's pixels (and the yaw estimate's), not only the sphere fit's: a blot
    outside the mask adds no row."""
    seen = {}

    def observing(image, geometry, **kwargs):
        seen.setdefault("masks", []).append(kwargs.get("mask"))
        return real(image, geometry, **kwargs)

    real = capture.image_observations
    monkeypatch.setattr(capture, "image_observations", observing)
    mask = np.ones(IMAGE.shape[:2], bool)
    mask[:, : IMAGE.shape[1] // 2] = False
    recover_mod.recover_from_photo(IMAGE, probe, mask=mask, sphere=(24.0, 24.0, 20.0), saturation=None, **SMALL)
    assert seen["masks"] and all(m is not None and np.array_equal(m, mask) for m in seen["masks"])
    with pytest.raises(InputError, match="both mask and masks"):
        recover_mod.recover_from_photo(IMAGE, probe, mask=mask, masks=mask, **SMALL)


@pytest.mark.parametrize("alpha", [0.0, (1e-2, 0.0, 1e-2)])
def test_alpha_zero_warns_that_the_table_is_unconstrained(probe, no_work, alpha):
    """alpha 0 (the unregularised fit, the paper's ablation) is allowed, but without a word it gave tables of
    4e19 1/sr on a small sphere: it now warns, before any work."""
    with pytest.warns(InputWarning, match="alpha 0: no smoothness prior"), \
            pytest.raises(AssertionError, match="started work"):
        recover(IMAGE, probe, SPHERE, **{**SMALL, "alpha": alpha})


@pytest.mark.parametrize("env", [None, "llvm_ad_rgb"])
def test_a_variant_that_cannot_start_names_where_it_came_from(monkeypatch, env):
    """A default variant that fails to start named MI_BIVARIATE_VARIANT even where it was not set."""
    import mitsuba as mi

    from mi_bivariate import variants

    if env is None:
        monkeypatch.delenv("MI_BIVARIATE_VARIANT", raising=False)
    else:
        monkeypatch.setenv("MI_BIVARIATE_VARIANT", env)
    monkeypatch.setattr(mi, "variant", lambda: "scalar_rgb")

    def fail(name):
        raise RuntimeError("no LLVM")

    monkeypatch.setattr(mi, "set_variant", fail)
    with pytest.raises(InputError, match="cannot start on this machine") as info:
        variants.ensure_variant(vectorised=True)
    assert info.value.source == ("default variant" if env is None else "MI_BIVARIATE_VARIANT")


@pytest.mark.parametrize("kwargs", [dict(max_view_angle_deg=90.0), dict(footprint=90.0), dict(saturation=1e-30)],
                         ids=lambda v: next(iter(v)))
def test_recover_accepts_the_ends_of_its_documented_ranges(probe, no_work, kwargs):
    """``max_view_angle_deg`` and ``footprint`` in (0, 90] (90 included), ``saturation`` any positive level:
    the recovery gets as far as reading the pixels."""
    with pytest.raises(AssertionError, match="started work"):
        recover(IMAGE, probe, SPHERE, **{**SMALL, **kwargs})


def test_one_noise_model_applies_to_every_image(probe):
    """``noise=(a, b)`` with two images is each image's model: recorded for both, and the same table as
    giving it once per image."""
    second = np.full((48, 48, 3), 0.25, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        shared = recover([IMAGE, second], probe, SPHERE, **{**SMALL, "noise": (1e-4, 1e-6)})
        each = recover([IMAGE, second], probe, SPHERE, **{**SMALL, "noise": [(1e-4, 1e-6), (1e-4, 1e-6)]})
    assert shared.brdf.provenance["noise"] == [[1e-4, 1e-6], [1e-4, 1e-6]]
    np.testing.assert_array_equal(shared.brdf.table, each.brdf.table)
