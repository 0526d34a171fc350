"""Prompts instead of masks (articulated_dataset/methods/prompts.py, docs/robot_view.md): the
simulated click and box of a label mask, the object segmented from a prompt and the depth of a
kitchen render, and the shipped dense model's estimate from a rough mask."""

from __future__ import annotations

import numpy as np
import pytest

from articulated_dataset.classes.registry import all_classes
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split
from articulated_dataset.format.schema import MASK_BODY, MASK_FIRST_PART, MASK_OCCLUDER, MASK_SCENE
from articulated_dataset.format.shards import Shard
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.methods.prompts import (
    BOX_MARGIN_FRACTION,
    Prompt,
    class_extent_m,
    find_object,
    object_pixels,
    segment_from_prompt,
    simulated_prompt,
)

#: Median IoU (over a class's 32 kitchen images) of the object segmented from a simulated prompt
#: with the stored object mask, at least: measured 0.69 to 0.95 (box), 0.45 to 0.87 (point) and
#: 0.34 to 0.87 (none) over the classes, against 0.05 to 0.34 for every pixel with depth; faces
#: flush with a neighbour's (a dishwasher between base units) are where they fail.
MIN_MEDIAN_IOU = {"box": 0.65, "point": 0.4, "none": 0.3}
#: Rough masks' estimates against the true mask's (axis origins, m): per rough mask, the largest
#: and the median over ROUGH_IMAGES of each class allowed.  Measured over the classes: eroded by
#: 2 px at most 0.114 m (medians 0.032-0.054 m); leaking 3 px down onto the counter at most 0.082 m
#: (medians 0.013-0.054 m); dilated by 2 px (onto the wall and counter all round) up to 0.414 m
#: (a drawer; medians 0.039-0.133 m).  Every-valid-pixel estimates (no mask) differ by 0.397 m or
#: more on the first image of each class.
ROUGH_ORIGIN_TOL_M = {"eroded": (0.15, 0.08), "leaking": (0.15, 0.08), "dilated": (None, 0.2)}
#: Classes allowed larger moves under a rough mask (m; largest, median), a known weakness
#: (docs/robot_view.md, "Rough masks"): the lidded box on a counter, whose few pixels a rough mask
#: changes most: leaking 3 px down onto the counter moved one of four estimates by 0.165 m (median
#: 0.019 m); dilated by 2 px all round, by 0.22-0.50 m (median 0.26 m).
ROUGH_CLASS_TOL_M = {("lidded_box", "leaking"): (0.2, 0.08), ("lidded_box", "dilated"): (None, 0.3)}
#: ... and axis directions within this (degrees; measured at most 3.7).
ROUGH_DIRECTION_TOL_DEG = 8.0
#: The no-mask estimate of each class's first image is farther than this from the true mask's (m):
#: beyond every tolerance above, so the check can fail (the oven's: 0.29 m).
NO_MASK_FARTHER_THAN_M = 0.2
#: Images of each class the rough-mask estimates are compared on.
ROUGH_IMAGES = (0, 5, 10, 17)


def _square(mask, y0, y1, x0, x1, code):
    mask[y0:y1, x0:x1] = code


def test_simulated_point_is_deepest_inside_an_l_shape():
    """An L of a 12-px-thick vertical bar and a 6-px-thick foot: the click is inside, in the bar
    (the deepest part), at the largest distance to the edge that any object pixel has."""
    m = np.zeros((40, 40), np.uint8)
    _square(m, 5, 35, 5, 17, MASK_BODY)  # bar, 12 px wide
    _square(m, 29, 35, 17, 35, MASK_FIRST_PART)  # foot, 6 px tall
    p = simulated_prompt("point", m)
    u, v = p.point_px
    assert p.kind == "point" and m[v, u] == MASK_BODY
    # chessboard distance to the nearest non-object pixel, by brute force
    obj = object_pixels(m)
    ys, xs = np.nonzero(~obj)
    depth_in = lambda y, x: np.min(np.maximum(np.abs(ys - y), np.abs(xs - x)))  # noqa: E731
    best = max(depth_in(y, x) for y, x in zip(*np.nonzero(obj)))
    assert depth_in(v, u) == best == 6
    assert 5 + 5 <= u <= 16 - 5  # in the middle columns of the bar


def test_simulated_box_is_grown_five_percent_and_ignores_the_scene():
    m = np.full((60, 100), MASK_SCENE, np.uint8)
    _square(m, 10, 30, 20, 60, MASK_BODY)  # 40 x 20 px object
    _square(m, 0, 60, 80, 100, MASK_OCCLUDER)
    box = simulated_prompt("box", m).box_px
    mx, my = round(BOX_MARGIN_FRACTION * 40), round(BOX_MARGIN_FRACTION * 20)
    assert box == (20 - mx, 10 - my, 59 + mx, 29 + my) == (18, 9, 61, 30)
    _square(m, 0, 5, 0, 100, MASK_BODY)  # object at the top border: clipped to the image
    assert simulated_prompt("box", m).box_px[1] == 0
    assert simulated_prompt("mask", m).mask.sum() == 40 * 20 + 5 * 100
    assert simulated_prompt("none", m) == Prompt("none")


