"""The grasp rule and the waypoints: from estimated kinematics to an end-effector plan.

The paper (Sec. 4.2) opens novel objects with a fixed grasp on the handle and end-effector
waypoints computed from the estimated kinematics, the end-effector pose and the desired
configuration (formulas in docs/manipulation.md):

1. :func:`grasp_pose_from_estimate` -- the handle's grasp pose (camera frame) from an axis
   pose, part offset and configuration, by the rule the Xacro templates follow
   (``classes/common.xacro``: handles sit :data:`HANDLE_INSET_M` in from the free
   edge, standing :data:`HANDLE_STANDOFF_M` out of the panel's outer face).
2. :func:`plan_waypoints` -- end-effector poses carrying the grasp along the arc (revolute:
   rotation about the axis line) or the line (prismatic: translation along the axis) from
   the current to the target configuration, every :data:`DEFAULT_STEP_RAD` /
   :data:`DEFAULT_STEP_M`, ending exactly at the target.
3. :func:`plan_from_estimate` -- both for one joint of an
   :class:`~articulated_dataset.manipulation.hypotheses.ObjectKinematics`, as a :class:`Plan`.

Poses are ``(7,)`` arrays: position (m, camera frame) + quaternion (w, x, y, z).  Everything
here is pure (numpy in, numpy out); the execution (:mod:`.execution`) touches MuJoCo state.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from articulated_dataset.classes.registry import BUILTIN_GENERATORS, JOINT_TYPES, PAPER_CLASSES, PRISMATIC, REVOLUTE
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.rotations import axis_angle_quat, quat_multiply, quat_to_matrix
from articulated_dataset.core.units import normalise
from articulated_dataset.generation.labels import mat_to_quat

if TYPE_CHECKING:
    from articulated_dataset.manipulation.hypotheses import ObjectKinematics

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# Template constants (mirrors of classes/common.xacro; tests check the grasp rule
# against the compiled handle geoms, so a template change that breaks the rule fails CI)
# --------------------------------------------------------------------------------------

#: Distance of the handle bar's centre line from the panel's free edge (common.xacro ``handle_inset_m``).
HANDLE_INSET_M = 0.05
#: How far the handle bar stands out of the panel's outer face (``handle_standoff_m``); the
#: grasp point is the bar's centre, half of it out of the face.
HANDLE_STANDOFF_M = 0.03
#: Thickness of doors and drawer fronts (``panel_m``): the hinge line lies on the panel's
#: outer face, so the part centre sits half of it behind the hinge plane.
PANEL_THICKNESS_M = 0.02
#: The built-in classes whose handles the grasp rule places: the paper's, whose templates build
#: the handles of the constants above.  The package's own classes (oven, dishwasher,
#: lidded_box) build thicker doors and lids whose handles and latches stand elsewhere;
#: planning refuses them with one line (:func:`check_grasp_rule`).
GRASP_RULE_CLASSES = PAPER_CLASSES


def check_grasp_rule(class_name: str) -> None:
    """UserError unless the grasp rule knows where a built-in class's handles are
    (:data:`GRASP_RULE_CLASSES`); a third-party class passes."""
    if class_name in BUILTIN_GENERATORS and class_name not in GRASP_RULE_CLASSES:
        raise UserError(f"class {class_name!r}: manipulation places grasps on the handles of the paper's classes only "
                        f"({', '.join(GRASP_RULE_CLASSES)})")

# --------------------------------------------------------------------------------------
# Planning defaults
# --------------------------------------------------------------------------------------

#: Revolute waypoint spacing: 1 degree.  On the largest door (handle radius ~1.35 m) the
#: chord between waypoints deviates from the arc by r (1 - cos(step / 2)) = 0.05 mm.
DEFAULT_STEP_RAD = math.radians(1.0)
#: Prismatic waypoint spacing: 1 cm (the path is a straight line, so spacing only sets
#: the resolution of the plan).
DEFAULT_STEP_M = 0.01
#: Default opening targets of the benchmark: 60 degrees / 20 cm (clipped to the joint range).
DEFAULT_TARGET_RAD = math.radians(60.0)
DEFAULT_TARGET_M = 0.20
#: Success tolerance on the reached configuration: 5 degrees (revolute) / 2 cm (prismatic).
SUCCESS_TOL_RAD = math.radians(5.0)
SUCCESS_TOL_M = 0.02


#: Vectors/quaternions shorter than this have no direction (axis, rotation): rejected.
ZERO_LENGTH = 1e-9
#: A step count |dq| / step within this of an integer is that integer (so 60 deg in 1 deg
#: steps is 60 steps, not 61, despite floating-point round-off).
STEP_COUNT_SLACK = 1e-9
#: Most waypoints one plan may have: a 0.001 deg step over a 90 deg door gives 90,000; a
#: finer spacing resolves nothing the simulation or an arm controller could use.
MAX_WAYPOINTS = 100_000


def quat_angle(a, b) -> float:
    """Angle (rad) of the rotation between two orientations: 2 acos(|<a, b>|)."""
    d = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return 2.0 * math.acos(min(1.0, d))


def canonical_quat(quat: np.ndarray) -> np.ndarray:
    """``quat`` (w, x, y, z) normalised to unit length, with ``w >= 0``."""
    q = np.asarray(quat, np.float64)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


# --------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------

def check_joint_type(joint_type: str) -> None:
    """A joint type other than revolute or prismatic is the user's mistake."""
    if joint_type not in JOINT_TYPES:
        raise UserError(f"joint type must be one of {', '.join(JOINT_TYPES)}, got {joint_type!r}")


