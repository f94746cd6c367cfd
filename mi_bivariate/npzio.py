"""Reading ``.npz`` archives that may be hostile.

:func:`read_npz` checks an archive before numpy inflates anything: the zip
signature (a bare ``.npy`` array named ``.npz`` is refused), each member's
uncompressed size and its ``.npy`` header (shape x itemsize must match the
member's size and stay under a limit), and the dtype (real numbers, booleans
and strings only: no objects, complex numbers or datetimes). Only then does
``numpy.load`` (``allow_pickle=False``) read the arrays. Every problem is an
:class:`InputError` naming the file.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import numpy as np

from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError

#: Largest uncompressed array read from an archive (bytes): 1 GiB.
MAX_MEMBER_BYTES = 1 << 30
#: Largest total uncompressed size of an archive (bytes): 2 GiB.
MAX_TOTAL_BYTES = 2 << 30
#: dtype kinds accepted: bool, signed/unsigned integers, real floats, strings.
ALLOWED_KINDS = "biufUS"
_KIND_NAMES = {"c": "complex", "M": "datetime", "m": "timedelta", "O": "object", "V": "structured/void"}


def read_npz(path: PathLike, what: str = "file", required: Sequence[str] = (),
             max_member_bytes: int = MAX_MEMBER_BYTES, max_total_bytes: int = MAX_TOTAL_BYTES,
             hint: Optional[str] = None, text: Sequence[str] = ("meta",)) -> Dict[str, np.ndarray]:
    """All arrays of a ``.npz`` archive, after checking sizes and dtypes.

    Args:
        path: the archive.
        what: what the file should be, for messages (e.g. ``"bivariate BRDF file"``).
        required: member names that must be present.
        max_member_bytes, max_total_bytes: limits on the uncompressed sizes.
        hint: what to do, appended to a missing-member message.
        text: the members that may hold strings (the JSON metadata); every other member must hold
            numbers or booleans, which the readers convert to float without a second check.

    Returns:
        ``{name: array}`` (names without ``.npy``).

    Raises:
        InputError: missing file, not a zip archive (e.g. a bare ``.npy``),
            corrupt or truncated archive, a member over the size limits, a
            ``.npy`` header inconsistent with the member, a disallowed dtype,
            a missing required member, text in a member other than ``text``.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, f"{what} not found", "check the path")
    if not path.is_file():
        raise InputError(path, "not a file", "give the path of a .npz file, not of a folder")
    try:
        with open(path, "rb") as f:
            head = f.read(6)
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})", "check the file's permissions") from None
    if head.startswith(b"\x93NUMPY"):
        raise InputError(path, f"is a single .npy array, not an .npz archive: not a {what}")
    if not head.startswith(b"PK"):
        raise InputError(path, f"not a readable .npz file (no zip signature): not a {what}")
    try:
        with zipfile.ZipFile(path) as zf:
            total = 0
            for info in zf.infolist():
                name = info.filename
                if not name.endswith(".npy"):
                    raise InputError(path, f"not a readable .npz file: member {name!r} is not a .npy array")
                if info.file_size > max_member_bytes:
                    raise InputError(path, f"member {name!r} inflates to {info.file_size} bytes, over the limit "
                                           f"of {max_member_bytes} bytes", "the file is corrupt or not a "
                                                                             f"{what}")
                total += info.file_size
                if total > max_total_bytes:
                    raise InputError(path, f"archive inflates to over {max_total_bytes} bytes, the limit",
                                     f"the file is corrupt or not a {what}")
                _check_member(path, zf, info, max_member_bytes)
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: np.asarray(npz[k]) for k in npz.files}
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, f"too large to read: not a {what}") from None
    except Exception as e:  # noqa: BLE001 -- zipfile/zlib/numpy raise a dozen types on corrupt bytes
        raise InputError(path, f"not a readable .npz file ({type(e).__name__})",
                         "the file is truncated or corrupt") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(path, f"not a {what}: missing {', '.join(missing)}", hint)
    for name, array in arrays.items():
        if array.dtype.kind in "US" and name not in text:
            raise InputError(path, f"member {name!r} holds text ({array.dtype}), not numbers",
                             f"the file is corrupt or not a {what}")
    return arrays


def _check_member(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, max_member_bytes: int) -> None:
    """Check one member's ``.npy`` header against its size and the allowed dtypes (reads only the header)."""
    name = info.filename
    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise InputError(path, f"member {name!r} has an unsupported .npy version {version}")
        header_bytes = fh.tell()
    if dtype.kind not in ALLOWED_KINDS or dtype.hasobject or dtype.fields is not None:
        kind = _KIND_NAMES.get(dtype.kind, str(dtype))
        raise InputError(path, f"member {name!r} holds {kind} values ({dtype})", "expected real numbers")
    n_bytes = math.prod(int(s) for s in shape) * dtype.itemsize
    if n_bytes > max_member_bytes:
        raise InputError(path, f"member {name!r} declares {n_bytes} bytes, over the limit of {max_member_bytes}")
    if header_bytes + n_bytes != info.file_size:
        raise InputError(path, f"member {name!r} is {info.file_size - header_bytes} bytes where its header "
                               f"declares {n_bytes}", "the file is truncated or corrupt")


def provenance_dict(value: Any, source: Any) -> dict:
    """``value`` as a table's or a prior's provenance (``None``: empty): a JSON object (``dict``) whose
    ``"materials"``, where given, list names. :class:`InputError` naming ``source`` (the file, or the
    argument) for anything else: the provenance is read back (which materials a prior saw, where a table
    came from), so a list or a number there would fail later, inside the solve."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise InputError(source, f"provenance must be a JSON object, got a {type(value).__name__}",
                         "give a dict; a file holding another is corrupt or not mi_bivariate's")
    materials = value.get("materials", [])
    if isinstance(materials, (str, bytes)) or not isinstance(materials, (list, tuple)) or not all(
            isinstance(m, str) for m in materials):
        raise InputError(source, "provenance 'materials' must be a list of names",
                         "give a list of strings; a file holding another is corrupt or not mi_bivariate's")
    return dict(value)
