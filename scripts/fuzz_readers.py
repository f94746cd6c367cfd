#!/usr/bin/env python
"""Seeded fuzzing of the toolkit's file readers, crashes caught as signals.

Mutates small valid files (truncations, byte flips biased to the header,
insertions, deletions, spliced chunks, extreme integers) and loads each with
the reader a user's file would meet: ``images.load_image`` and ``Probe.load``
(EXR, Radiance HDR, PFM, and the content/extension confusions RGBE named
``.exr``/``.pfm``, EXR named ``.hdr``, PNG named ``.exr``),
``BivariateBRDF.load`` and ``Prior.load`` (npz) and ``MERLBRDF.read``.

The cases run in child processes, in batches; a child that dies by a signal
(SIGSEGV, SIGABRT from glibc's heap checks) is a crash of the case it had
started, one that stops making progress for ``--timeout`` seconds is a hang.
Outcomes per case:

- ``ok``: loaded, and the data is sane (shape, dtype; probes finite, >= 0);
- ``input_error``: a one-line :class:`InputError` starting with the file name;
- ``bad_message``: an InputError with several lines or without the file name;
- ``other``: any other exception (its type is reported), or insane data;
- ``crash`` / ``hang``.

Usage::

    python scripts/fuzz_readers.py --cases 10000 --seed 0 [--keep DIR] [--readers exr hdr ...]

Prints the counts per reader and in total; exit status 1 if anything but
``ok`` and ``input_error`` occurred. The files of failing cases are written to
``--keep`` (default: a temporary folder that is reported).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import numpy as np

#: reader -> (share of the cases, file name the mutated bytes get, seed builder name, loader name)
READERS: Dict[str, Tuple[float, str, str, str]] = {
    "exr": (0.22, "case.exr", "exr", "image_or_probe"),
    "hdr": (0.13, "case.hdr", "rgbe", "image_or_probe"),
    "rgbe-as-exr": (0.10, "case.exr", "rgbe", "image_or_probe"),
    "rgbe-as-pfm": (0.08, "case.pfm", "rgbe", "image_or_probe"),
    "pfm": (0.13, "case.pfm", "pfm", "image_or_probe"),
    "exr-as-hdr": (0.05, "case.hdr", "exr", "image_or_probe"),
    "png-as-exr": (0.03, "case.exr", "png", "image_or_probe"),
    "npz": (0.15, "case.npz", "npz", "bivariate"),
    "prior": (0.07, "case.npz", "prior", "prior"),
    "merl": (0.04, "case.binary", "merl", "merl"),
}
OUTCOMES = ("ok", "input_error", "bad_message", "other", "crash", "hang")


# ----------------------------------------------------------------- seed files

def _seed_files(folder: Path) -> Dict[str, List[bytes]]:
    """Small valid files of every kind (several variants each), written by the toolkit or by the libraries."""
    import OpenEXR

    import mitsuba as mi

    from mi_bivariate import images
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.merl import MERL_SHAPE, MERLBRDF
    from mi_bivariate.prior import default_prior

    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(12345)
    img = rng.uniform(0.0, 4.0, (12, 20, 3)).astype(np.float32)
    seeds: Dict[str, List[bytes]] = {k: [] for k in ("exr", "rgbe", "pfm", "png", "npz", "prior", "merl")}

    def grab(path: Path) -> bytes:
        return path.read_bytes()

    seeds["exr"].append(grab(images.write_exr(folder / "a.exr", img)))
    for comp in (OpenEXR.NO_COMPRESSION, OpenEXR.RLE_COMPRESSION, OpenEXR.PIZ_COMPRESSION,
                 OpenEXR.PXR24_COMPRESSION, OpenEXR.B44_COMPRESSION):
        OpenEXR.File({"compression": comp, "type": OpenEXR.scanlineimage},
                     {"RGBA": np.concatenate([img, np.ones_like(img[..., :1])], -1).astype(np.float16)}
                     ).write(str(folder / "b.exr"))
        seeds["exr"].append(grab(folder / "b.exr"))
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize = 8, 8
    OpenEXR.File({"compression": OpenEXR.ZIPS_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": tiles},
                 {"Y": img[..., 0].copy()}).write(str(folder / "c.exr"))
    seeds["exr"].append(grab(folder / "c.exr"))
    mi.Bitmap(img).write(str(folder / "d.hdr"))                      # run-length encoded scanlines
    seeds["rgbe"].append(grab(folder / "d.hdr"))
    mi.Bitmap(img[:, :6].copy()).write(str(folder / "e.hdr"))         # too narrow for RLE: flat pixels
    seeds["rgbe"].append(grab(folder / "e.hdr"))
    mi.Bitmap(img).write(str(folder / "f.pfm"))
    seeds["pfm"].append(grab(folder / "f.pfm"))
    (folder / "g.pfm").write_bytes(b"Pf\n20 12\n-1.0\n" + img[::-1, :, 0].astype("<f4").tobytes())
    seeds["pfm"].append(grab(folder / "g.pfm"))
    images.write_png(folder / "h.png", img)
    seeds["png"].append(grab(folder / "h.png"))
    BivariateBRDF(rng.uniform(0.0, 2.0, (6, 5, 3)).astype(np.float32), provenance={"fuzz": 1}).save(folder / "i.npz")
    seeds["npz"].append(grab(folder / "i.npz"))
    with open(folder / "j.npz", "wb") as f:                           # uncompressed members
        z = np.load(folder / "i.npz")
        np.savez(f, **{k: z[k] for k in z.files})
    seeds["npz"].append(grab(folder / "j.npz"))
    default_prior().resampled(6, 6).save(folder / "k.npz")
    seeds["prior"].append(grab(folder / "k.npz"))
    MERLBRDF(rng.uniform(0.0, 1.0, MERL_SHAPE + (3,)), name="noise").write(folder / "l.binary")
    seeds["merl"].append(grab(folder / "l.binary"))
    return seeds


# ------------------------------------------------------------------ mutations

def mutate(data: bytes, rng: np.random.Generator) -> Tuple[str, bytes]:
    """One random mutation of ``data`` (biased to the first 512 bytes, where headers live)."""
    n = len(data)

    def pos(head_bias: bool = True) -> int:
        if head_bias and rng.random() < 0.6:
            return int(rng.integers(0, max(1, min(n, 512))))
        return int(rng.integers(0, max(1, n)))

    kind = int(rng.integers(0, 7))
    buf = bytearray(data)
    if kind == 0:
        cut = pos()
        return f"truncate@{cut}", bytes(buf[:cut])
    if kind == 1:
        for p in [pos() for _ in range(int(rng.integers(1, 9)))]:
            if p < len(buf):
                buf[p] ^= int(rng.integers(1, 256))
        return "flip", bytes(buf)
    if kind == 2:
        p = pos()
        return f"insert@{p}", bytes(buf[:p] + rng.bytes(int(rng.integers(1, 33))) + buf[p:])
    if kind == 3:
        p = pos()
        return f"delete@{p}", bytes(buf[:p] + buf[p + int(rng.integers(1, 65)):])
    if kind == 4:                                                  # extreme little/big-endian integers
        p = pos()
        value = [b"\xff\xff\xff\xff", b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80", b"\x00\x00\x00\x00",
                 b"\x7f\xff\xff\xff", b"\x00\x00\x01\x00"][int(rng.integers(0, 6))]
        buf[p:p + 4] = value
        return f"int@{p}", bytes(buf)
    if kind == 5:                                                  # copy a chunk over another place
        a, b = pos(False), pos()
        size = int(rng.integers(1, 257))
        buf[b:b + size] = data[a:a + size]
        return f"splice@{a}->{b}", bytes(buf)
    # ASCII digits in text headers (RGBE/PFM resolutions, sizes)
    digits = [i for i in range(min(n, 256)) if 48 <= buf[i] <= 57]
    if digits:
        p = digits[int(rng.integers(0, len(digits)))]
        buf[p:p + 1] = str(int(rng.integers(0, 10))).encode() * int(rng.integers(1, 12))
    return "digits", bytes(buf)


def case_bytes(seeds: Dict[str, List[bytes]], reader: str, seed: int, index: int) -> Tuple[str, bytes]:
    """The mutated file of case ``index`` of ``reader`` (deterministic in ``seed``)."""
    rng = np.random.default_rng([seed, list(READERS).index(reader), index])
    variants = seeds[READERS[reader][2]]
    data = variants[int(rng.integers(0, len(variants)))]
    what, out = mutate(data, rng)
    if rng.random() < 0.2:                                         # a second mutation on top
        what2, out = mutate(out, rng)
        what = f"{what}+{what2}"
    return what, out


# --------------------------------------------------------------------- child

def _loader(name: str, index: int) -> Callable[[Path], None]:
    from mi_bivariate import images
    from mi_bivariate.bivariate import BivariateBRDF
    from mi_bivariate.merl import MERL_SHAPE, MERLBRDF
    from mi_bivariate.prior import Prior
    from mi_bivariate.probes import Probe

    def image_or_probe(path: Path) -> None:
        if index % 2:
            probe = Probe.load(path)
            assert np.all(np.isfinite(probe.data)) and np.all(probe.data >= 0.0), "probe with bad values"
        else:
            data = images.load_image(path)
            assert data.dtype == np.float32 and data.ndim == 3 and data.shape[2] == 3 and data.size > 0

    def bivariate(path: Path) -> None:
        biv = BivariateBRDF.load(path)
        assert np.all(np.isfinite(biv.table)) and np.all(biv.table >= 0.0)

    def prior(path: Path) -> None:
        p = Prior.load(path)
        assert p.n_t >= 2 and p.n_s >= 2

    def merl(path: Path) -> None:
        m = MERLBRDF.read(path)
        assert m.table.shape == MERL_SHAPE + (3,) and not np.isinf(m.table).any()

    return {"image_or_probe": image_or_probe, "bivariate": bivariate, "prior": prior, "merl": merl}[name]


def child(seed_dir: str, reader: str, seed: int, start: int, stop: int, work: str) -> None:
    """Run cases ``start..stop-1`` of ``reader``: prints ``start I`` before and ``done I OUTCOME`` after each."""
    import mitsuba as mi

    from mi_bivariate.errors import InputError

    mi.set_variant("llvm_ad_rgb")
    seeds = json.loads(Path(seed_dir, "index.json").read_text())
    seeds = {k: [Path(seed_dir, f).read_bytes() for f in v] for k, v in seeds.items()}
    path = Path(work) / READERS[reader][1]
    for index in range(start, stop):
        print(f"start {index}", flush=True)
        _, data = case_bytes(seeds, reader, seed, index)
        path.write_bytes(data)
        load = _loader(READERS[reader][3], index)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                load(path)
            outcome = "ok"
        except InputError as exc:
            msg = str(exc)
            outcome = "input_error" if "\n" not in msg and msg.startswith(str(path)) else "bad_message"
            if outcome == "bad_message":
                outcome += ":" + json.dumps(msg[:300])
        except AssertionError as exc:
            outcome = f"other:insane data {exc}"
        except Exception as exc:  # noqa: BLE001 -- the point of the fuzzer
            outcome = f"other:{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
            traceback.print_exc(limit=3, file=sys.stderr)
        print(f"done {index} {outcome}", flush=True)


# -------------------------------------------------------------------- parent

def _child_env() -> dict:
    env = dict(os.environ, MALLOC_CHECK_="3", PYTHONFAULTHANDLER="1")
    debug = Path("/usr/lib/x86_64-linux-gnu/libc_malloc_debug.so.0")
    if debug.is_file():
        env["LD_PRELOAD"] = f"{debug} {env['LD_PRELOAD']}" if env.get("LD_PRELOAD") else str(debug)
    return env


def run_reader(reader: str, n: int, seed: int, seed_dir: Path, work: Path, timeout: float,
               batch: int, on_case: Callable[[str, int, str], None]) -> None:
    """Run ``n`` cases of ``reader`` in child processes, restarting after crashes and hangs."""
    next_index = 0
    env = _child_env()
    while next_index < n:
        stop = min(n, next_index + batch)
        cmd = [sys.executable, os.path.abspath(__file__), "--child", str(seed_dir), reader, str(seed),
               str(next_index), str(stop), str(work)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True,
                                bufsize=1)
        started = None
        last = time.monotonic()
        startup = timeout + 30.0                                  # imports and the first JIT compile
        buf = ""
        while True:
            ready, _, _ = select.select([proc.stdout], [], [], 0.5)
            if ready:
                chunk = os.read(proc.stdout.fileno(), 65536).decode()
                if not chunk:                                      # EOF: the child ended
                    break
                buf += chunk
                *lines, buf = buf.split("\n")
                for line in lines:
                    word, _, rest = line.partition(" ")
                    if word == "start":
                        started, last = int(rest), time.monotonic()
                    elif word == "done":
                        index, _, outcome = rest.partition(" ")
                        on_case(reader, int(index), outcome)
                        next_index, started = int(index) + 1, None
                        last = time.monotonic()
            limit = timeout if started is not None else startup
            if time.monotonic() - last > limit:
                proc.kill()
                proc.wait()
                if started is not None:
                    on_case(reader, started, "hang")
                    next_index = started + 1
                else:
                    raise RuntimeError(f"{reader}: the child made no progress for {limit:.0f} s")
                break
        rc = proc.wait()
        if rc != 0 and started is not None and next_index <= started:
            name = signal.Signals(-rc).name if rc < 0 else f"exit {rc}"
            on_case(reader, started, f"crash:{name}")
            next_index = started + 1
        elif rc != 0 and next_index < stop and started is None:
            raise RuntimeError(f"{reader}: the child failed before its first case (status {rc})")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10000, help="total number of mutated files")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--readers", nargs="+", default=list(READERS), choices=list(READERS))
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds without progress that make a hang")
    parser.add_argument("--batch", type=int, default=2000, help="cases per child process")
    parser.add_argument("--keep", default=None, help="folder for the files of failing cases")
    parser.add_argument("--json", default=None, help="also write the counts as JSON here")
    args = parser.parse_args(argv)

    shares = {r: READERS[r][0] for r in args.readers}
    total_share = sum(shares.values())
    counts_per = {r: max(1, round(args.cases * s / total_share)) for r, s in shares.items()}
    with tempfile.TemporaryDirectory(prefix="fuzz-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None) as tmp:
        tmp = Path(tmp)
        seed_dir, work = tmp / "seeds", tmp / "work"
        seed_dir.mkdir()
        work.mkdir()
        seeds = _seed_files(seed_dir)
        index = {}
        for kind, variants in seeds.items():
            index[kind] = []
            for k, data in enumerate(variants):
                (seed_dir / f"{kind}{k}.bin").write_bytes(data)
                index[kind].append(f"{kind}{k}.bin")
        (seed_dir / "index.json").write_text(json.dumps(index))
        keep = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fuzz-failures-"))
        table = {r: dict.fromkeys(OUTCOMES, 0) for r in args.readers}
        failures: List[str] = []
        t0 = time.monotonic()

        def on_case(reader: str, index: int, outcome: str) -> None:
            kind = outcome.split(":", 1)[0]
            table[reader][kind] += 1
            if kind not in ("ok", "input_error"):
                what, data = case_bytes(seeds, reader, args.seed, index)
                name = f"{reader}-{index}{Path(READERS[reader][1]).suffix}"
                (keep / name).write_bytes(data)
                failures.append(f"{reader} #{index} ({what}): {outcome} -> {keep / name}")

        for reader in args.readers:
            run_reader(reader, counts_per[reader], args.seed, seed_dir, work, args.timeout, args.batch, on_case)
        elapsed = time.monotonic() - t0

    width = max(len(r) for r in table) + 2
    print(f"{'reader':<{width}}" + "".join(f"{o:>13}" for o in OUTCOMES))
    totals = dict.fromkeys(OUTCOMES, 0)
    for reader, row in table.items():
        print(f"{reader:<{width}}" + "".join(f"{row[o]:>13}" for o in OUTCOMES))
        for o in OUTCOMES:
            totals[o] += row[o]
    print(f"{'total':<{width}}" + "".join(f"{totals[o]:>13}" for o in OUTCOMES))
    print(f"{sum(totals.values())} cases, seed {args.seed}, {elapsed:.0f} s")
    for line in failures[:50]:
        print("FAIL", line)
    if args.json:
        Path(args.json).write_text(json.dumps({"seed": args.seed, "per_reader": table, "total": totals,
                                               "failures": failures, "seconds": elapsed}, indent=2))
    if not failures and not args.keep:
        os.rmdir(keep)
    return 1 if failures else 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]), sys.argv[7])
    else:
        sys.exit(main())
