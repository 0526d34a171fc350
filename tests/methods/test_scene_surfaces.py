"""The scene's planes and depth-continuous regions (articulated_dataset/methods/scene_surfaces.py,
docs/robot_view.md), on hand-built depth images whose answer is known pixel by pixel."""

from __future__ import annotations

import numpy as np
import pytest

from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.prompts import Prompt, find_object, segment_from_prompt
from articulated_dataset.methods.scene_surfaces import (
    depth_components,
    joined_by_proximity,
    scene_planes,
)

H, W, F = 120, 160, 100.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
WALL_M = 3.0
#: The object's front: rows and columns of the image, and its depth.
FRONT = (slice(40, 80), slice(60, 100))
FRONT_M = 2.0
EXTENT_M = 0.8


def _points(depth):
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    return np.stack([(cols - W / 2) / F, (rows - H / 2) / F, np.ones_like(depth)], -1) * depth[..., None]


def _scene():
    """A frontal wall 3 m away (4.8 m x 3.6 m in view), the floor 1.2 m below the camera from row
    100 (where it meets the wall), and an object's front 2 m away (0.8 m x 0.8 m)."""
    depth = np.full((H, W), WALL_M)
    rows = np.arange(H)[:, None].repeat(W, 1).astype(float)
    floor = rows >= 100
    depth[floor] = 1.2 * F / (rows[floor] - H / 2)  # the points with y = 1.2 m
    depth[FRONT] = FRONT_M
    return depth


def test_components_join_pixels_only_across_small_depth_steps():
    """Two surfaces with a 0.5 m step are two regions; a 1 cm ramp is one; pixels outside
    ``allowed`` are 0."""
    depth = np.full((20, 30), 3.0)
    depth[5:15, 10:20] = 2.5
    allowed = np.ones_like(depth, bool)
    allowed[0] = False
    labels = depth_components(depth, allowed, 0.01, 0.02)
    assert (labels[0] == 0).all() and len(np.unique(labels[1:])) == 2
    assert len(np.unique(labels[5:15, 10:20])) == 1 and labels[5, 10] != labels[1, 0]
    ramp = 1.0 + 0.01 * np.arange(30)[None].repeat(20, 0)
    assert (depth_components(ramp, np.ones_like(ramp, bool), 0.011, 0.0) == 1).all()
    assert len(np.unique(depth_components(ramp, np.ones_like(ramp, bool), 0.009, 0.0))) == 30


def test_the_wall_and_the_floor_are_scene_and_the_object_is_not():
    depth = _scene()
    scene = scene_planes(_points(depth), depth > 0, EXTENT_M)
    assert not scene[FRONT].any()
    assert scene[:40].mean() > 0.99 and scene[100:].mean() > 0.99  # wall above the object, floor
    # a plane no larger than the class is an object's face, not the scene
    assert not scene_planes(_points(depth), depth > 0, 10.0).any()


def test_a_face_flush_with_a_thin_strip_of_the_scene_stays():
    """A counter's 3-pixel front edge runs the image's width flush with the object's front: the
    plane spans more than the class, but the object's face is cut from the strip and kept."""
    depth = _scene()
    depth[80:83] = FRONT_M  # the strip below the object, at its depth
    scene = scene_planes(_points(depth), depth > 0, EXTENT_M)
    assert not scene[FRONT].any()
    assert scene[81, :40].all() and scene[81, 120:].all()


def test_planes_are_drawn_from_the_generator_given():
    depth = _scene()
    a = scene_planes(_points(depth), depth > 0, EXTENT_M, rng=np.random.default_rng(5))
    b = scene_planes(_points(depth), depth > 0, EXTENT_M, rng=np.random.default_rng(5))
    default = scene_planes(_points(depth), depth > 0, EXTENT_M)
    assert (a == b).all() and (scene_planes(_points(depth), depth > 0, EXTENT_M) == default).all()


