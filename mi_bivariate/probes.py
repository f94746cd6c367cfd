"""Light probes: HDR environment maps in Mitsuba's latitude-longitude frame.

A :class:`Probe` is a linear-radiance lat-long image ``data`` (H, W, 3) float32
plus an explicit rotation ``to_world`` (4, 4) that is handed to Mitsuba's
``envmap`` emitter unchanged. Rotating a probe never resamples it.

Conventions (all measured against Mitsuba 3.9's ``envmap`` emitter, see
``tests/test_probes.py``):

- **Directions** point from the surface towards the light (the direction one
  looks in to see that part of the environment). World y is up.
- **Lat-long frame** (Mitsuba's, in the emitter's local frame ``d``)::

      u = atan2(d.x, -d.z) / (2 pi)   (wrapped to [0, 1))
      v = acos(d.y) / pi
      d(u, v) = (sin(2 pi u) sin(pi v), cos(pi v), -cos(2 pi u) sin(pi v))

  So v = 0 (top row) is +y, the left edge u = 0 is -z, u = 1/4 is +x, the
  image centre u = 1/2 is +z and u = 3/4 is -x: a panorama seen from the
  inside, facing +z. A world direction is first taken to the local frame
  with ``to_world^-1``.
- **Texel positions** (Mitsuba's interpolation): column i is centred at
  u = (i + 1/2) / W and wraps around; row j sits at v = j / (H - 1), so the
  first and last rows lie *on* the poles. Radiance is bilinear between these
  positions. :meth:`Probe.solid_angles` gives each texel the sin-weighted
  band between its neighbours (half bands at the poles); they sum to 4 pi.
- **Angular map** (Debevec's "light probe" format) and **mirror ball**
  images share one frame: image right = +x, image up = +y, image centre =
  +z. With normalised image coordinates (a, b) in [-1, 1] (a right, b up) and
  theta = angle between d and +z::

      angular map:  (a, b) = theta / pi        * (d.x, d.y) / |(d.x, d.y)|
      mirror ball:  (a, b) = sin(theta / 2)     * (d.x, d.y) / |(d.x, d.y)|

  The rim is -z. The mirror-ball formula is an orthographic photograph of a
  mirror sphere by this project's default camera (on +z, looking towards -z,
  image up = +y): rendering the converted probe on a mirror sphere with that
  camera gives the photograph back. Both map into Mitsuba's world with the
  identity; any other pose is an explicit :meth:`Probe.rotated`.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_bivariate.common import PathLike, luminance
from mi_bivariate.errors import InputError
from mi_bivariate.images import read_image, write_exr
from mi_bivariate.limits import MAX_RESOLUTION, RADIANCE_FLOOR, check_brightest, check_max, whole_number

#: Readable probe file types (extension -> description).
PROBE_FORMATS: Dict[str, str] = {
    ".exr": "OpenEXR",
    ".hdr": "Radiance RGBE",
    ".rgbe": "Radiance RGBE",
    ".pic": "Radiance RGBE",
    ".pfm": "PFM",
}

#: Stems of the probes in ``$MI_BIVARIATE_DATA/probes``.
SHARED_PROBES: Tuple[str, ...] = (
    "grace_latlong_1k",
    "grace_256",
    "uffizi_256",
    "pisa_256",
    "venice_sunset_1k",
    "pedestrian_overpass_1k",
    "royal_esplanade_1k",
)

#: Rotation (the probe's ``to_world``) taking ``grace_latlong_1k.exr`` (pbrt-v2's
#: lat-long) into Mitsuba's frame so that it lines up with ``grace_256.hdr``:
#: ``Ry(275 deg) @ Rz(180 deg)``, a proper rotation (det +1, no mirror flip).
#: Loaded as is, the file is upside down (pbrt-v2's own scenes turn its top row
#: to world *down* with ``Rotate 90 1 0 0``); Rz(180) makes it upright and
#: Ry sets the azimuth. Found by a search maximising the solid-angle weighted
#: correlation with grace_256 over the upper hemisphere (the lower one of
#: grace_latlong is the smeared rim of the original angular map) at 64x32 and
#: 128x64 texels, over all 48 signed axis permutations x azimuths (0.5 deg steps)
#: and a free 3-D refinement: log-luminance peaks at 273-274 deg, log-chromaticity
#: at 277-279 deg; the mirrored family (vertical flip, det -1) scores lower and
#: its features disagree on the azimuth (247 vs 81 deg), so no flip is applied.
#: The two captures were taken at different places in the cathedral, so
#: correlations stay moderate (log-luminance 0.39, identity -0.13).
GRACE_LATLONG_ROTATION: np.ndarray = np.array([
    [-math.cos(math.radians(275.0)), 0.0, math.sin(math.radians(275.0))],
    [0.0, -1.0, 0.0],
    [math.sin(math.radians(275.0)), 0.0, math.cos(math.radians(275.0))],
])


_TO_WORLD_KEY = "mi_bivariate_to_world"
_EVAL_CHUNK = 1 << 22


# ---------------------------------------------------------------- image I/O


def read_hdr_image(path: PathLike) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Read an HDR image (OpenEXR, Radiance RGBE or PFM content) as linear RGB.

    The format is decided by the content (:func:`mi_bivariate.images.read_image`,
    the toolkit's one image reader); PNG and JPEG content is refused. Alpha channels
    are dropped and grey images expanded to RGB. Values must be finite and
    non-negative; nothing is clamped.

    Returns:
        ``(H, W, 3) float32`` radiance and the ``(4, 4)`` ``to_world`` stored
        by :meth:`Probe.save_exr` in the file's metadata (``None`` if absent).

    Raises:
        InputError: unknown extension or content, missing or unreadable file,
            unsupported channel layout, NaN/Inf/negative pixels.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in PROBE_FORMATS:
        raise InputError(path, f"unknown image type: extension {path.suffix or '(none)'!r}",
                         f"use one of {', '.join(PROBE_FORMATS)}")
    pixels, metadata = read_image(path, allow_ldr=False)
    check_radiance(pixels, path)
    to_world = None
    if _TO_WORLD_KEY in metadata:
        try:
            to_world = np.array([float(x) for x in str(metadata[_TO_WORLD_KEY]).split()]).reshape(4, 4)
        except ValueError:
            raise InputError(path, f"malformed {_TO_WORLD_KEY} metadata") from None
        if not np.all(np.isfinite(to_world)):
            raise InputError(path, f"malformed {_TO_WORLD_KEY} metadata (non-finite values)")
    return pixels, to_world


def check_radiance(data: np.ndarray, source: Any) -> None:
    """Raise :class:`InputError` naming ``source`` if ``data`` (..., 3) has NaN,
    infinite or negative values (counted per pixel)."""
    if np.isfinite(data).all() and not (data < 0).any():  # the common case in two flat passes (~2 ms at 1k)
        return
    nan = np.isnan(data).any(axis=-1)
    inf = np.isinf(data).any(axis=-1)
    neg = (data < 0).any(axis=-1)
    n_bad = int((nan | inf | neg).sum())
    if n_bad:
        parts = [f"{int(n)} {what}" for n, what in ((nan.sum(), "NaN"), (inf.sum(), "infinite"),
                                                   (neg.sum(), "negative")) if n]
        raise InputError(source, f"{n_bad} of {nan.size} pixels are not valid radiance ("
                         + ", ".join(parts) + ")", "repair the image; values are never clamped")


def check_probe(value: Any, source: Any = "probe") -> "Probe":
    """``value`` if it is a :class:`Probe`, else :class:`InputError` naming ``source`` (a front door's
    check: a file name or an array given where a probe goes)."""
    if not isinstance(value, Probe):
        raise InputError(source, f"expected a mi_bivariate.probes.Probe, got a {type(value).__name__}",
                         "load one with mi_bivariate.sources.load_probe(path or shared name) or Probe.load(path)")
    return value


def refuse_probe(value: Any, source: Any = "brdf", hint: str = "pass the BRDF first and the probe second") -> None:
    """Raise :class:`InputError` naming ``source`` if ``value`` is a :class:`Probe` where a BRDF goes.

    A probe has an ``eval`` (its radiance in a direction), so the duck typing that takes any object with
    ``eval(theta_h, theta_d, phi_d)`` as a BRDF would read radiance as reflectance: every front door that
    accepts such objects asks this first."""
    if isinstance(value, Probe):
        raise InputError(source, "got a Probe where a BRDF goes", hint)


def check_lit(probe: "Probe", source: Any, every_channel: bool = False) -> None:
    """Raise :class:`InputError` naming ``source`` if ``probe`` emits no light at all (every texel 0), its
    brightest texel lies outside float32's working range (:data:`~mi_bivariate.limits.MAX_RADIANCE`,
    :data:`~mi_bivariate.limits.MIN_RADIANCE`, as a photo's brightest pixel), or, with ``every_channel``
    (as a recovery from it needs), no light in one of its colour channels. The front doors that light
    with a user's probe ask this; probes made from it (downsampled, rotated) are not asked again."""
    top = float(probe.data.max())  # (no negative value: check_radiance)
    if not top > 0.0:
        raise InputError(source, "probe is black: nothing would be lit", "give a probe that emits light")
    check_brightest(top, source, "probe")
    if every_channel:
        dark = [name for name, lit in zip("RGB", np.any(probe.data[..., :3] > 0.0, axis=(0, 1))) if not lit]
        if dark:
            raise InputError(source, f"the probe sheds no light in its {'/'.join(dark)} channel: the table "
                             "cannot be measured there", "give a probe with light in every colour channel")


