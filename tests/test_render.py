"""mi_bivariate.render: camera conventions, masks, determinism, outputs, scene XML."""

from __future__ import annotations

import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mi_bivariate.analytic import CookTorranceGGX, Lambertian
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.geometry import SphereCamera, SphereGeometry
from mi_bivariate.images import write_exr, write_png
from mi_bivariate.merl import MERLBRDF
from mi_bivariate.probes import Probe
from mi_bivariate.render import bsdf_dict, render_like, render_mesh, render_sphere

SCENES = Path(__file__).resolve().parents[1] / "scenes"
DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def ray_traced_normals(camera: SphereCamera) -> np.ndarray:
    """Unit-sphere normals at pixel centres from the camera model, ``(H, W, 3)`` (NaN on a miss)."""
    width, height = camera.resolution
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    o, d = camera.rays(px, py)
    od = np.sum(o * d, -1)
    disc = od * od - (np.sum(o * o, -1) - 1.0)
    t = -od - np.sqrt(np.where(disc >= 0, disc, np.nan))
    return o + t[..., None] * d


# ----------------------------------------------------------------- camera

@pytest.mark.parametrize("kwargs", [
    {},
    {"resolution": (48, 32)},
    {"camera_to_world": [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]},  # camera on world +x
])
def test_orthographic_normals_follow_geometry_convention(kwargs):
    # Mitsuba's own sh_normal AOV against SphereGeometry.normals(): a mirrored or
    # flipped axis would give errors of tens of degrees.
    r = render_sphere(DIFFUSE, Probe.constant(1.0, 16), **{"resolution": 48, "spp": 16, **kwargs})
    height, width = r.mask.shape
    expected, inside = r.geometry.normals(width, height)
    assert r.mask.sum() > 0.5 * inside.sum() and np.all(inside[r.mask])
    err = angle_deg(r.normals[r.mask], expected[r.mask])
    # Normals are averaged over random positions in the pixel (16 spp): a few
    # tenths of a degree from the centre normal; a mirrored axis would be tens.
    assert np.median(err) < 0.5 and err.max() < 3.0
    assert np.all(r.normals[~r.mask] == 0.0)  # the rim's partly covered pixels too (documented: 0 outside)
    np.testing.assert_allclose(r.geometry.view_direction(), np.asarray(r.camera.camera_to_world) @ [0, 0, 1])


def test_orthographic_geometry_is_exact():
    cam = SphereCamera.create("orthographic", 64)
    r = render_sphere(DIFFUSE, Probe.constant(1.0, 16), resolution=64, spp=4)
    assert (r.geometry.cx, r.geometry.cy, r.geometry.radius) == (32.0, 32.0, 0.45 * 64)
    # The camera model used for masks agrees with the geometry at pixel centres.
    n_geo, inside = r.geometry.normals(64, 64)
    n_ray = ray_traced_normals(cam)
    np.testing.assert_allclose(n_ray[inside], n_geo[inside], atol=1e-9)
    assert np.all(np.isnan(n_ray[~inside][:, 0]) | (np.abs(np.linalg.norm(n_geo[~inside], axis=-1)) == 0))


def test_perspective_normals_follow_camera_model():
    r = render_sphere(DIFFUSE, Probe.constant(1.0, 16), resolution=(40, 30), spp=16, camera="perspective", fov=40)
    assert r.geometry is None
    expected = ray_traced_normals(r.camera)
    err = angle_deg(r.normals[r.mask], expected[r.mask])
    assert np.median(err) < 0.5 and err.max() < 3.0
    # Default distance: silhouette radius = radius_fraction * width pixels.
    assert abs(r.mask[15].sum() - 2 * 0.45 * 40) <= 3


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_mask_is_full_coverage(camera):
    # An emitting sphere (radiance 1) over a black background renders each pixel's
    # covered fraction: exactly 1 on fully covered pixels, < 1 on partial ones.
    cam = SphereCamera.create(camera, 32)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"}, "sensor": cam.sensor_dict(),
        "sphere": {"type": "sphere", "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
    })
    coverage = np.array(mi.render(scene, spp=256, seed=0))[..., 0]
    mask = cam.coverage_mask()
    assert np.all(coverage[mask] == pytest.approx(1.0, abs=1e-6))
    # Unmasked pixels that happen to catch only hits have a tiny uncovered corner.
    full_outside = (coverage > 1.0 - 1e-6) & ~mask
    assert full_outside.sum() <= 0.1 * mask.sum()
    assert np.all(coverage[~mask] <= 1.0 + 1e-6)


