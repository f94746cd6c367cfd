"""The data-driven table prior: learning, prediction at unobserved nodes, files, leave-one-out."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate import nbrdf, training_set
from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.errors import InputError

N_T, N_S = 8, 7


def _family(n: int, seed: int, n_t: int = N_T, n_s: int = N_S) -> dict:
    """Tables from a known 2-parameter family: a lobe of varying width on a Fresnel-like rise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n_t)[:, None]
    s = np.linspace(0, 1, n_s)[None, :]
    tables = {}
    for i in range(n):
        width, rise = rng.uniform(0.1, 0.4), rng.uniform(0.5, 3.0)
        f = 0.2 + 5.0 * np.exp(-(t / width) ** 2) + 0.3 * np.exp(rise * s**4)
        colour = rng.uniform(0.3, 1.0, 3)
        tables[f"m{i}"] = f[..., None] * colour
    return tables


def test_prediction_fills_unobserved_nodes_from_the_family():
    tables = _family(40, 0)
    truth = _family(1, 99)["m0"]
    prior = BasisPrior.learn(tables, components=8)
    assert prior.basis.shape == (N_T * N_S, 8)
    np.testing.assert_allclose(prior.basis.T @ prior.basis, np.eye(8), atol=1e-10)
    # Observe all but the grazing columns (s > 0.7), with a flat (wrong) first guess there.
    observed = np.broadcast_to((np.linspace(0, 1, N_S) <= 0.7)[None, :, None], truth.shape)
    first = np.where(observed, truth, truth[:, :1])
    resolution = observed.astype(float)
    mean, std = prior.predict(first, resolution, 0.01 * first)
    hidden = ~observed
    err_first = np.abs(first - truth)[hidden].mean() / truth[hidden].mean()
    err_prior = np.abs(mean - truth)[hidden].mean() / truth[hidden].mean()
    assert err_prior < 0.3 * err_first
    # Observed nodes are reproduced closely; the std is larger where nothing was seen.
    assert np.abs(mean - truth)[observed].mean() / truth[observed].mean() < 0.05
    assert np.median(std[hidden] / mean[hidden]) > np.median(std[observed] / mean[observed])


def test_leave_one_out_and_files(tmp_path):
    tables = _family(10, 1)
    prior = BasisPrior.learn(tables, exclude=["m3"])
    assert "m3" not in prior.materials and len(prior.materials) == 9
    path = tmp_path / "basis.npz"
    prior.save(path)
    back = BasisPrior.load(path)
    np.testing.assert_array_equal(back.basis, prior.basis)
    assert back.materials == prior.materials
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="bad.npz"):
        BasisPrior.load(tmp_path / "bad.npz")
    with pytest.raises(InputError, match="grid"):
        prior.predict(np.ones((4, 4, 3)), np.ones((4, 4, 3)), np.ones((4, 4, 3)))
    with pytest.raises(InputError):
        BasisPrior.learn({"a": np.ones((N_T, N_S, 1))})


def test_resampled_to_a_finer_grid_interpolates_and_still_predicts():
    """On a grid whose every other node is an old node (2 (n - 1) + 1 per axis) the resampled prior has the
    old mean, residual and per-node covariance there and their averages between; and it fills the hidden
    nodes of a table of the same family tabulated on that grid (the property of the first test)."""
    prior = BasisPrior.learn(_family(40, 0), components=8)
    fine_t, fine_s = 2 * (N_T - 1) + 1, 2 * (N_S - 1) + 1
    fine = prior.resampled(fine_t, fine_s)
    assert (fine.n_t, fine.n_s) == (fine_t, fine_s) and fine.provenance["resampled_from"] == [N_T, N_S]
    mean, old_mean = fine.mean.reshape(fine_t, fine_s), prior.mean.reshape(N_T, N_S)
    np.testing.assert_allclose(mean[::2, ::2], old_mean, atol=1e-12)
    np.testing.assert_allclose(mean[1::2, ::2], 0.5 * (old_mean[:-1] + old_mean[1:]), atol=1e-12)
    np.testing.assert_allclose(fine.residual.reshape(fine_t, fine_s)[::2, ::2], prior.residual.reshape(N_T, N_S))
    variance = np.einsum("nk,k,nk->n", fine.basis, fine.variances, fine.basis).reshape(fine_t, fine_s)
    old_variance = np.einsum("nk,k,nk->n", prior.basis, prior.variances, prior.basis).reshape(N_T, N_S)
    np.testing.assert_allclose(variance[::2, ::2], old_variance, rtol=1e-10)

    truth = _family(1, 99, fine_t, fine_s)["m0"]
    observed = np.broadcast_to((np.linspace(0, 1, fine_s) <= 0.7)[None, :, None], truth.shape)
    first = np.where(observed, truth, truth[:, :1])
    predicted, _ = fine.predict(first, observed.astype(float), 0.01 * first)
    hidden = ~observed
    err_first = np.abs(first - truth)[hidden].mean() / truth[hidden].mean()
    err_prior = np.abs(predicted - truth)[hidden].mean() / truth[hidden].mean()
    assert err_prior < 0.3 * err_first

    assert prior.resampled(N_T, N_S) is prior
    with pytest.raises(InputError, match="grid"):
        prior.resampled(1, 8)


