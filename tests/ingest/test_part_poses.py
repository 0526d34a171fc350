"""Captures annotated with part poses: joint labels from the parts' poses (hand-worked cases),
COCO masks (hand-encoded polygons and run lengths), and ``artdata ingest`` on NAME.parts.json
(the worked example of docs/real_data.md and its hostile variants)."""

from __future__ import annotations

import json
import logging
import math
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split
from articulated_dataset.ingest.coco_masks import coco_mask, decode_rle_string, polygon_mask, rle_mask
from articulated_dataset.ingest.part_annotations import load_part_pose_ground_truth
from articulated_dataset.ingest.part_poses import (
    MIN_REVOLUTE_MOTION_RAD,
    axis_frame_labels,
    joint_from_part_poses,
    rigid_problem,
    rotation_about,
    rotation_vector,
)
from helpers_core import ROOT, assert_one_line_error

EXAMPLE = ROOT / "docs" / "examples" / "part_poses"
#: The worked example's labels: the render it was made from (`artdata generate --class microwave
#: --n 1 --split test --seed 5`, image 6), its part poses and boxes written with 6 and 4 decimals.
EXAMPLE_Q_RAD = 0.6028538
EXAMPLE_AXIS_ORIGIN_M = (1.569295, 0.381169, -0.080719)
EXAMPLE_AXIS_DIRECTION = (0.0, 0.0, -1.0)
EXAMPLE_PART_OFFSET_M = (0.211214, 0.0, 0.0)
EXAMPLE_MASK_PIXELS = {1: 285, 2: 870}
#: Agreement of the example's labels with the render's: its boxes have 4 decimals (0.05 mm).
EXAMPLE_TOL_M = 1e-4

C30, S30 = math.sqrt(3.0) / 2.0, 0.5


