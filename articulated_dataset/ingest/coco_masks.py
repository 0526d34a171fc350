"""COCO segmentations as boolean masks: polygons (:func:`polygon_mask`) and run-length
encodings, uncompressed or compressed (:func:`rle_mask`, :func:`decode_rle_string`).

Pure functions; every malformed value is a one-line :class:`UserError` naming ``what``.
Pixel ``(u, v)`` (column, row) has its centre at the integer coordinates ``(u, v)``, as the
intrinsics' (docs/real_data.md, section 1).
"""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.images.intrinsics import read_numbers

#: Polygon vertices may lie this far (px) outside the image's pixel centres: a COCO polygon
#: traced along the image border reaches its outer edge (half a pixel beyond the centres) or,
#: with pixel corners at integers, a whole pixel; farther is a polygon of another image.
POLYGON_MARGIN_PX = 1.0
#: Most polygons one segmentation may hold (an object's part is one or a few outlines).
MAX_POLYGONS = 256
#: Most point-in-polygon tests (pixels tested times the polygon's vertices) of the polygons of
#: one frame, about 3 s of ``contains_points``: an outline of 1,000 vertices around a 640 x 480
#: object takes 3e8; crafted polygons could otherwise cost hours.
MAX_POLYGON_TESTS = 2_000_000_000
#: First character of COCO's compressed counts (``chr(48 + 6-bit group)``) and the groups'
#: continuation and sign bits.
RLE_CHAR_OFFSET = 48
RLE_MORE_BIT = 0x20
RLE_SIGN_BIT = 0x10
RLE_VALUE_BITS = 5
#: Most 5-bit groups of one compressed count (a 64-bit count needs 13).
MAX_RLE_GROUPS = 13


def decode_rle_string(s: str, what: str) -> list[int]:
    """The run lengths of COCO's compressed RLE string ``s`` (pycocotools' ``rleFrString``).

    Each count is written as 5-bit groups, least significant first, one character each
    (``chr(48 + g)``): bit ``0x20`` of ``g`` says another group follows; the last group's bit
    ``0x10`` is the sign (the value is sign-extended).  From the fourth count on (index
    ``i > 2``) a value is stored as the difference to the count two before:
    ``counts[i] = x + counts[i - 2]``.  Negative counts, characters outside ``'0'..'o'``
    and a string ending inside a count are refused.
    """
    counts: list[int] = []
    x = k = 0
    for ch in s:
        g = ord(ch) - RLE_CHAR_OFFSET
        if not 0 <= g < 2 * RLE_MORE_BIT:
            raise UserError(f"{what}: character {ch!r} is not in COCO's compressed RLE alphabet ('0'..'o')")
        x |= (g & (RLE_MORE_BIT - 1)) << (RLE_VALUE_BITS * k)
        k += 1
        if g & RLE_MORE_BIT:
            if k >= MAX_RLE_GROUPS:
                raise UserError(f"{what}: compressed RLE count longer than {MAX_RLE_GROUPS} characters")
            continue
        if g & RLE_SIGN_BIT:
            x -= 1 << (RLE_VALUE_BITS * k)
        if len(counts) > 2:
            x += counts[-2]
        if x < 0:
            raise UserError(f"{what}: compressed RLE count {len(counts)} is negative ({x})")
        counts.append(x)
        x = k = 0
    if k:
        raise UserError(f"{what}: compressed RLE string ends inside a count")
    return counts


def rle_mask(rle: dict, shape: tuple[int, int], what: str) -> np.ndarray:
    """The (H, W) boolean mask of a COCO RLE ``{"size": [H, W], "counts": ...}``.

    ``counts``: a list of run lengths, or a compressed string (:func:`decode_rle_string`);
    runs alternate 0 and 1, starting with 0, over the pixels in column-major order (down the
    first column, then the next).  ``size`` must equal ``shape`` and the runs must cover
    ``H * W`` pixels exactly.
    """
    unknown = set(rle) - {"size", "counts"}
    if unknown or "size" not in rle or "counts" not in rle:
        raise UserError(f"{what}: a COCO RLE has exactly the keys 'size' and 'counts' (got {', '.join(sorted(rle))[:80]})")
    size = read_numbers(rle["size"], f"{what}: 'size'")
    if size.shape != (2,) or tuple(size) != tuple(shape):
        raise UserError(f"{what}: RLE size {rle['size']!r:.40} is not the image's [height, width] {list(shape)}")
    counts_value = rle["counts"]
    if isinstance(counts_value, str):
        counts = np.asarray(decode_rle_string(counts_value, what), dtype=object)
    else:
        c = read_numbers(counts_value, f"{what}: 'counts'")
        if c.ndim != 1 or (c < 0).any() or (c != np.round(c)).any():
            raise UserError(f"{what}: RLE counts must be a list of whole numbers >= 0 (or a compressed string)")
        counts = c
    n = int(shape[0]) * int(shape[1])
    total = sum(int(v) for v in counts)
    if total != n:
        raise UserError(f"{what}: RLE counts cover {total:,} pixels, the {shape[1]}x{shape[0]} image has {n:,}")
    values = np.arange(len(counts)) % 2 == 1
    flat = np.repeat(values, np.asarray(counts, np.int64))
    return flat.reshape(shape, order="F")


