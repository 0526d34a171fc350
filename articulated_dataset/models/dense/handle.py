"""Refinement step 7: a closed door's hinge side from its handle.

A closed door looks the same hinged on the left or on the right except for its handle, which
every template puts near the door's *free* edge (``common.xacro``'s ``side_door``: a bar
standing :data:`HANDLE_STANDOFF_M` out of the panel, its centre ``handle_inset_m`` from the free
edge).  The network decides the side from the image, and on the cabinet (the one class hinged
on either side) it sometimes puts the hinge at the handle: a mirrored door, about a door's width
(60-140 cm) and 180 degrees off.  The handle is visible in the depth as door pixels standing a
few centimetres in front of the door's face, so the side is measured instead:

1. the door's face (:func:`handle_evidence`): the door pixels' normals, turned towards the
   camera and made perpendicular to the axis line, are averaged (twice: the second time only
   those within :data:`FACE_INLIER_DEG` of the first mean), giving the face normal ``n``; the
   face's offset ``c`` is the mean of ``n . p`` over those pixels, trimmed to within
   :data:`FACE_TRIM_M` of a first mean;
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

from .aggregate import argmax_channels
from .features import MIN_NORMAL_NORM, OUTPUT_STRIDE, POINT_SCALE_M

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
#: Door pixels this far or further in front of the face (m) are taken for the handle ...
HANDLE_MIN_STANDOFF_M = 0.4 * HANDLE_STANDOFF_M
#: ... up to this far (m): nearer the camera than that is not the door's.
HANDLE_MAX_STANDOFF_M = 1.7 * HANDLE_STANDOFF_M
#: The face's normal is the mean of the door normals within this angle (deg) of their first mean.
FACE_INLIER_DEG = 10.0
#: The face's offset is the mean of ``n . p`` within this distance (m) of a first mean.
FACE_TRIM_M = 0.01
#: The voted door radius is clipped below at this (m) before a door is mirrored (and, in
#: :mod:`.refine`, before the hinge offset's angle is taken).
MIN_RADIUS_M = 0.05


def _per_image_mean(values: torch.Tensor, image: torch.Tensor, weight: torch.Tensor, B: int) -> tuple:
    """Weighted sums per image of listed ``values`` (n, C) with ``weight`` (n,) -> (mean (B, C), total (B,)).
    ``image`` (n,) is sorted (the pixels listed image by image), so the sums are over consecutive
    runs (:func:`torch.segment_reduce`: twice as fast as ``index_add_``)."""
    lengths = torch.bincount(image, minlength=B)
    total = torch.segment_reduce(weight, "sum", lengths=lengths)
    sums = torch.segment_reduce(values * weight[:, None], "sum", lengths=lengths, axis=0)
    return sums / total.clamp_min(1e-12)[:, None], total


@torch.no_grad()
def handle_evidence(parts: dict, inputs: dict, axis_line: torch.Tensor, joint_types, candidates: torch.Tensor) -> dict:
    """Steps 1-2 for a batch: ``handle_px`` (B, J) handle pixels of each door, ``handle_point``
    (B, J, 3) their mean camera-frame point (m) and ``handle_size_m`` (B, J, 2) their extent along
    the axis and across it on the door's face (all 0 without any, for prismatic joints and where
    ``candidates`` (B, J) is False: only those doors are measured).

    ``parts``: :meth:`~.model.DenseNet.split` output (its segmentation, upsampled to the input
    by nearest neighbour); ``inputs``: :func:`~.features.make_inputs` output; ``axis_line``
    (B, J, 3): each joint's axis direction (its sign does not matter).
    """
    x = inputs["x"]
    B, C, H, W = x.shape
    J = axis_line.shape[1]
    dtype = x.dtype
    handle_px = torch.zeros(B, J, dtype=dtype)
    handle_point = torch.zeros(B, J, 3, dtype=dtype)
    handle_size = torch.zeros(B, J, 2, dtype=dtype)
    handle_cut = torch.zeros(B, J, dtype=dtype)
    handle_end_centre = torch.zeros(B, J, 3, dtype=dtype)
    seg = parts["seg"]
    flat = x.reshape(-1)  # a view: the input is contiguous
    P = H * W
    cos_inlier = math.cos(math.radians(FACE_INLIER_DEG))
    # written component by component on the listed pixels (no (n, 3) stacks and reductions over
    # their last axis, several times slower), the same arithmetic as the vector formulas
    for j, joint_type in enumerate(joint_types):
        images = candidates[:, j].nonzero()[:, 0]
        if joint_type != "revolute" or len(images) == 0:
            continue
        k = len(images)
        door = argmax_channels(seg[images]) == 1 + j  # (k, h, w) at the output resolution
        door = door.repeat_interleave(OUTPUT_STRIDE, 1).repeat_interleave(OUTPUT_STRIDE, 2)[:, :H, :W]
        b, p = (door & (x[images, 3] > 0)).flatten(1).nonzero(as_tuple=True)  # its valid pixels (nearest upsampling)
        if len(b) == 0:
            continue
        at = images[b] * (C * P) + p
        anchor = inputs["anchor"][images]
        pts = [flat[c * P:].index_select(0, at) * POINT_SCALE_M + anchor[:, c].index_select(0, b) for c in range(3)]
        nrm = [flat[(4 + c) * P:].index_select(0, at) for c in range(3)]
        z_image = torch.nn.functional.normalize(axis_line[images, j], dim=-1)  # (k, 3)
        z = [z_image[:, c].index_select(0, b) for c in range(3)]
        has_normal = (nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]) > MIN_NORMAL_NORM**2
        # the normals towards the camera (at the origin) and perpendicular to the axis line
        sign = torch.where(nrm[0] * pts[0] + nrm[1] * pts[1] + nrm[2] * pts[2] > 0, -1.0, 1.0).to(dtype)
        f = [sign * v for v in nrm]
        fz = f[0] * z[0] + f[1] * z[1] + f[2] * z[2]
        f = [f[c] - fz * z[c] for c in range(3)]
        inv = torch.rsqrt((f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).clamp_min(1e-24))
        facing = torch.stack([v * inv for v in f], -1)  # (n, 3)
        weight = has_normal.to(dtype)
        n, _ = _per_image_mean(facing, b, weight, k)
        n = torch.nn.functional.normalize(n, dim=-1)
        nb = [n[:, c].index_select(0, b) for c in range(3)]
        inlier = weight * ((facing[:, 0] * nb[0] + facing[:, 1] * nb[1] + facing[:, 2] * nb[2]) > cos_inlier).to(dtype)
        n, _ = _per_image_mean(facing, b, inlier, k)
        n = torch.nn.functional.normalize(n, dim=-1)
        s = pts[0] * n[:, 0].index_select(0, b) + pts[1] * n[:, 1].index_select(0, b) + pts[2] * n[:, 2].index_select(0, b)
        c, _ = _per_image_mean(s[:, None], b, inlier, k)  # each pixel's coordinate along the face normal
        trimmed = inlier * ((s - c[:, 0].index_select(0, b)).abs() < FACE_TRIM_M).to(dtype)
        c, count = _per_image_mean(s[:, None], b, trimmed, k)
        standoff = s - c[:, 0].index_select(0, b)
        at_handle = ((standoff > HANDLE_MIN_STANDOFF_M) & (standoff < HANDLE_MAX_STANDOFF_M)
                     & (count.index_select(0, b) > 0)).nonzero()[:, 0]
        hb = b.index_select(0, at_handle)  # the handle's pixels only from here on
        hp = torch.stack([v.index_select(0, at_handle) for v in pts], -1)
        ones = torch.ones(len(hb), dtype=dtype)
        point, px = _per_image_mean(hp, hb, ones, k)
        rel = hp - point.index_select(0, hb)
        across = torch.cross(z_image, n, dim=-1).index_select(0, hb)  # along the face, perpendicular to the axis
        along = (rel * z_image.index_select(0, hb)).sum(-1)  # each handle pixel's height above the bar's mean point
        spread, _ = _per_image_mean(torch.stack([along ** 2, (rel * across).sum(-1) ** 2], -1), hb, ones, k)
        # a bar cut by the image's top or bottom border (step 9's cut bars): its centre is half
        # a bar's length from its one visible end, the end away from the border
        row = p.index_select(0, at_handle) // W
        border = ((row < BORDER_ROWS_PX) | (row >= H - BORDER_ROWS_PX)).to(dtype)
        at_border, n_border = _per_image_mean(along[:, None], hb, border, k)
        low = torch.full((k,), math.inf, dtype=dtype).scatter_reduce(0, hb, along, "amin")
        high = torch.full((k,), -math.inf, dtype=dtype).scatter_reduce(0, hb, along, "amax")
        border_at_high = (at_border[:, 0] - low).abs() > (at_border[:, 0] - high).abs()
        centre = torch.where(border_at_high, low + 0.5 * HANDLE_LEN_M, high - 0.5 * HANDLE_LEN_M)
        cut = (n_border > 0) & (px > 0)
        handle_cut[images, j] = cut.to(dtype)
        handle_end_centre[images, j] = torch.where(cut[:, None], point + centre[:, None] * z_image, torch.zeros_like(point))
        handle_px[images, j] = px
        handle_point[images, j] = point * (px > 0).to(dtype)[:, None]
        # the handle's extent along the axis and across it (a uniform bar of length l has variance l^2 / 12)
        handle_size[images, j] = torch.sqrt(12.0 * spread) * (px > 0).to(dtype)[:, None]
    return {"handle_px": handle_px, "handle_point": handle_point, "handle_size_m": handle_size,
            "handle_cut": handle_cut, "handle_end_centre": handle_end_centre}


def handle_candidates_evidence(parts: dict, inputs: dict, modes: dict, refined: dict, joint_types,
                               max_q_deg: float) -> dict:
    """:func:`handle_evidence` of the doors that step 7 may check: those with a vote mode, or a
    normal-based angle (refinement step 5, NaN when unmeasured), below ``max_q_deg``.
    ``modes``: :func:`~.aggregate.vote_modes` output; ``refined``: :func:`~.refine.refined_quantities`'."""
    if max_q_deg >= EVERY_DOOR_DEG:  # every door (the refined angles need not have been computed)
        candidates = torch.ones(refined["axis"].shape[:2], dtype=torch.bool)
    else:
        limit = math.radians(max_q_deg)
        measured = refined["q"]
        voted = torch.where(modes["weight"] > 0, modes["q"], torch.full_like(modes["q"], math.inf)).amin(-1)
        candidates = (voted < limit) | (measured < limit) | measured.isnan()
    return handle_evidence(parts, inputs, refined["axis"][:, :, 0], joint_types, candidates)


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
