"""The robot's view: the object given by a prompt (a click, a detector's box, a mask or nothing)
instead of a label mask, and the object's pixels segmented from the prompt and the depth.

A :class:`Prompt` says where the object is; :func:`segment_from_prompt` turns it into the
object's pixels (the depth-continuous region a point or a box picks once the scene's large
planes are removed: :mod:`~articulated_dataset.methods.scene_surfaces`; without a prompt, the
largest one of the class's size), and :func:`simulated_prompt`
makes the prompt a click or a detector would give from a split's stored label mask, so whole
splits can be predicted as a robot would see them (``artdata predict --prompt``).  Rules and
limits: docs/robot_view.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format.schema import CONTEXT_MASK_CODES, MASK_BODY

#: The prompt kinds: a pixel on the object, a box around it, its mask, or nothing.
PROMPT_KINDS = ("point", "box", "mask", "none")
#: A simulated box is the object mask's bounding box grown by this fraction of its width
#: (height) on each side, as a detector's box is looser than the object.
BOX_MARGIN_FRACTION = 0.05
#: Neighbouring pixels belong to one surface when their depths differ by less than this (m) ...
FILL_STEP_ABS_M = 0.01
#: ... plus this fraction of their depth (a surface seen at a slant steps further between pixels
#: the further away it is).
FILL_STEP_REL = 0.02
#: An image with a longer side than this (px) is segmented on every n-th pixel of each axis, n
#: the smallest that brings it within (:func:`segment_from_prompt`): 640x480 on every 4th pixel.
SEGMENT_MAX_SIDE_PX = 200
#: Fewest pixels an isolated object's prompt region must hold to be taken whole (fewer, or wider
#: than the class's largest size: the fill from the prompt is used).
MIN_BOX_OBJECT_PX = 20


def _pixel_coords(value, name: str, form: str) -> tuple:
    """``value`` as a tuple of ``len(form.split(","))`` whole pixel coordinates (ints); anything
    else is a one-line :class:`UserError` naming the quantity ``name``."""
    n = len(form.split(","))
    try:
        a = np.asarray(value).ravel()
        ok = a.dtype.kind in "iu" or (a.dtype.kind == "f" and bool(np.all(np.isfinite(a) & (a == np.round(a)))))
    except (TypeError, ValueError):
        ok = False
    if not ok or len(a) != n:
        raise UserError(f"{option(name)} must be {n} whole pixel coordinates {form}, got {value!r}")
    return tuple(int(v) for v in a)


@dataclass(frozen=True)
class Prompt:
    """Where the object is: ``kind`` of :data:`PROMPT_KINDS`; ``point_px`` (u, v) a pixel on it
    (column, row); ``box_px`` (x0, y0, x1, y1) the pixels it covers (inclusive bounds);
    ``mask`` an (H, W) boolean mask of it."""

    kind: str
    point_px: tuple[int, int] | None = None
    box_px: tuple[int, int, int, int] | None = None
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in PROMPT_KINDS:
            raise UserError(f"{option('prompt')} must be one of {', '.join(PROMPT_KINDS)}, got {self.kind!r}")
        given = {"point": self.point_px is not None, "box": self.box_px is not None, "mask": self.mask is not None}
        extra = [k for k, v in given.items() if v and k != self.kind]
        if extra:
            raise UserError(f"a {self.kind} prompt takes no {', '.join(option(k) for k in extra)}")
        if self.kind in given and not given[self.kind]:
            raise UserError(f"a {self.kind} prompt needs {option(self.kind)}")
        if self.point_px is not None:
            object.__setattr__(self, "point_px", _pixel_coords(self.point_px, "point", "U,V"))
        if self.box_px is not None:
            b = _pixel_coords(self.box_px, "box", "X0,Y0,X1,Y1")
            if b[2] < b[0] or b[3] < b[1]:
                raise UserError(f"{option('box')} {','.join(map(str, b))} is inverted (X1 < X0 or Y1 < Y0)")
            object.__setattr__(self, "box_px", b)
        if self.mask is not None:
            m = np.asarray(self.mask)
            if m.ndim != 2:
                raise UserError(f"{option('mask')} must be a 2-D image, got shape {m.shape}")
            object.__setattr__(self, "mask", m.astype(bool))

    def check_image(self, shape: tuple[int, ...]) -> None:
        """One-line errors for a prompt that does not fit an (H, W) image: a point outside it, a box
        with no pixel inside it, a mask of another shape or with no pixel."""
        h, w = int(shape[0]), int(shape[1])
        if self.point_px is not None:
            u, v = self.point_px
            if not (0 <= u < w and 0 <= v < h):
                raise UserError(f"{option('point')} {u},{v} lies outside the {w}x{h} image")
        if self.box_px is not None:
            x0, y0, x1, y1 = self.box_px
            if x1 < 0 or y1 < 0 or x0 >= w or y0 >= h:
                raise UserError(f"{option('box')} {x0},{y0},{x1},{y1} holds no pixel of the {w}x{h} image")
        if self.mask is not None:
            if self.mask.shape != (h, w):
                raise UserError(f"{option('mask')} shape {self.mask.shape} differs from the depth's {(h, w)}")
            if not self.mask.any():
                raise UserError(f"{option('mask')} marks no object pixel")


def object_pixels(label_mask: np.ndarray) -> np.ndarray:
    """The object's pixels of a stored label mask: its body and moving parts (codes from
    :data:`~articulated_dataset.format.schema.MASK_BODY`, not the scene or occluder codes)."""
    m = np.asarray(label_mask)
    return (m >= MASK_BODY) & ~np.isin(m, CONTEXT_MASK_CODES)


def _eroded(mask: np.ndarray) -> np.ndarray:
    """``mask`` eroded by one pixel (3x3 neighbourhood; outside the image counts as not the mask)."""
    p = np.pad(mask, 1, constant_values=False)
    h, w = mask.shape
    out = mask.copy()
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out &= p[dy : dy + h, dx : dx + w]
    return out


def deepest_pixel(mask: np.ndarray) -> tuple[int, int]:
    """The (u, v) pixel of a non-empty boolean mask farthest inside it: the last pixels left by
    repeated 3x3 erosion (the largest chessboard distance to the mask's edge), of those the one
    nearest their centroid (ties: the first in row-major order)."""
    survivors = np.asarray(mask, bool)
    while True:
        nxt = _eroded(survivors)
        if not nxt.any():
            break
        survivors = nxt
    rows, cols = np.nonzero(survivors)
    d2 = (rows - rows.mean()) ** 2 + (cols - cols.mean()) ** 2
    k = int(np.argmin(d2))  # argmin takes the first of equals: row-major order
    return int(cols[k]), int(rows[k])


def grown_box(mask: np.ndarray, margin_fraction: float = BOX_MARGIN_FRACTION) -> tuple[int, int, int, int]:
    """The bounding box (x0, y0, x1, y1, inclusive) of a non-empty boolean mask grown by
    ``margin_fraction`` of its width (height) on each side, rounded to whole pixels and clipped to
    the image."""
    rows, cols = np.nonzero(mask)
    x0, x1, y0, y1 = int(cols.min()), int(cols.max()), int(rows.min()), int(rows.max())
    mx = int(round(margin_fraction * (x1 - x0 + 1)))
    my = int(round(margin_fraction * (y1 - y0 + 1)))
    h, w = mask.shape
    return max(0, x0 - mx), max(0, y0 - my), min(w - 1, x1 + mx), min(h - 1, y1 + my)


def simulated_prompt(kind: str, label_mask: np.ndarray) -> Prompt:
    """The prompt of ``kind`` a click or a detector would give for the object of a stored label
    mask: ``point`` its :func:`deepest_pixel`, ``box`` its :func:`grown_box`, ``mask`` its pixels
    (:func:`object_pixels`), ``none`` no prompt.  An image without object pixels: a
    :class:`UserError` (except for ``none``)."""
    if kind not in PROMPT_KINDS:
        raise UserError(f"{option('prompt')} must be one of {', '.join(PROMPT_KINDS)}, got {kind!r}")
    if kind == "none":
        return Prompt("none")
    obj = object_pixels(label_mask)
    if not obj.any():
        raise UserError(f"a {kind} prompt needs an object pixel in the label mask; it has none")
    if kind == "point":
        return Prompt("point", point_px=deepest_pixel(obj))
    if kind == "box":
        return Prompt("box", box_px=grown_box(obj))
    return Prompt("mask", mask=obj)


def _nearest_valid(valid: np.ndarray, centre_uv: tuple[float, float]) -> tuple[int, int] | None:
    """The (row, col) of the valid pixel nearest ``centre_uv`` (first in row-major order on ties); None without one."""
    rows, cols = np.nonzero(valid)
    if len(rows) == 0:
        return None
    k = int(np.argmin((cols - centre_uv[0]) ** 2 + (rows - centre_uv[1]) ** 2))
    return int(rows[k]), int(cols[k])


def _scene_fill(depth: np.ndarray, points: np.ndarray, valid: np.ndarray, scene: np.ndarray, region: np.ndarray,
                seed: tuple[int, int], focal_px: float, max_extent_m: float) -> np.ndarray:
    """The object's pixels in a scene, from the ``seed`` pixel (row, col) on it: the ``scene``'s planes
    (:func:`~articulated_dataset.methods.scene_surfaces.scene_planes`) are removed unless the seed
    lies on one, the depth-continuous region of the ``region`` pixels left that holds the seed is
    taken, and the regions that meet it in 3-D are added
    (:func:`~articulated_dataset.methods.scene_surfaces.joined_by_proximity`)."""
    from articulated_dataset.methods.scene_surfaces import depth_components, joined_by_proximity

    keep = np.ones_like(scene) if scene[seed] else ~scene
    allowed = valid & region & keep
    labels = depth_components(depth, allowed, FILL_STEP_ABS_M, FILL_STEP_REL)
    return joined_by_proximity(labels == labels[seed], labels, points, focal_px, max_extent_m)


def find_object(depth_m: np.ndarray, K: np.ndarray, *, max_extent_m: float) -> np.ndarray:
    """The object's pixels of an image without a prompt, an (H, W) boolean mask: :func:`segment_from_prompt`
    with no prompt (``Prompt("none")``)."""
    return segment_from_prompt(depth_m, K, Prompt("none"), max_extent_m=max_extent_m)


def _box_iou(region: np.ndarray, box_px: tuple[int, int, int, int]) -> float:
    """Intersection over union of the bounding box of ``region``'s pixels with ``box_px`` (x0, y0,
    x1, y1, inclusive)."""
    rows, cols = np.nonzero(region)
    a = (int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()))

    def area(b):
        return max(0, b[2] - b[0] + 1) * max(0, b[3] - b[1] + 1)

    inter = area((max(a[0], box_px[0]), max(a[1], box_px[1]), min(a[2], box_px[2]), min(a[3], box_px[3])))
    return inter / (area(a) + area(box_px) - inter)


def _object_part(region: np.ndarray, points: np.ndarray, max_extent_m: float) -> np.ndarray | None:
    """``region`` if it could be one object (:func:`_object_sized`); else its largest piece once
    thin strips are cut (:func:`~articulated_dataset.methods.scene_surfaces.without_strips`: a
    counter's front edge flush with the object's front) if that could be; else None."""
    from scipy import ndimage

    from articulated_dataset.methods.scene_surfaces import without_strips

    if _object_sized(region, points, max_extent_m):
        return region
    pieces, n = ndimage.label(without_strips(region), structure=np.ones((3, 3), bool))
    if not n:
        return None
    largest = pieces == 1 + int(np.argmax(np.bincount(pieces.ravel())[1:]))
    return largest if _object_sized(largest, points, max_extent_m) else None


def _found_object(depth: np.ndarray, points: np.ndarray, valid: np.ndarray, scene: np.ndarray,
                  max_extent_m: float, focal_px: float, box_px: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The object's pixels in a scene: of the depth-continuous regions of the ``valid`` pixels left
    once the ``scene``'s planes are removed, those that hold at least :data:`MIN_BOX_OBJECT_PX` and
    span at most ``max_extent_m`` (or whose largest piece without thin strips does:
    :func:`_object_part`); of them the one with most pixels or, with ``box_px``, the one
    whose bounding box overlaps the box most (:func:`_box_iou`: an occluder crossing the box is
    not the object it frames); with the regions within ``max_extent_m`` of it that meet it in 3-D.
    No such region is a one-line :class:`UserError`."""
    from articulated_dataset.methods.scene_surfaces import depth_components, joined_by_proximity

    labels = depth_components(depth, valid & ~scene, FILL_STEP_ABS_M, FILL_STEP_REL)
    ids, sizes = np.unique(labels[labels > 0], return_counts=True)
    candidates = [r for r in (_object_part(labels == k, points, max_extent_m) for k in ids[sizes >= MIN_BOX_OBJECT_PX])
                  if r is not None]
    if not candidates:
        raise UserError(f"found no object of at most {max_extent_m:g} m apart from the scene's planes; prompt it with "
                        f"{option('point')}, {option('box')} or {option('mask')}")
    score = (lambda r: _box_iou(r, box_px)) if box_px is not None else (lambda r: int(r.sum()))
    best = max(candidates, key=score)  # the first of equals: the lowest label
    near = np.linalg.norm(points - points[best].mean(0), axis=-1) <= max_extent_m
    return joined_by_proximity(best, np.where(near, labels, 0), points, focal_px, max_extent_m)


