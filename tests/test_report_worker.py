"""The recovery report drawn in a worker process (mi_bivariate.report_worker): the same PNG as this
process draws, its warnings said here, this process drawing it where the worker is gone or fails, no
file written by the worker, and no worker left behind (by a command, or when its parent dies)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mi_bivariate import analytic, cli, probes, render, report, report_worker
from mi_bivariate.errors import InputError
from mi_bivariate.images import write_exr
from mi_bivariate.recover import recover
from mi_bivariate.report_worker import ReportWorker
from mi_bivariate.sources import synthetic_environment

ROOT = Path(__file__).resolve().parents[1]


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


def test_what_the_worker_does_not_draw_is_drawn_here(tmp_path, panels, monkeypatch):
    """Another format than PNG (the suffix decides, as for a report drawn here) and panels over the size
    limit are drawn in this process without asking the worker (here a dead one, which a question would
    close): the same bytes, and an upper-case ``.PNG`` the same as ``.png``."""
    with ReportWorker() as worker:
        worker._process.kill()
        worker._process.wait()
        pdf = worker.write(panels, tmp_path / "r.pdf")
        assert pdf.read_bytes().startswith(b"%PDF") and worker._process is not None  # not asked
        monkeypatch.setattr(report_worker, "MAX_PANEL_BYTES", 0)
        big = worker.write(panels, tmp_path / "big.PNG")
        assert worker._process is not None  # not asked
        monkeypatch.setattr(report_worker, "MAX_PANEL_BYTES", 2**40)
        worker.write(panels, tmp_path / "asked.png")
        assert worker._process is None  # asked, found dead, closed
    here = report.draw_recovery_report(panels, tmp_path / "here.png").read_bytes()
    assert big.read_bytes() == here == (tmp_path / "asked.png").read_bytes()


def test_warnings_come_back_as_their_nearest_builtin_category():
    from matplotlib import MatplotlibDeprecationWarning

    assert report_worker._builtin_category(MatplotlibDeprecationWarning) is DeprecationWarning
    assert report_worker._builtin_category(RuntimeWarning) is RuntimeWarning
    assert report_worker._builtin_category(type("Mine", (Warning,), {})) is Warning


def test_worker_imports_what_the_command_imports_not_the_current_folders(tmp_path, panels):
    """A command started as the console script is (its folder first on its path, not the current one), in a
    folder holding a ``matplotlib.py``: the worker draws the report without running that file."""
    folder = tmp_path / "work"
    folder.mkdir()
    (folder / "matplotlib.py").write_text("open('ran', 'w').close()\nraise ImportError('not this one')\n")
    (tmp_path / "panels.pickle").write_bytes(pickle.dumps(panels))
    script = tmp_path / "bin" / "command.py"
    script.parent.mkdir()
    script.write_text(f"import pickle, sys\nsys.path.insert(1, {str(ROOT)!r})\n"
                      "from mi_bivariate.report_worker import ReportWorker\n"
                      "panels = pickle.loads(open(sys.argv[1], 'rb').read())\n"
                      "with ReportWorker() as worker:\n"
                      "    worker.write(panels, 'r.png')\n"
                      "    assert worker._process is not None and worker._process.poll() is None\n")
    run = subprocess.run([sys.executable, str(script), str(tmp_path / "panels.pickle")], cwd=folder,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert not (folder / "ran").exists()
    assert (folder / "r.png").read_bytes() == report.draw_recovery_report(panels, tmp_path / "here.png").read_bytes()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_worker_runs_with_the_commands_interpreter_flags():
    """``python -B -W ...``: the worker writes no bytecode either, and has the same warning options."""
    code = ("import time; from mi_bivariate.report_worker import ReportWorker\n"
            "with ReportWorker() as w:\n"
            "    for _ in range(100):\n"
            "        argv = open(f'/proc/{w._process.pid}/cmdline').read().split(chr(0))\n"
            "        if '-c' in argv: break\n"
            "        time.sleep(0.05)  # between the fork and the exec\n"
            "    print(argv)")
    run = subprocess.run([sys.executable, "-B", "-W", "ignore::DeprecationWarning", "-c", code], capture_output=True,
                         text=True, timeout=60, check=True)
    argv = eval(run.stdout)  # the list printed above
    flags = argv[1:argv.index("-c")]
    assert "-B" in flags and "-Wignore::DeprecationWarning" in flags, argv


@pytest.fixture(scope="module")
def package_copy(tmp_path_factory):
    """A copy of the package (and its plugins) whose ``report.warm_up`` first does what ``$COPY_WARM_UP``
    says: ``mark:FILE`` creates FILE; ``hold:FILE`` creates FILE, sleeps 60 s and removes it on the way out
    (as matplotlib's font-cache lock file)."""
    import shutil

    root = tmp_path_factory.mktemp("copy")
    shutil.copytree(ROOT / "mi_bivariate", root / "mi_bivariate", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "plugins", root / "mi_bivariate" / "plugins", ignore=shutil.ignore_patterns("__pycache__"))
    source = (root / "mi_bivariate" / "report.py").read_text()
    hook = ('def warm_up() -> None:\n'
            '    import os, time\n'
            '    how, _, name = os.environ.get("COPY_WARM_UP", "").partition(":")\n'
            '    if how == "mark":\n'
            '        open(name, "w").close()\n'
            '    if how == "hold":\n'
            '        open(name, "w").close()\n'
            '        try:\n'
            '            time.sleep(60)\n'
            '        finally:\n'
            '            os.remove(name)\n')
    assert source.count("def warm_up() -> None:\n") == 1
    (root / "mi_bivariate" / "report.py").write_text(source.replace("def warm_up() -> None:\n", hook + "    return _warm_up()\n\n\ndef _warm_up() -> None:\n"))
    return root


def _run_with_copy(copy: Path, tmp_path: Path, panels, body: str, env: dict) -> subprocess.CompletedProcess:
    """Run ``body`` in a fresh process whose path puts ``copy`` first, with ``panels`` and a ``ReportWorker``
    class of the copy at hand."""
    (tmp_path / "panels.pickle").write_bytes(pickle.dumps(panels))
    code = (f"import pickle, sys\nsys.path.insert(0, {str(copy)!r})\n"
            "from mi_bivariate import report_worker\nfrom mi_bivariate.report_worker import ReportWorker\n"
            f"panels = pickle.loads(open({str(tmp_path / 'panels.pickle')!r}, 'rb').read())\n" + body)
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=180,
                          env={**os.environ, **env})


