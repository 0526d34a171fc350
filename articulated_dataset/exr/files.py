"""The per-image files of an EXR export: ``<stem>.exr`` depth (float32, channel ``Z``, metres,
ZIP), ``<stem>.mask.png`` (8-bit greyscale) and the JSON values of ``<stem>.json``; the stem
``o<object:06d>_i<image:03d>``."""

from __future__ import annotations

import contextlib
import os
import re
import sys
from pathlib import Path

import numpy as np

from ..errors import DataFormatError


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


def exr_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an EXR file's data window, read from its header alone (no pixel is
    decoded: a hostile header cannot make the caller allocate its size); OpenEXR's own errors
    (RuntimeError, ValueError, OSError, KeyError, TypeError) propagate, its C++ diagnostics silenced."""
    import OpenEXR

    with c_output_silenced(), OpenEXR.File(str(path), header_only=True) as f:
        lo, hi = f.header()["dataWindow"]
    return int(hi[0]) - int(lo[0]) + 1, int(hi[1]) - int(lo[1]) + 1


def read_depth_exr(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read the float32 "Z" channel of an EXR file; anything else is a DataFormatError.

    ``expect_hw``: the (height, width) the image must have, checked from the header before
    any pixel is decoded (a hostile header cannot make us allocate its size)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing depth image")
    try:
        if expect_hw is not None:
            _size_mismatch(path, "depth", *exr_size(path), expect_hw)
        with c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if DEPTH_CHANNEL not in channels:
                raise DataFormatError(f"{path}: no {DEPTH_CHANNEL!r} channel (has {sorted(channels)})")
            pixels = channels[DEPTH_CHANNEL].pixels
    except (RuntimeError, ValueError, OSError, KeyError, TypeError) as exc:
        raise DataFormatError(f"{path}: not a readable OpenEXR file ({str(exc).splitlines()[0][:150]})") from None
    if pixels is None or pixels.dtype != np.float32 or pixels.ndim != 2:
        raise DataFormatError(f"{path}: channel {DEPTH_CHANNEL!r} must be 2-D float32 "
                              f"(got {getattr(pixels, 'dtype', None)}, {getattr(pixels, 'shape', None)})")
    return pixels


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(str(path), format="PNG")


def write_rgb_png(path: str | Path, rgb: np.ndarray) -> None:
    write_mask_png(path, rgb)  # (H, W, 3) uint8 -> an 8-bit RGB PNG


def read_mask_png(path: str | Path, expect_hw: tuple[int, int] | None = None, *, what: str = "mask",
                  mode: str = "L") -> np.ndarray:
    """Read an 8-bit greyscale PNG (``mode="RGB"``: an 8-bit colour PNG, (H, W, 3)); ``expect_hw``
    is checked before the pixels are decoded."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing {what} image")
    try:
        with Image.open(path) as im:
            _size_mismatch(path, what, im.size[0], im.size[1], expect_hw)
            if im.mode != mode:
                kind = "an 8-bit greyscale" if mode == "L" else "an 8-bit RGB"
                raise DataFormatError(f"{path}: {what} must be {kind} PNG, got mode {im.mode}")
            return np.asarray(im, dtype=np.uint8).copy()
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError) as exc:
        raise DataFormatError(f"{path}: not a readable PNG ({str(exc).splitlines()[0][:150]})") from None
