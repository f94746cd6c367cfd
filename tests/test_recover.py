"""End-to-end recovery: rendered spheres in, BRDFs out (issue: passive reflectometry).

Truths are independent of the recovery: closed-form BRDFs tabulated on the
MERL grid, Mitsuba renders of the full 3D tables, and the bivariate reduction.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import drjit as dr
import numpy as np
import pytest
from helpers import assert_same_sums

from mi_bivariate import analytic, nbrdf, probes, render
from mi_bivariate.bivariate import BivariateBRDF, reduction_error
from mi_bivariate.cli import main as cli_main
from mi_bivariate.errors import InputError, InputWarning
from mi_bivariate.export import write_outputs
from mi_bivariate.images import write_exr
from mi_bivariate.merl import MERLBRDF
from mi_bivariate.metrics import image_relative_rmse
from mi_bivariate.recover import recover
from mi_bivariate.sources import synthetic_environment


def _probe(data_dir_or_none, name="grace_latlong_1k"):
    if data_dir_or_none is None:
        return probes.Probe(synthetic_environment(seed=1), source="synthetic")
    return probes.shared_probe(name, data_dir_or_none)


@pytest.fixture(scope="module")
def any_probe():
    import os

    data = os.environ.get("MI_BIVARIATE_DATA")
    return _probe(data if data and os.path.isdir(data) else None)


def _assert_novel_image_close(truth, recovered, tolerance: float) -> None:
    """Render truth and recovery under a novel environment with the same seed (correlated
    Monte Carlo noise, so the difference shows the BRDFs, not the sampler) and compare."""
    novel = probes.Probe(synthetic_environment(seed=9), source="novel")
    want = render.render_sphere(render.bsdf_dict(truth), novel, resolution=96, spp=256, seed=5)
    got = render.render_sphere(render.bsdf_dict(recovered), novel, resolution=96, spp=256, seed=5)
    error = image_relative_rmse(got.image, want.image, want.mask)
    print(f"novel-probe image: relative RMSE {error:.4f}")
    assert error < tolerance, error


def _well_observed(result, fraction: float = 0.5) -> np.ndarray:
    """``(n_t, n_s) bool``: the st nodes carrying the most observation weight (top ``fraction``)."""
    weight = result.adequacy.observation_map
    return weight >= np.quantile(weight, 1.0 - fraction)


def test_lambertian_sphere_round_trip(any_probe):
    """A rendered Lambertian sphere: the albedo comes back where the image observes the table.

    Eq. 1 over *all* MERL cells is printed, not asserted: weakly observed nodes (the
    theta_h ~ 0 rows, grazing theta_d) are set by the prior and noise, and Eq. 1 weighs
    them like any other cell (see docs/results.md).
    """
    albedo = np.array([0.7, 0.45, 0.2])
    merl = analytic.to_merl(analytic.Lambertian(albedo))
    shot = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=128, spp=256, seed=3)
    result = recover(shot.image, any_probe, shot.geometry, n_normals=3000, n_dirs=16000)
    print(f"Lambertian: Eq. 1 over all cells {reduction_error(merl, result.brdf):.3f}")
    observed = result.brdf.table[_well_observed(result)]
    relative = np.abs(observed / (albedo / np.pi) - 1.0)
    assert np.median(relative) < 0.02, np.median(relative)
    assert np.percentile(relative, 75) < 0.1, np.percentile(relative, 75)
    # The same check catches an albedo 5% off.
    assert np.median(np.abs(observed * 1.05 / (albedo / np.pi) - 1.0)) > 0.03
    _assert_novel_image_close(merl, result.brdf, tolerance=0.025)


def test_glossy_bivariate_sphere_round_trip(any_probe):
    """A glossy bivariate BRDF, converged input (the reference renderer, < 0.5% noise, through the
    ``merl`` plugin): table close where observed, novel-light image close.

    (A 512-spp path-traced input has ~5% per-pixel noise in the highlight; the noise-aware solve
    then rightly smooths more, and the node error is ~6%: an accuracy check needs a clean input.)
    """
    from mi_bivariate.reference import render_reference

    truth = analytic.BivariateLobe(diffuse=(0.4, 0.3, 0.2), specular=(1.5, 1.5, 1.5), width=0.3, f0=1.0)
    merl = analytic.to_merl(truth)
    shot = render_reference(render.bsdf_dict(merl), any_probe, resolution=128, seed=1)
    result = recover(shot.image, any_probe, shot.geometry, n_normals=4000, n_dirs=32000)
    print(f"bivariate lobe: Eq. 1 over all cells {reduction_error(merl, result.brdf):.3f}")
    floor = BivariateBRDF.reduce(truth)
    mask = _well_observed(result)
    relative = np.abs(result.brdf.table[mask] / floor.table[mask] - 1.0)
    lambertian = np.broadcast_to(result.solution.lambertian, floor.table.shape)[mask]
    relative_lambertian = np.abs(lambertian / floor.table[mask] - 1.0)
    assert np.median(relative) < 0.05, np.median(relative)
    assert np.median(relative) < 0.25 * np.median(relative_lambertian)  # far better than a constant BRDF
    _assert_novel_image_close(merl, result.brdf, tolerance=0.05)


@pytest.mark.parametrize("name", ["yellow-matte-plastic", "red-phenolic"])
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
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", InputWarning)
        recover(image, probes.shared_probe("grace_latlong_1k", data_dir), geometry, **kwargs)
    # No adequacy warning. The others: no table lit by grace makes a uniform disc (the fit check), and a
    # grey disc under grace's warm light is a grey photo under a coloured probe.
    problems = [str(w.message) for w in seen if issubclass(w.category, InputWarning)]
    grey = [p for p in problems if "the photo is grey" in p]
    rest = [p for p in problems if p not in grey]
    assert len(grey) == 1 and all("the recovered table explains" in p for p in rest) and len(rest) <= 1, problems


def test_a_probe_that_does_not_match_the_photo_warns():
    """A sphere rendered under a sky, recovered under that sky turned upside down (the shared grace_latlong_1k
    file read without its rotation looks like this): the table cannot explain the image, and the recovery
    says so; under the right probe it does not."""
    import warnings

    from mi_bivariate.errors import InputWarning

    sky = probes.Probe(synthetic_environment(seed=1), source="sky")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.7, 0.45, 0.2])))
    shot = render.render_sphere(render.bsdf_dict(merl), sky, resolution=64, spp=64, seed=3)
    kwargs = dict(n_normals=1000, n_dirs=4000)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*explains", category=InputWarning)
        right = recover(shot.image, sky, shot.geometry, **kwargs)
    upside_down = sky.rotated(probes.rotation_matrix([180.0, 0.0, 0.0]))
    with pytest.warns(InputWarning, match=r"^image: the recovered table explains \d+% of the image's variation "
                                          r"\(relative residual 0\.\d\d\): the probe, the camera or the sphere"):
        wrong = recover(shot.image, upside_down, shot.geometry, **kwargs)
    assert wrong.relative_residual() > 3 * right.relative_residual()


def test_the_packaged_basis_prior_is_resampled_to_the_recoverys_grid(any_probe):
    """The packaged basis prior is learnt on 32 x 32; a recovery on another grid uses it resampled (as the
    smoothness prior is), records that, and the solve's second stage uses it; ``basis_prior=None`` runs
    without it."""
    from mi_bivariate.basis_prior import default_basis_prior
    from mi_bivariate.geometry import SphereGeometry

    packaged = default_basis_prior()
    assert packaged is not None and (packaged.n_t, packaged.n_s) == (32, 32)
    image = np.full((48, 48, 3), 0.5, np.float32)
    geometry = SphereGeometry(24, 24, 20)
    kwargs = dict(n_normals=400, n_dirs=1000, grid=(8, 8))
    with_basis = recover(image, any_probe, geometry, **kwargs)
    used = with_basis.brdf.provenance["basis_prior"]
    assert used["grid"] == [8, 8] and used["resampled_from"] == [32, 32], used
    assert "basis prior on" in with_basis.summary()
    without = recover(image, any_probe, geometry, basis_prior=None, **kwargs)
    assert without.brdf.provenance["basis_prior"] is None and "basis prior off" in without.summary()
    assert not np.allclose(with_basis.brdf.table, without.brdf.table)


def test_the_summary_counts_dropped_normals_not_pixels(any_probe):
    """The summary's drop counts are of the sampled normals (``Observations.dropped``), not of pixels: 16 NaN
    pixels on the sphere were said as "dropped pixels: ... nonfinite: 4" when 4 sampled normals fell on them."""
    from mi_bivariate.geometry import SphereGeometry

    image = np.full((48, 48, 3), 0.5, np.float32)
    image[20:24, 20:24] = np.nan  # 16 pixels on the sphere
    result = recover(image, any_probe, SphereGeometry(24, 24, 20), n_normals=300, n_dirs=200, grid=(4, 4),
                     basis_prior=None)
    dropped = result.observations.dropped
    assert 0 < dropped["nonfinite"] < 16 and len(result.observations.values) + sum(dropped.values()) == 300
    assert f"{len(result.observations.values)} normals (sampled normals dropped: " in result.summary()
    assert "pixels" not in result.summary().splitlines()[0]


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
    # Every file of the set holds the table (the temporaries exist before they are written: an output that
    # was never written would be published empty), each read back by its own reader.
    np.testing.assert_array_equal(probes.read_hdr_image(tmp_path / "brdf.exr")[0], result.brdf.table)
    merl = MERLBRDF.read(tmp_path / "brdf.binary").table            # to_merl: the same value at every phi_d
    assert (merl == merl[:, :, :1]).all()
    np.testing.assert_allclose(merl[:, :, 0], result.brdf.to_merl().table[:, :, 0], rtol=1e-15)
    assert (tmp_path / "brdf_report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    image = tmp_path / "sphere.exr"
    write_exr(image, shot.image)
    probe_file = tmp_path / "probe.exr"
    any_probe.save_exr(probe_file)
    out = tmp_path / "cli" / "brdf.npz"
    g = shot.geometry
    code = cli_main(["recover", str(image), "--probe", str(probe_file), "--out", str(out), "--normals", "800",
                     "--dirs", "4000", "--no-report", "--sphere", f"{g.cx},{g.cy},{g.radius}"])
    assert code == 0
    cli_table = BivariateBRDF.load(out)
    # Same image, probe and defaults through the CLI as through the API (file round trip).
    api = recover(shot.image, any_probe, shot.geometry, n_normals=800, n_dirs=4000)
    np.testing.assert_allclose(cli_table.table, api.brdf.table, rtol=1e-3, atol=1e-4)


def test_write_outputs_never_replaces_the_recoverys_inputs(tmp_path):
    """Before, ``write_outputs(result, "probe")`` replaced the probe file the recovery read (probe.exr) with the
    table's EXR view, and ``out="photo.npz"`` the photo. Now it refuses, naming ``out``, before anything is
    written: the probe's file always (the Recovery knows it), a photo given in ``inputs`` or recorded in the
    table's provenance (the Recovery holds its pixels, not its path)."""
    probe_file, photo = tmp_path / "probe.exr", tmp_path / "photo.exr"
    probes.Probe.constant([1.0, 0.9, 0.8], res=16).save_exr(probe_file)
    probe = probes.Probe.load(probe_file)
    shot = render.render_sphere({"type": "diffuse"}, probe, resolution=32, spp=2, seed=0)
    write_exr(photo, shot.image)
    result = recover(shot.image, probe, shot.geometry, n_normals=200, n_dirs=300, grid=(8, 8), basis_prior=None,
                     noise=None)
    before = {p: p.read_bytes() for p in (probe_file, photo)}
    for out, kwargs in ((tmp_path / "probe", {}), (tmp_path / "probe.npz", {"merl": True}),
                        (tmp_path / "photo.npz", {"inputs": [photo]})):
        with pytest.raises(InputError, match="output would overwrite the input") as info:
            write_outputs(result, out, report=False, **kwargs)
        assert info.value.source == "out", str(info.value)
    result.brdf.provenance["photos"] = [str(photo)]  # what `mi-bivariate recover` records
    with pytest.raises(InputError, match=f"would overwrite the input {photo}"):
        write_outputs(result, tmp_path / "photo", report=False)
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photo.exr", "probe.exr"]  # nothing written
    paths = write_outputs(result, tmp_path / "brdf.npz", report=False, inputs=[photo])
    assert [p.name for p in paths] == ["brdf.npz", "brdf.exr"] and all(p.is_file() for p in paths)


