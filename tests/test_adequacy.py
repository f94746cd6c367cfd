"""mi_bivariate.adequacy: rank, coverage and the inadequate-illumination warning."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mi_bivariate import adequacy, capture, lighting
from mi_bivariate.errors import InputWarning
from mi_bivariate.geometry import SphereGeometry
from mi_bivariate.probes import Probe


@pytest.fixture(scope="module")
def sphere_obs() -> capture.Observations:
    geo = SphereGeometry(128.0, 128.0, 120.0)
    normals, mask = geo.normals(256, 256)
    image = np.where(mask[..., None], 0.2 + normals[..., 2:], 0.0).repeat(3, axis=2).astype(np.float32)
    return capture.observations_from_sphere(image, geo, n_normals=1600)


def analyse(obs, probe, **kwargs):
    L = lighting.lighting_matrix(obs, probe, n_dirs=4000)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = adequacy.analyse(L, 32, 32, probes=[probe], **kwargs)
    return L, report, [w for w in caught if issubclass(w.category, InputWarning)]


def test_constant_environment_is_inadequate(sphere_obs):
    L, report, caught = analyse(sphere_obs, Probe.constant(1.0, 32))
    assert not report.adequate and caught
    assert report.rank_fraction < 0.5  # each row depends on the view angle only
    assert report.detail == [0.0]
    assert "rank" in report.summary() and "INADEQUATE" in report.summary()


def test_a_rank_short_for_want_of_rows_says_so(sphere_obs):
    """Too few rows, not the lighting, is named as the cause when the rows alone cap the rank; with
    enough rows a constant probe is blamed on the lighting (the negative control)."""
    _, report, _ = analyse(sphere_obs.subset(np.arange(5)), Probe.constant(1.0, 32))
    assert not report.adequate and "only 5 observed normals for 1024 nodes" in report.summary(), report.summary()
    _, report, _ = analyse(sphere_obs, Probe.constant(1.0, 32))
    assert "too little variety in the lighting" in report.summary(), report.summary()


def test_observation_map_and_regions(sphere_obs):
    L, report, _ = analyse(sphere_obs, Probe.constant(1.0, 32))
    omap = report.observation_map
    assert omap.shape == (32, 32)
    assert omap.sum() == pytest.approx(len(sphere_obs), rel=1e-6)
    # A constant environment lights every reachable node; theta_h > theta_d + 80 deg is not.
    assert report.unobserved_nodes > 0 and omap[-1, 0] == 0.0
    assert set(report.regions) == {"specular", "retro", "grazing"}
    for region in report.regions.values():
        assert 0 < region["observed"] <= region["nodes"]
    fig = report.figure()
    assert len(fig.axes) >= 2
    # Its coverage cells are centred on their nodes (extent (0, 1, 0, 1) put cell i at (i + 0.5) / n).
    x0, x1, y0, y1 = fig.axes[0].images[0].get_extent()
    np.testing.assert_allclose(x0 + (np.arange(32) + 0.5) * (x1 - x0) / 32, np.linspace(0, 1, 32), atol=1e-12)
    np.testing.assert_allclose(y0 + (np.arange(32) + 0.5) * (y1 - y0) / 32, np.linspace(0, 1, 32), atol=1e-12)
    assert fig.axes[0].get_xlim() == (0.0, 1.0) and fig.axes[0].get_ylim() == (0.0, 1.0)


def test_spectrum_is_scale_invariant(sphere_obs):
    L = lighting.lighting_matrix(sphere_obs, Probe.constant(1.0, 32), n_dirs=2000)
    a, observed = adequacy.singular_spectrum(L)
    b, _ = adequacy.singular_spectrum(L * np.linspace(1, 100, L.shape[1])[None, :, None])
    assert np.allclose(a, b, atol=1e-6) and a[0] == 1.0 and observed.sum() == len(a)


@pytest.mark.parametrize("name,adequate", [("grace_latlong_1k", True), ("royal_esplanade_1k", False)])
def test_shared_probes(sphere_obs, data_dir, name, adequate):
    """Calibration: the blurred royal_esplanade must warn, Grace Cathedral must not."""
    from mi_bivariate.probes import shared_probe

    probe = shared_probe(name, data_dir)
    _, report, caught = analyse(sphere_obs, probe)
    assert report.adequate is adequate and bool(caught) is not adequate, report.summary()
    if adequate:
        assert report.rank_fraction > 0.7 and report.detail[0] > 3 * adequacy.MIN_DETAIL
    else:
        assert report.detail[0] < 0.5 * adequacy.MIN_DETAIL
        assert "detail" in str(caught[0].message)


def _reference_spectrum(L):
    """The pre-Gram implementation: SVD of the column-normalised M x N luminance (independent truth)."""
    lum = L.astype(np.float64) @ np.array([0.212671, 0.715160, 0.072169])
    norms = np.linalg.norm(lum, axis=0)
    observed = norms > 1e-12 * norms.max()
    sigma = np.linalg.svd(lum[:, observed] / norms[observed], compute_uv=False)
    return sigma / sigma[0], observed, lum


def test_gram_spectrum_matches_svd(data_dir):
    """The N x N Gram route gives the SVD's spectrum, rank, effective rank, condition and coverage."""
    from mi_bivariate.probes import shared_probe

    geo = SphereGeometry(128.0, 128.0, 120.0)
    normals, mask = geo.normals(256, 256)
    image = np.where(mask[..., None], 0.2 + normals[..., 2:], 0.0).repeat(3, axis=2).astype(np.float32)
    obs = capture.observations_from_sphere(image, geo, n_normals=3000)
    L = lighting.lighting_matrix(obs, shared_probe("grace_latlong_1k", data_dir), n_t=16, n_s=16, n_dirs=4000)
    ref_sigma, ref_observed, lum = _reference_spectrum(L)
    report = adequacy.analyse(L, 16, 16, warn=False)
    assert np.array_equal(adequacy.singular_spectrum(L)[1], ref_observed)
    # Eigenvalues of the Gram matrix carry an absolute error ~eps * sigma_max^2, so sigma
    # an absolute error ~sqrt(eps) ~ 1e-8 relative to the largest: far below RANK_TOL.
    assert report.singular_values.shape == ref_sigma.shape
    assert np.allclose(report.singular_values, ref_sigma, rtol=1e-6, atol=1e-7)
    assert report.numerical_rank == int(np.count_nonzero(ref_sigma > adequacy.RANK_TOL))
    p = ref_sigma / ref_sigma.sum()
    assert report.effective_rank == pytest.approx(float(np.exp(-np.sum(p * np.log(p)))), rel=1e-9)
    assert report.condition_number == pytest.approx(1.0 / ref_sigma[-1], rel=1e-4)
    totals = lum.sum(axis=1, keepdims=True)
    share = np.divide(lum, totals, out=np.zeros_like(lum), where=totals > 0)
    assert np.allclose(report.observation_map, share.sum(axis=0).reshape(16, 16), rtol=1e-12, atol=1e-12)


