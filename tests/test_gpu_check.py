"""The GPU check's scripts (``scripts/gpu_check.sh``, ``gpu_site.sh``, ``gpu_compare.py``) stay runnable
where no GPU is: the shell scripts parse, and the comparison finds equal tables equal and a changed
table changed."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_bivariate import analytic, probes, render
from mi_bivariate.images import write_exr

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script", ["gpu_check.sh", "gpu_site.sh"])
def test_gpu_shell_scripts_parse(script):
    out = subprocess.run(["bash", "-n", str(ROOT / "scripts" / script)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def _largest(stdout: str) -> float:
    found = re.search(r"largest \|cuda - llvm\| ([0-9.e+-]+) of the largest entry", stdout)
    assert found, stdout
    return float(found.group(1))


def test_gpu_compare_finds_equal_tables_equal_and_a_changed_one_changed(tmp_path):
    data = np.ones((16, 32, 3), dtype=np.float32)
    data[2:4, 5:7] = 20.0  # a small bright source: the lighting varies over the sphere
    probe = probes.Probe(data, source="synthetic")
    shot = render.render_sphere(render.bsdf_dict(analytic.to_merl(analytic.Lambertian(0.5))), probe,
                                resolution=40, spp=16, seed=0)
    write_exr(tmp_path / "sphere.exr", shot.image)
    probe.save_exr(tmp_path / "probe.exr")
    table = tmp_path / "table_cuda.npz"
    subprocess.run([sys.executable, "-m", "mi_bivariate", "recover", str(tmp_path / "sphere.exr"), "--probe",
                    str(tmp_path / "probe.exr"), "--out", str(table), "--no-report"],
                   check=True, capture_output=True, timeout=300)
    compare = [sys.executable, str(ROOT / "scripts" / "gpu_compare.py"), str(table), str(tmp_path)]
    same = subprocess.run(compare, capture_output=True, text=True, timeout=300)
    assert same.returncode == 0, same.stderr[-2000:]
    assert _largest(same.stdout) < 1e-4  # the same backend: float32 accumulation order at most

    with np.load(table) as arrays:
        changed = {k: arrays[k] for k in arrays.files}
    changed["table"] = changed["table"] * 1.1
    np.savez(tmp_path / "changed.npz", **changed)
    compare[2] = str(tmp_path / "changed.npz")
    differ = subprocess.run(compare, capture_output=True, text=True, timeout=300)
    assert differ.returncode == 0, differ.stderr[-2000:]
    assert _largest(differ.stdout) == pytest.approx(0.1, rel=1e-3)