def test_write_outputs_warns_of_an_earlier_runs_files_beside_the_new_table(tmp_path):
    """A rerun to the same out without --merl left the earlier run's brdf.binary beside the new brdf.npz, which
    read as one set. It is warned about (not deleted); a run that writes the whole set again says nothing."""
    probe = probes.Probe.constant([1.0, 0.9, 0.8], res=16)
    shot = render.render_sphere({"type": "diffuse"}, probe, resolution=32, spp=2, seed=0)
    result = recover(shot.image, probe, shot.geometry, n_normals=200, n_dirs=300, grid=(8, 8), basis_prior=None,
                     noise=None)
    out = tmp_path / "brdf.npz"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        write_outputs(result, out, merl=True, report=False)
        write_outputs(result, out, merl=True, report=False)
    with pytest.warns(InputWarning, match=r"^out: brdf.binary beside brdf.npz was not written by this run"):
        write_outputs(result, out, report=False)
    assert (tmp_path / "brdf.binary").is_file()
    # A table no MERL reader accepts (all zero) is refused with --merl, naming the output, before any write.
    import dataclasses

    black = dataclasses.replace(result, brdf=BivariateBRDF(np.zeros_like(result.brdf.table)))
    with pytest.raises(InputError, match=r"black.binary: the BRDF table holds no positive value"):
        write_outputs(black, tmp_path / "black.npz", merl=True, report=False)
    assert not any(tmp_path.glob("black*")) and not any(tmp_path.glob(".black*"))