def _image_argument(image: Union[np.ndarray, PathLike], source: Optional[str]) -> Tuple[np.ndarray, str]:
    if isinstance(image, (str, os.PathLike)):
        return read_hdr_image(image)[0], source or os.fspath(image)
    source = source or "<array>"
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise InputError(source, f"image has shape {image.shape}; expected (H, W), (H, W, 3) or (H, W, 4)")
    image = np.repeat(image, 3, axis=-1) if image.shape[-1] == 1 else image[..., :3]
    check_radiance(image, source)
    return image, source


# ------------------------------------------------------------ lat-long frame


def latlong_directions(height: int, width: int) -> np.ndarray:
    """Local-frame directions of the texel positions, ``(H, W, 3) float64``.

    Column i at u = (i + 1/2) / W, row j at v = j / (H - 1): exactly where
    Mitsuba's envmap returns the stored texel without interpolation.
    """
    phi = 2 * math.pi * (np.arange(width) + 0.5) / width
    theta = math.pi * np.arange(height) / (height - 1)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(np.sin(phi) * st, ct, -np.cos(phi) * st), axis=-1)


def _row_band_edges(height: int) -> Tuple[np.ndarray, np.ndarray]:
    """Polar-angle band [lo, hi] (radians) represented by each row."""
    half = 0.5 * math.pi / (height - 1)
    theta = math.pi * np.arange(height) / (height - 1)
    return np.clip(theta - half, 0.0, math.pi), np.clip(theta + half, 0.0, math.pi)


