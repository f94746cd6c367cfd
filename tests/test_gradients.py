"""Table gradients of the BSDF plugins under ``prb`` with table importance sampling.

The truth is a central finite difference of the same scalar loss (a fixed
random weighting of the image) rendered with the same seed as the gradient
pass. The image's expectation is exactly linear in the table whatever the
sampling, so the difference quotient is unbiased for any step ``h``; with
table importance sampling the perturbed table is sampled slightly
differently, which adds zero-mean noise to the quotient. The tests therefore
compare the mean over seeds of (finite difference - gradient) with its own
standard error, measured in the same run: a gradient off by a few percent
(checked below by scaling the plugin's gradient by 0.9) is many standard
errors away. Measured (8 x 8 lobe table, 24 px, 64 spp, 6 seeds): the standard error of
the mean difference is 0.04-0.6% of the gradient, the worst |mean difference| 4.3 standard errors
(1.4%), which 16 seeds brought to 0.8 (0.3%); the 10% error is 20-250 standard errors. Seeds are
fixed, so the test is deterministic. With cosine sampling (no table dependence) the quotient equals
the gradient to float32 rounding.
"""

from __future__ import annotations

import math
from typing import List, Sequence, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import sun_sky_probe

from mi_bivariate.analytic import BivariateLobe
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.geometry import SphereCamera
from mi_bivariate.render import bsdf_dict, sphere_scene_dict
from mi_bivariate.variants import ensure_variant

RES = 24
SPP = 64
SEEDS = (11, 12, 13, 14, 15, 16, 17, 18)
#: Allowed |mean(fd - grad)| in standard errors of that mean (plus a float32 floor).
Z = 5.0


@pytest.fixture(autouse=True, scope="module")
def _variant():
    ensure_variant()


def lobe_table(n: int = 8) -> BivariateBRDF:
    """A glossy bivariate lobe (closed form) on an n x n st grid, coloured."""
    lobe = BivariateLobe(diffuse=0.3, specular=1.0, width=0.3)
    theta_h = 0.5 * math.pi * np.linspace(0.0, 1.0, n) ** 2
    theta_d = 0.5 * math.pi * np.linspace(0.0, 1.0, n)
    table = lobe.eval_half_diff(theta_h[:, None], theta_d[None, :])
    return BivariateBRDF(table * np.array([1.0, 0.7, 0.4]))


def make_scene(bsdf: dict, integrator: str = "prb") -> mi.Scene:
    scene = sphere_scene_dict(bsdf, sun_sky_probe(), SphereCamera.create("orthographic", RES), normals=False)
    scene["integrator"] = {"type": integrator, "max_depth": 2, "hide_emitters": True}
    if integrator == "direct":
        scene["integrator"] = {"type": "direct", "hide_emitters": True}
    return mi.load_dict(scene)