def test_write_outputs_refuses_a_folder_as_out(tmp_path):
    """Before, ``write_outputs(result, folder)`` wrote ``folder.npz`` and ``folder.exr`` beside the folder, not
    in it (and ``"new/"`` wrote ``new.npz``), where the docstring promised an InputError for a directory; the
    CLI's --out refused both. Now one check (atomic.check_out_file) refuses both, naming ``out``."""
    probe = probes.Probe.constant([1.0, 0.9, 0.8], res=16)
    shot = render.render_sphere({"type": "diffuse"}, probe, resolution=32, spp=2, seed=0)
    result = recover(shot.image, probe, shot.geometry, n_normals=200, n_dirs=300, grid=(8, 8), basis_prior=None,
                     noise=None)
    folder = tmp_path / "outputs"
    folder.mkdir()
    for out in (folder, str(tmp_path / "new") + "/"):
        with pytest.raises(InputError, match="out is a folder") as info:
            write_outputs(result, out, report=False)
        assert info.value.source == "out", str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outputs"] and not any(folder.iterdir())

def test_demo_runs_small(tmp_path, capsys, loo_reductions):
    """The README's main command, at a small size (its leave-one-out priors' training reductions made by the
    session's fixture, shared with the quickstart notebook's test)."""
    code = cli_main(["demo", "--out", str(tmp_path), "--resolution", "64", "--spp", "16"])
    assert code == 0
    for name in ("demo.png", "recovered.npz", "metrics.json", "novel_truth.exr", "novel_recovered.exr"):
        assert (tmp_path / name).is_file(), name
    out = capsys.readouterr().out
    assert "BRDF error" in out
    # A shared material is scored by priors that never saw it (the packaged ones did); the scoring
    # renders' own noise is measured and stated.
    numbers = json.loads((tmp_path / "metrics.json").read_text())
    shared = "MERL-NBRDF" in numbers["material"]
    assert numbers["priors"].startswith("leave-one-out" if shared else "packaged"), numbers["priors"]
    assert f"priors                                  {numbers['priors']}" in out
    # measured (at 16 spp the reference's directions are cut to 1/16: about a third of the floor)
    assert 0.0 < numbers["reference"]["noise"] < numbers["relight_floor"], numbers
    assert f"reference noise (truth, two seeds)      {numbers['reference']['noise']:.4f}" in out
    assert "brdf_error_bivariate_floor_eq1" not in numbers and {"exact_floor", "grid_floor"} <= set(numbers)