def _segmented_coarsely(depth: np.ndarray, K: np.ndarray, prompt: Prompt, stride: int,
                        max_extent_m: float) -> np.ndarray:
    """:func:`segment_from_prompt` of a large image on every ``stride``-th pixel of each axis (the
    intrinsics and the prompt scaled alike; a click on a pixel with depth whose coarse pixel has
    none moves to the nearest coarse pixel with depth), brought back to the full image: a pixel
    is the object's where one of the four coarse pixels around it is and its depth differs from
    that one's by less than :data:`FILL_STEP_ABS_M` + :data:`FILL_STEP_REL` x depth (the edges
    stay sharp).  The
    model reads the image at 192x108: the mask need not be finer than that."""
    from articulated_dataset.methods.scene_surfaces import depth_step_tolerance_m

    small = depth[::stride, ::stride]
    K_small = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ K
    if prompt.kind == "point":
        assert prompt.point_px is not None
        u, v = prompt.point_px
        if not depth[v, u] > 0:
            raise UserError(f"{option('point')} {u},{v} is a pixel without depth; click on the object")
        at = _nearest_valid(small > 0, (u / stride, v / stride))
        assert at is not None  # the clicked pixel has depth, so some coarse pixel near it does
        coarse = Prompt("point", point_px=(at[1], at[0]))
    elif prompt.kind == "box":
        assert prompt.box_px is not None
        x0, y0, x1, y1 = prompt.box_px
        cx1, cy1 = x1 // stride, y1 // stride  # the coarse pixels inside the box (one at least)
        cx0, cy0 = min(max(-(-x0 // stride), 0), cx1), min(max(-(-y0 // stride), 0), cy1)
        if not (small[cy0 : cy1 + 1, cx0 : cx1 + 1] > 0).any():
            raise UserError(f"{option('box')} {x0},{y0},{x1},{y1} holds no pixel with depth")
        coarse = Prompt("box", box_px=(cx0, cy0, cx1, cy1))
    else:
        coarse = prompt
    mask_small = segment_from_prompt(small, K_small, coarse, max_extent_m=max_extent_m)
    h, w = depth.shape
    full = depth.astype(np.float32)
    padded_m = np.pad(small.astype(np.float32), ((0, 1), (0, 1)), mode="edge")
    padded_mask = np.pad(mask_small, ((0, 1), (0, 1)), mode="edge")

    def up(a):  # each coarse pixel over the stride x stride full pixels it stands for
        return np.repeat(np.repeat(a, stride, axis=0), stride, axis=1)[:h, :w]

    out = np.zeros((h, w), bool)
    for dy in (0, 1):  # the coarse pixels around each pixel: above-left, above-right, below-left, below-right
        for dx in (0, 1):
            near_m = up(padded_m[dy : dy + small.shape[0], dx : dx + small.shape[1]])
            inside = up(padded_mask[dy : dy + small.shape[0], dx : dx + small.shape[1]])
            out |= inside & (np.abs(full - near_m) < depth_step_tolerance_m(full, near_m, FILL_STEP_ABS_M, FILL_STEP_REL))
    return out & (depth > 0)


def segment_from_prompt(depth_m: np.ndarray, K: np.ndarray, prompt: Prompt, *, max_extent_m: float) -> np.ndarray:
    """The object's pixels, an (H, W) boolean mask, from ``prompt`` and the depth itself.

    ``mask``: the prompt's mask.  Otherwise the scene's large planes are found first
    (:func:`~articulated_dataset.methods.scene_surfaces.scene_planes`: planes spanning more than
    the class's largest size ``max_extent_m``).  An image without them shows an isolated object:
    a box keeps every pixel with depth in it, a point every pixel with depth within
    ``max_extent_m`` of the clicked one's 3-D point (with the intrinsics ``K``), if they are at
    least :data:`MIN_BOX_OBJECT_PX` and span at most ``max_extent_m``, and no prompt keeps every
    pixel with depth.  In a scene the planes are removed and the object's region filled
    (:func:`_scene_fill`) over 4-neighbours whose depths differ by less than
    :data:`FILL_STEP_ABS_M` + :data:`FILL_STEP_REL` x depth: for a box the object-sized region
    in it that fills it best (:func:`_found_object`), or else the fill from
    the valid pixel nearest its centre, kept to the box; for a point from the point, kept within ``max_extent_m``
    of it; without a prompt the object is found (:func:`_found_object`) or refused in one line.
    An image with a side longer than :data:`SEGMENT_MAX_SIDE_PX` is segmented on every n-th pixel
    (:func:`_segmented_coarsely`).  A point on a pixel without depth, or a box with none, is a
    :class:`UserError`."""
    depth = np.nan_to_num(np.asarray(depth_m, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    valid = depth > 0
    prompt.check_image(depth.shape)
    if prompt.kind == "mask":
        assert prompt.mask is not None
        return prompt.mask.copy()
    stride = -(-max(depth.shape) // SEGMENT_MAX_SIDE_PX)
    if stride > 1:
        return _segmented_coarsely(depth, np.asarray(K, np.float64), prompt, stride, max_extent_m)
    from articulated_dataset.methods.scene_surfaces import scene_planes

    points = _points(depth, K)
    focal_px = float(np.sqrt(abs(K[0][0] * K[1][1])))
    scene = scene_planes(points, valid, max_extent_m)
    isolated = not scene.any()
    if prompt.kind == "none":
        return valid if isolated else _found_object(depth, points, valid, scene, max_extent_m, focal_px)
    if prompt.kind == "box":
        assert prompt.box_px is not None
        x0, y0, x1, y1 = prompt.box_px
        inside = np.zeros_like(valid)
        inside[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1] = True
        centre = ((x0 + x1) / 2, (y0 + y1) / 2)
        seed = _nearest_valid(inside & valid, centre)
        if seed is None:
            raise UserError(f"{option('box')} {x0},{y0},{x1},{y1} holds no pixel with depth")
        if isolated and _object_sized(inside & valid, points, max_extent_m):
            return inside & valid  # an isolated object: all of the box's pixels with depth
        try:  # the largest object-sized region in the box; else the fill from its centre
            return _found_object(depth, points, valid & inside, scene, max_extent_m, focal_px, prompt.box_px)
        except UserError:
            return _scene_fill(depth, points, valid, scene, inside, seed, focal_px, max_extent_m)
    assert prompt.point_px is not None
    u, v = prompt.point_px
    if not valid[v, u]:
        raise UserError(f"{option('point')} {u},{v} is a pixel without depth; click on the object")
    near = np.linalg.norm(points - points[v, u], axis=-1) <= max_extent_m
    if isolated and _object_sized(valid & near, points, max_extent_m):
        return valid & near  # an isolated object: every pixel with depth within its size of the click
    return _scene_fill(depth, points, valid, scene, near, (v, u), focal_px, max_extent_m)


def _points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) optical-frame points of a depth image with intrinsics ``K``."""
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    hh, ww = depth.shape
    cols, rows = np.meshgrid(np.arange(ww), np.arange(hh))
    rays = np.stack([cols, rows, np.ones_like(cols)], -1) @ Kinv.T  # optical-frame rays, z = 1
    return rays * depth[..., None]


def _object_sized(pixels: np.ndarray, points: np.ndarray, max_extent_m: float) -> bool:
    """Whether ``pixels`` could be one object: at least :data:`MIN_BOX_OBJECT_PX`, spanning at most
    ``max_extent_m`` along each optical axis (pieces of a scene left apart from its surroundings
    span more)."""
    if pixels.sum() < MIN_BOX_OBJECT_PX:
        return False
    span = np.ptp(points[pixels], axis=0)
    return bool(span.max() <= max_extent_m)


def class_extent_m(class_name: str) -> float:
    """The largest size (m) an object of ``class_name`` may have: the largest upper bound of depth,
    width and height in its sampling tables (paper, realistic and varied), the bound a point
    prompt's fill is kept within (:func:`segment_from_prompt`)."""
    from articulated_dataset.classes.registry import get_class

    obj_class = get_class(class_name)
    tables = [t for t in (obj_class.table, obj_class.realistic_table, obj_class.varied_table) if t is not None]
    return max(float(t.geometry[k][1]) for t in tables for k in ("depth_m", "width_m", "height_m"))


def prompted_depth(depth_m: np.ndarray, K: np.ndarray, kind: str, label_mask: np.ndarray, *,
                   max_extent_m: float) -> np.ndarray:
    """A stored image's depth as a robot prompted with ``kind`` would segment it: the depth inside
    :func:`segment_from_prompt` of the :func:`simulated_prompt` of its label mask, no return (0)
    elsewhere.  An image whose object shows no pixel with depth (nothing to click on), or where
    ``none`` finds no object (:func:`find_object`), keeps none."""
    depth = np.asarray(depth_m)
    obj = object_pixels(label_mask) & (np.nan_to_num(depth) > 0)
    if kind != "none" and not obj.any():
        return np.zeros_like(depth)
    prompt = simulated_prompt(kind, obj)
    try:
        keep = segment_from_prompt(depth, K, prompt, max_extent_m=max_extent_m)
    except UserError:
        if kind != "none":
            raise
        return np.zeros_like(depth)  # no object found: the image gets no answer
    return np.where(keep, depth, 0).astype(depth.dtype)
