"""The package's public surface: every submodule resolves lazily, and the README's Python runs."""

from __future__ import annotations

import ast
import ctypes
import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import pytest

import mi_bivariate as mb
from mi_bivariate import cli, process

ROOT = Path(__file__).resolve().parents[1]


def test_every_module_is_reachable_as_an_attribute():
    names = {m.name for m in pkgutil.iter_modules(mb.__path__) if not m.name.startswith("_")}
    assert names == set(mb._SUBMODULES), sorted(names ^ set(mb._SUBMODULES))  # the package's listing, checked
    for name in mb._SUBMODULES:
        assert getattr(mb, name) is importlib.import_module(f"mi_bivariate.{name}")


def test_readme_names_resolve():
    """Every ``mb.module.name`` the README shows exists."""
    text = (ROOT / "README.md").read_text()
    for module, name in set(re.findall(r"\bmb\.(\w+)\.(\w+)", text)):
        assert hasattr(getattr(mb, module), name), f"mb.{module}.{name}"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    """The README's Python blocks, on a small rendered sphere (file names swapped for real ones)."""
    from mi_bivariate import analytic, render
    from mi_bivariate.images import write_exr
    from mi_bivariate.probes import Probe
    from mi_bivariate.sources import synthetic_environment
    from mi_bivariate.variants import ensure_variant

    ensure_variant()
    probe = Probe(synthetic_environment(seed=1))
    probe.save_exr(tmp_path / "probe.exr")
    merl = analytic.to_merl(analytic.Lambertian(np.array([0.6, 0.4, 0.3])))
    shot = render.render_sphere(render.bsdf_dict(merl), probe, resolution=64, spp=16, seed=0)
    write_exr(tmp_path / "photo.exr", shot.image)
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 2
    code = "\n".join(blocks).replace("mb.recover.recover(image, probe, fit.geometry)",
                                     "mb.recover.recover(image, probe, fit.geometry, n_normals=500, n_dirs=2000)")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)  # every Python block, in order, as a reader runs them
    assert (tmp_path / "brdf.npz").is_file() and (tmp_path / "brdf.binary").is_file()
    assert "table" in namespace["params"]


def test_readme_python_loads_a_shared_probe_as_the_command_line_does(data_dir, monkeypatch):
    """The README's "From Python" loads its probe with ``Probe.load`` no more: given the shared
    grace_latlong_1k.exr (stored upside down), that read it as stored (to_world = I) and the recovery was
    silently wrong, while ``--probe`` of the same file turns it (:data:`probes.GRACE_LATLONG_ROTATION`). Every
    line of the README's Python that loads a probe, run on that file, gives the command line's probe."""
    from mi_bivariate import probes, sources

    path = probes.shared_probe_path("grace_latlong_1k", data_dir)
    monkeypatch.setenv("MI_BIVARIATE_DATA", str(data_dir))
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    lines = [line for block in blocks for line in block.splitlines() if re.search(r"probe\w*\s*=.*load", line)]
    assert lines, "the README's Python loads no probe"
    command_line = sources.load_probe(str(path))  # what `--probe PATH` loads
    for line in lines:
        code = re.sub(r'"[^"]*\.(exr|hdr)"', repr(str(path)), line.split("#")[0])
        namespace: dict = {"mb": mb}
        exec(code, namespace)
        (probe,) = [v for v in namespace.values() if isinstance(v, probes.Probe)]
        np.testing.assert_array_equal(probe.to_world, command_line.to_world, err_msg=line)


#: glibc's allocator settings in the environment (a test of the command line's own must not inherit them).
_MALLOC_ENV = process.MALLOC_ENV_VARS + ("GLIBC_TUNABLES",)


def _fresh_python(code: str, cwd: Path, env_extra: Optional[dict] = None) -> subprocess.CompletedProcess:
    """``python -c code`` in ``cwd``, with this environment less ``MI_BIVARIATE_VARIANT``, glibc's
    allocator settings and numpy's huge-page switch, plus ``env_extra``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("MI_BIVARIATE_VARIANT", process.HUGEPAGE_ENV_VAR) and k not in _MALLOC_ENV}
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def _console_script(argv: list, before: str = "", after: str = "", env_extra: Optional[dict] = None) -> str:
    """The console script's ``cli.run()`` on ``argv`` in a fresh interpreter (:func:`_fresh_python`), with
    ``before`` run first and ``after`` (which sees its ``status``) last; the run's stdout, once it exited 0."""
    code = (f"import sys\n{before}import mi_bivariate.cli as cli\n"
            f"sys.argv = ['mi-bivariate', *{list(argv)!r}]\nstatus = cli.run()\n{after}")
    out = _fresh_python(code, ROOT, env_extra)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    return out.stdout