def test_demo_writes_strict_json_when_a_figure_is_undefined(tmp_path, capsys):
    """A sphere too small for any cell to count as observed: Eq. 1 on observed cells is undefined, and
    metrics.json says null (strict JSON), not NaN."""
    assert cli_main(["demo", "--out", str(tmp_path), "--resolution", "8", "--spp", "4"]) == 0

    def refuse(constant):
        raise ValueError(f"metrics.json holds {constant}")

    numbers = json.loads((tmp_path / "metrics.json").read_text(), parse_constant=refuse)
    assert numbers["observed_cell_fraction"] == 0.0 and numbers["brdf_error_recovered_eq1_observed"] is None
    assert "Eq. 1 on observed cells     n/a   (0% of the cells)" in capsys.readouterr().out


def test_demo_without_shared_data_uses_the_probes_it_is_given(tmp_path, monkeypatch, capsys):
    """Without the shared data only the default (shared) probes get synthetic stand-ins: a probe file the
    user names is used, a black one is refused, and a data folder given explicitly must exist."""
    monkeypatch.delenv("MI_BIVARIATE_DATA", raising=False)
    write_exr(tmp_path / "black.exr", np.zeros((8, 16, 3), np.float32))
    write_exr(tmp_path / "grey.exr", np.full((8, 16, 3), 0.5, np.float32))
    small = ["--resolution", "24", "--spp", "4", "--material", "ggx:alpha=0.3"]
    assert cli_main(["demo", "--out", str(tmp_path / "a"), *small, "--input-probe", str(tmp_path / "grey.exr")]) == 0
    out = capsys.readouterr().out
    assert f"under {tmp_path / 'grey.exr'}" in out and "pisa_256 -> synthetic:7" in out
    assert cli_main(["demo", "--out", str(tmp_path / "b"), *small, "--input-probe", str(tmp_path / "black.exr")]) == 2
    assert cli_main(["demo", "--out", str(tmp_path / "c"), *small, "--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "probe is black" in err[0] and "shared data folder does not exist" in err[1]
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_cli_recover_batch_matches_recover_and_goes_on_past_a_bad_photo(tmp_path, any_probe, capsys, monkeypatch):
    """``recover-batch``: each photo's table is bit-identical to ``recover``'s on it (to float32 rounding
    under CUDA's atomics), a missing photo gets one error line while the others are
    written, and the exit status is then 2."""
    truth = analytic.to_merl(analytic.Lambertian(0.5))
    shot = render.render_sphere(render.bsdf_dict(truth), any_probe, resolution=48, spp=16, seed=0)
    photos = tmp_path / "photos"
    write_exr(photos / "a.exr", shot.image)
    write_exr(photos / "b.exr", 0.5 * shot.image)
    probe_file = tmp_path / "probe.exr"
    any_probe.save_exr(probe_file)
    small = ["--normals", "400", "--dirs", "2000", "--grid", "8", "8", "--no-report", "--threads", "1"]
    out = tmp_path / "batch"
    threads = dr.thread_count()
    code = cli_main(["recover-batch", str(photos / "a.exr"), str(photos / "missing.exr"), str(photos / "b.exr"),
                     "--probe", str(probe_file), "--out-dir", str(out), *small])
    assert dr.thread_count() == threads  # --threads is restored for whatever runs next in this process
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mi-bivariate: error:")]
    assert code == 2 and len(err) == 1 and "missing.exr" in err[0], err
    assert sorted(p.name for p in out.iterdir()) == ["a.exr", "a.npz", "b.exr", "b.npz"]
    assert cli_main(["recover", str(photos / "b.exr"), "--probe", str(probe_file), "--out",
                     str(tmp_path / "single.npz"), *small]) == 0
    with np.load(out / "b.npz") as batch, np.load(tmp_path / "single.npz") as single:
        for key in batch.files:
            if key != "meta":
                assert_same_sums(batch[key], single[key], rel=1e-4, err_msg=key)
    # A bad photo named as a shell glob or a user writes it ("./photos//c.exr") is still that photo's
    # problem: the batch goes on (the reader names it "photos/c.exr").
    (photos / "c.exr").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert cli_main(["recover-batch", "./photos//c.exr", "./photos/a.exr", "--probe", str(probe_file),
                     "--out-dir", "dotted", *small]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mi-bivariate: error:")]
    assert len(err) == 1 and "c.exr" in err[0] and (tmp_path / "dotted" / "a.npz").is_file(), err
    # Two photos with the same name would write the same outputs: refused before any work.
    write_exr(tmp_path / "a.exr", shot.image)
    capsys.readouterr()
    assert cli_main(["recover-batch", str(photos / "a.exr"), str(tmp_path / "a.exr"), "--probe", str(probe_file),
                     "--out-dir", str(tmp_path / "twice"), *small]) == 2
    assert "as " + str(photos / "a.exr") + " does" in capsys.readouterr().err and not (tmp_path / "twice").exists()
    # The photos' own folder as --out-dir: each photo's EXR view would overwrite it; refused, photo intact.
    before = (photos / "a.exr").read_bytes()
    assert cli_main(["recover-batch", str(photos / "a.exr"), "--probe", str(probe_file), "--out-dir", str(photos),
                     *small]) == 2
    assert "overwrite the input" in capsys.readouterr().err and (photos / "a.exr").read_bytes() == before


def test_cli_recover_batch_stops_on_a_shared_problem_and_warns_for_every_photo(tmp_path):
    """A problem every photo shares (here ``--grid 1 8``, which the library refuses) stops the batch with one
    line and no outputs; and a warning the library gives for every photo is shown for every photo, not
    only the first (Python shows a warning once per code location unless told otherwise). A fresh process,
    as a user runs it: pytest records warnings itself."""
    probe = probes.Probe.constant(1.0, 16)
    shot = render.render_sphere(render.bsdf_dict(analytic.to_merl(analytic.Lambertian(0.5))), probe,
                                resolution=48, spp=16, seed=0)
    clipped = np.minimum(shot.image, 0.8 * float(shot.image.max()))  # a clipped photo: the capture warns
    photos = [tmp_path / "a.exr", tmp_path / "b.exr"]
    for photo in photos:
        write_exr(photo, clipped)
    probe.save_exr(tmp_path / "probe.exr")
    run = [sys.executable, "-m", "mi_bivariate", "recover-batch", *map(str, photos), "--probe",
           str(tmp_path / "probe.exr"), "--normals", "400", "--dirs", "2000", "--no-report"]
    path = [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in path if p))
    shared = subprocess.run(run + ["--out-dir", str(tmp_path / "o1"), "--grid", "1", "8"], capture_output=True,
                            text=True, env=env, timeout=300)
    errors = [line for line in shared.stderr.splitlines() if line.startswith("mi-bivariate: error:")]
    assert shared.returncode == 2 and len(errors) == 1 and "grid" in errors[0], shared.stderr[-2000:]
    assert not any((tmp_path / "o1").glob("*.npz"))
    both = subprocess.run(run + ["--out-dir", str(tmp_path / "o2"), "--grid", "8", "8"], capture_output=True,
                          text=True, env=env, timeout=300)
    assert both.returncode == 0, both.stderr[-2000:]
    assert both.stderr.count("sit exactly at the maximum") == 2, both.stderr[-3000:]


def test_noise_check_counts_channels_with_signal_only():
    """A noise model that swamps every lit channel is refused; a red-only image (G and B exactly 0,
    whose relative noise is unbounded) and dark rows are not."""
    from mi_bivariate.recover import MAX_NOISE_TO_SIGNAL, _check_noise_against_signal

    rng = np.random.default_rng(3)
    red = np.zeros((500, 3))
    red[:, 0] = rng.uniform(0.01, 1.0, 500)
    red[:300, 0] = 0.0                                         # dark rows, most of them
    fine = 0.02 * red + 1e-4
    _check_noise_against_signal(fine, red)
    fine[300, 0] = 1e9                                         # one wild row moves a mean, not the median
    _check_noise_against_signal(fine, red)
    _check_noise_against_signal(np.where(red > 0, 0.5 * MAX_NOISE_TO_SIGNAL * red, 1e-4), red)
    with pytest.raises(InputError, match="carry no information"):
        _check_noise_against_signal(2.0 * MAX_NOISE_TO_SIGNAL * red + 1e-4, red)
    grey = np.repeat(red[:, :1], 3, axis=1)
    swamped = 2.0 * MAX_NOISE_TO_SIGNAL * grey + 1e-4
    swamped[:, 1] = 0.02 * grey[:, 1] + 1e-4                   # one channel with information is enough
    _check_noise_against_signal(swamped, grey)


def test_recover_out_keeps_an_upper_case_npz_suffix(tmp_path):
    from mi_bivariate.export import output_paths

    assert output_paths(tmp_path / "x.NPZ", merl=True)[:3] == [tmp_path / "x.NPZ", tmp_path / "x.exr",
                                                               tmp_path / "x.binary"]
    assert output_paths(tmp_path / "x")[0] == tmp_path / "x.npz"


def test_cli_recover_models_a_perspective_photo_with_fov(tmp_path, any_probe, capsys):
    """A pinhole render (60 degrees across a 80 x 56 image) is explained far better as what it is
    (recover --fov 60) than as an orthographic view, with the report written too; the sphere line
    reports the camera distance. Width and height swapped in the field of view fails it."""
    from mi_bivariate.render import bsdf_dict, render_sphere

    truth = analytic.to_merl(analytic.analytic_from_spec("ggx:diffuse=0.2,specular=0.6,alpha=0.15"))
    shot = render_sphere(bsdf_dict(truth), any_probe, resolution=(80, 56), spp=512, camera="perspective", seed=0,
                         fov=60.0, radius_fraction=0.3)        # not square: the field of view is horizontal
    write_exr(tmp_path / "photo.exr", shot.image)
    any_probe.save_exr(tmp_path / "probe.exr")
    residual = {}
    for fov in (None, "60"):
        argv = ["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "probe.exr"), "--out",
                str(tmp_path / "x.npz"), "--normals", "800", "--dirs", "2000", "--grid", "12", "12",
                "--noise", "none"] + (["--fov", fov] if fov else ["--no-report"])     # the report under --fov too
        assert cli_main(argv) == 0
        out = capsys.readouterr().out
        residual[fov] = float(out.split("relative residual ")[1].split()[0])
        assert ("distance" in out.split("sphere")[1].splitlines()[0]) == (fov is not None)
    assert residual["60"] < 0.75 * residual[None], residual     # measured 0.35-0.40 (with or without the data)
    assert (tmp_path / "x_report.png").stat().st_size > 0


def test_cli_recover_batch_goes_on_past_a_photo_the_noise_swamps(tmp_path, any_probe, capsys):
    """The noise check measures each photo's own rows: a photo 1e6 times dimmer than the given noise
    allows fails by its name, and the batch recovers the others (it used to stop at it)."""
    truth = analytic.to_merl(analytic.Lambertian(0.5))
    shot = render.render_sphere(render.bsdf_dict(truth), any_probe, resolution=48, spp=16, seed=0)
    write_exr(tmp_path / "a.exr", shot.image)
    write_exr(tmp_path / "dim.exr", 1e-6 * shot.image)
    write_exr(tmp_path / "b.exr", 0.5 * shot.image)
    any_probe.save_exr(tmp_path / "probe.exr")
    # Read noise (std) of 1e-3 of the photo's mean signal: nothing for a.exr and b.exr, a thousand
    # times the signal of dim.exr, whatever the probe's brightness (shared or synthetic).
    read_variance = (1e-3 * float(np.mean(shot.image[shot.mask]))) ** 2
    code = cli_main(["recover-batch", *(str(tmp_path / n) for n in ("a.exr", "dim.exr", "b.exr")), "--probe",
                     str(tmp_path / "probe.exr"), "--out-dir", str(tmp_path / "out"), "--noise", f"0,{read_variance:.6g}",
                     "--normals", "400", "--dirs", "1000", "--grid", "8", "8", "--no-report"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("mi-bivariate: error:")]
    assert code == 2 and len(err) == 1 and err[0].startswith(f"mi-bivariate: error: {tmp_path / 'dim.exr'}: "), err
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["a.npz", "b.npz"]


def test_a_very_bright_image_recovers_like_a_dim_one(any_probe):
    """Radiance near 1e19 (finite in float32, its square is not): the same relative residual and the
    same table up to the scale, not a NaN from a float32 norm."""
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.4, 0.3])))
    shot = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=48, spp=16, seed=1)
    base = recover(shot.image, any_probe, shot.geometry, n_normals=800, n_dirs=2000)
    bright = recover(shot.image * np.float32(1e20), any_probe, shot.geometry, n_normals=800, n_dirs=2000)
    assert np.isfinite(bright.relative_residual())
    assert bright.relative_residual() == pytest.approx(base.relative_residual(), rel=1e-4)
    np.testing.assert_allclose(bright.brdf.table, base.brdf.table * 1e20, rtol=1e-3,
                               atol=1e-6 * 1e20 * base.brdf.table.max())