def test_leave_one_out_priors_are_cached_per_training_set_and_learnt_again_when_damaged(tmp_path, monkeypatch):
    """``training_set.leave_one_out_priors`` keeps each pair on disk, keyed by the training tables it was
    learnt from (the basis prior takes seconds to learn): a second call reads it back unchanged, another
    material, grid or set of tables learns its own, and a damaged entry is learnt again."""
    names = list(nbrdf.ALL_NBRDF_MATERIALS[:8])

    def tables_on(n: int, seed: int) -> dict:
        rng, t = np.random.default_rng(seed), np.linspace(0, 1, n)[:, None, None]
        return {name: (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k % 2 else 0.0))
                * np.exp(rng.normal(0.0, 0.1, (n, n, 3))) for k, name in enumerate(names)}  # diffuse and glossy

    original = tables_on(8, 0)
    by_grid = {8: original, 6: tables_on(6, 1)}
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(tmp_path))
    monkeypatch.setattr(training_set, "reduced_tables", lambda n_t, n_s, data_dir=None: by_grid[n_t])
    learnt = []
    real_learn = training_set.learn_priors
    monkeypatch.setattr(training_set, "learn_priors",
                        lambda *a, **k: learnt.append(k["exclude"]) or real_learn(*a, **k))

    first = training_set.leave_one_out_priors(names[0], 8, 8)
    entry = set(tmp_path.iterdir())
    again = training_set.leave_one_out_priors(names[0], 8, 8)
    assert learnt == [(names[0],)] and len(entry) == 2
    assert again[1].materials == first[1].materials and names[0] not in again[1].materials
    for a, b in zip(first[0].pairs.values(), again[0].pairs.values()):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first[1].basis, again[1].basis)
    training_set.leave_one_out_priors(names[1], 8, 8)             # another material
    training_set.leave_one_out_priors(names[0], 6, 6)             # another grid
    by_grid[8] = tables_on(8, 2)                                  # other tables: new data or a changed reduction
    training_set.leave_one_out_priors(names[0], 8, 8)
    assert learnt == [(names[0],)] * 1 + [(names[1],), (names[0],), (names[0],)]
    by_grid[8] = original
    for path in entry:
        path.write_bytes(b"damaged")
    repaired = training_set.leave_one_out_priors(names[0], 8, 8)
    assert len(learnt) == 5 and learnt[-1] == (names[0],)
    np.testing.assert_array_equal(repaired[1].basis, first[1].basis)
    outside = training_set.leave_one_out_priors("a-material-of-mine", 8, 8)  # all of them, nothing excluded
    assert learnt[-1] == () and sorted(outside[1].materials) == sorted(names)


def test_leave_one_out_priors_cache_tells_grids_with_the_same_bytes_apart(tmp_path, monkeypatch):
    """Two training sets holding the same numbers on different grids (4 x 16 and 8 x 8 here) are different
    training sets: each learns its own priors, and each call gets priors on its own grid (the cache key
    once hashed names and values only, so the second grid was handed the first grid's priors)."""
    names = list(nbrdf.ALL_NBRDF_MATERIALS[:6])
    rng = np.random.default_rng(3)
    peak = np.where(np.arange(4 * 16 * 3) < 16 * 3, 1000.0, 0.0)  # row t = 0 of 4 x 16, rows 0-1 of 8 x 8
    flat = {name: (0.1 + (peak if k % 2 else 0.0)) * np.exp(rng.normal(0.0, 0.1, 4 * 16 * 3))
            for k, name in enumerate(names)}  # diffuse and glossy on both grids
    by_grid = {4: {n: v.reshape(4, 16, 3) for n, v in flat.items()},
               8: {n: v.reshape(8, 8, 3) for n, v in flat.items()}}
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(tmp_path))
    monkeypatch.setattr(training_set, "reduced_tables", lambda n_t, n_s, data_dir=None: by_grid[n_t])
    wide = training_set.leave_one_out_priors(names[0], 4, 16)
    square = training_set.leave_one_out_priors(names[0], 8, 8)
    assert (wide[1].n_t, wide[1].n_s) == (4, 16)
    assert (square[1].n_t, square[1].n_s) == (8, 8)
    assert training_set._tables_digest(by_grid[4]) != training_set._tables_digest(by_grid[8])


