"""Joint labels from the poses of an object's parts, as real articulated datasets annotate them.

A *pose* is a 4x4 rigid transform ``T = [[R, t], [0, 0, 0, 1]]`` from a link's frame to the
camera frame: ``p_camera = R p_link + t``.  Given the camera poses ``T_p`` and ``T_c`` of a
joint's parent and child links, and the child's pose ``T_rest`` in the parent's frame at the
closed configuration (q = 0; the identity where both links share one frame at rest), the child's
displacement in the parent's frame is

    ``M = T_p^-1 T_c T_rest^-1 = [[R, t], [0, 0, 0, 1]]``

(a point of the closed child at ``x`` in the parent's frame is at ``R x + t`` now).
:func:`joint_from_part_poses` reads the joint's axis and configuration off ``M``, cross-checks
them against the annotated joint and returns them in the camera frame; :func:`axis_frame_labels`
turns them into the dataset's ``axis_pose`` and ``part_offset`` (docs/format.md, Labels).

Pure functions of numpy arrays; the files are read by :mod:`.part_annotations`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from articulated_dataset.core.rotations import axis_angle_quat, matrix_to_quat, quat_to_matrix
from articulated_dataset.core.units import PRISMATIC, REVOLUTE, normalise, point_line_distance_m
from articulated_dataset.ingest.ground_truth import axis_frame_from_direction

#: A pose's rotation may differ from an orthonormal matrix by this much (largest entry of
#: ``|R^T R - I|``): annotations written with 4-6 decimals are a few 1e-5 off; 1e-3 is a
#: matrix that is not a rotation (a scale, a shear, a typo).
RIGID_TOL = 1e-3
#: Below this rotation (rad) a revolute part counts as closed: its axis is the annotated one
#: (a pose annotation's noise, ~0.5 deg, makes the axis of a smaller rotation meaningless).
MIN_REVOLUTE_MOTION_RAD = math.radians(1.0)
#: Below this translation (m) a prismatic part counts as closed: its axis is the annotated one.
MIN_PRISMATIC_MOTION_M = 0.005
#: The axis from the poses and the annotated axis disagree beyond this angle (rad) between
#: their directions (as lines for revolute axes)...
MAX_AXIS_ANGLE_RAD = math.radians(5.0)
#: ... or beyond this distance (m) of the axis origin from the annotated axis line (revolute).
MAX_AXIS_DISTANCE_M = 0.02
#: The part's motion is not the joint's beyond this rotation (rad) left unexplained (a slider
#: that turned, a hinge about another axis than its rotation's)...
MAX_RESIDUAL_ROTATION_RAD = math.radians(2.0)
#: ... or this translation (m) left unexplained (a hinge that slid along its axis, a slider
#: that moved sideways).
MAX_RESIDUAL_TRANSLATION_M = 0.01
#: Axis-frame x vectors shorter than this (m or unitless) are degenerate (a part centre on its
#: hinge line, a slider along the object's up): the frame is completed from the camera's axes.
MIN_FRAME_NORM = 1e-9


def rigid_problem(T: np.ndarray, tol: float = RIGID_TOL) -> str | None:
    """Why the 4x4 ``T`` is not a rigid transform, or None: its last row must be ``0 0 0 1``
    (within ``tol``), its rotation orthonormal (``max |R^T R - I| <= tol``) and proper
    (``det R > 0``: not a reflection); every entry finite."""
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4):
        return f"has shape {T.shape}, expected (4, 4)"
    if not np.isfinite(T).all():
        return "has NaN or infinite values"
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > tol:
        return f"has last row {T[3].tolist()}, expected [0, 0, 0, 1]"
    R = T[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > tol:
        return f"has a rotation that is not orthonormal (|R^T R - I| up to {off:.3g}, at most {tol:g})"
    if np.linalg.det(R) <= 0:
        return "has a reflection, not a rotation (det R < 0)"
    return None


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest ``R`` (Frobenius norm): ``U diag(1, 1, det(U V^T)) V^T`` of the SVD
    ``R = U S V^T``; a rotation is returned as it is (up to rounding)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, np.float64))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def rigid(T: np.ndarray) -> np.ndarray:
    """``T`` (a transform passing :func:`rigid_problem`) with its rotation made exactly
    orthonormal (:func:`nearest_rotation`) and its last row exactly ``0 0 0 1``."""
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(np.asarray(T, np.float64)[:3, :3])
    out[:3, 3] = np.asarray(T, np.float64)[:3, 3]
    return out


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``[[R^T, -R^T t], [0, 0, 0, 1]]``."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def rotation_vector(R: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit axis ``u`` and angle ``theta`` in [0, pi] of the rotation ``R`` (``R`` rotates by
    ``theta`` about ``u``, right hand): from its quaternion ``(w, v)``, ``w >= 0``,
    ``theta = 2 atan2(|v|, w)``, ``u = v / |v|`` (u = z and theta = 0 for the identity)."""
    quat = matrix_to_quat(R)
    n = float(np.linalg.norm(quat[1:]))
    if n == 0.0:
        return np.array([0.0, 0.0, 1.0]), 0.0
    return quat[1:] / n, 2.0 * math.atan2(n, float(quat[0]))


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """The rotation by ``angle_rad`` about the unit ``axis`` (right hand)."""
    return quat_to_matrix(axis_angle_quat(axis, angle_rad))