def test_cli_probe_rotation_turns_a_probe_stored_in_another_orientation(tmp_path, capsys):
    """A photo lit by a sky turned upside down (180 degrees about x), with the sky's file stored unturned: recover
    warns that the table does not explain the photo, and with --probe-rotation=180,0,0 it does not,
    records the rotation in the table's provenance, and fits the photo far better."""
    import json
    import warnings

    sky = probes.Probe(synthetic_environment(seed=1), source="sky")
    turned = sky.rotated(euler_deg=(180.0, 0.0, 0.0))
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.7, 0.45, 0.2])))
    shot = render.render_sphere(render.bsdf_dict(merl), turned, resolution=64, spp=64, seed=3)
    write_exr(tmp_path / "photo.exr", shot.image)
    sky.save_exr(tmp_path / "sky.exr")
    residual = {}
    for rotation in ([], ["--probe-rotation=180,0,0"]):
        out = tmp_path / f"x{len(rotation)}.npz"
        argv = ["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "sky.exr"), "--out", str(out),
                "--normals", "1000", "--dirs", "4000", "--grid", "16", "16", "--no-report"] + rotation
        with warnings.catch_warnings(record=True) as seen:  # pytest records warnings before stderr sees them
            warnings.simplefilter("always")
            assert cli_main(argv) == 0
        captured = capsys.readouterr()
        residual[bool(rotation)] = float(captured.out.split("relative residual ")[1].split()[0])
        warned = any("the recovered table explains" in str(w.message) for w in seen)
        assert warned != bool(rotation), [str(w.message) for w in seen]
        to_world = json.loads(str(np.load(out)["meta"]))["provenance"]["probe_to_world"][0]
        np.testing.assert_allclose(to_world, turned.to_world if rotation else np.eye(4), atol=1e-12)
    assert residual[True] < 0.5 * residual[False], residual