def test_bad_camera_arguments():
    with pytest.raises(InputError, match="unknown camera"):
        SphereCamera.create("fisheye")
    with pytest.raises(InputError, match="rotation"):
        SphereCamera.create(camera_to_world=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(InputError, match="outside the unit sphere"):
        SphereCamera.create("perspective", distance=0.5)


# --------------------------------------------------------- renders proper

def test_same_seed_same_image():
    probe = Probe(np.random.default_rng(0).uniform(0.1, 2.0, (16, 32, 3)).astype(np.float32))
    bsdf = bsdf_dict(BivariateBRDF(np.random.default_rng(1).uniform(0.05, 1.0, (8, 8, 3))))
    a = render_sphere(bsdf, probe, resolution=32, spp=32, seed=5)
    b = render_sphere(bsdf, probe, resolution=32, spp=32, seed=5)
    c = render_sphere(bsdf, probe, resolution=32, spp=32, seed=6)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert not np.array_equal(a.image, c.image)
    assert a.image.dtype == np.float32 and a.image.shape == (32, 32, 3)
    assert np.all(a.image[~a.camera.coverage_mask() & (a.normals[..., 2] == 0)] >= 0.0)


@pytest.mark.parametrize("source", ["bivariate", "merl-file", "analytic"])
def test_furnace_through_render_sphere(tmp_path, source):
    rho = np.array([0.3, 0.6, 0.9])
    biv = BivariateBRDF(np.broadcast_to(rho / math.pi, (4, 4, 3)))
    if source == "bivariate":
        bsdf = biv
    elif source == "merl-file":
        bsdf = tmp_path / "lambert.binary"
        biv.write_merl(bsdf)
    else:
        bsdf = Lambertian(rho)
    r = render_sphere(bsdf, Probe.constant(1.0, 16), resolution=32, spp=64)
    np.testing.assert_allclose(r.image[r.mask].mean(0), rho, rtol=3e-3)


def test_bsdf_dict_mapping(tmp_path):
    biv = BivariateBRDF(np.full((4, 4, 3), 0.1))
    assert bsdf_dict(biv)["type"] == "bivariate"
    assert bsdf_dict(biv.to_merl())["type"] == "merl"
    assert bsdf_dict(Lambertian(0.5))["type"] == "merl"
    biv.save(tmp_path / "b.npz")
    assert bsdf_dict(tmp_path / "b.npz") == {"type": "bivariate", "filename": str(tmp_path / "b.npz"),
                                             "sampling": "table"}
    assert bsdf_dict(DIFFUSE) is DIFFUSE
    with pytest.raises(InputError, match="not found"):
        bsdf_dict(tmp_path / "missing.npz")
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(InputError, match="unknown BRDF file type"):
        bsdf_dict(tmp_path / "x.txt")
    with pytest.raises(InputError, match="cannot make a BSDF"):
        bsdf_dict(42)


def test_plugin_errors_surface_as_input_errors(tmp_path):
    (tmp_path / "bad.binary").write_bytes(b"\x00" * 100)
    with pytest.raises(InputError, match="not a MERL .binary file"):
        render_sphere(tmp_path / "bad.binary", Probe.constant(1.0, 16), resolution=8, spp=1)


# ----------------------------------------------------------------- output

def test_write_exr_and_png(tmp_path):
    image = np.random.default_rng(0).uniform(0.0, 4.0, (12, 20, 3)).astype(np.float32)
    write_exr(tmp_path / "out.exr", image)
    back = np.array(mi.Bitmap(str(tmp_path / "out.exr")), np.float32)
    np.testing.assert_array_equal(back[..., :3], image)
    write_png(tmp_path / "out.png", image)
    import matplotlib.image

    png = matplotlib.image.imread(str(tmp_path / "out.png"))
    assert png.shape[:2] == (12, 20)
    with pytest.raises(InputError):
        write_exr(tmp_path / "bad.exr", image[..., 0])
    assert not (tmp_path / "bad.exr").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.exr", "out.png"]  # no temporaries left


# -------------------------------------------------------------- scene XML

def lopsided_probe(height: int = 16) -> Probe:
    """A dim sky with one bright soft lobe off every axis: any mirror or half turn of the sphere's image
    moves its highlight (a probe of i.i.d. noise renders a sphere nearly symmetric)."""
    theta = (np.arange(height) + 0.5) / height * math.pi
    phi = (np.arange(2 * height) + 0.5) / (2 * height) * 2.0 * math.pi
    d = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.cos(theta)[:, None] * np.ones_like(phi),
                  np.sin(theta)[:, None] * np.sin(phi)], axis=-1)
    lobe = np.array([0.6, 0.5, 0.62]) / np.linalg.norm([0.6, 0.5, 0.62])
    radiance = 0.2 + 4.0 * np.exp((d @ lobe - 1.0) / 0.15)
    return Probe((radiance[..., None] * np.array([1.0, 0.9, 0.8])).astype(np.float32))


