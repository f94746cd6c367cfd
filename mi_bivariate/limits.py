"""Limits on user numbers, checked before anything is allocated: one home for the CLI and the library.

Each limit is far above the documented defaults and below what a 16 GB machine (or Dr.Jit's 32-bit
array sizes) can hold. The checks name the argument as the caller knows it: the library's front
doors (:func:`mi_bivariate.recover.recover`, :func:`mi_bivariate.render.render_sphere`, ...) pass
their parameter names (``n_normals``), the CLI its flags (``--normals``).
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from mi_bivariate.errors import InputError

#: The largest radiance accepted in a photo or a probe: a thousandth of float32's largest, so that the
#: table (which scales with the image over the probe) and the solve's sums stay finite (measured: a
#: recovery at a pixel of 1e34 is right, at 1e37 it overflowed inside the priors).
MAX_RADIANCE = 3.4028234663852886e38 / 1e3
#: The least value the brightest pixel of a photo, or texel of a probe, may have: a recovery scales with
#: the image down to a brightest pixel of 1e-25 (measured on the bench sphere, the table the same to 7e-7
#: of its largest value); below it float32's squares underflow (a review measured the table 3% off at
#: 1e-27 and 80% off, the sphere fit moved, at 1e-30). Five decades of margin.
MIN_RADIANCE = 1e-20
#: A probe's texels below this read as 0 (:class:`~mi_bivariate.probes.Probe`): five decades under the
#: dimmest brightest texel accepted, where the lighting kernels' products of them would leave float32's
#: normal range, which some of their threads flush to 0 and others keep (so ``--threads 1`` and ``2``
#: would recover different tables).
RADIANCE_FLOOR = 1e-25
#: The range of a recovery's Lambertian level (its best constant table, 1/sr), which the image over the
#: probe sets (:func:`check_table_level`). Beyond it the float32 table, or the basis prior's exponentials
#: of it, leave float32's working range: an image of 3e35 under a probe of 1e-30 gave a level of ~1e65
#: and an overflow deep in the priors; levels of 1.2-1.8e-30 came back 2-6.5% off, 1.8e-29 1e-5 off
#: (a review's scaled 32 px Lambertian sphere), hence five decades of margin below. Above, a glossy
#: table's peak is up to ~1e4-1e5 times its level, and float32 ends at 3.4e38: a Lambertian sphere
#: recovered right at levels up to ~5e34, a glossy one would not.
MAX_TABLE_LEVEL = 1e33
MIN_TABLE_LEVEL = 1e-25
#: Nodes per st axis, and nodes of the whole grid (the solve's normal equations are N x N).
MAX_GRID_AXIS = 256
MAX_GRID_NODES = 64 * 64
#: Normals M and light directions K of a recovery.
MAX_NORMALS = 1_000_000
MAX_DIRS = 10_000_000
#: Bytes of the lighting matrix (M x N x 3 float32).
MAX_LIGHTING_BYTES = 4 << 30
#: Lanes of one lighting kernel (on CUDA rows of a chunk x direction pairs, on the CPU its rows): Dr.Jit
#: indexes with uint32.
MAX_KERNEL_LANES = 1 << 31
#: Render width/height, samples per pixel, and samples of one render (width x height x spp).
MAX_RESOLUTION = 8192
MAX_SPP = 1 << 16
MAX_RENDER_SAMPLES = 1 << 28
#: Sampler seeds are unsigned 32-bit integers.
MAX_SEED = 2**32 - 1
#: Evaluations of a BRDF in one reduction to the st grid (:meth:`~mi_bivariate.bivariate.BivariateBRDF.reduce`:
#: n_t x n_s x n_phi; float64 RGB of 2^24 takes 400 MB): the default 32 x 32 x 180 is 184 320, 256 x 256 x 180
#: 11.8 million.
MAX_REDUCE_SAMPLES = 1 << 24


def whole_number(name: str, value: Any) -> int:
    """``value`` as an ``int``, refused (:class:`InputError` naming ``name``) unless it is a whole
    number: an integer type, or a finite float with no fraction (``8.0``, not ``8.7``)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(name, f"must be a whole number, got {value!r}")
    if not isinstance(value, numbers.Integral) and not (math.isfinite(value) and float(value).is_integer()):
        raise InputError(name, f"must be a whole number, got {value!r}")
    return int(value)


