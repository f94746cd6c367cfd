"""The bivariate BRDF f(theta_h, theta_d): a table on the paper's st grid.

The domain is sampled uniformly in ``s = 2 theta_d / pi`` and
``t = sqrt(2 theta_h / pi)`` (denser near the specular peak), with nodes at
``s_j = j / (n_s - 1)``, ``t_i = i / (n_t - 1)`` and bilinear interpolation
between them. The table is RGB in 1/sr, layout ``[theta_h (t) index,
theta_d (s) index, channel]``, shape ``(n_t, n_s, 3)``, 32 x 32 by default.

A full isotropic BRDF is projected onto this domain by the paper's Eq. 1:
``f_bar(theta_h, theta_d)`` is the mean of ``f(theta_h, theta_d, phi_d)`` over
the valid phi_d (both directions above the horizon, sample not missing);
:func:`reduction_error` is Eq. 1's relative RMS error of that projection.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Optional

import mitsuba as mi
import numpy as np

from mi_bivariate import __version__
from mi_bivariate.atomic import atomic_path
from mi_bivariate.common import PathLike
from mi_bivariate.coordinates import grid_nodes, half_diff_from_st, st_from_half_diff
from mi_bivariate.errors import InputError, array_from
from mi_bivariate.images import write_exr
from mi_bivariate.limits import MAX_REDUCE_SAMPLES, check_grid, whole_number
from mi_bivariate.merl import MERL_SHAPE, MERLBRDF, above_horizon, node_angles
from mi_bivariate.npzio import provenance_dict, read_npz
from mi_bivariate.probes import refuse_probe

FORMAT = "mi_bivariate.BivariateBRDF"
FORMAT_VERSION = 1
UNITS = "1/sr"
LAYOUT = "[theta_h (t) index, theta_d (s) index, channel RGB]"
ST_MAP = "s = 2 theta_d / pi, t = sqrt(2 theta_h / pi); nodes at i / (n - 1)"
# Generic BRDFs are evaluated no further out than MERL's last nodes (s, t = 89/90):
# at theta = pi/2 no configuration is above the horizon, and models with a
# 1 / (cos_i cos_o) factor diverge there.
_ST_MAX = (MERL_SHAPE[0] - 1) / MERL_SHAPE[0]


def validate_table(table: Any, source: str) -> np.ndarray:
    """Check a ``(n_t >= 2, n_s >= 2, 3)`` table (finite, non-negative); return a C-contiguous float32
    copy (a :class:`BivariateBRDF` does not share the caller's array, and :meth:`BivariateBRDF.save`
    checks its table again)."""
    kind = getattr(getattr(table, "dtype", None), "kind", "f")
    if kind not in "biuf":
        raise InputError(source, f"bivariate BRDF table holds {getattr(table, 'dtype')} values", "expected real numbers")
    try:
        table = np.asarray(table, dtype=np.float32)
    except (TypeError, ValueError):
        raise InputError(source, "bivariate BRDF table is not a numeric array") from None
    if table.ndim != 3 or table.shape[2] != 3 or table.shape[0] < 2 or table.shape[1] < 2:
        raise InputError(source, f"bivariate BRDF table must have shape (n_t >= 2, n_s >= 2, 3), got {table.shape}")
    if not np.all(np.isfinite(table)):
        raise InputError(source, "bivariate BRDF table has non-finite (NaN or infinite) values",
                         "a table is finite and >= 0 (1/sr): recover or reduce it again")
    if np.any(table < 0.0):
        raise InputError(source, f"bivariate BRDF table has negative values (min {table.min():g} 1/sr)")
    return np.array(table, dtype=np.float32, order="C", copy=True)


def _checked_confidence(value: Any, name: str, shape: tuple, source: str) -> np.ndarray:
    """A confidence map as a float32 copy, refused unless real, finite and shaped as the table."""
    kind = getattr(getattr(value, "dtype", None), "kind", "f")
    if kind not in "biuf":
        raise InputError(source, f"confidence map {name!r} holds {getattr(value, 'dtype')} values",
                         "expected real numbers")
    try:
        value = np.array(value, np.float32, copy=True)
    except (TypeError, ValueError):
        raise InputError(source, f"confidence map {name!r} is not a numeric array") from None
    if value.shape != shape or not np.all(np.isfinite(value)):
        raise InputError(source, f"confidence map {name!r} must be finite and shaped {shape}")
    return value


class BivariateBRDF:
    """A bivariate BRDF table on the st grid.

    Args:
        table: ``(n_t, n_s, 3)`` (float32 after conversion), 1/sr,
            ``[theta_h (t) index, theta_d (s) index, channel]``.
        provenance: JSON-serialisable description of where the table came
            from (saved with it).
        source: names the input in error messages.
        confidence: optional per-node maps ``{name: (n_t, n_s, 3)}`` saved with the
            table, e.g. from a recovery: ``resolution`` (0..1, how much of the node's
            value the image set rather than the prior), ``posterior_std`` (1/sr) and
            ``observation_weight`` (the lighting matrix's information per node).

    Raises:
        InputError: wrong shape, non-finite or negative values.
    """

    def __init__(self, table: Any, provenance: Optional[dict] = None, source: str = "bivariate table",
                 confidence: Optional[dict] = None):
        self.table = validate_table(table, source)
        self.provenance = provenance_dict(provenance, source)
        self.confidence = {}
        if confidence is not None and not isinstance(confidence, Mapping):
            raise InputError(source, "confidence must map names to (n_t, n_s, 3) arrays, "
                             f"got a {type(confidence).__name__}")
        for name, value in (confidence or {}).items():
            self.confidence[str(name)] = _checked_confidence(value, name, self.table.shape, source)

    def __repr__(self) -> str:
        return f"BivariateBRDF(n_t={self.n_t}, n_s={self.n_s}, provenance={self.provenance!r})"

    @property
    def n_t(self) -> int:
        return self.table.shape[0]

    @property
    def n_s(self) -> int:
        return self.table.shape[1]

    @property
    def s_nodes(self) -> np.ndarray:
        """``(n_s,)`` float64 s coordinates of the table columns."""
        return grid_nodes(self.n_s)

    @property
    def t_nodes(self) -> np.ndarray:
        """``(n_t,)`` float64 t coordinates of the table rows."""
        return grid_nodes(self.n_t)

    def node_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(theta_h (n_t,), theta_d (n_s,))`` float64 radians of the nodes."""
        theta_h, _ = half_diff_from_st(0.0, self.t_nodes)
        _, theta_d = half_diff_from_st(self.s_nodes, 0.0)
        return np.asarray(theta_h), np.asarray(theta_d)

    # ----------------------------------------------------------- evaluation

    def eval_st(self, s, t) -> np.ndarray:
        """Bilinear lookup at st coordinates (broadcast, clamped to [0, 1]) -> ``(..., 3)`` float64
        (NaN where ``s`` or ``t`` is not finite)."""
        s, t = np.broadcast_arrays(np.asarray(s, np.float64), np.asarray(t, np.float64))
        known = np.isfinite(s) & np.isfinite(t)  # NaN in, NaN out
        u = np.clip(np.where(known, s, 0.0), 0.0, 1.0) * (self.n_s - 1)
        v = np.clip(np.where(known, t, 0.0), 0.0, 1.0) * (self.n_t - 1)
        j0 = np.minimum(np.floor(u).astype(np.int64), self.n_s - 2)
        i0 = np.minimum(np.floor(v).astype(np.int64), self.n_t - 2)
        ws = (u - j0)[..., None]
        wt = (v - i0)[..., None]
        f = self.table.astype(np.float64, copy=False)
        value = ((1.0 - wt) * ((1.0 - ws) * f[i0, j0] + ws * f[i0, j0 + 1])
                 + wt * ((1.0 - ws) * f[i0 + 1, j0] + ws * f[i0 + 1, j0 + 1]))
        return np.where(known[..., None], value, np.nan)

    def eval(self, theta_h, theta_d) -> np.ndarray:
        """Bilinear (in st) lookup at half/difference angles (radians, broadcast) -> ``(..., 3)`` 1/sr.

        Angles outside ``[0, pi/2]`` are clamped to the table's edge (a negative theta_h reads as 0, beyond
        pi/2 as the last node), as :meth:`eval_st` clamps s and t; NaN angles give NaN."""
        s, t = st_from_half_diff(np.asarray(theta_h, np.float64), np.asarray(theta_d, np.float64))
        return self.eval_st(s, t)

    # ------------------------------------------------------------ reduction

    @classmethod
    def reduce(cls, brdf: Any, n_t: int = 32, n_s: int = 32, n_phi: int = 180,
               provenance: Optional[dict] = None) -> "BivariateBRDF":
        """Project an isotropic BRDF onto the st grid by Eq. 1 (mean over the valid phi_d).

        A :class:`MERLBRDF` is averaged over its own phi_d samples at its own
        (theta_h, theta_d) nodes (valid = both directions above the horizon and
        all channels finite); that ``(90, 90)`` map, uniform in st at
        ``t = i / 90, s = j / 90``, is interpolated bilinearly onto the st nodes
        (clamped beyond the last MERL node, 89 / 90). With ``n_t = n_s = 91``
        the nodes coincide with MERL's and the reduction is exact there.

        Any other object with ``eval(theta_h, theta_d, phi_d) -> (..., 3)`` is
        evaluated at the st nodes themselves, at ``phi_d = k pi / n_phi``,
        keeping the configurations above the horizon with finite values. Like
        MERL data, it is sampled no further out than s, t = 89/90: nodes beyond
        (the last row and column) take the value there, so both paths agree.

        Nodes without any valid sample take the value of the nearest node that
        has one. A :class:`BivariateBRDF` is resampled bilinearly.

        Raises:
            InputError: naming ``brdf`` for an object that is none of these (a file name: read it
                with :meth:`MERLBRDF.read` or :meth:`load` first), ``n_t``/``n_s`` off the grid limits,
                or ``n_phi`` not a whole number from 1 with ``n_t * n_s * n_phi`` at most
                :data:`~mi_bivariate.limits.MAX_REDUCE_SAMPLES`, or an ``eval`` that returns
                other than one RGB value per configuration.
        """
        n_t, n_s = check_grid((n_t, n_s), max_nodes=None)
        refuse_probe(brdf, "brdf", "reduce a MERLBRDF, a BRDF with eval() or a table")
        if not isinstance(brdf, (BivariateBRDF, MERLBRDF)) and not callable(getattr(brdf, "eval", None)):
            raise InputError("brdf", f"expected a MERLBRDF, a BivariateBRDF or a BRDF with eval(theta_h, theta_d, "
                             f"phi_d), got a {type(brdf).__name__}",
                             "read a file first: MERLBRDF.read(path) for a .binary, BivariateBRDF.load(path) for a "
                             ".npz, BivariateBRDF(array) for an (n_t, n_s, 3) table")
        n_phi = whole_number("n_phi", n_phi)
        if n_phi < 1:
            raise InputError("n_phi", f"must be at least 1, got {n_phi}")
        if n_t * n_s * n_phi > MAX_REDUCE_SAMPLES:
            raise InputError("n_phi", f"{n_t} x {n_s} nodes x {n_phi} = {n_t * n_s * n_phi} evaluations is over the "
                             f"limit of {MAX_REDUCE_SAMPLES}", "lower n_phi (MERL's tables have 180)")
        t_nodes, s_nodes = grid_nodes(n_t), grid_nodes(n_s)
        if isinstance(brdf, BivariateBRDF):  # already bivariate: resample
            table = brdf.eval_st(s_nodes[None, :], t_nodes[:, None])
            method = "bilinear resampling of a bivariate table"
        elif isinstance(brdf, MERLBRDF):
            f_bar = phi_d_average(brdf)
            f_bar = _fill_nearest(f_bar, source=brdf.name)
            table = _resample_merl_map(f_bar, t_nodes, s_nodes)
            method = "Eq. 1: MERL phi_d average at MERL nodes, bilinear in st onto the grid"
        else:
            theta_h, _ = half_diff_from_st(0.0, np.minimum(t_nodes, _ST_MAX))
            _, theta_d = half_diff_from_st(np.minimum(s_nodes, _ST_MAX), 0.0)
            phi_d = np.arange(n_phi) * (math.pi / n_phi)
            th, td, pd = np.broadcast_arrays(theta_h[:, None, None], theta_d[None, :, None], phi_d[None, None, :])
            shape = th.shape + (3,)
            value = array_from(brdf.eval(th, td, pd), "brdf", "eval to return numbers", np.float64,
                               f"return one RGB value (1/sr) per configuration: shape {shape}")
            if value.shape != shape:
                raise InputError("brdf", f"eval returned shape {value.shape} for angles of shape {th.shape}",
                                 f"return one RGB value (1/sr) per configuration: shape {shape}")
            valid = above_horizon(th, td, pd)[..., None] & np.isfinite(value)
            count = valid.sum(axis=2)
            with np.errstate(invalid="ignore", divide="ignore"):
                table = np.where(valid, value, 0.0).sum(axis=2) / count
            table = _fill_nearest(table, source=getattr(brdf, "name", repr(brdf)))
            method = f"Eq. 1: phi_d average of {n_phi} samples at the st nodes"
        prov = {"source": getattr(brdf, "name", type(brdf).__name__), "reduction": method}
        prov.update(provenance_dict(provenance, "provenance"))
        return cls(np.maximum(table, 0.0), provenance=prov, source=prov["source"])

    # ------------------------------------------------------------------ I/O

    @classmethod
    def from_array(cls, table: Any, provenance: Optional[dict] = None, source: str = "array") -> "BivariateBRDF":
        """From an ``(n_t, n_s, 3)`` array (1/sr); InputError naming ``source`` if it is not one."""
        return cls(table, provenance=provenance, source=source)

    @classmethod
    def from_bitmap(cls, bitmap: Any, provenance: Optional[dict] = None, source: str = "bitmap") -> "BivariateBRDF":
        """From an ``mi.Bitmap`` (RGB, H = n_t, W = n_s), e.g. one made by :meth:`to_bitmap`."""
        try:
            array = np.array(bitmap, copy=True)
        except Exception:
            raise InputError(source, f"cannot read a bitmap from {type(bitmap).__name__}") from None
        if array.ndim == 2 or (array.ndim == 3 and array.shape[2] != 3):
            channels = 1 if array.ndim == 2 else array.shape[2]
            raise InputError(source, f"bivariate BRDF bitmap must be RGB (3 channels), got {channels}")
        return cls(array, provenance=provenance, source=source)

    def to_bitmap(self):
        """``mi.Bitmap`` RGB float32, H = n_t, W = n_s: the form the ``bivariate`` plugin takes."""
        return mi.Bitmap(np.ascontiguousarray(self.table, np.float32))

    def metadata(self) -> dict:
        """The JSON metadata saved alongside the table."""
        return {"format": FORMAT, "version": FORMAT_VERSION, "units": UNITS, "layout": LAYOUT,
                "st_map": ST_MAP, "n_t": self.n_t, "n_s": self.n_s, "provenance": self.provenance}

    def save(self, path: PathLike) -> None:
        """Write ``.npz`` (atomic) with keys ``table``, ``s_nodes``, ``t_nodes``, ``meta`` (JSON string).

        Raises:
            InputError: naming ``path``, if the table or a confidence map was made invalid since it
                was checked (NaN or negative values written into it, another shape assigned):
                nothing is written that :meth:`load` refuses.
        """
        table = validate_table(self.table, os.fspath(path))
        for name, value in self.confidence.items():
            _checked_confidence(value, name, table.shape, os.fspath(path))
        meta = json.dumps(self.metadata(), default=str)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, table=self.table, s_nodes=self.s_nodes, t_nodes=self.t_nodes,
                                    meta=np.array(meta),
                                    **{f"confidence_{k}": v for k, v in self.confidence.items()})

    @classmethod
    def load(cls, path: PathLike) -> "BivariateBRDF":
        """Read a table written by :meth:`save`.

        Raises:
            InputError: missing, corrupt or foreign file; inconsistent nodes or units.
        """
        path = Path(path)
        arrays = read_npz(path, what="bivariate BRDF file", required=("table", "s_nodes", "t_nodes", "meta"),
                          hint="write it with BivariateBRDF.save")
        table, s_nodes, t_nodes = arrays["table"], arrays["s_nodes"], arrays["t_nodes"]
        if arrays["meta"].shape != () or arrays["meta"].dtype.kind not in "US":
            raise InputError(path, "bivariate BRDF metadata is not a JSON string")
        meta_text = str(arrays["meta"])
        confidence = {k[len("confidence_"):]: arrays[k] for k in arrays if k.startswith("confidence_")}
        try:
            meta = json.loads(meta_text)
        except json.JSONDecodeError:
            raise InputError(path, "bivariate BRDF metadata is not JSON",
                             "write it with BivariateBRDF.save; the file was edited or is not a table") from None
        if not isinstance(meta, dict) or meta.get("units") != UNITS:
            units = meta.get("units") if isinstance(meta, dict) else None
            raise InputError(path, f"bivariate BRDF units must be {UNITS!r}, got {units!r}")
        if meta.get("format", FORMAT) != FORMAT:  # (tables from before the field: no format, read as this one)
            raise InputError(path, f"not a bivariate BRDF table (its format is {meta.get('format')!r})",
                             f"give a table written by BivariateBRDF.save ({FORMAT!r})")
        version = meta.get("version", FORMAT_VERSION)
        if not (isinstance(version, int) and not isinstance(version, bool) and 1 <= version <= FORMAT_VERSION):
            raise InputError(path, f"the table is of format version {version!r}, which this mi_bivariate "
                             f"({__version__}) does not know (it reads versions 1 to {FORMAT_VERSION})",
                             "read it with the mi_bivariate that wrote it, or update this one")
        biv = cls(table, provenance=meta.get("provenance"), source=os.fspath(path), confidence=confidence)
        for name, nodes, n in (("s_nodes", s_nodes, biv.n_s), ("t_nodes", t_nodes, biv.n_t)):
            if np.shape(nodes) != (n,) or not np.allclose(nodes, grid_nodes(n), atol=1e-9):
                raise InputError(path, f"{name} are not the uniform st nodes i/(n-1) of a {n}-node axis",
                                 "write it with BivariateBRDF.save; the file was edited or is not a table")
        return biv

    def save_exr(self, path: PathLike) -> None:
        """Write the table as an RGB float32 EXR image (rows = theta_h (t), columns = theta_d (s)), atomic.

        The header records the units, layout and st map besides the tool's provenance.
        """
        write_exr(path, self.table, units=UNITS,
                  metadata={"layout": LAYOUT, "st_map": ST_MAP,
                            "provenance": json.dumps(self.provenance, default=str)})

    def to_merl(self, name: Optional[str] = None) -> MERLBRDF:
        """A MERL table whose every cell (valid or not) holds the bivariate value at its (theta_h, theta_d)."""
        theta_h, theta_d, _ = node_angles()
        f = self.eval(theta_h[:, None], theta_d[None, :])
        table = np.broadcast_to(f[:, :, None, :], MERL_SHAPE + (3,)).copy()
        return MERLBRDF(table, name=name or str(self.provenance.get("source", "bivariate")))

    def write_merl(self, path: PathLike) -> None:
        """Write :meth:`to_merl` as a MERL ``.binary`` file (atomic) for any MERL renderer."""
        self.to_merl().write(path)