def test_predict_without_data_is_the_prior_itself():
    """With no node resolved the prediction is the prior, in closed form: per channel, the mean
    ``level max(exp(mu) - EPS, 0)`` and the std ``level exp(mu) sqrt(diag(U diag(lambda) U^T) + tau^2)``,
    ``level`` the table's median."""
    from mi_bivariate.basis_prior import EPS

    rng = np.random.default_rng(2)
    n_t, n_s, k = 4, 5, 3
    basis, _ = np.linalg.qr(rng.normal(size=(n_t * n_s, k)))
    mu = rng.normal(0.0, 0.5, n_t * n_s)
    lam = np.array([0.5, 0.2, 0.05])
    tau = rng.uniform(0.05, 0.2, n_t * n_s)
    prior = BasisPrior(mu, basis, lam, tau, n_t, n_s)
    table = rng.uniform(0.1, 3.0, (n_t, n_s, 3))
    mean, std = prior.predict(table, np.zeros_like(table), np.ones_like(table))
    spread = np.sqrt(np.einsum("nk,k,nk->n", basis, lam, basis) + tau**2)
    for c in range(3):
        level = np.median(table[..., c])
        np.testing.assert_allclose(mean[..., c].ravel(), level * np.maximum(np.exp(mu) - EPS, 0.0), rtol=1e-9)
        np.testing.assert_allclose(std[..., c].ravel(), level * np.exp(mu) * spread, rtol=1e-9)


def test_predict_with_data_is_the_gaussian_posterior_in_data_space():
    """With every node resolved, the prediction against the posterior written in data space (Woodbury's
    other side): ``c_hat = Lambda U^T S^-1 (g - mu)``, ``Cov c = Lambda - Lambda U^T S^-1 U Lambda``,
    ``S = U Lambda U^T + D``, ``D`` the observations' variances ``(rel_std^2 + 0.05^2 + tau^2) / resolution``
    with ``rel_std = posterior_std / (f + EPS level)``; the learnt variances are the sample covariance's
    eigenvalues (``ddof = 1``)."""
    from mi_bivariate.basis_prior import EPS, OBSERVATION_FLOOR

    tables = _family(12, 3)
    prior = BasisPrior.learn(tables, components=4)
    samples = np.array([np.log(np.maximum(t[..., c].ravel() / np.median(t[..., c]), 0.0) + EPS)
                        for t in tables.values() for c in range(3)])
    eig = np.sort(np.linalg.eigvalsh(np.cov(samples.T)))[::-1][:4]
    np.testing.assert_allclose(prior.variances, eig, rtol=1e-8)
    rng = np.random.default_rng(4)
    table = _family(1, 50)["m0"] * rng.uniform(0.8, 1.2, (N_T, N_S, 3))
    resolution = rng.uniform(0.2, 1.0, table.shape)
    post = rng.uniform(0.01, 0.3, table.shape) * table
    mean, std = prior.predict(table, resolution, post)
    u, lam, tau = prior.basis, prior.variances, prior.residual
    for c in range(3):
        f = table[..., c].ravel()
        level = np.median(f)
        g = np.log(f / level + EPS)
        rel = post[..., c].ravel() / (f + EPS * level)
        d = (rel**2 + OBSERVATION_FLOOR**2 + tau**2) / resolution[..., c].ravel()
        s = (u * lam) @ u.T + np.diag(d)
        c_hat = lam * (u.T @ np.linalg.solve(s, g - prior.mean))
        cov = np.diag(lam) - (lam[:, None] * u.T) @ np.linalg.solve(s, u * lam)
        g_hat = prior.mean + u @ c_hat
        var = np.einsum("nk,kl,nl->n", u, cov, u) + tau**2
        np.testing.assert_allclose(mean[..., c].ravel(), level * np.maximum(np.exp(g_hat) - EPS, 0.0), rtol=1e-9)
        np.testing.assert_allclose(std[..., c].ravel(), level * np.exp(g_hat) * np.sqrt(var), rtol=1e-9)


def test_learn_takes_one_channel_tables_as_the_smoothness_prior_does():
    """A ``(n_t, n_s)`` table is one channel (as ``Prior.learn`` reads it): the prior equals the one learnt
    from the same tables with a channel axis. It was read as ``n_s`` channels of ``n_t`` nodes, a mean of
    ``n_t`` values that ``predict`` then failed on with a numpy ValueError; a table of another rank is an
    InputError naming it."""
    grey = {name: t[..., 0] for name, t in _family(6, 5).items()}
    flat = BasisPrior.learn(grey, components=3)
    want = BasisPrior.learn({name: t[..., None] for name, t in grey.items()}, components=3)
    assert (flat.n_t, flat.n_s) == (N_T, N_S) and flat.mean.shape == (N_T * N_S,)
    for got, ref in ((flat.mean, want.mean), (flat.basis, want.basis), (flat.variances, want.variances),
                     (flat.residual, want.residual)):
        np.testing.assert_array_equal(got, ref)
    with pytest.raises(InputError, match="m2: expected a bivariate table"):
        BasisPrior.learn({**grey, "m2": np.ones(N_T * N_S)})


def test_one_material_to_exclude_may_be_given_as_a_string():
    """``exclude="m3"`` leaves m3 out of both priors, as ``exclude=["m3"]`` does: it was read as the
    characters {"m", "3"}, so the material silently stayed in the leave-one-out priors."""
    tables = _family(6, 7)
    tables["m1"] = tables["m1"] * np.exp(-((np.linspace(0, 1, N_T)[:, None, None] / 0.05) ** 2)) * 1e3 + 0.01
    basis = BasisPrior.learn(tables, components=3, exclude="m3")
    assert "m3" not in basis.materials
    np.testing.assert_array_equal(basis.mean, BasisPrior.learn(tables, components=3, exclude=["m3"]).mean)
    smooth, basis = training_set.learn_priors(tables, exclude="m3")
    assert "m3" not in smooth.provenance["materials"] and "m3" not in basis.materials
    assert basis.provenance["excluded"] == ["m3"]


