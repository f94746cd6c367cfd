"""What a process that exists for the toolkit's work sets for itself: its BLAS libraries start with the one
thread its linear algebra uses (:func:`one_blas_thread_at_load`), glibc keeps freed memory
(:func:`keep_freed_memory`), the kernel's transparent huge pages off (:func:`no_huge_pages`), the
modules that scipy's import loads for nothing run on first use (:func:`defer_unused_modules`);
and a worker process ends with the process that started it (:func:`die_with_parent`). Likewise
Dr.Jit's rewrite of Mitsuba's ``@dr.syntax`` functions, on their first call
(:func:`syntax_on_first_call`, a block: also where any process selects a variant), and scipy's docstrings
extended without parsing them (:func:`plain_scipy_docstrings`, a block).

Each changes the whole process and is measured on the 2-core VM the project runs on (docs/recovery.md
Rounds 35 and 36). The command line calls them in a process of its own (:func:`mi_bivariate.cli.main`);
a program importing the toolkit is left as it is, unless it calls them itself, e.g. a notebook::

    from mi_bivariate import process
    process.no_huge_pages()       # before the first large array: its first recover ~2x faster here

The first three return whether they changed anything, and leave the process alone where the user set
the matching variable (``OPENBLAS_NUM_THREADS``, ``MALLOC_*``, ``NUMPY_MADVISE_HUGEPAGE``) or the platform
lacks the switch; :func:`defer_unused_modules` leaves a module alone that is already loaded.
"""
from __future__ import annotations

import contextlib
import ctypes
import functools
import importlib.util
import inspect
import os
import signal
import sys
import threading
import time
import types
from typing import Callable, Iterator, Optional

#: BLAS threads in the toolkit's linear algebra (:func:`mi_bivariate.threads.blas_threads`) when
#: :data:`BLAS_THREADS_ENV_VAR` does not say otherwise.
DEFAULT_BLAS_THREADS = 1
#: Environment variable overriding :data:`DEFAULT_BLAS_THREADS`: a positive integer, or ``0`` /
#: ``default`` / ``none`` to leave the libraries' own setting alone.
BLAS_THREADS_ENV_VAR = "MI_BIVARIATE_BLAS_THREADS"
#: The variables by which BLAS libraries size their thread pools as they load (OpenBLAS's, MKL's).
BLAS_LOAD_ENV_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def configured_blas_threads() -> Optional[int]:
    """BLAS threads to use: :data:`BLAS_THREADS_ENV_VAR` or :data:`DEFAULT_BLAS_THREADS`; ``None``: leave
    the libraries alone (also for ``0`` or a negative number; text that is not a number reads as the default)."""
    text = os.environ.get(BLAS_THREADS_ENV_VAR, "").strip().lower()
    if not text:
        return DEFAULT_BLAS_THREADS
    if text in ("0", "default", "none"):
        return None
    try:
        n = int(text)
    except ValueError:
        return DEFAULT_BLAS_THREADS
    return n if n > 0 else None


