"""Reading and writing the toolkit's images (linear HDR, float32 RGB).

One reader, :func:`read_image`, serves every image input (photographs,
probes, masks). It decides the format by the file's content (magic bytes),
never by its name:

- OpenEXR (``76 2f 31 01``) through the ``OpenEXR`` package;
- Radiance RGBE (``#?``) after :func:`check_rgbe` validated its structure
  (Mitsuba's RGBE reader corrupts the heap on a bad run length), then Mitsuba,
  with the header's ``EXPOSURE``/``COLORCORR`` undone (:func:`check_rgbe` reads them);
- PFM (``PF``/``Pf`` header) after its header and size are checked, then Mitsuba;
- PNG and JPEG (8- or 16-bit sRGB, not radiometric): with an :class:`InputWarning`, or
  an :class:`InputError` where a linear image is required or the file is
  named like an HDR image.

Image sizes are checked before pixels are allocated. Readers raise
:class:`InputError` naming the file; writers are atomic, and EXR outputs
carry provenance (tool version, command line, units) in their header.
"""

from __future__ import annotations

import contextlib
import math
import os
import shlex
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Any, Dict, Iterator, Optional, Tuple

import mitsuba as mi
import numpy as np

from mi_bivariate import __version__
from mi_bivariate.atomic import atomic_path
from mi_bivariate.common import PathLike, luminance
from mi_bivariate.errors import InputError, InputWarning, array_from

HDR_SUFFIXES = (".exr", ".hdr", ".rgbe", ".pic", ".pfm")
LDR_SUFFIXES = (".png", ".jpg", ".jpeg")

#: Largest image read, in pixels (width x height): 2^28 (16384 x 16384, 3 GiB as float32 RGB).
MAX_IMAGE_PIXELS = 1 << 28

EXR_MAGIC = b"\x76\x2f\x31\x01"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
FORMAT_NAMES = {"exr": "OpenEXR", "rgbe": "Radiance HDR", "pfm": "PFM", "png": "PNG", "jpeg": "JPEG"}
#: Default units written into EXR headers of rendered or captured images.
RADIANCE_UNITS = "linear RGB radiance (relative, W m^-2 sr^-1 up to the probe's scale)"


def sniff_format(path: PathLike) -> Optional[str]:
    """The image format of a file's content: ``exr``, ``rgbe``, ``pfm``, ``png``, ``jpeg`` or ``None``."""
    with open(path, "rb") as f:
        head = f.read(16)
    if head.startswith(EXR_MAGIC):
        return "exr"
    if head.startswith(b"#?"):
        return "rgbe"
    if head[:2] in (b"PF", b"Pf") and head[2:3].isspace():
        return "pfm"
    if head.startswith(PNG_MAGIC):
        return "png"
    if head.startswith(JPEG_MAGIC):
        return "jpeg"
    return None