def _log_shapes(table: np.ndarray) -> np.ndarray:
    """``(C, N)``: each channel over its median, ``log(x + EPS)`` (the model's map), written out here."""
    from mi_bivariate.basis_prior import EPS

    return np.array([np.log(table[..., c].ravel() / np.median(table[..., c]) + EPS) for c in range(table.shape[-1])])


def test_residual_is_the_leave_one_material_out_error_of_a_pca_by_eigendecomposition():
    """``residual`` per node, against a second implementation: for each material, the top eigenvectors of
    the other materials' sample covariance (``np.cov``, ``eigh``), the material's centred log shapes minus
    their projection, the RMS over all materials' channels; floored at 1e-3. The training set's tables all
    equal their median at node 0 (a node every shape shares: residual 0 there, so the floor)."""
    rng = np.random.default_rng(8)
    n_t, n_s, k = 5, 5, 3
    tables = {}
    for i in range(5):
        f = np.exp(rng.normal(0.0, 1.0, (n_t * n_s, 3)))
        f[0] = np.median(f[1:], axis=0)  # 25 nodes: node 0 is the 13th value, the median
        tables[f"m{i}"] = f.reshape(n_t, n_s, 3)
    prior = BasisPrior.learn(tables, components=k)
    shapes = {name: _log_shapes(t) for name, t in tables.items()}
    errors = []
    for name in tables:
        others = np.concatenate([s for n, s in shapes.items() if n != name])
        _, vec = np.linalg.eigh(np.cov(others.T))
        top = vec[:, ::-1][:, :k]
        centred = shapes[name] - others.mean(axis=0)
        errors.append(centred - centred @ top @ top.T)
    want = np.sqrt(np.mean(np.concatenate(errors) ** 2, axis=0))
    assert want[0] < 1e-12 and want[1:].min() > 1e-2
    np.testing.assert_allclose(prior.residual, np.maximum(want, 1e-3), rtol=1e-8)


def test_components_are_at_most_the_rank_of_the_centred_samples():
    """Two materials of three channels: six centred log shapes span five directions, so five components
    (the sample covariance's nonzero eigenvalues), however many were asked for."""
    rng = np.random.default_rng(9)
    tables = {name: np.exp(rng.normal(0.0, 1.0, (N_T, N_S, 3))) for name in ("a", "b")}  # six distinct shapes
    prior = BasisPrior.learn(tables, components=12)
    samples = np.concatenate([_log_shapes(t) for t in tables.values()])
    eig = np.sort(np.linalg.eigvalsh(np.cov(samples.T)))[::-1]
    assert prior.basis.shape == (N_T * N_S, 5)
    np.testing.assert_allclose(prior.variances, eig[:5], rtol=1e-8)


def test_save_load_keeps_every_field_on_a_non_square_grid(tmp_path):
    prior = BasisPrior.learn(_family(5, 10), components=4, provenance={"note": "x"})
    prior.save(tmp_path / "b.npz")
    back = BasisPrior.load(tmp_path / "b.npz")
    assert (back.n_t, back.n_s) == (N_T, N_S) and back.provenance == prior.provenance
    for name in ("mean", "basis", "variances", "residual"):
        np.testing.assert_array_equal(getattr(back, name), getattr(prior, name))


@pytest.mark.parametrize("module", ["prior", "basis_prior", "training_set"])
def test_leave_one_out_priors_are_learnt_again_when_the_code_that_learns_them_changes(tmp_path, monkeypatch, module):
    """The cache key holds the source of both priors' modules and of ``learn_priors``: an edited copy of any
    of them (its ``__file__`` pointing at other bytes) is a new entry, learnt again."""
    import importlib
    import pathlib

    names = list(nbrdf.ALL_NBRDF_MATERIALS[:6])
    rng, t = np.random.default_rng(3), np.linspace(0, 1, 6)[:, None, None]
    tables = {name: (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k % 2 else 0.0))
              * np.exp(rng.normal(0.0, 0.1, (6, 6, 3))) for k, name in enumerate(names)}
    cache = tmp_path / "cache"
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(cache))
    monkeypatch.setattr(training_set, "reduced_tables", lambda n_t, n_s, data_dir=None: tables)
    training_set.leave_one_out_priors(names[0], 6, 6)
    training_set.leave_one_out_priors(names[0], 6, 6)
    assert len(list(cache.glob("loo_priors_*.npz"))) == 2  # one entry: the smoothness and the basis prior
    mod = importlib.import_module(f"mi_bivariate.{module}")
    edited = tmp_path / f"{module}.py"
    edited.write_bytes(pathlib.Path(mod.__file__).read_bytes() + b"\n# edited\n")
    monkeypatch.setattr(mod, "__file__", str(edited))
    training_set.leave_one_out_priors(names[0], 6, 6)
    assert len(list(cache.glob("loo_priors_*.npz"))) == 4


