"""MERL ``.binary`` isotropic BRDF tables: read, write, evaluate.

File layout (Matusik et al. 2003, as read by MERL's reference ``BRDFRead``):
an int32 header ``90 90 180``, then ``3 * 90 * 90 * 180`` float64 values,
channel-major (R, G, B), each channel indexed ``[theta_h][theta_d][phi_d]``.
Stored values times :data:`MERL_SCALE` give the BRDF in 1/sr; negative values
mark missing samples.

In memory a :class:`MERLBRDF` holds ``table``, ``(90, 90, 180, 3)`` in 1/sr,
layout ``[theta_h][theta_d][phi_d][channel]``, NaN where a sample is missing.
Node positions (all radians)::

    theta_h_i = (i / 90)^2 * pi / 2     (t = i / 90: uniform in the paper's t)
    theta_d_j = j / 90 * pi / 2         (s = j / 90)
    phi_d_k   = k / 180 * pi            (phi_d folded into [0, pi))
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from pathlib import Path
from typing import Any, Callable, List, Optional, Tuple, Union

import mitsuba as mi
import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.common import PathLike
from mi_bivariate.coordinates import fold_phi_d
from mi_bivariate.errors import InputError

MERL_SHAPE: Tuple[int, int, int] = (90, 90, 180)
MERL_SCALE: Tuple[float, float, float] = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)

_HEADER_BYTES = 3 * 4
_N_VALUES = 3 * MERL_SHAPE[0] * MERL_SHAPE[1] * MERL_SHAPE[2]
MERL_FILE_BYTES = _HEADER_BYTES + 8 * _N_VALUES
# Raw value written for a missing sample (any negative value means missing).
_MISSING_RAW = -1.0
# Index slack so that a lookup exactly at a node angle never floors to the
# node below through a last-bit rounding error.
_INDEX_EPS = 1e-9
# wi.z and wo.z as above_horizon computes them are off by up to ~2e-16: a configuration exactly on the
# horizon (theta_h + theta_d = pi/2 at phi_d = 0, as at the MERL nodes (30, 80, 0) and (60, 50, 0))
# came out as +8e-17 and +1.1e-16 and counted as above it, where a model with 1/cos (Ward's lobe) is
# ~1e7 1/sr. Heights within this of 0 are on the horizon (the nearest MERL node above it is 1.7e-7 up).
_HORIZON_EPS = 1e-12


def node_angles() -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MERL node angles: ``theta_h (90,)``, ``theta_d (90,)``, ``phi_d (180,)`` float64, radians."""
    n_h, n_d, n_p = MERL_SHAPE
    theta_h = (np.arange(n_h) / n_h) ** 2 * (0.5 * math.pi)
    theta_d = np.arange(n_d) / n_d * (0.5 * math.pi)
    phi_d = np.arange(n_p) / n_p * math.pi
    return theta_h, theta_d, phi_d


def above_horizon(theta_h, theta_d, phi_d, height: float = _HORIZON_EPS) -> np.ndarray:
    """True where both wi and wo of a Rusinkiewicz configuration lie strictly above the horizon (by more
    than ``height``; by default ``_HORIZON_EPS``, the rounding of their heights: one exactly on it is not
    above it. ``height=0.0`` is the test before commit dc21ff3, which kept two MERL nodes lying on it:
    ``benchmarks/baselines_horizon.py`` rebuilds the old truths with it).

    Angles broadcast against each other (radians); phi_h is irrelevant (isotropy).
    With phi_h = 0, ``wi.z = cos td cos th - sin td sin th cos pd`` and ``wo.z``
    is the same with ``+`` (wo is wi mirrored about h).
    """
    theta_h, theta_d, phi_d = (np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d))
    along = np.cos(theta_d) * np.cos(theta_h)
    across = np.sin(theta_d) * np.sin(theta_h) * np.cos(phi_d)
    return (along - across > height) & (along + across > height)


def check_reflects(table: np.ndarray, source: Any, hint: str = "give a material that reflects light") -> None:
    """Raise :class:`InputError` naming ``source`` if a MERL ``(90, 90, 180, 3)`` table holds no positive
    value above the horizon (every value there 0 or missing; the nodes below it are never lit): such a
    material reflects no light, its photo is black, and a reduction's relative error is undefined."""
    table = np.asarray(table)
    if table.shape[:3] == MERL_SHAPE:
        table = table[geometric_mask()]
    if not np.any(table > 0.0):  # NaN (missing) compares False
        raise InputError(source, "the BRDF table holds no positive value above the horizon (every value is 0 "
                                 "or missing): it reflects no light, and the relative error of a reduction "
                                 "is undefined", hint)


