"""mi_bivariate.sources: every kind of name and path turns into the right material or probe,
and bad names fail with one InputError naming them."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate import analytic, nbrdf, sources
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERLBRDF

GGX = "ggx:diffuse=0.2,specular=0.5,alpha=0.2"


def test_analytic_specs_tabulate_the_parsed_model():
    brdf = sources.load_brdf(GGX)
    want = analytic.to_merl(analytic.CookTorranceGGX([0.2] * 3, [0.5] * 3, alpha=0.2))
    assert isinstance(brdf, MERLBRDF) and brdf.table.dtype == np.float64
    np.testing.assert_array_equal(brdf.table, want.table)
    assert sources.load_brdf(GGX, dtype=np.float32).table.dtype == np.float32
    for name in sources.ANALYTIC_NAMES:                     # bare family names take the class defaults
        assert sources.is_analytic_spec(name)
        assert type(analytic.analytic_from_spec(name)).__name__ != "AnalyticBRDF"
    assert isinstance(sources.load_brdf("lambertian"), MERLBRDF)
    assert sources.DEFAULT_ANALYTIC.startswith("ggx:")
    analytic.analytic_from_spec(sources.DEFAULT_ANALYTIC)


def test_files_are_read_by_their_type(tmp_path):
    merl = analytic.to_merl(analytic.Lambertian([0.5, 0.3, 0.2]))
    merl.write(tmp_path / "m.binary")
    np.testing.assert_array_equal(sources.load_brdf(str(tmp_path / "m.binary")).table,
                                  MERLBRDF.read(tmp_path / "m.binary").table)
    biv = BivariateBRDF.reduce(merl, n_t=8, n_s=8)
    biv.save(tmp_path / "b.npz")
    np.testing.assert_array_equal(sources.load_brdf(str(tmp_path / "b.npz")).table, biv.table)
    (tmp_path / "t.txt").write_text("x")
    with pytest.raises(InputError, match="unknown BRDF file type"):
        sources.load_brdf(str(tmp_path / "t.txt"))
    with pytest.raises(InputError, match="not a file, an NBRDF material name or an analytic spec"):
        sources.load_brdf("no-such-material")
    # Folders expand to their .binary files, sorted; an empty folder is an error.
    merl.write(tmp_path / "a.binary")
    assert sources.merl_files([tmp_path, "gold-paint"]) == [tmp_path / "a.binary", tmp_path / "m.binary",
                                                            "gold-paint"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no MERL .binary"):
        sources.merl_files(tmp_path / "empty")


def test_resolve_materials_kinds_order_and_duplicates(tmp_path):
    analytic.to_merl(analytic.Lambertian([0.5, 0.3, 0.2])).write(tmp_path / "m.binary")
    specs = sources.resolve_materials([str(tmp_path / "m.binary"), "blue-acrylic", GGX, "blue-acrylic",
                                       str(tmp_path)])
    assert [(s.kind, s.label) for s in specs] == [("merl", "m"), ("nbrdf", "blue-acrylic"),
                                                  ("analytic", analytic.analytic_from_spec(GGX).name)]
    assert [s.spec for s in sources.resolve_materials(["nbrdf"])] == list(nbrdf.NBRDF_MATERIALS)
    assert [s.spec for s in sources.resolve_materials(["nbrdf-train"])] == list(nbrdf.NBRDF_TRAIN_MATERIALS)
    everything = sources.resolve_materials(["aventurnine", "nbrdf-all", "nbrdf"])   # duplicates dropped
    assert [s.spec for s in everything] == ["aventurnine"] + [n for n in nbrdf.ALL_NBRDF_MATERIALS if n != "aventurnine"]
    assert len(everything) == 73 and all(s.kind == "nbrdf" for s in everything)
    with pytest.raises(InputError, match="not a folder, .binary file, MERL-NBRDF name or analytic spec"):
        sources.resolve_materials(["no-such-material"])
    with pytest.raises(InputError, match="MERL file not found"):
        sources.resolve_materials([str(tmp_path / "missing.binary")])
    truth = sources.load_truth(specs[2])
    assert truth.table.dtype == np.float32      # the evaluation's truths of analytic specs are float32
    np.testing.assert_allclose(truth.table, sources.load_brdf(GGX).table, rtol=1e-6)


def test_synthetic_probes_and_labels():
    probe = sources.load_probe("synthetic:3")
    np.testing.assert_array_equal(probe.data[..., :3], sources.synthetic_environment(seed=3))
    assert sources.load_probe("synthetic:3", cache=True) is sources.load_probe("synthetic:3", cache=True)
    assert sources.load_probe("synthetic:3") is not probe                       # uncached by default
    with pytest.raises(InputError, match="seed must be an integer"):
        sources.load_probe("synthetic:x")
    for seed in ("-1", "4294967296"):  # -1 was numpy's ValueError, a traceback from recover --probe synthetic:-1
        with pytest.raises(InputError, match=f"synthetic:{seed}: synthetic probe seed must be an integer from 0 to"):
            sources.load_probe("synthetic:" + seed)
    assert sources.probe_label("/a/b/pisa_256.hdr") == "pisa_256"
    assert sources.probe_label("synthetic:1") == "synthetic:1"


def test_a_shared_probe_by_path_is_the_shared_probe_and_a_copy_is_read_as_is(data_dir, tmp_path, monkeypatch):
    """``--probe .../probes/grace_latlong_1k.exr`` and ``--probe grace_latlong_1k`` are one probe (its rotation:
    the file is stored upside down, pbrt's convention); a copy of the file elsewhere is read as stored."""
    import shutil

    from mi_bivariate import probes

    monkeypatch.delenv("MI_BIVARIATE_DATA", raising=False)
    by_name = sources.load_probe("grace_latlong_1k", data_dir)
    path = probes.shared_probe_path("grace_latlong_1k", data_dir)
    np.testing.assert_array_equal(by_name.to_world[:3, :3], probes.GRACE_LATLONG_ROTATION)
    for given in (data_dir, None):  # found through the data folder, or as a shared data folder's probes/
        by_path = sources.load_probe(str(path), given)
        np.testing.assert_array_equal(by_path.to_world, by_name.to_world)
        np.testing.assert_array_equal(by_path.data, by_name.data)
    copy = tmp_path / path.name
    shutil.copyfile(path, copy)
    np.testing.assert_array_equal(sources.load_probe(str(copy), data_dir).to_world, np.eye(4))
    other = probes.shared_probe_path("pisa_256", data_dir)
    np.testing.assert_array_equal(sources.load_probe(str(other), data_dir).to_world, np.eye(4))
    link = tmp_path / "my_probe.exr"  # a symbolic link to the shared file, under any name, is that file
    link.symlink_to(path)
    np.testing.assert_array_equal(sources.load_probe(str(link), None).to_world, by_name.to_world)


def test_an_uncached_load_is_fresh_after_a_cached_one():
    """``cache=False`` (the default) never hands out the process's cached probe, before or after one is kept."""
    cached = sources.load_probe("synthetic:5", cache=True)
    assert sources.load_probe("synthetic:5") is not cached
    assert sources.load_probe("synthetic:5", cache=True) is cached


def test_the_probe_cache_follows_the_data_folder_and_the_file(tmp_path, monkeypatch):
    """Before, a cached probe was keyed by its spec and the ``data_dir`` argument only: after
    ``$MI_BIVARIATE_DATA`` moved to another data folder, ``load_probe("pisa_256", cache=True)`` handed back the
    first folder's probe, and a probe file rewritten since was not read again. The truth: each folder's own
    file, as read uncached."""
    import os

    from mi_bivariate import images

    folders = [tmp_path / "data_a", tmp_path / "data_b"]
    for folder, level in zip(folders, (1.0, 2.0)):
        (folder / "probes").mkdir(parents=True)
        images.write_exr(folder / "probes" / "pisa_256.exr", np.full((8, 16, 3), level, np.float32))
    for folder, level in zip(folders, (1.0, 2.0)):
        monkeypatch.setenv("MI_BIVARIATE_DATA", str(folder))
        probe = sources.load_probe("pisa_256", cache=True)
        np.testing.assert_array_equal(probe.data[..., :3], sources.load_probe("pisa_256").data[..., :3])
        assert np.all(probe.data[..., :3] == level)
        assert sources.load_probe("pisa_256", cache=True) is probe        # still kept for its folder
    path = folders[0] / "probes" / "pisa_256.exr"
    kept = sources.load_probe(str(path), cache=True)
    images.write_exr(path, np.full((8, 16, 3), 3.0, np.float32))          # rewritten in place
    stat = os.stat(path)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))      # a later time, on any file system
    assert np.all(kept.data[..., :3] == 1.0)
    assert np.all(sources.load_probe(str(path), cache=True).data[..., :3] == 3.0)