def _check_size(path: Path, width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise InputError(path, f"cannot be read as an image: empty ({width}x{height} pixels)")
    if width * height > MAX_IMAGE_PIXELS:
        raise InputError(path, f"image is {width}x{height} pixels, over the limit of {MAX_IMAGE_PIXELS} pixels",
                         "downsample it")


def read_image(path: PathLike, allow_ldr: bool = True) -> Tuple[np.ndarray, Dict[str, str]]:
    """Read an image file as linear RGB, whatever its name says.

    Grey images are expanded to RGB; alpha (and any channel past RGB) is
    dropped. Values are not validated here (probes reject NaN/Inf/negatives,
    capture counts and drops them).

    Args:
        path: the file; its extension must be an image one (``.exr``,
            ``.hdr``, ``.rgbe``, ``.pic``, ``.pfm``, ``.png``, ``.jpg``), but
            the content decides the format.
        allow_ldr: accept PNG/JPEG (linearised from sRGB, with an
            :class:`InputWarning`); otherwise they are an :class:`InputError`.

    Returns:
        ``(H, W, 3) float32`` pixels and the file's string metadata (EXR
        header attributes; empty for other formats).

    Raises:
        InputError: unknown extension or content, missing, truncated or
            corrupt file, too large, unsupported channel layout, PNG/JPEG content
            where linear radiance is required.
    """
    return _read_checked(Path(path), allow_ldr, keep_alpha=False)


def _read_checked(path: Path, allow_ldr: bool, keep_alpha: bool,
                  radiance: bool = True) -> Tuple[np.ndarray, Dict[str, str]]:
    """:func:`read_image` (with the file's alpha last when ``keep_alpha`` and it has one; integer EXR channels
    refused unless ``radiance`` is false, as for a mask, where object ids are a fine selection)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in HDR_SUFFIXES + LDR_SUFFIXES:
        raise InputError(path, f"unknown image type: extension {path.suffix or '(none)'!r}",
                         f"use one of {', '.join(HDR_SUFFIXES + LDR_SUFFIXES)}")
    if not path.exists():
        raise InputError(path, "no such file", "check the path")
    if not path.is_file():
        raise InputError(path, "not a file", "give the path of an image file, not of a folder")
    try:
        fmt = sniff_format(path)
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror or e})", "check the file's permissions") from None
    if fmt is None:
        raise InputError(path, "cannot be read as an image: not an OpenEXR, Radiance HDR, PFM, PNG or JPEG file",
                         "the file is corrupt or of another type")
    if fmt in ("png", "jpeg"):
        kind = f"{_ldr_bits(path, fmt)}-bit {FORMAT_NAMES[fmt]}"
        if suffix in HDR_SUFFIXES:
            raise InputError(path, f"is {'an' if kind.startswith('8') else 'a'} {kind} image named {path.suffix}: "
                                   "not linear radiance",
                             "convert the original capture to a linear HDR image")
        if not allow_ldr:
            raise InputError(path, f"{kind} image: not radiometric", "use a linear HDR image (.exr, .hdr, .pfm)")
        warnings.warn(f"{path}: {kind} image is not radiometric; it is linearised from sRGB, "
                      "and the recovered BRDF is only qualitative", InputWarning, stacklevel=4)
    return _read_pixels(path, fmt, keep_alpha, radiance)


def _read_pixels(path: Path, fmt: str, keep_alpha: bool, radiance: bool = True) -> Tuple[np.ndarray, Dict[str, str]]:
    """:func:`read_image`'s pixels of a file of format ``fmt``: ``(H, W, 3) float32``, or ``(H, W, 4)``
    with its alpha last when ``keep_alpha`` and the file has one."""
    if fmt == "exr":
        data, metadata = _read_exr(path, keep_alpha, radiance)
    else:
        data, metadata = _read_with_mitsuba(path, fmt, keep_alpha), {}
    if fmt == "pfm":
        _check_pfm_values(path, data)
    if data.ndim == 2:
        data = data[..., None]
    channels = data.shape[2]
    if channels in (1, 2):  # Y or YA
        data = np.concatenate([np.repeat(data[..., :1], 3, axis=2), data[..., 1:2 if keep_alpha else 1]], axis=2)
    elif channels in (3, 4):
        data = data[..., :4 if keep_alpha else 3]
    else:
        raise InputError(path, f"has {channels} channels", "expected grey, RGB or RGBA")
    if data.size == 0:
        raise InputError(path, "is empty")
    return np.ascontiguousarray(data, dtype=np.float32), metadata


def _exr_error(path: Path, exc: BaseException) -> InputError:
    text = " ".join(str(exc).split())[:200] or type(exc).__name__
    return InputError(path, f"cannot be read as an image: corrupt OpenEXR file ({text})",
                      "the file is truncated or corrupt")


def _read_exr(path: Path, keep_alpha: bool = False, radiance: bool = True) -> Tuple[np.ndarray, Dict[str, str]]:
    """An EXR's first part through the ``OpenEXR`` package: ``(H, W, C) float32`` (RGB or Y, then A
    when ``keep_alpha`` and the file has it) and string metadata."""
    import OpenEXR

    try:
        with _library_output():
            return _read_exr_unchecked(path, OpenEXR, keep_alpha, radiance)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 -- RuntimeError, UnicodeDecodeError, ... on corrupt files
        raise _exr_error(path, exc) from None


#: One holder of file descriptors 1 and 2 at a time (:func:`_library_output`).
_HOLD_LOCK = threading.Lock()


@contextlib.contextmanager
def _library_output() -> Iterator[None]:
    """Hold what C libraries write to file descriptors 1 and 2 inside the block (libOpenEXR prints its
    own lines about a corrupt file before raising): replayed if the block succeeds, dropped if it
    raises (the caller reports the problem in its one line instead).

    Only in the main thread, one block at a time: the descriptors belong to the whole process, so
    a read in another thread (a Dask worker, a notebook's pool) leaves them alone, and output other
    threads write during a held block is replayed or dropped with it."""
    if threading.current_thread() is not threading.main_thread() or not _HOLD_LOCK.acquire(blocking=False):
        yield  # another thread, or a block nested in a held one: nothing held
        return
    try:
        with contextlib.ExitStack() as stack:
            for fd, stream in ((1, sys.stdout), (2, sys.stderr)):
                stack.enter_context(_held_fd(fd, stream))
            yield
    finally:
        _HOLD_LOCK.release()


@contextlib.contextmanager
def _held_fd(fd: int, stream: Any) -> Iterator[None]:
    """File descriptor ``fd`` into a temporary file inside the block; its content replayed unless the
    block raises."""
    if stream is not None:
        stream.flush()
    try:
        saved = os.dup(fd)
    except OSError:  # no such descriptor: nothing to hold
        yield
        return
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), fd)
        raised = True
        try:
            yield
            raised = False
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            if not raised:
                held.seek(0)
                text = held.read()
                if text:
                    os.write(fd, text)


def _read_exr_unchecked(path: Path, OpenEXR, keep_alpha: bool = False,  # noqa: N803
                        radiance: bool = True) -> Tuple[np.ndarray, Dict[str, str]]:
    part = _exr_part(path, OpenEXR.File(str(path), header_only=True).parts)
    header = part.header
    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise InputError(path, "is a deep OpenEXR image (a list of samples per pixel), not a flat one",
                         "flatten it (composite its samples) into a scanline or tiled image")
    lo, hi = (np.asarray(v, np.int64) for v in header["dataWindow"])
    width, height = int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    _check_size(path, width, height)
    shown_lo, shown_hi = (np.asarray(v, np.int64) for v in header.get("displayWindow", (lo, hi)))
    _check_size(path, int(shown_hi[0] - shown_lo[0] + 1), int(shown_hi[1] - shown_lo[1] + 1))
    channels = list(header.get("channels", []))
    names = [str(c.name) for c in channels]
    if any((c.xSampling, c.ySampling) != (1, 1) for c in channels):
        raise InputError(path, "has sub-sampled channels", "write full-resolution channels")
    upper = {n.upper(): n for n in names}
    if all(k in upper for k in "RGB"):
        order = [upper[k] for k in "RGB"]
    elif "Y" in upper:
        order = [upper["Y"]]
    else:
        layers = sorted({n.rsplit(".", 1)[0] for n in names
                         if "." in n and n.rsplit(".", 1)[1].upper() in ("R", "G", "B")})
        raise InputError(path, f"has {len(names)} channels ({', '.join(names[:8]) or 'none'}"
                               f"{', ...' if len(names) > 8 else ''})",
                         f"expected grey, RGB or RGBA at the top level; its colour is in the layer(s) "
                         f"{', '.join(repr(v) for v in layers[:4])}: save the one to use as a plain RGB image"
                         if layers else "expected grey, RGB or RGBA")
    if keep_alpha and "A" in upper:
        order.append(upper["A"])
    planes = OpenEXR.File(str(path), separate_channels=True).parts[part.part_index].channels
    integer = [n for n in order if radiance and np.issubdtype(np.asarray(planes[n].pixels).dtype, np.integer)]
    if integer:
        raise InputError(path, f"channel {integer[0]} holds integers (UINT), not radiance",
                         "save the image's colour as HALF or FLOAT channels")
    stack = [np.asarray(planes[n].pixels, dtype=np.float32) for n in order]
    if any(p.shape != (height, width) for p in stack):
        raise InputError(path, "cannot be read as an image: channel sizes disagree with the data window")
    metadata = {str(k): v for k, v in header.items() if isinstance(v, str)}
    return _in_display_window(path, np.stack(stack, axis=-1), lo, shown_lo, shown_hi), metadata


def _exr_part(path: Path, parts: list):
    """The part of a (multi-part) EXR to read: the only one, or the only one with its colour (R, G, B
    or Y) at the top level. A file whose several parts hold colour (render passes: beauty, diffuse,
    ...) is refused with their names, not read from its first part without a word."""
    if len(parts) == 1:
        return parts[0]

    def has_colour(part) -> bool:
        upper = {str(c.name).upper() for c in part.header.get("channels", [])}
        return {"R", "G", "B"} <= upper or "Y" in upper

    coloured = [p for p in parts if has_colour(p)]
    if len(coloured) == 1:
        return coloured[0]
    names = [str(p.name()) or f"#{i}" for i, p in enumerate(coloured or parts)]
    raise InputError(path, f"is a multi-part OpenEXR image whose parts {', '.join(repr(n) for n in names[:6])}"
                           f"{', ...' if len(names) > 6 else ''} {'all hold' if coloured else 'hold no'} colour",
                     "save the part to use as a single-part image")


def _in_display_window(path: Path, data: np.ndarray, lo: np.ndarray, shown_lo: np.ndarray,
                       shown_hi: np.ndarray) -> np.ndarray:
    """An EXR's pixels ``data`` (its data window, from ``lo``) placed in its display window (what a viewer
    shows, and what pixel coordinates such as ``--sphere`` or a principal point refer to): pixels outside
    the data window are 0, pixels outside the display window (overscan) are left out. Unchanged when the
    windows agree."""
    height, width = data.shape[:2]
    if np.array_equal(lo, shown_lo) and np.array_equal(lo + [width - 1, height - 1], shown_hi):
        return data
    shown = np.zeros((int(shown_hi[1] - shown_lo[1] + 1), int(shown_hi[0] - shown_lo[0] + 1)) + data.shape[2:],
                     data.dtype)
    x0, y0 = (int(v) for v in np.maximum(lo, shown_lo))
    x1, y1 = (int(v) for v in np.minimum(lo + [width - 1, height - 1], shown_hi) + 1)
    if x0 >= x1 or y0 >= y1:
        raise InputError(path, "its data window lies outside its display window: no pixel would be shown",
                         "write the image with its data inside the display window")
    shown[y0 - shown_lo[1]:y1 - shown_lo[1], x0 - shown_lo[0]:x1 - shown_lo[0]] = \
        data[y0 - lo[1]:y1 - lo[1], x0 - lo[0]:x1 - lo[0]]
    return shown


def _check_pfm(path: Path) -> None:
    """Validate a PFM header (``PF``/``Pf``, width, height, non-zero finite scale) and its data size."""
    with open(path, "rb") as f:
        head = f.read(256)
    tokens, pos = [], 0
    while len(tokens) < 4:
        while pos < len(head) and head[pos:pos + 1].isspace():
            pos += 1
        start = pos
        while pos < len(head) and not head[pos:pos + 1].isspace():
            pos += 1
        if start == pos:
            raise InputError(path, "cannot be read as an image: corrupt PFM file, incomplete header")
        tokens.append(head[start:pos])
    pos += 1  # the single whitespace byte before the data
    kind, width, height, scale = tokens
    try:
        width, height, scale = int(width), int(height), float(scale)
    except ValueError:
        raise InputError(path, "cannot be read as an image: corrupt PFM file, bad header") from None
    if not np.isfinite(scale) or scale == 0.0:
        raise InputError(path, "cannot be read as an image: corrupt PFM file, bad scale",
                         "its third header line must be a non-zero number (negative: little-endian); write it again")
    _check_size(path, width, height)
    expected = pos + width * height * (3 if kind == b"PF" else 1) * 4
    size = path.stat().st_size
    if size != expected:
        raise InputError(path, f"cannot be read as an image: corrupt PFM file, {size} bytes where its header "
                               f"implies {expected}", "the file is truncated or corrupt")


#: Radiance no capture holds (float16's largest value is 6.5e4): a PFM decoded with the wrong
#: byte order has values up to 3.4e38 and NaNs where the swapped bytes make them.
PLAUSIBLE_RADIANCE = 1e30


def _check_pfm_values(path: Path, data: np.ndarray) -> None:
    """A PFM's decoded floats must look like radiance: nothing beyond :data:`PLAUSIBLE_RADIANCE`. (NaN,
    infinite or negative pixels alone are left to the callers' checks, which count and name them.)"""
    n_nan = int(np.count_nonzero(np.isnan(data)))
    finite = data[np.isfinite(data)]
    top = float(np.abs(finite).max()) if finite.size else 0.0
    if top > PLAUSIBLE_RADIANCE:
        raise InputError(path, f"PFM values are not radiance ({n_nan} NaN, largest magnitude {top:.3g})",
                         "its byte order may be wrong: a negative scale in the header means little-endian")


