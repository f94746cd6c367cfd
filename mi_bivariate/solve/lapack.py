"""LAPACK's Cholesky routines, called without holding the GIL.

scipy's ``scipy.linalg.lapack`` wrappers hold Python's global interpreter lock while
LAPACK runs, so the solve's channels, which are independent, could not use a second
core: four independent 1024 x 1024 ``dpotrf`` on two Python threads ran 1.12x faster
than one after another (``docs/recovery.md``, Round 5). The same routines are reached
here through the function pointers scipy exports for Cython
(``scipy.linalg.cython_lapack.__pyx_capi__``, the interface numba uses too) and called
with :mod:`ctypes`, which releases the GIL for the call: the same LAPACK, the same
answers, and two threads run two factorisations at once (1.6-1.8x on the 2-core VM).

A factor is ``(c, lower)`` as :func:`scipy.linalg.cho_factor` returns it, so the two
are interchangeable: ``c``'s lower (``lower=True``) or upper triangle, in numpy's
indexing, holds the Cholesky factor; the other triangle holds leftovers. Routines
that write return new arrays unless ``overwrite`` says otherwise.

Where scipy does not export the routines (a build without ``cython_lapack``), every
function here falls back to ``scipy.linalg``'s wrappers (same results, GIL held);
:data:`GIL_FREE` says which is in use.
"""

from __future__ import annotations

import ctypes
from typing import Callable, Dict, Tuple

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack

_P_INT = ctypes.POINTER(ctypes.c_int)
#: Fortran signatures (every argument by pointer) of the routines used.
_SIGNATURES = {
    "dpotrf": (ctypes.c_char_p, _P_INT, ctypes.c_void_p, _P_INT, _P_INT),
    "dpotrs": (ctypes.c_char_p, _P_INT, _P_INT, ctypes.c_void_p, _P_INT, ctypes.c_void_p, _P_INT, _P_INT),
    "dpotri": (ctypes.c_char_p, _P_INT, ctypes.c_void_p, _P_INT, _P_INT),
    "dtrtri": (ctypes.c_char_p, ctypes.c_char_p, _P_INT, ctypes.c_void_p, _P_INT, _P_INT),
}


def _functions() -> Dict[str, Callable[..., None]]:
    """The routines of :data:`_SIGNATURES` from scipy's Cython capsules ({} if unavailable)."""
    try:
        from scipy.linalg import cython_lapack

        capsules = cython_lapack.__pyx_capi__
        # Private prototypes: setting restype/argtypes on ctypes.pythonapi's shared function objects
        # would change them for every other ctypes user in the process.
        get_name = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
        get_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
            ("PyCapsule_GetPointer", ctypes.pythonapi))
        out = {}
        for name, argtypes in _SIGNATURES.items():
            capsule = capsules[name]
            address = get_pointer(capsule, get_name(capsule))
            if not address:
                return {}
            out[name] = ctypes.CFUNCTYPE(None, *argtypes)(address)
        return out
    except (ImportError, AttributeError, KeyError, TypeError, ValueError):
        return {}


_LAPACK = _functions()
#: ``True`` when the routines run without the GIL (scipy's Cython LAPACK is reachable).
GIL_FREE = bool(_LAPACK)


def _fortran_view(c: np.ndarray, lower: bool) -> Tuple[np.ndarray, bytes]:
    """``c`` as LAPACK will read it (contiguous, either order, no copy) and the ``uplo`` that
    names numpy's ``lower`` triangle in that order: a C-ordered array is its transpose to Fortran."""
    if c.flags.f_contiguous:
        return c, b"L" if lower else b"U"
    return c, b"U" if lower else b"L"


#: Largest dimension LAPACK's 32-bit integers can describe.
_MAX_DIM = 2**31 - 1


def _square_float64(a: np.ndarray, overwrite: bool, what: str = "matrix") -> np.ndarray:
    """A contiguous float64 square array: ``a`` itself when ``overwrite`` allows, else a copy.

    Raises:
        ValueError: not a real square 2-D array, or too large for LAPACK's integers.
    """
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"expected a square {what}, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"expected a real {what}, got dtype {a.dtype}")
    if a.shape[0] > _MAX_DIM or a.size > _MAX_DIM:
        raise ValueError(f"{what} of shape {a.shape} is too large for LAPACK's 32-bit integers")
    ok = (a.dtype == np.float64 and (a.flags.c_contiguous or a.flags.f_contiguous) and a.flags.writeable
          and a.dtype.isnative)
    return a if overwrite and ok else np.array(a, dtype=np.float64, order="C", copy=True)


def cho_factor(a: np.ndarray, overwrite: bool = False) -> Tuple[np.ndarray, bool]:
    """Cholesky factorisation ``a = L L^T`` (LAPACK ``dpotrf``) of a float64 SPD matrix.

    Args:
        a: ``(N, N)`` real, symmetric (only its lower triangle is read); computed in float64.
        overwrite: factorise ``a`` in place when it is a writeable contiguous float64 array.

    Returns:
        ``(c, True)``: ``L`` in ``c``'s lower triangle, as :func:`scipy.linalg.cho_factor`.

    Raises:
        numpy.linalg.LinAlgError: ``a`` is not (numerically) positive definite.
        ValueError: ``a`` is not a real square matrix.
    """
    if not GIL_FREE:
        return sla.cho_factor(a, lower=True, overwrite_a=overwrite, check_finite=False)
    c = _square_float64(np.asarray(a), overwrite)
    c, uplo = _fortran_view(c, True)
    n, info = ctypes.c_int(c.shape[0]), ctypes.c_int(0)
    if c.shape[0]:
        _LAPACK["dpotrf"](uplo, ctypes.byref(n), c.ctypes.data, ctypes.byref(n), ctypes.byref(info))
    if info.value > 0:
        raise np.linalg.LinAlgError(f"{info.value}-th leading minor not positive definite")
    if info.value < 0:
        raise ValueError(f"illegal value in argument {-info.value} of dpotrf")
    return c, True


