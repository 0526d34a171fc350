"""What the dense estimator's inference needs beyond its weights, chosen on validation objects.

:func:`fit_refinement` decides which steps of the geometric refinement (:mod:`.refine`) a model
uses and fits the hinge offset ``t``.  Every choice is made on the training split's validation
objects (never the test split) and stored in the checkpoint's ``"refinement"``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from articulated_dataset.methods.dense.refine import DOOR_FACE_MAX_DEG, Refinement, apply_refinement, door_face_side

#: Thresholds tried for ``min_door_px`` (door pixels with a normal) by :func:`fit_refinement`.
DOOR_PX_CANDIDATES = (20, 40, 80, 160, 320)
#: Gates tried for ``door_angle_gate_deg`` (deg from the mode's voted angle; None: no gate), the
#: first kept on a tie.
DOOR_ANGLE_GATE_CANDIDATES_DEG = (None, 10.0, 15.0, 20.0, 30.0)
#: Offsets (m) fitted from rotations further than this from the truth (deg) are discarded.
MAX_OFFSET_FIT_ANGLE_DEG = 15.0
#: Gates tried for ``max_turn_deg`` by :func:`fit_refinement` (None: never gate).
TURN_GATE_CANDIDATES_DEG = (5.0, 8.0, 10.0, 15.0, 20.0, 30.0, None)
#: Gates tried for ``door_extent_gate_m`` by :func:`fit_refinement` (m; None: never gate).
DOOR_EXTENT_GATE_CANDIDATES_M = (0.05, 0.1, 0.2, None)
#: Door angles (deg) below which step 7 (the handle's side) may be used, tried by :func:`fit_refinement`.
HANDLE_Q_CANDIDATES_DEG = (5.0, 10.0, 20.0, 30.0, 45.0)
#: Handle pixels step 7 needs, tried by :func:`fit_refinement`.
HANDLE_PX_CANDIDATES = (1.0, 3.0, 6.0)
#: Gates (m) tried for step 9 (the hinge's height from the handle) by :func:`fit_refinement`.
HANDLE_HEIGHT_GATE_CANDIDATES_M = (0.05, 0.1, 0.2, 0.4)
#: ... which is used only where it lowers the validation position error by at least this fraction:
#: it measures the handle of every door, which costs inference time (about 1.6x the refinement's
#: time per batch).
HANDLE_HEIGHT_MIN_GAIN = 0.03
#: Segmentation probabilities a pixel needs to enter the box-frame fit (step 2), tried by
#: :func:`~.predict.fit_inference` (None: every body pixel).  A threshold keeps an open door's
#: pixels, taken for the body's, from pulling the frame towards the door's face; 0.7 still admits
#: the strips of body pixels beside a door (labelled with less confidence) that one-sided normals
#: read.  Each model keeps the one that gives the lowest rotation error on its validation objects.
FRAME_PROB_CANDIDATES = (None, 0.7, 0.9)
#: Whether step 2 also reads one-sided normals (:attr:`~.refine.Refinement.frame_one_sided`), tried
#: with each threshold by :func:`~.predict.fit_inference`.
FRAME_ONE_SIDED_CANDIDATES = (False, True)
#: Elongations (variance along the line / across it) tried for step 2's strip of body pixels
#: (:attr:`~.refine.Refinement.frame_strip_elongation`) by :func:`~.predict.fit_inference`, with
#: the chosen threshold and normals (the validation errors differ little between them; each
#: lowers the cabinet's rotation and configuration errors against no strip).
FRAME_STRIP_CANDIDATES = (100.0, 1000.0, 10000.0)
#: ... the best of which is kept only where it lowers the validation rotation error by at least
#: this fraction (a strip that turns a few images' frames by a hair is not worth its inference
#: time).
FRAME_STRIP_MIN_GAIN = 0.005
#: Gates (m) tried for step 10 (the hinge onto the door's face plane) by :func:`fit_refinement`.
DOOR_FACE_GATE_CANDIDATES_M = (0.01, 0.02, 0.03, 0.05, 0.1)
#: ... whose offset from a face (outer or inner) is fitted from at least this many doors seen so.
DOOR_FACE_MIN_FIT = 20
#: Gates (m) tried for step 11's ``q`` from a drawer's front plane by :func:`fit_refinement`.
DRAWER_FRONT_GATE_CANDIDATES_M = (0.02, 0.05, 0.1, 0.2)
#: Gates (m) tried for step 11's origin on the drawer front's centre by :func:`fit_refinement`.
DRAWER_CENTRE_GATE_CANDIDATES_M = (0.01, 0.02, 0.05, 0.1)
#: Gates (m) tried for step 11's origin on the shell's edge by :func:`fit_refinement`.
DRAWER_SHELL_GATE_CANDIDATES_M = (0.02, 0.05, 0.1, 0.2)
#: Step 11's plane and shell offsets are fitted from at least this many drawers (else 0, and the
#: shell's edge is not used).
DRAWER_FRONT_MIN_FIT = 20


def fit_refinement(m: dict, r: dict, truth: dict, joint_types) -> tuple["Refinement", dict]:
    """Choose and fit the refinement on validation images.

    ``m``/``r``: numpy mode arrays and refined quantities of the validation images; ``truth``:
    ``axis_pose`` (N, J, 7) and ``q`` (N, J).  The hinge offset is the median over revolute
    joints (whose box frame is within :data:`MAX_OFFSET_FIT_ANGLE_DEG` of the truth, sides
    agreeing) of ``r tan(a)``, ``a`` the signed angle from the box frame's ``x`` to the true
    ``x`` about the true axis and ``r`` the true radius.  The box frame is kept when it lowers
    the mean axis rotation error of the heaviest mode, with the gate of
    :data:`TURN_GATE_CANDIDATES_DEG` (keep the votes' frame where the box frame turns it further;
    a face mistaken for another) that lowers it most; the normal-based angle (with the best of
    :data:`DOOR_PX_CANDIDATES`, each pixel's angle as it is, folded towards the voted ``q``
    (``door_angle_folded``) or signed (``door_angle_signed``), with the best gate of
    :data:`DOOR_ANGLE_GATE_CANDIDATES_DEG` from the voted ``q``; tried in the chosen frame, since a
    signed angle depends on each mode's x) when it lowers the mean configuration error; the hinge height
    (step 6, with the best gate of :data:`DOOR_EXTENT_GATE_CANDIDATES_M`) when it lowers the mean
    axis position error of each joint's heaviest mode; the handle's side (step 7) with the
    pair of :data:`HANDLE_Q_CANDIDATES_DEG` and :data:`HANDLE_PX_CANDIDATES` that lowers that
    error most, if any does; the hinge's height from the handle (step 9) with the gate of
    :data:`HANDLE_HEIGHT_GATE_CANDIDATES_M`, from whole bars only or also from bars the image's
    border cuts (``handle_cut_bars``), that lowers it most, if that is by at least
    :data:`HANDLE_HEIGHT_MIN_GAIN` (``r`` must hold :func:`~.handle.handle_evidence`'s keys for
    steps 7 and 9, measured for every door); last, the hinge plane from the door's face (step 10,
    with the offsets of :func:`fit_door_face_offsets`) with the gate of
    :data:`DOOR_FACE_GATE_CANDIDATES_M` that lowers that error most, if any does; for drawers, the
    origin on the front's centre (step 11) with the gate of :data:`DRAWER_CENTRE_GATE_CANDIDATES_M`
    that lowers the position error most, the origin along the axis on the shell's edge (with the
    offset of :func:`fit_drawer_shell_offset`) with the gate of
    :data:`DRAWER_SHELL_GATE_CANDIDATES_M` that lowers it most, then ``q`` from the front's plane (with the offset of
    :func:`fit_drawer_front_offset`) with the gate of :data:`DRAWER_FRONT_GATE_CANDIDATES_M` that
    lowers the configuration error most, each if any does.  Returns the
    :class:`Refinement` and the validation errors of every candidate.
    """
    from articulated_dataset.benchmark import metrics as M

    revolute = np.array([t == "revolute" for t in joint_types])
    true_q = truth["axis_pose"][..., 3:]
    tz, tx = M.quat_axis_z(true_q), M.quat_axis_x(true_q)
    hz, hx = r["axis"][:, :, 0], r["xaxis"][:, :, 0]
    angle = np.arctan2((np.cross(hx, tx) * tz).sum(-1), (hx * tx).sum(-1))
    ok = revolute[None] & ((hz * tz).sum(-1) > 0) & (np.abs(angle) < np.radians(MAX_OFFSET_FIT_ANGLE_DEG))
    radius = truth["part_offset"][..., 0] if "part_offset" in truth else m["part_offset"][:, :, 0, 0]
    offset = float(np.median((radius * np.tan(angle))[ok])) if ok.any() else 0.0

    def rot_err(mm):
        return rotation_error_deg(mm, truth)

    def cfg_err(mm):
        return configuration_error(mm, truth, joint_types)

    report: dict[str, Any] = {"hinge_offset_m": offset, "rotation_deg": {"votes": rot_err(m)},
                              "configuration": {"votes": cfg_err(m)}}
    framed = apply_refinement(m, r, Refinement(frame=True, hinge_offset_m=offset), joint_types)
    report["rotation_deg"]["box_frame"] = rot_err(framed)
    use_frame = report["rotation_deg"]["box_frame"] < report["rotation_deg"]["votes"]
    best_turn, best_rot = None, report["rotation_deg"]["box_frame"]
    for turn in TURN_GATE_CANDIDATES_DEG[:-1]:
        e = rot_err(apply_refinement(m, r, Refinement(frame=True, hinge_offset_m=offset, max_turn_deg=turn), joint_types))
        report["rotation_deg"][f"box_frame_turn<={turn:g}deg"] = e
        if e < best_rot:
            best_turn, best_rot = turn, e
    use_frame = best_rot < report["rotation_deg"]["votes"]
    refinement = Refinement(frame=bool(use_frame), hinge_offset_m=offset if use_frame else 0.0,
                            max_turn_deg=best_turn if use_frame else None)
    def configuration(ref):  # the configuration error with a refinement
        return cfg_err(apply_refinement(m, r, ref, joint_types))

    if revolute.any():
        # the signed angle depends on each mode's x, so the candidates are tried in the chosen frame
        readings = [(False, False)] + ([(True, False)] if "q_folded" in r else []) + ([(False, True)] if "q_signed" in r else [])
        best, _ = _best_choice(configuration, refinement, {
            f"normals>={px}px" + ("_folded" if fold else "") + ("_signed" if signed else "")
            + ("" if gate is None else f"_gate<={gate:g}deg"):
                dict(min_door_px=px, door_angle_folded=fold, door_angle_signed=signed, door_angle_gate_deg=gate)
            for fold, signed in readings for px in DOOR_PX_CANDIDATES for gate in DOOR_ANGLE_GATE_CANDIDATES_DEG},
            report["configuration"], report["configuration"]["votes"])
        refinement = replace(refinement, **(best or {}))

    def pos_err(mm):
        heaviest = mm["weight"].argmax(-1)[..., None, None]  # (N, J, 1, 1)
        origin = np.take_along_axis(mm["origin"], heaviest, axis=2)[:, :, 0]
        return float(np.mean(M.axis_position_error_cm(origin, truth["axis_pose"][..., :3])))

    def position(ref):  # the position error with a refinement
        return pos_err(apply_refinement(m, r, ref, joint_types))

    if revolute.any() and "door_mid" in r:
        report["position_cm"] = {"votes": position(refinement)}
        best_extent, best_pos = _best_choice(position, refinement, {
            "door_extent" + ("" if gate is None else f"_gate<={gate:g}m"): dict(door_extent=True, door_extent_gate_m=gate)
            for gate in DOOR_EXTENT_GATE_CANDIDATES_M}, report["position_cm"], report["position_cm"]["votes"])
        refinement = replace(refinement, **(best_extent or {}))
    if revolute.any() and "handle_px" in r:
        report.setdefault("position_cm", {})["before_handle"] = best_pos = position(refinement)
        best_handle, best_pos = _best_choice(position, refinement, {
            f"handle_q<{q_deg:g}deg_px>={px:g}": dict(handle_max_q_deg=q_deg, handle_min_px=px)
            for q_deg in HANDLE_Q_CANDIDATES_DEG for px in HANDLE_PX_CANDIDATES}, report["position_cm"], best_pos)
        refinement = replace(refinement, **(best_handle or {}))
        report["position_cm"]["before_handle_height"] = before = best_pos
        best_gate, best_cut = None, False
        for cut in (False, True):
            for gate in HANDLE_HEIGHT_GATE_CANDIDATES_M:
                e = pos_err(apply_refinement(m, r, replace(refinement, handle_height_gate_m=gate, handle_cut_bars=cut),
                                             joint_types))
                report["position_cm"][f"handle_height_gate<={gate:g}m" + ("_cut_bars" if cut else "")] = e
                if e < best_pos and e <= before * (1 - HANDLE_HEIGHT_MIN_GAIN):
                    best_gate, best_cut, best_pos = gate, cut, e
        refinement = replace(refinement, handle_height_gate_m=best_gate, handle_cut_bars=best_cut)
    if revolute.any() and "door_face_m" in r:
        base = apply_refinement(m, r, refinement, joint_types)
        offsets = fit_door_face_offsets(base, r, truth, joint_types)
        report.setdefault("position_cm", {})["before_door_face"] = best_pos = pos_err(base)
        report["door_face_offsets_m"] = list(offsets)
        best_face, best_pos = _best_choice(position, refinement, {
            f"door_face_gate<={gate:g}m": dict(door_face_gate_m=gate, door_face_offsets_m=offsets)
            for gate in DOOR_FACE_GATE_CANDIDATES_M}, report["position_cm"], best_pos)
        refinement = replace(refinement, **(best_face or {}))
    if (~revolute).any() and "front_m" in r:
        # step 11: the drawer's origin onto its front's centre (position), then q from its plane
        report.setdefault("position_cm", {})["before_drawer_centre"] = best_pos = position(refinement)
        best_centre, best_pos = _best_choice(position, refinement, {
            f"drawer_centre_gate<={gate:g}m": dict(drawer_centre_gate_m=gate)
            for gate in DRAWER_CENTRE_GATE_CANDIDATES_M}, report["position_cm"], best_pos)
        refinement = replace(refinement, **(best_centre or {}))
        shell_offset = fit_drawer_shell_offset(r, truth, joint_types) if "shell_front_m" in r else None
        report["drawer_shell_offset_m"] = shell_offset
        if shell_offset is not None:
            report["position_cm"]["before_drawer_shell"] = best_pos
            best_shell, best_pos = _best_choice(position, refinement, {
                f"drawer_shell_gate<={gate:g}m": dict(drawer_shell_gate_m=gate, drawer_shell_offset_m=shell_offset)
                for gate in DRAWER_SHELL_GATE_CANDIDATES_M}, report["position_cm"], best_pos)
            refinement = replace(refinement, **(best_shell or {}))
        offset = fit_drawer_front_offset(r, truth, joint_types)
        report["drawer_front_offset_m"] = offset
        report["configuration"]["before_drawer_front"] = best_cfg = configuration(refinement)
        best_front, _ = _best_choice(configuration, refinement, {
            f"drawer_front_gate<={gate:g}m": dict(drawer_front_gate_m=gate, drawer_front_offset_m=offset)
            for gate in DRAWER_FRONT_GATE_CANDIDATES_M}, report["configuration"], best_cfg)
        refinement = replace(refinement, **(best_front or {}))
    return refinement, report


def _best_choice(error, refinement: Refinement, choices: dict, report: dict, best: float) -> tuple[dict | None, float]:
    """Of ``choices`` ({report name: Refinement fields}) tried on ``refinement``, the fields whose
    ``error(refinement with them)`` is lowest, if below ``best``, and that error (None and ``best``
    where none is); every choice's error is written to ``report`` under its name."""
    chosen = None
    for name, fields in choices.items():
        e = report[name] = error(replace(refinement, **fields))
        if e < best:
            chosen, best = fields, e
    return chosen, best