@pytest.mark.parametrize("name, camera", [("sphere_envmap_ortho.xml", "orthographic"),
                                          ("sphere_envmap_perspective.xml", "perspective")])
@pytest.mark.parametrize("brdf_type", ["bivariate", "merl"])
def test_scene_xml_matches_render_sphere(tmp_path, name, camera, brdf_type):
    """The scene files render what ``render_sphere`` renders, pixel for pixel up to noise: same
    silhouette, same pose of the probe and of the image (a mirrored or half-turned image is 5x further)."""
    from mi_bivariate.analytic import BivariateLobe

    theta_h = 0.5 * math.pi * np.linspace(0.0, 1.0, 8) ** 2
    theta_d = 0.5 * math.pi * np.linspace(0.0, 1.0, 8)
    lobe = BivariateLobe(diffuse=0.2, specular=2.0, width=0.25).eval_half_diff(theta_h[:, None], theta_d[None, :])
    biv = BivariateBRDF(lobe * np.array([1.0, 0.8, 0.6]))
    probe = lopsided_probe()
    probe.save_exr(tmp_path / "env.exr")
    if brdf_type == "bivariate":
        biv.save(tmp_path / "brdf.npz")
        brdf_file = tmp_path / "brdf.npz"
    else:
        biv.write_merl(tmp_path / "brdf.binary")
        brdf_file = tmp_path / "brdf.binary"
    scene = mi.load_file(str(SCENES / name), brdf_type=brdf_type, brdf_file=str(brdf_file),
                         envmap=str(tmp_path / "env.exr"), spp="64", res="24", seed="3")
    xml_image = np.array(mi.render(scene), np.float64)
    ref = render_sphere(biv, probe, resolution=24, spp=256, camera=camera)
    assert xml_image.shape == (24, 24, 3)
    m, r = ref.mask, ref.image

    def relative_rms(other: np.ndarray) -> float:
        return float(np.sqrt(np.mean((xml_image[m] - other[m]) ** 2) / np.mean(r[m] ** 2)))

    assert np.all(xml_image[m].sum(-1) > 0.0)
    np.testing.assert_allclose(xml_image[m].mean(0), r[m].mean(0), rtol=0.03)
    error = relative_rms(r)  # the two renders' noise: 0.08-0.10 measured (0.05 at 4x the samples)
    assert error < 0.15
    for turned in (r[:, ::-1], r[::-1], r[::-1, ::-1]):  # 0.61-0.88 measured
        assert relative_rms(turned) > 5.0 * error


@pytest.mark.parametrize("name, camera", [("sphere_envmap_ortho.xml", "orthographic"),
                                          ("sphere_envmap_perspective.xml", "perspective")])
@pytest.mark.parametrize("brdf_type, suffix", [("bivariate", ".npz"), ("merl", ".binary")])
def test_scene_xml_renders_a_brdf_file_as_the_toolkit_does(tmp_path, name, camera, brdf_type, suffix):
    """Same file, probe, seed and samples: the scene file and ``render_sphere`` (what ``mi-bivariate render``
    and the evaluation render) give the same pixels. Before, the scenes gave the ``merl`` plugin no
    ``interpolation``, so a MERL file (``recover --merl``'s) was looked up nearest-node there and linearly
    in the toolkit's renders: 2-12% apart per pixel."""
    brdf = CookTorranceGGX((0.2, 0.1, 0.05), specular=0.6, alpha=0.2)  # varies with phi_d: not bivariate
    brdf_file = tmp_path / f"brdf{suffix}"
    if brdf_type == "bivariate":
        BivariateBRDF.reduce(brdf, 16, 16).save(brdf_file)
    else:
        MERLBRDF.from_function(brdf.eval, "ggx").write(brdf_file)
    probe = lopsided_probe()
    probe.save_exr(tmp_path / "env.exr")
    scene = mi.load_file(str(SCENES / name), brdf_type=brdf_type, brdf_file=str(brdf_file),
                         envmap=str(tmp_path / "env.exr"), spp="8", res="24", seed="3")
    xml_image = np.array(mi.render(scene), np.float32)
    ref = render_sphere(brdf_file, Probe.load(tmp_path / "env.exr"), resolution=24, spp=8, seed=3, camera=camera)
    assert ref.image[ref.mask].min() > 0.0
    np.testing.assert_array_equal(xml_image, ref.image)