def _fake_reductions(tmp_path, monkeypatch):
    """A data folder whose two shared files hold their own names, an empty cache, and a fake reduction
    (a table of ones) that records each material it reduces: ``(root, reduced)``."""
    root = tmp_path / "data"
    (root / "merl_nbrdf").mkdir(parents=True)
    for rel in (nbrdf.NBRDF_FILE, nbrdf.NBRDF_TRAIN_FILE):
        (root / rel).write_bytes(str(rel).encode())
    monkeypatch.setenv("MI_BIVARIATE_CACHE", str(tmp_path / "cache"))
    reduced = []

    class Reduced:
        def __init__(self, n_t, n_s):
            self.table = np.ones((n_t, n_s, 3))

    monkeypatch.setattr(training_set, "nbrdf_merl", lambda name, data_root: name)
    monkeypatch.setattr(training_set.BivariateBRDF, "reduce",
                        lambda merl, n_t, n_s: reduced.append(merl) or Reduced(n_t, n_s))
    return root, reduced


@pytest.mark.parametrize("change", ["grid", "dev file", "train file", "bivariate", "merl", "coordinates"])
def test_reductions_are_made_again_when_the_data_the_grid_or_the_reduction_code_changes(tmp_path, monkeypatch, change):
    """The reductions cache (``reduced_tables``) is keyed by both shared files' bytes, the grid and the
    reduction's code: any one of them changed, the materials are reduced again (a fake reduction counts)."""
    import importlib
    import pathlib

    root, reduced = _fake_reductions(tmp_path, monkeypatch)
    names = ["brass", "black-fabric"]
    training_set.reduced_tables(4, 5, names, root)
    training_set.reduced_tables(4, 5, names, root)
    assert reduced == names
    grid = (4, 5)
    if change == "grid":
        grid = (5, 4)
    elif change.endswith("file"):
        rel = nbrdf.NBRDF_FILE if change == "dev file" else nbrdf.NBRDF_TRAIN_FILE
        (root / rel).write_bytes(b"new data")
    else:
        mod = importlib.import_module(f"mi_bivariate.{change}")
        edited = tmp_path / f"{change}.py"
        edited.write_bytes(pathlib.Path(mod.__file__).read_bytes() + b"\n# edited\n")
        monkeypatch.setattr(mod, "__file__", str(edited))
    training_set.reduced_tables(*grid, names, root)
    assert reduced == names * 2


def test_a_cached_reduction_that_is_not_finite_or_of_another_shape_is_made_again(tmp_path, monkeypatch):
    """A reductions cache entry holding NaN, or a table of another shape, is not used: that material is
    reduced again (a fake reduction counts) and the tables returned are the fresh ones, those asked for."""
    root, reduced = _fake_reductions(tmp_path, monkeypatch)
    names = ["brass", "black-fabric", "gold-paint"]
    training_set.reduced_tables(4, 5, names, root)
    (path,) = (tmp_path / "cache").glob("nbrdf_reductions_*.npz")
    stored = dict(np.load(path))
    stored["brass"] = np.full((4, 5, 3), np.nan)
    stored["black-fabric"] = np.ones((5, 4, 3))
    np.savez(path, **stored)
    tables = training_set.reduced_tables(4, 5, names, root)
    assert reduced == names + ["brass", "black-fabric"]
    for name in names:
        np.testing.assert_array_equal(tables[name], np.ones((4, 5, 3)))
    assert list(training_set.reduced_tables(4, 5, names[1:], root)) == names[1:]   # the names asked, no more


def test_priors_are_learnt_from_three_materials_at_least():
    """Fewer than 3 training tables (after the exclusions) is refused naming the training set."""
    tables = _family(3, seed=2)
    with pytest.raises(InputError, match=r"^prior training set: has 2 materials \(give at least 3\)$"):
        training_set.learn_priors(tables, exclude="m0")
    with pytest.raises(InputError, match="has 2 materials"):
        training_set.learn_priors({k: tables[k] for k in ("m0", "m1")})


def test_two_merl_files_of_one_material_name_or_none_are_refused(tmp_path, monkeypatch):
    """``tables_from_sources`` (learn-prior's inputs): two files that hold the same material name (two
    ``m.binary`` in two folders) are refused, not one silently replaced by the other; so is no source."""
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "m.binary").write_bytes(b"read by the stand-in")

    class Read:
        name = None

    monkeypatch.setattr(training_set.MERLBRDF, "read", staticmethod(lambda path: Read()))
    monkeypatch.setattr(training_set.BivariateBRDF, "reduce",
                        lambda merl, n_t, n_s: type("Reduced", (), {"table": np.ones((n_t, n_s, 3))})())
    tables, origin = training_set.tables_from_sources([tmp_path / "a"], 4, 4)
    assert list(tables) == ["m"] and origin["m"] == "MERL file m.binary"
    with pytest.raises(InputError, match="material 'm' given twice"):
        training_set.tables_from_sources([tmp_path / "a", tmp_path / "b"], 4, 4)
    with pytest.raises(InputError, match=r"^prior training set: is empty$"):
        training_set.tables_from_sources([], 4, 4)
    Read.name = "gold"                                     # a file that names its material is read as that
    assert list(training_set.tables_from_sources([tmp_path / "a" / "m.binary"], 4, 4)[0]) == ["gold"]


