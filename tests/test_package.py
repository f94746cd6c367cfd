"""The package's public surface: every submodule resolves lazily, and the README's Python runs."""

from __future__ import annotations

import importlib
import pkgutil
import re
from pathlib import Path

import numpy as np

import mi_bivariate as mb

ROOT = Path(__file__).resolve().parents[1]


def test_every_module_is_reachable_as_an_attribute():
    names = {m.name for m in pkgutil.iter_modules(mb.__path__) if not m.name.startswith("_")} - {"plugins"}
    assert names <= set(mb._SUBMODULES), sorted(names - set(mb._SUBMODULES))
    for name in mb._SUBMODULES:
        assert getattr(mb, name) is importlib.import_module(f"mi_bivariate.{name}")


def test_readme_names_resolve():
    """Every ``mb.module.name`` the README shows exists."""
    text = (ROOT / "README.md").read_text()
    for module, name in set(re.findall(r"\bmb\.(\w+)\.(\w+)", text)):
        assert hasattr(getattr(mb, module), name), f"mb.{module}.{name}"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    """The README's first Python block, on a small rendered sphere (file names swapped for real ones)."""
    from mi_bivariate import analytic, render
    from mi_bivariate.demo import synthetic_environment
    from mi_bivariate.images import write_exr
    from mi_bivariate.probes import Probe
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    probe = Probe(synthetic_environment(seed=1))
    probe.save_exr(tmp_path / "probe.exr")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.4, 0.3])))
    shot = render.render_sphere(render.bsdf_dict(merl), probe, resolution=64, spp=16, seed=0)
    write_exr(tmp_path / "photo.exr", shot.image)
    block = re.search(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S).group(1)
    block = block.replace("mb.recover.recover(image, probe, fit.geometry)",
                          "mb.recover.recover(image, probe, fit.geometry, n_normals=500, n_dirs=2000)")
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "README.md", "exec"), {})
    assert (tmp_path / "brdf.npz").is_file() and (tmp_path / "brdf.binary").is_file()