def cho_solve(factor: Tuple[np.ndarray, bool], b: np.ndarray) -> np.ndarray:
    """``a^-1 b`` from ``factor = cho_factor(a)`` (LAPACK ``dpotrs``); ``b`` ``(N,)`` or ``(N, K)``,
    returned as a new float64 array of its shape.

    Raises:
        ValueError: a factor that is not square, or a right-hand side that does not match it.
    """
    c, lower = factor
    if not GIL_FREE:
        return sla.cho_solve(factor, b, check_finite=False)
    c = _square_float64(np.asarray(c), overwrite=True, what="factor")  # no copy when already usable
    b = np.asarray(b)
    if b.ndim not in (1, 2) or b.shape[0] != c.shape[0]:
        raise ValueError(f"right-hand side of shape {b.shape} does not match the factor's {c.shape}")
    if not (np.issubdtype(b.dtype, np.floating) or np.issubdtype(b.dtype, np.integer)) or b.size > _MAX_DIM:
        raise ValueError(f"right-hand side must be real and at most {_MAX_DIM} entries, got {b.dtype} {b.shape}")
    x = np.array(b, dtype=np.float64, order="F", copy=True)
    if x.size == 0:
        return x
    c, uplo = _fortran_view(c, lower)
    n, nrhs, info = ctypes.c_int(c.shape[0]), ctypes.c_int(1 if x.ndim == 1 else x.shape[1]), ctypes.c_int(0)
    _LAPACK["dpotrs"](uplo, ctypes.byref(n), ctypes.byref(nrhs), c.ctypes.data, ctypes.byref(n),
                      x.ctypes.data, ctypes.byref(n), ctypes.byref(info))
    if info.value != 0:
        raise ValueError(f"illegal value in argument {-info.value} of dpotrs")
    return x


def _on_factor(name: str, factor: Tuple[np.ndarray, bool], overwrite: bool,
               fallback: Callable[..., Tuple[np.ndarray, int]], *flags: bytes) -> np.ndarray:
    """LAPACK ``name`` (``uplo, *flags, n, a, lda, info``) run on the factor's triangle, in a copy
    unless ``overwrite`` allows the factor's own array; ``fallback(c, lower=, overwrite_c=)`` is
    scipy's wrapper of the same routine.

    Raises:
        numpy.linalg.LinAlgError: the routine reports a zero on the factor's diagonal.
        ValueError: the routine reports an illegal argument.
    """
    c, lower = factor
    if np.shape(c) == (0, 0):  # nothing to invert (scipy's wrappers reject n = 0)
        return np.zeros((0, 0))
    if not GIL_FREE:
        out, info = fallback(c, lower=lower, overwrite_c=overwrite)
    else:
        out, uplo = _fortran_view(_square_float64(np.asarray(c), overwrite, what="factor"), lower)
        n, status = ctypes.c_int(out.shape[0]), ctypes.c_int(0)
        if out.shape[0]:
            _LAPACK[name](uplo, *flags, ctypes.byref(n), out.ctypes.data, ctypes.byref(n), ctypes.byref(status))
        info = status.value
    if info < 0:
        raise ValueError(f"illegal value in argument {-info} of {name}")
    if info > 0:
        raise np.linalg.LinAlgError(f"{name[1:]} failed (info {info})")
    return out


def potri(factor: Tuple[np.ndarray, bool], overwrite: bool = False) -> np.ndarray:
    """``a^-1`` from ``factor = cho_factor(a)`` (LAPACK ``dpotri``), in the factor's triangle
    (numpy's indexing); the other triangle holds leftovers. ``overwrite``: in the factor's own
    array when it is a writeable contiguous float64 one (the factor is then lost).

    Raises:
        numpy.linalg.LinAlgError: the factor has a zero on its diagonal.
    """
    return _on_factor("dpotri", factor, overwrite, lapack.dpotri)


def trtri(factor: Tuple[np.ndarray, bool], overwrite: bool = False) -> np.ndarray:
    """The factor's inverse ``L^-1`` (or ``U^-1``) from ``factor = cho_factor(a)`` (LAPACK ``dtrtri``,
    N^3 / 3 flops, half of :func:`potri`), in the factor's triangle (numpy's indexing); the other
    triangle holds leftovers. ``a^-1 = L^-T L^-1`` (lower) or ``U^-1 U^-T`` (upper).
    ``overwrite``: in the factor's own array when it is a writeable contiguous float64 one.

    Raises:
        numpy.linalg.LinAlgError: the factor has a zero on its diagonal.
    """
    return _on_factor("dtrtri", factor, overwrite, lapack.dtrtri, b"N")