def test_blocked_statistics_match_dense():
    """The one-pass, column-compacted Gram and shares equal the dense route (an independent product)."""
    rng = np.random.default_rng(3)
    m, n = 203, 64
    L = rng.random((m, n, 3)).astype(np.float32)
    # Rows touch a band of columns that moves with the row, as sphere pixels do; one block is all zero.
    band = np.abs(np.arange(n)[None, :] - np.linspace(0, n, m)[:, None]) < 12
    L *= band[:, :, None]
    L[40:60] = 0.0
    L[:, 5] = 0.0  # a column no row reaches
    lum = L.astype(np.float64) @ np.array(adequacy.LUMINANCE_WEIGHTS, dtype=np.float64)
    dense = lum.T @ lum
    totals = lum.sum(axis=1, keepdims=True)
    shares = np.divide(lum, totals, out=np.zeros_like(lum), where=totals > 0).sum(axis=0)
    for block_rows in (1, 7, 64, 1000):
        gram, got = adequacy._luminance_statistics(L, block_rows=block_rows)
        np.testing.assert_allclose(gram, dense, rtol=1e-13, atol=1e-13 * dense.max())  # both triangles
        np.testing.assert_allclose(got, shares, rtol=1e-13, atol=1e-13)
    # One channel (M, N) takes the same path.
    gram, _ = adequacy._luminance_statistics(L[..., 1], block_rows=7)
    g1 = L[..., 1].astype(np.float64).T @ L[..., 1].astype(np.float64)
    np.testing.assert_allclose(gram, g1, rtol=1e-13, atol=1e-13 * g1.max())