def polygon_mask(polygons, shape: tuple[int, int], what: str,
                 max_tests: int = MAX_POLYGON_TESTS) -> tuple[np.ndarray, int]:
    """The (H, W) boolean union of COCO polygons ``[[x0, y0, x1, y1, ...], ...]`` (pixels), and
    the point-in-polygon tests it took: pixel ``(u, v)`` is inside where its centre is
    (``matplotlib.path.Path.contains_points``, tested within each polygon's bounding box).

    A polygon needs at least three vertices, all within :data:`POLYGON_MARGIN_PX` of the
    image's pixel centres; more than ``max_tests`` tests (pixels in the boxes times the
    polygons' vertices) are refused before any is made.
    """
    from matplotlib.path import Path as MplPath

    H, W = shape
    if not isinstance(polygons, list) or not polygons:
        raise UserError(f"{what}: a COCO polygon segmentation is a non-empty list of [x0, y0, x1, y1, ...] lists")
    if len(polygons) > MAX_POLYGONS:
        raise UserError(f"{what}: {len(polygons)} polygons (at most {MAX_POLYGONS})")
    boxes = []
    tests = 0
    for i, poly in enumerate(polygons):
        xy = read_numbers(poly, f"{what}: polygon {i}")
        if xy.ndim != 1 or xy.size < 6 or xy.size % 2:
            raise UserError(f"{what}: polygon {i} must be a flat list of at least 3 x, y pairs")
        if not np.isfinite(xy).all():
            raise UserError(f"{what}: polygon {i} has NaN or infinite coordinates")
        xy = xy.reshape(-1, 2)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        if (lo < -POLYGON_MARGIN_PX).any() or hi[0] > W - 1 + POLYGON_MARGIN_PX or hi[1] > H - 1 + POLYGON_MARGIN_PX:
            raise UserError(f"{what}: polygon {i} reaches ({float(lo[0]):g}, {float(lo[1]):g})-"
                            f"({float(hi[0]):g}, {float(hi[1]):g}) px, outside the {W}x{H} image")
        u0, v0 = max(int(np.ceil(lo[0])), 0), max(int(np.ceil(lo[1])), 0)
        u1, v1 = min(int(np.floor(hi[0])), W - 1), min(int(np.floor(hi[1])), H - 1)
        if u1 >= u0 and v1 >= v0:
            boxes.append((xy, u0, v0, u1, v1))
            tests += (u1 - u0 + 1) * (v1 - v0 + 1) * len(xy)
    if tests > max_tests:
        raise UserError(f"{what}: the polygons take {tests:,} point-in-polygon tests (pixels in their boxes times "
                        f"vertices), more than the {max_tests:,} a frame may take")
    mask = np.zeros((H, W), bool)
    for xy, u0, v0, u1, v1 in boxes:
        uu, vv = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
        inside = MplPath(xy).contains_points(np.stack([uu.ravel(), vv.ravel()], axis=1))
        mask[v0 : v1 + 1, u0 : u1 + 1] |= inside.reshape(uu.shape)
    return mask, tests


def coco_mask(value, shape: tuple[int, int], what: str, max_tests: int = MAX_POLYGON_TESTS) -> tuple[np.ndarray, int]:
    """A COCO segmentation ``value``, polygons (a list) or an RLE (a mapping), as an (H, W)
    boolean mask, and the point-in-polygon tests it took (0 for an RLE; :func:`polygon_mask`,
    :func:`rle_mask`)."""
    if isinstance(value, dict):
        return rle_mask(value, shape, what), 0
    if isinstance(value, list):
        return polygon_mask(value, shape, what, max_tests)
    raise UserError(f"{what}: expected COCO polygons (a list) or an RLE ({{'size', 'counts'}}), got {str(value)[:40]!r}")
