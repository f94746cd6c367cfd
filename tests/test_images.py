"""images.py against files written by hand: every byte placed here from the format's specification, the
decoded pixels compared one by one with the closed-form value those bytes stand for (not with another
reader's output); its writers and its exposure against what their docstrings promise."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_bivariate import images
from mi_bivariate.errors import InputError
from mi_bivariate.probes import Probe


def test_a_folder_named_like_an_image_is_not_a_file(tmp_path):
    """A folder given where an image goes (``photo.exr/``) is 'not a file', for a photo, a mask and a probe,
    not an operating-system error about permissions."""
    (tmp_path / "photo.exr").mkdir()
    for read in (images.load_image, lambda p: images.load_mask(p, (4, 4)), Probe.load):
        with pytest.raises(InputError, match=r"photo.exr: not a file \(give the path of an image file, not of a"):
            read(tmp_path / "photo.exr")


# ------------------------------------------------------------ Radiance RGBE

def _rgbe_value(rgbe: np.ndarray) -> np.ndarray:
    """The radiance of RGBE bytes ``(..., 4) uint8``: ``mantissa * 2^(exponent - 136)``, 0 where the
    exponent byte is 0 (Bruce Walter's rgbe.c convention, which Mitsuba's reader follows: no half-code
    offset, unlike Radiance's own colr_color). ``(..., 3) float64``."""
    e = rgbe[..., 3:4].astype(np.int64)
    return np.where(e == 0, 0.0, rgbe[..., :3] * np.ldexp(1.0, e - 136))


def _rle_channel(values: np.ndarray, pieces) -> bytes:
    """One channel of one scanline, run-length encoded as ``pieces``: ``("lit", n)`` n bytes as they are
    (a count byte n <= 128), ``("run", n)`` n copies of one byte (a count byte 128 + n, n <= 127)."""
    out, x = bytearray(), 0
    for kind, n in pieces:
        if kind == "lit":
            out += bytes([n]) + values[x:x + n].tobytes()
        else:
            assert np.all(values[x:x + n] == values[x])
            out += bytes([128 + n, values[x]])
        x += n
    assert x == len(values)
    return bytes(out)


def test_a_hand_written_radiance_file_decodes_to_its_closed_form(tmp_path):
    """A 131 x 2 Radiance file written byte by byte, run-length encoded with the format's extreme counts
    (a literal of 128 bytes, the longest; a run of 127, the longest; short runs and literals), and the
    same pixels written flat: both decode to mantissa * 2^(exponent - 136) exactly, pixel by pixel, and a
    header EXPOSURE=4 divides them by 4. (A reader taking the count byte 128 for a run read the valid
    file as corrupt.) Either file one byte short is refused as truncated."""
    width, height = 131, 2
    rng = np.random.default_rng(0)
    rgbe = np.empty((height, width, 4), np.uint8)
    rgbe[..., :3] = rng.integers(0, 256, (height, width, 3))
    rgbe[..., 3] = rng.integers(120, 140, (height, width))
    rgbe[0, 128:] = rgbe[0, 128]           # row 0: a literal of 128, then a run of 3
    rgbe[1, :127] = rgbe[1, 0]             # row 1: a run of 127, then a literal of 4
    rgbe[0, 7] = 0                         # exponent 0: black
    layout = ([("lit", 128), ("run", 3)], [("run", 127), ("lit", 4)])
    body = bytearray()
    for y in range(height):
        body += bytes([2, 2, width >> 8, width & 0xFF])
        for c in range(4):
            body += _rle_channel(rgbe[y, :, c], layout[y])
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (height, width)
    expected = _rgbe_value(rgbe)

    (tmp_path / "rle.hdr").write_bytes(header + bytes(body))
    (tmp_path / "flat.hdr").write_bytes(header + rgbe.tobytes())
    for name in ("rle.hdr", "flat.hdr"):
        got = images.load_image(tmp_path / name)
        assert got.dtype == np.float32 and got.shape == (height, width, 3)
        np.testing.assert_array_equal(got, expected, err_msg=name)
    assert np.all(expected[0, 7] == 0.0) and np.all(expected[0, :7] > 0.0)

    # One byte short: refused by the structural check, before Mitsuba's reader sees it.
    (tmp_path / "short_rle.hdr").write_bytes(header + bytes(body[:-1]))
    (tmp_path / "short_flat.hdr").write_bytes(header + rgbe.tobytes()[:-1])
    for name, problem in (("short_rle", "truncated at scanline 1"), ("short_flat", "truncated pixel data")):
        with pytest.raises(InputError, match=f"{name}.hdr: cannot be read as an image: corrupt Radiance HDR file, "
                                             f"{problem}"):
            images.load_image(tmp_path / f"{name}.hdr")

    # A last run one pixel longer than the scanline has room for (a reader trusting it writes past the row).
    overlong = bytearray(body)
    at = 4 + 1 + 128                       # row 0, red: marker, the literal's count and bytes, then the run
    assert overlong[at:at + 2] == bytes([128 + 3, rgbe[0, 128, 0]])
    overlong[at] = 128 + 4
    (tmp_path / "overlong.hdr").write_bytes(header + bytes(overlong))
    with pytest.raises(InputError, match="overlong.hdr: .*corrupt Radiance HDR file, bad run length in scanline 0"):
        images.load_image(tmp_path / "overlong.hdr")

    exposed = header.replace(b"FORMAT=", b"EXPOSURE=4\nFORMAT=")
    (tmp_path / "exposed.hdr").write_bytes(exposed + bytes(body))
    np.testing.assert_array_equal(images.load_image(tmp_path / "exposed.hdr"), expected / 4)


def test_the_last_format_line_of_a_radiance_header_decides(tmp_path):
    """Radiance reads header lines in order, a later FORMAT= line overriding an earlier one: RGBE then XYZE
    is XYZ pixels, refused; XYZE then RGBE is RGB pixels, read."""
    pixels = bytes([128, 64, 32, 129]) * 4
    for name, formats, ok in (("xyz_last", (b"rgbe", b"xyze"), False), ("rgb_last", (b"xyze", b"rgbe"), True)):
        header = b"#?RADIANCE\nFORMAT=32-bit_rle_%s\nFORMAT=32-bit_rle_%s\n\n-Y 2 +X 2\n" % formats
        (tmp_path / f"{name}.hdr").write_bytes(header + pixels)
        if ok:
            np.testing.assert_array_equal(images.load_image(tmp_path / f"{name}.hdr"),
                                          np.tile([1.0, 0.5, 0.25], (2, 2, 1)))
        else:
            with pytest.raises(InputError, match=f"{name}.hdr: Radiance HDR pixels are '32-bit_rle_xyze', not RGBE"):
                images.load_image(tmp_path / f"{name}.hdr")


# --------------------------------------------------------------------- PFM

@pytest.mark.parametrize("order", ["<", ">"])
def test_a_hand_written_pfm_decodes_pixel_by_pixel(tmp_path, order):
    """2 x 3 colour (``PF``) and grey (``Pf``) PFMs written with numpy bytes, in both byte orders (the sign of
    the scale: negative little-endian), rows stored bottom to top: read back exactly, the top row first and
    grey expanded to three equal channels."""
    scale = b"-1.0" if order == "<" else b"1.0"
    colour = np.arange(18, dtype=np.float32).reshape(2, 3, 3) * 0.375 + 0.125
    grey = np.array([[0.5, 1.5, 2.5], [3.5, 4.5, 1e-3]], np.float32)
    (tmp_path / "colour.pfm").write_bytes(b"PF\n3 2\n" + scale + b"\n" + colour[::-1].astype(order + "f4").tobytes())
    (tmp_path / "grey.pfm").write_bytes(b"Pf\n3 2\n" + scale + b"\n" + grey[::-1].astype(order + "f4").tobytes())
    np.testing.assert_array_equal(images.load_image(tmp_path / "colour.pfm"), colour)
    np.testing.assert_array_equal(images.load_image(tmp_path / "grey.pfm"), np.repeat(grey[..., None], 3, axis=2))


def test_a_pfm_with_a_huge_negative_value_is_refused_like_a_huge_positive_one(tmp_path):
    """A byte-swapped float is as often hugely negative as hugely positive: one value of -1e35 in a PFM is
    refused by its magnitude (a photo's reader would otherwise pass it on, and capture drop it as one more
    negative pixel, hiding the wrong byte order)."""
    data = np.full((2, 3, 3), 0.5, "<f4")
    data[1, 2, 0] = -1e35
    (tmp_path / "negative.pfm").write_bytes(b"PF\n3 2\n-1.0\n" + data.tobytes())
    problem = r"negative.pfm: PFM values are not radiance \(0 NaN, largest magnitude 1e\+35\)"
    with pytest.raises(InputError, match=problem):
        images.load_image(tmp_path / "negative.pfm")


@pytest.mark.parametrize("width, height", [(3, 0), (0, 2)])
def test_a_pfm_of_no_pixels_is_refused_before_decoding(tmp_path, width, height):
    """A PFM header of zero width or height (its data, none, matches it) is refused as empty before Mitsuba
    decodes it: Mitsuba's PFM reader dies on a zero height (SIGFPE, the whole process)."""
    (tmp_path / "empty.pfm").write_bytes(b"PF\n%d %d\n-1.0\n" % (width, height))
    with pytest.raises(InputError, match=rf"empty.pfm: cannot be read as an image: empty \({width}x{height} pixels\)"):
        images.load_image(tmp_path / "empty.pfm")


# ------------------------------------------------------------------ OpenEXR

def _exr(path: Path, channels: dict, header: dict = None) -> Path:
    """An EXR written by the ``OpenEXR`` package (not by images.write_exr): ``channels`` ``{name: (H, W)}``."""
    import OpenEXR

    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})},
                 {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}).write(str(path))
    return path