def test_front_doors_select_the_variant_and_nothing_below_them_does(tmp_path):
    """In a fresh interpreter ``recover()`` and ``render_sphere()`` work without a selected variant,
    while a data-model method leaves the (unselected) variant alone and Mitsuba says what to do."""
    code = """
import numpy as np, mitsuba as mi
from mi_bivariate.probes import Probe
from mi_bivariate.geometry import SphereGeometry
probe = Probe(np.full((16, 32, 3), 0.5, np.float32))
try:
    probe.emitter()
except (RuntimeError, AttributeError) as exc:  # Mitsuba's own message
    print("below:", "variant" in str(exc))
assert mi.variant() is None, mi.variant()
from mi_bivariate.recover import recover
from mi_bivariate.render import render_sphere
shot = render_sphere({"type": "diffuse"}, probe, resolution=32, spp=4)
print("render:", mi.variant())
mi.set_variant("scalar_rgb")                     # a user switching away: recover switches back
result = recover(shot.image, probe, shot.geometry, n_normals=300, n_dirs=1000, noise=None)
print("recover:", mi.variant(), result.brdf.table.shape)
"""
    out = _fresh_python(code, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "below: True" in out.stdout, out.stdout
    assert "render: llvm_ad_rgb" in out.stdout and "recover: llvm_ad_rgb" in out.stdout, out.stdout


def test_cli_import_is_cheap():
    """``import mi_bivariate.cli`` loads neither Mitsuba nor scipy (commands import what they run)."""
    out = _fresh_python("import sys, mi_bivariate.cli; print(sorted(m for m in sys.modules "
                        "if m.split('.')[0] in ('mitsuba', 'drjit', 'scipy', 'matplotlib')))", ROOT)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_console_script_freezes_the_imports_and_main_leaves_the_collector_alone():
    """The console script (``run``) freezes what the pipeline imported out of the cyclic GC before the
    command runs, and what the command left alive after it; ``main`` called from Python (tests,
    notebooks) leaves the collector as it is. A stand-in command records the freeze count while it
    runs, so each of the two freezes is checked on its own."""
    code = ("import gc, sys, mi_bivariate.cli as cli, mi_bivariate.commands as commands\n"
            "seen, kept = [], []\n"
            "def probe(args):\n"
            "    seen.append(gc.get_freeze_count()); kept.extend([] for _ in range(1000)); return 0\n"
            "commands.COMMANDS['info'] = probe\n"
            "assert cli.main(['info']) == 0 and seen[-1] == 0 and gc.get_freeze_count() == 0, 'main froze'\n"
            "sys.argv = ['mi-bivariate', 'info']\n"
            "assert cli.run() == 0\n"
            "print('during', seen[-1] > 10000, 'after', gc.get_freeze_count() > seen[-1] + 500)\n")
    out = _fresh_python(code, ROOT)
    assert out.returncode == 0 and "during True after True" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]
    scripts = re.search(r"\[project\.scripts\]\s*\nmi-bivariate = \"([^\"]+)\"", (ROOT / "pyproject.toml").read_text())
    assert scripts and scripts.group(1) == "mi_bivariate.__main__:main"  # run, behind the early Ctrl-C guard


def test_console_script_runs_no_collection_while_the_pipeline_loads():
    """In its own process (``run``) the command line turns the cyclic garbage collector off while the
    pipeline's modules load (``mi_bivariate.commands`` initialising), then freezes them and turns it back
    on: no collection (the old code ran ~170, one of them full) and the collector enabled afterwards."""
    before = ("import gc\n"
              "during = []\n"
              "def seen(phase, info):\n"
              "    module = sys.modules.get('mi_bivariate.commands')\n"
              "    if phase == 'start' and module is not None and getattr(module.__spec__, '_initializing', False):\n"
              "        during.append(info['generation'])\n"
              "gc.callbacks.append(seen)\n")
    out = _console_script(["info"], before, "print('status', status, 'collections while loading:', len(during), "
                                            "'enabled:', gc.isenabled())\n")
    assert "status 0 collections while loading: 0 enabled: True" in out, out[-2000:]


def _run_stand_in(*argv: str) -> str:
    """Code to append to a fresh interpreter's that defines ``stand_in(args)``: ``mi-bivariate ARGV``
    through :func:`cli.run` (its own process), with the pipeline loading inside it as for a user and
    the command replaced by ``stand_in`` once it has loaded (nothing of the command itself runs)."""
    return f"""
import importlib, sys
import mi_bivariate.cli as cli
real = importlib.import_module
def load(name, *args, **kwargs):
    module = real(name, *args, **kwargs)
    if name == "mi_bivariate.commands":
        module.COMMANDS[{argv[0]!r}] = stand_in
    return module
importlib.import_module = load
sys.argv = ["mi-bivariate", *{list(argv)!r}]
assert cli.run() == 0
"""