def test_auto_exposure_maps_the_percentile_of_the_masked_luminance_to_white():
    """Grey pixels (luminance = value): the exposure is 1 / the percentile of the positive, finite
    values under the mask; an image without such a pixel gets 1."""
    from mi_bivariate.images import auto_exposure

    values = np.arange(1.0, 101.0).reshape(10, 10)
    image = np.repeat(values[..., None], 3, axis=2)
    image[0, 0] = np.nan
    mask = values <= 50.0
    assert auto_exposure(image) == pytest.approx(1.0 / np.percentile(values.ravel()[1:], 99.0))  # NaN left out
    assert auto_exposure(image, mask) == pytest.approx(1.0 / np.percentile(np.arange(2.0, 51.0), 99.0))
    assert auto_exposure(image, mask, percentile=50.0) == pytest.approx(1.0 / 26.0)
    assert auto_exposure(np.zeros((4, 4, 3))) == 1.0


def test_cli_render_probe_rotation_renders_the_turned_probe(tmp_path):
    """``render --probe-rotation`` renders what the library renders under ``Probe.rotated`` (the same seed:
    the same pixels), and differs from the unturned probe (the option is not ignored)."""
    from mi_bivariate.cli import main as cli_main
    from mi_bivariate.images import load_image
    from mi_bivariate.sources import load_brdf, synthetic_environment

    sky = Probe(synthetic_environment(seed=1), source="sky")
    sky.save_exr(tmp_path / "sky.exr")
    spec = "lambertian:albedo=0.7"
    turned = Probe.load(tmp_path / "sky.exr").rotated(euler_deg=(180.0, 30.0, 0.0))
    expected = render_sphere(bsdf_dict(load_brdf(spec)), turned, resolution=32, spp=16, seed=5).image
    images = {}
    for rotation in ([], ["--probe-rotation=180,30,0"]):
        out = tmp_path / f"r{len(rotation)}.exr"
        assert cli_main(["render", spec, "--probe", str(tmp_path / "sky.exr"), "--out", str(out), "--resolution", "32",
                         "--spp", "16", "--seed", "5"] + rotation) == 0
        images[bool(rotation)] = load_image(out)
    scale = float(np.abs(expected).max())
    np.testing.assert_allclose(images[True], expected, atol=1e-5 * scale)
    assert float(np.abs(images[False] - expected).mean()) > 0.05 * float(np.abs(expected).mean())


def test_render_like_puts_the_sphere_where_the_geometry_says():
    """An off-centre sphere in a non-square image seen by a turned camera (what a photo's fitted geometry
    is): the render is lit exactly inside the geometry's silhouette and black outside it, up to the rim's
    partly covered pixels. A centre offset with a flipped axis, or not turned with the camera, moves the disc."""
    turned = Rotation.from_euler("xyz", [30.0, -50.0, 20.0], degrees=True).as_matrix()
    geometry = SphereGeometry(20.0, 27.0, 9.0, camera_to_world=turned)
    image = render_like(DIFFUSE, Probe.constant(1.0, 16), geometry, 48, 36, spp=4).image
    yy, xx = np.mgrid[0:36, 0:48] + 0.5
    distance = np.hypot(xx - geometry.cx, yy - geometry.cy)
    lit = image.sum(axis=-1) > 0.0
    assert np.all(lit[distance < geometry.radius - 0.75]) and not np.any(lit[distance > geometry.radius + 0.75])


@pytest.mark.parametrize("geometry, problem", [
    (None, "expected a mi_bivariate.geometry.SphereGeometry, got a NoneType"),
    ((24.0, 24.0, 21.6), "got a tuple"),
    (SphereGeometry(float("nan"), 24.0, 10.0), "invalid sphere"),            # before: a black image, no error
    (SphereGeometry(24.0, 24.0, float("inf")), "invalid sphere"),
    (SphereGeometry(24.0, 24.0, 0.0), "invalid sphere"),                    # before: named "radius_fraction"
    (SphereGeometry("24", 24.0, 10.0), "must be numbers"),
    (SphereGeometry(24.0, 24.0, 10.0, camera_to_world=np.eye(3) * 2), "not a (3, 3) rotation"),
], ids=["None", "tuple", "NaN centre", "infinite radius", "zero radius", "string centre", "scaled rotation"])
def test_render_like_names_a_bad_geometry(geometry, problem):
    with pytest.raises(InputError) as info:
        render_like(DIFFUSE, Probe.constant(1.0, 16), geometry, 48, 48, spp=1)
    assert info.value.source == "geometry" and problem in info.value.problem, str(info.value)