def transform(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def rot_z(c: float, s: float) -> np.ndarray:
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# A parent turned 90 deg about z (x -> y, y -> -x) and moved to (1.5, 0.2, -0.3); a door hinged on
# the vertical line through (0.2, 0.3, 0) of the parent's frame, its box centred at (0.2, 0, 0.25).
T_PARENT = transform(rot_z(0.0, 1.0), (1.5, 0.2, -0.3))
HINGE_ORIGIN, HINGE_Z = np.array([0.2, 0.3, 0.0]), np.array([0.0, 0.0, 1.0])
DOOR_CENTRE, DOOR_SIZE = np.array([0.2, 0.0, 0.25]), np.array([0.02, 0.6, 0.5])


def door_motion(c: float, s: float, slide_m: float = 0.0) -> np.ndarray:
    """Rotation about the hinge line by the angle of cosine c, sine s (and a slide along it)."""
    R = rot_z(c, s)
    return transform(R, HINGE_ORIGIN - R @ HINGE_ORIGIN + slide_m * HINGE_Z)


def test_door_rotated_30_deg_gives_its_axis_and_angle():
    j = joint_from_part_poses(T_PARENT, T_PARENT @ door_motion(C30, S30), "revolute", DOOR_CENTRE, DOOR_SIZE,
                              HINGE_Z, HINGE_ORIGIN)
    # the hinge point at the door centre's height, (0.2, 0.3, 0.25), turned: (-0.3, 0.2, 0.25) + (1.5, 0.2, -0.3)
    np.testing.assert_allclose(j.origin_m, [1.2, 0.4, -0.05], atol=1e-9)
    np.testing.assert_allclose(j.direction, [0.0, 0.0, 1.0], atol=1e-9)
    assert j.q == pytest.approx(math.radians(30.0), abs=1e-9)
    np.testing.assert_allclose(j.part_centre_m, [1.5, 0.4, -0.05], atol=1e-9)  # (0.2, 0, 0.25) turned and moved
    assert j.from_motion and j.disagreements() == []
    assert j.direction_error_rad == pytest.approx(0.0, abs=1e-9) and j.line_distance_m == pytest.approx(0.0, abs=1e-9)
    assert j.residual_rotation_rad == pytest.approx(0.0, abs=1e-7) and j.residual_translation_m < 1e-9
    pose, offset = axis_frame_labels(j, np.array([0.0, 0.0, 1.0]))
    # x from the hinge to the centre: (0.3, 0, 0) -> the frame is the camera's axes, quaternion (1, 0, 0, 0)
    np.testing.assert_allclose(pose, [1.2, 0.4, -0.05, 1.0, 0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(offset, [0.3, 0.0, 0.0], atol=1e-9)


def test_annotated_axis_pointing_the_other_way_flips_direction_and_q():
    j = joint_from_part_poses(T_PARENT, T_PARENT @ door_motion(C30, S30), "revolute", DOOR_CENTRE, DOOR_SIZE,
                              -HINGE_Z, HINGE_ORIGIN)
    np.testing.assert_allclose(j.direction, [0.0, 0.0, -1.0], atol=1e-9)
    assert j.q == pytest.approx(-math.radians(30.0), abs=1e-9)
    assert j.direction_error_rad == pytest.approx(0.0, abs=1e-9)


def test_closed_door_takes_the_annotated_axis():
    j = joint_from_part_poses(T_PARENT, T_PARENT, "revolute", DOOR_CENTRE, DOOR_SIZE, HINGE_Z, HINGE_ORIGIN)
    assert not j.from_motion and j.q == 0.0
    np.testing.assert_allclose(j.origin_m, [1.2, 0.4, -0.05], atol=1e-12)
    np.testing.assert_allclose(j.direction, [0.0, 0.0, 1.0], atol=1e-12)
    half = 0.5 * MIN_REVOLUTE_MOTION_RAD  # below the threshold: the annotated axis, q the angle about it
    j = joint_from_part_poses(T_PARENT, T_PARENT @ door_motion(math.cos(half), math.sin(half)), "revolute",
                              DOOR_CENTRE, DOOR_SIZE, HINGE_Z, HINGE_ORIGIN)
    assert not j.from_motion and j.q == pytest.approx(half, abs=1e-12)
    assert j.residual_translation_m < 1e-12 and j.disagreements() == []


def test_drawer_translated_20_cm():
    T_p = transform(t=(2.0, 0.0, 0.5))
    out = np.array([-1.0, 0.0, 0.0])  # the drawer opens towards -x
    centre, size = np.array([0.1, 0.0, 0.3]), np.array([0.4, 0.5, 0.2])
    j = joint_from_part_poses(T_p, T_p @ transform(t=0.2 * out), "prismatic", centre, size, out)
    assert j.q == pytest.approx(0.2, abs=1e-12) and j.from_motion
    np.testing.assert_allclose(j.direction, out, atol=1e-12)
    # the closed box's face leading along -x: its centre (0.1, 0, 0.3) - 0.2 x; then moved by (2, 0, 0.5)
    np.testing.assert_allclose(j.origin_m, [1.9, 0.0, 0.8], atol=1e-12)
    assert math.isnan(j.line_distance_m) and j.disagreements() == []
    pose, offset = axis_frame_labels(j, np.array([0.0, 0.0, 1.0]))
    # z = -x, x = up = z_camera, y = z cross x = (0, 1, 0); the centre is 0.2 m behind the face: -0.2 along z
    frame = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    from articulated_dataset.core.rotations import quat_to_matrix

    np.testing.assert_allclose(quat_to_matrix(pose[3:]), frame, atol=1e-12)
    np.testing.assert_allclose(offset, [0.0, 0.0, -0.2], atol=1e-12)
    # the same drawer with its own frame 0.1 m along y of the parent's at rest, its box given in it
    rest = transform(t=(0.0, 0.1, 0.0))
    j2 = joint_from_part_poses(T_p, T_p @ transform(t=0.2 * out) @ rest, "prismatic", centre - (0.0, 0.1, 0.0), size,
                               out, rest_pose=rest)
    assert j2.q == pytest.approx(0.2, abs=1e-12)
    np.testing.assert_allclose(j2.origin_m, [1.9, 0.0, 0.8], atol=1e-12)
    # pulled the other way than annotated: a negative q along the annotated direction
    j3 = joint_from_part_poses(T_p, T_p @ transform(t=-0.2 * out), "prismatic", centre, size, out)
    assert j3.q == pytest.approx(-0.2, abs=1e-12)
    np.testing.assert_allclose(j3.direction, out, atol=1e-12)


def test_motions_built_about_random_axes_are_recovered():
    """Parent poses, rest poses, axes and angles drawn at random: the joint the motion was built
    from comes back (revolute angles up to 3 rad, slides up to 0.5 m)."""
    from articulated_dataset.core.rotations import quat_to_matrix

    rng = np.random.default_rng(7)
    for _ in range(50):
        T_p = transform(quat_to_matrix(rng.normal(size=4)), rng.uniform(-2.0, 2.0, 3))
        rest = transform(quat_to_matrix(rng.normal(size=4)), rng.uniform(-0.3, 0.3, 3))
        a, o, centre = rng.normal(size=3), rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.3, 0.3, 3)
        a /= np.linalg.norm(a)
        angle, slide = rng.uniform(0.05, 3.0), rng.uniform(0.01, 0.5)
        turn = transform(rotation_about(a, angle), o - rotation_about(a, angle) @ o)
        j = joint_from_part_poses(T_p, T_p @ turn @ rest, "revolute", centre, DOOR_SIZE, a, o, rest)
        c = rest[:3, :3] @ centre + rest[:3, 3]
        assert j.q == pytest.approx(angle, abs=1e-9)
        np.testing.assert_allclose(j.direction, T_p[:3, :3] @ a, atol=1e-9)
        np.testing.assert_allclose(j.origin_m, T_p[:3, :3] @ (o + ((c - o) @ a) * a) + T_p[:3, 3], atol=1e-9)
        j = joint_from_part_poses(T_p, T_p @ transform(t=slide * a) @ rest, "prismatic", centre, DOOR_SIZE, a, None, rest)
        assert j.q == pytest.approx(slide, abs=1e-9)
        np.testing.assert_allclose(j.direction, T_p[:3, :3] @ a, atol=1e-9)


def test_cross_check_figures_against_the_annotation():
    moved = T_PARENT @ door_motion(C30, S30)
    tilt = math.radians(10.0)
    j = joint_from_part_poses(T_PARENT, moved, "revolute", DOOR_CENTRE, DOOR_SIZE,
                              np.array([math.sin(tilt), 0.0, math.cos(tilt)]), HINGE_ORIGIN)
    assert j.direction_error_rad == pytest.approx(tilt, abs=1e-9)
    # the tilted line passes through the hinge point at height 0, the origin lies 0.25 m above it
    assert j.line_distance_m == pytest.approx(0.25 * math.sin(tilt), abs=1e-9)
    assert j.disagreements() == ["axis direction 10.00 deg from the annotated one",
                                 "axis 4.34 cm from the annotated axis line"]
    # the annotated hinge 5 cm off along y: the axis at the door is 5 cm from it
    j = joint_from_part_poses(T_PARENT, moved, "revolute", DOOR_CENTRE, DOOR_SIZE, HINGE_Z,
                              HINGE_ORIGIN + (0.0, 0.05, 0.0))
    assert j.line_distance_m == pytest.approx(0.05, abs=1e-9)
    assert ["axis 5.00 cm from the annotated axis line"] == j.disagreements()
    np.testing.assert_allclose(j.origin_m, [1.2, 0.4, -0.05], atol=1e-9)  # from the poses, not the annotation
    # a hinge that also slid 3 cm along its axis (a screw motion): left unexplained
    j = joint_from_part_poses(T_PARENT, T_PARENT @ door_motion(C30, S30, slide_m=0.03), "revolute", DOOR_CENTRE,
                              DOOR_SIZE, HINGE_Z, HINGE_ORIGIN)
    assert j.residual_translation_m == pytest.approx(0.03, abs=1e-9) and j.q == pytest.approx(math.radians(30.0))
    # a slider that also turned 5 deg
    c5, s5 = math.cos(math.radians(5.0)), math.sin(math.radians(5.0))
    j = joint_from_part_poses(np.eye(4), transform(rot_z(c5, s5), (-0.2, 0.0, 0.0)), "prismatic", DOOR_CENTRE,
                              DOOR_SIZE, np.array([-1.0, 0.0, 0.0]))
    assert j.residual_rotation_rad == pytest.approx(math.radians(5.0), abs=1e-9)
    assert j.q == pytest.approx(0.2, abs=1e-12) and j.residual_translation_m == pytest.approx(0.0, abs=1e-12)


def test_rotation_vector_and_rigid_checks():
    u, theta = rotation_vector(rot_z(0.0, 1.0))
    np.testing.assert_allclose(u, [0.0, 0.0, 1.0], atol=1e-12)
    assert theta == pytest.approx(math.pi / 2, abs=1e-12)
    assert rotation_vector(np.eye(3))[1] == 0.0
    assert rigid_problem(T_PARENT) is None
    assert "not orthonormal" in str(rigid_problem(transform(1.1 * np.eye(3))))
    assert "last row" in str(rigid_problem(np.vstack([T_PARENT[:3], [0.0, 0.0, 1.0, 1.0]])))
    assert "reflection" in str(rigid_problem(transform(np.diag([1.0, 1.0, -1.0]))))
    assert "NaN" in str(rigid_problem(np.full((4, 4), np.nan)))
    assert rigid_problem(transform(rot_z(C30 + 5e-4, S30))) is None  # written with 3-4 decimals: within RIGID_TOL


# ------------------------------------------------------------------------------------ COCO masks


def test_compressed_rle_decodes_hand_encoded_strings():
    assert decode_rle_string("123", "t") == [1, 2, 3]
    # the third count (index 2) is stored as it is, the fourth as 5 - 3 = 2
    assert decode_rle_string("2342", "t") == [2, 3, 4, 5]
    # 40 = 0b01000 + (1 << 5): groups 8 | 0x20 ('X') and 1 ('1'); 3 is stored as 3 - 5 = -2:
    # the group 30 = 0b11110 ('N') with its sign bit 0x10 set
    assert decode_rle_string("05X1N", "t") == [0, 5, 40, 3]
    m = rle_mask({"size": [6, 8], "counts": "05X1N"}, (6, 8), "t")
    expected = np.zeros((6, 8), bool)
    expected[0:5, 0] = True  # pixels 0-4 in column-major order: down column 0
    expected[3:6, 7] = True  # pixels 45-47: column 7 (45 = 7 * 6 + 3), rows 3-5
    np.testing.assert_array_equal(m, expected)
    np.testing.assert_array_equal(rle_mask({"size": [6, 8], "counts": [0, 5, 40, 3]}, (6, 8), "t"), expected)


@pytest.mark.parametrize("rle, needle", [
    ({"size": [6, 8], "counts": "05X1"}, "cover 45 pixels"),
    ({"size": [6, 8], "counts": "05X"}, "ends inside a count"),
    ({"size": [6, 8], "counts": "05 1N"}, "alphabet"),
    ({"size": [6, 8], "counts": "0N"}, "negative"),  # the first count -2
    ({"size": [8, 6], "counts": "05X1N"}, "not the image's"),
    ({"size": [6, 8], "counts": [0, 5, 40.5, 2.5]}, "whole numbers"),
    ({"size": [6, 8], "counts": [0, 5, -40, 83]}, "whole numbers >= 0"),
    ({"size": [6, 8]}, "exactly the keys"),
])
def test_malformed_rle_is_one_line_error(rle, needle):
    with pytest.raises(UserError, match=needle):
        rle_mask(rle, (6, 8), "t")


def test_polygons_cover_the_pixel_centres_inside():
    square = [0.5, 0.5, 3.5, 0.5, 3.5, 2.5, 0.5, 2.5]  # centres u = 1..3, v = 1..2
    m, tests = polygon_mask([square], (4, 5), "t")
    expected = np.zeros((4, 5), bool)
    expected[1:3, 1:4] = True
    np.testing.assert_array_equal(m, expected)
    assert tests == 6 * 4  # 3 x 2 pixels in the box, 4 vertices
    # a triangle whose long side is u + v = 3.5: the centres with u + v <= 3 (10 of them), with the square
    triangle = [-0.5, -0.5, 4.0, -0.5, -0.5, 4.0]
    m, _ = coco_mask([square, triangle], (4, 5), "t")
    uu, vv = np.meshgrid(np.arange(5), np.arange(4))
    np.testing.assert_array_equal(m, expected | (uu + vv <= 3))
    assert (uu + vv <= 3).sum() == 10


@pytest.mark.parametrize("polygons, needle", [
    ([[0.5, 0.5, 9.0, 0.5, 3.5, 2.5]], "outside the 5x4 image"),
    ([[0.5, 0.5, 3.5, 0.5]], "at least 3"),
    ([[0.5, 0.5, 3.5, 0.5, "x", 2.5]], "must be numbers"),
    ([], "non-empty list"),
])
def test_malformed_polygons_are_one_line_errors(polygons, needle):
    with pytest.raises(UserError, match=needle):
        polygon_mask(polygons, (4, 5), "t")


def test_polygon_test_budget_is_checked_before_rasterising():
    with pytest.raises(UserError, match="point-in-polygon tests"):
        polygon_mask([[0.5, 0.5, 3.5, 0.5, 3.5, 2.5, 0.5, 2.5]], (4, 5), "t", max_tests=23)


# ------------------------------------------------------------------------------------ ingest


def _ingest(*args):
    return CliRunner().invoke(main, ["ingest", "-q", *map(str, args)])


def test_worked_example_ingests_to_the_rendered_labels(tmp_path):
    res = _ingest(EXAMPLE, "--class", "microwave", "--out", tmp_path)
    assert res.exit_code == 0, res.output
    manifest, [shard] = open_split(tmp_path / "microwave" / "real")
    s = shard.sample(0)
    assert s["q"][0] == pytest.approx(EXAMPLE_Q_RAD, abs=1e-5)
    np.testing.assert_allclose(s["axis_direction"][0], EXAMPLE_AXIS_DIRECTION, atol=1e-6)
    np.testing.assert_allclose(s["axis_origin"][0], EXAMPLE_AXIS_ORIGIN_M, atol=EXAMPLE_TOL_M)
    np.testing.assert_allclose(s["part_offset"][0], EXAMPLE_PART_OFFSET_M, atol=EXAMPLE_TOL_M)
    np.testing.assert_allclose(s["axis_pose"][0, :3], EXAMPLE_AXIS_ORIGIN_M, atol=EXAMPLE_TOL_M)
    assert np.isnan(s["object_pose"]).all() and np.isnan(s["geometry"]).all()
    assert {v: int((s["mask"] == v).sum()) for v in (1, 2)} == EXAMPLE_MASK_PIXELS
    assert manifest["real"]["objects"] == ["microwave-5"]


def _example_copy(tmp_path):
    folder = tmp_path / "caps"
    shutil.copytree(EXAMPLE, folder)
    return folder


def _edit(path, change):
    d = json.loads(path.read_text())
    change(d)
    path.write_text(json.dumps(d))


def _instance(d):
    return d["instances"][0]


def _set(d, keys, value):
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def _objects_of(folder):
    return folder / "objects.json"


def _frame_of(folder):
    return folder / "frame_000.parts.json"


DOOR_POSE = ("instances", 0, "links", "door")


@pytest.mark.parametrize("which, change, needle", [
    ("frame", lambda d: _set(d, DOOR_POSE, (np.diag([1.1, 1.1, 1.1, 1.0]) @ _instance(d)["links"]["door"]).tolist()), "not orthonormal"),
    ("frame", lambda d: _set(d, (*DOOR_POSE, 3), [0, 0, 0.5, 1]), "last row"),
    ("frame", lambda d: _set(d, DOOR_POSE, [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "expected (4, 4)"),
    ("frame", lambda d: _set(d, (*DOOR_POSE, 0, 3), "0.1"), "must be numbers"),
    ("frame", lambda d: _set(d, (*DOOR_POSE, 0, 3), 1e6), "farther than 20 m"),
    ("frame", lambda d: _instance(d)["links"].update(handle=np.eye(4).tolist()), "unknown link 'handle'"),
    ("frame", lambda d: _instance(d)["links"].pop("door"), "no pose of link 'door'"),
    ("frame", lambda d: _instance(d)["masks"].update(knob=[[0.5, 0.5, 3.5, 0.5, 3.5, 2.5]]), "mask of unknown link 'knob'"),
    ("frame", lambda d: _set(d, ("instances", 0, "masks", "door", "size"), [424, 512]), "RLE size"),
    ("frame", lambda d: _set(d, ("instances", 0, "masks", "door"), [[0, 0, 300, 0, 0, 50]]), "outside the 192x108 image"),
    ("frame", lambda d: _set(d, ("instances", 0, "object"), "toaster-1"), "object 'toaster-1' is not in"),
    ("frame", lambda d: _set(d, ("objects_file",), "../objects.json"), "same folder"),
    ("frame", lambda d: _set(d, ("objects_file",), "other.json"), "object metadata file not found"),
    ("frame", lambda d: _set(d, ("frame",), "opengl"), "unknown frame 'opengl'"),
    ("frame", lambda d: _set(d, ("camera",), "kinect"), "unknown key(s) camera"),
    ("frame", lambda d: _set(d, ("instances",), []), "'instances' must be a list"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "type"), "prismatic"),
     "joint 0 of class microwave is revolute"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "type"), "hinge"), "choose from"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "child"), "lid"), "unknown link 'lid'"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "axis", "direction"), [0, 0, 0]),
     "zero length"),
    ("objects", lambda d: d["objects"]["microwave-5"]["links"]["door"].pop("bbox"), "needs a 'bbox'"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "links", "door", "bbox", "size"), [0.03, -0.4, 0.4]),
     "box sizes"),
    ("objects", lambda d: d["objects"]["microwave-5"]["joints"].append(
        {"name": "again", "type": "fixed", "parent": "body", "child": "door"}), "more than one joint"),
    ("objects", lambda d: (d["objects"]["microwave-5"]["links"].update(tray={}, rack={}),
                           d["objects"]["microwave-5"]["joints"].extend(
                               [{"name": "a", "type": "fixed", "parent": "tray", "child": "rack"},
                                {"name": "b", "type": "fixed", "parent": "rack", "child": "tray"}])),
     "not connected to the root link 'body'"),
    ("objects", lambda d: d["objects"]["microwave-5"]["links"].update(tray={}), "found 2 roots"),
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "class"), "drawer"), "0 instances of class microwave"),
    # the annotated axis pointing up: the door opened by -34.5 deg about it, outside [0, 90] deg
    ("objects", lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "axis", "direction"), [0, 0, 1]),
     "outside the class's joint range"),
])
def test_hostile_part_pose_files_are_one_line_errors(tmp_path, which, change, needle):
    folder = _example_copy(tmp_path)
    _edit(_frame_of(folder) if which == "frame" else _objects_of(folder), change)
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"), needle)