def test_a_grey_photo_under_a_coloured_probe_warns():
    """A one-channel photo read as R = G = B, lit by a coloured probe, warns (its table's colour would be the
    probe's inverse); an RGB photo, or a grey photo under a grey probe, does not."""
    import warnings

    from mi_bivariate.errors import InputWarning

    warm = probes.Probe(np.full((16, 32, 3), (1.0, 0.8, 0.5), np.float32), source="warm")
    grey = probes.Probe(np.full((16, 32, 3), 0.8, np.float32), source="grey")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.7, 0.45, 0.2])))
    shot = render.render_sphere(render.bsdf_dict(merl), warm, resolution=32, spp=16, seed=3)
    luminance = shot.image.mean(axis=-1, keepdims=True).repeat(3, axis=-1)
    small = dict(n_normals=300, n_dirs=1000, grid=(8, 8), noise=None)
    for image, probe, expected in ((luminance, warm, True), (shot.image, warm, False), (luminance, grey, False)):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            recover(image, probe, shot.geometry, **small)
        said = [str(w.message) for w in seen
                if issubclass(w.category, InputWarning) and "photo is grey" in str(w.message)]
        assert bool(said) == expected, (probe.source, said)


@pytest.fixture(scope="module")
def two_photos():
    """A small two-image recovery (32 px spheres, 300 normals, 1000 directions, 8 x 8 nodes): an RGB photo
    under a grey probe and a grey (R = G = B) photo under a warm one, with the wall time it took and its
    warnings."""
    import time
    import warnings

    grey = probes.Probe(np.full((16, 32, 3), 0.8, np.float32), source="grey")
    warm = probes.Probe(np.full((16, 32, 3), (1.0, 0.8, 0.5), np.float32), source="warm")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.7, 0.45, 0.2])))
    under_grey = render.render_sphere(render.bsdf_dict(merl), grey, resolution=32, spp=16, seed=3)
    under_warm = render.render_sphere(render.bsdf_dict(merl), warm, resolution=32, spp=16, seed=4)
    luminance = under_warm.image.mean(axis=-1, keepdims=True).repeat(3, axis=-1)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        start = time.perf_counter()
        result = recover([under_grey.image, luminance], [grey, warm], [under_grey.geometry, under_warm.geometry],
                         n_normals=300, n_dirs=1000, grid=(8, 8), noise=None)
        wall = time.perf_counter() - start
    return result, wall, [str(w.message) for w in seen if issubclass(w.category, InputWarning)]