def test_detail_cache_matches_fresh_and_follows_content(monkeypatch):
    """environment_detail is cached by probe content: same value as a fresh computation, computed
    once per content, recomputed for a different probe (data or rotation)."""
    rng = np.random.default_rng(5)
    data = (rng.random((128, 256, 3)) ** 6 * 10).astype(np.float32)  # 1.4 degree texels
    probe = Probe(data, source="a")
    fresh = adequacy._environment_detail(probe, adequacy.DETAIL_SCALE_DEG, 40000)
    calls = []
    original = adequacy._environment_detail
    monkeypatch.setattr(adequacy, "_environment_detail", lambda *a: calls.append(a) or original(*a))
    monkeypatch.setattr(adequacy, "_DETAIL_CACHE", type(adequacy._DETAIL_CACHE)())
    assert adequacy.environment_detail(probe) == fresh and len(calls) == 1
    assert adequacy.environment_detail(Probe(data.copy(), source="b")) == fresh and len(calls) == 1  # same content
    other = data.copy()
    other[10:60, 10:130] *= 0.01
    changed = adequacy.environment_detail(Probe(other))
    assert len(calls) == 2 and changed != fresh
    assert changed == original(Probe(other), adequacy.DETAIL_SCALE_DEG, 40000)
    adequacy.environment_detail(probe.rotated(euler_deg=(0, 30, 0)))
    assert len(calls) == 3
    adequacy.environment_detail(probe, scale_deg=6.0)
    assert len(calls) == 4
    assert probe.content_digest() != Probe(other).content_digest()


def test_observation_strength_region_shares_and_verdict_by_hand(monkeypatch):
    """Closed forms on a 2-D lighting matrix whose rows share their light equally between the nodes they
    see: a node seen equally by r rows has Kish effective number r and signal r / (nodes per row); it is
    observed only with both enough rows and enough signal; a region's share of the weight is its share of
    the nodes when every node is seen alike; with several probes the one with the most detail counts."""
    n_t = n_s = 4
    n = n_t * n_s
    L = np.ones((40, n))  # every row sees every node alike: share 1/n, effective rows 40, signal 40/n
    effective, signal = adequacy.node_observation_strength(L, n_t, n_s)
    np.testing.assert_allclose(effective, 40.0)
    np.testing.assert_allclose(signal, 40.0 / n)
    assert adequacy.observed_nodes(L, n_t, n_s).all()
    # Node 0 alone in 3 rows (effective 3, signal 3 + 40/n); the others faintly in 1000 rows.
    sparse = np.vstack([np.eye(n)[[0, 0, 0]], np.full((1000, n), 1e-3) * (np.arange(n) > 0)])
    effective, signal = adequacy.node_observation_strength(sparse, n_t, n_s)
    assert effective.ravel()[0] == pytest.approx(3.0) and signal.ravel()[0] == pytest.approx(3.0)
    np.testing.assert_allclose(effective.ravel()[1:], 1000.0)
    np.testing.assert_allclose(signal.ravel()[1:], 1000.0 / (n - 1))
    observed = adequacy.observed_nodes(sparse, n_t, n_s, min_effective=8.0, min_signal=2.0).ravel()
    assert not observed[0] and observed[1:].all()  # node 0: signal enough, too few rows
    # Many rows, too little signal: not observed either.
    assert not adequacy.observed_nodes(sparse, n_t, n_s, min_effective=8.0, min_signal=100.0).ravel()[1:].any()
    monkeypatch.setattr(adequacy, "environment_detail", lambda probe: probe)  # a probe given by its detail
    report = adequacy.analyse(L + np.eye(n)[np.arange(40) % n], n_t, n_s, probes=[0.01, 0.5], warn=False)
    assert report.detail == [0.01, 0.5] and report.adequate
    assert not adequacy.analyse(L + np.eye(n)[np.arange(40) % n], n_t, n_s, probes=[0.01, 0.02], warn=False).adequate
    masks = adequacy.region_masks(n_t, n_s)
    for name, stats in report.regions.items():
        assert stats["share"] == pytest.approx(masks[name].sum() / n, rel=0.1)