def test_a_grey_exr_with_alpha_reads_as_grey_and_masks_by_its_alpha(tmp_path):
    """A Y + A EXR (a grey mask painted on a transparent layer): as an image, Y in all three channels and the
    alpha dropped; as a mask, the pixels where Y > 0 and A > 0 (a reader that took two channels for a bad
    layout refused it)."""
    rng = np.random.default_rng(1)
    y = rng.uniform(0.1, 2.0, (6, 9)).astype(np.float32)
    y[0, :] = 0.0
    alpha = np.zeros((6, 9), np.float32)
    alpha[1:5, 2:7] = 1.0
    path = _exr(tmp_path / "ya.exr", {"Y": y, "A": alpha})
    np.testing.assert_array_equal(images.load_image(path), np.repeat(y[..., None], 3, axis=2))
    np.testing.assert_array_equal(images.load_mask(path, (6, 9)), (y > 0) & (alpha > 0))


def test_an_exr_data_window_at_the_display_windows_corner_is_padded_to_it(tmp_path):
    """A data window that starts where the display window does but is smaller (a render cropped to its
    top-left 3 x 4 pixels in a 8 x 5 frame) is placed in the display window, 0 elsewhere: the image keeps
    the frame's size, so pixel coordinates given as a viewer shows them stay right."""
    pixels = np.random.default_rng(2).uniform(0.1, 1.0, (3, 4)).astype(np.float32)
    path = _exr(tmp_path / "corner.exr", {"R": pixels, "G": 2 * pixels, "B": 3 * pixels},
                {"dataWindow": (np.array([0, 0], np.int32), np.array([3, 2], np.int32)),
                 "displayWindow": (np.array([0, 0], np.int32), np.array([7, 4], np.int32))})
    expected = np.zeros((5, 8, 3), np.float32)
    expected[:3, :4] = pixels[..., None] * [1, 2, 3]
    np.testing.assert_array_equal(images.load_image(path), expected)