def test_console_script_defers_the_modules_scipy_loads_for_nothing_and_they_work_when_used():
    """In its own process (``run``) the command line registers ``numpy.f2py``, ``numpy.testing``,
    ``numpy.ma``, ``numpy.polynomial`` and ``scipy.special`` as lazy modules before the pipeline loads
    (scipy's vendored ``array_api_compat`` touches every numpy attribute, which imported numpy's; the
    sphere fit's ``scipy.ndimage`` imports ``scipy.special``): none of their code has run once the
    pipeline is loaded, nor after the ndimage operations the pipeline runs, and each works on its first
    use. ``main`` called from Python leaves numpy and scipy as they are (there, loading the pipeline
    imports them, as before)."""
    code = ("import sys\n"
            "def loaded():\n"
            "    return sorted(m for m in ('numpy.f2py.crackfortran', 'numpy.testing._private.utils', "
            "'numpy.ma.core', 'numpy.polynomial.polynomial', 'scipy.special._ufuncs') if m in sys.modules)\n"
            "def stand_in(args):\n"
            "    print('while the command runs:', loaded())\n"
            "    import numpy as np\n"
            "    from scipy import ndimage\n"
            "    image = np.add.outer(np.arange(32.0), np.arange(32.0)) % 7 > 2\n"
            "    labels, n = ndimage.label(image)\n"
            "    ndimage.find_objects(labels), ndimage.binary_fill_holes(image)\n"
            "    ndimage.binary_erosion(image, iterations=2)\n"
            "    ndimage.binary_dilation(image, iterations=2), ndimage.distance_transform_edt(~image)\n"
            "    ndimage.distance_transform_edt(image, return_distances=False, return_indices=True)\n"
            "    ndimage.gaussian_filter(image * 1.0, 1.5), ndimage.sobel(image * 1.0, axis=0)\n"
            "    ndimage.map_coordinates(image * 1.0, [[1.5, 3.25], [2.5, 9.0]], order=1, mode='constant',\n"
            "                            cval=np.nan)\n"
            "    print('after ndimage:', loaded())\n"
            "    import numpy.ma as ma, numpy.testing as npt, scipy.special as sc\n"
            "    from numpy.polynomial import Polynomial\n"
            "    npt.assert_allclose(np.ones(2), 1.0)\n"
            "    print('used:', float(ma.masked_array([1.0, 5.0], mask=[0, 1]).sum()), Polynomial([1, 2])(3.0), "
            "np.f2py.__name__, np.testing is npt, round(float(sc.erf(0.5)), 6), loaded())\n"
            "    return 0\n")
    out = _fresh_python(code + _run_stand_in("info"), ROOT)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "while the command runs: []" in out.stdout, out.stdout[-2000:]
    assert "after ndimage: []" in out.stdout, out.stdout[-2000:]
    assert ("used: 1.0 7.0 numpy.f2py True 0.5205 ['numpy.f2py.crackfortran', 'numpy.ma.core', "
            "'numpy.polynomial.polynomial', 'numpy.testing._private.utils', 'scipy.special._ufuncs']") in out.stdout, \
        out.stdout[-2000:]
    control = _fresh_python("import sys, mi_bivariate.cli as cli\n"
                            "assert cli.main(['info']) == 0\n"
                            "print('lazy:', [name for name in ('numpy.f2py', 'numpy.testing', 'numpy.ma', "
                            "'numpy.polynomial', 'scipy.special') "
                            "if type(sys.modules.get(name)).__name__ == '_LazyModule'])\n", ROOT)
    assert control.returncode == 0 and "lazy: []" in control.stdout, control.stdout[-2000:] + control.stderr


def _small_recover_argv(tmp_path: Path) -> list:
    """``recover`` of a 48 px sphere (a smooth GGX) under a small synthetic probe, written to ``tmp_path``:
    the command's arguments without ``--out``."""
    from mi_bivariate import analytic, render
    from mi_bivariate.images import write_exr
    from mi_bivariate.probes import Probe
    from mi_bivariate.sources import synthetic_environment

    probe = Probe(synthetic_environment(height=32, width=64, seed=1), source="synthetic")
    truth = analytic.to_merl(analytic.analytic_from_spec("ggx:alpha=0.3"))
    shot = render.render_sphere(render.bsdf_dict(truth), probe, resolution=48, spp=16, seed=0)
    write_exr(tmp_path / "photo.exr", shot.image)
    probe.save_exr(tmp_path / "probe.exr")
    return ["recover", str(tmp_path / "photo.exr"), "--probe", str(tmp_path / "probe.exr"), "--normals", "500",
            "--dirs", "512", "--grid", "8", "8"]


def test_recover_runs_no_code_of_scipy_special(tmp_path):
    """A whole ``recover`` (its own process, its report drawn in the command's process) never runs
    ``scipy.special``'s code, which the command line defers (``process.defer_unused_modules``): its
    ndimage operations, noise estimate and report do not need it, so the ~0.04 s its loading costs is
    saved; the table is the one ``main`` called from Python (scipy loaded as scipy loads) recovers."""
    argv = _small_recover_argv(tmp_path) + ["--threads", "1"]
    out = _console_script(argv + ["--out", str(tmp_path / "run.npz")], after=(
        "print('status', status, 'special ran:', 'scipy.special._ufuncs' in sys.modules, "
        "'report drawn here:', 'matplotlib.backends.backend_agg' in sys.modules)\n"))
    assert "status 0 special ran: False report drawn here: True" in out, out[-2000:]
    assert (tmp_path / "run_report.png").is_file()
    control = _fresh_python("import mi_bivariate.cli as cli\n"
                            f"assert cli.main({argv!r} + ['--out', {str(tmp_path / 'main.npz')!r}]) == 0\n", ROOT)
    assert control.returncode == 0, control.stdout[-2000:] + control.stderr[-2000:]
    with np.load(tmp_path / "run.npz") as a, np.load(tmp_path / "main.npz") as b:
        assert np.array_equal(a["table"], b["table"])


