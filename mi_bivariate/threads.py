"""BLAS thread control for numpy/scipy linear algebra.

OpenBLAS (and MKL) start one thread per core by default. On a machine where
other processes already use the cores, those threads oversubscribe them: a
1024 x 1024 Cholesky-based solve was measured at 18.3 s with the default
threads against 0.78 s single-threaded on the shared 2-core machine
(``/work/shared/field-notes.md``). :func:`blas_threads` pins the BLAS pools
for the duration of a block, with :mod:`threadpoolctl`, and restores them
afterwards. Dr.Jit's own thread pool is not affected.

The default is :data:`DEFAULT_BLAS_THREADS` (1), overridable with the
environment variable ``MI_BIVARIATE_BLAS_THREADS`` (a positive integer, or
``0``/``default`` to leave the libraries' own setting alone).
"""

from __future__ import annotations

import contextlib
import functools
import os
from typing import Any, Callable, Iterator, Optional, TypeVar

#: BLAS threads inside :func:`blas_threads` when neither the argument nor the environment says.
DEFAULT_BLAS_THREADS = 1
#: Environment variable overriding :data:`DEFAULT_BLAS_THREADS`.
ENV_VAR = "MI_BIVARIATE_BLAS_THREADS"

F = TypeVar("F", bound=Callable[..., Any])


@functools.lru_cache(maxsize=1)
def _controller() -> Any:
    """One :class:`threadpoolctl.ThreadpoolController` per process (scanning the libraries costs ~ms)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def configured_threads() -> Optional[int]:
    """BLAS threads to use: ``MI_BIVARIATE_BLAS_THREADS`` or the default; ``None`` = leave alone."""
    text = os.environ.get(ENV_VAR, "").strip().lower()
    if not text:
        return DEFAULT_BLAS_THREADS
    if text in ("0", "default", "none"):
        return None
    try:
        n = int(text)
    except ValueError:
        return DEFAULT_BLAS_THREADS
    return n if n > 0 else None


@contextlib.contextmanager
def blas_threads(n: Optional[int] = -1) -> Iterator[None]:
    """Limit the BLAS thread pools of numpy/scipy to ``n`` threads inside the block.

    Args:
        n: threads; ``-1`` (default): :func:`configured_threads`; ``None``: no limit
            (the block runs with whatever is in force).

    Nested blocks are fine: each restores what it found.
    """
    if n == -1:
        n = configured_threads()
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