def test_render_mesh_names_a_view_that_is_not_a_mesh_view():
    """Before: AttributeError ('SphereGeometry' object has no attribute 'camera')."""
    with pytest.raises(InputError, match="expected a mi_bivariate.mesh.MeshView") as info:
        render_mesh(DIFFUSE, Probe.constant(1.0, 16), SphereGeometry(24.0, 24.0, 20.0))
    assert info.value.source == "view"


@pytest.mark.parametrize("kwargs, name", [
    (dict(camera="perspective", distance=float("nan")), "distance"),   # before: a black image, no error
    (dict(camera="perspective", distance=float("inf")), "distance"),
    (dict(camera="perspective", distance="5"), "distance"),
    (dict(camera="perspective", fov="30"), "fov"),                     # before: TypeError
    (dict(camera="perspective", fov=float("nan")), "fov"),
    (dict(radius_fraction=float("inf")), "radius_fraction"),           # before: accepted, radius inf
    (dict(radius_fraction=float("nan")), "radius_fraction"),
    (dict(radius_fraction="0.4"), "radius_fraction"),                  # before: TypeError
    (dict(camera_to_world="x"), "camera_to_world"),                    # before: ValueError from numpy
], ids=["NaN distance", "infinite distance", "string distance", "string fov", "NaN fov", "infinite radius",
        "NaN radius", "string radius", "string rotation"])
def test_render_sphere_requires_a_finite_camera(kwargs, name):
    with pytest.raises(InputError) as info:
        render_sphere(DIFFUSE, Probe.constant(1.0, 16), resolution=16, spp=1, **kwargs)
    assert info.value.source == name, str(info.value)


def test_png_previews_are_srgb_encoded_and_rounded(tmp_path):
    """write_png's codes at exposure 1, read back by Pillow: the sRGB standard's rounded codes at a few
    radiances (linear segment below 0.0031308, the 1/2.4 power above it, clipped at 1), and within one
    code of Mitsuba's own sRGB conversion over a ramp (Mitsuba's rounding differs by one code)."""
    from PIL import Image

    radiance = np.array([0.0, 0.002, 0.02, 0.18, 0.5, 0.9, 1.0, 4.0], np.float32)
    write_png(tmp_path / "points.png", np.repeat(radiance.reshape(1, -1, 1), 3, axis=2), exposure=1.0)
    codes = np.asarray(Image.open(tmp_path / "points.png").convert("RGB"))
    np.testing.assert_array_equal(codes[0, :, 0], [0, 7, 39, 118, 188, 243, 255, 255])

    ramp = np.linspace(0.0, 1.0, 4096, dtype=np.float32).reshape(64, 64, 1) * np.array([1.0, 0.5, 0.25], np.float32)
    write_png(tmp_path / "ramp.png", ramp, exposure=1.0)
    mitsuba_codes = np.array(mi.Bitmap(ramp, pixel_format=mi.Bitmap.PixelFormat.RGB).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)).astype(int)
    ours = np.asarray(Image.open(tmp_path / "ramp.png").convert("RGB")).astype(int)
    assert np.abs(ours - mitsuba_codes).max() <= 1


def test_render_like_at_render_spheres_own_geometry_is_render_sphere_and_follows_the_seed():
    """Two implementations of one camera: ``render_like`` given the geometry ``render_sphere`` reports (centred,
    radius 0.45 x the size) builds the same scene, so at the same samples and seed it renders the same pixels;
    another seed renders other pixels (before, a seed or spp dropped on the way to Mitsuba went unseen)."""
    probe = lopsided_probe(8)
    ref = render_sphere(DIFFUSE, probe, resolution=16, spp=8, seed=3)
    like = render_like(DIFFUSE, probe, ref.geometry, 16, 16, spp=8, seed=3)
    np.testing.assert_array_equal(like.image, ref.image)
    # render_sphere's normals (Mitsuba's, averaged over the pixel) are unit vectors to float32 rounding.
    np.testing.assert_allclose(np.linalg.norm(ref.normals[ref.mask].astype(np.float64), axis=-1), 1.0, atol=1e-6)
    assert (like.spp, like.seed) == (8, 3)
    other = render_like(DIFFUSE, probe, ref.geometry, 16, 16, spp=8, seed=4)
    assert not np.array_equal(other.image, ref.image)


