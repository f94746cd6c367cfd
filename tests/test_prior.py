"""The learned smoothness prior: operators, learning against closed forms, files."""

from __future__ import annotations

import time

import numpy as np
import pytest

from mi_bivariate.errors import InputError
from mi_bivariate.prior import DEFAULT_PRIOR_PATH, PAIRS, Prior, default_prior, difference_operators, plot_prior, specular_ratio
from mi_bivariate.training_set import learn_prior_from_merl


def test_difference_operators_on_ramps():
    n_t, n_s = 7, 5
    ds, dt = difference_operators(n_t, n_s)
    assert ds.shape == (n_t * (n_s - 1), n_t * n_s)
    assert dt.shape == ((n_t - 1) * n_s, n_t * n_s)
    t, s = np.meshgrid(np.linspace(0, 1, n_t), np.linspace(0, 1, n_s), indexing="ij")
    ramp_s = (2.5 * s + 0.3).ravel()  # column it * n_s + is
    np.testing.assert_allclose(ds @ ramp_s, 2.5, rtol=1e-12)
    np.testing.assert_allclose(dt @ ramp_s, 0.0, atol=1e-12)
    ramp_t = (-1.5 * t).ravel()
    np.testing.assert_allclose(dt @ ramp_t, -1.5, rtol=1e-12)
    np.testing.assert_allclose(ds @ ramp_t, 0.0, atol=1e-12)
    # Row order: Ds row it * (n_s - 1) + is is the difference (it, is) -> (it, is + 1).
    f = np.random.default_rng(0).random((n_t, n_s))
    np.testing.assert_allclose(ds @ f.ravel(), (np.diff(f, axis=1) * (n_s - 1)).ravel())
    np.testing.assert_allclose(dt @ f.ravel(), (np.diff(f, axis=0) * (n_t - 1)).ravel())
    with pytest.raises(InputError):
        difference_operators(1, 5)


def test_regulariser_is_the_weighted_sum_of_squared_derivatives():
    rng = np.random.default_rng(1)
    n_t, n_s = 5, 4
    sig = {p: (rng.uniform(0.5, 2, (n_t, n_s)), rng.uniform(0.5, 2, (n_t, n_s))) for p in PAIRS}
    prior = Prior(sig)
    f = rng.random((n_t, n_s))
    sigma_s, sigma_t = sig["gloss"]
    expected = (np.sum((np.diff(f, axis=1) * (n_s - 1) / sigma_s[:, :-1]) ** 2)
                + np.sum((np.diff(f, axis=0) * (n_t - 1) / sigma_t[:-1, :]) ** 2))
    assert np.sum((prior.regulariser("gloss") @ f.ravel()) ** 2) == pytest.approx(expected, rel=1e-12)
    assert f.ravel() @ prior.penalty_matrix("gloss") @ f.ravel() == pytest.approx(expected, rel=1e-12)


def _linear_tables(coeffs_s, coeffs_t, n: int = 9):
    """Tables ``1 + a (s - 1/2) + b (t - 1/2)`` per channel: median 1, dF/ds = a, dF/dt = b."""
    t, s = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    return np.stack([1 + a * (s - 0.5) + b * (t - 0.5) for a, b in zip(coeffs_s, coeffs_t)], axis=-1)


