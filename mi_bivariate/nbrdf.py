"""MERL-NBRDF: neural fits (Sztrajman et al. 2021) of 23 MERL materials, evaluated in numpy.

The shared file ``merl_nbrdf/merl_nbrdf_dev.npz`` (see the shared data README)
holds, per material, a 6-21-21-3 MLP. For Rusinkiewicz angles the input row is
``x = (sin th, 0, cos th, sin td cos pd, sin td sin pd, cos td)`` (the half
vector and the difference vector) and the BRDF, in 1/sr, is
``exp(relu(relu(x W1 + b1) W2 + b2) W3 + b3) - 1`` clamped at 0.

These tables approximate the measurements; name results "MERL-NBRDF <material>".

The network is evaluated in float64, whatever the precision of its weights (float32) and of
the table it fills: it is the truth every recovery is scored against, so it must not depend on
the machine. A float32 evaluation rounds its matrix products as the CPU's BLAS kernels and thread
count sum them. Near-zero values (1e-9 to 1e-6 1/sr, where ``exp(z) - 1`` cancels) then move by up to
their own size, and Eq. 1 over all cells, which divides by them, moved with the machine: brass's
exact floor was 40.8 in float32 (either machine) and is 80.3 in float64; color-changing-paint1's
grid floor was 2.33, 1.95 or 2.22 depending on the machine and the BLAS threads.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np

from mi_bivariate.common import PathLike
from mi_bivariate.errors import InputError
from mi_bivariate.merl import MERL_SHAPE, MERLBRDF, geometric_mask, node_angles
from mi_bivariate.npzio import read_npz

NBRDF_MATERIALS: Tuple[str, ...] = (
    "alum-bronze", "black-fabric", "blue-acrylic", "brass", "colonial-maple-223",
    "color-changing-paint1", "dark-specular-fabric", "gold-metallic-paint3", "green-acrylic",
    "green-fabric", "hematite", "natural-209", "pearl-paint", "pink-jasper", "purple-paint",
    "red-phenolic", "silver-metallic-paint2", "specular-green-phenolic", "specular-white-phenolic",
    "tungsten-carbide", "white-acrylic", "white-paint", "yellow-matte-plastic",
)
#: The 50 materials of ``merl_nbrdf_train.npz``: for learning priors and choosing settings,
#: so that the development materials above are scored by models that never saw them.
NBRDF_TRAIN_MATERIALS: Tuple[str, ...] = (
    "aventurnine", "beige-fabric", "black-oxidized-steel", "black-phenolic", "black-soft-plastic",
    "blue-fabric", "blue-metallic-paint2", "blue-rubber", "chrome-steel", "color-changing-paint2",
    "color-changing-paint3", "dark-blue-paint", "fruitwood-241", "gold-metallic-paint2", "gold-paint",
    "gray-plastic", "grease-covered-steel", "green-metallic-paint", "green-metallic-paint2",
    "green-plastic", "light-brown-fabric", "maroon-plastic", "neoprene-rubber", "nickel", "orange-paint",
    "pickled-oak-260", "pink-fabric2", "pink-plastic", "polyethylene", "pure-rubber", "pvc", "red-fabric",
    "red-fabric2", "red-metallic-paint", "red-specular-plastic", "silicon-nitrade", "silver-metallic-paint",
    "special-walnut-224", "specular-black-phenolic", "specular-blue-phenolic", "specular-maroon-phenolic",
    "specular-red-phenolic", "specular-yellow-phenolic", "ss440", "two-layer-silver", "violet-acrylic",
    "white-fabric", "white-fabric2", "yellow-phenolic", "yellow-plastic",
)
#: Every shared MERL-NBRDF material (development first).
ALL_NBRDF_MATERIALS: Tuple[str, ...] = NBRDF_MATERIALS + NBRDF_TRAIN_MATERIALS
NBRDF_FILE = Path("merl_nbrdf") / "merl_nbrdf_dev.npz"
NBRDF_TRAIN_FILE = Path("merl_nbrdf") / "merl_nbrdf_train.npz"
_LAYERS = ("W1", "b1", "W2", "b2", "W3", "b3")
_SHAPES = {"W1": (6, 21), "b1": (21,), "W2": (21, 21), "b2": (21,), "W3": (21, 3), "b3": (3,)}
# Rows per MLP pass. Small enough that OpenBLAS runs these skinny products on
# one thread: its threaded path is no faster here and 5-20x slower when the
# cores are busy (measured: 0.14 s vs 1-4 s for the 1.1M MERL nodes under load).
_CHUNK = 2048


def data_dir(explicit: Optional[PathLike] = None) -> Path:
    """The shared data folder: ``explicit`` if given, else ``$MI_BIVARIATE_DATA``.

    Raises:
        InputError: neither is set, or the folder does not exist.
    """
    value = explicit if explicit is not None else os.environ.get("MI_BIVARIATE_DATA")
    if not value:
        raise InputError("MI_BIVARIATE_DATA", "the shared data folder is not set",
                         "set MI_BIVARIATE_DATA to the folder holding merl_nbrdf/ and probes/, "
                         "or pass --data")
    path = Path(value)
    if not path.is_dir():
        where = "--data (data_dir=)" if explicit is not None else "MI_BIVARIATE_DATA"
        raise InputError(path, "the shared data folder is a file, not a folder" if path.exists() else
                         "shared data folder does not exist",
                         f"set {where} to the folder holding merl_nbrdf/ and probes/")
    return path


# The public functions take a ``data_dir`` argument that shadows :func:`data_dir`.
_resolve_data_dir = data_dir


def _check_name(name: str) -> None:
    if name not in ALL_NBRDF_MATERIALS:
        raise InputError(name, "unknown MERL-NBRDF material", f"valid: {', '.join(ALL_NBRDF_MATERIALS)}")


def _weights_file(name: str) -> Path:
    """The shared file holding material ``name`` (development or training set)."""
    return NBRDF_FILE if name in NBRDF_MATERIALS else NBRDF_TRAIN_FILE


def weights_path(name: str, data_dir: Optional[PathLike] = None) -> Path:
    """The file that :func:`load_nbrdf` reads for material ``name``.

    Raises:
        InputError: unknown material, or no shared data folder.
    """
    _check_name(name)
    return _resolve_data_dir(data_dir) / _weights_file(name)


class NBRDF:
    """One MERL-NBRDF material: the MLP weights (stored float32, held float64) and their evaluation."""

    def __init__(self, name: str, weights: Dict[str, np.ndarray]):
        self.name = name
        self.weights = {k: np.asarray(weights[k], np.float64) for k in _LAYERS}

    def __repr__(self) -> str:
        return f"NBRDF({self.name!r})"

    def eval_inputs(self, x: np.ndarray, dtype=np.float64) -> np.ndarray:
        """Evaluate the MLP on input rows ``(N, 6)`` -> ``(N, 3)`` ``dtype``, 1/sr, >= 0.

        Computed in float64 (the module's docstring says why) and rounded to ``dtype`` once.
        """
        w = self.weights
        out = np.empty((x.shape[0], 3), dtype)
        for start in range(0, x.shape[0], _CHUNK):
            rows = np.asarray(x[start:start + _CHUNK], np.float64)
            hidden = np.maximum(rows @ w["W1"] + w["b1"], 0.0)
            hidden = np.maximum(hidden @ w["W2"] + w["b2"], 0.0)
            with np.errstate(over="ignore"):  # an overflow is an infinite value, which the tables refuse by name
                out[start:start + _CHUNK] = np.maximum(np.expm1(hidden @ w["W3"] + w["b3"]), 0.0)
        return out

    def eval(self, theta_h, theta_d, phi_d) -> np.ndarray:
        """BRDF at Rusinkiewicz angles (radians, broadcast) -> ``(..., 3)`` float64, 1/sr.

        The network is defined for any angles; horizon validity is the caller's concern.
        """
        theta_h, theta_d, phi_d = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d)))
        x = _inputs(theta_h.reshape(-1), theta_d.reshape(-1), phi_d.reshape(-1))
        return self.eval_inputs(x).reshape(theta_h.shape + (3,))


def _inputs(theta_h: np.ndarray, theta_d: np.ndarray, phi_d: np.ndarray) -> np.ndarray:
    """Network input rows ``(N, 6)`` float64 from flat angle arrays."""
    sin_d = np.sin(theta_d)
    x = np.empty((theta_h.shape[0], 6), np.float64)
    x[:, 0] = np.sin(theta_h)
    x[:, 1] = 0.0
    x[:, 2] = np.cos(theta_h)
    x[:, 3] = sin_d * np.cos(phi_d)
    x[:, 4] = sin_d * np.sin(phi_d)
    x[:, 5] = np.cos(theta_d)
    return x


def check_weights(path: Path) -> Path:
    """``path`` (from :func:`weights_path`), or :class:`InputError` naming it if the file is not there."""
    if not path.is_file():
        raise InputError(path, "MERL-NBRDF weights not found",
                         "MI_BIVARIATE_DATA (or --data) must point at the shared data folder")
    return path


@functools.lru_cache(maxsize=4)
def _load_npz(path: Path) -> Dict[str, np.ndarray]:
    return read_npz(check_weights(path), what="MERL-NBRDF weights file", text=())


def load_nbrdf(name: str, data_dir: Optional[PathLike] = None) -> NBRDF:
    """Load one material's weights from ``<data_dir>/merl_nbrdf/merl_nbrdf_{dev,train}.npz``.

    Raises:
        InputError: unknown material (lists the valid ones), missing data, malformed file.
    """
    path = weights_path(name, data_dir)
    arrays = _load_npz(path)
    weights = {}
    for layer in _LAYERS:
        key = f"{name}/{layer}"
        if key not in arrays:
            raise InputError(path, f"missing array {key!r}")
        if arrays[key].shape != _SHAPES[layer]:
            raise InputError(path, f"{key} has shape {arrays[key].shape}, expected {_SHAPES[layer]}")
        if not np.all(np.isfinite(arrays[key])):
            raise InputError(path, f"{key} holds non-finite values", "the file is corrupt")
        weights[layer] = arrays[key]
    return NBRDF(name, weights)


def tabulate(nbrdf: NBRDF, dtype=np.float32) -> MERLBRDF:
    """Evaluate an NBRDF on the MERL nodes (in float64, stored as ``dtype``); below-horizon nodes are
    missing (NaN), as in MERL."""
    theta_h, theta_d, phi_d = node_angles()
    mask = geometric_mask()
    i_h, i_d, i_p = np.nonzero(mask)
    # Sines and cosines per axis, gathered: ~10x cheaper than per sample.
    sin_d = np.sin(theta_d)
    x = np.empty((i_h.shape[0], 6), np.float64)
    x[:, 0] = np.sin(theta_h)[i_h]
    x[:, 1] = 0.0
    x[:, 2] = np.cos(theta_h)[i_h]
    x[:, 3] = sin_d[i_d] * np.cos(phi_d)[i_p]
    x[:, 4] = sin_d[i_d] * np.sin(phi_d)[i_p]
    x[:, 5] = np.cos(theta_d)[i_d]
    table = np.full(MERL_SHAPE + (3,), np.nan, dtype)
    table[i_h, i_d, i_p] = nbrdf.eval_inputs(x, dtype)
    return MERLBRDF(table, name=f"MERL-NBRDF {nbrdf.name}")


@functools.lru_cache(maxsize=8)
def _nbrdf_merl_cached(name: str, path: Path) -> MERLBRDF:
    merl = tabulate(load_nbrdf(name, path))
    if np.isinf(merl.table).any():  # finite weights whose network overflows float (below-horizon cells are NaN)
        raise InputError(weights_path(name, path), f"{name}: the network's values overflow (its weights are far "
                         "out of range)", "the file is corrupt")
    merl.table.setflags(write=False)  # shared by every caller of the cache
    return merl


def nbrdf_merl(name: str, data_dir: Optional[PathLike] = None) -> MERLBRDF:
    """MERL-NBRDF material ``name`` tabulated on the MERL grid (float32, read-only, cached in-process)."""
    _check_name(name)
    return _nbrdf_merl_cached(name, _resolve_data_dir(data_dir).resolve())