def test_nan_and_oversized_files_are_refused(tmp_path):
    folder = _example_copy(tmp_path)
    text = _frame_of(folder).read_text()
    _frame_of(folder).write_text(text.replace("0.302628", "NaN", 1))
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"), "NaN or infinite")
    _frame_of(folder).write_text(text + " " * 4_000_001)
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"), "bytes is not a part-pose file")
    _frame_of(folder).write_text(text)
    _objects_of(folder).unlink()
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"),
                          "object metadata file not found")


@pytest.mark.parametrize("which", ["frame", "objects"])
def test_a_link_leading_out_of_the_folder_is_refused_unread(tmp_path, which):
    """The part-pose file and the object metadata file are read only inside the capture's
    folder: a link to a file elsewhere (a valid copy, so only the link can be the refusal)."""
    folder = _example_copy(tmp_path)
    target = _frame_of(folder) if which == "frame" else _objects_of(folder)
    outside = tmp_path / "elsewhere.json"
    shutil.copy(target, outside)
    target.unlink()
    target.symlink_to(outside)
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"), "leads outside")
    target.unlink()
    shutil.copy(outside, target)
    assert _ingest(folder, "--class", "microwave", "--out", tmp_path / "out").exit_code == 0


def test_labels_and_parts_beside_one_capture_are_refused(tmp_path):
    folder = _example_copy(tmp_path)
    (folder / "frame_000.labels.json").write_text(json.dumps({"q": [0.5]}))
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"),
                          "frame_000.labels.json and frame_000.parts.json", "keep one")
    (folder / "frame_000.labels.json").unlink()
    Image.fromarray(np.full((108, 192), 255, np.uint8)).save(folder / "frame_000.mask.png")
    assert_one_line_error(_ingest(folder, "--class", "microwave", "--out", tmp_path / "out"), "masks in both")
    _edit(_frame_of(folder), lambda d: _instance(d).pop("masks"))  # the mask PNG alone: accepted
    res = _ingest(folder, "--class", "microwave", "--out", tmp_path / "out")
    assert res.exit_code == 0, res.output