def _ldr_bits(path: Path, fmt: str) -> int:
    """Bits per channel of a PNG (its IHDR's bit depth: 16, or 8 for 1-8) or a JPEG (8)."""
    if fmt == "png":
        with open(path, "rb") as f:
            head = f.read(25)
        if len(head) == 25 and head[12:16] == b"IHDR" and head[24] == 16:
            return 16
    return 8


def _png_size(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise InputError(path, "cannot be read as an image: corrupt PNG file")
    _check_size(path, int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big"))


#: JPEG start-of-frame markers (SOF0-SOF15 less DHT, JPG and DAC), whose segment holds the image size.
JPEG_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(path: Path) -> None:
    """Check a JPEG's size (its start-of-frame segment, found by walking the marker segments) before
    Mitsuba decodes it (libjpeg allocates the whole image first)."""
    def corrupt() -> InputError:
        return InputError(path, "cannot be read as an image: corrupt JPEG file, no frame header",
                          "the file is truncated or corrupt")

    with open(path, "rb") as f:
        f.seek(2)  # past SOI
        while True:
            if f.read(1) != b"\xff":
                raise corrupt()
            marker = f.read(1)
            while marker == b"\xff":  # fill bytes
                marker = f.read(1)
            if not marker:
                raise corrupt()
            if marker[0] == 0x01 or 0xD0 <= marker[0] <= 0xD8:  # standalone markers: no length
                continue
            if marker[0] in (0xD9, 0xDA):  # end of image, or a scan before any frame header
                raise corrupt()
            length = int.from_bytes(f.read(2), "big")
            if marker[0] in JPEG_SOF_MARKERS:
                body = f.read(5)  # precision, height, width
                if length < 7 or len(body) < 5:
                    raise corrupt()
                _check_size(path, int.from_bytes(body[3:5], "big"), int.from_bytes(body[1:3], "big"))
                return
            if length < 2:
                raise corrupt()
            f.seek(length - 2, os.SEEK_CUR)


def _read_with_mitsuba(path: Path, fmt: str, keep_alpha: bool = False) -> np.ndarray:
    """RGBE, PFM, PNG or JPEG through ``mi.Bitmap`` after the structural checks (PNG and JPEG as
    linear RGB, or RGBA when ``keep_alpha`` and the file has alpha)."""
    scale = None
    if fmt == "rgbe":
        scale = check_rgbe(path)
    elif fmt == "pfm":
        _check_pfm(path)
    elif fmt == "png":
        _png_size(path)
    elif fmt == "jpeg":
        _jpeg_size(path)
    try:
        bitmap = mi.Bitmap(str(path))
        if fmt in ("png", "jpeg"):
            layout = mi.Bitmap.PixelFormat.RGBA if keep_alpha and bitmap.has_alpha() else mi.Bitmap.PixelFormat.RGB
            bitmap = bitmap.convert(layout, mi.Struct.Type.Float32, srgb_gamma=False)
        data = np.array(bitmap, dtype=np.float32, copy=True)
        if scale is not None:
            data *= scale
        return data
    except Exception as exc:  # noqa: BLE001 -- Mitsuba raises RuntimeError with a long C++ message
        text = " ".join(str(exc).split())
        # Mitsuba repeats the path and prefixes its class name; keep only the problem.
        for junk in (f'"{path}":', str(path), "[Bitmap]", "Bitmap:"):
            text = text.replace(junk, "")
        text = text.strip(" :") or type(exc).__name__
        raise InputError(path, f"cannot be read as an image: {text[:200]}",
                         "the file is truncated or corrupt") from None


def load_image(path: PathLike, allow_ldr: bool = True) -> np.ndarray:
    """Load a linear RGB image as ``(H, W, 3) float32`` (see :func:`read_image`)."""
    return read_image(path, allow_ldr=allow_ldr)[0]


def check_rgbe(path: PathLike) -> np.ndarray:
    """Validate a Radiance RGBE file's header and run-length structure without decoding it.

    Returns:
        ``(3,) float32``: what the file's pixels are multiplied by to give the radiance they were
        written from (:func:`_header_scale`: the header's ``EXPOSURE`` and ``COLORCORR``, which
        Mitsuba's reader ignores).

    Raises:
        InputError: no signature, no header end, pixels other than RGBE (a
            ``FORMAT=32-bit_rle_xyze`` file), an unsupported resolution
            line, a scanline of the wrong width, a zero or overlong run, or
            missing data.
    """
    path = Path(path)
    data = path.read_bytes()
    n = len(data)

    def bad(problem: str) -> InputError:
        return InputError(path, f"cannot be read as an image: corrupt Radiance HDR file, {problem}",
                          "write it again, or convert it to OpenEXR")

    if not data.startswith(b"#?"):
        raise bad("no '#?' signature")
    end = data.find(b"\n\n")
    if end < 0:
        raise bad("the header never ends")
    formats = [line[len(b"FORMAT="):].strip() for line in data[:end].split(b"\n") if line.startswith(b"FORMAT=")]
    if formats and formats[-1] != b"32-bit_rle_rgbe":  # Mitsuba reads XYZE pixels as if they were RGB
        raise InputError(path, f"Radiance HDR pixels are {formats[-1].decode(errors='replace')!r}, not RGBE "
                               "(32-bit_rle_rgbe)", "convert it to RGB (ra_xyze -r) or to OpenEXR")
    res_end = data.find(b"\n", end + 2)
    fields = data[end + 2:res_end].split() if res_end > 0 else []
    if len(fields) != 4 or fields[0] not in (b"-Y", b"+Y") or fields[2] not in (b"+X", b"-X") \
            or not fields[1].isdigit() or not fields[3].isdigit():
        raise bad("unsupported resolution line")
    scale = _header_scale(path, data[:end])
    if (fields[0], fields[2]) != (b"-Y", b"+X"):  # Mitsuba reads top-down, left-to-right files only
        raise InputError(path, f"Radiance HDR orientation '{b' '.join(fields).decode()}' (flipped or "
                               "mirrored) is not supported", "write it top-down (-Y H +X W), or convert it to OpenEXR")
    height, width = int(fields[1]), int(fields[3])
    if height == 0 or width == 0:
        raise bad("empty image")
    _check_size(path, width, height)
    pos = res_end + 1
    for y in range(height):
        rle = 8 <= width <= 0x7FFF and pos + 4 <= n and data[pos] == 2 and data[pos + 1] == 2 \
            and not data[pos + 2] & 0x80
        if not rle:
            # Flat (uncompressed) pixels are only valid for the whole image: Mitsuba's
            # reader switching to flat mode mid-image reads past its buffer.
            if y > 0:
                raise bad(f"scanline {y} lacks its run-length marker")
            if n - pos < 4 * width * height:
                raise bad("truncated pixel data")
            return scale
        if (data[pos + 2] << 8 | data[pos + 3]) != width:
            raise bad(f"scanline {y} has the wrong width")
        pos += 4
        for _ in range(4):
            x = 0
            while x < width:
                if pos >= n:
                    raise bad(f"truncated at scanline {y}")
                count = data[pos]
                if count > 128:
                    count, step = count - 128, 2
                else:
                    step = 1 + count
                if count == 0 or count > width - x:
                    raise bad(f"bad run length in scanline {y}")
                pos += step
                x += count
        if pos > n:
            raise bad(f"truncated at scanline {y}")
    return scale


def _header_scale(path: Path, header: bytes) -> np.ndarray:
    """What a Radiance file's pixels are multiplied by to give the radiance they were written from:
    ``(3,) float32``, one over the product of the ``header``'s ``EXPOSURE=`` values and, per channel, of
    its ``COLORCORR=`` values (both cumulative, Radiance's file format); ones without them.

    Raises:
        InputError: a value that is not a positive finite number (or not three of them for COLORCORR).
    """
    scale = np.ones(3, np.float64)
    for line in header.split(b"\n"):
        for key, count in ((b"EXPOSURE=", 1), (b"COLORCORR=", 3)):
            if line.startswith(key):
                try:
                    values = np.array([float(v) for v in line[len(key):].split()], np.float64)
                except ValueError:
                    values = np.array([])
                if len(values) != count or not np.all(np.isfinite(values)) or np.any(values <= 0.0):
                    raise InputError(path, f"Radiance header line {line.decode(errors='replace')!r} is not "
                                           f"{'a positive number' if count == 1 else 'three positive numbers'}",
                                     "fix or remove the line")
                scale /= values
    return scale.astype(np.float32)


def load_mask(path: PathLike, shape: tuple) -> np.ndarray:
    """Load a mask image as ``(H, W) bool`` (usable: a value > 0 in any colour channel and, where the file
    has alpha, alpha > 0; 0, negative, NaN or transparent: not), checking it matches ``shape`` and selects a
    pixel. (A mask painted on a transparent layer over white is the painted part, not the whole image.)

    Any image format will do (8-bit ones without a warning: a mask is not radiometric).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        data = _read_checked(Path(path), allow_ldr=True, keep_alpha=True, radiance=False)[0]  # UINT ids are fine
    if data.shape[:2] != tuple(shape[:2]):
        raise InputError(path, f"mask is {data.shape[1]}x{data.shape[0]} but the image is {shape[1]}x{shape[0]}",
                         "give a mask of the image's size")
    mask = np.any(data[..., :3] > 0, axis=2)
    if data.shape[2] == 4:
        mask &= data[..., 3] > 0
    if not mask.any():
        raise InputError(path, "the mask selects no pixel (no value > 0)",
                         "mark the sphere's pixels with values > 0; 0, negative, NaN and transparent pixels are "
                         "left out")
    return mask


def provenance_header(units: str, extra: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """String attributes for an output EXR header: tool version, command line, units, plus ``extra``."""
    header = {"mi_bivariate_version": __version__,
              "mi_bivariate_command": shlex.join([os.path.basename(sys.argv[0] or "python")] + sys.argv[1:]),
              "units": units}
    header.update({str(k): str(v) for k, v in (extra or {}).items()})
    return header


def write_exr(path: PathLike, image: np.ndarray, units: str = RADIANCE_UNITS,
              metadata: Optional[Dict[str, str]] = None) -> Path:
    """Write a linear ``(H, W, 3)`` image as a float32 RGB EXR (ZIP compressed), atomically.

    Written with the ``OpenEXR`` package; the header carries
    :func:`provenance_header` (``units`` and any ``metadata`` strings).
    """
    import OpenEXR

    path = Path(path)
    image = np.ascontiguousarray(array_from(image, path, "an (H, W, 3) image", np.float32))
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(path, f"image must have shape (H, W, 3), got {image.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              **provenance_header(units, metadata)}
    with atomic_path(path, suffix=".exr") as tmp:
        try:
            OpenEXR.File(header, {"RGB": image}).write(str(tmp))
        except RuntimeError as exc:  # OpenEXR reports I/O failures (a full disk) as RuntimeError
            # its message names the temporary file; keep the operating system's reason only
            reason = str(exc).rstrip(". ").rsplit(". ", 1)[-1] or "write failed"
            raise InputError(path, f"cannot be written ({reason})",
                             "check the folder exists and is writable, and that the disk has space") from None
    return path


#: Rows of a photo that per-pixel float64 arithmetic handles at a time (``silhouette.luminance_map``, ``disc_mask``,
#: ``SphereGeometry.object_mask``): its temporaries stay a few MB instead of a few hundred for a 4096 px photo, whose
#: fresh pages alone cost ~75 ms per float64 array on this project's VM.
CHUNK_ROWS = 256


def bounding_box(mask: np.ndarray) -> Tuple[slice, slice]:
    """``(rows, cols)``: the slices of the smallest box holding every True pixel of an ``(H, W) bool`` mask
    (empty slices when it has none)."""
    rows, cols = np.flatnonzero(np.any(mask, axis=1)), np.flatnonzero(np.any(mask, axis=0))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def circle_box(shape: Tuple[int, int], cx: float, cy: float, r: float) -> Tuple[slice, slice]:
    """``(rows, cols)`` within the ``(H, W)`` frame that hold every pixel whose centre ``k + 0.5`` lies inside the
    circle (``|k + 0.5 - c| < |r|`` along each axis), with a pixel to spare on each side (rounding); the whole
    frame for a circle that is not finite."""
    def span(centre: float, size: int) -> slice:
        lo, hi = centre - abs(r) - 0.5, centre + abs(r) - 0.5  # a centre k + 0.5 inside: lo < k < hi
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return slice(0, size)
        start = min(max(math.floor(lo), 0), size)
        return slice(start, max(start, min(math.ceil(hi) + 1, size)))
    return span(float(cy), shape[0]), span(float(cx), shape[1])


def block_mean(values: np.ndarray, factor: int) -> np.ndarray:
    """``(ceil(H / factor), ceil(W / factor), ...) float64``: the mean of each ``factor x factor`` block of
    ``(H, W)`` or ``(H, W, C)`` values over its finite ones, per channel (NaN where a block has none; the
    last blocks may be cut by the frame). A photo's pixels averaged in linear radiance: what a camera
    of ``factor`` times larger pixels would record."""
    values = np.asarray(values)
    height, width = values.shape[:2]
    rows, cols = -(-height // factor), -(-width // factor)
    pad = ((0, rows * factor - height), (0, cols * factor - width)) + ((0, 0),) * (values.ndim - 2)
    blocks = (rows, factor, cols, factor) + values.shape[2:]
    finite = np.isfinite(values)
    all_finite = bool(finite.all())
    # Copies only where needed: the non-finite values zeroed, the frame padded to whole blocks.
    kept = values if all_finite else np.where(finite, values, np.zeros((), values.dtype))
    if any(after for _, after in pad):
        kept, finite = np.pad(kept, pad), np.pad(finite, pad)
    # Two one-axis sums, each 3x faster than both axes at once for RGB: an (H, W) image's along each block's
    # rows first; an (H, W, C) image's down its columns first, adding whole rows (there 4.5x faster than
    # along the rows first: 0.12 s against 0.53 s for a 4096 px RGB photo by 8).
    first, second = (3, 1) if values.ndim == 2 else (1, 2)
    total = kept.reshape(blocks).sum(axis=first, dtype=np.float64).sum(axis=second)
    if all_finite and not any(after for _, after in pad):
        count = np.full(total.shape, factor * factor, dtype=np.int64)
    else:
        count = finite.reshape(blocks).sum(axis=first).sum(axis=second)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def auto_exposure(image: np.ndarray, mask: Optional[np.ndarray] = None, percentile: float = 99.0) -> float:
    """The exposure (a factor on radiance) that maps the ``percentile`` of the positive, finite
    luminance of ``image`` ``(H, W, 3)`` (over ``mask`` ``(H, W) bool`` when given) to display white; 1
    for an image with no such pixel."""
    values = np.asarray(image)[mask] if mask is not None else np.asarray(image).reshape(-1, 3)
    lum = luminance(values)
    lum = lum[np.isfinite(lum) & (lum > 0.0)]
    level = float(np.percentile(lum, percentile)) if lum.size else 1.0
    return 1.0 / level if level > 0.0 else 1.0


def tonemap(image: np.ndarray, exposure: Optional[float] = None, percentile: float = 99.0) -> np.ndarray:
    """Linear ``(H, W, 3)`` -> sRGB ``(H, W, 3) uint8``.

    ``exposure`` scales radiance before the sRGB curve; by default the
    ``percentile`` of the non-zero luminance maps to 1 (so highlights clip, not the body).
    """
    image = np.nan_to_num(np.asarray(image, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    image = np.clip(image, 0.0, None)
    if exposure is None:
        exposure = auto_exposure(image, percentile=percentile)
    x = np.clip(image * exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path: PathLike, image: np.ndarray, exposure: Optional[float] = None) -> Path:
    """Write a tonemapped sRGB PNG preview of a linear image atomically."""
    path = Path(path)
    image = array_from(image, path, "an (H, W, 3) image")
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(path, f"image must have shape (H, W, 3), got {image.shape}")
    if not np.issubdtype(image.dtype, np.number) or np.iscomplexobj(image):
        raise InputError(path, f"image has dtype {image.dtype}; expected real numbers (linear radiance, or uint8 sRGB)")
    rgb = tonemap(image, exposure) if image.dtype != np.uint8 else image
    # Encoded in memory and written by Python: Mitsuba's file stream does not report a full disk (it left
    # an empty PNG and no error).
    stream = mi.MemoryStream()
    mi.Bitmap(np.ascontiguousarray(rgb), pixel_format=mi.Bitmap.PixelFormat.RGB).write(stream, mi.Bitmap.FileFormat.PNG)
    with atomic_path(path, suffix=".png") as tmp:
        Path(tmp).write_bytes(stream.raw_buffer())
    return path
