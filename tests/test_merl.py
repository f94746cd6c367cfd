"""MERL .binary I/O and lookups, and the MERL-NBRDF materials."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_bivariate.coordinates import dirs_from_half_diff
from mi_bivariate.errors import InputError
from mi_bivariate.merl import (
    MERL_FILE_BYTES,
    MERL_SCALE,
    MERL_SHAPE,
    MERLBRDF,
    above_horizon,
    geometric_mask,
    node_angles,
)


def reference_index(theta_h: float, theta_d: float, phi_d: float) -> tuple:
    """MERL's reference BRDFRead indexing, transcribed scalar by scalar."""
    if theta_h <= 0.0:
        i_h = 0
    else:
        i_h = int(math.sqrt(theta_h / (math.pi / 2.0) * 90.0 * 90.0))
        i_h = min(max(i_h, 0), 89)
    i_d = min(max(int(theta_d / (math.pi / 2.0) * 90.0), 0), 89)
    if phi_d < 0.0:
        phi_d += math.pi
    i_p = min(max(int(phi_d / math.pi * 360 / 2), 0), 179)
    return i_h, i_d, i_p


@pytest.fixture(scope="module")
def raw_file(tmp_path_factory):
    """A MERL file written by hand (header, channel-major float64) with some missing samples."""
    rng = np.random.default_rng(0)
    raw = rng.uniform(0.0, 3000.0, (3,) + MERL_SHAPE)
    raw[rng.random(raw.shape) < 0.01] = -1.0
    path = tmp_path_factory.mktemp("merl") / "handmade.binary"
    with open(path, "wb") as f:
        np.array(MERL_SHAPE, np.int32).tofile(f)
        raw.tofile(f)
    return path, raw


def test_read_layout_and_scales(raw_file):
    path, raw = raw_file
    merl = MERLBRDF.read(path)
    assert merl.table.shape == (90, 90, 180, 3) and merl.name == "handmade"
    for c in range(3):
        expected = np.where(raw[c] < 0.0, np.nan, raw[c] * MERL_SCALE[c])
        np.testing.assert_array_equal(merl.table[..., c], expected)


def test_read_uses_merls_published_scales_and_keeps_zeros(tmp_path):
    """MERL's BRDFRead scales the channels by 1/1500, 1.15/1500 and 1.66/1500 (written out here, not taken
    from the module); a raw 0 is a black sample (0 1/sr), only a negative raw value is missing."""
    raw = np.full((3,) + MERL_SHAPE, 1500.0)
    raw[:, 5, 6, 7] = 0.0
    raw[:, 5, 6, 8] = -1.0
    path = tmp_path / "scales.binary"
    with open(path, "wb") as f:
        np.array(MERL_SHAPE, "<i4").tofile(f)
        raw.astype("<f8").tofile(f)
    table = MERLBRDF.read(path).table
    np.testing.assert_allclose(table[0, 0, 0], [1.0, 1.15, 1.66], rtol=1e-15)
    np.testing.assert_array_equal(table[5, 6, 7], [0.0, 0.0, 0.0])
    assert np.all(np.isnan(table[5, 6, 8]))


def test_valid_mask_needs_every_channel(raw_file):
    """A sample missing in one channel only (the file's channels miss 1% of their samples independently) is
    not valid: ``valid_mask`` is every raw value non-negative, at a node above the horizon."""
    path, raw = raw_file
    merl = MERLBRDF.read(path)
    expected = np.all(raw >= 0.0, axis=0) & geometric_mask()
    partly = np.any(raw < 0.0, axis=0) & np.any(raw >= 0.0, axis=0) & geometric_mask()
    assert partly.sum() > 1000
    np.testing.assert_array_equal(merl.valid_mask(), expected)


def test_write_read_round_trip(raw_file, tmp_path):
    merl = MERLBRDF.read(raw_file[0])
    out = tmp_path / "copy.binary"
    merl.write(out)
    assert out.stat().st_size == MERL_FILE_BYTES
    np.testing.assert_array_equal(np.fromfile(out, np.int32, count=3), MERL_SHAPE)
    back = MERLBRDF.read(out)
    np.testing.assert_array_equal(np.isnan(back.table), np.isnan(merl.table))
    np.testing.assert_allclose(back.table, merl.table, rtol=1e-15, equal_nan=True)
    # Missing samples are stored as negative raw values.
    raw = np.fromfile(out, "<f8", offset=12).reshape((3,) + MERL_SHAPE)
    assert np.all(raw[np.moveaxis(np.isnan(merl.table), -1, 0)] < 0.0)