def one_blas_thread_at_load() -> bool:
    """Have the BLAS libraries start with one thread (:data:`BLAS_LOAD_ENV_VARS` set to ``1``) where the
    toolkit's own BLAS setting is one thread (:func:`configured_blas_threads`, the default). Returns
    whether it set anything. Call it before numpy loads (afterwards it changes nothing and returns False).

    The command line runs its linear algebra with one BLAS thread (:func:`mi_bivariate.threads.blas_threads`:
    threads of its own run the solve's channels). OpenBLAS, loaded by numpy and again by scipy (each has
    its own copy), starts a thread per core anyway, and those threads busy-wait for work for a while
    after they start and after every change of their number, which each ``blas_threads`` block makes
    twice: CPU spent on no work. Sampled with ``perf`` in a ``recover --no-report`` (256 px, 2026-12-08,
    this 2-core AMD EPYC VM): 0.26 s of its ~4 s of CPU were OpenBLAS's idle loop, most of it while the
    pipeline loaded, when the second core is idle anyway. Measured with one thread from the start
    (docs/recovery.md Round 41): ``recover --no-report``'s CPU 3.97 -> 3.52 s and 3.73 -> 3.61 s
    (medians of two sets of eight alternating processes) and the same tables bit for bit, but no change
    in its wall time (A/B 0.99x and 1.03x, 12 rounds each; with the report 1.00x); ``learn-prior`` of
    the 73 shared materials the same wall time with half the CPU (user 5.0 -> 2.5 s); ``evaluate
    --quick`` 35.3 -> 33.6 s (one pair).

    A variable the user set is left as it is, as is every variable where :data:`BLAS_THREADS_ENV_VAR`
    asks for more threads or for the libraries' own. The processes this one starts inherit it (the
    report's worker, an evaluation's workers) and start single-threaded too (an evaluation's worker then
    takes its job's share of the cores, :func:`mi_bivariate.threads.pin_process_threads`). OpenBLAS reads
    ``OPENBLAS_NUM_THREADS`` before ``GOTO_NUM_THREADS`` and ``OMP_NUM_THREADS``, so a count given only
    through those two is overridden here; set ``OPENBLAS_NUM_THREADS`` (or ``MI_BIVARIATE_BLAS_THREADS``)
    to keep one.
    The console script and ``python -m mi_bivariate.cli`` call this first (:mod:`mi_bivariate.__main__`);
    a program importing the toolkit keeps the libraries' default.
    """
    if "numpy" in sys.modules or configured_blas_threads() != 1:
        return False
    unset = [name for name in BLAS_LOAD_ENV_VARS if not os.environ.get(name, "").strip()]  # blank: as unset
    for name in unset:
        os.environ[name] = "1"
    return bool(unset)