def checked_vector(name: str, v, n: int) -> np.ndarray:
    """``v`` as a float64 array of shape ``(n,)``; another shape raises ValueError, a NaN or infinite value is the
    user's mistake."""
    a = np.asarray(v, np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{name} has NaN/inf values: {a.tolist()}")
    return a


def given_unit(name: str, v) -> np.ndarray:
    """A 3-vector given by the user, finite and of nonzero length, normalised."""
    return normalise(checked_vector(name, v, 3), min_norm=ZERO_LENGTH, what=name)


def axis_frame(axis_pose) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), R (3, 3))`` of an axis pose; ``R[:, 2]`` is the axis direction."""
    pose = checked_vector("axis_pose", axis_pose, 7)
    if np.linalg.norm(pose[3:]) < ZERO_LENGTH:
        raise UserError("axis_pose has a zero-length quaternion")
    return pose[:3].copy(), quat_to_matrix(pose[3:])


def default_target(joint_type: str) -> float:
    """The benchmark's opening target: 60 deg (revolute) or 0.2 m (prismatic)."""
    check_joint_type(joint_type)
    return DEFAULT_TARGET_RAD if joint_type == REVOLUTE else DEFAULT_TARGET_M


def success_tolerance(joint_type: str) -> float:
    """Allowed |q_reached - q_target|: 5 deg in rad (revolute) or 0.02 m (prismatic)."""
    check_joint_type(joint_type)
    return SUCCESS_TOL_RAD if joint_type == REVOLUTE else SUCCESS_TOL_M


# --------------------------------------------------------------------------------------
# Grasp rule
# --------------------------------------------------------------------------------------

def handle_offset_in_axis_frame(part_offset, joint_type: str) -> np.ndarray:
    """Handle centre at q = 0 in the axis frame, from the part centre ``c = part_offset``.

    Revolute (doors; the built-in templates put the hinge line on the panel's outer face):
    with ``r = |(c_x, c_y)|``, the door's half-width is ``L = sqrt(r^2 - (t/2)^2)`` (t =
    :data:`PANEL_THICKNESS_M`), the panel runs along ``u = R_z(beta + alpha) e_x`` with
    ``beta = atan2(c_y, c_x)`` and ``alpha = atan2(t/2, L)``, and its outward normal is
    ``n = e_z x u``.  The handle bar sits ``HANDLE_INSET_M`` in from the free edge (radius
    ``2 L - inset``), ``HANDLE_STANDOFF_M / 2`` out of the face, at the part centre's
    height along the axis::

        h = (2 L - inset) u + (standoff / 2) n + c_z e_z

    Prismatic (drawers): the centre of the front face -- the part centre moved along the
    axis onto the leading face, which is the axis origin's plane (z = 0) -- plus half the
    standoff along the axis: ``h = (c_x, c_y, standoff / 2)``.
    """
    check_joint_type(joint_type)
    c = checked_vector("part_offset", part_offset, 3)
    if joint_type == PRISMATIC:
        return np.array([c[0], c[1], 0.5 * HANDLE_STANDOFF_M])
    r = float(np.hypot(c[0], c[1]))
    half_t = 0.5 * PANEL_THICKNESS_M
    half_width = math.sqrt(max(r * r - half_t * half_t, 0.0))
    angle = math.atan2(c[1], c[0]) + math.atan2(half_t, half_width)
    u = np.array([math.cos(angle), math.sin(angle), 0.0])
    n = np.array([-math.sin(angle), math.cos(angle), 0.0])  # e_z x u
    radius = max(2.0 * half_width - HANDLE_INSET_M, 0.0)
    return radius * u + 0.5 * HANDLE_STANDOFF_M * n + np.array([0.0, 0.0, c[2]])


