"""End-to-end recovery: rendered spheres in, BRDFs out (issue: passive reflectometry).

Truths are independent of the recovery: closed-form BRDFs tabulated on the
MERL grid, Mitsuba renders of the full 3D tables, and the bivariate reduction.
"""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate import analytic, nbrdf, probes, render
from mi_bivariate.bivariate import BivariateBRDF, reduction_error
from mi_bivariate.cli import main as cli_main
from mi_bivariate.demo import synthetic_environment
from mi_bivariate.errors import InputError
from mi_bivariate.metrics import image_relative_rmse
from mi_bivariate.recover import recover, write_outputs


def _probe(data_dir_or_none, name="grace_latlong_1k"):
    if data_dir_or_none is None:
        return probes.Probe(synthetic_environment(seed=1), source="synthetic")
    return probes.shared_probe(name, data_dir_or_none)


@pytest.fixture(scope="module")
def any_probe():
    import os

    data = os.environ.get("MI_BIVARIATE_DATA")
    return _probe(data if data and os.path.isdir(data) else None)


def test_lambertian_sphere_round_trip(any_probe):
    """A rendered Lambertian sphere (bivariate: constant) comes back within 2% (Eq. 1)."""
    truth = analytic.Lambertian((0.7, 0.45, 0.2))
    merl = analytic.to_merl(truth)
    shot = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=128, spp=256, seed=3)
    result = recover(shot.image, any_probe, shot.geometry, n_normals=3000, n_dirs=16000)
    error = reduction_error(merl, result.brdf)
    assert error < 0.02, error
    # An albedo 10% off must be caught by the same metric.
    assert reduction_error(merl, BivariateBRDF(result.brdf.table * 1.1)) > 0.05


def test_glossy_bivariate_sphere_round_trip(any_probe):
    """A glossy bivariate BRDF rendered in Mitsuba: recovered table and novel-light image are close."""
    truth = analytic.BivariateLobe(diffuse=(0.4, 0.3, 0.2), specular=(1.5, 1.5, 1.5), width=0.3, f0=1.0)
    merl = analytic.to_merl(truth)
    shot = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=128, spp=512, seed=1)
    result = recover(shot.image, any_probe, shot.geometry, n_normals=4000, n_dirs=32000)
    error = reduction_error(merl, result.brdf)
    lambertian = BivariateBRDF(np.broadcast_to(result.solution.lambertian, result.brdf.table.shape).copy())
    assert error < 0.3, error
    assert error < 0.5 * reduction_error(merl, lambertian)  # far better than the best constant BRDF
    novel = probes.Probe(synthetic_environment(seed=9), source="novel")
    want = render.render_sphere(render.bsdf_dict(merl), novel, resolution=96, spp=256, seed=5)
    got = render.render_sphere(render.bsdf_dict(result.brdf), novel, resolution=96, spp=256, seed=5)
    assert image_relative_rmse(got.image, want.image, want.mask) < 0.05


@pytest.mark.parametrize("name", ["yellow-matte-plastic", "gold-metallic-paint3"])
def test_nbrdf_sphere_round_trip(data_dir, name):
    """Measured (3D) materials under Grace: the novel-probe image is within 5% of the 3D truth's."""
    truth = nbrdf.nbrdf_merl(name, data_dir)
    probe_in = probes.shared_probe("grace_latlong_1k", data_dir)
    shot = render.render_sphere(render.bsdf_dict(truth), probe_in, resolution=128, spp=256, seed=0)
    result = recover(shot.image, probe_in, shot.geometry)
    floor = reduction_error(truth, BivariateBRDF.reduce(truth))
    error = reduction_error(truth, result.brdf)
    print(f"{name}: Eq. 1 recovered {error:.3f}, floor {floor:.3f}")
    novel = probes.shared_probe("pisa_256", data_dir)
    want = render.render_sphere(render.bsdf_dict(truth), novel, resolution=96, spp=256, seed=2)
    got = render.render_sphere(render.bsdf_dict(result.brdf), novel, resolution=96, spp=256, seed=2)
    assert image_relative_rmse(got.image, want.image, want.mask) < 0.05
    assert result.adequacy.adequate


def test_blurred_probe_warns_and_grace_does_not(data_dir):
    """Sect. 3.1: the pre-filtered probe is flagged, Grace is not (adequacy depends on L, not the image)."""
    import warnings

    from mi_bivariate.errors import InputWarning
    from mi_bivariate.geometry import SphereGeometry

    image = np.full((128, 128, 3), 0.5, np.float32)
    geometry = SphereGeometry(64, 64, 60)
    kwargs = dict(n_normals=3000, n_dirs=8000, saturation=10.0)
    with pytest.warns(InputWarning, match="inadequate illumination"):
        recover(image, probes.shared_probe("royal_esplanade_1k", data_dir), geometry, **kwargs)
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        recover(image, probes.shared_probe("grace_latlong_1k", data_dir), geometry, **kwargs)


def test_bad_input_is_reported(any_probe):
    from mi_bivariate.geometry import SphereGeometry

    image = np.full((64, 64, 3), 0.5, np.float32)
    geometry = SphereGeometry(32, 32, 28)
    with pytest.raises(InputError, match="mask"):
        recover(image, any_probe, geometry, masks=np.ones((10, 10), bool))
    with pytest.raises(InputError, match="outside"):
        recover(image, any_probe, SphereGeometry(500, 500, 20))
    with pytest.raises(InputError):
        recover(np.zeros_like(image), any_probe, geometry, n_normals=500, n_dirs=2000)
    with pytest.raises(InputError, match="alpha"):
        recover(image, any_probe, geometry, alpha=-1.0)
    with pytest.raises(InputError):
        recover(image, probes.Probe.constant(0.0, 16), geometry, n_normals=500, n_dirs=2000)


def test_write_outputs_and_cli_recover(tmp_path, any_probe):
    truth = analytic.to_merl(analytic.Lambertian(0.5))
    shot = render.render_sphere(render.bsdf_dict(truth), any_probe, resolution=64, spp=64, seed=0)
    result = recover(shot.image, any_probe, shot.geometry, n_normals=800, n_dirs=4000)
    paths = write_outputs(result, tmp_path / "brdf.npz", merl=True, report=True)
    assert [p.name for p in paths] == ["brdf.npz", "brdf.exr", "brdf.binary", "brdf_report.png"]
    back = BivariateBRDF.load(tmp_path / "brdf.npz")
    np.testing.assert_array_equal(back.table, result.brdf.table)

    image = tmp_path / "sphere.exr"
    render.write_exr(image, shot.image)
    probe_file = tmp_path / "probe.exr"
    any_probe.save_exr(probe_file)
    out = tmp_path / "cli" / "brdf.npz"
    code = cli_main(["recover", str(image), "--probe", str(probe_file), "--out", str(out), "--normals", "800",
                     "--dirs", "4000", "--no-report"])
    assert code == 0
    cli_table = BivariateBRDF.load(out)
    assert reduction_error(truth, cli_table) < 0.05


def test_demo_runs_small(tmp_path, capsys):
    """The README's main command, at a small size."""
    code = cli_main(["demo", "--out", str(tmp_path), "--resolution", "64", "--spp", "16"])
    assert code == 0
    for name in ("demo.png", "recovered.npz", "metrics.json", "novel_truth.exr", "novel_recovered.exr"):
        assert (tmp_path / name).is_file(), name
    assert "BRDF error" in capsys.readouterr().out