@pytest.mark.parametrize("centred", [False, True])
def test_learned_sigmas_match_closed_form(centred):
    rng = np.random.default_rng(2)
    # b < 0: brighter towards theta_h = 0 (specular ratio > 1, "gloss" at threshold 1); b >= 0: "diffuse".
    materials = {}
    for i in range(4):
        materials[f"d{i}"] = (rng.uniform(-0.8, 0.8, 3), rng.uniform(0.0, 0.8, 3))
        materials[f"g{i}"] = (rng.uniform(-0.8, 0.8, 3), rng.uniform(-0.8, -0.1, 3))
    tables = {name: _linear_tables(a, b) for name, (a, b) in materials.items()}
    prior = Prior.learn(tables, gloss_threshold=1.0, centred=centred)
    assert prior.provenance["split"] == {name: "gloss" if name[0] == "g" else "diffuse" for name in materials}
    for pair in PAIRS:
        a = np.concatenate([materials[n][0] for n in materials if prior.provenance["split"][n] == pair])
        b = np.concatenate([materials[n][1] for n in materials if prior.provenance["split"][n] == pair])
        spread = (lambda v: v.std()) if centred else (lambda v: np.sqrt(np.mean(v**2)))
        sig_a, sig_b = spread(a), spread(b)
        sigma_s, sigma_t = prior.pairs[pair]
        scale = np.sqrt(sig_a * sig_b)  # geometric mean: as many s- as t-differences
        assert prior.provenance["pair_scale"][pair] == pytest.approx(scale, rel=1e-10)
        np.testing.assert_allclose(sigma_s, sig_a / scale, rtol=1e-10)
        np.testing.assert_allclose(sigma_t, sig_b / scale, rtol=1e-10)


def test_specular_ratio_and_split_errors():
    lambertian = np.full((8, 8, 3), 0.2)
    assert specular_ratio(lambertian) == pytest.approx(1.0)
    peaked = lambertian.copy()
    peaked[0] *= 50
    assert specular_ratio(peaked) == pytest.approx(50.0)
    with pytest.raises(InputError, match="no gloss materials"):
        Prior.learn({"a": lambertian, "b": lambertian * 2})
    with pytest.raises(InputError, match="different grids"):
        Prior.learn({"a": lambertian, "b": np.ones((4, 4, 3))})
    with pytest.raises(InputError, match="empty"):
        Prior.learn({})


def test_a_sequence_naming_a_material_twice_is_refused():
    """Tables given as a sequence are named by their provenance; a later table of an earlier one's name
    is refused as the CLI refuses it (it once replaced the earlier table silently)."""
    from mi_bivariate.bivariate import BivariateBRDF

    peaked = np.full((8, 8, 3), 0.2)
    peaked[0] *= 50
    tables = [BivariateBRDF(np.full((8, 8, 3), 0.2), provenance={"name": "gold"}),
              BivariateBRDF(peaked, provenance={"name": "gold"}), BivariateBRDF(peaked, provenance={"name": "tin"})]
    with pytest.raises(InputError, match=r"^prior training set: material 'gold' given twice \(give each material once\)$"):
        Prior.learn(tables)
    tables[1] = BivariateBRDF(peaked, provenance={"name": "brass"})
    assert Prior.learn(tables).provenance["materials"] == ["brass", "gold", "tin"]


def test_learning_twice_writes_the_same_bytes(tmp_path):
    """A prior is a function of its training tables: learnt again, its file is byte for byte the same
    (no date in it), so a configuration keyed by the file's digest sees the same prior."""
    rng = np.random.default_rng(4)
    tables = {name: rng.uniform(0.1, 2.0, (6, 6, 3)) for name in ("a", "b", "c", "d")}
    for k in range(2):
        Prior.learn(tables, gloss_threshold=1.0).save(tmp_path / f"p{k}.npz")
        time.sleep(1.1 if k == 0 else 0.0)  # a date in seconds would differ
    assert (tmp_path / "p0.npz").read_bytes() == (tmp_path / "p1.npz").read_bytes()


def test_floor_bounds_the_weights():
    flat = np.ones((6, 6, 3))
    bumpy = flat.copy()
    bumpy[3, 3] = 2.0  # derivatives only around one node: elsewhere sigma would be 0
    peaked = bumpy.copy()
    peaked[0] = 100.0
    prior = Prior.learn({"flat": flat, "bumpy": bumpy, "peaked": peaked}, floor=1e-2)
    for sigma_s, sigma_t in prior.pairs.values():
        assert np.all(np.isfinite(sigma_s)) and np.all(sigma_s > 0)
        assert np.all(np.isfinite(sigma_t)) and np.all(sigma_t > 0)