def test_pieces_join_when_they_meet_in_3d():
    """A door apart from its body in the image (11 columns, 0.22 m, and 5 cm deeper: 0.226 m away)
    joins it when the reach is a quarter of a 1 m class (0.25 m), not within 3 cm + 6 pixel widths
    (0.15 m at 2 m); what stands a metre behind never joins."""
    depth = np.full((H, W), 0.0)
    depth[40:80, 40:70] = 2.0  # body
    depth[40:80, 80:95] = 2.05  # door
    depth[40:80, 120:140] = 3.0  # something else
    labels = depth_components(depth, depth > 0, 0.01, 0.0)
    body = labels == labels[50, 50]
    joined = joined_by_proximity(body, labels, _points(depth), F, max_extent_m=1.0)
    assert joined[50, 85] and not joined[50, 130]
    assert not joined_by_proximity(body, labels, _points(depth), F, max_extent_m=0.0)[50, 85]


def test_no_prompt_finds_the_object_or_refuses_in_one_line():
    depth = _scene()
    found = find_object(depth, K, max_extent_m=EXTENT_M)
    expected = np.zeros_like(found)
    expected[FRONT] = True
    assert (found == expected).all()
    point = segment_from_prompt(depth, K, Prompt("point", point_px=(80, 60)), max_extent_m=EXTENT_M)
    box = segment_from_prompt(depth, K, Prompt("box", box_px=(50, 30, 110, 90)), max_extent_m=EXTENT_M)
    assert (point == expected).all() and (box == expected).all()
    with pytest.raises(UserError, match="found no object of at most 0.5 m") as info:
        find_object(depth, K, max_extent_m=0.5)  # the front is larger than the class
    assert "\n" not in str(info.value)


def test_a_large_image_is_segmented_on_a_coarser_grid_with_sharp_edges():
    """The scene at 4x the size (640x480, f x4): segmented on every 4th pixel (SEGMENT_MAX_SIDE_PX),
    the object found is the front's pixels exactly, and a click or a box gives the same."""
    from articulated_dataset.methods.prompts import SEGMENT_MAX_SIDE_PX

    big = np.repeat(np.repeat(_scene(), 4, axis=0), 4, axis=1)  # each pixel 4x4: the same rays, to a pixel
    K4 = np.array([[4 * F, 0, 4 * W / 2 - 1.5], [0, 4 * F, 4 * H / 2 - 1.5], [0, 0, 1]])
    assert max(big.shape) > SEGMENT_MAX_SIDE_PX
    expected = np.zeros(big.shape, bool)
    expected[4 * FRONT[0].start : 4 * FRONT[0].stop, 4 * FRONT[1].start : 4 * FRONT[1].stop] = True
    assert (find_object(big, K4, max_extent_m=EXTENT_M) == expected).all()
    point = segment_from_prompt(big, K4, Prompt("point", point_px=(321, 241)), max_extent_m=EXTENT_M)
    box = segment_from_prompt(big, K4, Prompt("box", box_px=(200, 120, 440, 360)), max_extent_m=EXTENT_M)
    assert (point == expected).all() and (box == expected).all()
    thin = segment_from_prompt(big, K4, Prompt("box", box_px=(301, 200, 302, 280)), max_extent_m=EXTENT_M)
    assert thin.any() and not (thin & ~expected).any()  # a box narrower than the grid's step still holds a pixel


def test_a_noisy_wall_is_still_one_plane():
    """Depth noise of 2 cm (a stereo sensor's at 2-3 m, beyond the plane's 2.1 cm tolerance at 3 m)
    widens the wall's tolerance to its own spread: nearly all of it is scene, the object is not."""
    depth = _scene()
    depth[:100] += np.random.default_rng(0).normal(0.0, 0.02, (100, W))
    depth[FRONT] = FRONT_M
    scene = scene_planes(_points(depth), depth > 0, EXTENT_M)
    assert scene[:40].mean() > 0.95 and not scene[FRONT].any()