def test_polygon_masks_and_camera_frame_poses(tmp_path):
    """The example's poses given in the camera frame and the door's mask as a polygon ingest to the
    same labels, the polygon's pixels labelled 2."""
    from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL

    folder = _example_copy(tmp_path)
    to_camera = np.eye(4)
    to_camera[:3, :3] = R_CAMERA_TO_OPTICAL.T

    def change(d):
        d["frame"] = "camera"
        inst = _instance(d)
        inst["links"] = {k: (to_camera @ np.asarray(v)).tolist() for k, v in inst["links"].items()}
        inst["masks"] = {"door": [[80.5, 40.5, 90.5, 40.5, 90.5, 60.5, 80.5, 60.5]]}

    _edit(_frame_of(folder), change)
    record = load_part_pose_ground_truth(_frame_of(folder), "microwave", (108, 192))
    assert record.labels["q"][0] == pytest.approx(EXAMPLE_Q_RAD, abs=1e-5)
    np.testing.assert_allclose(record.labels["axis_origin"][0], EXAMPLE_AXIS_ORIGIN_M, atol=EXAMPLE_TOL_M)
    assert record.mask is not None and int((record.mask == 2).sum()) == 10 * 20 and int(record.mask.sum()) == 2 * 200


def test_disagreeing_annotation_is_logged_not_refused(tmp_path, caplog):
    folder = _example_copy(tmp_path)
    # the annotated hinge 10 cm off the door's rotation axis (along the object's x)
    _edit(_objects_of(folder), lambda d: _set(d, ("objects", "microwave-5", "joints", 0, "axis", "origin"),
                                              [-0.1772, 0.2813, 0.2219]))
    with caplog.at_level(logging.WARNING, logger="articulated_dataset.ingest.part_annotations"):
        record = load_part_pose_ground_truth(_frame_of(folder), "microwave", (108, 192))
    [joint] = record.joints
    assert joint.line_distance_m == pytest.approx(0.1, abs=1e-3)
    assert "disagrees with its annotation" in caplog.text and "from the annotated axis line" in caplog.text
    np.testing.assert_allclose(record.labels["axis_origin"][0], EXAMPLE_AXIS_ORIGIN_M, atol=EXAMPLE_TOL_M)