def test_the_probe_cache_tells_a_same_size_rewrite_and_a_shared_file_apart(tmp_path, monkeypatch):
    """Keys that only look alike: a PFM rewritten in place with other values has the same size (a fixed
    header and 4 bytes a value), so only its modification time tells the cached probe is stale; and one
    file named like a shared probe is that shared probe (turned by its rotation) with its data folder given
    and a plain file (as stored) without. The truth: what an uncached load gives each time."""
    import os

    monkeypatch.delenv("MI_BIVARIATE_DATA", raising=False)
    path = tmp_path / "sky.pfm"
    for level in (1.0, 3.0):
        path.write_bytes(b"PF\n8 4\n-1.0\n" + np.full((4, 8, 3), level, "<f4").tobytes())
        stat = os.stat(path)
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + int(level) * 10**9))   # later, on any file system
        assert np.all(sources.load_probe(str(path), cache=True).data == level)

    (tmp_path / "probes").mkdir()
    shared = tmp_path / "probes" / "grace_latlong_1k.pfm"
    shared.write_bytes(b"PF\n8 4\n-1.0\n" + np.arange(96, dtype="<f4").tobytes())
    for data_dir in (tmp_path, None, tmp_path):
        got = sources.load_probe(str(shared), data_dir=data_dir, cache=True)
        np.testing.assert_array_equal(got.to_world, sources.load_probe(str(shared), data_dir=data_dir).to_world)
    assert not np.array_equal(sources.load_probe(str(shared), data_dir=tmp_path, cache=True).to_world,
                              sources.load_probe(str(shared), cache=True).to_world)