def rotation_matrix(euler_deg: Sequence[float]) -> np.ndarray:
    """``(3, 3)`` rotation from Euler angles in degrees.

    Order: extrinsic x, then y, then z (about the fixed world axes), i.e.
    ``R = Rz(z) @ Ry(y) @ Rx(x)``; positive angles turn counter-clockwise
    when looking down the axis (right-hand rule). scipy's ``"xyz"``.
    """
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", euler_angles(euler_deg), degrees=True).as_matrix()


def euler_angles(euler_deg: Any, source: str = "euler_deg") -> np.ndarray:
    """Three finite Euler angles in degrees as ``(3,) float64``, else :class:`InputError` naming ``source``."""
    try:
        angles = np.asarray(euler_deg, dtype=np.float64)
    except (TypeError, ValueError):
        angles = None
    if angles is None or angles.shape != (3,) or not np.all(np.isfinite(angles)):
        raise InputError(source, f"must be three finite angles in degrees (about x, then y, then z), got {euler_deg!r}",
                         "e.g. (0, 90, 0)")
    return angles


def _as_transform(matrix: Any, source: str, allow_reflection: bool) -> np.ndarray:
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(source, f"rotation must be a finite (3, 3) or (4, 4) matrix, got {matrix!r}") from None
    if m.shape == (4, 4):
        if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9 or np.abs(m[:3, 3]).max() > 1e-9:
            raise InputError(source, "an environment map transform must be a pure rotation (no translation/projection)")
        m = m[:3, :3]
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InputError(source, f"rotation must be a finite (3, 3) or (4, 4) matrix, got shape {m.shape}")
    if np.abs(m.T @ m - np.eye(3)).max() > 1e-5:
        raise InputError(source, "rotation matrix is not orthonormal",
                         "give a rotation (orthonormal rows, no scale), or Euler angles")
    if np.linalg.det(m) < 0 and not allow_reflection:
        raise InputError(source, "rotation matrix has determinant -1 (a mirror flip)",
                         "pass allow_reflection=True if the flip is intended")
    out = np.eye(4)
    out[:3, :3] = m
    return out