def test_write_is_atomic(tmp_path):
    """A negative value (it would read back as missing) is refused with an InputError naming the file,
    before anything is written."""
    table = np.ones(MERL_SHAPE + (3,))
    table[0, 0, 0, 0] = -0.5
    with pytest.raises(InputError, match=r"bad\.binary: MERL table .* has negative values \(min -0\.5 1/sr\)"):
        MERLBRDF(table).write(tmp_path / "bad.binary")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("values", ["zero", "infinite", "huge", "underflow"])
def test_write_refuses_a_table_read_would_refuse(tmp_path, values):
    """MERLBRDF.write (and BivariateBRDF.to_merl().write) wrote files MERLBRDF.read refuses: an all-zero
    table, an infinite value, values beyond or below float32. Each is refused before anything is written."""
    table = np.full(MERL_SHAPE + (3,), 0.5)
    table[..., :] = {"zero": 0.0, "infinite": 0.5, "huge": 1e39, "underflow": 1e-39}[values]
    if values == "infinite":
        table[10, 10, 10] = np.inf
    with pytest.raises(InputError, match="bad.binary.*a MERL reader would refuse it"):
        MERLBRDF(table).write(tmp_path / "bad.binary")
    assert list(tmp_path.iterdir()) == []
    if values == "zero":
        from mi_bivariate.bivariate import BivariateBRDF

        with pytest.raises(InputError, match="no positive value"):
            BivariateBRDF(np.zeros((8, 8, 3), np.float32)).to_merl().write(tmp_path / "bad.binary")


def test_light_only_below_the_horizon_is_refused(tmp_path):
    """Only the nodes above the horizon are ever lit: a table whose positive values all lie below it
    reflects no light and is refused, before anything is written."""
    table = np.zeros(MERL_SHAPE + (3,))
    table[~geometric_mask()] = 1.0
    with pytest.raises(InputError, match="no positive value above the horizon"):
        MERLBRDF(table).write(tmp_path / "below.binary")
    assert list(tmp_path.iterdir()) == []


def test_channels_lit_only_where_another_is_missing_are_refused(tmp_path):
    """Each channel positive only on phi_d slices where the other two are missing (raw -1), the nodes valid in
    all three black: every reader keeps only the samples valid in all three channels, so the material is black
    and Eq. 1's relative error undefined (reduce printed floors of nan). Read and write refuse it by name."""
    raw = np.full((3,) + MERL_SHAPE, -1.0)
    for c in range(3):
        raw[c][:, :, c::3] = 1000.0
    raw[:, :, :, -1] = 0.0
    path = tmp_path / "apart.binary"
    with open(path, "wb") as f:
        np.array(MERL_SHAPE, np.int32).tofile(f)
        raw.tofile(f)
    problem = "no sample above the horizon that is valid in all three colour channels has a positive value"
    with pytest.raises(InputError, match=f"^{path}: {problem}"):
        MERLBRDF.read(path)
    table = np.moveaxis(np.where(raw < 0.0, np.nan, raw / 1000.0), 0, -1)
    with pytest.raises(InputError, match=f"out.binary: {problem}"):
        MERLBRDF(table).write(tmp_path / "out.binary")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["apart.binary"]


def test_channels_overlapping_only_below_the_horizon_are_refused(tmp_path):
    """As above, but the three channels are all valid and positive at the nodes below the horizon, which are
    never lit: the check of the samples valid in all three channels looks above the horizon only."""
    table = np.full(MERL_SHAPE + (3,), np.nan)
    for c in range(3):
        table[:, :, c::3, c] = 1.0
    table[~geometric_mask()] = 2.0
    with pytest.raises(InputError, match="no sample above the horizon is valid in all three colour channels"):
        MERLBRDF(table).write(tmp_path / "below.binary")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("case", ["truncated", "trailing", "foreign", "tiny", "missing", "directory"])