def test_recover_imports_nothing_off_its_main_thread(tmp_path):
    """The lazy modules of ``process.defer_unused_modules`` are not thread-safe on first use before
    CPython's fix (gh-114763; three threads asking for ``scipy.special.erf`` at once fail): a ``recover``
    with its solve on three worker threads (and its report worker) imports nothing off its main thread,
    so none of them is first loaded on a worker. Every import is recorded with its thread."""
    before = ("import threading\n"
              "off_main = []\n"
              "class Record:\n"
              "    def find_spec(self, name, path, target=None):\n"
              "        if threading.current_thread() is not threading.main_thread():\n"
              "            off_main.append((threading.current_thread().name, name))\n"
              "        return None\n"
              "sys.meta_path.insert(0, Record())\n")
    out = _console_script(_small_recover_argv(tmp_path) + ["--out", str(tmp_path / "run.npz")], before,
                          "print('status', status, 'imports off the main thread:', off_main)\n",
                          {"MI_BIVARIATE_SOLVE_THREADS": "3"})
    assert "status 0 imports off the main thread: []" in out, out[-2000:]


def test_recover_in_its_own_process_leaves_mitsubas_syntax_rewrites_to_their_first_call(tmp_path):
    """``process.syntax_on_first_call``: in the command line's own process, the ``@dr.syntax`` methods that
    ``import mitsuba`` (``ProjectiveDetail``) and the variant's start (``prb``) define are not rewritten
    before their first call, and ``drjit.syntax`` is Dr.Jit's own again once the pipeline is loaded (a
    rendering notebook or evaluation worker started from it decorates as Dr.Jit does)."""
    argv = _small_recover_argv(tmp_path) + ["--no-report", "--out", str(tmp_path / "run.npz")]
    out = _console_script(argv, after=(
        "import drjit, drjit.ast\n"
        "from mitsuba.python.ad.projective import ProjectiveDetail\n"
        "from mitsuba.python.ad.integrators.prb import PRBIntegrator\n"
        "print('status', status, hasattr(ProjectiveDetail.init_indirect_silhouette_grid_unif, '__wrapped__'),\n"
        "      hasattr(PRBIntegrator.sample, '__wrapped__'), drjit.syntax is drjit.ast.syntax)\n"))
    assert "status 0 True True True" in out, out[-2000:]