def test_resampled_interpolates_log_sigma():
    n = 9
    t, s = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    # sigma_s varies along t (node axis of its map), sigma_t along s: linear in log -> exact.
    pairs = {p: (np.exp(1.0 + 2.0 * t), np.exp(-1.0 + 3.0 * s)) for p in PAIRS}
    prior = Prior(pairs, {"materials": ["x"]})
    finer = prior.resampled(17, 13)
    t2, s2 = np.meshgrid(np.linspace(0, 1, 17), np.linspace(0, 1, 13), indexing="ij")
    for sigma_s, sigma_t in finer.pairs.values():
        assert sigma_s.shape == (17, 13)
        np.testing.assert_allclose(sigma_s, np.exp(1.0 + 2.0 * t2), rtol=1e-12)
        np.testing.assert_allclose(sigma_t, np.exp(-1.0 + 3.0 * s2), rtol=1e-12)
    same = prior.resampled(n, n)
    np.testing.assert_array_equal(same.pairs["gloss"][0], pairs["gloss"][0])
    back = finer.resampled(n, n)
    np.testing.assert_allclose(back.pairs["diffuse"][1], pairs["diffuse"][1], rtol=1e-12)
    assert finer.provenance["grid"]["n_t"] == 17 and finer.provenance["resampled_from"]["n_t"] == n


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    prior = Prior({p: (rng.uniform(0.1, 9, (4, 6)), rng.uniform(0.1, 9, (4, 6))) for p in PAIRS},
                  {"materials": ["a", "b"], "split": {"a": "diffuse", "b": "gloss"}})
    path = tmp_path / "prior.npz"
    prior.save(path)
    loaded = Prior.load(path)
    for p in PAIRS:
        for x, y in zip(prior.pairs[p], loaded.pairs[p]):
            np.testing.assert_array_equal(x, y)
    assert loaded.provenance == prior.provenance
    with pytest.raises(InputError, match="not found"):
        Prior.load(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    with pytest.raises(InputError, match="garbage.npz"):
        Prior.load(garbage)
    other = tmp_path / "other.npz"
    np.savez(other, table=np.ones((2, 2)))
    with pytest.raises(InputError, match="other.npz"):
        Prior.load(other)


def test_default_prior_shape_and_provenance():
    from mi_bivariate.nbrdf import ALL_NBRDF_MATERIALS

    prior = default_prior()
    assert (prior.n_t, prior.n_s) == (32, 32)
    assert set(prior.pairs) == set(PAIRS)
    for sigma_s, sigma_t in prior.pairs.values():
        assert sigma_s.shape == sigma_t.shape == (32, 32)
        assert sigma_s.dtype == np.float64 and np.all(sigma_s > 0) and np.all(sigma_t > 0)
        # Each pair is normalised to a geometric mean of 1 over its differences.
        edges = np.concatenate([np.log(sigma_s[:, :-1]).ravel(), np.log(sigma_t[:-1, :]).ravel()])
        assert abs(edges.mean()) < 1e-9
    prov = prior.provenance
    assert sorted(prov["materials"]) == sorted(ALL_NBRDF_MATERIALS)
    assert set(prov["split"].values()) == set(PAIRS)
    assert prov["grid"]["n_t"] == 32 and prov["date"]
    # The gloss pair allows much more variation in t at the specular peak than the diffuse pair.
    assert prior.pairs["gloss"][1][0, :16].mean() > 10 * prior.pairs["diffuse"][1][0, :16].mean()
    # ... within the documented cap: no node is left (nearly) unregularised.
    assert prov["ceiling"].startswith("100")
    for sigma_s, sigma_t in prior.pairs.values():
        for sigma in (sigma_s[:, :-1], sigma_t[:-1, :]):  # the padding copies are not used
            assert sigma.max() <= 100.0 * np.median(sigma) * (1 + 1e-9)
    fig = plot_prior(prior)
    assert len(fig.axes) == 8  # 4 maps + 4 colour bars
    # Each sigma is drawn between the two nodes of its difference and on the nodes across it; the padded
    # copy (the last column of sigma_s, the last row of sigma_t) is not drawn.
    nodes, mids = np.linspace(0, 1, 32), (np.arange(31) + 0.5) / 31
    for ax, (along, sigma) in zip(fig.axes[:4], [(a, m) for pair in PAIRS for a, m in zip("st", prior.pairs[pair])]):
        image = ax.images[0]
        rows, cols = image.get_array().shape
        x0, x1, y0, y1 = image.get_extent()
        xs, ys = x0 + (np.arange(cols) + 0.5) * (x1 - x0) / cols, y0 + (np.arange(rows) + 0.5) * (y1 - y0) / rows
        np.testing.assert_allclose(xs, mids if along == "s" else nodes, atol=1e-12)
        np.testing.assert_allclose(ys, nodes if along == "s" else mids, atol=1e-12)
        np.testing.assert_allclose(image.get_array(), np.log10(sigma[:, :-1] if along == "s" else sigma[:-1]))


def test_learn_prior_from_merl_names(data_dir):
    prior = learn_prior_from_merl(["black-fabric", "brass"], n_t=8, n_s=8, data_dir=data_dir)
    assert prior.provenance["split"] == {"black-fabric": "diffuse", "brass": "gloss"}
    assert "MERL-NBRDF" in prior.provenance["sources"]["brass"]
    assert (prior.n_t, prior.n_s) == (8, 8)
    with pytest.raises(InputError, match="not a MERL"):
        learn_prior_from_merl(["no-such-material"], data_dir=data_dir)


@pytest.mark.parametrize("tiny", [1e-160, 1e-153])
def test_load_refuses_sigmas_whose_precision_leaves_float64(tmp_path, tiny):
    """Sigmas of 1e-160 overflow 1/sigma^2 to infinity, and 1e-153 (1/sigma^2 ~ 1e306, finite) still
    failed the solve's eigen-decomposition: both were LinAlgError tracebacks from ``recover --prior``.
    They are refused when the file is read, naming it; 1e-100 stays usable."""
    with np.load(DEFAULT_PRIOR_PATH) as z:
        arrays = {k: z[k] for k in z.files}
    path = tmp_path / "tiny.npz"
    arrays["gloss_sigma_s"][:] = tiny
    np.savez(path, **arrays)
    with pytest.raises(InputError, match=r"tiny\.npz: pair 'gloss' has a sigma .* so small that the prior's "
                                         r"precision"):
        Prior.load(path)
    arrays["gloss_sigma_s"][:] = 1e-100
    np.savez(path, **arrays)
    assert Prior.load(path).pairs["gloss"][0].min() == 1e-100


def test_a_damaged_or_unwritable_reduction_cache_costs_time_only(data_dir, tmp_path, monkeypatch):
    """The shared materials' reductions cache (``MI_BIVARIATE_CACHE``): a cache file cut short (a crash
    between write and rename) or emptied is reduced again and rewritten; a cache folder nothing can be
    written in (``/proc``, even for root) is skipped. Either way the tables are the same."""
    from mi_bivariate import training_set

    names = ["gold-metallic-paint3", "blue-acrylic", "black-fabric"]
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(tmp_path))
    first = training_set.reduced_tables(8, 8, names, data_dir)
    (cached,) = tmp_path.glob("nbrdf_reductions_*.npz")
    whole = cached.read_bytes()
    for damaged in (b"", whole[:1000]):
        cached.write_bytes(damaged)
        again = training_set.reduced_tables(8, 8, names, data_dir)
        assert all(np.array_equal(again[n], first[n]) for n in names)
        assert cached.read_bytes() == whole  # written again, whole
    monkeypatch.setenv("MI_BIVARIATE_CACHE", "/proc")
    unwritable = training_set.reduced_tables(8, 8, names, data_dir)
    assert all(np.array_equal(unwritable[n], first[n]) for n in names)


