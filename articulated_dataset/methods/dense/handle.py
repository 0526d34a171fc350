"""Refinement step 7: a closed door's hinge side from its handle.

A closed door looks the same hinged on the left or on the right except for its handle, which
every template puts near the door's *free* edge (``common.xacro``'s ``side_door``: a bar
standing :data:`HANDLE_STANDOFF_M` out of the panel, its centre ``handle_inset_m`` from the free
edge).  The network decides the side from the image, and on the cabinet (the one class hinged
on either side) it sometimes puts the hinge at the handle: a mirrored door, about a door's width
(60-140 cm) and 180 degrees off.  The handle is visible in the depth as door pixels standing a
few centimetres in front of the door's face, so the side is measured instead:

1. the door's face (:func:`door_face`, which refinement step 10 reads too): the door pixels'
   normals (turned to face the camera along their rays) are averaged perpendicular to the axis line, then again over
   those within each of :data:`FACE_INLIER_DEG` of the previous mean, giving the face normal
   ``n``; the face's offset ``c`` is the median of ``n . p`` over the pixels within the last
   angle;
2. the handle: the door pixels with ``n . p - c`` between :data:`HANDLE_MIN_STANDOFF_M` and
   :data:`HANDLE_MAX_STANDOFF_M`; their count, mean point and extent along and across the axis
   (``sqrt(12 var)``, a uniform bar's length); only a bar-sized one (:data:`HANDLE_MAX_LENGTH_M`,
   :data:`HANDLE_MAX_WIDTH_M`) is used;
3. the side (:func:`apply_handle_side`): a vote mode whose ``x`` (from its hinge towards the
   door's centre, refinement step 3) puts the handle nearer its hinge than the door's centre,
   ``(h - o) . x < r`` (``r`` the voted door radius), is on the wrong side.  It is mirrored:
   its origin moves across the door to ``o + 2 r x`` and its frame becomes ``(-x, y, -z)``
   (the same axis line, the door now turning the other way), ``q`` and the part offset unchanged.

Only doors whose estimated angle is below ``handle_max_q_deg`` are checked (an open door shows
its hinge, and the body's edges beside an open door stand in front of the door's plane too)
and only with at least ``handle_min_px`` handle pixels; both are chosen on validation objects
by :func:`~.fit.fit_refinement` (never, where checking does not lower the position error).

The same bar gives the hinge's height (refinement step 9, :func:`apply_handle_height`): ``side_door``
(the doors of the cabinet, two-door cabinet, microwave and refrigerator) centres the handle on the
hinge frame's ``z = 0``, the door's mid-height, which is where a door's axis origin is labelled.  Turning the door about its axis moves the handle round
the axis, never along it, so wherever the handle is seen whole, its mean point's coordinate along
the axis is the origin's, however far the door is open and however much of the door the image
cuts off (the votes must infer a cut door's height).  The handle is measured on every door for
this step, open ones included; a bar seen shorter than :data:`HANDLE_MIN_WHOLE_LENGTH_M` (cut by
the image's border or hidden in part) is not used, nor one whose height is further than a fitted
gate from the vote mode's.  Where the fit chooses it (``Refinement.handle_cut_bars``, refinement
version 8), a bar that the image's top or bottom border cuts is used too: its centre lies half a
bar's length from its other, visible end (:func:`handle_cut_usable`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from articulated_dataset.methods.dense.aggregate import argmax_channels, compact_mask, lower_median, rows_dot
from articulated_dataset.methods.dense.features import MIN_NORMAL_NORM, OUTPUT_STRIDE, POINT_SCALE_M

#: How far a handle bar stands out of its door's face (m): ``handle_standoff_m`` of common.xacro.
HANDLE_STANDOFF_M = 0.03
#: The bar's width across (m) and its length (m): ``handle_bar_m`` and ``handle_len_m`` of common.xacro.
HANDLE_BAR_M = 0.02
HANDLE_LEN_M = 0.12
#: What is taken for a handle must be a bar: seen from the front or obliquely it spans at most its
#: width and its standoff across (m) ...
HANDLE_MAX_WIDTH_M = HANDLE_BAR_M + HANDLE_STANDOFF_M
#: ... and at most this along the axis (m); an open door's neighbouring body edges, or a face
#: taken for the door's, stand in front of the door's plane over far larger areas.
HANDLE_MAX_LENGTH_M = 1.5 * HANDLE_LEN_M
#: Step 9 uses a handle only where its pixels span at least this much along the axis (m): a bar
#: cut by the image's border or partly hidden has its centre elsewhere.  (Every template's bar is
#: ``min(handle_len_m, door_h / 2)`` long, at least 0.11 m for the tables' doors.)
HANDLE_MIN_WHOLE_LENGTH_M = 0.75 * HANDLE_LEN_M
#: A handle with pixels in this many rows at the image's top or bottom is cut by the border:
#: step 9 may then place its centre half a bar's length from its other, visible end.
BORDER_ROWS_PX = 2
#: ... where the bar is seen at least this long (m): a few pixels at the border give no end (the
#: generated splits' bars seen 2 cm long put their centre 10 cm off, a bar's length, in 2 of 32).
HANDLE_MIN_CUT_LENGTH_M = 0.03
#: The door angle limit (deg) under which :func:`handle_candidates_evidence` measures every door
#: (step 9 reads the handles of open doors too).
EVERY_DOOR_DEG = 180.0
#: The keys of :func:`handle_evidence` (and :func:`door_handles`).
HANDLE_KEYS = ("handle_px", "handle_point", "handle_size_m", "handle_cut", "handle_end_centre")
#: Door pixels this far or further in front of the face (m) are taken for the handle ...
HANDLE_MIN_STANDOFF_M = 0.4 * HANDLE_STANDOFF_M
#: ... up to this far (m): nearer the camera than that is not the door's.
HANDLE_MAX_STANDOFF_M = 1.7 * HANDLE_STANDOFF_M
#: The door's face normal is the mean of its normals within these angles (deg) of the previous
#: round's mean (the first round's: the mean of every door pixel's normal) (:func:`door_face`).
FACE_INLIER_DEG = (15.0, 5.0)
#: A face needs at least this many pixels within the last of those angles, among those read.
FACE_MIN_PX = 10
#: :func:`door_face` reads every this-many-th of a door's pixels (in image order; a door's face has
#: hundreds to thousands, and a quarter of them gives the same face to within 0.03 mm on
#: validation objects).
FACE_STRIDE = 4
#: The voted door radius is clipped below at this (m) before a door is mirrored (and, in
#: :mod:`.refine`, before the hinge offset's angle is taken).
MIN_RADIUS_M = 0.05


def _row_mean(values: list, weight: torch.Tensor) -> tuple[list, torch.Tensor]:
    """Weighted means along each row of ``values`` (components, each (D, m)) with ``weight``
    (D, m) -> (the components' means (D,) each, the total weight (D,))."""
    total = weight.sum(-1)
    denominator = total.clamp_min(1e-12)
    return [(v * weight).sum(-1) / denominator for v in values], total


def door_face(normal: list, points: list, real: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 1 (and refinement step 10): each door's face normal (D, 3), unit and perpendicular to its
    unit ``axis`` (D, 3; its sign does not matter), and its face's offset ``median p . n`` (D,) m
    (NaN with fewer than :data:`FACE_MIN_PX` face pixels), from its pixels' normals and points
    (three (D, m) components each) and which of them have a normal (D, m).  Reads every
    :data:`FACE_STRIDE`-th pixel.  The inlier tests compare the unit normals themselves with the
    current direction (perpendicular to the axis), and each round's mean is taken perpendicular to
    the axis.  Each normal is first turned to face the camera (at the origin) along its pixel's
    ray, so the normal returned faces the camera and the offset is negative."""
    k = FACE_STRIDE
    normal, points, real = [v[:, ::k] for v in normal], [v[:, ::k] for v in points], real[:, ::k]
    # each normal turned to face the camera (at the origin) along its pixel's ray: n . p < 0 (the input's
    # normals face it along the optical axis, n_x < 0, which a face seen obliquely near the image's
    # side edges can fail: a door's inner face then reads as its outer face, 2 cm off)
    away = (normal[0] * points[0] + normal[1] * points[1] + normal[2] * points[2]) > 0
    facing = 1.0 - 2.0 * away.to(normal[0].dtype)
    normal = [v * facing for v in normal]

    def perpendicular_mean(w):  # the weighted mean normal, perpendicular to the axis, unit
        mean = torch.stack([(w * nc).sum(-1) for nc in normal], -1)  # (D, 3)
        mean = mean - (mean * axis).sum(-1, keepdim=True) * axis
        return torch.nn.functional.normalize(mean, dim=-1, eps=1e-12)

    inlier = real
    u = perpendicular_mean(real.to(normal[0].dtype))
    for angle_deg in FACE_INLIER_DEG:
        cos = math.cos(math.radians(angle_deg))
        inlier = real & (rows_dot(normal, u) > cos)
        u = perpendicular_mean(inlier.to(normal[0].dtype))
    offset = rows_dot(points, u)
    face_m = lower_median(offset, inlier)
    return u, torch.where(inlier.sum(-1) >= FACE_MIN_PX, face_m, torch.full_like(face_m, float("nan")))


def door_handles(points: list, normals: list, real: torch.Tensor, row: torch.Tensor, axis_line: torch.Tensor,
                 H: int, face: tuple | None = None) -> dict:
    """Steps 1-2 for doors listed row by row: ``points`` and ``normals`` (x, y, z components, each
    (D, m): camera-frame points, m, and input normals) of each door's valid pixels, which of
    them are ``real`` (D, m; the rest padding), their image rows (D, m), each door's axis line
    (D, 3; its sign does not matter) and the image height ``H`` -> :func:`handle_evidence`'s
    keys with one row per door; ``face``: the doors' :func:`door_face` (normal (D, 3), offset (D,))
    where the caller has it (the refinement), else measured here.  Each sum is over a row (no per-image scatter), written
    component by component (no (D, m, 3) stacks and reductions over their last axis)."""
    dtype = points[0].dtype
    nz = torch.nn.functional.normalize(axis_line, dim=-1)  # (D, 3)
    z = [nz[:, c:c + 1] for c in range(3)]
    if face is None:
        with_normal = real & ((normals[0] * normals[0] + normals[1] * normals[1] + normals[2] * normals[2])
                              > MIN_NORMAL_NORM**2)
        face = door_face(normals, points, with_normal, nz)
    n_face, c = face
    n = [n_face[:, k] for k in range(3)]
    pts = points
    s = pts[0] * n[0][:, None] + pts[1] * n[1][:, None] + pts[2] * n[2][:, None]  # along the face normal
    standoff = s - c[:, None]
    handle = real & (standoff > HANDLE_MIN_STANDOFF_M) & (standoff < HANDLE_MAX_STANDOFF_M) & torch.isfinite(c)[:, None]
    # the handle's pixels only from here on (a few dozen of a door's thousands), gathered to the
    # front of each row
    hidx, handle = compact_mask(handle)
    pts = [torch.gather(v, 1, hidx) for v in pts]
    row = torch.gather(row, 1, hidx)
    on = handle.to(dtype)
    point: list | torch.Tensor
    point, px = _row_mean(pts, on)
    rel = [pts[k] - point[k][:, None] for k in range(3)]
    across = torch.cross(nz, torch.stack(n, -1), dim=-1)  # along the face, perpendicular to the axis
    along = rel[0] * z[0] + rel[1] * z[1] + rel[2] * z[2]  # each pixel's height above the bar's mean point
    wide = rows_dot(rel, across)
    spread, _ = _row_mean([along * along, wide * wide], on)
    # a bar cut by the image's top or bottom border (step 9's cut bars): its centre is half a bar's
    # length from its one visible end, the end away from the border
    border = on * ((row < BORDER_ROWS_PX) | (row >= H - BORDER_ROWS_PX)).to(dtype)
    (at_border,), n_border = _row_mean([along], border)
    low = torch.where(handle, along, math.inf).amin(-1)
    high = torch.where(handle, along, -math.inf).amax(-1)
    border_at_high = (at_border - low).abs() > (at_border - high).abs()
    centre = torch.where(border_at_high, low + 0.5 * HANDLE_LEN_M, high - 0.5 * HANDLE_LEN_M)
    cut = (n_border > 0) & (px > 0)
    seen = (px > 0).to(dtype)[:, None]
    point = torch.stack(point, -1)
    return {"handle_px": px, "handle_point": point * seen,
            # the handle's extent along the axis and across it (a uniform bar of length l has variance l^2 / 12)
            "handle_size_m": torch.sqrt(12.0 * torch.stack(spread, -1)) * seen, "handle_cut": cut.to(dtype),
            "handle_end_centre": torch.where(cut[:, None], point + centre[:, None] * nz, torch.zeros_like(point))}


@torch.no_grad()
def handle_evidence(parts: dict, inputs: dict, axis_line: torch.Tensor, joint_types, candidates: torch.Tensor) -> dict:
    """Steps 1-2 for a batch: ``handle_px`` (B, J) handle pixels of each door, ``handle_point``
    (B, J, 3) their mean camera-frame point (m) and ``handle_size_m`` (B, J, 2) their extent along
    the axis and across it on the door's face, ``handle_cut`` (B, J: 1 where the image's top or
    bottom border cuts the bar) and ``handle_end_centre`` (B, J, 3: there, the centre half a bar's
    length from its visible end) (all 0 without any, for prismatic joints and where ``candidates``
    (B, J) is False: only those doors are measured; :func:`door_handles`, which
    :func:`~.refine.refined_quantities` also calls on the door pixels it has gathered).

    ``parts``: :meth:`~.model.DenseNet.split` output (its segmentation, upsampled to the input
    by nearest neighbour); ``inputs``: :func:`~.features.make_inputs` output; ``axis_line``
    (B, J, 3): each joint's axis direction (its sign does not matter).
    """
    x = inputs["x"]
    B, C, H, W = x.shape
    J = axis_line.shape[1]
    P = H * W
    revolute = torch.tensor([t == "revolute" for t in joint_types])
    label = argmax_channels(parts["seg"])  # (B, h, w) at the output resolution, upsampled (nearest)
    label = label.repeat_interleave(OUTPUT_STRIDE, 1).repeat_interleave(OUTPUT_STRIDE, 2)[:, :H, :W].flatten(1)
    valid = x[:, 3].flatten(1) > 0
    measured = candidates & revolute[None]  # (B, J)
    door = torch.stack([label == 1 + j for j in range(J)], 1) & valid[:, None] & measured[..., None]  # (B, J, P)
    idx, real = compact_mask(door.flatten(0, 1))  # (B * J, m)
    at = (torch.arange(B).repeat_interleave(J)[:, None] * (C * P) + idx).view(-1)
    flat = x.reshape(-1)  # a view: the input is contiguous
    m = idx.shape[1]
    anchor = inputs["anchor"].repeat_interleave(J, 0)  # (B * J, 3)
    pts = [flat[c * P:].index_select(0, at).view(B * J, m) * POINT_SCALE_M + anchor[:, c:c + 1] for c in range(3)]
    nrm = [flat[(4 + c) * P:].index_select(0, at).view(B * J, m) for c in range(3)]
    out = door_handles(pts, nrm, real, idx // W, axis_line.reshape(B * J, 3), H)
    return {k: v.view(B, J, *v.shape[1:]) for k, v in out.items()}


def handle_candidates(modes: dict, refined: dict, max_q_deg: float) -> torch.Tensor:
    """(B, J) the doors that step 7 may check: those with a vote mode, or a normal-based angle
    (refinement step 5, NaN when unmeasured), below ``max_q_deg`` (every door from
    :data:`EVERY_DOOR_DEG` on).  ``modes``: :func:`~.aggregate.vote_modes` output; ``refined``:
    :func:`~.refine.refined_quantities`'."""
    if max_q_deg >= EVERY_DOOR_DEG:  # every door (the refined angles need not have been computed)
        return torch.ones(refined["axis"].shape[:2], dtype=torch.bool)
    limit = math.radians(max_q_deg)
    measured = refined["q"]
    voted = torch.where(modes["weight"] > 0, modes["q"], torch.full_like(modes["q"], math.inf)).amin(-1)
    return (voted < limit) | (measured < limit) | measured.isnan()


def handle_candidates_evidence(parts: dict, inputs: dict, modes: dict, refined: dict, joint_types,
                               max_q_deg: float) -> dict:
    """:func:`handle_evidence` of the doors that step 7 may check (:func:`handle_candidates`).
    (:func:`~.refine.refined_quantities` with ``handles`` gives the same for every door, from the
    pixels it has gathered.)"""
    return handle_evidence(parts, inputs, refined["axis"][:, :, 0], joint_types, handle_candidates(modes, refined, max_q_deg))


def mirrored_by_handle(m: dict, r: dict, max_q_deg: float, min_px: float, joint_types) -> np.ndarray:
    """Step 3's test: (B, J, M) whether each vote mode of ``m`` (numpy mode arrays after the other
    refinement steps) is on its handle's side, for revolute doors whose mode angle is below
    ``max_q_deg`` and with at least ``min_px`` handle pixels of a bar's size (``r``:
    :func:`handle_evidence`'s keys)."""
    revolute = np.array([t == "revolute" for t in joint_types])
    radius = np.maximum(m["part_offset"][..., 0], MIN_RADIUS_M)  # (B, J, M)
    along = ((r["handle_point"][:, :, None] - m["origin"]) * m["xaxis"]).sum(-1) / np.maximum(
        np.linalg.norm(m["xaxis"], axis=-1), 1e-12)
    bar = _bar_sized(r["handle_size_m"])
    checked = revolute[None, :, None] & (r["handle_px"][..., None] >= min_px) & bar[..., None] & (m["q"] < math.radians(max_q_deg))
    return checked & (along < radius)


def apply_handle_side(m: dict, r: dict, max_q_deg: float | None, min_px: float, joint_types) -> dict:
    """Mode arrays ``m`` with every mode on its handle's side mirrored (step 3 of the module
    docstring); ``m`` itself where ``max_q_deg`` is None or nothing is mirrored."""
    if max_q_deg is None or "handle_px" not in r:
        return m
    wrong = mirrored_by_handle(m, r, max_q_deg, min_px, joint_types)
    if not wrong.any():
        return m
    out = dict(m)
    x = _unit(m["xaxis"])
    radius = np.maximum(m["part_offset"][..., 0], MIN_RADIUS_M)
    out["origin"] = np.where(wrong[..., None], m["origin"] + 2.0 * radius[..., None] * x, m["origin"])
    out["axis"] = np.where(wrong[..., None], -m["axis"], m["axis"])
    out["xaxis"] = np.where(wrong[..., None], -m["xaxis"], m["xaxis"])
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) scaled to unit length (a zero vector stays zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _bar_sized(size_m: np.ndarray) -> np.ndarray:
    """Whether handle regions of ``handle_size_m`` (..., 2) (along, across) fit a bar
    (:data:`HANDLE_MAX_LENGTH_M`, :data:`HANDLE_MAX_WIDTH_M`)."""
    return (size_m[..., 0] < HANDLE_MAX_LENGTH_M) & (size_m[..., 1] < HANDLE_MAX_WIDTH_M)


def handle_seen_whole(handle_px: np.ndarray, size_m: np.ndarray) -> np.ndarray:
    """Whether each door's handle (:func:`handle_evidence`'s ``handle_px`` (B, J) and
    ``handle_size_m`` (B, J, 2)) is a bar seen at least :data:`HANDLE_MIN_WHOLE_LENGTH_M` long:
    the handles step 9 uses."""
    return (handle_px > 0) & (size_m[..., 0] >= HANDLE_MIN_WHOLE_LENGTH_M) & _bar_sized(size_m)


def handle_cut_usable(r: dict) -> np.ndarray:
    """Whether each door's handle (:func:`handle_evidence`'s keys) is a bar cut by the image's top
    or bottom border whose visible end is seen at least :data:`HANDLE_MIN_CUT_LENGTH_M` long: its
    centre is then ``handle_end_centre``, half a bar's length from that end."""
    size = r["handle_size_m"]
    return (r["handle_cut"] > 0) & (r["handle_px"] > 0) & (size[..., 0] >= HANDLE_MIN_CUT_LENGTH_M) & _bar_sized(size)


def handle_height_shift(m: dict, r: dict, gate_m: float, joint_types, cut_bars: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Step 9's move (B, J, M) of each vote mode's origin along its unit axis (B, J, M, 3) (m; 0
    where unused), and that axis: the handle's centre's coordinate along the axis minus the
    origin's, for revolute doors whose handle is seen whole (:func:`handle_seen_whole`; its mean
    point) or, with ``cut_bars``, cut by the image's border (:func:`handle_cut_usable`; half a
    bar's length from its visible end, which takes the place of the mean point of a bar seen
    whole but touching the border), where the move is shorter than ``gate_m``.
    ``m``: numpy mode arrays after the other refinement steps; ``r``: :func:`handle_evidence`'s keys."""
    revolute = np.array([t == "revolute" for t in joint_types])
    z = _unit(m["axis"])
    use = handle_seen_whole(r["handle_px"], r["handle_size_m"])
    centre = r["handle_point"]
    if cut_bars:
        cut = handle_cut_usable(r)
        use = use | cut
        centre = np.where(cut[..., None], r["handle_end_centre"], centre)
    shift = ((centre[:, :, None] - m["origin"]) * z).sum(-1)
    use = revolute[None] & use
    return np.where(use[..., None] & (np.abs(shift) < gate_m), shift, 0.0), z


def apply_handle_height(m: dict, r: dict, gate_m: float | None, joint_types, cut_bars: bool = False) -> dict:
    """Mode arrays ``m`` with each origin moved along its axis to its door's handle's height
    (step 9, :func:`handle_height_shift`, with ``cut_bars`` also from bars the image's border
    cuts); ``m`` itself where ``gate_m`` is None, the handles were not measured, or nothing moves."""
    if gate_m is None or "handle_px" not in r:
        return m
    shift, z = handle_height_shift(m, r, gate_m, joint_types, cut_bars)
    if not shift.any():
        return m
    return dict(m, origin=m["origin"] + shift[..., None] * z)
