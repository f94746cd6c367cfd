"""BLAS thread control for numpy/scipy linear algebra.

OpenBLAS (and MKL) start one thread per core by default. On a machine where
other processes already use the cores, those threads oversubscribe them: a
1024 x 1024 Cholesky-based solve was measured at 18.3 s with the default
threads against 0.78 s single-threaded on the shared 2-core machine
(``/work/shared/field-notes.md``). :func:`blas_threads` pins the BLAS pools
for the duration of a block, with :mod:`threadpoolctl`, and restores them
afterwards. Dr.Jit's own thread pool is not affected.

The default is :data:`~mi_bivariate.process.DEFAULT_BLAS_THREADS` (1), overridable with the
environment variable ``MI_BIVARIATE_BLAS_THREADS`` (a positive integer, or
``0``/``default`` to leave the libraries' own setting alone;
:func:`~mi_bivariate.process.configured_blas_threads`). The command line's own process
also starts the libraries with that one thread (:func:`~mi_bivariate.process.one_blas_thread_at_load`).

The solve's channels are independent, and its LAPACK calls release the GIL
(:mod:`mi_bivariate.solve.lapack`), so they run on Python worker threads instead:
:func:`thread_map`, with :func:`solve_threads` workers (one per channel where two
cores are free for them; ``MI_BIVARIATE_SOLVE_THREADS`` overrides, ``1`` runs them one after
another). Each worker's BLAS calls stay single-threaded, so the cores are never
oversubscribed by more than the workers themselves.
"""

from __future__ import annotations

import contextlib
import functools
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable, Iterator, List, Optional, TypeVar

import drjit as dr

from mi_bivariate.process import configured_blas_threads, usable_cores

#: Environment variable setting :func:`solve_threads`.
SOLVE_ENV_VAR = "MI_BIVARIATE_SOLVE_THREADS"
#: Most worker threads :func:`solve_threads` gives by default: the three colour channels.
MAX_SOLVE_THREADS = 3

F = TypeVar("F", bound=Callable[..., Any])
T = TypeVar("T")
R = TypeVar("R")


@functools.lru_cache(maxsize=1)
def _controller() -> Any:
    """One :class:`threadpoolctl.ThreadpoolController` per process (scanning the libraries costs ~ms).

    It sees the BLAS libraries loaded when it is built, so numpy's and scipy's (scipy bundles its
    own OpenBLAS, the one :mod:`mi_bivariate.solve.lapack` calls) are loaded first.
    """
    import importlib

    from threadpoolctl import ThreadpoolController

    for module in ("numpy", "scipy.linalg"):  # load numpy's BLAS, and scipy's
        importlib.import_module(module)

    return ThreadpoolController()


@contextlib.contextmanager
def blas_threads(n: Optional[int] = -1) -> Iterator[None]:
    """Limit the BLAS thread pools of numpy/scipy to ``n`` threads inside the block.

    Args:
        n: threads; ``-1`` (default): :func:`~mi_bivariate.process.configured_blas_threads`; ``None``: no limit
            (the block runs with whatever is in force).

    Nested blocks are fine: each restores what it found.
    """
    if n == -1:
        n = configured_blas_threads()
    if n is None:
        yield
        return
    with _controller().limit(limits=int(n), user_api="blas"):
        yield


def with_blas_threads(func: F) -> F:
    """Decorator: run ``func`` inside :func:`blas_threads` (the configured thread count)."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with blas_threads():
            return func(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


@contextlib.contextmanager
def jit_threads(n: Optional[int]) -> Iterator[None]:
    """Dr.Jit's thread count ``n`` inside the block (``None``: unchanged), restored after it (the CLI's
    ``--threads``), so that a command run in a process that goes on (tests, notebooks) leaves it as it
    was: left at 1, the next ``mi.Bitmap`` EXR write in that process never returns."""
    if n is None:
        yield
        return
    before = dr.thread_count()
    dr.set_thread_count(n)
    try:
        yield
    finally:
        dr.set_thread_count(before)


def pin_process_threads(n: int) -> None:
    """For a process that exists for one job (an evaluation worker): ``n`` BLAS/OpenMP threads
    (numpy's and scipy's pools, through :mod:`threadpoolctl`) and ``n`` solve workers
    (:data:`SOLVE_ENV_VAR`) for the rest of the process. Not restored: use :func:`blas_threads`
    and :func:`solve_thread_limit` in a process that goes on."""
    os.environ[SOLVE_ENV_VAR] = str(int(n))
    _controller().limit(limits=int(n))   # applied at construction; kept, never restored


_solve_limit: Optional[int] = None


@contextlib.contextmanager
def solve_thread_limit(n: Optional[int]) -> Iterator[None]:
    """At most ``n`` solve workers inside the block (``None``: no change; nested limits: the smaller),
    whatever :func:`solve_threads` would give; e.g. the CLI's ``--threads``."""
    global _solve_limit
    old = _solve_limit
    _solve_limit = old if n is None else max(1, int(n)) if old is None else min(old, max(1, int(n)))
    try:
        yield
    finally:
        _solve_limit = old


def solve_threads() -> int:
    """Worker threads for the solve's independent channels: ``MI_BIVARIATE_SOLVE_THREADS`` (a positive
    integer), else, with single-threaded BLAS (inside :func:`blas_threads`), :data:`MAX_SOLVE_THREADS`
    (one per channel) on two or more cores; with more BLAS threads, the cores shared out among them.
    Measured on the 2-core VM: two workers with two BLAS threads each ran the solve 3x slower than
    with one each; three workers with one each beat two by 10%. Inside :func:`solve_thread_limit`,
    at most its limit."""
    text = os.environ.get(SOLVE_ENV_VAR, "").strip()
    try:
        n = int(text) if text else 0
    except ValueError:
        n = 0
    if n <= 0:
        cores = usable_cores()
        blas = [lib.num_threads for lib in _controller().select(user_api="blas").lib_controllers]
        # With single-threaded BLAS, one worker per channel where two cores are free: three CPU-bound
        # workers on two cores balance the three channels (0.38 s against 0.42 s with two workers, 0.67 s
        # with one). With more BLAS threads each, never more threads than cores.
        per_worker = max(blas + [1])
        n = MAX_SOLVE_THREADS if per_worker == 1 and cores >= 2 else max(1, min(MAX_SOLVE_THREADS,
                                                                               cores // per_worker))
    return n if _solve_limit is None else min(n, _solve_limit)


def thread_map(fn: Callable[[T], R], items: Iterable[T], threads: Optional[int] = None) -> List[R]:
    """``[fn(item) for item in items]``, on up to ``threads`` worker threads (default
    :func:`solve_threads`), in the items' order; the first exception is raised.

    An error (or Ctrl-C) in one item cancels the items not yet started, then is raised once the
    running ones end (a thread cannot be interrupted). Only worth it for work that releases the
    GIL (LAPACK through :mod:`mi_bivariate.solve.lapack`, numpy's large products). The BLAS thread limit in force (:func:`blas_threads`) applies to
    every worker.
    """
    items = list(items)
    threads = solve_threads() if threads is None else max(1, int(threads))
    if threads == 1 or len(items) <= 1:
        return [fn(item) for item in items]
    pool = ThreadPoolExecutor(max_workers=min(threads, len(items)))
    try:
        return list(pool.map(fn, items))
    finally:
        # On an error (or Ctrl-C) items not yet started are dropped; running ones cannot be stopped.
        pool.shutdown(wait=True, cancel_futures=True)