def test_recover_into_a_pipe_whose_reader_has_gone_ends_quietly_with_its_outputs(tmp_path):
    """``mi-bivariate recover ... | head -1``: the reader closes the pipe, the command's summary cannot be
    printed. It ends with status 141 (a shell's for SIGPIPE) and no error line (a helper's run ended with
    status 2 and "Broken pipe (check the path, permissions and free space)", blaming a file)."""
    argv = _small_recover_argv(tmp_path) + ["--no-report", "--out", str(tmp_path / "t.npz")]
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the command prints anything
    try:
        out = subprocess.run([sys.executable, "-m", "mi_bivariate", *argv], stdout=write, stderr=subprocess.PIPE,
                             text=True, cwd=ROOT, timeout=300, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    finally:
        os.close(write)
    assert out.returncode == cli.STATUS_READER_GONE == 141, (out.returncode, out.stderr[-2000:])
    assert "error" not in out.stderr and "Traceback" not in out.stderr and "Exception" not in out.stderr, out.stderr
    # The first print (the sphere fit's summary) broke: nothing was recovered, and nothing half-written is left.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photo.exr", "probe.exr"]


_MALLOC_PROBE = """
import ctypes, sys, threading
import numpy as np
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
kept = []
def stand_in(args=None):
    worker = threading.Thread(target=lambda: kept.append(np.ones(2 * 2**20)))  # 16 MiB on another thread
    worker.start()
    worker.join()
    print("mapped MiB", round(libc.mallinfo2().hblkhd / 2**20), flush=True)
    libc.malloc_stats()  # one "Arena N:" block per arena, on standard error
    return 0
"""


def _arenas_and_mapped(out: subprocess.CompletedProcess) -> Tuple[int, int]:
    """``(arenas, MiB mapped)`` that :data:`_MALLOC_PROBE` printed."""
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    return out.stderr.count("Arena "), int(re.search(r"mapped MiB (\d+)", out.stdout).group(1))


@pytest.mark.parametrize("argv", [("recover", "photo.exr", "--probe", "probe.exr", "--out", "o.npz"),
                                  ("recover-batch", "a.exr", "b.exr", "--probe", "probe.exr", "--out-dir", "o")],
                         ids=["recover", "recover-batch"])
def test_recover_commands_keep_freed_memory_in_one_arena(argv):
    """In its own process (``run``) ``recover`` has glibc keep freed memory for the next arrays: a
    worker thread's 16 MiB array comes from the one shared arena's heap, not from a mapping of its own,
    and no second arena exists. Left as glibc has it: another command's process (``info``), ``main``
    called from Python, and a process whose user set the allocator (``MALLOC_ARENA_MAX=4``): there the
    array is mapped, in a second arena."""
    try:
        if not hasattr(ctypes.CDLL(None), "mallinfo2"):
            raise OSError
    except (OSError, TypeError):
        pytest.skip("needs glibc >= 2.33 (mallinfo2)")
    arenas, mapped = _arenas_and_mapped(_fresh_python(_MALLOC_PROBE + _run_stand_in(*argv), ROOT))
    assert arenas == 1 and mapped < 16, (arenas, mapped)
    left_alone = [_fresh_python(_MALLOC_PROBE + _run_stand_in("info"), ROOT),
                  _fresh_python(_MALLOC_PROBE + _run_stand_in(*argv), ROOT, {"MALLOC_ARENA_MAX": "4"}),
                  _fresh_python(_MALLOC_PROBE + "import mi_bivariate.cli as cli, mi_bivariate.commands as commands\n"
                                f"commands.COMMANDS[{argv[0]!r}] = stand_in\n"
                                f"assert cli.main({list(argv)!r}) == 0\n", ROOT)]
    for out in left_alone:
        arenas, mapped = _arenas_and_mapped(out)
        assert arenas >= 2 and mapped >= 16, (arenas, mapped, out.stdout[-500:])


_THP_PROBE = """
import ctypes, subprocess, sys
assert ctypes.CDLL(None).prctl(41, 0, 0, 0, 0) == 0  # PR_SET_THP_DISABLE off: a process whose huge pages are on
def stand_in(args=None):
    status = open("/proc/self/status").read()
    print("THP_enabled", status.split("THP_enabled:")[1].split()[0], flush=True)
    child = subprocess.run([sys.executable, "-c", "print(open('/proc/self/status').read().split('THP_enabled:')[1]"
                            ".split()[0])"], capture_output=True, text=True)
    print("THP_enabled", child.stdout.strip(), flush=True)
    return 0
"""


@pytest.mark.parametrize("argv", [("recover", "photo.exr", "--probe", "probe.exr", "--out", "o.npz"),
                                  ("render", "ggx:alpha=0.1", "--probe", "probe.exr"), ("info",)],
                         ids=["recover", "render", "info"])
def test_commands_turn_transparent_huge_pages_off(argv):
    """In its own process (``run``) every command turns the kernel's transparent huge pages off for itself
    (``prctl(PR_SET_THP_DISABLE)``; the kernel says so in ``/proc/self/status``), also where the user set
    ``NUMPY_MADVISE_HUGEPAGE=0`` (or ``00``, which numpy reads as 0), and a process it starts inherits that.
    Left on: ``main`` called from Python, and a process whose user asked numpy for huge pages
    (``NUMPY_MADVISE_HUGEPAGE=1``). Each child turns huge pages on first (the suite's own process has them
    off, tests/conftest.py)."""
    status = Path("/proc/self/status")
    if not status.is_file() or "THP_enabled:" not in status.read_text():
        pytest.skip("needs Linux >= 5.0 (THP_enabled in /proc/PID/status)")
    if not Path("/sys/kernel/mm/transparent_hugepage").is_dir():
        pytest.skip("a kernel without transparent huge pages")
    if ctypes.CDLL(None).prctl(42, 0, 0, 0, 0) < 0:  # PR_GET_THP_DISABLE refused (seccomp, gVisor)
        pytest.skip("prctl's huge-page switch is not available here")

    def thp(out: subprocess.CompletedProcess) -> str:
        assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
        return " ".join(re.findall(r"THP_enabled (\d)", out.stdout))

    off = [_fresh_python(_THP_PROBE + _run_stand_in(*argv), ROOT),
           _fresh_python(_THP_PROBE + _run_stand_in(*argv), ROOT, {"NUMPY_MADVISE_HUGEPAGE": "0"}),
           _fresh_python(_THP_PROBE + _run_stand_in(*argv), ROOT, {"NUMPY_MADVISE_HUGEPAGE": "00"})]  # numpy: off
    assert [thp(out) for out in off] == ["0 0", "0 0", "0 0"]
    left_alone = [_fresh_python(_THP_PROBE + _run_stand_in(*argv), ROOT, {"NUMPY_MADVISE_HUGEPAGE": "1"}),
                  _fresh_python(_THP_PROBE + "import mi_bivariate.cli as cli, mi_bivariate.commands as commands\n"
                                f"commands.COMMANDS[{argv[0]!r}] = stand_in\n"
                                f"assert cli.main({list(argv)!r}) == 0\n", ROOT)]
    assert [thp(out) for out in left_alone] == ["1 1", "1 1"]


def test_console_script_exit_status_on_bad_input(tmp_path):
    """Through ``run`` (``python -m mi_bivariate.cli``), bad input still ends in one line and status 2."""
    missing = tmp_path / "missing.exr"
    out = subprocess.run([sys.executable, "-m", "mi_bivariate.cli", "recover", str(missing), "--probe",
                          str(missing), "--out", str(tmp_path / "o.npz")], capture_output=True, text=True,
                         cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and lines[0].startswith("mi-bivariate: error: "), out.stderr
    assert str(missing) in lines[0] and not (tmp_path / "o.npz").exists()


@pytest.mark.parametrize("module", ["mi_bivariate", "mi_bivariate.cli"])
def test_ctrl_c_while_the_command_line_loads_ends_in_one_line(module):
    """A Ctrl-C while the command loads numpy (before the command sets up its own stop) ends as a later
    one does: ``mi-bivariate: interrupted``, status 130, no traceback; through ``python -m mi_bivariate``
    (the console script's ``main``) and ``python -m mi_bivariate.cli`` alike. The process sends itself SIGINT
    from inside the import of numpy's core library (an import hook): the same signal at the same
    moment on a busy machine or an idle one (polling ``/proc/PID/maps`` from outside for that moment
    raced the command under load and could miss it)."""
    code = """
import importlib.abc, os, runpy, signal, sys

class CtrlC(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "numpy._core._multiarray_umath":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)  # raised as KeyboardInterrupt inside numpy's import
        return None

sys.meta_path.insert(0, CtrlC())
sys.argv = ["mi-bivariate", "info"]
runpy.run_module(MODULE, run_name="__main__", alter_sys=True)  # python -m MODULE info
""".replace("MODULE", repr(module))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 130 and out.stderr.strip() == "mi-bivariate: interrupted", \
        (out.returncode, out.stderr[-2000:])
    assert "numpy" not in out.stdout and not out.stdout.strip(), out.stdout[-2000:]  # it never ran the command


_BLAS_AT_EXIT = """
import atexit, os, sys
def _report():
    import threadpoolctl
    pools = sorted(pool["num_threads"] for pool in threadpoolctl.threadpool_info() if pool["user_api"] == "blas")
    print("BLAS", pools, os.environ.get("OPENBLAS_NUM_THREADS"), file=sys.stderr)
atexit.register(_report)
"""


def test_command_line_starts_blas_with_one_thread(tmp_path):
    """The command line's own process (the console script's ``main``: ``python -m mi_bivariate`` and
    ``python -m mi_bivariate.cli``) has numpy's and scipy's OpenBLAS start with the one thread its linear
    algebra uses (``process.one_blas_thread_at_load``): no idle threads busy-waiting beside its own. Left as
    the libraries have it: where the user set ``OPENBLAS_NUM_THREADS``, where ``MI_BIVARIATE_BLAS_THREADS``
    asks for more threads or for the libraries' own, and in a program that imports the toolkit. Read at
    exit by a ``sitecustomize`` (threadpoolctl), after a ``recover`` that loaded the pipeline and refused its
    missing photo."""
    (tmp_path / "sitecustomize.py").write_text(_BLAS_AT_EXIT)
    missing = str(tmp_path / "missing.exr")
    argv = ["recover", missing, "--probe", missing, "--out", str(tmp_path / "o.npz")]
    base = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                                              process.BLAS_THREADS_ENV_VAR)}

    def pools(command: list, **env: str) -> str:
        out = subprocess.run([sys.executable, *command], capture_output=True, text=True, cwd=ROOT, timeout=300,
                             env=dict(base, PYTHONPATH=f"{tmp_path}{os.pathsep}{ROOT}", **env))
        found = re.findall(r"^BLAS (.*)$", out.stderr, re.M)
        assert len(found) == 1, out.stderr[-2000:]
        return found[0]

    plain = pools(["-c", "import numpy, scipy.linalg"])  # the libraries' own: a thread per core
    assert plain.endswith("None") and plain.count(",") == 1, plain  # numpy's and scipy's libraries, loaded
    for module in ("mi_bivariate", "mi_bivariate.cli"):
        assert pools(["-m", module, *argv]) == "[1, 1] 1", module
        assert pools(["-m", module, *argv], OPENBLAS_NUM_THREADS="2") == "[2, 2] 2", module
        assert pools(["-m", module, *argv], OPENBLAS_NUM_THREADS=" ") == "[1, 1] 1", module  # blank: as unset
        for setting in ("2", "default"):
            assert pools(["-m", module, *argv], MI_BIVARIATE_BLAS_THREADS=setting) == plain, (module, setting)
    imported = pools(["-c", f"import mi_bivariate.cli as cli; cli.main({argv!r})"])
    assert imported == plain