def check_values(table: np.ndarray, source: Any, hint: Optional[str] = None) -> None:
    """Raise :class:`InputError` naming ``source`` unless a MERL ``(90, 90, 180, 3)`` float64 table (1/sr, NaN
    for a missing sample) is one :meth:`MERLBRDF.read` accepts: no infinite value, some light above the
    horizon, a valid sample in every channel and in all three at one node (a positive value at one such node),
    values within float32's range.
    ``hint`` replaces the hints, which speak of a file read."""
    table = np.asarray(table, np.float64)
    path = source
    if np.isinf(table).any():
        raise InputError(path, "MERL file holds infinite values", hint or "the file is corrupt")
    check_reflects(table, path, hint or hint or "check the file")
    finite = table[np.isfinite(table)]
    missing = [name for c, name in enumerate("RGB") if not np.isfinite(table[..., c]).any()]
    if missing:  # the others hold light, but no sample is valid in every channel
        raise InputError(path, f"channel {'/'.join(missing)} has no valid sample (every value there is "
                               "negative, MERL's mark of a missing sample)", hint or "check the file")
    valid = np.all(np.isfinite(table), axis=-1) & geometric_mask()
    if not np.any(valid):
        raise InputError(path, "no sample above the horizon is valid in all three colour channels (the "
                               "channels' valid samples do not overlap)", hint or "check the file")
    if not np.any(table[valid] > 0.0):  # only these samples are reduced and rendered: the material is black
        raise InputError(path, "no sample above the horizon that is valid in all three colour channels has a "
                               "positive value (each channel's light lies where another channel is missing, and "
                               "only samples valid in all three are used): the material is black and the "
                               "relative error of a reduction is undefined", hint or "check the file")
    if finite.max() > np.finfo(np.float32).max:  # renders, reductions and the solve run in float32
        raise InputError(path, f"MERL file holds values up to {finite.max():.3g} 1/sr, beyond float32",
                         hint or "check the file")
    if finite.max() < np.finfo(np.float32).tiny:  # every value would be 0 (or subnormal) in float32
        raise InputError(path, f"MERL file holds values up to {finite.max():.3g} 1/sr only, below float32's "
                               "range: the material would render black", hint or "check the file (its scale)")


@functools.lru_cache(maxsize=1)
def geometric_mask() -> np.ndarray:
    """``(90, 90, 180) bool``, read-only: MERL nodes whose wi and wo are both above the horizon."""
    theta_h, theta_d, phi_d = node_angles()
    mask = above_horizon(theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :])
    mask.setflags(write=False)
    return mask


def _continuous_index(theta_h, theta_d, phi_d) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fractional node coordinates (node i sits at index i) of Rusinkiewicz angles."""
    n_h, n_d, n_p = MERL_SHAPE
    theta_h = np.asarray(theta_h, np.float64)
    theta_d = np.asarray(theta_d, np.float64)
    phi_d = np.asarray(phi_d, np.float64)
    u_h = np.sqrt(np.maximum(theta_h, 0.0) / (0.5 * math.pi)) * n_h
    u_d = np.maximum(theta_d, 0.0) / (0.5 * math.pi) * n_d
    u_p = fold_phi_d(phi_d) / math.pi * n_p
    return u_h, u_d, u_p


def merl_indices(theta_h, theta_d, phi_d) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MERL's own floor indexing (reference ``BRDFRead``), clamped to the table.

    Returns:
        ``(i_h, i_d, i_p)`` int64 arrays broadcast to the angles' common shape.
    """
    n_h, n_d, n_p = MERL_SHAPE
    u_h, u_d, u_p = np.broadcast_arrays(*_continuous_index(theta_h, theta_d, phi_d))
    i_h = np.clip(np.floor(u_h + _INDEX_EPS), 0, n_h - 1).astype(np.int64)
    i_d = np.clip(np.floor(u_d + _INDEX_EPS), 0, n_d - 1).astype(np.int64)
    i_p = np.floor(u_p + _INDEX_EPS).astype(np.int64) % n_p
    return i_h, i_d, i_p