def test_specular_ratio_reads_the_row_nearest_45_degrees_and_the_first_half_of_theta_d():
    """By hand on an 11 x 9 grid: the off-specular row is round(sqrt(1/2) * 10) = 7 (theta_h = 45 deg at
    t = sqrt(1/2)), the columns s <= 1/2 (theta_d <= 45 deg) are 0..4; the rest does not count."""
    grey = np.ones((11, 9))
    grey[0, :5] = 12.0
    grey[7, :5] = 3.0
    grey[:, 5:] = 1000.0  # grazing theta_d: ignored
    grey[5] = 0.5  # the middle row in t, not theta_h = 45 deg
    assert specular_ratio(grey) == pytest.approx(4.0, rel=1e-12)


def test_sigma_maps_floor_and_ceiling_relative_to_each_maps_median():
    """The derivative RMS per edge, floored at ``floor`` x and capped at ``ceiling`` x its own map's median
    (s- and t-maps each their own), then divided by the geometric mean of all edge sigmas: by hand."""
    from mi_bivariate.prior import _sigma_maps

    rng = np.random.default_rng(11)
    samples = rng.standard_normal((6, 5, 7)) * np.exp(3.0 * rng.standard_normal((1, 5, 7)))  # sigmas over decades
    samples[:, :, 0] = 0.0  # a flat column: zero s-derivative at its edge
    d_s = np.diff(samples, axis=2) * 6
    d_t = np.diff(samples, axis=1) * 4
    edges = []
    for d in (d_s, d_t):
        sig = np.sqrt(np.mean(d**2, axis=0))
        sig = np.maximum(sig, 0.05 * np.median(sig))
        edges.append(np.minimum(sig, 3.0 * np.median(sig)))
    assert np.median(edges[0]) != pytest.approx(np.median(edges[1]), rel=0.1)  # the maps' own medians differ
    scale = np.exp(np.mean(np.log(np.concatenate([e.ravel() for e in edges]))))
    (sigma_s, sigma_t), got_scale = _sigma_maps(samples, 0.05, centred=False, ceiling=3.0)
    assert got_scale == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(sigma_s[:, :-1], edges[0] / scale, rtol=1e-12)
    np.testing.assert_allclose(sigma_t[:-1, :], edges[1] / scale, rtol=1e-12)
    # The padding (last column of sigma_s, last row of sigma_t) is a copy of its neighbour, as stored.
    np.testing.assert_array_equal(sigma_s[:, -1], sigma_s[:, -2])
    np.testing.assert_array_equal(sigma_t[-1], sigma_t[-2])