def part_offset_from_geometry(geometry, axis_direction, joint_type: str) -> np.ndarray:
    """Coarse part offset when an estimate has none, from the body geometry alone.

    Revolute: the door is assumed to span the body's extent across the axis -- the width
    ``geometry[1]`` if the axis is within 45 degrees of vertical (camera z = the objects'
    up), else the height ``geometry[2]`` -- so ``c = (extent / 2, 0, 0)``.  Prismatic: the
    front face is centred on the axis origin, ``c = (0, 0, -depth / 2)``.  This is right
    for full-width doors only (cabinet, refrigerator, toaster's height) and overestimates
    narrower doors (microwave, cabinet2): prefer a predicted ``part_offset``.
    """
    check_joint_type(joint_type)
    g = checked_vector("geometry", geometry, 4)
    a = given_unit("axis_direction", axis_direction)
    if joint_type == PRISMATIC:
        return np.array([0.0, 0.0, -0.5 * g[0]])
    vertical = abs(a[2]) >= math.cos(math.pi / 4)
    extent = g[1] if vertical else g[2]
    return np.array([0.5 * extent, 0.0, 0.0])


def move_pose(pose, joint_type: str, axis_origin, axis_direction, delta: float) -> np.ndarray:
    """A pose carried by the part when its joint moves by ``delta`` (rad or m).

    Revolute: ``p' = o + R(a, delta) (p - o)``, ``quat' = quat(a, delta) * quat``.
    Prismatic: ``p' = p + delta a``, orientation unchanged.
    """
    check_joint_type(joint_type)
    pose = checked_vector("pose", pose, 7)
    o = checked_vector("axis_origin", axis_origin, 3)
    a = given_unit("axis_direction", axis_direction)
    out = pose.copy()
    if joint_type == PRISMATIC:
        out[:3] = pose[:3] + delta * a
        return out
    rq = axis_angle_quat(a, delta)
    rot = quat_to_matrix(rq)
    out[:3] = o + rot @ (pose[:3] - o)
    out[3:] = canonical_quat(quat_multiply(rq, pose[3:]))
    return out


def grasp_pose_from_estimate(axis_pose, part_offset, geometry, joint_type: str, q: float) -> np.ndarray:
    """The handle's grasp pose (7,) in the camera frame at configuration ``q``.

    Position: :func:`handle_offset_in_axis_frame` mapped to the camera frame through the
    axis pose (``o + R h``) and moved by ``q`` (:func:`move_pose`).  Orientation: the axis
    frame carried with the part (x: radial (revolute) / object up (prismatic), z: the axis,
    y = z x x).  For a door y points out of the panel (the gripper approaches along -y);
    for a drawer z does (it approaches along -z).
    ``part_offset`` may be None: then :func:`part_offset_from_geometry` estimates it from
    ``geometry`` (which is otherwise unused).
    """
    check_joint_type(joint_type)
    origin, rot = axis_frame(axis_pose)
    if part_offset is None:
        if geometry is None:
            raise UserError("the estimate has neither part_offset nor geometry: cannot place the handle")
        part_offset = part_offset_from_geometry(geometry, rot[:, 2], joint_type)
        log.info("no part_offset: handle placed from the geometry (coarse)")
    h = handle_offset_in_axis_frame(part_offset, joint_type)
    pose0 = np.concatenate([origin + rot @ h, canonical_quat(mat_to_quat(rot))])
    return move_pose(pose0, joint_type, origin, rot[:, 2], float(q))


# --------------------------------------------------------------------------------------
# Waypoints
# --------------------------------------------------------------------------------------