class MERLBRDF:
    """An isotropic BRDF tabulated on the MERL grid.

    Attributes:
        table: ``(90, 90, 180, 3)`` float (float64 when read from a file), 1/sr,
            ``[theta_h][theta_d][phi_d][channel]``, NaN = missing sample.
        name: a label (file stem, material name, analytic spec).
    """

    def __init__(self, table: np.ndarray, name: str = "merl"):
        table = np.asarray(table)
        if table.shape != MERL_SHAPE + (3,):
            raise InputError(name, f"a MERL table must have shape {MERL_SHAPE + (3,)}, got {table.shape}")
        if table.dtype.kind not in "biuf":
            raise InputError(name, f"a MERL table holds real numbers, got {table.dtype}")
        if not np.issubdtype(table.dtype, np.floating):
            table = table.astype(np.float64)
        self.table = table
        self.name = name

    def __repr__(self) -> str:
        return f"MERLBRDF(name={self.name!r}, dtype={self.table.dtype}, valid={self.valid_mask().mean():.3f})"

    def content_digest(self) -> str:
        """A hex digest of the table's values and dtype (as :meth:`Probe.content_digest
        <mi_bivariate.probes.Probe.content_digest>`): equal digests mean equal tables. Computed
        on each call (~30 ms for float32), since the table is a plain, writable array."""
        h = hashlib.sha256(str(self.table.dtype).encode())
        h.update(np.ascontiguousarray(self.table).data)
        return h.hexdigest()

    # ------------------------------------------------------------------ I/O

    @staticmethod
    def check_file(path: PathLike) -> None:
        """Check a MERL ``.binary`` file's header and size without reading its table.

        Raises:
            InputError: the file is missing, not a file, truncated, too long or not a MERL table.
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "MERL file not found" if not path.exists() else "not a file",
                             "give the path of a MERL .binary file")
        try:
            size = path.stat().st_size
            if size < _HEADER_BYTES:
                raise InputError(path, f"not a MERL .binary file: {size} bytes, too short for its header",
                                 "the file is truncated or not a MERL table")
            header = tuple(int(v) for v in np.fromfile(path, dtype="<i4", count=3))
        except OSError as e:
            raise InputError(path, f"cannot read MERL file ({e.strerror or e})",
                             "check the file's permissions") from None
        if header != MERL_SHAPE:
            raise InputError(path, f"not a MERL .binary file: header {header}, expected {MERL_SHAPE}",
                             "give a MERL isotropic BRDF table (90 x 90 x 180)")
        if size != MERL_FILE_BYTES:
            what = "truncated" if size < MERL_FILE_BYTES else "has trailing data"
            raise InputError(path, f"MERL file {what}: {size} bytes, expected {MERL_FILE_BYTES}",
                             "download or write it again")

    @classmethod
    def read(cls, path: PathLike, name: str | None = None) -> "MERLBRDF":
        """Read a MERL ``.binary`` file (validates header and size).

        Raises:
            InputError: the file is missing, truncated or not a MERL table, or holds no positive value
            or values beyond float32 (too large, or all too small).
        """
        path = Path(path)
        cls.check_file(path)
        try:
            raw = np.fromfile(path, dtype="<f8", offset=_HEADER_BYTES, count=_N_VALUES)
        except OSError as e:
            raise InputError(path, f"cannot read MERL file ({e.strerror or e})",
                             "check the file's permissions") from None
        raw = raw.reshape((3,) + MERL_SHAPE)
        table = np.empty(MERL_SHAPE + (3,), np.float64)
        for c in range(3):
            channel = raw[c] * MERL_SCALE[c]
            channel[raw[c] < 0.0] = np.nan
            table[..., c] = channel
        check_values(table, path)
        return cls(table, name=name or path.stem)

    def write(self, path: PathLike, validate: bool = True) -> None:
        """Write a MERL ``.binary`` file atomically; missing (NaN) samples are written as -1.

        Raises:
            InputError: naming ``path``, for a table :meth:`read` would refuse (:func:`check_values`);
            ``validate=False`` writes it anyway (files to test readers with).
        """
        table = np.asarray(self.table, np.float64)
        if np.any(table < 0.0):
            raise InputError(path, f"MERL table {self.name!r} has negative values (min {np.nanmin(table):g} 1/sr); "
                                   "they would read back as missing", "clip them at 0, or write NaN for a missing sample")
        if validate:  # as read() would
            check_values(table, path, "a MERL reader would refuse it: check the table's values")
        raw = np.empty((3,) + MERL_SHAPE, np.float64)
        for c in range(3):
            channel = table[..., c] / MERL_SCALE[c]
            raw[c] = np.where(np.isnan(channel), _MISSING_RAW, channel)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.asarray(MERL_SHAPE, "<i4").tofile(f)
                raw.astype("<f8", copy=False).tofile(f)

    @classmethod
    def from_function(cls, fn: Callable, name: str, dtype=np.float64, chunk: int = 1 << 18) -> "MERLBRDF":
        """Tabulate ``fn(theta_h, theta_d, phi_d) -> (..., 3)`` (1/sr) on the MERL nodes.

        ``fn`` is called on flat arrays of the geometrically valid nodes only;
        configurations whose wi or wo falls below the horizon are stored as
        missing (NaN), like real MERL data. Negative values are clamped to 0.

        Args:
            fn: vectorised isotropic BRDF in Rusinkiewicz angles (radians).
            name: label of the result.
            dtype: table precision.
            chunk: nodes per call of ``fn`` (bounds its memory use).
        """
        theta_h, theta_d, phi_d = node_angles()
        i_h, i_d, i_p = np.nonzero(geometric_mask())
        values = np.empty((i_h.shape[0], 3), dtype)
        for start in range(0, i_h.shape[0], chunk):
            rows = slice(start, start + chunk)
            th, td, pd = theta_h[i_h[rows]], theta_d[i_d[rows]], phi_d[i_p[rows]]
            value = np.asarray(fn(th, td, pd), np.float64)
            if value.shape != th.shape + (3,):
                raise ValueError(f"{name}: BRDF function returned shape {value.shape}, expected {th.shape + (3,)}")
            values[rows] = np.maximum(value, 0.0)  # keeps NaN
        table = np.full(MERL_SHAPE + (3,), np.nan, dtype)
        table[i_h, i_d, i_p] = values
        return cls(table, name=name)

    # ----------------------------------------------------------- evaluation

    node_angles = staticmethod(node_angles)

    def valid_mask(self) -> np.ndarray:
        """``(90, 90, 180) bool``: finite in all channels and geometrically valid."""
        return np.all(np.isfinite(self.table), axis=-1) & geometric_mask()

    def eval(self, theta_h, theta_d, phi_d, interpolation: str = "nearest") -> np.ndarray:
        """Look the table up at arbitrary Rusinkiewicz angles (radians).

        Args:
            interpolation: ``"nearest"`` (MERL's floor indexing) or ``"linear"``
                (trilinear between nodes; phi_d periodic with period pi, theta
                axes clamped). Linear weights are renormalised over the finite
                neighbours, so a lookup next to a missing sample stays finite;
                it is NaN only where all its neighbours are missing.

        Returns:
            ``(..., 3)`` float64, 1/sr (NaN where missing, and where an angle is NaN or infinite).
        """
        if interpolation not in ("nearest", "linear"):
            raise ValueError(f"interpolation must be 'nearest' or 'linear', got {interpolation!r}")
        angles = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d)))
        known = np.isfinite(angles[0]) & np.isfinite(angles[1]) & np.isfinite(angles[2])  # NaN in, NaN out
        theta_h, theta_d, phi_d = (np.where(known, a, 0.0) for a in angles)
        if interpolation == "nearest":
            i_h, i_d, i_p = merl_indices(theta_h, theta_d, phi_d)
            value = np.asarray(self.table[i_h, i_d, i_p], np.float64)
        else:
            value = self._eval_linear(theta_h, theta_d, phi_d)
        return np.where(known[..., None], value, np.nan)

    def _eval_linear(self, theta_h, theta_d, phi_d) -> np.ndarray:
        n_h, n_d, n_p = MERL_SHAPE
        u_h, u_d, u_p = np.broadcast_arrays(*_continuous_index(theta_h, theta_d, phi_d))
        u_h = np.clip(u_h, 0.0, n_h - 1)
        u_d = np.clip(u_d, 0.0, n_d - 1)
        h0 = np.minimum(np.floor(u_h).astype(np.int64), n_h - 2)
        d0 = np.minimum(np.floor(u_d).astype(np.int64), n_d - 2)
        p0 = np.floor(u_p).astype(np.int64) % n_p
        wh, wd, wp = u_h - h0, u_d - d0, u_p - np.floor(u_p)
        acc = np.zeros(u_h.shape + (3,))
        wsum = np.zeros(u_h.shape + (3,))
        for dh in (0, 1):
            w_h = wh if dh else 1.0 - wh
            for dd in (0, 1):
                w_d = wd if dd else 1.0 - wd
                for dp in (0, 1):
                    w = (w_h * w_d * (wp if dp else 1.0 - wp))[..., None]
                    v = np.asarray(self.table[h0 + dh, d0 + dd, (p0 + dp) % n_p], np.float64)
                    ok = np.isfinite(v) & (w > 0.0)
                    acc += np.where(ok, w * np.where(ok, v, 0.0), 0.0)
                    wsum += np.where(ok, w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(wsum > 0.0, acc / wsum, np.nan)

    def to_bitmap(self):
        """The table as ``mi.Bitmap`` RGB float32, H = 90 * 90, W = 180 (for the ``merl`` plugin).

        Row ``i_h * 90 + i_d``, column ``i_p``. Missing samples stay NaN (the
        plugin fills them).
        """
        img = np.asarray(self.table, np.float32).reshape(MERL_SHAPE[0] * MERL_SHAPE[1], MERL_SHAPE[2], 3)
        return mi.Bitmap(np.ascontiguousarray(img))


def merl_files_in(folder: Union[str, os.PathLike]) -> List[Path]:
    """The MERL ``.binary`` files of a folder (the suffix in any case), sorted by name.

    Raises:
        InputError: the folder holds none.
    """
    folder = Path(folder)
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() == ".binary" and f.is_file())
    if not files:
        raise InputError(folder, "folder holds no MERL .binary files",
                         "give a folder of MERL .binary files, or the files")
    return files