def test_the_basis_prior_file_sits_beside_the_smoothness_prior_and_is_read_when_asked(tmp_path):
    """``learn-prior --out P.npz`` writes the basis prior to ``P_basis.npz``; ``load_prior_files`` reads it
    back unless told not to (``--no-basis-prior``), and gives ``None`` where there is none. A path without a
    file name is refused."""
    rng, t = np.random.default_rng(0), np.linspace(0, 1, 8)[:, None, None]
    tables = {f"m{k}": (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k % 2 else 0.0))   # diffuse and glossy
              * np.exp(rng.normal(0.0, 0.1, (8, 8, 3))) for k in range(6)}
    smooth, basis = training_set.learn_priors(tables)
    path = tmp_path / "mine.npz"
    assert training_set.basis_path_for(path) == tmp_path / "mine_basis.npz"
    with pytest.raises(InputError, match="not a file"):
        training_set.basis_path_for("/")                     # a folder has no name to put "_basis" after
    smooth.save(path)
    assert training_set.load_prior_files(path)[1] is None
    basis.save(training_set.basis_path_for(path))
    loaded = training_set.load_prior_files(path)
    assert isinstance(loaded[1], BasisPrior) and loaded[1].materials == basis.materials
    assert training_set.load_prior_files(path, basis=False)[1] is None


def _toy_prior(n_t: int = 4, n_s: int = 5) -> BasisPrior:
    """A prior with an orthonormal 3-component basis, written down (no learning)."""
    rng = np.random.default_rng(2)
    basis, _ = np.linalg.qr(rng.normal(size=(n_t * n_s, 3)))
    return BasisPrior(rng.normal(0.0, 0.5, n_t * n_s), basis, np.array([0.5, 0.2, 0.05]),
                      rng.uniform(0.05, 0.2, n_t * n_s), n_t, n_s, {"materials": ["a", "b", "c"]})


@pytest.mark.parametrize("case", ["a zero variance", "a NaN in the mean", "a mean of another grid",
                                  "one variance too many", "an infinite residual", "another format", "truncated",
                                  "a finite mean of 1e300", "a component spread of e^90"])