@pytest.mark.parametrize("name,detail", [("grace_latlong_1k", 0.19), ("grace_256", 0.32), ("uffizi_256", 0.23),
                                         ("pisa_256", 0.14), ("venice_sunset_1k", 0.16),
                                         ("pedestrian_overpass_1k", 0.25), ("royal_esplanade_1k", 0.02)])
def test_detail_matches_the_calibration_table(data_dir, name, detail):
    """The module docstring's calibration table (detail at 3 degrees) is what environment_detail gives on
    each shared probe, to its two decimals."""
    from mi_bivariate.probes import shared_probe

    assert adequacy.environment_detail(shared_probe(name, data_dir)) == pytest.approx(detail, abs=0.006)


def test_a_node_at_either_threshold_counts_as_observed():
    """``effective_rows >= min_effective`` and ``signal >= min_signal``, both inclusive (closed forms): a node
    holding half of each of 8 rows has exactly 8 effective rows and signal 4; one row fewer is too few."""
    n_t, n_s = 2, 2
    half = np.zeros((8, n_t * n_s))
    half[:, 0] = half[:, 1] = 0.5                     # node 0 and node 1 share every row equally
    effective, signal = adequacy.node_observation_strength(half, n_t, n_s)
    assert effective.ravel()[0] == 8.0 and signal.ravel()[0] == 4.0
    assert adequacy.observed_nodes(half, n_t, n_s).ravel().tolist() == [True, True, False, False]
    assert adequacy.observed_nodes(half, n_t, n_s, min_signal=4.0).ravel()[0]
    assert not adequacy.observed_nodes(half, n_t, n_s, min_signal=4.0 + 1e-9).ravel()[0]
    assert not adequacy.observed_nodes(half[:7], n_t, n_s).ravel()[0]


def test_a_lighting_matrix_of_another_grid_is_refused():
    """Every front door that reshapes L's columns to the st grid refuses a mismatch with one InputError."""
    from mi_bivariate.errors import InputError

    L = np.ones((5, 16))
    for call in (lambda: adequacy.observation_map(L, 4, 5), lambda: adequacy.node_observation_strength(L, 4, 5),
                 lambda: adequacy.observed_nodes(L, 4, 5), lambda: adequacy.analyse(L, 4, 5, warn=False)):
        with pytest.raises(InputError, match="lighting matrix has 16 columns, expected 4x5"):
            call()


def test_region_masks_are_the_closed_form_with_both_ends_included():
    """On a 4 x 4 grid the nodes sit at theta_h = 90 (i / 3)^2 = 0, 10, 40, 90 and theta_d = 30 j = 0 .. 90
    degrees: specular (theta_h 0-2) is the first row, retro (theta_d 0-10) the first column, grazing
    (theta_d 75-90) the last; each interval's two ends belong to it."""
    masks = adequacy.region_masks(4, 4)
    first_row, first_col, last_col = (np.zeros((4, 4), bool) for _ in range(3))
    first_row[0], first_col[:, 0], last_col[:, 3] = True, True, True
    np.testing.assert_array_equal(masks["specular"], first_row)
    np.testing.assert_array_equal(masks["retro"], first_col)
    np.testing.assert_array_equal(masks["grazing"], last_col)