#: glibc's ``mallopt`` parameters (``<malloc.h>``) and the values :func:`keep_freed_memory` sets.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
MALLOC_SETTINGS = ((M_ARENA_MAX, 1), (M_MMAP_THRESHOLD, 32 * 2**20), (M_TRIM_THRESHOLD, 2**31 - 1))
#: The environment variables by which a user sets glibc's allocator: with any of them, or a
#: ``glibc.malloc`` tunable in ``GLIBC_TUNABLES``, the allocator is left as the user chose.
MALLOC_ENV_VARS = ("MALLOC_ARENA_MAX", "MALLOC_ARENA_TEST", "MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_",
                   "MALLOC_TOP_PAD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Have glibc's allocator keep what the command frees for its next arrays (one arena for every
    thread, arrays up to 32 MiB from the heap, the heap never trimmed). Returns whether it could
    (glibc only; elsewhere nothing changes).

    The solve, the normal equations and the adequacy test allocate and free many arrays of 1-30 MB
    on worker threads. By default each thread has its own arena, which glibc trims, and arrays
    above a moving threshold are mapped and unmapped one by one: every new array's pages are
    faulted in afresh (~55,000 page faults in one ``recover``), and on this project's 2-core VM such
    a fault, with another thread mapping and unmapping beside it, costs tens of microseconds of
    system time. Measured, ``recover --no-report`` in fresh processes (2026-12-07, this 2-core AMD
    EPYC VM, nothing else running, these settings as ``MALLOC_*`` environment variables, with the
    trim threshold at 4 GiB, six alternating rounds): system time 0.40-4.3 s (median 0.68) -> 0.22-1.5 s (median 0.29), page
    faults ~55,000 -> ~47,000, wall 2.32-5.87 s (median 2.59) -> 2.17-3.45 s (median 2.40). The
    process's peak memory is what its largest moment needs either way; what it freed stays
    reserved until it ends. The command line does this in its own process for the commands it was
    measured on (:data:`mi_bivariate.cli.KEEP_FREED_MEMORY_COMMANDS`), and not where the user set the allocator
    (:data:`MALLOC_ENV_VARS`) or on a 32-bit build (whose largest mmap threshold is 512 KiB).
    Called before any other thread has allocated: ``M_ARENA_MAX`` binds the threads that allocate
    afterwards, but a new thread first takes the arena of one that has ended. (OpenBLAS's threads,
    where they exist (:func:`one_blas_thread_at_load`), are idle by then and have not allocated.)
    """
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(name in os.environ for name in MALLOC_ENV_VARS) or "glibc.malloc." in tunables:
        return False
    if ctypes.sizeof(ctypes.c_void_p) != 8:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # not glibc (macOS; Windows refuses CDLL(None))
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in MALLOC_SETTINGS)


#: numpy's documented switch for its huge-page advice: a user who set it to a number other than 0 asked
#: for huge pages, and :func:`no_huge_pages` leaves the process as it is.
HUGEPAGE_ENV_VAR = "NUMPY_MADVISE_HUGEPAGE"
#: ``<linux/prctl.h>``: the process's transparent huge pages off (Linux >= 3.15).
PR_SET_THP_DISABLE = 41


def no_huge_pages() -> bool:
    """Turn transparent huge pages off for this process (Linux's ``prctl(PR_SET_THP_DISABLE)``), so that
    the arrays numpy (4 MiB and more) and Dr.Jit (its large host buffers) advise onto huge pages
    (``madvise(MADV_HUGEPAGE)``) get the kernel's 4 KiB pages. Returns whether it did (Linux only;
    elsewhere nothing changes). Pages from a reserved ``hugetlbfs`` pool (which Dr.Jit asks for first,
    ``MAP_HUGETLB``; this project's VM has none) are not transparent ones and stay as they are.

    Where the kernel's huge pages are ``madvise`` (numpy's default on Linux >= 4.6 then advises every
    large array; Dr.Jit advises its own), each advised array's first touch takes fresh 2 MiB pages.
    On a VM whose host backs free memory lazily that can cost far more than the 4 KiB pages the kernel
    recycles: touching an 80 MB numpy array took 0.30-0.66 s of system time with the advice against
    0.04-0.05 s without it in fresh processes after a pause, though back to back it can be cheaper with
    it (0.01-0.02 s, a review's measurement). A ``recover`` touches ~0.4 GB of new memory (its
    ``(M, N, 3)`` lighting matrix alone is 80 MB), and over whole commands turning them off paid
    (2026-12-07, this 2-core AMD EPYC VM, nothing else running; docs/recovery.md Round 36):

    - ``recover --no-report``, ten fresh processes back to back each way: wall median 2.70 s (2.03-3.12,
      system time 0.25-1.40 s) with huge pages, 2.32 s (2.19-2.53, system time 0.40-0.46 s) without;
    - the same, five alternating pairs, both sides with numpy's advice off (``NUMPY_MADVISE_HUGEPAGE=0``
      does that alone): wall 2.86-3.47 s -> 2.46-2.88 s, the lighting matrix 0.96-1.63 s -> 0.71-0.88 s
      (Dr.Jit's buffers);
    - ``recover-batch`` of four photos, three pairs: 7.60-9.30 s -> 6.48-7.16 s;
    - ``render gold-metallic-paint3 --resolution 256 --spp 64``, three pairs: 4.33-5.49 s -> 3.67-4.98 s;
    - ``evaluate --quick`` (one process, minutes of compute), two pairs: 39.4 and 33.7 s -> 32.2 and
      33.9 s, the same user time (no cost from the smaller pages' TLB misses).

    Not where the user set :data:`HUGEPAGE_ENV_VAR` to a number other than 0 (read as numpy reads it)
    or to something that is not a number. The processes this one starts afterwards inherit the setting
    (an evaluation's workers). The command line does this in its own process for every command
    (:func:`mi_bivariate.cli.main`); a program importing the toolkit keeps the kernel's and numpy's
    defaults unless it calls this itself (a notebook on such a VM: its first ``recover`` took 3.8-4.3 s
    with huge pages, 1.85-1.9 s without).
    """
    if not sys.platform.startswith("linux"):
        return False
    setting = os.environ.get(HUGEPAGE_ENV_VAR)
    if setting is not None:
        try:
            if int(setting) != 0:  # as numpy reads it: "1", " 1", "+01" ask for huge pages
                return False
        except ValueError:  # not a number: the user meant something; leave the process as it is
            return False
    return _prctl(PR_SET_THP_DISABLE, 1)


def _prctl(option: int, value: int) -> bool:
    """Linux's ``prctl(option, value, 0, 0, 0)`` for this process; whether it succeeded (``False`` where the C
    library has none)."""
    try:
        prctl = ctypes.CDLL(None).prctl
    except (OSError, AttributeError, TypeError):
        return False
    prctl.argtypes, prctl.restype = (ctypes.c_int,) + (ctypes.c_ulong,) * 4, ctypes.c_int
    return prctl(option, value, 0, 0, 0) == 0


#: Modules that loading scipy imports and a default ``recover`` need not run (see
#: :func:`defer_unused_modules`): numpy's submodules that scipy's vendored ``array_api_compat``
#: touches, and ``scipy.special``, which ``scipy.ndimage`` imports for a function the toolkit does not call.
DEFERRED_MODULES = ("numpy.f2py", "numpy.testing", "numpy.ma", "numpy.polynomial", "scipy.special")


def defer_unused_modules() -> None:
    """Register :data:`DEFERRED_MODULES` as lazy modules (:class:`importlib.util.LazyLoader`, the
    standard library's lazy import): each loads on its first use, where a command uses it, and not before.

    - ``import scipy.linalg`` loads scipy's vendored ``array_api_compat.numpy``, which copies every
      public attribute of numpy (``hasattr`` on each name of ``dir(numpy)``) and so imports each of
      numpy's lazily loaded submodules: ``numpy.f2py``, ``numpy.testing`` (and ``unittest``),
      ``numpy.ma``, ``numpy.polynomial``. Measured, three fresh processes each, ``import
      mi_bivariate.commands`` with bytecode compiled (2026-12-07, this 2-core AMD EPYC VM): 0.53-0.62 s
      with them, 0.45-0.53 s without. (numpy's own ``np.unique`` asks ``numpy.ma`` whether its argument
      is masked, so a recovery loads that one later anyway, ~8 ms, on its main thread.)
    - ``scipy.ndimage`` (the sphere fit's and the noise estimate's image operations) imports
      ``scipy.special`` (in ``_interpolation``, for ``rotate`` alone), which formats the docstrings of
      its ~300 functions at import (scipy 1.17). Measured, six fresh processes each, ``from scipy
      import ndimage`` and a call of each ndimage function the pipeline uses, after ``import
      mi_bivariate.commands``:
      0.108-0.121 s with it loaded, 0.061-0.108 s (median 0.07) lazy (2026-12-07, same VM). A default
      ``recover`` never runs its code; ``--refine-sphere`` (``scipy.optimize``), ``--probe-rotation``
      (``scipy.spatial.transform``) and the evaluation's baselines load it, on the main thread.

    The command line does this in its own process (:func:`mi_bivariate.cli.main`'s ``own_process``):
    a program importing the toolkit keeps numpy and scipy as they made themselves.
    Modules already loaded, or already an attribute of their package, are left alone. In the Python
    this runs on (3.11; CPython made it thread-safe later, gh-114763) a lazy module's first use is
    not thread-safe: a second thread touching it meanwhile finds it empty (measured: three threads
    asking for ``scipy.special.erf`` at once fail every time). So the commands' worker threads
    (``threads.thread_map``) import nothing: a test records every import made off the main thread in
    a default ``recover`` and finds none. The one exception, the solve's rare ``scipy.optimize``
    fallback on a channel's thread (``solve.nnls``), loads ``scipy.special`` inside that module's
    import, whose lock the other channels wait on; and what uses ``numpy.ma`` (matplotlib, trimesh,
    distributed) is imported on the main thread. Keep it so.
    """
    for full in DEFERRED_MODULES:
        package, _, name = full.rpartition(".")
        parent = importlib.import_module(package)  # numpy is loaded already; scipy here (the pipeline needs it)
        if full in sys.modules or name in vars(parent):
            continue
        spec = importlib.util.find_spec(full)
        if spec is None or spec.loader is None:
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[full] = module
        spec.loader.exec_module(module)  # lazily: the module's code runs on its first attribute access
        setattr(parent, name, module)  # the package's own __getattr__ (which imports) is not asked


#: The process-wide changes of :func:`syntax_on_first_call` and :func:`plain_scipy_docstrings` now made:
#: ``name -> [open blocks, what undoes the change]``.
_PATCH_LOCK = threading.Lock()
_patches: dict = {}


@contextlib.contextmanager
def _shared_change(name: str, make: Callable[[], Callable[[], None]]) -> Iterator[None]:
    """A block within which a process-wide change stays made: ``make`` makes it and returns what undoes it.
    Blocks of one ``name`` may nest or overlap, in any thread: the first to open makes the change (once, not a
    change of the change), the last to end undoes it."""
    with _PATCH_LOCK:
        entry = _patches.setdefault(name, [0, None])
        if entry[0] == 0:
            entry[1] = make()
        entry[0] += 1
    try:
        yield
    finally:
        with _PATCH_LOCK:
            entry[0] -= 1
            if entry[0] == 0:
                del _patches[name]
                entry[1]()


@contextlib.contextmanager
def syntax_on_first_call() -> Iterator[None]:
    """Within the block, ``@dr.syntax`` (Dr.Jit's rewrite of a function's loops and conditionals
    from its source: ``inspect.getsource``, ``ast``, ``compile``) rewrites each function it decorates
    on that function's first call, not at its definition.

    Mitsuba's Python modules decorate methods they define at import: ``mitsuba.python.ad.projective``
    when ``mitsuba`` is imported, and the AD integrators (``prb``, ``prb_basic``, ``prbvolpath``, ...)
    again at every start of a JIT variant. A recovery, which renders nothing, never calls them.
    The decorated name holds a wrapper (``functools.wraps``: the same name, docstring and signature)
    that calls ``drjit.syntax``'s own rewrite of the function once, under a lock, and then always
    that rewritten function: the code that runs is the one the decorator would have made
    (``tests/test_gradients.py`` renders ``prb`` and its gradient both ways). ``drjit.syntax`` is
    restored when the last open block ends (blocks may nest or overlap, in any thread; meanwhile a
    decoration in another thread is deferred too). Measured on this project's 2-core VM (three fresh
    processes each): the start of ``llvm_ad_rgb`` took 0.13-0.18 s eagerly and 0.03 s so; ``import
    mitsuba`` 0.04-0.06 s and 0.03 s. :func:`mi_bivariate.variants.ensure_variant` starts a variant
    within it in any process; the command line also loads its pipeline within it, in a process of its
    own (:func:`mi_bivariate.cli.main`).
    """
    dr = importlib.import_module("drjit")  # the pipeline loads it anyway

    def make() -> Callable[[], None]:
        rewrite = dr.syntax
        dr.syntax = _deferred_syntax(rewrite)
        return lambda: setattr(dr, "syntax", rewrite)

    with _shared_change("drjit.syntax", make):
        yield


def _deferred_syntax(rewrite: Callable) -> Callable:
    """A stand-in for ``drjit.syntax`` (:func:`syntax_on_first_call`) whose wrappers call ``rewrite`` once."""
    def deferred(f: Optional[types.FunctionType] = None, **options) -> Callable:
        if f is None:  # @dr.syntax(recursive=True)
            return lambda g: deferred(g, **options)
        rewritten = []
        lock = threading.Lock()

        @functools.wraps(f)
        def on_first_call(*args, **kwargs):
            if not rewritten:
                with lock:
                    if not rewritten:
                        rewritten.append(rewrite(f, **options))
            return rewritten[0](*args, **kwargs)

        return on_first_call

    return deferred


@contextlib.contextmanager
def plain_scipy_docstrings() -> Iterator[None]:
    """Within the block, the decorators with which scipy extends its functions' docstrings at import append
    their notes to the docstring as plain text, instead of parsing and re-rendering each whole docstring.

    scipy 1.17 decorates many functions as their module is imported (``xp_capabilities`` on each of
    ``scipy.ndimage``'s ~75 functions, ``_apply_over_batch`` on ~70 of ``scipy.linalg``'s) with a note that
    it inserts by parsing the function's numpydoc docstring (``scipy._lib._docscrape.FunctionDoc``, a
    pure-Python parser) and rendering it again: ~0.05 s for the ~150 functions that a ``recover`` decorates
    so (measured: ``import scipy.linalg, scipy.ndimage`` after :func:`defer_unused_modules`, six fresh
    processes each, 0.13-0.21 s (median 0.154) with the parse and 0.09-0.12 s (median 0.102) without,
    2026-12-07, this project's 2-core VM; ``recover --no-report`` end to end 2.210 -> 2.164 s, 12 rounds
    of ``benchmarks/ab_revision.py``). Here ``FunctionDoc`` keeps the docstring as written and appends what
    the decorators add to its summary and notes; what they change in its parameter list (``rng``'s text)
    is dropped. The functions, their names and signatures are scipy's own; only the text of those
    docstrings differs, in a process where nothing reads them. ``FunctionDoc``'s own methods are restored
    when the last open block ends (blocks may nest or overlap), so what is loaded after it is documented
    as scipy documents it. Where scipy has no such parser (another version), the block changes nothing.
    The command line runs a whole command within it, in a process of its own
    (:func:`mi_bivariate.cli.main`): what the command loads on first use (the sphere fit's
    ``scipy.ndimage``, ``scipy.special``, ``scipy.optimize``) is extended so too.
    """
    try:
        function_doc = importlib.import_module("scipy._lib._docscrape").FunctionDoc
        sections = dict(function_doc.sections)
    except (ImportError, AttributeError, TypeError):  # not the scipy this was measured on: leave it be
        function_doc = None
    if function_doc is None:
        yield
        return

    def __init__(self, func, role="func", doc=None, config=None):  # noqa: N807 (FunctionDoc's signature)
        self._f, self._role = func, role
        self._plain_text = (inspect.getdoc(func) if doc is None else doc) or ""
        self._parsed_data = {key: type(value)() for key, value in sections.items()}
        self._parsed_data["Summary"] = self._plain_text.split("\n")  # what scipy's own __str__ would show of it

    own: dict = {}  # FunctionDoc's own methods, once this block's are the ones installed

    def __str__(self):  # noqa: N807
        if not hasattr(self, "_plain_text"):  # parsed before the block began (another thread's)
            return own["__str__"](self)
        added = [str(text) for key in ("Extended Summary", "Notes") for text in self._parsed_data[key]]
        return "\n" + "\n\n".join([self._plain_text, *added])  # the decorators drop the first line (a signature)

    def make() -> Callable[[], None]:
        own.update(__init__=vars(function_doc)["__init__"], __str__=vars(function_doc)["__str__"])
        function_doc.__init__, function_doc.__str__ = __init__, __str__

        def undo() -> None:
            for name, method in own.items():
                setattr(function_doc, name, method)
        return undo

    with _shared_change("scipy FunctionDoc", make):
        yield


def usable_cores() -> int:
    """The CPUs this process may run on (its affinity where the platform says, else the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


#: ``<linux/prctl.h>``: the signal a process gets when its parent ends.
PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int, interval: float = 0.5) -> None:
    """End this worker process when ``parent`` (the process that started it, ``os.getpid()`` there) ends,
    killed included: SIGTERM from the kernel on Linux (``prctl(PR_SET_PDEATHSIG)``), and everywhere a
    daemon thread that checks ``os.getppid()`` every ``interval`` seconds. A worker whose parent has
    already gone ends at once. On Linux the kernel's signal comes when the parent's *thread* that started
    the worker ends: start workers from a thread that lives as long as they should (the command line's
    main thread).
    """
    if sys.platform.startswith("linux"):
        _prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(interval)
        os._exit(1)

    threading.Thread(target=watch, name="mi-bivariate-parent-watch", daemon=True).start()