class GradientCheck:
    """Reverse-mode gradients and same-seed central differences of ``sum(W * image)``."""

    def __init__(self, scene: mi.Scene, key: str = "sphere.bsdf.table"):
        self.scene = scene
        self.params = mi.traverse(scene)
        self.key = key
        self.params.keep(key)
        self.table0 = np.array(self.params[key], dtype=np.float32)
        rng = np.random.default_rng(1)
        self.weights = rng.uniform(0.5, 1.5, size=(RES, RES, 3)).astype(np.float32)

    def _set(self, table: np.ndarray) -> None:
        self.params[self.key] = mi.TensorXf(np.ascontiguousarray(table, dtype=np.float32))
        self.params.update()

    def loss(self, table: np.ndarray, seed: int) -> float:
        self._set(table)
        with dr.suspend_grad():
            image = np.array(mi.render(self.scene, self.params, spp=SPP, seed=seed), np.float64)[..., :3]
        return float(np.sum(image * self.weights))

    def gradient(self, seed: int) -> np.ndarray:
        """d loss / d table, the backward pass traced with ``seed`` (``seed_grad``)."""
        table = mi.TensorXf(self.table0)
        dr.enable_grad(table)
        self.params[self.key] = table
        self.params.update()
        image = mi.render(self.scene, self.params, spp=SPP, seed=seed + 1000, seed_grad=seed)
        dr.backward(dr.sum(image[..., :3] * mi.TensorXf(self.weights), axis=None))
        grad = np.array(dr.grad(table), np.float64)
        self._set(self.table0)
        return grad

    def compare(self, directions: Sequence[np.ndarray], seeds: Sequence[int] = SEEDS,
                rel_step: float = 0.2) -> List[Tuple[float, float, float]]:
        """Per direction: ``(mean gradient . d, mean central difference, standard error of their difference)``."""
        rows = [[] for _ in directions]
        for seed in seeds:
            grad = self.gradient(seed)
            for k, d in enumerate(directions):
                h = rel_step
                fd = (self.loss(self.table0 + h * d, seed) - self.loss(self.table0 - h * d, seed)) / (2.0 * h)
                rows[k].append((float(np.sum(grad * d)), fd))
        self._set(self.table0)
        out = []
        for r in rows:
            g, f = np.array(r).T
            diff = f - g
            out.append((float(g.mean()), float(f.mean()), float(diff.std(ddof=1) / math.sqrt(len(diff)))))
        return out


