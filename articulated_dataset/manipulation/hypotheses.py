"""Estimates of an object's kinematics as a planner sees them, fused and turned into hypotheses.

:class:`ObjectKinematics` is one image's kinematics (truth labels or a model's prediction, with the
model's other hypotheses as :attr:`ObjectKinematics.alternatives`).  :func:`transform_estimate` moves
one into another camera's frame; :func:`fuse_estimates` makes one of several images.  The
hypotheses of the closed loop: :func:`group_hypotheses` (by :func:`same_axis`),
:func:`mirrored_hypothesis` (the door hinged on its other edge), :func:`consistent_hypothesis`,
:func:`anchor_to_handle` (onto a sighted handle) and :func:`overview_hypothesis`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from articulated_dataset.classes.registry import REVOLUTE
from articulated_dataset.core.rotations import axis_angle_quat, quat_multiply, quat_to_matrix
from articulated_dataset.generation.labels import mat_to_quat
from articulated_dataset.manipulation.planning import (
    ZERO_LENGTH,
    axis_frame,
    canonical_quat,
    checked_vector,
    grasp_pose_from_estimate,
    outward_normal,
)

if TYPE_CHECKING:
    from articulated_dataset.manipulation.perception import HandleSighting

@dataclass
class ObjectKinematics:
    """Kinematics of one image as seen by a planner (all joints; camera frame)."""

    axis_pose: np.ndarray  # (J, 7)
    q: np.ndarray  # (J,)
    part_offset: np.ndarray | None = None  # (J, 3)
    geometry: np.ndarray | None = None  # (4,)
    source: str = "truth"
    #: this hypothesis's probability among the image's (1 for a point estimate)
    weight: float = 1.0
    #: the image's other hypotheses (e.g. the mixture's other components: a closed door hinged
    #: on the other side), each an ObjectKinematics with its own ``weight``; empty for a point estimate
    alternatives: list = field(default_factory=list)

    def axis(self, joint: int) -> tuple[np.ndarray, np.ndarray]:
        """``(origin (3,) m, unit direction (3,))`` of joint ``joint``'s axis, camera frame."""
        origin, rot = axis_frame(self.axis_pose[joint])
        return origin, rot[:, 2]

    def hypotheses(self) -> list["ObjectKinematics"]:
        """This estimate and its alternatives, heaviest first."""
        return sorted([self, *self.alternatives], key=lambda e: -e.weight)


def transform_estimate(estimate: ObjectKinematics, rot: np.ndarray, trans: np.ndarray) -> ObjectKinematics:
    """An estimate made in a camera at pose ``(rot, trans)`` (camera -> reference frame:
    ``p_ref = rot p + trans``) expressed in the reference frame.  Axis origins and frames move;
    q, part offsets (axis frame) and geometry do not."""
    pose = np.array(estimate.axis_pose, np.float64)
    rq = canonical_quat(mat_to_quat(rot))
    for j in range(len(pose)):
        pose[j, :3] = rot @ pose[j, :3] + trans
        pose[j, 3:] = canonical_quat(quat_multiply(rq, pose[j, 3:]))
    return ObjectKinematics(pose, np.array(estimate.q, np.float64),
                    None if estimate.part_offset is None else np.array(estimate.part_offset, np.float64),
                    None if estimate.geometry is None else np.array(estimate.geometry, np.float64), estimate.source,
                    estimate.weight, [transform_estimate(a, rot, trans) for a in estimate.alternatives])


def fuse_estimates(estimates: list[ObjectKinematics], source: str | None = None) -> ObjectKinematics:
    """One estimate from several of the same object in the same configuration (same frame).

    Per joint: axis direction = normalised mean of the directions (signs aligned to the
    first); origin = coordinate-wise median; q and part offset = medians.  The axis frame
    is that of the estimate whose direction is nearest the mean, turned minimally onto the
    mean direction.  Geometry = median.  Medians make one wild view harmless.
    """
    if not estimates:
        raise ValueError("no estimates to fuse")
    if len(estimates) == 1:
        return estimates[0]
    J = len(estimates[0].q)
    pose = np.zeros((J, 7))
    for j in range(J):
        frames = [axis_frame(e.axis_pose[j]) for e in estimates]
        d0 = frames[0][1][:, 2]
        dirs = np.array([f[1][:, 2] * (1.0 if f[1][:, 2] @ d0 >= 0 else -1.0) for f in frames])
        d = dirs.mean(axis=0)
        d /= np.linalg.norm(d)
        k = int(np.argmax(dirs @ d))
        rot = frames[k][1]
        if rot[:, 2] @ d < 0:  # its own direction was flipped to align: keep its frame, flip d
            d = -d
        cross = np.cross(rot[:, 2], d)
        angle = math.atan2(np.linalg.norm(cross), float(rot[:, 2] @ d))
        turn = quat_to_matrix(axis_angle_quat(cross, angle)) if np.linalg.norm(cross) > ZERO_LENGTH else np.eye(3)
        pose[j, :3] = np.median([f[0] for f in frames], axis=0)
        pose[j, 3:] = canonical_quat(mat_to_quat(turn @ rot))
    po = [e.part_offset for e in estimates if e.part_offset is not None]
    geo = [e.geometry for e in estimates if e.geometry is not None]
    return ObjectKinematics(pose, np.median([e.q for e in estimates], axis=0), np.median(po, axis=0) if po else None,
                    np.median(geo, axis=0) if geo else None, source or estimates[0].source)