def phi_d_average(merl: MERLBRDF) -> np.ndarray:
    """Eq. 1's ``f_bar`` on the MERL (theta_h, theta_d) nodes: ``(90, 90, 3)`` float64.

    The mean over the valid phi_d (both directions above the horizon and all
    channels finite); NaN where no phi_d is valid.
    """
    valid = merl.valid_mask()
    values = np.where(valid[..., None], merl.table, 0.0).astype(np.float64)
    count = valid.sum(axis=2)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, values.sum(axis=2) / np.maximum(count, 1), np.nan)


def _fill_nearest(values: np.ndarray, source: str) -> np.ndarray:
    """Fill NaN cells of a ``(n_t, n_s, 3)`` map with the nearest finite cell's value."""
    missing = np.any(~np.isfinite(values), axis=-1)
    if not missing.any():
        return values
    if missing.all():
        raise InputError(source, "BRDF has no (theta_h, theta_d) cell with a sample valid in every colour "
                                 "channel to reduce", "check the table: a channel may be missing (NaN) throughout")
    from scipy.ndimage import distance_transform_edt

    _, (ii, jj) = distance_transform_edt(missing, return_indices=True)
    return values[ii, jj]


def _resample_merl_map(f_bar: np.ndarray, t_nodes: np.ndarray, s_nodes: np.ndarray) -> np.ndarray:
    """Bilinear resampling of a ``(90, 90, 3)`` map with nodes at ``t = i/90, s = j/90`` onto st nodes."""
    n_h, n_d = MERL_SHAPE[:2]

    def axis(nodes: np.ndarray, n: int):
        u = np.clip(nodes * n, 0.0, n - 1)
        i0 = np.minimum(np.floor(u).astype(np.int64), n - 2)
        return i0, (u - i0)

    i0, wt = axis(t_nodes, n_h)
    j0, ws = axis(s_nodes, n_d)
    wt, ws = wt[:, None, None], ws[None, :, None]
    f00, f01 = f_bar[i0][:, j0], f_bar[i0][:, j0 + 1]
    f10, f11 = f_bar[i0 + 1][:, j0], f_bar[i0 + 1][:, j0 + 1]
    return (1.0 - wt) * ((1.0 - ws) * f00 + ws * f01) + wt * ((1.0 - ws) * f10 + ws * f11)