def test_prompt_errors_are_one_line():
    for make, needle in [(lambda: Prompt("click"), "must be one of"),
                         (lambda: Prompt("point"), "needs point"),
                         (lambda: Prompt("point", point_px=(1, 2), box_px=(0, 0, 1, 1)), "takes no box"),
                         (lambda: Prompt("box", box_px=(5, 0, 2, 3)), "inverted"),
                         (lambda: Prompt("point", point_px=(1.5, 2)), "whole pixel coordinates"),
                         (lambda: Prompt("box", box_px=(1, 2, 3)), "4 whole pixel coordinates"),
                         (lambda: simulated_prompt("box", np.full((5, 5), MASK_SCENE, np.uint8)), "none")]:
        with pytest.raises(UserError, match=needle) as info:
            make()
        assert "\n" not in str(info.value)
    depth = np.ones((10, 20))
    for prompt, needle in [(Prompt("point", point_px=(20, 3)), "outside the 20x10 image"),
                           (Prompt("box", box_px=(25, 0, 30, 5)), "holds no pixel")]:
        with pytest.raises(UserError, match=needle):
            segment_from_prompt(depth, np.eye(3), prompt, max_extent_m=1.0)


def test_fill_stops_at_a_depth_step_and_within_the_extent():
    """A box in front of a wall larger than the class: the fill from a point on it keeps the box (a
    0.5 m step), and on a tilted plane (all scene) the point's fill stops at the class's largest
    size while no prompt finds nothing, in one line."""
    depth = np.full((50, 80), 3.0)  # 4 m x 2.5 m at f = 60 px
    depth[10:30, 20:50] = 2.5  # 1.25 m x 0.83 m
    K = np.array([[60.0, 0, 40], [0, 60.0, 25], [0, 0, 1]])
    seg = segment_from_prompt(depth, K, Prompt("point", point_px=(30, 20)), max_extent_m=2.0)
    assert seg.sum() == 20 * 30 and seg[10:30, 20:50].all()
    box = segment_from_prompt(depth, K, Prompt("box", box_px=(0, 0, 79, 49)), max_extent_m=2.0)
    assert box.sum() == 20 * 30  # the one object-sized region in the box
    assert (segment_from_prompt(depth, K, Prompt("none"), max_extent_m=2.0) == box).all()
    floor = 1.0 + 0.01 * np.arange(80)[None].repeat(50, 0)  # steps of 1 cm: one surface
    near = segment_from_prompt(floor, K, Prompt("point", point_px=(0, 25)), max_extent_m=0.3)
    assert 0 < near.sum() < floor.size and near[25, 0] and not near[25, 79]
    with pytest.raises(UserError, match="found no object of at most 0.3 m") as info:
        segment_from_prompt(floor, K, Prompt("none"), max_extent_m=0.3)
    assert "\n" not in str(info.value)


@pytest.fixture(scope="module")
def kitchen(tmp_path_factory):
    """``root/<class>/train``: 2 objects x 16 images of every class in a kitchen, no occluders."""
    root = tmp_path_factory.mktemp("kitchen")
    for c in all_classes():
        generate_split(GenerationConfig(c.name, n_objects=2, objects_per_shard=2, scene="kitchen", occluders=0), root)
    return root


def _images(root, class_name):
    _, shards = open_split(root / class_name / "train")
    sh = Shard(shards[0].path)
    try:
        return sh.read("depth"), sh.read("mask"), np.asarray(sh.K, np.float64)
    finally:
        sh.close()


@pytest.mark.parametrize("class_name", [c.name for c in all_classes()])
def test_prompts_recover_the_object_in_a_kitchen(kitchen, class_name):
    """Every class: the box, point and no prompt's segmentations overlap the stored object mask with
    a median IoU of at least MIN_MEDIAN_IOU, and better than taking every pixel with depth."""
    depth, mask, K = _images(kitchen, class_name)
    extent = class_extent_m(class_name)
    iou: dict = {kind: [] for kind in MIN_MEDIAN_IOU}
    every = []
    for d, m in zip(depth, mask):
        obj = object_pixels(m) & (d > 0)
        assert MASK_SCENE in m  # a scene is in view: segmentation has something to leave out
        for kind in iou:
            try:
                seg = segment_from_prompt(d, K, simulated_prompt(kind, m), max_extent_m=extent)
            except UserError:  # no prompt found no object: no overlap
                assert kind == "none"
                seg = np.zeros_like(obj)
            iou[kind].append((seg & obj).sum() / (seg | obj).sum())
        every.append(obj.sum() / (d > 0).sum())
    for kind, lowest in MIN_MEDIAN_IOU.items():
        assert np.median(iou[kind]) >= lowest, (kind, np.median(iou[kind]))
        assert np.median(iou[kind]) > np.median(every), (kind, np.median(iou[kind]), np.median(every))