def fit_drawer_shell_offset(r: dict, truth: dict, joint_types) -> float | None:
    """Step 11's shell offset (m): the median, over the prismatic joints whose shell edge was
    measured, of the true origin's coordinate along the front's axis less the edge's
    (``o . zc - r["shell_front_m"]``); None where fewer than :data:`DRAWER_FRONT_MIN_FIT` were."""
    prismatic = np.array([t == "prismatic" for t in joint_types])
    residual = (truth["axis_pose"][..., :3] * r["front_axis"]).sum(-1) - r["shell_front_m"]
    seen = prismatic[None] & np.isfinite(residual)
    return float(np.median(residual[seen])) if seen.sum() >= DRAWER_FRONT_MIN_FIT else None


def fit_drawer_front_offset(r: dict, truth: dict, joint_types) -> float:
    """Step 11's plane offset (m): the median, over the prismatic joints whose front was measured,
    of the front's plane (``r["front_m"]`` along ``r["front_axis"]``) less the true outer face's
    (``o . zc + q z . zc``, ``o``, ``z`` and ``q`` the truth's); 0 (the template's outer face) where
    fewer than :data:`DRAWER_FRONT_MIN_FIT` fronts were measured."""
    from articulated_dataset.benchmark import metrics as M

    prismatic = np.array([t == "prismatic" for t in joint_types])
    zc = r["front_axis"]
    tz = M.quat_axis_z(truth["axis_pose"][..., 3:])
    residual = r["front_m"] - (truth["axis_pose"][..., :3] * zc).sum(-1) - truth["q"] * (tz * zc).sum(-1)
    seen = prismatic[None] & np.isfinite(residual)
    return float(np.median(residual[seen])) if seen.sum() >= DRAWER_FRONT_MIN_FIT else 0.0