#: Two hypotheses of a joint are the same axis when their directions (signed: a door hinged
#: on the other side turns about the opposite direction) are within HYPOTHESIS_SAME_ANGLE_DEG
#: and their origins within HYPOTHESIS_SAME_DISTANCE_M.
HYPOTHESIS_SAME_ANGLE_DEG = 45.0
HYPOTHESIS_SAME_DISTANCE_M = 0.3


def same_axis(a: ObjectKinematics, b: ObjectKinematics, joint: int) -> bool:
    """Whether two hypotheses put joint ``joint``'s axis in the same place (see HYPOTHESIS_SAME_*)."""
    (oa, da), (ob, db) = a.axis(joint), b.axis(joint)
    return bool(da @ db >= math.cos(math.radians(HYPOTHESIS_SAME_ANGLE_DEG))
                and np.linalg.norm(oa - ob) <= HYPOTHESIS_SAME_DISTANCE_M)


def group_hypotheses(estimates: list[ObjectKinematics], joint: int) -> list[tuple[float, list[ObjectKinematics]]]:
    """Axis hypotheses of several images of one object (same frame), grouped by :func:`same_axis`
    with each group's heaviest member: ``[(score, members)]``, best first.  A group's score is the
    mean over the images of the weight its members have in their image (weights normalised per
    image), so it is the images' average belief in that axis."""
    groups: list[list] = []  # [score, representative, members]
    for e in estimates:
        hyps = e.hypotheses()
        total = sum(h.weight for h in hyps)
        for h in hyps:
            w = h.weight / total / len(estimates)
            g = next((g for g in groups if same_axis(g[1], h, joint)), None)
            if g is None:
                groups.append([w, h, [h]])
            else:
                g[0] += w
                g[2].append(h)
    groups.sort(key=lambda g: -g[0])
    return [(float(g[0]), g[2]) for g in groups]


def mirrored_hypothesis(estimate: ObjectKinematics, joint: int) -> ObjectKinematics | None:
    """The door's panel where the estimate puts it now, hinged on its other edge and closed
    (revolute joints; None for prismatic ones or without a part offset).

    With the estimate's axis origin ``o``, frame ``(x, y, z)`` at q = 0, radius ``r`` (the part
    centre's distance from the axis, :attr:`ObjectKinematics.part_offset`) and configuration ``q``, the
    panel now runs along ``x_q = R_z(q) x``; the mirrored door has its origin at the other edge
    ``o + 2 r x_q``, ``x' = -x_q``, ``z' = -z`` (so ``y' = z' x x'``, the panel's outward normal,
    is the estimate's at ``q``), ``q' = 0`` and the part centre's height negated.  A closed
    door seen at an angle looks much like a door on the other hinge opened by that angle, so
    this is the one ambiguity a depth image leaves when the handle is not seen; the hypothesis
    has weight 0 (a last resort, checked by looking at its handle)."""
    if estimate.part_offset is None or estimate.axis_pose.shape[0] <= joint or estimate.q.shape[0] <= joint:
        return None
    r = float(estimate.part_offset[joint][0])
    if not r > 0 or abs(float(estimate.part_offset[joint][1])) > r:
        return None
    origin, rot = axis_frame(estimate.axis_pose[joint])
    turn = quat_to_matrix(axis_angle_quat(rot[:, 2], float(estimate.q[joint])))
    x_q, y_q = turn @ rot[:, 0], turn @ rot[:, 1]
    pose = np.array(estimate.axis_pose, np.float64)
    pose[joint, :3] = origin + 2.0 * r * x_q
    pose[joint, 3:] = canonical_quat(mat_to_quat(np.column_stack([-x_q, y_q, -rot[:, 2]])))
    po = np.array(estimate.part_offset, np.float64)
    po[joint, 2] = -po[joint, 2]
    q = np.array(estimate.q, np.float64)
    q[joint] = 0.0
    return ObjectKinematics(pose, q, po, estimate.geometry, estimate.source, weight=0.0)