def _dilated(m):
    p = np.pad(m, 1)
    h, w = m.shape
    return np.any([p[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], axis=0)


def _eroded(m):
    return ~_dilated(~m) & np.pad(np.ones((m.shape[0] - 2, m.shape[1] - 2), bool), 1)


def rough_masks(label_mask) -> dict:
    """The object mask eroded by 2 px, leaking 3 px down onto the scene below it, and dilated by 2 px."""
    obj = object_pixels(label_mask)
    below = obj.copy()
    for k in (1, 2, 3):
        below[k:] |= obj[:-k]
    return {"eroded": _eroded(_eroded(obj)), "leaking": obj | (below & (label_mask == MASK_SCENE)),
            "dilated": _dilated(_dilated(obj))}


@pytest.mark.slow
def test_a_rough_mask_moves_the_estimate_little(kitchen):
    """The shipped dense model on rough masks: axis origins within ROUGH_ORIGIN_TOL_M of the true
    mask's estimate and directions within ROUGH_DIRECTION_TOL_DEG; the estimate without a mask (every
    pixel with depth, the scene read as the object) is farther than the tolerances, so it can fail."""
    pytest.importorskip("torch")
    import articulated_dataset as ad

    for c in all_classes():
        depth, mask, K = _images(kitchen, c.name)
        moved: dict = {kind: [] for kind in ROUGH_ORIGIN_TOL_M}
        for i in ROUGH_IMAGES:
            obj = object_pixels(mask[i])
            true = ad.estimate(depth[i], K, c.name, mask=obj)
            for kind, rough in rough_masks(mask[i]).items():
                assert (rough != obj).any(), (c.name, i, kind)
                est = ad.estimate(depth[i], K, c.name, mask=rough)
                moved[kind].append(np.linalg.norm(true.axis_origin_m - est.axis_origin_m, axis=1).max())
                cos = np.abs((true.axis_direction * est.axis_direction).sum(1)).clip(0, 1)
                assert np.degrees(np.arccos(cos)).max() <= ROUGH_DIRECTION_TOL_DEG, (c.name, i, kind)
            if i == ROUGH_IMAGES[0]:
                whole = ad.estimate(depth[i], K, c.name, mask=depth[i] > 0)
                assert np.linalg.norm(true.axis_origin_m - whole.axis_origin_m, axis=1).max() > NO_MASK_FARTHER_THAN_M
        for kind, (largest, median) in ROUGH_ORIGIN_TOL_M.items():
            largest, median = ROUGH_CLASS_TOL_M.get((c.name, kind), (largest, median))
            assert largest is None or max(moved[kind]) <= largest, (c.name, kind, moved[kind])
            assert np.median(moved[kind]) <= median, (c.name, kind, moved[kind])


def test_estimate_takes_a_point_or_a_box(kitchen):
    """``ad.estimate`` with a box: the same estimate as with the mask it segments; with a point:
    an estimate; two prompts, a scene without one, a point outside the image or without depth:
    one line each."""
    pytest.importorskip("torch")
    import articulated_dataset as ad

    depth, mask, K = _images(kitchen, "microwave")
    d, m = depth[0], mask[0]
    box = simulated_prompt("box", m)
    seg = segment_from_prompt(d, K, box, max_extent_m=class_extent_m("microwave"))
    a = ad.estimate(d, K, "microwave", box=box.box_px)
    b = ad.estimate(d, K, "microwave", mask=seg)
    np.testing.assert_allclose(a.axis_pose, b.axis_pose)
    point = simulated_prompt("point", m).point_px
    assert ad.estimate(d, K, "microwave", point=point).class_name == "microwave"
    found = find_object(d, K, max_extent_m=class_extent_m("microwave"))  # no prompt: the object found
    np.testing.assert_allclose(ad.estimate(d, K, "microwave").axis_pose,
                               ad.estimate(d, K, "microwave", mask=found).axis_pose)
    for kwargs, needle in [({"point": point, "box": box.box_px}, "give one prompt of the object: point or box"),
                           ({"mask": seg, "point": point}, "mask or point, not both"),
                           ({"point": (d.shape[1], 0)}, "outside")]:
        with pytest.raises(UserError, match=needle):
            ad.estimate(d, K, "microwave", **kwargs)
    hole = d.copy()
    hole[point[1], point[0]] = 0
    with pytest.raises(UserError, match="without depth"):
        ad.estimate(hole, K, "microwave", point=point)