def test_bad_files_raise_input_error(raw_file, tmp_path, case):
    data = raw_file[0].read_bytes()
    path = tmp_path / f"{case}.binary"
    if case == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif case == "trailing":
        path.write_bytes(data + b"\0" * 8)
    elif case == "foreign":
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + data[8:])
    elif case == "tiny":
        path.write_bytes(b"ab")
    elif case == "directory":
        path.mkdir()
    with pytest.raises(InputError) as info:
        MERLBRDF.read(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message


def test_nearest_matches_reference_indexing(raw_file):
    merl = MERLBRDF.read(raw_file[0])
    rng = np.random.default_rng(1)
    theta_h = rng.uniform(-0.01, 0.5 * math.pi + 0.01, 300)
    theta_d = rng.uniform(-0.01, 0.5 * math.pi + 0.01, 300)
    phi_d = rng.uniform(-math.pi, math.pi, 300)
    got = merl.eval(theta_h, theta_d, phi_d)
    idx = np.array([reference_index(*a) for a in zip(theta_h, theta_d, phi_d)])
    expected = merl.table[idx[:, 0], idx[:, 1], idx[:, 2]]
    np.testing.assert_array_equal(got, expected)


def test_lookups_at_nodes_return_nodes(raw_file):
    merl = MERLBRDF.read(raw_file[0])
    theta_h, theta_d, phi_d = node_angles()
    ii = np.array([0, 1, 2, 17, 45, 88, 89])
    kk = np.array([0, 1, 90, 179, 100, 3, 45])
    th, td, pd = theta_h[ii][:, None], theta_d[ii][None, :], phi_d[kk][:, None]
    expected = merl.table[ii[:, None], ii[None, :], kk[:, None]]
    np.testing.assert_array_equal(merl.eval(th, td, pd), expected)
    finite = np.all(np.isfinite(expected), axis=-1)
    np.testing.assert_allclose(merl.eval(th, td, pd, "linear")[finite], expected[finite], rtol=1e-12)
    # phi_d and phi_d - pi address the same sample (reciprocity fold).
    np.testing.assert_array_equal(merl.eval(th, td, pd - math.pi), expected)


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
def test_lookups_at_non_finite_angles_give_nan(raw_file, interpolation):
    """Before, a NaN or infinite phi_d read a real sample (index 172 of 180, from the integer cast of NaN) and
    a NaN theta raised IndexError; now NaN in gives NaN out, as BivariateBRDF.eval, and the finite angles
    of the same call still read MERL's reference index."""
    merl = MERLBRDF.read(raw_file[0])
    theta_h = np.array([0.3, np.nan, 0.3, 0.3, np.inf, 0.3])
    theta_d = np.array([0.4, 0.4, np.nan, 0.4, 0.4, 0.4])
    phi_d = np.array([1.0, 1.0, 1.0, np.nan, 1.0, -np.inf])
    got = merl.eval(theta_h, theta_d, phi_d, interpolation)
    assert got.shape == (6, 3) and np.all(np.isnan(got[1:]))
    if interpolation == "nearest":
        np.testing.assert_array_equal(got[0], merl.table[reference_index(0.3, 0.4, 1.0)])
    np.testing.assert_array_equal(got[0], merl.eval(0.3, 0.4, 1.0, interpolation))
    assert np.all(np.isnan(merl.eval(0.3, 0.4, np.nan, interpolation)))


def test_nearest_clamps_at_and_beyond_ninety_degrees(raw_file):
    """theta_h, theta_d = pi/2 (and beyond) index MERL's last nodes, 89, as the reference clamps."""
    merl = MERLBRDF.read(raw_file[0])
    edge = np.array([0.5 * math.pi, 0.5 * math.pi + 1e-12, 1.7, 3.0])
    for th, td in [(edge, 0.3), (0.3, edge), (edge, edge)]:
        th, td = np.broadcast_arrays(th, td)
        idx = np.array([reference_index(a, b, 0.5) for a, b in zip(th, td)])
        np.testing.assert_array_equal(merl.eval(th, td, 0.5), merl.table[idx[:, 0], idx[:, 1], idx[:, 2]])


def test_linear_renormalises_over_finite_neighbours():
    """Next to a missing sample a linear lookup of a constant table is that constant (weights renormalised
    over the finite neighbours), not the constant times the finite neighbours' share of the weight."""
    table = np.broadcast_to(np.array([0.5, 1.0, 2.0]), MERL_SHAPE + (3,)).copy()
    table[10, 10, 10] = np.nan
    table[11, 11, 11] = np.nan
    value = MERLBRDF(table).eval(theta_h=(10.25 / 90) ** 2 * 0.5 * math.pi, theta_d=10.5 / 90 * 0.5 * math.pi,
                                 phi_d=10.75 / 180 * math.pi, interpolation="linear")
    np.testing.assert_allclose(value, [0.5, 1.0, 2.0], rtol=1e-12)


def test_linear_is_trilinear():
    # A function linear in the node indices (t, s, phi_d index) is reproduced exactly.
    i, j, k = np.meshgrid(np.arange(90), np.arange(90), np.arange(180), indexing="ij")
    table = np.stack([1.0 + i + 2.0 * j + 0.5 * k, 2.0 + 0.1 * i, 3.0 + 0.0 * k], axis=-1)
    merl = MERLBRDF(table)
    rng = np.random.default_rng(2)
    u_h, u_d = rng.uniform(0.0, 89.0, (2, 500))
    u_p = rng.uniform(0.0, 179.0, 500)
    theta_h = (u_h / 90.0) ** 2 * (0.5 * math.pi)
    theta_d = u_d / 90.0 * (0.5 * math.pi)
    phi_d = u_p / 180.0 * math.pi
    expected = np.stack([1.0 + u_h + 2.0 * u_d + 0.5 * u_p, 2.0 + 0.1 * u_h, np.full(500, 3.0)], axis=-1)
    np.testing.assert_allclose(merl.eval(theta_h, theta_d, phi_d, "linear"), expected, rtol=1e-10)
    # phi_d wraps with period pi: halfway between node 179 and node 0 (= pi).
    half = merl.eval(0.0, 0.0, 179.5 / 180.0 * math.pi, "linear")
    np.testing.assert_allclose(half[0], 1.0 + 0.5 * 0.5 * 179.0, rtol=1e-12)
    # Theta axes clamp beyond the last node.
    np.testing.assert_allclose(merl.eval(0.5 * math.pi, 0.5 * math.pi, 0.0, "linear"), table[89, 89, 0])
    # A missing neighbour is left out of the weights, not propagated.
    table[10, 10, 10] = np.nan
    merl = MERLBRDF(table)
    value = merl.eval(theta_h=(10.5 / 90) ** 2 * 0.5 * math.pi, theta_d=10.5 / 90 * 0.5 * math.pi,
                      phi_d=10.5 / 180 * math.pi, interpolation="linear")
    assert np.all(np.isfinite(value))


def test_geometric_mask_and_from_function():
    theta_h, theta_d, phi_d = node_angles()
    th, td, pd = np.meshgrid(theta_h, theta_d, phi_d, indexing="ij")
    wi, wo = dirs_from_half_diff(th, np.zeros_like(th), td, pd)
    # Heights within rounding (1e-12) of 0 are on the horizon: the nodes exactly on it (below) come out +8e-17.
    expected = (wi[..., 2] > 1e-12) & (wo[..., 2] > 1e-12)
    np.testing.assert_array_equal(geometric_mask(), expected)
    assert 0.6 < expected.mean() < 0.9

    merl = MERLBRDF.from_function(lambda a, b, c: np.stack([a, b, c], axis=-1), name="angles")
    np.testing.assert_array_equal(merl.valid_mask(), expected)
    np.testing.assert_array_equal(merl.table[expected], np.stack([th, td, pd], axis=-1)[expected])
    assert np.all(np.isnan(merl.table[~expected]))


def test_nodes_exactly_on_the_horizon_are_not_above_it():
    """theta_h + theta_d = pi/2 at phi_d = 0 puts wi exactly on the horizon: on MERL's nodes where
    (i/90)^2 + j/90 = 1, i.e. (i, j) = (30, 80) and (60, 50) (i^2 + 90 j = 8100). Its height came out as
    +8e-17 by rounding and both nodes counted as above the horizon, where Ward's 1/sqrt(cos_i cos_o) is
    ~3e7 1/sr: one such cell made a Ward fit's Eq. 1 ~400 times what the other 1.1 million cells give.
    They are missing now, in the mask and in every table tabulated on it; the nodes just beside them are not."""
    from mi_bivariate import analytic

    on = [(i, j) for i in range(90) for j in range(90) if i * i + 90 * j == 8100]
    assert on == [(30, 80), (60, 50)]
    mask = geometric_mask()
    for i, j in on:
        assert not mask[i, j, 0] and mask[i, j, 1] and mask[i, j - 1, 0] and mask[i - 1, j, 0]
    assert not above_horizon(math.pi / 18.0, 4.0 * math.pi / 9.0, 0.0)  # 10 + 80 degrees
    assert above_horizon(math.pi / 18.0, 4.0 * math.pi / 9.0 - 1e-9, 0.0)
    # height=0.0 is the old test, which kept both nodes (their heights round to ~1e-16 above 0) ...
    theta_h, theta_d, phi_d = node_angles()
    for i, j in on:
        assert above_horizon(theta_h[i], theta_d[j], phi_d[0], height=0.0)
        assert not above_horizon(theta_h[i], theta_d[j], phi_d[0])
    # ... and a height is a height: at theta_h = 0 both directions are cos(theta_d) above the horizon.
    assert above_horizon(0.0, math.pi / 3.0, 0.7, height=0.49) and not above_horizon(0.0, math.pi / 3.0, 0.7, height=0.51)
    table = analytic.to_merl(analytic.Lambertian(0.5)).table
    assert np.all(np.isnan(table[30, 80, 0])) and np.all(np.isnan(table[60, 50, 0]))


def test_from_function_clamps_negative_values():
    merl = MERLBRDF.from_function(lambda a, b, c: np.stack([np.full_like(a, -0.2), 0 * a + 0.3, np.cos(c)], -1),
                                  name="negative")
    valid = geometric_mask()
    _, _, phi_d = node_angles()
    np.testing.assert_array_equal(merl.table[valid][:, :2], np.broadcast_to([0.0, 0.3], (int(valid.sum()), 2)))
    np.testing.assert_array_equal(merl.table[..., 2][valid], np.maximum(np.cos(phi_d), 0.0)[np.nonzero(valid)[2]])
    assert np.all(np.isnan(merl.table[~valid]))


def test_to_bitmap_layout(raw_file):
    merl = MERLBRDF.read(raw_file[0])
    img = np.array(merl.to_bitmap())
    assert img.shape == (90 * 90, 180, 3) and img.dtype == np.float32
    np.testing.assert_array_equal(img[17 * 90 + 42, 99], merl.table[17, 42, 99].astype(np.float32))
    np.testing.assert_array_equal(np.isnan(img), np.isnan(merl.table.reshape(8100, 180, 3)))


def test_wrong_table_shape():
    with pytest.raises(InputError, match="mytable"):
        MERLBRDF(np.zeros((90, 90, 90, 3)), name="mytable")


# ----------------------------------------------------------------- MERL-NBRDF


def test_nbrdf_names_and_errors(monkeypatch, tmp_path):
    from mi_bivariate import nbrdf

    assert len(nbrdf.NBRDF_MATERIALS) == 23 and len(set(nbrdf.NBRDF_MATERIALS)) == 23
    with pytest.raises(InputError, match="alum-bronze"):
        nbrdf.load_nbrdf("not-a-material", data_dir=tmp_path)
    monkeypatch.delenv("MI_BIVARIATE_DATA", raising=False)
    with pytest.raises(InputError, match="MI_BIVARIATE_DATA"):
        nbrdf.data_dir()
    with pytest.raises(InputError, match="merl_nbrdf_dev.npz"):
        nbrdf.load_nbrdf("brass", data_dir=tmp_path)
    assert nbrdf.data_dir(tmp_path) == tmp_path


def test_nbrdf_explicit_data_folder_overrides_the_environment(monkeypatch, tmp_path):
    """``--data`` (``data_dir=``) wins over ``MI_BIVARIATE_DATA``: the weights are looked for where the user said."""
    from mi_bivariate import nbrdf

    other = tmp_path / "env"
    other.mkdir()
    monkeypatch.setenv("MI_BIVARIATE_DATA", str(other))
    assert nbrdf.data_dir(tmp_path) == tmp_path and nbrdf.data_dir() == other
    assert nbrdf.weights_path("brass", tmp_path) == tmp_path / "merl_nbrdf" / "merl_nbrdf_dev.npz"
    assert nbrdf.weights_path("chrome-steel", tmp_path) == tmp_path / "merl_nbrdf" / "merl_nbrdf_train.npz"


def test_nbrdf_matches_direct_formula(data_dir):
    from mi_bivariate import nbrdf

    npz = np.load(data_dir / "merl_nbrdf" / "merl_nbrdf_dev.npz")
    w = {k: npz[f"brass/{k}"].astype(np.float64) for k in ("W1", "b1", "W2", "b2", "W3", "b3")}
    rng = np.random.default_rng(3)
    th, td = rng.uniform(0.0, 0.5 * math.pi, (2, 200))
    pd = rng.uniform(0.0, math.pi, 200)
    x = np.stack([np.sin(th), 0 * th, np.cos(th), np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], 1)
    relu = lambda v: np.maximum(v, 0.0)  # noqa: E731
    expected = np.maximum(np.exp(relu(relu(x @ w["W1"] + w["b1"]) @ w["W2"] + w["b2"]) @ w["W3"] + w["b3"]) - 1, 0)
    got = nbrdf.load_nbrdf("brass", data_dir).eval(th, td, pd)
    np.testing.assert_allclose(got, expected, rtol=2e-4, atol=1e-6)

    merl = nbrdf.nbrdf_merl("brass", data_dir)
    assert nbrdf.nbrdf_merl("brass", data_dir) is merl  # cached
    theta_h, theta_d, phi_d = node_angles()
    node = (40, 30, 77)
    np.testing.assert_allclose(merl.table[node], nbrdf.load_nbrdf("brass", data_dir).eval(
        theta_h[node[0]], theta_d[node[1]], phi_d[node[2]]), rtol=1e-6)


def test_nbrdf_training_materials_match_direct_formula(data_dir):
    """A training-set material is read from merl_nbrdf_train.npz (the development file has no such key) and
    evaluated as the shared data README's formula, written out here as a plain float64 forward pass, at
    angles including the grazing and phi_d > pi/2 ones."""
    from mi_bivariate import nbrdf

    npz = np.load(data_dir / "merl_nbrdf" / "merl_nbrdf_train.npz")
    th = np.array([0.0, 0.01, 0.3, 0.7, 1.2, 1.5])
    td = np.array([0.0, 0.5, 1.4, 0.2, 0.9, 0.05])
    pd = np.array([0.0, 2.5, 0.3, 1.7, 3.0, 0.9])
    x = np.stack([np.sin(th), 0 * th, np.cos(th), np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], 1)
    for name in ("chrome-steel", "yellow-plastic"):
        w = {k: npz[f"{name}/{k}"].astype(np.float64) for k in ("W1", "b1", "W2", "b2", "W3", "b3")}
        h1 = np.maximum(x @ w["W1"] + w["b1"], 0.0)
        h2 = np.maximum(h1 @ w["W2"] + w["b2"], 0.0)
        expected = np.maximum(np.exp(h2 @ w["W3"] + w["b3"]) - 1.0, 0.0)
        assert expected.max() > 1.0 and np.count_nonzero(expected) > 9, name  # a lit, non-trivial comparison
        np.testing.assert_allclose(nbrdf.load_nbrdf(name, data_dir).eval(th, td, pd), expected, rtol=1e-9,
                                   atol=1e-12, err_msg=name)


@pytest.mark.parametrize("change", ["W2 transposed shape", "b3 missing"])
def test_nbrdf_malformed_weights_are_refused_by_name(data_dir, tmp_path, change):
    """A weights file whose layer has the wrong shape or is missing: an InputError naming the file and the
    array, not numpy's matmul error from inside the network (or a table of a network that is not the one stored)."""
    from mi_bivariate import nbrdf

    with np.load(data_dir / "merl_nbrdf" / "merl_nbrdf_dev.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    if change == "b3 missing":
        del arrays["brass/b3"]
        match = r"missing array 'brass/b3'"
    else:
        arrays["brass/W2"] = arrays["brass/W2"][:, :20]
        match = r"brass/W2 has shape \(21, 20\), expected \(21, 21\)"
    (tmp_path / "merl_nbrdf").mkdir()
    path = tmp_path / "merl_nbrdf" / "merl_nbrdf_dev.npz"
    np.savez(path, **arrays)
    with pytest.raises(InputError, match=match) as info:
        nbrdf.load_nbrdf("brass", data_dir=tmp_path)
    assert info.value.source == str(path)


def test_nbrdf_cached_table_is_read_only(data_dir):
    """nbrdf_merl hands every caller the same cached table: writing into it must fail, not change the
    truth that later callers in the process score against."""
    from mi_bivariate import nbrdf

    merl = nbrdf.nbrdf_merl("brass", data_dir)
    with pytest.raises(ValueError, match="read-only"):
        merl.table[40, 30, 77] = 0.0
    assert nbrdf.nbrdf_merl("brass", data_dir) is merl


def _fixed_order_decode(weights: dict, x: np.ndarray) -> np.ndarray:
    """The MLP in float64 with every sum in a fixed order (elementwise numpy, no BLAS)."""
    h = x
    for layer in ("1", "2", "3"):
        w, b = weights[f"W{layer}"].astype(np.float64), weights[f"b{layer}"].astype(np.float64)
        z = np.broadcast_to(b, (len(h), len(b))).copy()
        for k in range(w.shape[0]):
            z += h[:, k:k + 1] * w[k]
        h = np.maximum(z, 0.0) if layer != "3" else z
    return np.maximum(np.expm1(h), 0.0)


def test_nbrdf_truth_does_not_depend_on_the_blas(data_dir):
    """The truth tables are the float64 network rounded once: equal, to one float32 rounding, to a
    decoder that sums in a fixed order without BLAS, also at the near-zero values where a float32
    decoder (whose sums follow the CPU's BLAS kernels) is off by far more."""
    from mi_bivariate import nbrdf

    npz = np.load(data_dir / "merl_nbrdf" / "merl_nbrdf_dev.npz")
    for name in ("brass", "color-changing-paint1"):
        weights = {k: npz[f"{name}/{k}"] for k in ("W1", "b1", "W2", "b2", "W3", "b3")}
        table = nbrdf.nbrdf_merl(name, data_dir).table
        assert table.dtype == np.float32
        rng = np.random.default_rng(5)
        valid = np.argwhere(geometric_mask())
        tiny = np.argwhere(np.nanmin(table, axis=-1) < 1e-6)  # where exp(z) - 1 cancels
        nodes = np.concatenate([tiny, valid[rng.choice(len(valid), 3000, replace=False)]])
        assert len(tiny) > 50, name
        th, td, pd = (a[i] for a, i in zip(node_angles(), nodes.T))
        x = np.stack([np.sin(th), 0 * th, np.cos(th), np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], 1)
        expected = _fixed_order_decode(weights, x)
        got = table[tuple(nodes.T)]
        np.testing.assert_allclose(got, expected.astype(np.float32), rtol=2.4e-7, atol=0, err_msg=name)

        # The float32 decoder this replaced misses the near-zero values by more than 1e-3 of their size.
        relu = lambda v: np.maximum(v, np.float32(0))  # noqa: E731
        w32 = {k: v.astype(np.float32) for k, v in weights.items()}
        x32 = x.astype(np.float32)
        f32 = np.maximum(np.expm1(relu(relu(x32 @ w32["W1"] + w32["b1"]) @ w32["W2"] + w32["b2"]) @ w32["W3"]
                                  + w32["b3"]), 0)
        small = (expected > 0) & (expected < 1e-6)
        assert np.max(np.abs(f32[small] - expected[small]) / expected[small]) > 1e-3, name



# ------------------------------------------- MERL's reference lookup, transcribed


def _rotate(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """BRDFRead's ``rotate_vector``: Rodrigues' rotation of ``v (N, 3)`` about unit ``axis (3,)`` by ``angle (N,)``."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + axis * (v @ axis)[:, None] * (1.0 - c) + np.cross(axis, v) * s


def reference_lookup_index(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """BRDFRead's ``lookup_brdf_val`` up to the table read: ``std_coords_to_half_diff_coords`` (half vector,
    then ``wi`` rotated by ``-phi_h`` about the normal and ``-theta_h`` about the binormal) and the three
    index functions, for ``wi, wo (N, 3)``. Returns ``(N, 3)`` (i_h, i_d, i_p)."""
    half = wi + wo
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    theta_half = np.arccos(np.clip(half[:, 2], -1.0, 1.0))
    fi_half = np.arctan2(half[:, 1], half[:, 0])
    temp = _rotate(wi, np.array([0.0, 0.0, 1.0]), -fi_half)
    diff = _rotate(temp, np.array([0.0, 1.0, 0.0]), -theta_half)
    theta_diff = np.arccos(np.clip(diff[:, 2], -1.0, 1.0))
    fi_diff = np.arctan2(diff[:, 1], diff[:, 0])
    return np.array([reference_index(*a) for a in zip(theta_half, theta_diff, fi_diff)])


@pytest.fixture(scope="module")
def indexed_file(tmp_path_factory):
    """A MERL file whose raw values encode their own position: raw[c][i_h][i_d][i_p] = 1 + the flat index
    ``((c * 90 + i_h) * 90 + i_d) * 180 + i_p`` (at most 4.4e6: exact in float64)."""
    raw = 1.0 + np.arange(3 * 90 * 90 * 180, dtype=np.float64)
    path = tmp_path_factory.mktemp("merl") / "indexed.binary"
    with open(path, "wb") as f:
        np.array([90, 90, 180], "<i4").tofile(f)
        raw.astype("<f8").tofile(f)
    return path


def _decode(value: np.ndarray) -> np.ndarray:
    """``(..., 3)`` looked-up values of :func:`indexed_file` -> ``(..., 3, 4)`` (c, i_h, i_d, i_p), undoing
    BRDFRead's published channel scales 1/1500, 1.15/1500, 1.66/1500."""
    flat = np.rint(value / (np.array([1.0, 1.15, 1.66]) / 1500.0)).astype(np.int64) - 1
    return np.stack([flat // (90 * 90 * 180), flat // (90 * 180) % 90, flat // 180 % 90, flat % 180], axis=-1)


def test_lookup_from_directions_matches_merls_reference_code(indexed_file):
    """Direction pairs through this project's Rusinkiewicz angles and nearest lookup read the sample that
    MERL's reference code (coordinates by rotations, then index functions, all transcribed here) reads,
    in the right channel: checked on a file whose values name their own channel and indices."""
    from mi_bivariate.coordinates import half_diff_from_dirs

    merl = MERLBRDF.read(indexed_file)
    rng = np.random.default_rng(7)
    v = rng.normal(size=(2, 3000, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    v[..., 2] = np.abs(v[..., 2]) + 1e-3
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    wi, wo = v
    theta_h, _, theta_d, phi_d = half_diff_from_dirs(wi, wo)
    got = _decode(merl.eval(theta_h, theta_d, phi_d))
    want = reference_lookup_index(wi, wo)
    np.testing.assert_array_equal(got[..., 0], np.broadcast_to([0, 1, 2], (3000, 3)))
    for c in range(3):
        np.testing.assert_array_equal(got[:, c, 1:], want, err_msg=f"channel {c}")


def test_node_angles_are_merls_bin_edges(indexed_file):
    """The node angles every truth table is tabulated at are the published ones, theta_h = (i/90)^2 pi/2,
    theta_d = j/90 pi/2, phi_d = k/180 pi (written out here), each the lower edge of its bin in the
    reference indexing; tabulating a function there stores it at the node's own index."""
    theta_h, theta_d, phi_d = node_angles()
    i, k = np.arange(90), np.arange(180)
    np.testing.assert_allclose(theta_h, (i / 90.0) ** 2 * (math.pi / 2.0), rtol=1e-15, atol=0)
    np.testing.assert_allclose(theta_d, i / 90.0 * (math.pi / 2.0), rtol=1e-15, atol=0)
    np.testing.assert_allclose(phi_d, k / 180.0 * math.pi, rtol=1e-15, atol=0)
    merl = MERLBRDF.read(indexed_file)
    nodes = np.array([(a, b, c) for a in (0, 1, 30, 89) for b in (0, 2, 45, 89) for c in (0, 1, 90, 179)])
    th, td, pd = theta_h[nodes[:, 0]], theta_d[nodes[:, 1]], phi_d[nodes[:, 2]]
    np.testing.assert_array_equal([reference_index(*a) for a in zip(th, td, pd)], nodes)
    np.testing.assert_array_equal(_decode(merl.eval(th, td, pd))[:, 0, 1:], nodes)
    # Just below a node's angle is the bin below (floor indexing, not rounding); phi_d wraps to bin 179.
    below = merl.eval(th * (1.0 - 1e-6), td * (1.0 - 1e-6), pd - 1e-6)
    want = np.stack([np.maximum(nodes[:, 0] - 1, 0), np.maximum(nodes[:, 1] - 1, 0), (nodes[:, 2] - 1) % 180], -1)
    np.testing.assert_array_equal(_decode(below)[:, 0, 1:], want)
