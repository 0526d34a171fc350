"""Refinement step 7 (models/dense/handle.py): a closed door's hinge side from its handle."""

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.camera import CameraConfig  # noqa: E402
from articulated_dataset.models.dense.features import OUTPUT_STRIDE, make_inputs  # noqa: E402
from articulated_dataset.models.dense.handle import (  # noqa: E402
    HANDLE_STANDOFF_M,
    apply_handle_side,
    handle_evidence,
    mirrored_by_handle,
)
from articulated_dataset.models.dense.refine import Refinement, apply_refinement  # noqa: E402

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