def test_an_inputs_label_names_each_of_its_probes():
    """An evaluation input of several probes joined by ``+`` is labelled probe by probe (file stems)."""
    assert sources.input_label("/a/b/pisa_256.hdr+grace_latlong_1k+synthetic:3") == "pisa_256+grace_latlong_1k+synthetic:3"
    assert sources.input_label("/a/b/pisa_256.hdr") == "pisa_256"


def test_input_files_are_what_each_spec_reads(data_dir, tmp_path):
    """The files behind specs, for the check that no output overwrites an input: a file as given, a folder's
    ``.binary`` files, the shared file behind a shared probe name or a MERL-NBRDF name; nothing for specs that
    read no file (analytic, synthetic, None, empty)."""
    from mi_bivariate import probes

    (tmp_path / "m.binary").write_bytes(b"listed, not read")
    (tmp_path / "notes.txt").write_text("x")
    got = sources.input_files(str(tmp_path), str(tmp_path / "notes.txt"), "grace_latlong_1k", "blue-acrylic",
                              GGX, "synthetic:1", None, "", data_dir=data_dir)
    assert got == [tmp_path / "m.binary", tmp_path / "notes.txt", probes.shared_probe_path("grace_latlong_1k", data_dir),
                   nbrdf.weights_path("blue-acrylic", data_dir)]


def test_the_synthetic_sun_is_a_disc_of_0_06_rad_where_its_docstring_puts_it():
    """The synthetic probe's sun (adds 160 over the three channels; sky, glow and windows stay below 40): its
    solid angle is the cap's ``2 pi (1 - cos 0.06)`` and its centre the stated direction (polar angle 0.7 from
    +y, azimuth 1.0), measured on a 256 x 512 lat-long grid (0.7 degree texels)."""
    env = sources.synthetic_environment(256, 512, seed=0).astype(np.float64)
    h, w = env.shape[:2]
    theta = ((np.arange(h) + 0.5) / h * np.pi)[:, None]
    phi = ((np.arange(w) + 0.5) / w * 2.0 * np.pi)[None, :]
    sun = env.sum(axis=2) > 100.0
    texel = np.sin(theta) * (np.pi / h) * (2.0 * np.pi / w) * sun
    assert texel.sum() == pytest.approx(2.0 * np.pi * (1.0 - np.cos(0.06)), rel=0.08)
    dirs = np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)), -1)
    centre = (dirs * texel[..., None]).sum(axis=(0, 1))
    want = [np.sin(0.7) * np.cos(1.0), np.cos(0.7), np.sin(0.7) * np.sin(1.0)]
    assert np.degrees(np.arccos(np.dot(centre / np.linalg.norm(centre), want))) < 0.2


def test_material_slugs_of_different_labels_differ():
    """Artifacts are named by slug: a label with characters a file name cannot hold gets a hashed slug, so
    that it never takes the file of a label that is already safe ('a b' is not 'a_b'); a safe label is its
    own slug, a long one is cut and hashed."""
    def slug(label):
        return sources.MaterialSpec(label, "analytic", "x").slug

    assert slug("gold-paint") == "gold-paint" and slug("a_b") == "a_b"
    assert slug("a b") != slug("a_b") and slug("a b").startswith("a_b-")
    assert len(slug("x" * 70)) == 57 and slug("x" * 70) != slug("x" * 71)


def test_merl_files_are_named_by_their_suffix_in_any_case(tmp_path):
    """``X.BINARY`` is a MERL file to ``render`` and ``load_brdf`` (they lower-case the suffix); the evaluation's
    ``resolve_materials`` and a folder's listing (``merl.merl_files_in``, also ``learn-prior``'s) took only
    ``.binary`` and refused it, or called the folder empty."""
    table = analytic.to_merl(analytic.Lambertian([0.5] * 3))
    for name in ("a.BINARY", "b.Binary", "c.binary"):
        table.write(tmp_path / name)
    (tmp_path / "d.binary.txt").write_text("not a table")
    (tmp_path / "e.BINARY").mkdir()
    specs = sources.resolve_materials([str(tmp_path / "a.BINARY")])
    assert [(s.label, s.kind, s.spec) for s in specs] == [("a", "merl", str(tmp_path / "a.BINARY"))]
    assert [s.label for s in sources.resolve_materials([str(tmp_path)])] == ["a", "b", "c"]
