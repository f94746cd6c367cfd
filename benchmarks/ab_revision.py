r"""Time the solve, the lighting matrix or ``recover`` end to end against another git revision, A/B.

    MI_BIVARIATE_DATA=../shared/data OPENBLAS_NUM_THREADS=1 python benchmarks/ab_revision.py REV [--rounds 3] \
        [--stages solve,lighting,end-to-end] [--resolution 256 --spp 256]

The inputs are ``bench_speed.py``'s (a 256 px gold-metallic-paint3 sphere under
grace_latlong_1k, recovered once here for its observations, lighting matrix and pixels);
``--resolution N`` renders the sphere at ``N x N`` pixels instead (``--spp`` samples per pixel),
as a user's photo of a few megapixels: the stages before the lighting matrix grow with it.
Each round runs, alternately, one fresh process per side (``REV`` checked out in a temporary
``git worktree``, its ``plugins/`` linked in where the package expects them; this checkout as
it is), with the side's package first on the path (checked before the rounds).

- ``solve``, ``lighting``: each process times its stage 3 times and reports the median.
- ``end-to-end``: each process is ``mi-bivariate recover IMAGE --probe PROBE --out ... --no-report``
  (``python -m mi_bivariate.cli``, the sphere fitted from the image as a user's run would),
  timed by wall clock from outside (:data:`LAUNCH`): process start, imports and shutdown included;
  its peak memory (the kernel's maximum resident set of that process) is printed with every round's time;
  ``end-to-end-report``: the same with the report (``recover``'s default).

Printed: the median over rounds per side, their ratio, and how far the sides' answers differ
(the solve's table and confidence, the lighting matrix's rows, the recovered table), then every
round's time. A shared, noisy machine slows both sides alike within a round, which is why the
sides alternate; which side goes first alternates between rounds (the second process of a round
can run faster: measured up to 1.2x on the unchanged solve in 2 rounds).
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: What a child process runs: ``python -c CHILD STAGE INPUTS OUTPUT`` with the side's package first on the path.
CHILD = r"""
import json, pickle, sys, time
import numpy as np
stage, inputs, output = sys.argv[1:4]
from mi_bivariate.variants import ensure_variant
ensure_variant()
times = []
if stage == "solve":
    from mi_bivariate import solve
    from mi_bivariate.basis_prior import default_basis_prior
    from mi_bivariate.prior import default_prior
    from mi_bivariate.solve import solve_stages
    from mi_bivariate.threads import blas_threads
    z = np.load(inputs + ".npz")
    with blas_threads():
        data = solve.prepare_data_term(z["L"], z["I"])
        for _ in range(3):
            t = time.perf_counter()
            r = solve_stages(data, default_prior(), None, default_basis_prior())
            answer = np.concatenate([r.table.ravel(), r.measured.ravel(), r.posterior_std.ravel()])
            times.append(time.perf_counter() - t)
else:
    from mi_bivariate import lighting, probes
    obs = pickle.load(open(inputs + ".obs", "rb"))
    probe = probes.shared_probe("grace_latlong_1k")
    lighting.lighting_matrix(obs, probe)
    for _ in range(3):
        t = time.perf_counter()
        L = lighting.lighting_matrix(obs, probe)
        times.append(time.perf_counter() - t)
    answer = L[::7]
np.save(output, answer)
print(json.dumps(float(np.median(times))))
"""


def _check_side(root: Path, cwd: str) -> None:
    """Exit unless a process run as the rounds run it (``root`` first on the path, in ``cwd``) imports the
    package and its plugins from ``root``."""
    code = "import mi_bivariate, mi_bivariate.plugins as p; print(mi_bivariate.__file__); print(p.__file__)"
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(root)),
                         capture_output=True, text=True, cwd=cwd)
    files = out.stdout.split()
    if out.returncode or len(files) != 2 or not all(f.startswith(str(root)) for f in files):
        sys.exit(f"the side at {root} imports {files or out.stderr[-2000:]}, not its own package")


def _run_side(stage: str, side: str, root: Path, tmp: str, inputs: str) -> float:
    """One fresh process of ``stage`` with ``root``'s package: its time (s); its answer goes to ``tmp/side.npy``."""
    env = dict(os.environ, PYTHONPATH=str(root))
    if not stage.startswith("end-to-end"):
        out = subprocess.run([sys.executable, "-c", CHILD, stage, inputs, f"{tmp}/{side}.npy"],
                             env=env, capture_output=True, text=True, cwd=tmp)
        if out.returncode:
            sys.exit(f"{side} side failed:\n{out.stderr[-3000:]}")
        return float(json.loads(out.stdout.strip().splitlines()[-1]))
    table = Path(tmp) / f"{side}_table.npz"
    table.unlink(missing_ok=True)
    for name in (table.with_suffix(".exr"), table.with_name(table.stem + "_report.png")):
        name.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "mi_bivariate.cli", "recover", inputs + "_sphere.exr", "--probe",
           inputs + "_probe.exr", "--out", str(table)]
    if stage != "end-to-end-report":
        cmd.append("--no-report")
    out = subprocess.run([sys.executable, "-c", LAUNCH, *cmd], env=env, capture_output=True, text=True, cwd=tmp)
    if out.returncode:
        sys.exit(f"{side} side failed:\n{out.stderr[-3000:]}")
    wall, peak_kb = out.stderr.strip().splitlines()[-1].split()[1::2]
    PEAK_MB.setdefault(side, []).append(int(peak_kb) / 1024.0)
    np.save(f"{tmp}/{side}.npy", np.load(table)["table"])
    return float(wall)


