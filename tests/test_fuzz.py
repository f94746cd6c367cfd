"""Seeded fuzzing of the file readers: truncations and byte flips of small valid files.

Every outcome must be a successful load of sane data or an :class:`InputError`:
never another exception type, never a crash. A few hundred cases in all.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from mi_bivariate import images
from mi_bivariate.bivariate import BivariateBRDF
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERL_SHAPE, MERLBRDF
from mi_bivariate.probes import Probe

N_CASES = 60  # per reader


def mutations(data: bytes, rng: np.random.Generator, n: int):
    """Truncations (anywhere, biased to the header) and 1-8 random byte flips."""
    for k in range(n):
        if k % 2 == 0:
            cut = int(rng.integers(0, min(len(data), 512))) if k % 4 == 0 else int(rng.integers(0, len(data)))
            yield f"truncate@{cut}", data[:cut]
        else:
            buf = bytearray(data)
            # Half the flips land in the first 256 bytes: headers are where parsers break.
            span = min(len(buf), 256) if k % 4 == 1 else len(buf)
            for pos in rng.integers(0, span, int(rng.integers(1, 9))):
                buf[pos] ^= int(rng.integers(1, 256))
            yield "flip", bytes(buf)


def fuzz(tmp_path: Path, name: str, original: bytes, load: Callable, check: Callable, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    outcomes = {"loaded": 0, "InputError": 0}
    path = tmp_path / name
    for what, data in mutations(original, rng, N_CASES):
        path.write_bytes(data)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = load(path)
        except InputError as exc:
            assert str(exc).startswith(str(path)), f"{what}: message does not name the file: {exc}"
            assert "\n" not in str(exc), f"{what}: multi-line message: {exc!r}"
            outcomes["InputError"] += 1
            continue
        except Exception as exc:  # noqa: BLE001 -- the point of the test
            pytest.fail(f"{name} {what}: {type(exc).__name__}: {exc}")
        check(result)
        outcomes["loaded"] += 1
    assert outcomes["InputError"] > 0
    return outcomes


def _image(h: int = 6, w: int = 8) -> np.ndarray:
    return np.random.default_rng(0).uniform(0.0, 4.0, (h, w, 3)).astype(np.float32)


def _check_image(data: np.ndarray) -> None:
    # load_image leaves NaN/Inf/negatives to capture (which counts and drops them).
    assert data.dtype == np.float32 and data.ndim == 3 and data.shape[2] == 3 and data.size > 0


def _check_probe(probe: Probe) -> None:
    assert np.all(np.isfinite(probe.data)) and np.all(probe.data >= 0.0)


def fuzz_images(folder: str, suffix: str) -> None:
    """Fuzz ``images.load_image`` and ``Probe.load`` on one format (run in a child process)."""
    import mitsuba as mi

    from mi_bivariate.variants import ensure_variant

    ensure_variant("llvm_ad_rgb")
    folder = Path(folder)
    valid = folder / f"valid{suffix}"
    mi.Bitmap(_image()).write(str(valid))
    original = valid.read_bytes()
    fuzz(folder, f"image{suffix}", original, images.load_image, _check_image, seed=1)
    fuzz(folder, f"probe{suffix}", original, Probe.load, _check_probe, seed=2)


@pytest.mark.parametrize("suffix", [
    ".exr",
    ".hdr",
])
def test_fuzz_load_image_and_probe(tmp_path, suffix):
    """In a child process: a reader that corrupts memory must fail the test, not kill pytest.

    glibc's malloc checks (where available) make heap corruption fail at the next free.
    """
    env = dict(os.environ, MALLOC_CHECK_="3", PYTHONFAULTHANDLER="1")
    debug = Path("/usr/lib/x86_64-linux-gnu/libc_malloc_debug.so.0")
    if debug.is_file():
        env["LD_PRELOAD"] = f"{debug} {env['LD_PRELOAD']}" if env.get("LD_PRELOAD") else str(debug)
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import test_fuzz; "
            f"test_fuzz.fuzz_images({str(tmp_path)!r}, {suffix!r}); print('fuzz ok')")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "fuzz ok" in proc.stdout, \
        f"child exited with {proc.returncode}:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"


def test_fuzz_merl_read(tmp_path):
    valid = tmp_path / "valid.binary"
    table = np.random.default_rng(3).uniform(0.0, 1.0, MERL_SHAPE + (3,))
    MERLBRDF(table, name="noise").write(valid)
    original = valid.read_bytes()

    def check(merl: MERLBRDF) -> None:
        values = merl.table[np.isfinite(merl.table)]
        assert merl.table.shape == MERL_SHAPE + (3,)
        assert not np.isinf(merl.table).any() and np.all(values >= 0.0)

    # MERL files are 33 MB: fewer cases, flips spread over the header and the body.
    global N_CASES
    saved, N_CASES = N_CASES, 16
    try:
        fuzz(tmp_path, "fuzzed.binary", original, MERLBRDF.read, check, seed=4)
    finally:
        N_CASES = saved


def test_fuzz_bivariate_load(tmp_path):
    valid = tmp_path / "valid.npz"
    BivariateBRDF(np.random.default_rng(5).uniform(0.0, 2.0, (6, 5, 3)).astype(np.float32),
                  provenance={"test": "fuzz"}).save(valid)

    def check(biv: BivariateBRDF) -> None:
        assert np.all(np.isfinite(biv.table)) and np.all(biv.table >= 0.0)

    fuzz(tmp_path, "fuzzed.npz", valid.read_bytes(), BivariateBRDF.load, check, seed=6)


def test_fuzz_readers_script_subset(tmp_path):
    """A seeded subset of ``scripts/fuzz_readers.py`` (every reader, including RGBE bytes named
    .exr/.pfm and PNG bytes named .exr): no crash, hang, other exception or bad message.
    The full run (>= 10,000 files) is reported in the issue's notes."""
    script = Path(__file__).resolve().parent.parent / "scripts" / "fuzz_readers.py"
    counts = tmp_path / "counts.json"
    proc = subprocess.run([sys.executable, str(script), "--cases", "300", "--seed", "11", "--timeout", "60",
                           "--keep", str(tmp_path / "failures"), "--json", str(counts)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    total = json.loads(counts.read_text())["total"]
    assert total["crash"] == total["hang"] == total["other"] == total["bad_message"] == 0, total
    assert total["ok"] > 0 and total["input_error"] > 0 and sum(total.values()) >= 300, total