def _relative_errors(merl: MERLBRDF, biv: Optional[BivariateBRDF], min_value: float):
    """Squared relative errors and the cells that count, ``(90, 90, 180, 3)`` each."""
    f = np.asarray(merl.table, np.float64)
    if biv is None:
        f_bar = phi_d_average(merl)
    else:
        theta_h, theta_d, _ = node_angles()
        f_bar = biv.eval(theta_h[:, None], theta_d[None, :])
    cells = merl.valid_mask()[..., None] & (f > max(min_value, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        rel2 = np.where(cells, ((f - f_bar[:, :, None, :]) / np.where(cells, f, 1.0)) ** 2, 0.0)
    return rel2, cells


def reduction_error_per_channel(merl: MERLBRDF, biv: Optional[BivariateBRDF] = None,
                                min_value: float = 0.0) -> np.ndarray:
    """Eq. 1 relative RMS error per channel, ``(3,)`` float64; see :func:`reduction_error`."""
    rel2, cells = _relative_errors(merl, biv, min_value)
    count = cells.sum(axis=(0, 1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(rel2.sum(axis=(0, 1, 2)) / count)


def reduction_error(merl: MERLBRDF, biv: Optional[BivariateBRDF] = None, min_value: float = 0.0) -> float:
    """Eq. 1: relative RMS error of a bivariate BRDF against a 3D MERL table.

    ``E = sqrt(mean over cells of ((f - f_bar) / f)^2)``, where

    - the cells are the MERL nodes ``(theta_h_i, theta_d_j, phi_d_k)`` and
      channels c with both directions above the horizon, all three channels
      finite (not missing), and ``f_c > min_value`` (default 0: the relative
      error is undefined at 0); the mean pools all channels (the paper's sum,
      normalised by the number of cells so that it is an RMS);
    - ``f_bar`` is ``biv`` evaluated (bilinear in st) at the node's
      (theta_h, theta_d), so a coarse grid's interpolation error counts; with
      ``biv=None`` it is the exact phi_d average at the MERL nodes (the
      paper's Fig. 3 number: the bivariate projection alone).

    Near-zero samples dominate a relative error: MERL-NBRDF fits have values
    down to ~1e-9 1/sr at grazing angles (brass: E ~ 80 from the 60 of its
    3.3 million cell values below 1e-6; 4.3 with ``min_value=1e-6``).
    ``min_value`` (1/sr) leaves such cells out.

    Returns:
        The pooled error (0.1 = 10%); NaN if no cell counts.
    """
    rel2, cells = _relative_errors(merl, biv, min_value)
    count = int(cells.sum())
    return float(np.sqrt(rel2.sum() / count)) if count else float("nan")


# ------------------------------------------------------------------ floors
#
# Two different "floors" of a bivariate representation, never to be confused:
#
# - the *exact floor*: Eq. 1 of the exact phi_d average at the MERL nodes
#   (the paper's Fig. 3: what the bivariate assumption alone costs);
# - the *grid floor*: Eq. 1 of the n_t x n_s st table reduced from the truth,
#   read back (bilinearly) at MERL resolution: the exact floor plus the
#   grid's interpolation error. On near-zero cells they differ a lot
#   (gold-metallic-paint3: 0.112 vs 0.280 on a 32 x 32 grid).
#
# The *relight floor* (an image error) is in mi_bivariate.evaluate.

def exact_floor(merl: MERLBRDF, min_value: float = 0.0) -> float:
    """Eq. 1 of the exact phi_d average at MERL resolution (the paper's Fig. 3 floor).

    The paper's reference for what a bivariate table loses, not a strict lower bound of Eq. 1: the
    constant per (theta_h, theta_d) that minimises a *relative* error is ``sum(1/f) / sum(1/f^2)``
    over the node's phi_d, not their mean (``benchmarks/eq1_optimal.py``: 0.048 against this
    floor's 0.112 for gold-metallic-paint3, 0.117 against 0.147 for red-phenolic).
    """
    return reduction_error(merl, None, min_value=min_value)


def grid_floor(merl: MERLBRDF, n_t: int = 32, n_s: int = 32, min_value: float = 0.0) -> float:
    """Eq. 1 of the ``n_t x n_s`` table reduced from ``merl``, read back at MERL resolution."""
    return reduction_error(merl, BivariateBRDF.reduce(merl, n_t=n_t, n_s=n_s), min_value=min_value)


def floors(merl: MERLBRDF, n_t: int = 32, n_s: int = 32) -> dict:
    """Both floors, all cells and cells with f > 1e-3 1/sr: ``{"exact_floor", "grid_floor",
    "exact_floor_min", "grid_floor_min"}`` (floats) and ``"grid"`` ``[n_t, n_s]``."""
    table = BivariateBRDF.reduce(merl, n_t=n_t, n_s=n_s)
    return {"exact_floor": reduction_error(merl, None), "grid_floor": reduction_error(merl, table),
            "exact_floor_min": reduction_error(merl, None, min_value=1e-3),
            "grid_floor_min": reduction_error(merl, table, min_value=1e-3), "grid": [int(n_t), int(n_s)]}