def test_samples_are_normalised_by_their_median_and_resampling_follows_s_too():
    """Each (material, channel) is divided by its median over the nodes (not its mean: a grazing corner
    would decide it); sigma_s varying along s (log-linear at the edge midpoints) is resampled exactly."""
    from mi_bivariate.prior import _normalised_samples

    table = np.ones((4, 5, 2))
    table[..., 0] = np.arange(20).reshape(4, 5) + 1.0  # 1 ... 20
    table[0, -1, 0] = 1000.0  # a grazing corner for the 5: median 11.5 (of 11 and 12), mean 60.25
    table[..., 1] *= 2.0
    got = _normalised_samples({"m": table})
    np.testing.assert_allclose(got[0], table[..., 0] / 11.5, rtol=1e-12)
    np.testing.assert_allclose(got[1], np.ones((4, 5)), rtol=1e-12)
    n = 9
    mids = (np.arange(n - 1) + 0.5) / (n - 1)
    edge_s = np.exp(0.5 + 2.0 * mids)[None, :] * np.ones((n, 1))
    sigma_s = np.concatenate([edge_s, edge_s[:, -1:]], axis=1)
    prior = Prior({p: (sigma_s, np.ones((n, n))) for p in PAIRS})
    coarse = prior.resampled(n, 5)
    np.testing.assert_allclose(coarse.pairs["gloss"][0][:, :-1],
                               np.exp(0.5 + 2.0 * (np.arange(4) + 0.5) / 4)[None, :] * np.ones((n, 1)), rtol=1e-12)