# ------------------------------------------------------------------- masks

def test_a_mask_painted_in_one_colour_channel_selects_its_pixels(tmp_path):
    """A mask is usable where any colour channel is > 0: a region painted pure red (G = B = 0) is selected,
    not only pixels lit in all three channels."""
    red = np.zeros((5, 7), np.float32)
    red[1:4, 2:5] = 1.0
    green = np.zeros((5, 7), np.float32)
    green[0, 0] = 0.5
    path = _exr(tmp_path / "red.exr", {"R": red, "G": green, "B": np.zeros((5, 7), np.float32)})
    np.testing.assert_array_equal(images.load_mask(path, (5, 7)), (red > 0) | (green > 0))


# ------------------------------------------------------- exposure and writing

def test_auto_exposure_leaves_black_pixels_out_of_its_percentile():
    """Grey pixels (luminance = value) 1, 2, 3, 4 and four black ones: the median of the positive luminance is
    2.5, so the exposure is 1 / 2.5 (with the black pixels counted the median would be 0.5)."""
    values = np.array([[0.0, 1.0, 0.0, 2.0], [3.0, 0.0, 4.0, 0.0]])
    image = np.repeat(values[..., None], 3, axis=2)
    assert images.auto_exposure(image, percentile=50.0) == pytest.approx(1.0 / 2.5)


@pytest.mark.parametrize("shape", [(4, 5, 4), (4, 5), (4, 5, 1)])
def test_write_exr_refuses_an_image_that_is_not_rgb_and_writes_nothing(tmp_path, shape):
    """write_exr writes (H, W, 3) only: RGBA, grey or flat arrays are an InputError naming the file and
    the shape, and no file (nor temporary) is left."""
    with pytest.raises(InputError, match=r"out.exr: image must have shape \(H, W, 3\), got " + re.escape(str(shape))):
        images.write_exr(tmp_path / "out.exr", np.ones(shape, np.float32))
    assert list(tmp_path.iterdir()) == []


def test_write_png_writes_an_8_bit_image_as_its_codes(tmp_path):
    """A uint8 image is already display codes: write_png stores them unchanged (no exposure, no second sRGB
    curve), as Pillow reads them back."""
    from PIL import Image

    codes = np.random.default_rng(3).integers(0, 256, (4, 6, 3)).astype(np.uint8)
    images.write_png(tmp_path / "codes.png", codes)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "codes.png").convert("RGB")), codes)


def test_write_exr_records_the_command_line_as_a_shell_would_retype_it(tmp_path, monkeypatch):
    """The provenance in an EXR header names the program by its base name and quotes each argument as a
    POSIX shell needs (a file name with a space in one pair of quotes); extra metadata and units come back
    through read_image's metadata, the pixels exactly."""
    monkeypatch.setattr(sys, "argv", ["/usr/local/bin/mi-bivariate", "recover", "my photo.exr", "--out", "o.npz"])
    image = np.random.default_rng(4).uniform(0.0, 2.0, (3, 4, 3)).astype(np.float32)
    images.write_exr(tmp_path / "out.exr", image, units="1/sr", metadata={"probe": "grace_256", "level": 2})
    pixels, meta = images.read_image(tmp_path / "out.exr")
    np.testing.assert_array_equal(pixels, image)
    assert meta["mi_bivariate_command"] == "mi-bivariate recover 'my photo.exr' --out o.npz"
    assert meta["units"] == "1/sr" and meta["probe"] == "grace_256" and meta["level"] == "2"