def finite_number(name: str, value: Any) -> float:
    """``value`` as a ``float``, refused (:class:`InputError` naming ``name``) unless it is a finite real
    number (an integer or float type, not a string, a bool, NaN or an infinity); the caller checks its range."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise InputError(name, f"must be a finite number, got {value!r}")
    return float(value)


def check_max(name: str, value: Optional[int], limit: int, hint: str = "") -> None:
    if value is not None and value > limit:
        raise InputError(name, f"{value} is over the limit of {limit}", hint or None)


def check_seed(seed: Any, name: str = "seed") -> int:
    """The seed as an ``int`` in ``[0, MAX_SEED]`` (the samplers' unsigned 32 bits): a whole number
    (:func:`whole_number`: ``3``, ``np.uint32(3)``, ``3.0`` or a 0-d array of one)."""
    if isinstance(seed, np.ndarray) and seed.ndim == 0:
        seed = seed.item()
    try:
        value = whole_number(name, seed)
    except InputError:
        value = None
    if value is None or not 0 <= value <= MAX_SEED:
        raise InputError(name, f"must be an integer from 0 to {MAX_SEED}, got {seed!r}")
    return value


def check_grid(grid: Any, name: str = "grid", axis_names: Optional[Tuple[str, str]] = None,
               max_nodes: Optional[int] = MAX_GRID_NODES) -> Tuple[int, int]:
    """``(n_t, n_s)`` of an st grid, each a whole number from 2 to :data:`MAX_GRID_AXIS`, their
    product at most ``max_nodes`` (the solve's limit, :data:`MAX_GRID_NODES`; ``None`` for a table
    that is not solved for, e.g. a reduction at MERL's 91 x 91)."""
    try:
        n_t, n_s = grid
    except (TypeError, ValueError):
        raise InputError(name, f"must be two node counts (n_t, n_s), got {grid!r}") from None
    axis_names = axis_names or (f"{name} n_t", f"{name} n_s")
    n_t, n_s = whole_number(axis_names[0], n_t), whole_number(axis_names[1], n_s)
    for axis, n in zip(axis_names, (n_t, n_s)):
        check_max(axis, n, MAX_GRID_AXIS)
        if n < 2:
            raise InputError(axis, f"{n} nodes is too small", "each st axis needs at least 2 nodes")
    if max_nodes is not None and n_t * n_s > max_nodes:
        raise InputError(name, f"{n_t} x {n_s} = {n_t * n_s} nodes is over the limit of {max_nodes}",
                         "the solve's normal equations grow as the square of the node count")
    return n_t, n_s


def check_recovery_sizes(normals: Optional[int], dirs: Optional[int], grid: Optional[Sequence[int]],
                         names: Sequence[str] = ("n_normals", "n_dirs", "grid")) -> None:
    """Limits on M (``normals``), K (``dirs``) and the grid, and on the lighting matrix they imply.
    ``names``: how the caller calls the three. The kernel's lane count is
    :func:`mi_bivariate.lighting.lighting_matrix`'s check (it knows its chunk size)."""
    normals_name, dirs_name, grid_name = names
    if grid is not None:
        grid = check_grid(grid, grid_name, (f"{grid_name} N_T", f"{grid_name} N_S") if grid_name.startswith("--")
                          else None)
    if normals is not None:
        normals = whole_number(normals_name, normals)
        if normals < 1:
            raise InputError(normals_name, f"must be at least 1, got {normals}")
    if dirs is not None:
        dirs = whole_number(dirs_name, dirs)
        if dirs < 2:
            raise InputError(dirs_name, f"must be at least 2 (light directions per normal), got {dirs}")
    check_max(normals_name, normals, MAX_NORMALS)
    check_max(dirs_name, dirs, MAX_DIRS)
    if normals is None or grid is None:
        return
    n_nodes = grid[0] * grid[1]
    size = normals * n_nodes * 3 * 4
    if size > MAX_LIGHTING_BYTES:
        raise InputError(normals_name, f"the lighting matrix of {normals} normals x {n_nodes} nodes would take "
                         f"{size / 2**30:.1f} GiB, over the limit of {MAX_LIGHTING_BYTES / 2**30:.0f} GiB",
                         "use fewer normals or a smaller grid")


def check_render_sizes(resolution: Optional[int], spp: Optional[int], names: Sequence[str] = ("resolution", "spp"),
                       hint: str = "lower --spp or --resolution", height: Optional[int] = None) -> None:
    """Limits on a render's width (``resolution``; the height too unless ``height`` is given), its
    samples per pixel and the samples of the whole render. ``names``: ``(resolution, spp)`` as the
    caller calls them (``height`` is named ``height``)."""
    resolution_name, spp_name = names
    sizes = [(resolution_name, resolution), ("height", height)]
    sizes = [(name, whole_number(name, value)) for name, value in sizes if value is not None]
    spp = None if spp is None else whole_number(spp_name, spp)
    for name, value in sizes:
        check_max(name, value, MAX_RESOLUTION)
        if value < 2:
            raise InputError(name, f"must be at least 2 pixels, got {value}")
    check_max(spp_name, spp, MAX_SPP)
    if spp is not None and spp < 1:
        raise InputError(spp_name, f"must be at least 1, got {spp}")
    if sizes and spp:
        width = sizes[0][1]
        tall = sizes[1][1] if len(sizes) > 1 else width
        if width * tall * spp > MAX_RENDER_SAMPLES:
            raise InputError(spp_name, f"{width} x {tall} pixels x {spp} spp = {width * tall * spp} samples, over "
                             f"the limit of {MAX_RENDER_SAMPLES} for one render", hint)


def check_brightest(top: float, source: Any, what: str = "image") -> None:
    """Refuse, naming ``source``, the brightest value ``top`` of an image or a probe (``what``) beyond
    :data:`MAX_RADIANCE` or (non-zero) below :data:`MIN_RADIANCE`; the limits themselves pass, also once
    rounded to float32 (a probe's data is float32 when it is checked, a photo's may not be yet). All zero is
    left to the callers (a black photo or probe has its own reasons)."""
    if top > MAX_RADIANCE * (1.0 + 2.0**-23):
        raise InputError(source, f"{what} values up to {top:.3g} are too large for float32 and the solve's sums "
                         f"(at most {MAX_RADIANCE:.3g})", f"scale the {what} down: the table scales with the "
                         "image over the probe")
    if 0.0 < top < MIN_RADIANCE * (1.0 - 2.0**-23):
        raise InputError(source, f"{what} values up to {top:.3g} are too small for float32 and the solve's sums "
                         f"(the largest must be at least {MIN_RADIANCE:g})", f"scale the {what} up: the table "
                         "scales with the image over the probe")


def check_table_level(level: Any, what: str = "image") -> None:
    """Refuse a recovery whose Lambertian level (``(3,)`` 1/sr, the best constant table per channel; a
    channel of 0 has no light and is left to the fit checks) lies outside :data:`MAX_TABLE_LEVEL` /
    :data:`MIN_TABLE_LEVEL`, naming ``"image"``: the image over the probe sets it, and each may be within
    its own limits (:data:`MAX_RADIANCE`, :data:`MIN_RADIANCE`) while their ratio is not. ``what`` says
    which (``"image"``, ``"image 1"``, ``"images"``)."""
    level = np.asarray(level, np.float64)
    lit = level[level > 0]
    if not lit.size:
        return
    top, low = float(lit.max()), float(lit.min())
    if top > MAX_TABLE_LEVEL or low < MIN_TABLE_LEVEL:
        value = top if top > MAX_TABLE_LEVEL else low
        verb = "give" if what == "images" else "gives"
        raise InputError("image", f"the {what} over the probe {verb} a table of about {value:.3g} 1/sr, outside "
                         f"float32's working range ({MIN_TABLE_LEVEL:g} to {MAX_TABLE_LEVEL:g})",
                         "scale the image or the probe so that their ratio is an ordinary reflectance: "
                         "the table scales with the image over the probe")
