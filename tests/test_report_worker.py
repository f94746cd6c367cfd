"""The recovery report drawn in a worker process (mi_bivariate.report_worker): the same PNG as this
process draws, its warnings said here, this process drawing it where the worker is gone or fails, no
file written by the worker, and no worker left behind (by a command, or when its parent dies)."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_bivariate import analytic, cli, probes, render, report
from mi_bivariate.errors import InputError
from mi_bivariate.images import write_exr
from mi_bivariate.recover import recover
from mi_bivariate.report_worker import ReportWorker
from mi_bivariate.sources import synthetic_environment


@pytest.fixture(scope="module")
def recovery():
    probe = probes.Probe(synthetic_environment(seed=1), source="synthetic")
    truth = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.4, 0.3])))
    shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=64, spp=64, seed=0)
    return recover(shot.image, probe, shot.geometry, n_normals=1500, n_dirs=4000), shot, probe


@pytest.fixture(scope="module")
def panels(recovery):
    return report.recovery_report_panels(recovery[0])


def _worker_alive(worker: ReportWorker) -> bool:
    """Whether the worker still runs: one that failed is closed (and its report drawn in this process)."""
    return worker._process is not None and worker._process.poll() is None


def test_worker_draws_the_same_png_as_this_process(tmp_path, recovery, panels):
    with ReportWorker() as worker:
        first = worker.write(panels, tmp_path / "worker.png")
        second = worker.write(panels, tmp_path / "again.png")  # one worker, many reports (recover-batch)
        assert _worker_alive(worker)  # drawn there, not here
    assert worker._process is None  # closed on leaving the block
    here = report.write_recovery_report(recovery[0], tmp_path / "here.png")
    assert first.read_bytes() == here.read_bytes() == second.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.png", "here.png", "worker.png"]


def test_worker_says_what_the_drawing_warned_about(tmp_path, panels):
    """A photo whose object has no pixels: numpy's all-NaN warning, said by the worker's command as by a
    report drawn in its own process."""
    empty = dataclasses.replace(panels, mask=np.zeros_like(panels.mask))
    with pytest.warns(RuntimeWarning, match="All-NaN"):
        here = report.draw_recovery_report(empty, tmp_path / "here.png")
    with ReportWorker() as worker, pytest.warns(RuntimeWarning, match="All-NaN"):
        there = worker.write(empty, tmp_path / "worker.png")
        assert _worker_alive(worker)
    assert there.read_bytes() == here.read_bytes()


def test_a_dead_worker_leaves_the_report_to_this_process(tmp_path, panels):
    worker = ReportWorker()
    worker._process.kill()
    worker._process.wait()
    path = worker.write(panels, tmp_path / "r.png")
    assert worker._process is None  # not asked again
    assert path.read_bytes() == report.draw_recovery_report(panels, tmp_path / "here.png").read_bytes()
    worker.close()  # a second close does nothing


def test_what_the_worker_cannot_draw_fails_here_as_it_would_have(tmp_path, panels):
    """The worker answers that it failed; this process draws again and raises what drawing raises."""
    broken = dataclasses.replace(panels, table=np.zeros((3, 3)))  # not an (n_t, n_s, 3) table
    with pytest.raises(InputError) as here:
        report.draw_recovery_report(broken, tmp_path / "here.png")
    with ReportWorker() as worker:
        with pytest.raises(InputError) as there:
            worker.write(broken, tmp_path / "worker.png")
        assert worker._process is None
    assert str(there.value) == str(here.value)
    assert list(tmp_path.iterdir()) == []


def test_worker_writes_no_file_and_an_unwritable_report_fails_as_here(tmp_path, panels):
    folder = tmp_path / "taken.png"
    folder.mkdir()  # a folder where the report would go
    with pytest.raises(InputError) as here:
        report.draw_recovery_report(panels, folder)
    with ReportWorker() as worker:
        with pytest.raises(InputError) as there:
            worker.write(panels, folder)
        assert _worker_alive(worker)  # drawn there; the write here failed
    assert str(there.value) == str(here.value)
    assert list(tmp_path.iterdir()) == [folder] and list(folder.iterdir()) == []


def _ended(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in "ZX"  # a zombie has ended
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_worker_ends_with_the_process_that_started_it():
    code = ("import os; from mi_bivariate.report_worker import ReportWorker; w = ReportWorker(); "
            "print(w._process.pid, flush=True); os._exit(0)")
    pid = int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             timeout=60).stdout)
    deadline = time.monotonic() + 30
    while not _ended(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _ended(pid)


@pytest.mark.parametrize("argv, pays", [
    (["recover", "x.exr", "--probe", "p"], True),
    (["recover", "x.exr", "--probe", "p", "--no-report"], False),
    (["recover", "x.exr", "--probe", "p", "--threads", "1"], False),
    (["recover", "x.exr", "--probe", "p", "--deterministic"], False),
    (["recover-batch", "x.exr", "y.exr", "--probe", "p", "--out-dir", "o"], True),
    (["render", "brdf.npz", "--probe", "p"], False),
])
def test_which_commands_draw_their_report_in_a_worker(argv, pays, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    args, _ = cli.build_parser().parse_known_args(argv)
    assert cli._report_worker_pays(args) is pays
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert cli._report_worker_pays(args) is False  # one core: nothing to overlap with


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_recover_draws_its_report_in_a_worker_that_ends_with_it(tmp_path, recovery):
    """``mi-bivariate recover`` in a process of its own: the report is the one this process draws of the
    same recovery, and the worker (named by the command's process id) is gone when the command ends."""
    _, shot, probe = recovery
    write_exr(tmp_path / "photo.exr", shot.image)
    probe.save_exr(tmp_path / "probe.exr")
    command = subprocess.Popen(
        [sys.executable, "-m", "mi_bivariate.cli", "recover", str(tmp_path / "photo.exr"), "--probe",
         str(tmp_path / "probe.exr"), "--out", str(tmp_path / "out.npz"), "--normals", "1500", "--dirs", "4000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    mark = f"mi_bivariate.report_worker\0{command.pid}"
    workers = set()
    while command.poll() is None:
        for entry in Path("/proc").iterdir():
            try:
                if entry.name.isdigit() and mark in (entry / "cmdline").read_text():
                    workers.add(int(entry.name))
            except OSError:
                pass
        time.sleep(0.05)
    out, err = command.communicate()
    assert command.returncode == 0, err
    assert workers, "no report worker ran"
    assert all(_ended(pid) for pid in workers)
    # The same command in this process (main's default: no worker) draws the same report.
    assert cli.main(["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "probe.exr"), "--out",
                     str(tmp_path / "here.npz"), "--normals", "1500", "--dirs", "4000"]) == 0
    assert (tmp_path / "out_report.png").read_bytes() == (tmp_path / "here_report.png").read_bytes()
