"""The per-image files of an EXR export: ``<stem>.exr`` depth (float32, channel ``Z``, metres,
ZIP), ``<stem>.mask.png`` (8-bit greyscale) and the JSON values of ``<stem>.json``; the stem
``o<object:06d>_i<image:03d>``."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError

EXPORT_FORMAT = "articulated_dataset-exr"
EXPORT_FORMAT_VERSION = "1.0"
INDEX_NAME = "split.json"
DEPTH_CHANNEL = "Z"
DEPTH_SUFFIX = ".exr"
MASK_SUFFIX = ".mask.png"
#: Colour image of a ``--rgb`` split (8-bit RGB PNG), only where the split stores ``rgb``.
RGB_SUFFIX = ".rgb.png"
LABEL_SUFFIX = ".json"
#: An image stem as :func:`sample_stem` writes it (read back from ``split.json``).
STEM_RE = re.compile(r"o[0-9]{6,}_i[0-9]{3,}")
#: The only image format the package reads (depth and mask captures, an export's masks and
#: colour images).  PIL picks its decoder by a file's content, whatever its name, and some of
#: its decoders hand the file to an external program (EPS to Ghostscript): images are opened
#: with PIL's PNG decoder alone, so a file of any other format is refused.
PNG_FORMATS = ("PNG",)
PNG_SUFFIX = ".png"
#: What PIL raises for a file its PNG decoder cannot read (SyntaxError: a damaged chunk;
#: EOFError, OSError: truncated data; also its DecompressionBombError: a size above its own limit).
PIL_READ_ERRORS = (OSError, ValueError, SyntaxError, EOFError)


def sample_stem(object_index: int, image_index: int) -> str:
    """File stem of one image: ``o<object:06d>_i<image:03d>``."""
    return f"o{int(object_index):06d}_i{int(image_index):03d}"


def json_value(v):
    """numpy -> JSON-able Python values (exact for float32/float64, ints, bytes)."""
    if isinstance(v, np.ndarray):
        if v.dtype.kind == "S":
            return [x.decode("ascii") for x in v.tolist()]
        return v.tolist()
    if isinstance(v, bytes):
        return v.decode("ascii")
    if isinstance(v, np.generic):
        return v.item()
    return v


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------

@contextlib.contextmanager
def c_output_silenced():
    """Point file descriptors 1 and 2 at /dev/null meanwhile: the OpenEXR C++ library prints
    its own diagnostics for damaged files there; we raise one clear error instead."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
        yield
    finally:
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)