def consistent_hypothesis(estimate: ObjectKinematics, reference: ObjectKinematics, joint: int, joint_type: str = REVOLUTE) -> ObjectKinematics | None:
    """The hypothesis of ``estimate`` (its own, or for a door their :func:`mirrored_hypothesis`)
    whose joint-``joint`` axis is the same as ``reference``'s (:func:`same_axis`) with the
    nearest origin; None when none is (the image says nothing consistent about this axis)."""
    hyps = estimate.hypotheses()
    if joint_type == REVOLUTE:
        hyps += [m for m in (mirrored_hypothesis(h, joint) for h in hyps) if m is not None]
    same = [h for h in hyps if same_axis(h, reference, joint)]
    if not same:
        return None
    o_ref = reference.axis(joint)[0]
    return min(same, key=lambda h: float(np.linalg.norm(h.axis(joint)[0] - o_ref)))


#: A sighted panel normal further than this from the hypothesis's (about its axis) is not used
#: to turn the hypothesis (the plane found then faces away from where the hypothesis's door can
#: face; the handle stands on the panel, so the plane is the door's; a door believed open 35
#: degrees and 25 degrees off in yaw is 60 off).
MAX_PANEL_TURN_DEG = 90.0


def anchor_to_handle(estimate: ObjectKinematics, joint: int, joint_type: str, handle_m, panel_normal) -> ObjectKinematics:
    """The estimate moved onto a sighted handle (reference frame).  A door (revolute) is first
    turned about its axis so that its panel's outward normal at the estimated ``q`` is
    ``panel_normal`` (projected across the axis; skipped if that turn exceeds
    :data:`MAX_PANEL_TURN_DEG`), then translated so that its planned grasp point
    (:func:`grasp_pose_from_estimate`) is ``handle_m``: the hinge then lies the estimated door
    width from the handle, along the seen panel.  A drawer is translated only."""
    pose = np.array(estimate.axis_pose, np.float64)
    po = None if estimate.part_offset is None else estimate.part_offset[joint]
    q = float(estimate.q[joint])
    grasp = grasp_pose_from_estimate(pose[joint], po, estimate.geometry, joint_type, q)
    if joint_type == REVOLUTE:
        o, rot = axis_frame(pose[joint])
        d = rot[:, 2]
        n_est, n_seen = outward_normal(grasp, joint_type), checked_vector("panel_normal", panel_normal, 3)
        n_est, n_seen = n_est - (n_est @ d) * d, n_seen - (n_seen @ d) * d
        if np.linalg.norm(n_est) > ZERO_LENGTH and np.linalg.norm(n_seen) > ZERO_LENGTH:
            angle = math.atan2(float(np.cross(n_est, n_seen) @ d), float(n_est @ n_seen))
            if abs(angle) <= math.radians(MAX_PANEL_TURN_DEG):
                pose[joint, 3:] = canonical_quat(mat_to_quat(quat_to_matrix(axis_angle_quat(d, angle)) @ rot))
                grasp = grasp_pose_from_estimate(pose[joint], po, estimate.geometry, joint_type, q)
    pose[joint, :3] += checked_vector("handle_m", handle_m, 3) - grasp[:3]
    return replace(estimate, axis_pose=pose, alternatives=[])


def overview_hypothesis(hypotheses: list[ObjectKinematics], joint: int, joint_type: str, seen: HandleSighting) -> int:
    """Index of the hypothesis a handle seen in an overview belongs to.  A door's handle is near
    its free edge, so its hinge is on the side of the handle where the seen panel runs further
    (across the hypothesis's axis, in the panel: :meth:`HandleSighting.panel_extent`); among the
    hypotheses whose hinge is on that side (all, for a drawer or when none is) the one whose
    planned grasp is nearest the handle."""
    grasps = [grasp_pose_from_estimate(h.axis_pose[joint], None if h.part_offset is None else h.part_offset[joint],
                                       h.geometry, joint_type, float(h.q[joint]))[:3] for h in hypotheses]

    def hinge_on_the_long_side(h: ObjectKinematics) -> bool:
        o, d = h.axis(joint)
        u = np.cross(seen.panel_normal, d)
        if np.linalg.norm(u) < ZERO_LENGTH:
            return True
        before, beyond = seen.panel_extent(u)
        return bool(((o - seen.centre_m) @ u) * (beyond - before) > 0)

    ok = [k for k, h in enumerate(hypotheses) if joint_type != REVOLUTE or hinge_on_the_long_side(h)]
    return min(ok or range(len(hypotheses)), key=lambda k: float(np.linalg.norm(grasps[k] - seen.centre_m)))


def __getattr__(name):
    """``Estimate``, this class's name before 0.2 (it collided with
    :class:`articulated_dataset.methods.estimation.Estimate`), until 0.3."""
    if name == "Estimate":
        import warnings

        warnings.warn("articulated_dataset.manipulation's Estimate is now ObjectKinematics; the old name is removed "
                      "in 0.3", DeprecationWarning, stacklevel=2)
        return ObjectKinematics
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