def fit_door_face_offsets(mm: dict, r: dict, truth: dict, joint_types) -> tuple[float | None, float | None]:
    """Step 10's offsets (m) of the hinge plane along a door's face normal from its outer and its
    inner face: the medians, over the revolute joints' heaviest modes of the mode arrays ``mm``
    whose face seen is the outer (inner) one (:func:`~.refine.door_face_side`), of ``o . n - f``
    with ``o`` the true axis origin, ``n`` and ``f`` the face's normal and offset
    (``r["door_face_normal"]``, ``r["door_face_m"]``); None where fewer than
    :data:`DOOR_FACE_MIN_FIT` faces of that kind were seen (step 10 then leaves those modes alone)."""
    revolute = np.array([t == "revolute" for t in joint_types])
    heaviest = mm["weight"].argmax(-1)[..., None]  # (N, J, 1)
    side = np.take_along_axis(door_face_side(mm, r), heaviest, axis=2)[..., 0]  # (N, J)
    residual = (truth["axis_pose"][..., :3] * r["door_face_normal"]).sum(-1) - r["door_face_m"]
    cos = np.cos(np.radians(DOOR_FACE_MAX_DEG))
    seen = revolute[None] & np.isfinite(residual)
    outer, inner = residual[seen & (side > cos)], residual[seen & (side < -cos)]
    # (two sides in, two offsets out: mypy types a tuple built from a generator as of any length)
    return tuple(float(np.median(v)) if v.size >= DOOR_FACE_MIN_FIT else None  # type: ignore[return-value]
                 for v in (outer, inner))


def rotation_error_deg(mm: dict, truth: dict) -> float:
    """Mean axis rotation error (deg) of the heaviest mode's frame of mode arrays ``mm``."""
    from articulated_dataset.benchmark import metrics as M
    from articulated_dataset.core.rotations import matrix_to_quat
    from articulated_dataset.training.targets import gram_schmidt

    frames = gram_schmidt(mm["axis"][:, :, 0], mm["xaxis"][:, :, 0])
    return float(np.mean(M.axis_rotation_error_deg(matrix_to_quat(frames), truth["axis_pose"][..., 3:])))


def configuration_error(mm: dict, truth: dict, joint_types) -> float:
    """Mean configuration error (deg or m as the metric gives it) of the heaviest mode's ``q``."""
    from articulated_dataset.benchmark import metrics as M

    prismatic = np.array([t == "prismatic" for t in joint_types])
    return float(np.mean(M.configuration_error(mm["q"][:, :, 0], truth["q"], prismatic)))
