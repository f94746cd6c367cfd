"""User-facing errors.

Every problem with a user's input is raised as :class:`InputError` whose message
is one line: the file (or argument) and what is wrong with it, and where it
helps, what to do. The CLI prints that line alone; library users can catch
the class.
"""

from __future__ import annotations

import os
from typing import Any, Mapping, Optional

import numpy as np

from mi_bivariate.common import PathLike


class InputError(ValueError):
    """Bad input: a file, an image, a probe or a parameter the toolkit cannot use."""

    def __init__(self, source: Optional[PathLike], problem: str, hint: Optional[str] = None):
        self.source = None if source is None else os.fspath(source)
        self.problem = problem
        self.hint = hint
        msg = problem if self.source is None else f"{self.source}: {problem}"
        if hint:
            msg = f"{msg} ({hint})"
        super().__init__(msg)

    def within(self, source: Optional[PathLike], part: str) -> "InputError":
        """The same problem named as a part of ``source`` (``camera: intrinsics: ...``): for a front door
        whose argument holds the object that was refused."""
        return InputError(source, f"{part}: {self.problem}", self.hint)


def renamed(message: str, names: Mapping[str, str]) -> Optional[str]:
    """``message`` with its leading internal source name (``"image: ..."``, ``"image 1: ..."``,
    ``"alpha: ..."``: the ``source`` of an :class:`InputError` or the start of an
    :class:`InputWarning`) replaced by what the user knows it as (``names[name]``: their file, their
    option, the material under its probe); ``None`` when the message starts with none of ``names``."""
    for name, user_name in names.items():
        if message.startswith(name + ":"):
            return user_name + message[len(name):]
    return None


class InputWarning(UserWarning):
    """Input that is usable but suspicious (LDR images, dropped pixels, weak lighting)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, a job scheduler, ``kill``) in a ``mi-bivariate`` process
    (:func:`mi_bivariate.atomic.stop_on_signal`): raised where the command is, so that it stops as after
    Ctrl-C, its outputs' temporary files removed and the earlier outputs as they were."""


def array_from(value: Any, source: Optional[PathLike], what: str = "an array of numbers", dtype: Any = None,
               hint: Optional[str] = None) -> np.ndarray:
    """``np.asarray(value, dtype)``, or :class:`InputError` naming ``source`` where numpy cannot make one array
    of real numbers of ``value`` (nested lists of unequal lengths, words where numbers go, a dict, integers
    beyond ``dtype``'s range, complex numbers for a real ``dtype``): numpy's own ``ValueError``,
    ``TypeError`` or ``OverflowError`` (or a silently dropped imaginary part) would otherwise leave a front
    door's shape and type checks unreached. ``what``: what the argument must be, for the message (e.g.
    ``"an (H, W, 3) image"``); ``hint``: what to do."""
    try:
        array = np.asarray(value)
        if dtype is not None and np.iscomplexobj(array) and not np.issubdtype(np.dtype(dtype), np.complexfloating):
            raise TypeError("complex")
        return array if dtype is None else array.astype(dtype, copy=False)
    except (TypeError, ValueError, OverflowError):
        raise InputError(source, f"expected {what}, got a {type(value).__name__} that is not one array of real numbers "
                                 "(nested lists of unequal lengths, or values that are not numbers)", hint) from None