def test_each_images_grey_photo_check_uses_its_own_probe(two_photos):
    """Image 1 is grey under the warm probe (warned); image 0 is RGB under the grey probe (not)."""
    said = [m for m in two_photos[2] if "photo is grey" in m]
    assert len(said) == 1 and said[0].startswith("image 1:"), said


def test_the_timings_add_up_to_no_more_than_the_recovery_took(two_photos):
    """Each stage is timed once: the stages' sum is at most the wall time around recover()."""
    result, wall, _ = two_photos
    assert {"observations", "lighting matrix", "solve"} <= set(result.timings), result.timings
    assert min(result.timings.values()) >= 0.0 and sum(result.timings.values()) <= wall, (result.timings, wall)


def test_an_image_and_probe_whose_ratio_leaves_float32_are_refused_before_the_solve(any_probe, tmp_path):
    """Each within its own limits, an image 1e38 times brighter than its probe (or 1e-32 times) asks for a
    table of ~1e37 1/sr (~1e-33): refused naming the image (a helper's image of 3e35 under a probe of 1e-30
    ended in "mean: the table prior's mean and std must be finite", an internal name and no advice); with
    two photos too, whose cross-image weights solve each alone first; the command line names the photo."""
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.5, 0.4])))
    shot = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=32, spp=16, seed=5)
    kwargs = dict(n_normals=300, n_dirs=1000, grid=(8, 8), noise=None)
    dim_probe = probes.Probe(any_probe.data * 1e-3, any_probe.to_world, "dim probe")
    bright_probe = probes.Probe(any_probe.data * 1e14, any_probe.to_world, "bright probe")
    for image, probe, value in ((shot.image * 1e35, dim_probe, r"e\+3[6-8]"),
                                (shot.image * 1e-18, bright_probe, r"e-3[2-4]")):
        with pytest.raises(InputError, match=rf"image over the probe gives a table of about [0-9.]+{value} 1/sr, "
                                             "outside float32's working range") as err:
            recover(image, probe, shot.geometry, **kwargs)
        assert err.value.source == "image" and "scale the image or the probe" in str(err.value)
    # Two photos: the cross-image weights solve each photo alone before recover's own check; each is checked
    # there too (a review's pair ended in "mean: ..." again).
    other = render.render_sphere(render.bsdf_dict(merl), any_probe, resolution=32, spp=16, seed=6)
    with pytest.raises(InputError, match=r"the image 0 over the probe gives a table of about [0-9.]+e\+3[6-8] 1/sr"):
        recover([shot.image * 1e35, other.image * 1e35], [dim_probe, dim_probe], [shot.geometry, other.geometry],
                **kwargs)
    # A channel without light (a blue albedo of 0: level 0) is no table out of range; nor is a table of
    # ~1e30 1/sr (recovered right before these checks: the same table, scaled).
    black_blue = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.5, 0.0])))
    no_blue = render.render_sphere(render.bsdf_dict(black_blue), any_probe, resolution=32, spp=16, seed=5)
    assert recover(no_blue.image, any_probe, no_blue.geometry, **kwargs).brdf.table[..., 2].max() < 1e-3
    plain = recover(shot.image, any_probe, shot.geometry, **kwargs).brdf.table
    scaled = recover(shot.image * 1e30, any_probe, shot.geometry, **kwargs).brdf.table
    np.testing.assert_allclose(scaled / 1e30, plain, rtol=1e-4, atol=1e-6 * plain.max())
    write_exr(tmp_path / "bright.exr", shot.image * 1e35)
    dim_probe.save_exr(tmp_path / "probe.exr")
    status = cli_main(["recover", str(tmp_path / "bright.exr"), "--probe", str(tmp_path / "probe.exr"),
                       "--normals", "300", "--dirs", "1000", "--grid", "8", "8", "--noise", "none",
                       "--out", str(tmp_path / "t.npz"), "--no-report"])
    assert status == 2 and not (tmp_path / "t.npz").exists()