#: Runs an end-to-end command from a small process of its own, which times it and reads its peak memory:
#: a child forked from this benchmark (its renders make it large) would count the benchmark's memory as
#: its own peak, since the kernel's maximum resident set survives ``exec``.
LAUNCH = r"""
import resource, subprocess, sys, time
t0 = time.perf_counter()
out = subprocess.run(sys.argv[1:], capture_output=True, text=True)
wall = time.perf_counter() - t0
sys.stderr.write(out.stdout + out.stderr)
sys.stderr.write(f"\nwall {wall} peak-kb {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}\n")
sys.exit(out.returncode)
"""
#: Each side's end-to-end processes' peak memory (MB), in the order run.
PEAK_MB: dict = {}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--stages", default="solve,lighting",
                        help="any of solve, lighting, end-to-end, end-to-end-report")
    parser.add_argument("--resolution", type=int, default=256, help="the sphere photo's side (pixels)")
    parser.add_argument("--spp", type=int, default=256, help="its samples per pixel")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_speed

    from mi_bivariate.images import write_exr
    from mi_bivariate.recover import recover
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        # A run killed before its cleanup leaves a registered worktree whose folder is gone.
        subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], check=False)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(tree), args.revision],
                       check=True)
        try:
            # The editable install maps mi_bivariate.plugins to the checkout's plugins/ folder: the
            # revision's own, linked in, or its side would load this checkout's plugins.
            (tree / "mi_bivariate" / "plugins").symlink_to(Path("..") / "plugins")
            for root in (tree, ROOT):  # bytecode as an install has it, on both sides alike
                subprocess.run([sys.executable, "-m", "compileall", "-q", str(root / "mi_bivariate"),
                                str(root / "plugins")], check=True, capture_output=True)
                _check_side(root, tmp)
            _, probe, shot = bench_speed.load_inputs(resolution=args.resolution, spp=args.spp)
            rec = recover(shot.image, probe, shot.geometry)
            inputs = str(Path(tmp) / "inputs")
            np.savez(inputs + ".npz", L=rec.lighting_matrix, I=rec.observations.values)
            with open(inputs + ".obs", "wb") as fh:
                pickle.dump(rec.observations, fh)
            write_exr(inputs + "_sphere.exr", shot.image)
            probe.save_exr(inputs + "_probe.exr")
            print(f"A/B against {args.revision}; {args.rounds} rounds; a {args.resolution} px sphere "
                  f"({args.spp} spp); load average "
                  f"{', '.join(f'{v:.1f}' for v in os.getloadavg())}\n")
            print(f"| stage | {args.revision} (s) | this checkout (s) | ratio | max answer difference / max |")
            print("|---|---:|---:|---:|---:|")
            details = []  # every round's time, printed under the table
            for stage in args.stages.split(","):
                times = {"rev": [], "here": []}
                for r in range(args.rounds):
                    sides = (("rev", tree), ("here", ROOT))
                    for side, root in sides if r % 2 == 0 else sides[::-1]:  # who goes first alternates too
                        times[side].append(_run_side(stage, side, root, tmp, inputs))
                a, b = np.load(f"{tmp}/rev.npy"), np.load(f"{tmp}/here.npy")
                diff = float(np.abs(a - b).max() / np.abs(a).max()) if a.shape == b.shape else float("nan")
                rev, here = np.median(times["rev"]), np.median(times["here"])
                details.append(f"{stage}: {args.revision} {sorted(round(v, 3) for v in times['rev'])}, "
                               f"this checkout {sorted(round(v, 3) for v in times['here'])}")
                if stage.startswith("end-to-end"):
                    details.append(f"{stage}, peak memory (MB): {args.revision} "
                                   f"{sorted(round(v) for v in PEAK_MB.pop('rev'))}, this checkout "
                                   f"{sorted(round(v) for v in PEAK_MB.pop('here'))}")
                print(f"| {stage} | {rev:.3f} | {here:.3f} | {rev / here:.2f}x | {diff:.1e} |", flush=True)
            print("\nEvery round, sorted (s):\n" + "\n".join(f"- {line}" for line in details))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


if __name__ == "__main__":
    main()