def test_region_summaries_by_hand():
    """A 4 x 4 lighting matrix whose rows put known shares on the specular row's nodes (3, 0.005, 1 and 0
    pixels' worth): ``observed`` counts the nodes with at least 0.01, ``median_per_node`` is their median,
    ``share`` their part of all rows."""
    n = 16
    L = np.zeros((5, n))
    L[0:3, 0] = 2.0                         # node 0: three rows of its own
    L[3, 1], L[3, 5] = 0.005, 0.995          # node 1: 0.005 of a row (the rest on node 5, not specular)
    L[4, 2] = 7.0                           # node 2: one row; node 3: none
    report = adequacy.analyse(L, 4, 4, warn=False)
    np.testing.assert_allclose(report.observation_map[0], [3.0, 0.005, 1.0, 0.0], rtol=1e-12)
    specular = report.regions["specular"]
    assert specular["nodes"] == 4 and specular["observed"] == 2
    assert specular["median_per_node"] == pytest.approx(0.5025, rel=1e-12)
    assert specular["share"] == pytest.approx(4.005 / 5, rel=1e-12)


def test_the_rank_verdict_at_exactly_half_the_nodes_and_its_cause():
    """Numerical rank half the nodes is adequate, one less is not (closed form: rows of the identity); a rank
    short although the rows alone could reach half the nodes is the lighting's fault, not the rows'."""
    n_t = n_s = 4
    eye = np.eye(n_t * n_s)
    assert adequacy.analyse(eye[:8], n_t, n_s, warn=False).adequate
    short = adequacy.analyse(eye[:7], n_t, n_s, warn=False)
    assert not short.adequate and "numerical rank 7 of 16" in short.summary()
    assert "only 7 observed normals for 16 nodes" in short.summary()
    same = adequacy.analyse(np.ones((10, n_t * n_s)), n_t, n_s, warn=False)   # ten rows, all alike: rank 1
    assert "numerical rank 1 of 16" in same.summary() and "too little variety in the lighting" in same.summary()


def test_detail_is_cached_per_number_of_points():
    """The detail's lattice size is part of its cache key: another ``n_points`` is computed afresh."""
    rng = np.random.default_rng(6)
    probe = Probe((rng.random((128, 256, 3)) ** 6 * 10).astype(np.float32), source="points")  # 1.4 degree texels
    default = adequacy.environment_detail(probe)
    fewer = adequacy.environment_detail(probe, n_points=2000)
    assert fewer == adequacy._environment_detail(probe, adequacy.DETAIL_SCALE_DEG, 2000) != default


def test_unobserved_nodes_and_a_single_probe_by_hand(monkeypatch):
    """``unobserved_nodes`` counts the columns of L that no row reaches (12 of 16 here, by construction), and
    ``probes`` may be one probe rather than a list of them (its detail then decides alone)."""
    L = np.zeros((5, 16))
    L[0:3, 0], L[3, 1], L[3, 5], L[4, 2] = 2.0, 0.005, 0.995, 7.0      # columns 0, 1, 2 and 5 are reached
    report = adequacy.analyse(L, 4, 4, warn=False)
    assert report.unobserved_nodes == 12 and len(report.singular_values) == 4
    monkeypatch.setattr(adequacy, "environment_detail", lambda probe: probe)  # a probe given by its detail
    single = adequacy.analyse(np.eye(16), 4, 4, probes=0.5, warn=False)
    assert single.detail == [0.5] and single.adequate
    blurred = adequacy.analyse(np.eye(16), 4, 4, probes=0.01, warn=False)
    assert blurred.detail == [0.01] and not blurred.adequate and "detail 0.010" in blurred.summary()


def test_an_empty_list_of_probes_skips_the_detail_test():
    """``probes=[]`` is no probe, as ``probes=None``: the rank verdict alone (before: max() of an empty list
    raised a bare ValueError)."""
    for probes in (None, [], ()):
        report = adequacy.analyse(np.eye(16), 4, 4, probes=probes, warn=False)
        assert report.detail == [] and report.adequate and "detail" not in report.summary()
        assert not adequacy.analyse(np.eye(16)[:7], 4, 4, probes=probes, warn=False).adequate