def write_depth_exr(path: str | Path, depth_m: np.ndarray, header_extra: dict | None = None) -> None:
    """Write a float32 (H, W) depth image as a single-channel ("Z") ZIP-compressed EXR."""
    import OpenEXR

    depth_m = np.ascontiguousarray(depth_m, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(header_extra or {})
    with OpenEXR.File(header, {DEPTH_CHANNEL: depth_m}) as f:
        f.write(str(path))


def _size_mismatch(path: Path, what: str, width: int, height: int, expect_hw) -> None:
    if expect_hw is not None and (height, width) != tuple(expect_hw):
        raise DataFormatError(f"{path}: {what} is {width}x{height} px, expected {expect_hw[1]}x{expect_hw[0]}")


#: What OpenEXR raises for a file it cannot read.
EXR_READ_ERRORS = (RuntimeError, ValueError, OSError, KeyError, TypeError)

Window = tuple[tuple[int, int], tuple[int, int]]


#: Most channels an EXR depth image may have (depth, or depth beside colour and alpha): OpenEXR
#: decodes them all, so their count bounds the memory one file costs.
MAX_EXR_CHANNELS = 8


def exr_windows(path: str | Path) -> tuple[Window, Window]:
    """``(data window, display window)`` of an EXR file, each ``((x_min, y_min), (x_max, y_max))``
    in pixels (inclusive), read from its header alone (no pixel is decoded: a hostile header
    cannot make the caller allocate its size).  The display window is the image; the data
    window the pixels the file stores, which may be a part of it (a crop) or reach beyond it.
    OpenEXR's own errors (:data:`EXR_READ_ERRORS`) propagate, its C++ diagnostics silenced.

    The header must also describe what a depth reader decodes and nothing more: one part, a
    scanline or tiled image (not deep data), at most :data:`MAX_EXR_CHANNELS` channels.  OpenEXR
    decodes every channel of the file, so a 650 KB file of 40 compressed channels costs 640 MB:
    anything else is a :class:`DataFormatError` before a pixel is decoded."""
    import OpenEXR

    with c_output_silenced(), OpenEXR.File(str(path), header_only=True) as f:
        parts = f.parts
        header = f.header()
        windows = header["dataWindow"], header["displayWindow"]
        storage = parts[0].header.get("type") if parts else None
        n_channels = len(header.get("channels", ()))
    if len(parts) != 1 or storage not in (OpenEXR.scanlineimage, OpenEXR.tiledimage) or n_channels > MAX_EXR_CHANNELS:
        raise DataFormatError(f"{path}: an EXR depth image must be one part of scanlines or tiles with at most "
                              f"{MAX_EXR_CHANNELS} channels (this one: {len(parts)} part(s), {storage}, "
                              f"{n_channels} channels)")
    # (two windows in, two out: mypy types a tuple built from a generator as of any length)
    return tuple(((int(lo[0]), int(lo[1])), (int(hi[0]), int(hi[1]))) for lo, hi in windows)  # type: ignore[return-value]


def window_size(window: Window) -> tuple[int, int]:
    """``(width, height)`` of a window of :func:`exr_windows`."""
    (x0, y0), (x1, y1) = window
    return x1 - x0 + 1, y1 - y0 + 1


def exr_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an EXR file's data window (the pixels it stores), from its header
    alone (:func:`exr_windows`)."""
    return window_size(exr_windows(path)[0])


def in_display_window(pixels: np.ndarray, data: Window, display: Window) -> np.ndarray:
    """A channel's ``pixels`` (its data window's rows and columns) placed in an image of the
    display window's size, as float64: the pixels outside the data window are NaN (the file
    holds nothing there), the data outside the display window is dropped."""
    (dx0, dy0), (dx1, dy1) = data
    (sx0, sy0), (sx1, sy1) = display
    out = np.full((sy1 - sy0 + 1, sx1 - sx0 + 1), np.nan)
    x0, y0, x1, y1 = max(dx0, sx0), max(dy0, sy0), min(dx1, sx1), min(dy1, sy1)
    if x0 <= x1 and y0 <= y1:
        out[y0 - sy0 : y1 - sy0 + 1, x0 - sx0 : x1 - sx0 + 1] = pixels[y0 - dy0 : y1 - dy0 + 1, x0 - dx0 : x1 - dx0 + 1]
    return out


def read_depth_exr(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read the float32 "Z" channel of an EXR file; anything else is a DataFormatError.

    ``expect_hw``: the (height, width) the image must have, checked from the header before
    any pixel is decoded (a hostile header cannot make us allocate its size)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing depth image")
    try:
        data, display = exr_windows(path)
        if expect_hw is not None:
            _size_mismatch(path, "depth", *window_size(data), expect_hw)
        if data != display:  # the export writes whole images: stored pixels placed elsewhere are not one
            raise DataFormatError(f"{path}: its data window {data} differs from its display window {display}; "
                                  f"an exported depth image stores every pixel of the image")
        with c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if DEPTH_CHANNEL not in channels:
                raise DataFormatError(f"{path}: no {DEPTH_CHANNEL!r} channel (has {sorted(channels)})")
            pixels = channels[DEPTH_CHANNEL].pixels
    except EXR_READ_ERRORS as exc:
        raise DataFormatError(f"{path}: not a readable OpenEXR file ({str(exc).splitlines()[0][:150]})") from None
    if pixels is None or pixels.dtype != np.float32 or pixels.ndim != 2:
        raise DataFormatError(f"{path}: channel {DEPTH_CHANNEL!r} must be 2-D float32 "
                              f"(got {getattr(pixels, 'dtype', None)}, {getattr(pixels, 'shape', None)})")
    return pixels


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    """Write an (H, W) mask (values cast to uint8) as an 8-bit greyscale PNG."""
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(str(path), format="PNG")


def write_rgb_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 image as an 8-bit RGB PNG."""
    write_mask_png(path, rgb)  # (H, W, 3) uint8 -> an 8-bit RGB PNG


def read_png(path: str | Path, what: str, check_header, *, error: type[UserError] = UserError) -> tuple[np.ndarray, str]:
    """Pixels and PIL mode of the PNG file ``path`` (a ``.png`` name and PNG content: see
    :data:`PNG_FORMATS`).  ``check_header(path, (width, height), mode)`` runs on the header
    before any pixel is decoded (a few hundred bytes can declare billions of pixels): it
    raises to refuse the image.  A file that is not a readable PNG is ``error`` naming ``what``."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if path.suffix.lower() != PNG_SUFFIX:
        raise error(f"{path}: the {what} must be a PNG file named *{PNG_SUFFIX}")

    def unreadable(exc: Exception) -> UserError:
        return error(f"{path}: not a readable {what} PNG ({(str(exc).splitlines() or [type(exc).__name__])[0][:150]})")

    try:
        with warnings.catch_warnings():  # PIL warns of large sizes; check_header decides
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path, formats=PNG_FORMATS)
    except UnidentifiedImageError:
        raise error(f"{path}: not PNG data (the {what} must be a PNG image; no other image format is read)") from None
    except (*PIL_READ_ERRORS, Image.DecompressionBombError) as exc:
        raise unreadable(exc) from None
    with im:
        check_header(path, im.size, im.mode)
        try:
            return np.array(im), im.mode
        except PIL_READ_ERRORS as exc:
            raise unreadable(exc) from None


def read_mask_png(path: str | Path, expect_hw: tuple[int, int], *, what: str = "mask", mode: str = "L") -> np.ndarray:
    """Read an 8-bit greyscale PNG (``mode="RGB"``: an 8-bit colour PNG, (H, W, 3)) of ``expect_hw``
    = (height, width) pixels; its size and mode are checked before the pixels are decoded."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing {what} image")

    def check(path: Path, size: tuple[int, int], got: str) -> None:
        _size_mismatch(path, what, size[0], size[1], expect_hw)
        if got != mode:
            kind = "an 8-bit greyscale" if mode == "L" else "an 8-bit RGB"
            raise DataFormatError(f"{path}: {what} must be {kind} PNG, got mode {got}")

    return read_png(path, what, check, error=DataFormatError)[0].astype(np.uint8, copy=False)