def test_the_provenance_and_summary_say_what_was_computed(two_photos):
    """Rows, probes and the summary's numbers, recomputed from the recovery's arrays (prediction = L f)."""
    import re

    result = two_photos[0]
    obs, provenance = result.observations, result.brdf.provenance
    assert provenance["normals"] == len(obs.values) == len(result.predicted)
    assert provenance["probes"] == ["grey", "warm"]
    predicted = np.einsum("mnc,nc->mc", result.lighting_matrix.astype(np.float64),
                          result.brdf.table.reshape(-1, 3).astype(np.float64))
    # The recovery's prediction is the solve's own (each channel's winner), L f to float32 rounding.
    np.testing.assert_array_equal(result.predicted, result.solution.predicted)
    np.testing.assert_allclose(result.predicted, predicted, rtol=0, atol=1e-6 * np.abs(predicted).max())
    values = np.asarray(obs.values, np.float64)
    overall = np.linalg.norm(values - predicted) / np.linalg.norm(values)
    summary = result.summary()
    assert float(re.search(r"relative residual (\S+) \(per image", summary).group(1)) == pytest.approx(overall, abs=2e-4)
    measured = np.asarray(result.brdf.confidence["measured"])
    percent = 100.0 * np.mean(np.all(measured > 0.5, axis=-1))
    assert f"measured {percent:.0f}% of the nodes" in summary, summary


def test_the_saved_image_factors_and_observation_weight_are_those_of_the_solve(two_photos):
    """The rows' sigma (the model error for noise=None, times the image factor the provenance records) gives
    the table again, and the saved observation weight is diag(L^T W L) times the table level squared, with
    W = 1 / (M sigma^2) and the level the weighted best constant fit (closed form, per channel)."""
    from mi_bivariate import solve
    from mi_bivariate.basis_prior import default_basis_prior
    from mi_bivariate.prior import default_prior

    result = two_photos[0]
    obs, L = result.observations, result.lighting_matrix.astype(np.float64)
    factors = np.asarray(result.brdf.provenance["image_sigma_factors"])
    assert factors.shape == (2,) and factors.max() > 1.0, factors  # the two images do not weigh alike
    sigma = solve.row_sigma(obs.values, obs.image_index, noise=None) * factors[obs.image_index][:, None]
    basis = default_basis_prior()
    again = solve.solve_stages(solve.prepare_data_term(result.lighting_matrix, obs.values, sigma),
                               default_prior().resampled(8, 8), None,
                               None if basis is None else basis.resampled(8, 8))
    np.testing.assert_array_equal(again.table, result.brdf.table)
    w = 1.0 / (len(obs.values) * sigma ** 2)                           # (M, 3)
    constant = L.sum(axis=1)                                           # (M, 3): L f for f = 1
    level = np.sum(constant * obs.values * w, 0) / np.sum(constant ** 2 * w, 0)
    truth = np.einsum("mnc,mc->nc", L ** 2, w) * level ** 2
    np.testing.assert_allclose(result.brdf.confidence["observation_weight"], truth.reshape(8, 8, 3), rtol=1e-6)


@pytest.mark.parametrize("report_render", [False, True])
def test_write_outputs_passes_report_render_to_the_report(tmp_path, two_photos, monkeypatch, report_render):
    """``report_render`` asks the report for a path-traced re-render (``--report-render``)."""
    from mi_bivariate import export

    asked = []

    def report(result, path, path_trace=False):
        asked.append(path_trace)
        Path(path).write_bytes(b"png")

    monkeypatch.setattr(export, "write_recovery_report", report)
    write_outputs(two_photos[0], tmp_path / "t.npz", report_render=report_render)
    assert asked == [report_render]


def test_a_fit_within_its_noise_is_not_told_the_probe_may_not_match():
    """A 24 px, 4 spp render under a uniform probe (almost no variation to explain): its residual is within
    a few sigma of its noise ("auto"), so the fit check stays silent although it explains ~0% of it."""
    import warnings

    uniform = probes.Probe(np.full((16, 32, 3), 1.0, np.float32), source="uniform")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.5, 0.4])))
    shot = render.render_sphere(render.bsdf_dict(merl), uniform, resolution=24, spp=4, seed=2)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        recover(shot.image, uniform, shot.geometry, n_normals=300, n_dirs=1000, grid=(8, 8))
    assert not [w for w in seen if "table explains" in str(w.message)], [str(w.message) for w in seen]


def test_auto_saturation_drops_a_clipped_plateau_but_not_an_unclipped_peak():
    """``recover_from_photo(saturation="auto")``: a render's own brightest pixel is no clipping level (no
    pixel dropped); the same render clipped at its 99th percentile drops the pixels at that level."""
    import warnings

    from mi_bivariate.recover import recover_from_photo

    probe = probes.Probe(np.full((16, 32, 3), (1.0, 0.8, 0.5), np.float32), source="warm")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.7, 0.45, 0.2])))
    shot = render.render_sphere(render.bsdf_dict(merl), probe, resolution=32, spp=64, seed=3)
    level = np.float32(np.quantile(shot.image[shot.mask], 0.99))
    clipped = np.minimum(shot.image, level)
    # n_normals above the sphere's ~800 pixels: every pixel is sampled, the brightest included
    small = dict(sphere=(shot.geometry.cx, shot.geometry.cy, shot.geometry.radius), n_normals=3000, n_dirs=1000,
                 grid=(8, 8), noise=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        assert recover_from_photo(shot.image, probe, **small).observations.dropped["saturated"] == 0
        assert recover_from_photo(clipped, probe, **small).observations.dropped["saturated"] > 0
