"""Reading and writing the toolkit's images (linear HDR, float32 RGB).

Readers validate what they load and raise :class:`InputError` naming the file;
writers are atomic. 8-bit formats load with an :class:`InputWarning`: they are
not radiometric, so a BRDF recovered from them is only qualitative.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Optional, Union

import numpy as np

from mi_bivariate.atomic import atomic_path
from mi_bivariate.errors import InputError, InputWarning

PathLike = Union[str, os.PathLike]
HDR_SUFFIXES = (".exr", ".hdr", ".pfm")
LDR_SUFFIXES = (".png", ".jpg", ".jpeg")


def load_image(path: PathLike, allow_ldr: bool = True) -> np.ndarray:
    """Load a linear RGB image as ``(H, W, 3) float32``.

    Grey images are expanded to RGB; an alpha channel is dropped. Values are
    not validated for NaN/Inf/negatives here: :mod:`mi_bivariate.capture`
    counts and drops such pixels, and probes reject them.
    """
    import mitsuba as mi

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in HDR_SUFFIXES + LDR_SUFFIXES:
        raise InputError(path, f"unknown image extension {path.suffix!r}",
                         f"use one of {', '.join(HDR_SUFFIXES + LDR_SUFFIXES)}")
    if not path.is_file():
        raise InputError(path, "no such file")
    bitmap = open_bitmap(path)
    if suffix in LDR_SUFFIXES:
        if not allow_ldr:
            raise InputError(path, "8-bit image: not radiometric", "use a linear HDR image (.exr, .hdr, .pfm)")
        warnings.warn(f"{path}: 8-bit image is not radiometric; it is linearised from sRGB, "
                      "and the recovered BRDF is only qualitative", InputWarning, stacklevel=2)
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    data = np.array(bitmap, dtype=np.float32, copy=True)
    if data.ndim == 2:
        data = data[..., None]
    channels = data.shape[2]
    if channels in (1, 2):  # Y or YA
        data = np.repeat(data[..., :1], 3, axis=2)
    elif channels in (3, 4):
        data = data[..., :3]
    else:
        raise InputError(path, f"has {channels} channels", "expected grey, RGB or RGBA")
    if data.size == 0:
        raise InputError(path, "is empty")
    return np.ascontiguousarray(data)


def open_bitmap(path: PathLike) -> "mi.Bitmap":
    """``mi.Bitmap(path)`` with its failures turned into one-line :class:`InputError`.

    Radiance ``.hdr`` files are checked with :func:`check_rgbe` first: Mitsuba
    3.9's RGBE reader overruns its buffer on a corrupt run length (heap
    corruption, then a crash far from the cause), so it only ever sees
    structurally valid files.
    """
    import mitsuba as mi

    path = Path(path)
    if path.suffix.lower() in (".hdr", ".rgbe", ".pic"):
        check_rgbe(path)
    try:
        return mi.Bitmap(str(path))
    except Exception as exc:  # Mitsuba raises RuntimeError with a long C++ message
        text = " ".join(str(exc).split())
        # Mitsuba repeats the path and prefixes its class name; keep only the problem.
        for junk in (f'"{path}":', str(path), "[Bitmap]", "Bitmap:"):
            text = text.replace(junk, "")
        text = text.strip(" :") or type(exc).__name__
        raise InputError(path, f"cannot be read as an image: {text[:200]}",
                         "the file is truncated or corrupt") from None


def check_rgbe(path: PathLike) -> None:
    """Validate a Radiance RGBE file's header and run-length structure without decoding it.

    Raises:
        InputError: no signature, no header end, an unsupported resolution
            line, a scanline of the wrong width, a zero or overlong run, or
            missing data.
    """
    path = Path(path)
    data = path.read_bytes()
    n = len(data)

    def bad(problem: str) -> InputError:
        return InputError(path, f"cannot be read as an image: corrupt Radiance HDR file, {problem}")

    if not data.startswith(b"#?"):
        raise bad("no '#?' signature")
    end = data.find(b"\n\n")
    if end < 0:
        raise bad("the header never ends")
    res_end = data.find(b"\n", end + 2)
    fields = data[end + 2:res_end].split() if res_end > 0 else []
    if len(fields) != 4 or fields[0] not in (b"-Y", b"+Y") or fields[2] not in (b"+X", b"-X") \
            or not fields[1].isdigit() or not fields[3].isdigit():
        raise bad("unsupported resolution line")
    height, width = int(fields[1]), int(fields[3])
    if height == 0 or width == 0:
        raise bad("empty image")
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
            return
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


def load_mask(path: PathLike, shape: tuple) -> np.ndarray:
    """Load a mask image as ``(H, W) bool`` (non-zero = usable), checking it matches ``shape``."""
    data = load_image(path, allow_ldr=True) if Path(path).suffix.lower() in HDR_SUFFIXES else _load_ldr_quiet(path)
    if data.shape[:2] != tuple(shape[:2]):
        raise InputError(path, f"mask is {data.shape[1]}x{data.shape[0]} but the image is {shape[1]}x{shape[0]}")
    return np.any(data > 0, axis=2)


def _load_ldr_quiet(path: PathLike) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        return load_image(path)


def write_exr(path: PathLike, image: np.ndarray) -> Path:
    """Write a linear ``(H, W, 3)`` image as a float32 RGB EXR, atomically."""
    import mitsuba as mi

    image = np.ascontiguousarray(image, dtype=np.float32)
    path = Path(path)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(path, f"image must have shape (H, W, 3), got {image.shape}")
    with atomic_path(path, suffix=".exr") as tmp:
        mi.Bitmap(image).write(str(tmp))
    return path


def tonemap(image: np.ndarray, exposure: Optional[float] = None, percentile: float = 99.0) -> np.ndarray:
    """Linear ``(H, W, 3)`` -> sRGB ``(H, W, 3) uint8``.

    ``exposure`` scales radiance before the sRGB curve; by default the
    ``percentile`` of the non-zero luminance maps to 1 (so highlights clip, not the body).
    """
    image = np.nan_to_num(np.asarray(image, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    image = np.clip(image, 0.0, None)
    if exposure is None:
        lum = image @ np.array([0.2126, 0.7152, 0.0722])
        lum = lum[lum > 0.0]
        level = np.percentile(lum, percentile) if lum.size else 1.0
        exposure = 1.0 / level if level > 0.0 else 1.0
    x = np.clip(image * exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path: PathLike, image: np.ndarray, exposure: Optional[float] = None) -> Path:
    """Write a tonemapped sRGB PNG preview of a linear image atomically."""
    import mitsuba as mi

    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(path, f"image must have shape (H, W, 3), got {image.shape}")
    rgb = tonemap(image, exposure) if image.dtype != np.uint8 else image
    with atomic_path(path, suffix=".png") as tmp:
        mi.Bitmap(np.ascontiguousarray(rgb), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(tmp))
    return path