def test_resampling_follows_t_at_the_t_differences_midpoints():
    """sigma_t belongs to the difference it -> it + 1, at t = (it + 1/2) / (n_t - 1): log-linear there along t,
    it is resampled exactly onto another n_t's midpoints (finer and coarser; clamped beyond the outer old
    midpoints); sigma_s, on the t nodes, exactly onto the new nodes."""
    n = 9
    mids, nodes = (np.arange(n - 1) + 0.5) / (n - 1), np.linspace(0, 1, n)
    edge_t = np.exp(-0.5 + 3.0 * mids)[:, None] * np.ones((1, 6))
    sigma_t = np.concatenate([edge_t, edge_t[-1:]], axis=0)
    sigma_s = np.exp(0.3 - 2.0 * nodes)[:, None] * np.ones((1, 6))
    prior = Prior({p: (sigma_s, sigma_t) for p in PAIRS})
    for n_t in (5, 17):
        new_mids, new_nodes = (np.arange(n_t - 1) + 0.5) / (n_t - 1), np.linspace(0, 1, n_t)
        got_s, got_t = prior.resampled(n_t, 4).pairs["diffuse"]
        np.testing.assert_allclose(got_t[:-1], np.exp(-0.5 + 3.0 * np.clip(new_mids, mids[0], mids[-1]))[:, None] * np.ones((1, 4)), rtol=1e-12)
        np.testing.assert_allclose(got_s[:, :-1], np.exp(0.3 - 2.0 * new_nodes)[:, None] * np.ones((1, 3)), rtol=1e-12)


def test_specular_ratio_counts_theta_d_of_45_degrees_on_an_odd_grid():
    """On 9 columns s = 4/8 is theta_d = 45 deg exactly: it is in both means (theta_d <= 45 deg)."""
    grey = np.ones((11, 9))
    grey[0, :4], grey[0, 4] = 10.0, 60.0  # peak row mean over columns 0..4: 20
    grey[7, :5] = 2.0
    assert specular_ratio(grey) == pytest.approx(10.0, rel=1e-12)


def test_a_channel_with_median_zero_is_normalised_by_its_mean_and_a_black_one_is_left_out():
    from mi_bivariate.prior import _normalised_samples

    table = np.zeros((4, 5, 3))
    table[0, :3, 0] = [4.0, 2.0, 2.0]  # median 0, mean 8 / 20
    table[..., 1] = 3.0
    got = _normalised_samples({"m": table})  # channel 2 is black: no shape, not a sample
    assert got.shape == (2, 4, 5)
    np.testing.assert_allclose(got[0], table[..., 0] / 0.4, rtol=1e-12)
    np.testing.assert_allclose(got[1], np.ones((4, 5)), rtol=1e-12)


def _small_prior() -> Prior:
    rng = np.random.default_rng(12)
    return Prior({p: (rng.uniform(0.5, 2, (4, 3)), rng.uniform(0.5, 2, (4, 3))) for p in PAIRS}, {"materials": ["a"]})


def test_penalty_by_hand_on_a_4_by_3_grid_and_its_null_space_is_the_constants():
    """``f^T R^T R f`` on a 4 x 3 grid written out difference by difference (``(f[it, is+1] - f[it, is]) 2 /
    sigma_s[it, is]``, ``(f[it+1, is] - f[it, is]) 3 / sigma_t[it, is]``, squared and summed), and the
    precision's null space: constant tables only (rank N - 1), whatever the weights."""
    prior = _small_prior()
    sigma_s, sigma_t = prior.pairs["diffuse"]
    f = np.random.default_rng(13).random((4, 3))
    want = 0.0
    for it in range(4):
        for i_s in range(3):
            if i_s + 1 < 3:
                want += ((f[it, i_s + 1] - f[it, i_s]) * 2.0 / sigma_s[it, i_s]) ** 2
            if it + 1 < 4:
                want += ((f[it + 1, i_s] - f[it, i_s]) * 3.0 / sigma_t[it, i_s]) ** 2
    precision = prior.penalty_matrix("diffuse")
    assert f.ravel() @ precision @ f.ravel() == pytest.approx(want, rel=1e-12)
    np.testing.assert_allclose(precision @ np.ones(12), 0.0, atol=1e-12)
    assert np.linalg.matrix_rank(precision) == 11