# --------------------------------------------------------------------- Probe


@dataclass(frozen=True, eq=False)
class Probe:
    """A light probe in Mitsuba's lat-long frame with an explicit rotation.

    ``Probe(data)`` takes any lat-long sampling of ``H >= 3`` rows and ``W >= 2`` columns (Mitsuba's
    envmap does: e.g. ``2^k + 1`` rows with texels on both poles), while :meth:`load` refuses a file that
    is not ``2H x H`` (such a file is usually an angular map, a mirror ball or a cube map:
    :meth:`from_angular_map`, :meth:`from_mirror_ball`).

    Attributes:
        data: ``(H, W, 3) float32`` linear radiance (read-only copy), H >= 3, W >= 2; NaN, infinite or
            negative values are refused, and texels below :data:`~mi_bivariate.limits.RADIANCE_FLOOR`
            (1e-25) read as 0. Whether its brightest texel is within float32's working range is asked
            where a recovery or the command line lights with it (:func:`check_lit`).
        to_world: ``(4, 4) float64`` orthogonal transform, the envmap emitter's
            ``to_world``: a local lat-long direction d is the world direction
            ``to_world[:3, :3] @ d``.
        source: where the data came from (file name), used in error messages.
    """

    data: np.ndarray
    to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    source: str = "<array>"
    _emitters: Dict[str, Any] = field(default_factory=dict, init=False, repr=False)
    _digest: List[str] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        if isinstance(self.data, (str, bytes, os.PathLike)):
            raise InputError("data", f"got the file name {os.fspath(self.data)!r} where the probe's radiance goes",
                             "read a file with Probe.load(path) or mi_bivariate.sources.load_probe(path)")
        try:
            data = np.array(self.data, dtype=np.float32, copy=True)
        except (TypeError, ValueError):
            raise InputError("data", f"expected an (H, W, 3) array of radiance, got a {type(self.data).__name__}",
                             "read a file with Probe.load(path) or mi_bivariate.sources.load_probe(path)") from None
        if data.ndim != 3 or data.shape[2] != 3 or data.shape[0] < 3 or data.shape[1] < 2:
            raise InputError(self.source, f"probe data has shape {data.shape}; expected (H >= 3, W >= 2, 3)",
                             "give a latitude-longitude environment map, twice as wide as it is tall")
        check_radiance(data, self.source)
        # Texels below RADIANCE_FLOOR count as 0: the lighting kernels' products of them leave float32's normal
        # range, and some threads flush such values while others keep them (300 texels of 1e-40 in uffizi_256
        # gave tables 1.3e-11 apart with --threads 1 and 2; of 1e-37, 7.7e-9).
        data[data < RADIANCE_FLOOR] = 0.0
        data.setflags(write=False)
        to_world = _as_transform(self.to_world, "to_world" if self.source == "<array>" else self.source,
                                 allow_reflection=True)
        to_world.setflags(write=False)
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "to_world", to_world)

    def __getstate__(self) -> dict:
        # Loaded emitters are per-process Mitsuba objects; rebuild them lazily.
        return {"data": self.data, "to_world": self.to_world, "source": self.source}

    def __setstate__(self, state: dict) -> None:
        for key, value in state.items():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, key, value)
        object.__setattr__(self, "_emitters", {})
        object.__setattr__(self, "_digest", [])

    def __repr__(self) -> str:
        return f"Probe({self.source!r}, {self.width}x{self.height})"

    def content_digest(self) -> str:
        """A hex digest of the radiance data, its shape and ``to_world`` (computed once: the probe is
        immutable). Equal digests mean equal probes; caches of probe-derived values key on it."""
        if not self._digest:
            h = hashlib.sha256()  # SHA-NI: ~3 ms for a 1k probe
            h.update(repr(self.data.shape).encode())
            h.update(np.ascontiguousarray(self.data).data)
            h.update(np.ascontiguousarray(self.to_world, dtype=np.float64).data)
            self._digest.append(h.hexdigest())
        return self._digest[0]

    @property
    def height(self) -> int:
        return self.data.shape[0]

    @property
    def width(self) -> int:
        return self.data.shape[1]

    # ---------------------------------------------------------- construction

    @classmethod
    def load(cls, path: PathLike, rotation: Any = None) -> "Probe":
        """Read a lat-long probe (.exr, .hdr/.rgbe, .pfm), ``2H x H`` pixels, as stored.

        The file is read as it is stored, whatever its name or folder: a shared probe's file
        (``$MI_BIVARIATE_DATA/probes/grace_latlong_1k.exr``) gets no rotation here, and
        ``grace_latlong_1k`` is stored upside down. :func:`mi_bivariate.sources.load_probe` (a path or
        a shared name, as the command line takes them) and :func:`shared_probe` give a shared probe
        with its rotation (:func:`shared_rotation`).

        Args:
            path: the image; a ``to_world`` written by :meth:`save_exr` is restored.
            rotation: optional extra rotation applied after it: a (3, 3) or
                (4, 4) matrix, or three Euler angles in degrees (see
                :func:`rotation_matrix`).

        Raises:
            InputError: an unreadable or invalid file (naming it), a file that is not 2:1, or a
                ``rotation`` that is none of these (naming ``rotation``).
        """
        if rotation is not None:  # checked before the file is read
            given = rotation
            try:
                rotation = np.asarray(given, dtype=np.float64)
            except (TypeError, ValueError):
                rotation = np.empty(0)
            if rotation.shape not in ((3,), (3, 3), (4, 4)):
                raise InputError("rotation", "must be three Euler angles in degrees, or a (3, 3) or (4, 4) rotation "
                                 f"matrix, got {given!r}", "e.g. rotation=(0, 90, 0)")
            if rotation.shape == (3,):
                rotation = rotation_matrix(euler_angles(rotation, "rotation"))
            rotation = _as_transform(rotation, "rotation", allow_reflection=False)
        data, to_world = read_hdr_image(path)
        if data.ndim == 3 and data.shape[1] != 2 * data.shape[0]:
            raise InputError(path, f"is {data.shape[1]} x {data.shape[0]} pixels, not a 2:1 lat-long (equirectangular) "
                                   "map", "convert an angular, mirror-ball or cube-map probe to lat-long first")
        probe = cls(data, np.eye(4) if to_world is None else to_world, os.fspath(path))
        if rotation is None:
            return probe
        return probe.rotated(matrix=rotation)

    @classmethod
    def constant(cls, radiance: Union[float, Sequence[float]], res: Union[int, Tuple[int, int]] = 32) -> "Probe":
        """Uniform environment (furnace tests).

        Args:
            radiance: scalar or RGB radiance.
            res: width W (height ``max(3, W // 2)``), or ``(H, W)``; each at most
                :data:`~mi_bivariate.limits.MAX_RESOLUTION`.
        """
        if np.ndim(res) == 0:  # the width
            w = whole_number("res", res)
            if w < 2:
                raise InputError("res", f"must be at least 2 (the width W; the height is max(3, W // 2)), got {w}")
            check_max("res", w, MAX_RESOLUTION)
            h = max(3, w // 2)
        else:
            if np.ndim(res) != 1 or len(res) != 2:
                raise InputError("res", f"must be the width W or (H, W), got {res!r}")
            h, w = whole_number("res H", res[0]), whole_number("res W", res[1])
            for name, value, least in (("res H", h, 3), ("res W", w, 2)):
                if value < least:
                    raise InputError(name, f"must be at least {least}, got {value}")
                check_max(name, value, MAX_RESOLUTION)
        try:
            rgb = np.broadcast_to(np.asarray(radiance, dtype=np.float32), (3,))
        except (TypeError, ValueError):
            raise InputError("radiance", f"must be one number or three (RGB), got {radiance!r}") from None
        return cls(np.broadcast_to(rgb, (h, w, 3)), source=f"constant{tuple(float(x) for x in rgb)}")

    @classmethod
    def from_angular_map(cls, image: Union[np.ndarray, PathLike], width: Optional[int] = None,
                         source: Optional[str] = None) -> "Probe":
        """Convert a Debevec angular map ("light probe" image) to lat-long.

        Args:
            image: square ``(S, S, 3)`` array (row 0 at the top) or a file;
                the circle inscribed in the square is the whole sphere.
            width: lat-long width W, a whole number from 2 to :data:`~mi_bivariate.limits.MAX_RESOLUTION`
                (height ``max(3, W // 2)``); defaults to S.
        """
        return cls._from_disk_image(image, width, source, "angular map")

    @classmethod
    def from_mirror_ball(cls, image: Union[np.ndarray, PathLike], width: Optional[int] = None,
                         source: Optional[str] = None) -> "Probe":
        """Convert an orthographic mirror-ball photograph to lat-long.

        Args:
            image: square ``(S, S, 3)`` crop whose inscribed circle is the
                ball's silhouette (row 0 at the top), or a file. Directions
                near -z (behind the ball) come from the unreliable rim.
            width: lat-long width W, a whole number from 2 to :data:`~mi_bivariate.limits.MAX_RESOLUTION`
                (height ``max(3, W // 2)``); defaults to S.
        """
        return cls._from_disk_image(image, width, source, "mirror ball")

    @classmethod
    def _from_disk_image(cls, image: Any, width: Optional[int], source: Optional[str], kind: str) -> "Probe":
        pixels, source = _image_argument(image, source)
        size = pixels.shape[0]
        if pixels.shape[1] != size:
            raise InputError(source, f"{kind} image is {pixels.shape[1]}x{size}; expected a square crop "
                             "whose inscribed circle is the sphere")
        if width is None:
            width = size
        else:
            width = whole_number("width", width)
            if width < 2:
                raise InputError("width", f"must be at least 2 (the lat-long width W; the height is max(3, W // 2)), "
                                 f"got {width}")
            check_max("width", width, MAX_RESOLUTION)
        d = latlong_directions(max(3, width // 2), width)
        theta = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])  # angle from +z
        radius = theta / math.pi if kind == "angular map" else np.sin(0.5 * theta)
        azimuth = np.arctan2(d[..., 1], d[..., 0])
        data = _bilinear_disk_lookup(pixels, radius * np.cos(azimuth), radius * np.sin(azimuth))
        return cls(data, source=f"{source} ({kind})")

    # ------------------------------------------------------------ transforms

    def rotated(self, matrix: Any = None, euler_deg: Optional[Sequence[float]] = None,
                allow_reflection: bool = False) -> "Probe":
        """The same probe turned by a rotation R applied after ``to_world``.

        ``rotated(R).eval(R @ d) == eval(d)``; the data is not resampled.

        Args:
            matrix: (3, 3) or (4, 4) orthogonal matrix.
            euler_deg: instead, Euler angles in degrees (see :func:`rotation_matrix`).
            allow_reflection: accept a matrix with determinant -1 (a mirror flip);
                refused by default so no flip happens by accident.
        """
        if (matrix is None) == (euler_deg is None):
            raise InputError("matrix" if matrix is not None else "euler_deg",
                             f"give exactly one of matrix or euler_deg, got {'both' if matrix is not None else 'neither'}",
                             "e.g. probe.rotated(euler_deg=(0, 90, 0))")
        if matrix is None:
            matrix = rotation_matrix(euler_deg)
        m = _as_transform(matrix, self.source, allow_reflection)
        return Probe(self.data, m @ self.to_world, self.source)

    def downsampled(self, factor: int) -> "Probe":
        """Area-averaged probe about ``factor`` times smaller in each direction.

        Columns are averaged in blocks of ``factor`` (W must divide); rows are
        re-binned to ``ceil(H / factor)`` rows by exact sin-weighted overlap
        of the row bands, so ``mean_radiance()`` is preserved exactly (up to
        float32 rounding). ``to_world`` is kept.
        """
        if factor < 1 or self.width % factor:
            raise ValueError(f"factor {factor} must be >= 1 and divide the width {self.width}")
        if factor == 1:
            return self
        # Column blocks summed in order and divided (what ``mean(axis=2)`` of the reshaped
        # array computes, bit for bit, without its strided reduction: ~4x faster at 1k).
        cols = self.data[:, 0::factor].astype(np.float64)
        for i in range(1, factor):
            cols += self.data[:, i::factor]
        cols /= factor
        new_h = max(3, -(-self.height // factor))
        lo, hi = _row_band_edges(self.height)
        new_lo, new_hi = _row_band_edges(new_h)
        a = np.maximum(new_lo[:, None], lo[None, :])
        b = np.minimum(new_hi[:, None], hi[None, :])
        overlap = np.where(b > a, np.cos(a) - np.cos(b), 0.0)  # (new_h, H) sin-weighted measure
        # One BLAS product over the rows (an einsum here was 4x slower).
        rows = (overlap @ cols.reshape(self.height, -1)).reshape(new_h, -1, 3)
        rows /= overlap.sum(axis=1)[:, None, None]
        return Probe(rows.astype(np.float32), self.to_world, self.source)

    # ------------------------------------------------------------- quadrature

    def solid_angles(self) -> np.ndarray:
        """Solid angle of each texel, ``(H, W) float64`` in sr (sums to 4 pi).

        Row j owns the polar band halfway to its neighbours (Mitsuba puts rows
        at theta = j pi / (H - 1)), column i a 2 pi / W wedge.
        """
        lo, hi = _row_band_edges(self.height)
        band = (np.cos(lo) - np.cos(hi)) * (2 * math.pi / self.width)
        return np.repeat(band[:, None], self.width, axis=1)

    def texel_directions(self) -> Tuple[np.ndarray, np.ndarray]:
        """World directions ``(H*W, 3) float64`` of the texel positions (row-major,
        matching ``data.reshape(-1, 3)``) and their solid angles ``(H*W,)`` in sr."""
        d = latlong_directions(self.height, self.width).reshape(-1, 3) @ self.to_world[:3, :3].T
        return d, self.solid_angles().reshape(-1)

    def mean_radiance(self) -> np.ndarray:
        """Solid-angle weighted mean radiance over the sphere, ``(3,) float64``."""
        w = self.solid_angles()
        return np.einsum("hw,hwc->c", w, self.data.astype(np.float64)) / w.sum()

    # ---------------------------------------------------------------- Mitsuba

    def emitter_dict(self) -> dict:
        """Mitsuba ``envmap`` emitter dictionary (data passed as a ``mi.Bitmap``)."""
        return {
            "type": "envmap",
            "bitmap": mi.Bitmap(np.array(self.data)),  # nanobind wants a writable array
            "to_world": mi.ScalarTransform4f(self.to_world),
        }

    def emitter(self) -> Any:
        """The loaded ``envmap`` emitter for the active variant (cached)."""
        variant = mi.variant()
        if variant not in self._emitters:
            self._emitters[variant] = mi.load_dict(self.emitter_dict())
        return self._emitters[variant]

    def eval_dr(self, directions: Any, active: Any = True) -> Any:
        """Radiance towards unit world ``directions`` (``mi.Vector3f``) as ``mi.Color3f``.

        Calls the envmap emitter's own ``eval`` (which looks up ``-si.wi``), so
        the values are bit-identical to what a render sees. Lanes where
        ``active`` (``mi.Bool``) is false return 0 without reading the map
        (masked gathers: the lighting kernels skip directions below the horizon).
        """
        emitter = self.emitter()
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = -directions
        return emitter.eval(si, active)

    def eval(self, directions: np.ndarray) -> np.ndarray:
        """Radiance towards world ``directions`` ``(N, 3)`` (normalised here): ``(N, 3) float32``."""
        d = np.asarray(directions, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3:
            raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        if not np.all(np.isfinite(norm) & (norm > 0)):
            raise ValueError("directions must be finite and non-zero")
        d = (d / norm).astype(np.float32)
        self.emitter()  # select the variant before creating Dr.Jit arrays
        out = np.empty((len(d), 3), dtype=np.float32)
        for start in range(0, len(d), _EVAL_CHUNK):  # bounds Dr.Jit memory, not a per-sample loop
            chunk = d[start:start + _EVAL_CHUNK]
            out[start:start + len(chunk)] = np.array(self.eval_dr(mi.Vector3f(chunk.T))).T
        return out

    # -------------------------------------------------------------------- I/O

    def save_exr(self, path: PathLike) -> None:
        """Write ``data`` as a float32 RGB OpenEXR (atomically, with provenance in the header).

        The image stays in the probe's own frame; ``to_world`` goes into the
        file's metadata and :meth:`load` restores it (Mitsuba's ``filename``
        loading ignores it).
        """
        write_exr(path, self.data, units="linear RGB radiance (relative)",
                  metadata={_TO_WORLD_KEY: " ".join(repr(float(x)) for x in self.to_world.reshape(-1))})


# ----------------------------------------------------------------- helpers


def _bilinear_disk_lookup(image: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a square image at normalised coordinates (a right,
    b up, both in [-1, 1]); pixel centres at (k + 1/2), edges clamped."""
    size = image.shape[0]
    x = np.clip((a + 1) * 0.5 * size - 0.5, 0, size - 1)
    y = np.clip((1 - b) * 0.5 * size - 0.5, 0, size - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), size - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), size - 2)
    wx, wy = (x - x0)[..., None], (y - y0)[..., None]
    img = image.astype(np.float64)
    top = img[y0, x0] * (1 - wx) + img[y0, x0 + 1] * wx
    bottom = img[y0 + 1, x0] * (1 - wx) + img[y0 + 1, x0 + 1] * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)



def log_luminance_correlation(reference: Probe, other: Probe, width: int = 64,
                              min_elevation_deg: float = -90.0) -> float:
    """Solid-angle weighted Pearson correlation of log-luminance of two probes.

    Both are area-averaged to about ``width`` texels across; ``other`` is
    looked up (with its ``to_world``) at ``reference``'s texel directions whose
    elevation above the world horizon (y = 0) exceeds ``min_elevation_deg``.
    Scale-invariant, so probes of different exposure compare fairly.
    """
    ref = reference.downsampled(max(1, reference.width // width))
    oth = other.downsampled(max(1, other.width // width))
    dirs, weights = ref.texel_directions()
    keep = dirs[:, 1] > math.sin(math.radians(min_elevation_deg)) if min_elevation_deg > -90 else slice(None)
    la = _safe_log(luminance(ref.data.reshape(-1, 3)))[keep]
    lb = _safe_log(luminance(oth.eval(dirs[keep])))
    return _weighted_correlation(la, lb, weights[keep])


def _safe_log(lum: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(lum, 1e-6 * max(float(lum.mean()), 1e-30)))


def _weighted_correlation(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    w = w / w.sum()
    a = a - w @ a
    b = b - w @ b
    return float((w @ (a * b)) / math.sqrt((w @ (a * a)) * (w @ (b * b))))


# ------------------------------------------------------------ shared probes


def shared_probe(name: str, data_dir: Optional[PathLike] = None) -> Probe:
    """Load one of the shared probes by stem (see :data:`SHARED_PROBES`).

    ``grace_latlong_1k`` gets :data:`GRACE_LATLONG_ROTATION`, so it lines up
    with ``grace_256``.

    Args:
        name: file stem, e.g. ``"grace_256"``.
        data_dir: the shared data folder (or its ``probes`` subfolder);
            defaults to ``$MI_BIVARIATE_DATA``.
    """
    return Probe.load(shared_probe_path(name, data_dir), rotation=shared_rotation(name))


def shared_rotation(name: str) -> Optional[np.ndarray]:
    """The rotation :func:`shared_probe` gives the shared probe ``name`` (``None``: as stored)."""
    return GRACE_LATLONG_ROTATION if name == "grace_latlong_1k" else None


def shared_probe_path(name: str, data_dir: Optional[PathLike] = None) -> Path:
    """The file :func:`shared_probe` reads for ``name``.

    Raises:
        InputError: an unknown name, no data folder, or no such file in it.
    """
    if name not in SHARED_PROBES:
        raise InputError(name, "unknown shared probe", "one of " + ", ".join(SHARED_PROBES))
    if data_dir is None:
        data_dir = os.environ.get("MI_BIVARIATE_DATA")
        if not data_dir:
            raise InputError("MI_BIVARIATE_DATA", "not set", "set it to the shared data folder, or give --data; "
                             "from Python, data_dir=")
    folder = Path(data_dir)
    if (folder / "probes").is_dir():
        folder = folder / "probes"
    matches = sorted(p for p in folder.glob(f"{name}.*") if p.suffix.lower() in PROBE_FORMATS)
    if not matches:
        problem = (f"shared probe {name!r} not found" if folder.is_dir() else
                   f"the shared data folder is a file, not a folder (looking for the probe {name!r})" if folder.exists()
                   else f"the shared data folder does not exist (looking for the probe {name!r})")
        raise InputError(folder, problem, "set MI_BIVARIATE_DATA or --data to the folder with probes/, or give a "
                         "probe file")
    return matches[0]