def relative_motion(T_parent: np.ndarray, T_child: np.ndarray, rest_pose: np.ndarray | None = None) -> np.ndarray:
    """The child's displacement from its closed pose in the parent's frame,
    ``M = T_parent^-1 T_child T_rest^-1`` (``T_rest``: the child's pose in the parent's frame at
    q = 0; identity if None)."""
    M = inverse(T_parent) @ T_child
    return M if rest_pose is None else M @ inverse(rest_pose)


def leading_face_centre(centre: np.ndarray, size: np.ndarray, R_box: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Centre of a box's face leading along the unit ``direction``: the box (``centre``, full
    ``size`` along the columns of ``R_box``) moved by ``h a`` with ``h = sum_i |a_i| size_i / 2``,
    ``a = R_box^T direction`` (for a direction along a box axis, that face's centre)."""
    a_box = R_box.T @ direction
    return centre + direction * float(np.abs(a_box) @ (0.5 * np.asarray(size, np.float64)))


@dataclass(frozen=True, eq=False)  # numpy fields: compared by identity
class PartPoseJoint:
    """A joint read off its parts' poses (camera frame; :func:`joint_from_part_poses`).

    ``origin_m``/``direction``: the axis (revolute: the point on it nearest the child part's
    centre; prismatic: the centre of the closed part's face leading along the axis);
    ``q``: rad or m, the sign given by the annotated axis; ``part_centre_m``: the child part's
    box centre at q = 0; ``from_motion``: False where the motion was too small for an axis
    (the annotated axis is used).  Cross-check figures: ``direction_error_rad`` (angle to the
    annotated direction), ``line_distance_m`` (``origin_m`` to the annotated axis line;
    NaN for prismatic joints, whose axis has no position), ``residual_rotation_rad`` and
    ``residual_translation_m`` (the part's motion the joint does not explain).
    """

    joint_type: str
    origin_m: np.ndarray
    direction: np.ndarray
    q: float
    part_centre_m: np.ndarray
    from_motion: bool
    direction_error_rad: float
    line_distance_m: float
    residual_rotation_rad: float
    residual_translation_m: float

    def disagreements(self) -> list[str]:
        """The cross-check figures beyond their thresholds (:data:`MAX_AXIS_ANGLE_RAD`,
        :data:`MAX_AXIS_DISTANCE_M`, :data:`MAX_RESIDUAL_ROTATION_RAD`,
        :data:`MAX_RESIDUAL_TRANSLATION_M`), each as a phrase; empty where they agree."""
        out = []
        if self.direction_error_rad > MAX_AXIS_ANGLE_RAD:
            out.append(f"axis direction {math.degrees(self.direction_error_rad):.2f} deg from the annotated one")
        if self.line_distance_m > MAX_AXIS_DISTANCE_M:  # NaN compares False
            out.append(f"axis {100 * self.line_distance_m:.2f} cm from the annotated axis line")
        if self.residual_rotation_rad > MAX_RESIDUAL_ROTATION_RAD:
            out.append(f"{math.degrees(self.residual_rotation_rad):.2f} deg of the part's rotation not about the axis")
        if self.residual_translation_m > MAX_RESIDUAL_TRANSLATION_M:
            out.append(f"{100 * self.residual_translation_m:.2f} cm of the part's translation not along the joint")
        return out


def joint_from_part_poses(T_parent: np.ndarray, T_child: np.ndarray, joint_type: str, box_centre_m: np.ndarray,
                          box_size_m: np.ndarray, annotated_direction: np.ndarray,
                          annotated_origin_m: np.ndarray | None = None, rest_pose: np.ndarray | None = None) -> PartPoseJoint:
    """The joint between two links from their camera poses (module docstring: ``M``, ``R``, ``t``).

    ``box_centre_m``/``box_size_m``: the child part's axis-aligned box in the child's frame;
    ``annotated_direction``/``annotated_origin_m``: the annotated axis in the parent's frame
    (the origin is needed for revolute joints); ``rest_pose``: ``T_rest`` (identity if None).
    In the parent's frame, with ``c = T_rest box_centre`` the closed part's centre and ``b``
    the annotated unit direction:

    * revolute: ``theta``, ``u`` = :func:`rotation_vector` of ``R``.  With ``theta >=``
      :data:`MIN_REVOLUTE_MOTION_RAD`: ``a = s u`` and ``q = s theta``, ``s = sign(u . b)``;
      the axis points ``p`` solve ``(I - R) p = t`` (least squares, ``numpy.linalg.lstsq``:
      rank 2, the minimum-norm solution ``p0``), and the origin is the one nearest ``c``,
      ``p = p0 + ((c - p0) . a) a``.  Below it the part is closed: ``a = b``, ``q = theta (u . b)``,
      ``p`` = the annotated line's point nearest ``c``.
    * prismatic: with ``|t| >=`` :data:`MIN_PRISMATIC_MOTION_M`: ``a = s t / |t|``,
      ``s = sign(t . b)``; below it ``a = b``; ``q = t . a``; the origin is the closed part's
      face leading along ``a`` (:func:`leading_face_centre` of the box turned by ``R_rest``).

    Cross-check: ``direction_error = acos(|a . b|)``; ``line_distance`` = distance of ``p`` from
    the annotated line (revolute); the motion the joint predicts, ``R' = rot(a, q)``,
    ``t' = (I - R') p`` (revolute) or ``R' = I``, ``t' = q a`` (prismatic), leaves
    ``residual_rotation`` = angle of ``R R'^T`` and ``residual_translation = |t - t'|``.
    Origin, direction and part centre are returned in the camera frame (``T_parent`` applied).
    """
    if joint_type not in (REVOLUTE, PRISMATIC):
        raise ValueError(f"unknown joint type {joint_type!r}")
    M = relative_motion(T_parent, T_child, rest_pose)
    R, t = M[:3, :3], M[:3, 3]
    T_rest = np.eye(4) if rest_pose is None else rest_pose
    c = T_rest[:3, :3] @ np.asarray(box_centre_m, np.float64) + T_rest[:3, 3]
    b = normalise(annotated_direction)
    u, theta = rotation_vector(R)
    if joint_type == REVOLUTE:
        if annotated_origin_m is None:
            raise ValueError("a revolute joint needs its annotated axis origin")
        o = np.asarray(annotated_origin_m, np.float64)
        from_motion = theta >= MIN_REVOLUTE_MOTION_RAD
        if from_motion:
            s = 1.0 if u @ b >= 0 else -1.0
            a, q = s * u, s * theta
            p0 = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
            p = p0 + ((c - p0) @ a) * a
        else:
            a, q = b, theta * float(u @ b)
            p = o + ((c - o) @ b) * b
        R_pred = rotation_about(a, q)
        t_pred = (np.eye(3) - R_pred) @ p
        line_distance = float(point_line_distance_m(p, o, b))
    else:
        n = float(np.linalg.norm(t))
        from_motion = n >= MIN_PRISMATIC_MOTION_M
        a = (t / n if t @ b >= 0 else -t / n) if from_motion else b
        q = float(t @ a)
        p = leading_face_centre(c, box_size_m, T_rest[:3, :3], a)
        R_pred, t_pred = np.eye(3), q * a
        line_distance = math.nan
    residual_rotation = rotation_vector(R @ R_pred.T)[1]
    Rp, tp = T_parent[:3, :3], T_parent[:3, 3]
    return PartPoseJoint(joint_type=joint_type, origin_m=Rp @ p + tp, direction=Rp @ a, q=float(q),
                         part_centre_m=Rp @ c + tp, from_motion=bool(from_motion),
                         direction_error_rad=math.acos(min(1.0, abs(float(a @ b)))), line_distance_m=line_distance,
                         residual_rotation_rad=residual_rotation, residual_translation_m=float(np.linalg.norm(t - t_pred)))


def axis_frame_labels(joint: PartPoseJoint, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``axis_pose`` (7: origin, quaternion w, x, y, z) and ``part_offset`` (3) of ``joint``
    (docs/format.md, Labels): the frame's z is the axis direction ``a``; its x points from the
    axis towards the closed part's centre ``c`` (revolute: ``x ~ d - (d . a) a``,
    ``d = c - origin``) or along the object's unit ``up`` (camera frame) made perpendicular to
    ``a`` (prismatic: ``x ~ up - (up . a) a``); ``y = z x x``.  Where that x vanishes
    (shorter than :data:`MIN_FRAME_NORM`) the frame is
    :func:`~.ground_truth.axis_frame_from_direction`'s.  ``part_offset = R^T (c - origin)``.
    """
    a = joint.direction
    v = joint.part_centre_m - joint.origin_m if joint.joint_type == REVOLUTE else np.asarray(up, np.float64)
    x = v - (v @ a) * a
    if np.linalg.norm(x) < MIN_FRAME_NORM:
        frame = axis_frame_from_direction(a)
    else:
        x = normalise(x)
        frame = np.stack([x, np.cross(a, x), a], axis=1)
    pose = np.concatenate([joint.origin_m, matrix_to_quat(frame)])
    return pose, frame.T @ (joint.part_centre_m - joint.origin_m)