def entry_directions(table: np.ndarray, grad: np.ndarray, count: int = 5) -> List[np.ndarray]:
    """Unit changes (scaled by the entry's value) of ``count`` table entries spread over |gradient| ranks."""
    order = np.argsort(-np.abs(grad).ravel())
    picks = order[np.unique(np.geomspace(1, max(2, len(order) // 4), count).astype(int) - 1)][:count]
    out = []
    for i in picks:
        d = np.zeros(table.size, np.float32)
        d[i] = max(float(table.ravel()[i]), 1e-3)
        out.append(d.reshape(table.shape))
    return out


def assert_agree(results, floor_rel: float = 2e-3) -> None:
    for g, f, se in results:
        assert abs(f - g) <= Z * se + floor_rel * abs(g) + 1e-6, (g, f, se)


def _checked(sampling: str, integrator: str = "prb", plugin: str = "bivariate"):
    biv = lobe_table()
    if plugin == "bivariate":
        bsdf = {**bsdf_dict(biv), "sampling": sampling}
    else:
        bsdf = {**bsdf_dict(biv.to_merl(), interpolation="linear"), "sampling": sampling}
    return GradientCheck(make_scene(bsdf, integrator))


def test_prb_table_sampling_gradient_matches_finite_differences():
    check = _checked("table")
    directions = entry_directions(check.table0, check.gradient(SEEDS[0]), count=4)
    rng = np.random.default_rng(3)
    directions.append(rng.uniform(0.0, 1.0, check.table0.shape).astype(np.float32) * check.table0)
    results = check.compare(directions)
    assert all(abs(g) > 0 for g, _, _ in results)
    assert_agree(results)


def test_prb_cosine_sampling_gradient_is_the_difference_quotient():
    """Without table-dependent sampling the same-seed quotient is the gradient (float32 rounding)."""
    check = _checked("cosine")
    directions = entry_directions(check.table0, check.gradient(SEEDS[0]), count=3)
    for g, f, se in check.compare(directions, seeds=SEEDS[:2]):
        assert f == pytest.approx(g, rel=2e-3)


def test_check_detects_a_wrong_gradient(monkeypatch):
    """The comparison is sensitive: a gradient 10% too small fails it."""
    from mi_bivariate.plugins import plugin_classes

    cls = plugin_classes()["bivariate"]
    original = cls._eval_brdf
    monkeypatch.setattr(cls, "_eval_brdf", lambda self, wi, wo: dr.replace_grad(original(self, wi, wo),
                                                                               0.9 * original(self, wi, wo)))
    check = _checked("table")
    directions = entry_directions(check.table0, check.gradient(SEEDS[0]), count=3)
    with pytest.raises(AssertionError):
        assert_agree(check.compare(directions))


def test_prb_path_and_direct_gradients_agree():
    """``prb`` and ``path`` trace the same paths: same-seed gradients agree to rounding; ``direct``
    (a different estimator of the same image) agrees in the mean over seeds."""
    grads = {name: [_checked("table", name).gradient(s) for s in SEEDS[:4]] for name in ("prb", "path", "direct")}
    for a, b in zip(grads["prb"], grads["path"]):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4 * np.abs(a).max())
    prb, direct = np.mean(grads["prb"], axis=0), np.mean(grads["direct"], axis=0)
    assert np.sum(prb * direct) / math.sqrt(np.sum(prb * prb) * np.sum(direct * direct)) > 0.99
    assert np.sum(direct) == pytest.approx(np.sum(prb), rel=0.03)


def test_merl_prb_table_sampling_gradient_matches_finite_differences():
    check = _checked("table", plugin="merl")
    rng = np.random.default_rng(4)
    direction = rng.uniform(0.0, 1.0, check.table0.shape).astype(np.float32) * check.table0
    results = check.compare([direction], seeds=SEEDS[:4])
    assert abs(results[0][0]) > 0
    assert_agree(results)


_PRB_RENDER = """
import hashlib, sys
import drjit as dr, drjit.ast
import mitsuba as mi
from mi_bivariate.variants import ensure_variant
if sys.argv[1] == "deferred":
    ensure_variant("llvm_ad_rgb")
    from mitsuba.python.ad.integrators import prb
    assert hasattr(prb.PRBIntegrator.sample, "__wrapped__"), "prb's sample was rewritten at definition"
else:
    mi.set_variant("llvm_ad_rgb")
    from mitsuba.python.ad.integrators import prb
    assert not hasattr(prb.PRBIntegrator.sample, "__wrapped__")
assert dr.syntax is drjit.ast.syntax, "drjit.syntax was left replaced"
scene = mi.load_dict({"type": "scene", "integrator": {"type": "prb", "max_depth": 3},
                      "sensor": {"type": "perspective", "fov": 40, "to_world": mi.ScalarTransform4f().look_at(
                          origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                                 "film": {"type": "hdrfilm", "width": 16, "height": 16}},
                      "sphere": {"type": "sphere", "bsdf": {"type": "roughconductor", "alpha": 0.3}},
                      "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -2]).scale(4),
                                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.4, 0.3]}}},
                      "light": {"type": "constant"}})
params = mi.traverse(scene)
key = "floor.bsdf.reflectance.value"
dr.enable_grad(params[key])
params.update()
image = mi.render(scene, params, spp=8, seed=3)
dr.backward(dr.sum(image))
print(hashlib.sha256(image.numpy().tobytes()).hexdigest(), float(image.numpy().sum()),
      *dr.grad(params[key]).numpy().ravel().tolist())
"""


def test_prb_rewritten_on_first_call_renders_as_rewritten_at_definition():
    """:func:`ensure_variant` defers ``@dr.syntax``'s rewrite of Mitsuba's AD integrators to their first call
    (``variants.syntax_on_first_call``): a ``prb`` render, in a fresh process, is bit for bit that of a process
    that selected the variant with ``mi.set_variant`` (rewritten at definition), and its gradient the same to
    float32 rounding (the gradient's parallel sum varies in its last bit from run to run, either way)."""
    import subprocess
    import sys
    runs = {mode: subprocess.run([sys.executable, "-c", _PRB_RENDER, mode], capture_output=True, text=True,
                                 timeout=300) for mode in ("deferred", "eager")}
    for mode, run in runs.items():
        assert run.returncode == 0, f"{mode}: {run.stderr[-2000:]}"
    (deferred_image, *deferred), (eager_image, *eager) = (runs[mode].stdout.split() for mode in ("deferred", "eager"))
    assert deferred_image == eager_image
    eager = np.array(eager, float)
    assert eager[0] > 0.0 and np.all(eager[1:] > 0.0)
    np.testing.assert_allclose(np.array(deferred, float), eager, rtol=1e-6)