def test_python_dash_m_package_runs_the_command():
    """``python -m mi_bivariate`` is the ``mi-bivariate`` command."""
    out = subprocess.run([sys.executable, "-m", "mi_bivariate", "--help"], capture_output=True, text=True,
                         cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert out.returncode == 0 and "recover" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


#: The README's "Layout" groups, in the order of the data flow (``plugins`` is the package's
#: ``mi_bivariate.plugins``, at the bottom: the BSDFs know nothing of the pipeline).
LAYERS = (
    "__init__ common errors limits atomic npzio images coordinates merl analytic nbrdf bivariate probes sources "
    "plugins variants threads process",
    "geometry silhouette spherefit mesh capture noise",
    "lighting adequacy",
    "prior basis_prior training_set solve alignment sphere_refine",
    "recover",
    "render reference metrics baselines report report_worker export figures evaluate synthesis demo cli commands "
    "__main__",
)


def test_modules_import_only_their_own_or_earlier_layers():
    """Data flows one way: no module (the plugins included) imports one of a later group of the
    README's layout, lazily or at the top, absolutely or relatively; and every module is named in
    that layout."""
    package = ROOT / "mi_bivariate"
    level = {name: i for i, names in enumerate(LAYERS) for name in names.split()}
    layout = (ROOT / "README.md").read_text().split("## Layout", 1)[1].split("```", 2)[1]
    upward, unlisted = [], []
    files = [(p, p.relative_to(package).with_suffix("").parts) for p in sorted(package.rglob("*.py"))]
    files += [(p, ("plugins",) + p.relative_to(ROOT / "plugins").with_suffix("").parts)
              for p in sorted((ROOT / "plugins").rglob("*.py"))]
    for path, parts in files:
        top = parts[0]
        if top not in level:
            unlisted.append(top)
            continue
        if top not in ("__init__", "__main__", "plugins") and not re.search(rf"(?<![\w.]){top}\b(?!-)", layout):
            unlisted.append(f"{top} (not in the README's layout)")
        here = ["mi_bivariate", *parts[:-1]]          # the package a relative import starts from
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = here[:len(here) - node.level + 1] if node.level else []
                module = ".".join(base + ([node.module] if node.module else [])).split(".")
                names = module[1:2] if len(module) > 1 else [a.name for a in node.names]
                if module[0] != "mi_bivariate":
                    continue
            elif isinstance(node, ast.Import):
                names = [a.name.split(".")[1] for a in node.names if a.name.startswith("mi_bivariate.")]
            else:
                continue
            upward += [f"{'/'.join(parts)} -> {n}" for n in names if level.get(n, -1) > level[top]]
    assert not unlisted, sorted(set(unlisted))
    assert not upward, sorted(set(upward))


def test_every_script_answers_help_and_does_no_work():
    """``python benchmarks/X.py --help`` (and scripts/) prints its usage and exits 0 without starting its
    work: three benchmarks ignored --help and started measuring, four crashed on it, and
    scripts/make_priors.py would have overwritten the packaged priors."""
    from concurrent.futures import ThreadPoolExecutor

    scripts = sorted(p for folder in ("benchmarks", "scripts") for p in (ROOT / folder).glob("*.py")
                     if not p.name.startswith("_"))
    assert len(scripts) >= 30
    packaged = {p: p.stat().st_mtime_ns for p in (ROOT / "mi_bivariate" / "data").iterdir()}
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    def ask(path: Path):
        run = subprocess.run([sys.executable, path.name, "--help"], cwd=path.parent, env=env, capture_output=True,
                             text=True, timeout=120)
        return path.name, run.returncode, run.stdout, run.stderr[-500:]

    with ThreadPoolExecutor(2) as pool:
        answers = list(pool.map(ask, scripts))
    wrong = [(name, rc, err) for name, rc, out, err in answers if rc != 0 or not out.startswith("usage:")]
    assert not wrong, wrong
    assert {p: p.stat().st_mtime_ns for p in (ROOT / "mi_bivariate" / "data").iterdir()} == packaged


def test_recover_from_a_photo_does_not_import_scipy_optimize(tmp_path):
    """``scipy.optimize`` costs a ``recover`` process ~0.09 s of imports (issue 10's 2 s budget) for ~30
    solvers it does not use: the sphere fit (:func:`spherefit.soft_l1_fit`) and the noise estimate
    (:func:`noise.nonnegative_fit`) do without it. In a fresh interpreter, the command line's modules and
    a whole recovery from a photo (the sphere found in the image, the noise estimated) leave it unloaded."""
    code = """
import sys, numpy as np
import mi_bivariate.commands
from mi_bivariate.probes import Probe
from mi_bivariate.render import render_sphere
from mi_bivariate.recover import recover
from mi_bivariate.spherefit import fit_sphere
probe = Probe(np.full((16, 32, 3), 0.5, np.float32))
shot = render_sphere({"type": "diffuse"}, probe, resolution=64, spp=16)
fit = fit_sphere(shot.image)
result = recover(shot.image, probe, fit.geometry, n_normals=300, n_dirs=1000)
print("fitted", round(fit.radius), result.brdf.table.shape, "optimize:", "scipy.optimize" in sys.modules)
"""
    out = _fresh_python(code, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "optimize: False" in out.stdout, out.stdout


def test_syntax_blocks_that_nest_or_overlap_restore_drjits_own_decorator_once_all_end():
    """``process.syntax_on_first_call`` entered twice and left in either order (two threads' blocks may
    overlap so): ``drjit.syntax`` is the deferring stand-in while any block is open, one level deep (not
    a stand-in of the stand-in), and Dr.Jit's own once the last ends (a helper's review found it left
    replaced when the first block entered left last)."""
    import drjit as dr
    import drjit.ast

    for order in ((0, 1), (1, 0)):
        blocks = [process.syntax_on_first_call(), process.syntax_on_first_call()]
        blocks[0].__enter__()
        stand_in = dr.syntax
        assert stand_in is not drjit.ast.syntax
        blocks[1].__enter__()
        assert dr.syntax is stand_in
        blocks[order[0]].__exit__(None, None, None)
        assert dr.syntax is stand_in
        blocks[order[1]].__exit__(None, None, None)
        assert dr.syntax is drjit.ast.syntax


def test_recover_in_its_own_process_leaves_scipys_docstrings_unparsed_and_recovers_the_same_table(tmp_path):
    """``process.plain_scipy_docstrings``: in the command line's own process no docstring of scipy's is
    parsed (``scipy._lib._docscrape``'s parser, which scipy 1.17 runs on each function it extends at
    import: ~0.09 s of one core), the sphere fit's ``scipy.ndimage`` included (loaded on first use, after the
    pipeline); ``main`` called from Python parses them as scipy does; both recover the same table."""
    count = ("import scipy._lib._docscrape as docscrape\n"
             "parsed = []\n"
             "def counting(self, _parse=docscrape.NumpyDocString._parse):\n"
             "    parsed.append(1)\n"
             "    return _parse(self)\n"
             "docscrape.NumpyDocString._parse = counting\n")
    argv = _small_recover_argv(tmp_path) + ["--no-report", "--threads", "1"]
    out = _console_script(argv + ["--out", str(tmp_path / "run.npz")], before=count, after=(
        "import scipy.ndimage\n"
        "note = 'Array API Standard Support' in scipy.ndimage.label.__doc__\n"
        "print('status', status, 'parsed', len(parsed), 'ndimage loaded:', 'scipy.ndimage' in sys.modules, note)\n"))
    assert "status 0 parsed 0 ndimage loaded: True True" in out, out[-2000:]
    control = _fresh_python(count + "import mi_bivariate.cli as cli\n"
                            f"assert cli.main({argv!r} + ['--out', {str(tmp_path / 'main.npz')!r}]) == 0\n"
                            "print('parsed', len(parsed))\n", ROOT)
    assert control.returncode == 0, control.stdout[-2000:] + control.stderr[-2000:]
    assert int(control.stdout.split("parsed")[-1]) > 100, control.stdout[-2000:]
    with np.load(tmp_path / "run.npz") as a, np.load(tmp_path / "main.npz") as b:
        assert np.array_equal(a["table"], b["table"])


def test_plain_scipy_docstrings_keep_the_text_and_notes_and_restore_scipys_parser_once_all_blocks_end():
    """Within ``process.plain_scipy_docstrings``, a function that scipy's decorators extend keeps its own
    docstring, followed by what they append (here ``_apply_over_batch``'s note on batches, as
    ``scipy.linalg`` decorates at import); blocks nest or overlap (entered twice, left in either order) and
    ``FunctionDoc``'s own methods, which parse, are back once the last ends."""
    from scipy._lib import _docscrape, _util

    def solve_like(a, b):
        """Solve something.

        Parameters
        ----------
        a : array_like
            The matrix.
        b : array_like
            The right-hand side.
        """
        return a

    init, text = vars(_docscrape.FunctionDoc)["__init__"], vars(_docscrape.FunctionDoc)["__str__"]
    parsed = _util._apply_over_batch(("a", 2), ("b", 1))(solve_like)
    for order in ((0, 1), (1, 0)):
        blocks = [process.plain_scipy_docstrings(), process.plain_scipy_docstrings()]
        blocks[0].__enter__()
        blocks[1].__enter__()
        plain = _util._apply_over_batch(("a", 2), ("b", 1))(solve_like)
        blocks[order[0]].__exit__(None, None, None)
        assert vars(_docscrape.FunctionDoc)["__init__"] is not init  # one block still open
        blocks[order[1]].__exit__(None, None, None)
        assert vars(_docscrape.FunctionDoc)["__init__"] is init and vars(_docscrape.FunctionDoc)["__str__"] is text
        assert plain.__doc__.startswith(inspect.getdoc(solve_like))
        assert "batch" in plain.__doc__ and "batch" in parsed.__doc__
        assert plain.__doc__.count("The right-hand side.") == 1
        assert plain.__name__ == parsed.__name__ and inspect.signature(plain) == inspect.signature(parsed)
        np.testing.assert_array_equal(plain(np.eye(2), np.ones(2)), np.eye(2))
    again = _util._apply_over_batch(("a", 2), ("b", 1))(solve_like)
    assert again.__doc__ == parsed.__doc__  # scipy's own rendering, as before any block
    # Begun on one side of a block's edge and rendered on the other (another thread's import meanwhile; a
    # helper's review found the first failing with an AttributeError and the second losing the text).
    before = _docscrape.FunctionDoc(solve_like)
    rendered = str(before)
    with process.plain_scipy_docstrings():
        assert str(before) == rendered  # parsed, and rendered by scipy's own
        within = _docscrape.FunctionDoc(solve_like)
    assert "Solve something." in str(within) and "The right-hand side." in str(within)