def test_a_damaged_basis_prior_file_is_refused_naming_it(tmp_path, case):
    """A basis prior file whose arrays disagree with its grid or each other, hold a non-finite value or a
    variance of 0 (a division by zero in ``predict``), names another format, or is cut short: an InputError
    naming the file (they were loaded, and failed or gave NaN later)."""
    import json

    path = tmp_path / "basis.npz"
    _toy_prior().save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    match = "basis prior arrays are inconsistent or non-finite"
    if case == "a zero variance":
        arrays["variances"][2] = 0.0
    elif case == "a NaN in the mean":
        arrays["mean"][3] = np.nan
    elif case == "a mean of another grid":
        arrays["mean"] = arrays["mean"][:-1]
    elif case == "one variance too many":
        arrays["variances"] = np.append(arrays["variances"], 0.01)
    elif case == "an infinite residual":
        arrays["residual"][0] = np.inf
    elif case == "a finite mean of 1e300":  # loaded, then exp() overflowed in predict (a helper's hostile input)
        arrays["mean"][1] = 1e300
        match = r"its log shapes reach 1e\+300, beyond any table \(at most 80"
    elif case == "a component spread of e^90":  # a node's spread, sqrt(sum_k basis^2 variance), of 90 or more
        arrays["variances"][0] = 90.0**2 / np.abs(arrays["basis"][:, 0]).max() ** 2
        match = r"its log shapes reach (9\d|1\d\d)(\.\d)?, beyond any table"
    elif case == "another format":
        arrays["meta"] = np.array(json.dumps({**json.loads(str(arrays["meta"])), "format": "mi_bivariate.prior"}))
        match = r"not a mi_bivariate basis prior \(format 'mi_bivariate.prior'\)"
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    if case == "truncated":
        whole = path.read_bytes()
        bad.write_bytes(whole[:len(whole) // 2])
        match = "not a readable .npz file"
    with pytest.raises(InputError, match=match) as info:
        BasisPrior.load(bad)
    assert info.value.source == str(bad)


def test_predicted_mean_is_never_negative_and_resolution_is_clipped_to_0_1():
    """Where the prior's log shape lies below ``log EPS`` (``exp(g) - EPS < 0``) the predicted table is 0, not
    negative; a channel of median 0 is scaled by its mean (closed form without data, as
    ``test_predict_without_data_is_the_prior_itself``); a resolution above 1 or below 0 predicts as 1 or 0
    (its documented range)."""
    from mi_bivariate.basis_prior import EPS

    prior = _toy_prior()
    prior.mean[[0, 7]] = np.log(0.1 * EPS)                     # far below what EPS can represent
    table = np.random.default_rng(5).uniform(0.1, 3.0, (4, 5, 3))
    mean, _ = prior.predict(table, np.zeros_like(table), np.ones_like(table))
    assert np.all(mean.reshape(20, 3)[[0, 7]] == 0.0) and np.all(mean >= 0.0)
    dark = table.copy()
    dark[..., 1] = 0.0
    dark[0, :3, 1] = [4.0, 2.0, 2.0]                              # median 0: the level is the mean, 0.4
    mean, _ = prior.predict(dark, np.zeros_like(dark), np.ones_like(dark))
    np.testing.assert_allclose(mean[..., 1].ravel(), 0.4 * np.maximum(np.exp(prior.mean) - EPS, 0.0), rtol=1e-12)
    resolution = np.random.default_rng(6).uniform(-1.0, 2.0, table.shape)
    post = 0.1 * table
    for got, want in zip(prior.predict(table, resolution, post), prior.predict(table, np.clip(resolution, 0, 1), post)):
        np.testing.assert_array_equal(got, want)


def test_learning_reads_negative_values_as_zero_and_a_median_zero_channel_by_its_mean():
    """The log map by hand: each channel over its median (its mean where the median is 0; a black channel is
    no sample), ``log(max(x, 0) + EPS)``; the prior's mean is the samples' mean. Negative values (ringing) are
    zeros (they were NaN logs, and a NaN prior or an SVD error)."""
    from mi_bivariate.basis_prior import EPS

    rng = np.random.default_rng(7)
    tables = {name: rng.uniform(0.5, 2.0, (4, 4, 1)) for name in ("a", "b", "c")}
    tables["a"][0, :2, 0] = -0.3                                  # (the median is taken with them)
    tables["b"][:, :, 0] = 0.0
    tables["b"][1, :3, 0] = [4.0, 2.0, 2.0]                       # median 0, mean 0.5
    tables["d"] = np.zeros((4, 4, 1))                             # black: no sample
    prior = BasisPrior.learn(tables, components=1)
    shapes = [np.log(np.maximum(tables["a"].ravel(), 0) / np.median(tables["a"]) + EPS),
              np.log(tables["b"].ravel() / 0.5 + EPS),
              np.log(tables["c"].ravel() / np.median(tables["c"]) + EPS)]
    np.testing.assert_allclose(prior.mean, np.mean(shapes, axis=0), rtol=1e-12)
    assert prior.provenance["samples"] == 3 and np.all(np.isfinite(prior.basis))


def test_residual_leaves_out_folds_with_fewer_than_three_other_samples():
    """Leave one material out only where three samples remain to learn from: material ``a`` (three channels)
    and ``b`` (one), so leaving ``a`` out would leave one sample and is skipped; the residual is ``b``'s error
    against a PCA of ``a``'s three log shapes by eigendecomposition (two components), floored at 1e-3."""
    from mi_bivariate.basis_prior import EPS

    rng = np.random.default_rng(10)
    tables = {"a": np.exp(rng.normal(0.0, 1.0, (4, 4, 3))), "b": np.exp(rng.normal(0.0, 1.0, (4, 4)))}
    prior = BasisPrior.learn(tables, components=3)
    a = np.array([np.log(tables["a"][..., c].ravel() / np.median(tables["a"][..., c]) + EPS) for c in range(3)])
    b = np.log(tables["b"].ravel() / np.median(tables["b"]) + EPS)
    _, vec = np.linalg.eigh(np.cov(a.T))
    top = vec[:, ::-1][:, :2]
    centred = b - a.mean(axis=0)
    np.testing.assert_allclose(prior.residual, np.maximum(np.abs(centred - top @ (top.T @ centred)), 1e-3), rtol=1e-8)


def test_learn_prior_writes_both_priors_on_the_grid_asked_from_the_materials_given(tmp_path, monkeypatch, capsys):
    """``learn-prior`` end to end (the shared materials' reduction replaced by tables of a known family, on
    the grid it is asked for): on a 5 x 4 grid, ``--out`` holds the smoothness prior and ``<stem>_basis.npz``
    the basis prior, each equal to the one learnt in Python from the same tables, with the data folder
    given passed on; an empty folder of MERL files is one error line and exit 2, writing nothing."""
    from mi_bivariate import cli
    from mi_bivariate.prior import Prior

    names = ["black-fabric", "brass", "gold-paint"]
    t = np.linspace(0, 1, 5)[:, None, None]
    rng = np.random.default_rng(1)
    made = {}

    def reduced(n_t, n_s, asked, data_dir=None, progress=False):
        assert (n_t, n_s, list(asked), str(data_dir)) == (5, 4, names, str(tmp_path))
        for k, name in enumerate(asked):          # brass glossy, the others diffuse
            made[name] = (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k == 1 else 0.0)) * rng.uniform(0.5, 2, (5, 4, 3))
        return dict(made)

    monkeypatch.setattr(training_set, "reduced_tables", reduced)
    out = tmp_path / "mine.npz"
    assert cli.main(["learn-prior", *names, "--grid", "5", "4", "--out", str(out), "--data", str(tmp_path)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    smooth, basis = Prior.load(out), BasisPrior.load(tmp_path / "mine_basis.npz")
    want_smooth, want_basis = Prior.learn(made), BasisPrior.learn(made)
    assert (smooth.n_t, smooth.n_s) == (basis.n_t, basis.n_s) == (5, 4)
    assert smooth.provenance["split"] == {"black-fabric": "diffuse", "brass": "gloss", "gold-paint": "diffuse"}
    assert "MERL-NBRDF" in smooth.provenance["sources"]["brass"] and basis.materials == tuple(names)
    for pair in want_smooth.pairs:
        for got, want in zip(smooth.pairs[pair], want_smooth.pairs[pair]):
            np.testing.assert_array_equal(got, want)
    for name in ("mean", "basis", "variances", "residual"):
        np.testing.assert_array_equal(getattr(basis, name), getattr(want_basis, name))

    (tmp_path / "empty").mkdir()
    assert cli.main(["learn-prior", str(tmp_path / "empty"), "--out", str(tmp_path / "p.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"mi-bivariate: error: {tmp_path / 'empty'}: folder holds no MERL")
    assert not (tmp_path / "p.npz").exists()


def test_a_leave_one_out_prior_is_learnt_from_the_other_materials_rows_only(monkeypatch):
    """``leave_one_out_priors`` (and ``BasisPrior.learn(exclude=)``) against the training rows, not the
    provenance: the basis prior's mean and variances are those of the *other* materials' log shapes written
    out here (their mean, the top eigenvalues of their ``np.cov``), and the smoothness prior is the one
    learnt from the others alone. (Learning from every table while naming only the others passed.)"""
    from mi_bivariate.prior import Prior

    names = list(nbrdf.ALL_NBRDF_MATERIALS[:6])
    rng, t = np.random.default_rng(12), np.linspace(0, 1, 6)[:, None, None]
    tables = {name: (0.1 + (1000.0 * np.exp(-(t / 0.1) ** 2) if k % 2 else 0.0))
              * np.exp(rng.normal(0.0, 0.3, (6, 5, 3))) for k, name in enumerate(names)}  # diffuse and glossy
    monkeypatch.setattr(training_set, "reduced_tables", lambda n_t, n_s, data_dir=None: tables)
    smooth, basis = training_set.leave_one_out_priors(names[2], 6, 5, cache=False)
    others = {n: tables[n] for n in names if n != names[2]}
    shapes = np.concatenate([_log_shapes(table) for table in others.values()])
    np.testing.assert_allclose(basis.mean, shapes.mean(axis=0), rtol=1e-12, atol=1e-12)
    eig = np.sort(np.linalg.eigvalsh(np.cov(shapes.T)))[::-1][:basis.variances.size]
    np.testing.assert_allclose(basis.variances, eig, rtol=1e-8)
    assert basis.provenance["samples"] == 15 and names[2] not in basis.materials
    direct = BasisPrior.learn(tables, exclude=names[2])            # BasisPrior.learn's own ``exclude``
    np.testing.assert_allclose(direct.mean, shapes.mean(axis=0), rtol=1e-12, atol=1e-12)
    assert direct.provenance["samples"] == 15
    want = Prior.learn(others)
    for pair in want.pairs:
        for got, ref in zip(smooth.pairs[pair], want.pairs[pair]):
            np.testing.assert_array_equal(got, ref)


def test_a_basis_prior_learnt_with_another_log_offset_is_refused_naming_it(tmp_path):
    """``predict`` maps tables with this module's ``EPS``; a file whose provenance says it was learnt with another
    offset would be read through the wrong log map without a word: it is refused, naming the file. A file with
    this EPS (or, as older files, none recorded) loads."""
    from mi_bivariate.basis_prior import EPS

    for eps, ok in ((EPS, True), (None, True), (10 * EPS, False)):
        prior = _toy_prior()
        prior.provenance = {k: v for k, v in prior.provenance.items() if k != "eps"}
        if eps is not None:
            prior.provenance["eps"] = eps
        path = tmp_path / f"basis_{eps}.npz"
        prior.save(path)
        if ok:
            assert BasisPrior.load(path).n_t == prior.n_t
        else:
            with pytest.raises(InputError, match="offset eps = 0.01") as info:
                BasisPrior.load(path)
            assert info.value.source == str(path)


def test_a_basis_prior_without_components_loads(tmp_path):
    """A prior learnt from too few materials keeps no component (``basis`` ``(N, 0)``): it saves and loads
    (the range check of its log shapes once took the largest of its empty variances and raised numpy's
    ValueError, a traceback from ``recover --prior``)."""
    prior = BasisPrior(np.zeros(20), np.zeros((20, 0)), np.zeros(0), np.full(20, 0.1), 4, 5, {"materials": ["a"]})
    prior.save(tmp_path / "b.npz")
    loaded = BasisPrior.load(tmp_path / "b.npz")
    assert loaded.basis.shape == (20, 0) and np.array_equal(loaded.residual, prior.residual)
