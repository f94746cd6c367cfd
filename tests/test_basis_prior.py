"""The data-driven table prior: learning, prediction at unobserved nodes, files, leave-one-out."""

from __future__ import annotations

import numpy as np
import pytest

from mi_bivariate.basis_prior import BasisPrior
from mi_bivariate.errors import InputError

N_T, N_S = 8, 7


def _family(n: int, seed: int) -> dict:
    """Tables from a known 2-parameter family: a lobe of varying width on a Fresnel-like rise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, N_T)[:, None]
    s = np.linspace(0, 1, N_S)[None, :]
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