_BAD_PRIOR_FILES = {
    "maps of another grid": r"pair 'gloss' has sigma maps of shape \(4, 2\), expected \(4, 3\)",
    "one theta_d node": r"needs at least 2 x 2 integer nodes, got 4 x 1",
    "a zero sigma": r"pair 'diffuse' has non-positive or non-finite sigmas",
    "a NaN sigma": r"pair 'diffuse' has non-positive or non-finite sigmas",
    "another format": r"not a mi_bivariate prior file \(format 'mi_bivariate.basis_prior'\)",
}


@pytest.mark.parametrize("case", list(_BAD_PRIOR_FILES))
def test_a_prior_file_of_the_wrong_grid_or_values_or_format_is_refused_naming_it(tmp_path, case):
    """A prior file whose maps disagree in shape (one pair on another grid), with one theta_d node (no
    s-difference at all), with a zero or NaN sigma, or whose metadata names another format: an InputError
    naming the file, before any solve (they were loaded, or failed later with the wrong message)."""
    import json

    path = tmp_path / "prior.npz"
    _small_prior().save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    if case == "maps of another grid":
        arrays["gloss_sigma_s"] = arrays["gloss_sigma_s"][:, :2]
    elif case == "one theta_d node":
        arrays = {k: (v[:, :1] if k != "meta" else v) for k, v in arrays.items()}
    elif case in ("a zero sigma", "a NaN sigma"):
        arrays["diffuse_sigma_t"][1, 1] = 0.0 if case == "a zero sigma" else np.nan
    else:
        meta = json.loads(str(arrays["meta"]))
        arrays["meta"] = np.array(json.dumps({**meta, "format": "mi_bivariate.basis_prior"}))
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(InputError, match=_BAD_PRIOR_FILES[case]) as info:
        Prior.load(bad)
    assert info.value.source == str(bad)
    with pytest.raises(InputError, match="needs at least 2 x 2"):
        difference_operators(4, 1)


def test_a_training_table_with_nan_is_refused_naming_the_material():
    """NaN in one training table: an InputError naming that material from both priors' learning (it became
    a NaN sigma, refused as "pair 'diffuse' has non-finite sigmas", or a NaN basis)."""
    from mi_bivariate.basis_prior import BasisPrior
    from mi_bivariate.training_set import learn_priors

    tables = {name: np.full((4, 4, 3), 0.2) for name in ("a", "b", "c")}
    tables["b"][0] *= 50  # glossy
    tables["c"][2, 1, 0] = np.nan
    for learn in (Prior.learn, BasisPrior.learn, learn_priors):
        with pytest.raises(InputError, match=r"^c: bivariate table has non-finite values$"):
            learn(tables)


def test_a_material_at_the_gloss_threshold_is_diffuse():
    """Gloss is a specular ratio *above* the threshold: a ratio of exactly 30 trains the diffuse pair."""
    at = np.ones((8, 8, 3))
    at[0] = 30.0                                  # specular ratio 30 / 1
    above = np.ones((8, 8, 3))
    above[0] = 31.0
    prior = Prior.learn({"at": at, "above": above, "flat": np.ones((8, 8, 3))})
    assert prior.provenance["specular_ratio"]["at"] == 30.0
    assert prior.provenance["split"] == {"at": "diffuse", "above": "gloss", "flat": "diffuse"}


def test_specular_ratio_is_that_of_the_channel_mean():
    """The ratio is read on the grey (channel-mean) table, not on one channel: red 10x brighter at the peak,
    green and blue flat, gives (10 + 1 + 1) / 3 = 4 (the red channel alone would give 10, blue 1)."""
    table = np.ones((11, 9, 3))
    table[0, :, 0] = 10.0
    assert specular_ratio(table) == pytest.approx(4.0, rel=1e-12)
    assert specular_ratio(table[..., ::-1]) == pytest.approx(4.0, rel=1e-12)
