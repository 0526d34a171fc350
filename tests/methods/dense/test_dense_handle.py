"""Refinement steps 7 and 9 (methods/dense/handle.py): a closed door's hinge side, and a door's
hinge height, from its handle."""

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.core.camera import CameraConfig  # noqa: E402
from articulated_dataset.methods.dense.features import OUTPUT_STRIDE, make_inputs  # noqa: E402
from articulated_dataset.methods.dense.handle import (  # noqa: E402
    EVERY_DOOR_DEG,
    HANDLE_LEN_M,
    HANDLE_STANDOFF_M,
    apply_handle_height,
    apply_handle_side,
    handle_cut_usable,
    handle_evidence,
    mirrored_by_handle,
)
from articulated_dataset.methods.dense.refine import Refinement, apply_refinement  # noqa: E402

W_PX, H_PX = 192, 108
DOOR_DEPTH_M = 1.5
#: the door spans these columns and rows; the handle bar is a few columns near its left edge
DOOR_COLS, DOOR_ROWS = (40, 152), (10, 98)
HANDLE_COLS, HANDLE_ROWS = (46, 48), (48, 56)  # about 2.8 x 11 cm at 1.5 m


def _scene(handle: bool = True, handle_cols=HANDLE_COLS):
    """A closed door facing the camera (a plane at 1.5 m) with its handle bar near the image-left
    edge, the parts of a network that labels every pixel door, and the door's hinge lines."""
    depth = torch.zeros(1, H_PX, W_PX)
    depth[0, DOOR_ROWS[0] : DOOR_ROWS[1], DOOR_COLS[0] : DOOR_COLS[1]] = DOOR_DEPTH_M
    if handle:
        depth[0, HANDLE_ROWS[0] : HANDLE_ROWS[1], handle_cols[0] : handle_cols[1]] = DOOR_DEPTH_M - HANDLE_STANDOFF_M
    K = torch.from_numpy(CameraConfig(W_PX, H_PX).K.astype(np.float32))[None]
    inputs = make_inputs(depth, K)
    h, w = -(-H_PX // OUTPUT_STRIDE), -(-W_PX // OUTPUT_STRIDE)
    seg = torch.zeros(1, 2, h, w)
    seg[:, 1] = 1.0  # every output pixel: the door (part 1)
    K_np = K[0].numpy().astype(np.float64)

    def point(col, row):  # the camera-frame point (x forward, y left, z up) of a pixel on the door's plane
        return np.array([DOOR_DEPTH_M, -(col - K_np[0, 2]) / K_np[0, 0] * DOOR_DEPTH_M,
                         -(row - K_np[1, 2]) / K_np[1, 1] * DOOR_DEPTH_M])

    mid_row = 0.5 * (DOOR_ROWS[0] + DOOR_ROWS[1])
    left, right = point(DOOR_COLS[0], mid_row), point(DOOR_COLS[1], mid_row)
    return inputs, {"seg": seg}, left, right, point(np.mean(HANDLE_COLS), np.mean(HANDLE_ROWS))


def _modes(origin, towards):
    """One revolute joint, one closed-door vote mode at ``origin`` whose x points at ``towards``."""
    x = (towards - origin) / np.linalg.norm(towards - origin)
    radius = 0.5 * np.linalg.norm(towards - origin)
    return {"origin": origin[None, None, None], "axis": np.array([0.0, 0.0, 1.0])[None, None, None],
            "xaxis": x[None, None, None], "q": np.zeros((1, 1, 1)), "weight": np.ones((1, 1, 1)),
            "part_offset": np.array([radius, 0.0, 0.0])[None, None, None]}


def test_handle_pixels_are_found_in_front_of_the_face():
    inputs, parts, _, _, handle = _scene()
    ev = handle_evidence(parts, inputs, torch.tensor([[[0.0, 0.0, 1.0]]]), ["revolute"], torch.ones(1, 1, dtype=torch.bool))
    n_bar = (HANDLE_COLS[1] - HANDLE_COLS[0]) * (HANDLE_ROWS[1] - HANDLE_ROWS[0])
    assert ev["handle_px"][0, 0] == pytest.approx(n_bar, abs=2)
    found = ev["handle_point"][0, 0].numpy()
    assert abs(found[1] - handle[1]) < 0.02  # across the door: the bar's column
    assert found[0] == pytest.approx(DOOR_DEPTH_M - HANDLE_STANDOFF_M, abs=0.005)
    length, width = ev["handle_size_m"][0, 0].tolist()
    assert 0.08 < length < 0.14 and 0.01 < width < 0.045


def test_no_handle_no_pixels_and_non_candidates_are_not_measured():
    inputs, parts, *_ = _scene(handle=False)
    z = torch.tensor([[[0.0, 0.0, 1.0]]])
    assert handle_evidence(parts, inputs, z, ["revolute"], torch.ones(1, 1, dtype=torch.bool))["handle_px"][0, 0] == 0
    inputs, parts, *_ = _scene()
    assert handle_evidence(parts, inputs, z, ["revolute"], torch.zeros(1, 1, dtype=torch.bool))["handle_px"][0, 0] == 0
    assert handle_evidence(parts, inputs, z, ["prismatic"], torch.ones(1, 1, dtype=torch.bool))["handle_px"][0, 0] == 0


def test_a_mode_hinged_at_the_handle_is_mirrored_across_the_door():
    inputs, parts, left, right, _ = _scene()  # the handle is near the left edge: the hinge is the right edge
    ev = {k: v.numpy().astype(np.float64) for k, v in
          handle_evidence(parts, inputs, torch.tensor([[[0.0, 0.0, 1.0]]]), ["revolute"], torch.ones(1, 1, dtype=torch.bool)).items()}
    wrong = _modes(left, right)
    assert mirrored_by_handle(wrong, ev, 20.0, 1.0, ["revolute"]).all()
    fixed = apply_handle_side(wrong, ev, 20.0, 1.0, ["revolute"])
    assert np.allclose(fixed["origin"][0, 0, 0], right, atol=1e-9)
    assert np.allclose(fixed["xaxis"][0, 0, 0], -wrong["xaxis"][0, 0, 0])
    assert np.allclose(fixed["axis"][0, 0, 0], [0.0, 0.0, -1.0])
    assert np.array_equal(fixed["q"], wrong["q"])
    right_side = _modes(right, left)
    assert not mirrored_by_handle(right_side, ev, 20.0, 1.0, ["revolute"]).any()
    assert apply_handle_side(right_side, ev, 20.0, 1.0, ["revolute"]) is right_side
    # the gates: an open door (q above the limit), too few handle pixels, or the step not chosen
    opened = dict(wrong, q=np.full((1, 1, 1), math.radians(30.0)))
    assert apply_handle_side(opened, ev, 20.0, 1.0, ["revolute"]) is opened
    assert apply_handle_side(wrong, ev, 20.0, 1e6, ["revolute"]) is wrong
    assert apply_handle_side(wrong, ev, None, 1.0, ["revolute"]) is wrong


def test_a_region_wider_than_a_handle_bar_is_not_taken_for_one():
    inputs, parts, left, right, _ = _scene(handle_cols=(46, 70))  # ~34 cm wide: not a bar
    ev = {k: v.numpy().astype(np.float64) for k, v in
          handle_evidence(parts, inputs, torch.tensor([[[0.0, 0.0, 1.0]]]), ["revolute"], torch.ones(1, 1, dtype=torch.bool)).items()}
    assert ev["handle_px"][0, 0] > 100 and ev["handle_size_m"][0, 0, 1] > 0.2
    assert not mirrored_by_handle(_modes(left, right), ev, 20.0, 1.0, ["revolute"]).any()


def test_refinement_applies_step_7_and_round_trips():
    inputs, parts, left, right, _ = _scene()
    ev = {k: v.numpy().astype(np.float64) for k, v in
          handle_evidence(parts, inputs, torch.tensor([[[0.0, 0.0, 1.0]]]), ["revolute"], torch.ones(1, 1, dtype=torch.bool)).items()}
    ref = Refinement(handle_max_q_deg=15.0, handle_min_px=3.0)
    assert ref.needed and Refinement.from_dict(ref.to_dict()) == ref
    out = apply_refinement(_modes(left, right), ev, ref, ["revolute"])
    assert np.allclose(out["origin"][0, 0, 0], right)
    # a checkpoint written before step 7 (refinement version 3) reads as without it
    old = {k: v for k, v in Refinement(frame=True).to_dict().items() if not k.startswith("handle")}
    assert Refinement.from_dict(old).handle_max_q_deg is None


# step 9: the hinge's height from the handle

def _evidence(inputs, parts):
    return {k: v.numpy().astype(np.float64) for k, v in
            handle_evidence(parts, inputs, torch.tensor([[[0.0, 0.0, 1.0]]]), ["revolute"], torch.ones(1, 1, dtype=torch.bool)).items()}


def test_the_origin_moves_along_the_axis_to_the_handles_height():
    inputs, parts, left, right, handle = _scene()
    ev = _evidence(inputs, parts)
    low = np.array([right[0], right[1], handle[2] - 0.07])  # the votes put the hinge 7 cm below the handle
    modes = _modes(low, left)
    out = apply_handle_height(modes, ev, 0.1, ["revolute"])
    assert out["origin"][0, 0, 0, 2] == pytest.approx(ev["handle_point"][0, 0, 2], abs=1e-9)
    assert out["origin"][0, 0, 0, 2] == pytest.approx(handle[2], abs=0.01)  # the bar's rows
    assert np.allclose(out["origin"][0, 0, 0, :2], low[:2])  # only along the axis
    for key in ("axis", "xaxis", "q", "weight", "part_offset"):
        assert out[key] is modes[key]
    # the refinement applies it (after step 6, before step 7), and reads it back
    ref = Refinement(handle_height_gate_m=0.1)
    assert ref.needed and Refinement.from_dict(ref.to_dict()) == ref and ref.handle_evidence_max_q_deg == EVERY_DOOR_DEG
    assert np.allclose(apply_refinement(modes, ev, ref, ["revolute"])["origin"], out["origin"])
    assert Refinement(handle_max_q_deg=20.0).handle_evidence_max_q_deg == 20.0
    assert Refinement().handle_evidence_max_q_deg is None


def test_the_handles_height_is_not_used_past_its_gates():
    inputs, parts, left, right, handle = _scene()
    ev = _evidence(inputs, parts)
    low = _modes(np.array([right[0], right[1], handle[2] - 0.07]), left)
    assert apply_handle_height(low, ev, 0.1, ["revolute"]) is not low
    assert apply_handle_height(low, ev, 0.05, ["revolute"]) is low  # further than the gate: another handle
    assert apply_handle_height(low, ev, None, ["revolute"]) is low  # the step not chosen
    assert apply_handle_height(low, ev, 0.1, ["prismatic"]) is low  # a drawer's pull is not at its axis
    assert apply_handle_height(low, {}, 0.1, ["revolute"]) is low  # no handle measured
    # a bar cut by the image's top row (its centre is elsewhere) and a region wider than a bar
    for rows, cols in (((0, 5), HANDLE_COLS), (HANDLE_ROWS, (46, 70))):
        ev2 = _evidence(*_scene_with_handle(rows, cols))
        assert ev2["handle_px"][0, 0] > 0
        assert apply_handle_height(low, ev2, 0.4, ["revolute"]) is low, (rows, cols)
    # a checkpoint written before step 9 (refinement version 6) reads as without it
    old = {k: v for k, v in Refinement(frame=True).to_dict().items() if k != "handle_height_gate_m"} | {"version": 6}
    assert Refinement.from_dict(old).handle_height_gate_m is None


def test_a_bar_cut_by_the_images_top_gives_its_centre_from_its_visible_end():
    """Step 9's cut bars: a bar whose pixels reach the image's top row is centred half a bar's
    length above its lowest visible point, and only ``cut_bars`` uses it."""
    inputs, parts = _scene_with_handle((0, 5), HANDLE_COLS)
    ev = _evidence(inputs, parts)
    assert ev["handle_cut"][0, 0] == 1 and handle_cut_usable(ev)[0, 0]
    K = CameraConfig(W_PX, H_PX).K
    bar_bottom_z = -(5 - 1 - K[1, 2]) / K[1, 1] * (DOOR_DEPTH_M - HANDLE_STANDOFF_M)  # the lowest bar row's centre
    assert ev["handle_end_centre"][0, 0, 2] == pytest.approx(bar_bottom_z + 0.5 * HANDLE_LEN_M, abs=1e-4)
    assert ev["handle_end_centre"][0, 0, 1] == pytest.approx(ev["handle_point"][0, 0, 1], abs=1e-9)  # only along the axis
    low = _modes(np.array([0.0, 0.0, bar_bottom_z - 0.1]), np.array([0.0, 1.0, bar_bottom_z - 0.1]))
    out = apply_handle_height(low, ev, 0.4, ["revolute"], cut_bars=True)
    assert out["origin"][0, 0, 0, 2] == pytest.approx(ev["handle_end_centre"][0, 0, 2], abs=1e-9)
    assert apply_handle_height(low, ev, 0.4, ["revolute"]) is low  # not without cut_bars
    ref = Refinement(handle_height_gate_m=0.4, handle_cut_bars=True)
    assert Refinement.from_dict(ref.to_dict()) == ref
    assert np.allclose(apply_refinement(low, ev, ref, ["revolute"])["origin"], out["origin"])
    # refinement version 7 (no handle_cut_bars) reads as without it
    old = {k: v for k, v in ref.to_dict().items() if k != "handle_cut_bars"} | {"version": 7}
    assert not Refinement.from_dict(old).handle_cut_bars
    # a bar inside the image is not cut; a few pixels at the border give no end
    assert _evidence(*_scene_with_handle(HANDLE_ROWS, HANDLE_COLS))["handle_cut"][0, 0] == 0
    assert not handle_cut_usable(_evidence(*_scene_with_handle((0, 1), HANDLE_COLS)))[0, 0]


def _scene_with_handle(rows, cols):
    """:func:`_scene`'s door, taller (from the image's top row), with its handle bar at ``rows`` x
    ``cols``: the network input and parts."""
    _, parts, *_ = _scene(handle=False)
    depth = torch.zeros(1, H_PX, W_PX)
    depth[0, : DOOR_ROWS[1], DOOR_COLS[0] : DOOR_COLS[1]] = DOOR_DEPTH_M
    depth[0, rows[0] : rows[1], cols[0] : cols[1]] = DOOR_DEPTH_M - HANDLE_STANDOFF_M
    K = torch.from_numpy(CameraConfig(W_PX, H_PX).K.astype(np.float32))[None]
    return make_inputs(depth, K), parts


#: Step 9 assumes ``side_door``'s handle is centred at its door's labelled axis origin height; the
#: toaster's door (hinged along its bottom edge, a bar along its top) and the drawer do not.
SIDE_DOOR_CLASSES = ("cabinet", "cabinet2", "microwave", "refrigerator")
#: Agreement (m) of a whole bar's mean point with the origin along the axis (pixels 1-3 cm tall).
HANDLE_HEIGHT_TOL_M = 0.02


@pytest.mark.parametrize("class_name", SIDE_DOOR_CLASSES)
def test_rendered_handles_seen_whole_are_at_the_labelled_origins_height(class_name, tmp_path):
    """Labels against rendered pixels: a generated split's doors, segmented by their true masks,
    whose handle step 9 would use have it (seen whole: its mean point; cut by the image's border:
    half a bar's length from its visible end) at the labelled origin's height along the true axis."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.handle import handle_seen_whole
    from helpers_core import generated_split

    n_joints = get_class(class_name).n_joints
    data = load_dense_split(generated_split(tmp_path, class_name, 4, seed=5), n_joints, (H_PX, W_PX))
    idx = np.arange(len(data.sample_id))
    inputs = make_inputs(data.depth(idx), torch.from_numpy(data.K))
    labels = torch.from_numpy(data.labels_out.astype(np.int64))  # 0 background, 1 body, 2 + j door j
    parts = {"seg": torch.nn.functional.one_hot((labels - 1).clamp_min(0), 1 + n_joints).permute(0, 3, 1, 2).float()}
    axis = torch.from_numpy(data.rot6[..., :3])
    ev = handle_evidence(parts, inputs, axis, ["revolute"] * n_joints, torch.ones(len(idx), n_joints, dtype=torch.bool))
    whole = handle_seen_whole(ev["handle_px"].numpy(), ev["handle_size_m"].numpy())
    assert whole.sum() >= 4, "too few handles seen whole to check"
    along = ((ev["handle_point"].numpy() - data.origin) * data.rot6[..., :3]).sum(-1)
    assert np.abs(along[whole]).max() < HANDLE_HEIGHT_TOL_M, np.round(along[whole], 3)
    # a bar cut by the image's top or bottom border: its centre half a bar's length from its visible end
    ev = {k: v.numpy().astype(np.float64) for k, v in ev.items()}
    cut = handle_cut_usable(ev)
    assert cut.sum() >= 2, "too few bars cut by the border to check"
    along = ((ev["handle_end_centre"] - data.origin) * data.rot6[..., :3]).sum(-1)
    assert np.abs(along[cut]).max() < HANDLE_HEIGHT_TOL_M, np.round(along[cut], 3)