def test_brdf_objects_render_what_their_merl_file_renders(tmp_path):
    """A MERLBRDF and an analytic BRDF handed to ``render_sphere`` as objects (tabulated into the plugin's
    bitmap) render the pixels their MERL ``.binary`` file renders (read by the plugin itself), for a BRDF that
    varies with theta_h, theta_d and phi_d differently: a table passed with its axes swapped would not."""

    class Skewed:
        name = "skewed"

        def eval(self, theta_h, theta_d, phi_d):
            lobe = 0.1 + 2.0 * np.exp(-theta_h / 0.2) * (1.0 + 0.5 * np.cos(phi_d)) + 0.4 * theta_d
            return lobe[..., None] * np.array([1.0, 0.7, 0.4])

    merl = MERLBRDF.from_function(Skewed().eval, "skewed", dtype=np.float32)
    merl.write(tmp_path / "skewed.binary")
    probe = lopsided_probe(8)
    kwargs = dict(resolution=16, spp=4, seed=2)
    from_file = render_sphere(tmp_path / "skewed.binary", probe, **kwargs).image
    assert from_file.max() > 0.0
    np.testing.assert_allclose(render_sphere(merl, probe, **kwargs).image, from_file, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(render_sphere(Skewed(), probe, **kwargs).image, from_file, rtol=1e-5, atol=1e-7)


def test_render_mesh_hides_the_probe_follows_the_seed_and_uses_its_depth():
    """The background is black (the probe hidden, as in the sphere renders); the same seed renders the same
    pixels and another seed others; ``max_depth`` 2 (the default: direct light, no interreflection) and 3
    (one interreflection, which the torus's inner ring receives: brighter on average) are both honoured."""
    import trimesh

    from mi_bivariate import mesh
    from mi_bivariate.geometry import Camera

    shape = mesh.MeshShape.load(trimesh.creation.torus(1.0, 0.45, major_sections=24, minor_sections=12),
                                normals="vertex")
    view = mesh.MeshView(shape, Camera.look_at((0.0, 3.2, 3.2), (0, 0, 0), width=16, fov_deg=60))
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.9}}
    probe = Probe.constant(1.0, 8)
    image = render_mesh(white, probe, view, spp=16, seed=1)
    assert np.all(image[0, 0] == 0.0) and np.all(image[-1, -1] == 0.0)   # corners: the sky, hidden
    assert image.max() > 0.1
    np.testing.assert_array_equal(render_mesh(white, probe, view, spp=16, seed=1, max_depth=2), image)
    assert not np.array_equal(render_mesh(white, probe, view, spp=16, seed=2), image)
    deeper = render_mesh(white, probe, view, spp=16, seed=1, max_depth=3)
    assert not np.array_equal(deeper, image) and deeper.mean() > 1.01 * image.mean()   # 1.04 x measured


def test_a_bsdf_dictionary_without_a_type_is_refused_in_one_line():
    """A dictionary is passed to Mitsuba as it is; one without ``type`` is named as the BSDF's problem before
    any scene is built (not Mitsuba's error from deep inside ``load_dict``)."""
    with pytest.raises(InputError, match="needs a 'type' entry") as info:
        bsdf_dict({"reflectance": {"type": "rgb", "value": 0.5}})
    assert info.value.source == "bsdf"


def test_bsdf_dict_passes_sampling_and_interpolation_on_for_every_source(tmp_path):
    """``sampling`` (and the ``merl`` plugin's ``interpolation``) reach the plugin whatever the source: before, a
    BivariateBRDF's dictionary could drop ``sampling`` unseen (the plugin's default is ``"table"``), and the
    benchmarks compare the two samplings through it."""
    biv = BivariateBRDF(np.full((4, 4, 3), 0.1))
    biv.save(tmp_path / "b.npz")
    for source in (biv, tmp_path / "b.npz"):
        assert bsdf_dict(source, sampling="cosine")["sampling"] == "cosine"
    merl = biv.to_merl()
    merl.write(tmp_path / "m.binary")
    for source in (merl, tmp_path / "m.binary", Lambertian(0.5)):
        d = bsdf_dict(source, interpolation="nearest", sampling="cosine")
        assert (d["type"], d["interpolation"], d["sampling"]) == ("merl", "nearest", "cosine")