def test_worker_imports_the_commands_copy_of_the_package(tmp_path, panels, package_copy):
    body = ("with ReportWorker() as worker:\n"
            "    worker.write(panels, 'r.png')\n"
            "    assert worker._process is not None, 'drawn here'\n")
    run = _run_with_copy(package_copy, tmp_path, panels, body, {"COPY_WARM_UP": f"mark:{tmp_path / 'copy-used'}"})
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "copy-used").exists()  # the worker's warm_up was the copy's


def test_a_worker_slow_to_start_is_not_waited_for_and_unwinds_when_ended(tmp_path, panels, package_copy):
    """The wait for the worker's start is bounded too; ending a worker inside its start lets it unwind (a
    lock file it holds, as matplotlib's font cache's, is removed)."""
    held = tmp_path / "held.lock"
    body = ("import time\nreport_worker.REPLY_TIMEOUT_S = 3.0\nt = time.monotonic()\n"
            "worker = ReportWorker()\nworker.write(panels, 'r.png')\n"
            "assert worker._process is None, 'not closed'\nprint(time.monotonic() - t)\n")
    run = _run_with_copy(package_copy, tmp_path, panels, body, {"COPY_WARM_UP": f"hold:{held}"})
    assert run.returncode == 0, run.stderr[-2000:]
    assert float(run.stdout) < 30.0  # 3 s of waiting, the report drawn here, the worker ended
    assert (tmp_path / "r.png").stat().st_size > 10000
    assert not held.exists()


def _ended(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in "ZX"  # a zombie has ended
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_worker_ends_with_the_process_that_started_it():
    """The parent ends while a process it forked still holds the worker's requests open (so the worker
    sees no end of its input): the worker ends all the same (:func:`mi_bivariate.process.die_with_parent`)."""
    code = ("import os, time; from mi_bivariate.report_worker import ReportWorker; w = ReportWorker()\n"
            "holder = os.fork()\n"
            "if holder == 0:\n"
            "    os.closerange(0, 3); time.sleep(30); os._exit(0)\n"
            "print(w._process.pid, holder, flush=True); time.sleep(0.5); os._exit(0)")
    command = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    worker, holder = (int(v) for v in command.stdout.split())
    try:
        deadline = time.monotonic() + 20
        while not _ended(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _ended(worker)
    finally:
        with contextlib.suppress(OSError):
            os.kill(holder, 9)


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
    mark = f"{report_worker.BOOT}\0{command.pid}\0"
    workers, drew_here = set(), False
    while command.poll() is None:
        for entry in Path("/proc").iterdir():
            try:
                if entry.name.isdigit() and mark in (entry / "cmdline").read_text():
                    workers.add(int(entry.name))
            except OSError:
                pass
        with contextlib.suppress(OSError):  # matplotlib's renderer in the command's own process
            drew_here = drew_here or "_backend_agg" in Path(f"/proc/{command.pid}/maps").read_text()
        time.sleep(0.05)
    out, err = command.communicate()
    assert command.returncode == 0, err
    assert workers, "no report worker ran"
    assert not drew_here, "the command drew its report itself"
    assert all(_ended(pid) for pid in workers)
    # The same command in this process (main's default: no worker) draws the same report.
    assert cli.main(["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "probe.exr"), "--out",
                     str(tmp_path / "here.npz"), "--normals", "1500", "--dirs", "4000"]) == 0
    assert (tmp_path / "out_report.png").read_bytes() == (tmp_path / "here_report.png").read_bytes()
