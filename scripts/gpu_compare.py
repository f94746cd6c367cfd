"""Compare a table recovered under ``cuda_ad_rgb`` with the one ``llvm_ad_rgb`` recovers from the same files.

    python scripts/gpu_compare.py CUDA_TABLE.npz INPUT_DIR [--out LLVM_TABLE.npz]

``INPUT_DIR`` holds the ``sphere.exr`` and ``probe.exr`` that ``scripts/gpu_check.sh`` recovered on the
GPU (``GPU_RECOVER_INPUT``). This script recovers the same image here with ``llvm_ad_rgb`` (the same
command line, ``--no-report``) and prints the largest table difference, relative to the largest entry,
and the relative RMS difference over the nodes: the two backends share the code and the seeds, so they
differ only by float32 rounding in the lighting matrix's kernels (its sums run in another order).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cuda_table", type=Path)
    parser.add_argument("input_dir", type=Path)
    parser.add_argument("--out", type=Path, help="keep the llvm_ad_rgb table here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "table_llvm.npz"
        env = dict(os.environ, MI_BIVARIATE_VARIANT="llvm_ad_rgb")
        subprocess.run([sys.executable, "-m", "mi_bivariate", "recover", str(args.input_dir / "sphere.exr"),
                        "--probe", str(args.input_dir / "probe.exr"), "--out", str(out), "--no-report"],
                       check=True, env=env, stdout=subprocess.DEVNULL)
        llvm = np.load(out)["table"].astype(np.float64)
    cuda = np.load(args.cuda_table)["table"].astype(np.float64)
    if cuda.shape != llvm.shape:
        sys.exit(f"gpu_compare: tables differ in shape: cuda {cuda.shape}, llvm {llvm.shape}")
    diff = np.abs(cuda - llvm)
    print(f"table {cuda.shape}: largest |cuda - llvm| {diff.max() / np.abs(llvm).max():.2e} of the largest entry; "
          f"relative RMS {np.sqrt(np.mean(diff ** 2) / np.mean(llvm ** 2)):.2e}; "
          f"median node |cuda - llvm| / llvm {np.median(diff / np.maximum(np.abs(llvm), 1e-12)):.2e}")


if __name__ == "__main__":
    main()