def waypoint_configurations(q_current: float, q_target: float, step: float) -> np.ndarray:
    """Configurations of the waypoints: ``n = max(1, ceil(|dq| / step))`` equal steps from
    ``q_current`` to exactly ``q_target`` (n + 1 values; one value if they are equal)."""
    if not (math.isfinite(q_current) and math.isfinite(q_target)):
        raise UserError(f"configurations must be finite, got {q_current} -> {q_target}")
    if not step > 0:
        raise UserError(f"waypoint step must be positive, got {step}")
    dq = q_target - q_current
    if dq == 0.0:
        return np.array([q_current])
    steps = abs(dq) / step
    if not steps <= MAX_WAYPOINTS:
        raise UserError(f"a step of {step:.3g} from {q_current:.4g} to {q_target:.4g} gives {steps:.3g} waypoints "
                        f"(at most {MAX_WAYPOINTS:,}); use a larger step")
    n = max(1, math.ceil(steps - STEP_COUNT_SLACK))
    qs = q_current + dq * np.arange(n + 1) / n
    qs[-1] = q_target
    return qs


def plan_waypoints(joint_type: str, axis_origin, axis_direction, q_current: float, q_target: float, grasp_pose,
                   step_rad: float = DEFAULT_STEP_RAD, step_m: float = DEFAULT_STEP_M) -> np.ndarray:
    """End-effector poses (K, 7) moving a grasped handle from ``q_current`` to ``q_target``.

    Waypoint k is ``grasp_pose`` moved by ``q_k - q_current`` (:func:`move_pose`): for a
    revolute joint a rotation about the line through ``axis_origin`` along
    ``axis_direction`` (consecutive positions are ``2 r sin(step / 2)`` apart for a handle at
    distance r from the axis, orientations ``step`` apart); for a prismatic joint a
    translation along the direction (positions ``step`` apart, fixed orientation).  The
    first pose is ``grasp_pose``; the last is exactly the pose at ``q_target``.
    """
    check_joint_type(joint_type)
    o = checked_vector("axis_origin", axis_origin, 3)
    a = given_unit("axis_direction", axis_direction)
    pose = checked_vector("grasp_pose", grasp_pose, 7)
    if np.linalg.norm(pose[3:]) < ZERO_LENGTH:
        raise UserError("grasp_pose has a zero-length quaternion")
    pose[3:] = canonical_quat(pose[3:])
    step = step_rad if joint_type == REVOLUTE else step_m
    qs = waypoint_configurations(float(q_current), float(q_target), float(step))
    return np.stack([move_pose(pose, joint_type, o, a, dq) for dq in qs - float(q_current)])


@dataclass
class Plan:
    """A grasp and its waypoints for one joint."""

    joint: int
    joint_type: str
    q_current: float
    q_target: float
    grasp_pose: np.ndarray  # (7,)
    waypoints: np.ndarray  # (K, 7)
    axis_origin: np.ndarray
    axis_direction: np.ndarray
    source: str

    def to_dict(self) -> dict:
        """The plan as plain JSON types (arrays as lists)."""
        return {
            "joint": self.joint, "joint_type": self.joint_type, "source": self.source,
            "q_current": self.q_current, "q_target": self.q_target,
            "axis_origin": self.axis_origin.tolist(), "axis_direction": self.axis_direction.tolist(),
            "grasp_pose": self.grasp_pose.tolist(), "waypoints": self.waypoints.tolist(),
        }


def plan_from_estimate(estimate: ObjectKinematics, joint: int, joint_type: str, q_target: float,
                       step_rad: float = DEFAULT_STEP_RAD, step_m: float = DEFAULT_STEP_M) -> Plan:
    """Grasp (:func:`grasp_pose_from_estimate`) and waypoints (:func:`plan_waypoints`) of
    joint ``joint`` from the estimated current configuration to ``q_target``."""
    if not 0 <= joint < len(estimate.q):
        raise UserError(f"joint {joint} out of range: the object has {len(estimate.q)} joint(s)")
    po = None if estimate.part_offset is None else estimate.part_offset[joint]
    q_now = float(estimate.q[joint])
    grasp = grasp_pose_from_estimate(estimate.axis_pose[joint], po, estimate.geometry, joint_type, q_now)
    origin, direction = estimate.axis(joint)
    wps = plan_waypoints(joint_type, origin, direction, q_now, q_target, grasp, step_rad, step_m)
    return Plan(joint, joint_type, q_now, float(q_target), grasp, wps, origin, direction, estimate.source)


def outward_normal(grasp_pose, joint_type: str) -> np.ndarray:
    """The panel's outward normal of a grasp pose (:func:`grasp_pose_from_estimate`): its frame's
    y axis for a door, z for a drawer."""
    check_joint_type(joint_type)
    return quat_to_matrix(checked_vector("grasp_pose", grasp_pose, 7)[3:])[:, 1 if joint_type == REVOLUTE else 2]
