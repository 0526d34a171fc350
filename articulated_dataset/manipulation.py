"""From estimated kinematics to manipulation: grasp, waypoints and simulated execution.

The paper (Sec. 4.2) opens novel objects with a fixed grasp on the handle and end-effector
waypoints computed from the estimated kinematics, the end-effector pose and the desired
configuration.  This module does the same in three steps (formulas in docs/manipulation.md):

1. :func:`grasp_pose_from_estimate` -- the handle's grasp pose (camera frame) from an axis
   pose, part offset and configuration, by the rule the Xacro templates follow
   (``urdf_templates/common.xacro``: handles sit :data:`HANDLE_INSET_M` in from the free
   edge, standing :data:`HANDLE_STANDOFF_M` out of the panel's outer face).
2. :func:`plan_waypoints` -- end-effector poses carrying the grasp along the arc (revolute:
   rotation about the axis line) or the line (prismatic: translation along the axis) from
   the current to the target configuration, every :data:`DEFAULT_STEP_RAD` /
   :data:`DEFAULT_STEP_M`, ending exactly at the target.
3. :func:`execute_plan` -- the TRUE object (rebuilt from a test split, :func:`load_true_object`)
   is simulated in MuJoCo while a compliant gripper (a Cartesian spring-damper between the
   planned pose and the grasped point of the part, like an impedance-controlled arm) tracks
   the waypoints.  The reached configuration, the gripper's force and torque and the
   tracking error are measured; success = grasp on the handle, final configuration within
   :data:`SUCCESS_TOL_RAD` / :data:`SUCCESS_TOL_M` of the target, and force/torque never
   above :data:`MAX_FORCE_N` / :data:`MAX_TORQUE_NM`.

Poses are ``(7,)`` arrays: position (m, camera frame) + quaternion (w, x, y, z).  Planning
functions are pure (numpy in, numpy out); only the execution touches MuJoCo state.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from .errors import UserError
from .format import MASK_FIRST_PART
from .generation.labels import HANDLE_SUFFIX, ModelInfo, mat_to_quat, read_object_labels
from .registry import JOINT_TYPES, PRISMATIC, REVOLUTE
from .rotations import axis_angle_quat, quat_multiply, quat_to_matrix  # noqa: F401  (re-exported)
from .generation.scene import set_configuration
from .units import format_q, normalise

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# Template constants (mirrors of urdf_templates/common.xacro; tests check the grasp rule
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
#: The grasp closes on the handle if the planned grasp point lies within 3 cm of the
#: handle bar's surface: with the bar's half-thickness (1-1.5 cm) the bar's centre line is
#: then within ~half the 85 mm stroke of a common parallel gripper, so it still ends up
#: between the fingers.
GRASP_CAPTURE_M = 0.03
#: Parallel-jaw fingers (a common 85 mm stroke gripper).  At the grasp pose the jaws close
#: along the pose frame's x axis (across the handle bar, for every built-in template), the
#: hand approaching along minus the outward normal (:func:`outward_normal`).  The fingers hold
#: the handle only if the bar, as it really is (its box, whatever its orientation), lies
#: between the open jaws (its extent along the closing axis within +-GRIPPER_STROKE_M / 2
#: of the grasp point) and overlaps each finger pad by at least FINGER_MIN_CONTACT_M both
#: along the approach (pads FINGER_PAD_DEPTH_M deep, centred on the grasp point) and across
#: it (pads FINGER_PAD_WIDTH_M wide); :func:`finger_hold`.  The jaws centre the bar between
#: them (self-centring), so the hand then holds the bar's centre line, offset from its
#: planned tool point along the closing axis, and carries that offset along the plan.
GRIPPER_STROKE_M = 0.085
FINGER_PAD_DEPTH_M = 0.03
FINGER_PAD_WIDTH_M = 0.02
FINGER_MIN_CONTACT_M = 0.01

# --------------------------------------------------------------------------------------
# Simulated gripper (Cartesian impedance) and its limits
# --------------------------------------------------------------------------------------

#: Translational stiffness of the grasp (N/m): the upper end of the Cartesian stiffness
#: used with impedance-controlled arms (a few hundred to ~3000 N/m).  It makes the force
#: limit below a limit on path mismatch: 2000 N/m * 2.5 cm = 50 N.
GRIPPER_STIFFNESS_N_PER_M = 2000.0
#: Effective mass at the handle (kg) for which the translational damping is critical.
GRIPPER_DAMPING_REFERENCE_MASS_KG = 5.0
#: Translational damping (N s/m): critical, 2 sqrt(k m), for the reference mass (200 N s/m);
#: heavier doors are underdamped, lighter ones overdamped (all stable at the 2 ms time
#: step: b dt / m < 2 down to m = 0.2 kg).
GRIPPER_DAMPING_N_S_PER_M = 2.0 * math.sqrt(GRIPPER_STIFFNESS_N_PER_M * GRIPPER_DAMPING_REFERENCE_MASS_KG)
#: Rotational stiffness (N m/rad) and damping (N m s/rad) of the grasp: a firm wrist.
GRIPPER_ROT_STIFFNESS_NM_PER_RAD = 50.0
GRIPPER_ROT_DAMPING_NM_S_PER_RAD = 2.0
#: Force limit (N).  Opening a door along its true arc needs little force: inertia at the
#: commanded acceleration, hinge damping and, for the toaster's drop-down door, its weight
#: (true-kinematics peaks are <= 16 N over the benchmark; docs/manipulation.md).  The US
#: accessibility standard (ADA 404.2.9) caps the force to open an interior door at 22 N; we
#: allow a little over twice that.  A plan about a wrong axis stretches the grasp spring by
#: the path mismatch, so 50 N also means "the arc deviates from the true one by ~2.5 cm".
MAX_FORCE_N = 50.0
#: Torque limit (N m) at the grasp: a wrist-twist budget; a true arc needs < ~2 N m
#: (the grasp turns with the part), a tilted axis twists the wrist by the tilt angle
#: times the rotational stiffness (10 N m = 11 degrees of twist).
MAX_TORQUE_NM = 10.0
#: Peak handle acceleration of the commanded motion (m/s^2): with a minimum-jerk profile
#: the motion takes T = sqrt(MINJERK_PEAK_ACCEL * L / a) for a handle path of length L.
PEAK_HANDLE_ACCEL_M_S2 = 0.5
#: Peak acceleration of a minimum-jerk profile s(t) = 10 t^3 - 15 t^4 + 6 t^5 is
#: (10 / sqrt(3)) L / T^2.
MINJERK_PEAK_ACCEL = 10.0 / math.sqrt(3.0)
#: Shortest commanded motion (s) and the hold after the last waypoint before the
#: configuration is read (s).
MIN_DURATION_S = 1.0
SETTLE_S = 0.5
#: Gravity is ON (MuJoCo's default -9.81 m/s^2 along the camera's -z, which is the objects'
#: down): the gripper must also hold the toaster's drop-down door.  Contacts are disabled:
#: the gripper has no geometry and the object's parts only interact through their joints.
GRAVITY_ON = True
#: Vectors/quaternions shorter than this have no direction (axis, rotation): rejected.
ZERO_LENGTH = 1e-9
#: A step count |dq| / step within this of an integer is that integer (so 60 deg in 1 deg
#: steps is 60 steps, not 61, despite floating-point round-off).
STEP_COUNT_SLACK = 1e-9
#: Most waypoints one plan may have: a 0.001 deg step over a 90 deg door gives 90,000; a
#: finer spacing resolves nothing the simulation or an arm controller could use.
MAX_WAYPOINTS = 100_000
#: A rebuilt true object's axis origins must match the stored labels to 1 mm (float32
#: labels agree to ~1e-6 m; a larger gap means the data came from other templates).
REBUILD_TOL_M = 1e-3


# --------------------------------------------------------------------------------------
# Small rotation helpers (MuJoCo's quaternion routines)
# --------------------------------------------------------------------------------------

def quat_angle(a, b) -> float:
    """Angle (rad) of the rotation between two orientations: 2 acos(|<a, b>|)."""
    d = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return 2.0 * math.acos(min(1.0, d))


def _canonical(quat: np.ndarray) -> np.ndarray:
    q = np.asarray(quat, np.float64)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


# --------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------

def _check_joint_type(joint_type: str) -> None:
    if joint_type not in JOINT_TYPES:
        raise UserError(f"joint type must be one of {', '.join(JOINT_TYPES)}, got {joint_type!r}")


def _vec(name: str, v, n: int) -> np.ndarray:
    a = np.asarray(v, np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{name} has NaN/inf values: {a.tolist()}")
    return a


def _given_unit(name: str, v) -> np.ndarray:
    """A 3-vector given by the user, finite and of nonzero length, normalised."""
    return normalise(_vec(name, v, 3), min_norm=ZERO_LENGTH, what=name)


def axis_frame(axis_pose) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), R (3, 3))`` of an axis pose; ``R[:, 2]`` is the axis direction."""
    pose = _vec("axis_pose", axis_pose, 7)
    if np.linalg.norm(pose[3:]) < ZERO_LENGTH:
        raise UserError("axis_pose has a zero-length quaternion")
    return pose[:3].copy(), quat_to_matrix(pose[3:])


def default_target(joint_type: str) -> float:
    """The benchmark's opening target: 60 deg (revolute) or 0.2 m (prismatic)."""
    _check_joint_type(joint_type)
    return DEFAULT_TARGET_RAD if joint_type == REVOLUTE else DEFAULT_TARGET_M


def success_tolerance(joint_type: str) -> float:
    """Allowed |q_reached - q_target|: 5 deg in rad (revolute) or 0.02 m (prismatic)."""
    _check_joint_type(joint_type)
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
    _check_joint_type(joint_type)
    c = _vec("part_offset", part_offset, 3)
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
    _check_joint_type(joint_type)
    g = _vec("geometry", geometry, 4)
    a = _given_unit("axis_direction", axis_direction)
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
    _check_joint_type(joint_type)
    pose = _vec("pose", pose, 7)
    o = _vec("axis_origin", axis_origin, 3)
    a = _given_unit("axis_direction", axis_direction)
    out = pose.copy()
    if joint_type == PRISMATIC:
        out[:3] = pose[:3] + delta * a
        return out
    rq = axis_angle_quat(a, delta)
    rot = quat_to_matrix(rq)
    out[:3] = o + rot @ (pose[:3] - o)
    out[3:] = _canonical(quat_multiply(rq, pose[3:]))
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
    _check_joint_type(joint_type)
    origin, rot = axis_frame(axis_pose)
    if part_offset is None:
        if geometry is None:
            raise UserError("the estimate has neither part_offset nor geometry: cannot place the handle")
        part_offset = part_offset_from_geometry(geometry, rot[:, 2], joint_type)
        log.info("no part_offset: handle placed from the geometry (coarse)")
    h = handle_offset_in_axis_frame(part_offset, joint_type)
    pose0 = np.concatenate([origin + rot @ h, _canonical(mat_to_quat(rot))])
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
    _check_joint_type(joint_type)
    o = _vec("axis_origin", axis_origin, 3)
    a = _given_unit("axis_direction", axis_direction)
    pose = _vec("grasp_pose", grasp_pose, 7)
    if np.linalg.norm(pose[3:]) < ZERO_LENGTH:
        raise UserError("grasp_pose has a zero-length quaternion")
    pose[3:] = _canonical(pose[3:])
    step = step_rad if joint_type == REVOLUTE else step_m
    qs = waypoint_configurations(float(q_current), float(q_target), float(step))
    return np.stack([move_pose(pose, joint_type, o, a, dq) for dq in qs - float(q_current)])


# --------------------------------------------------------------------------------------
# Estimates (truth labels or predictions) and plans
# --------------------------------------------------------------------------------------

@dataclass
class Estimate:
    """Kinematics of one image as seen by a planner (all joints; camera frame)."""

    axis_pose: np.ndarray  # (J, 7)
    q: np.ndarray  # (J,)
    part_offset: np.ndarray | None = None  # (J, 3)
    geometry: np.ndarray | None = None  # (4,)
    source: str = "truth"
    #: this hypothesis's probability among the image's (1 for a point estimate)
    weight: float = 1.0
    #: the image's other hypotheses (e.g. the mixture's other components: a closed door hinged
    #: on the other side), each an Estimate with its own ``weight``; empty for a point estimate
    alternatives: list = field(default_factory=list)

    def axis(self, joint: int) -> tuple[np.ndarray, np.ndarray]:
        origin, rot = axis_frame(self.axis_pose[joint])
        return origin, rot[:, 2]

    def hypotheses(self) -> list["Estimate"]:
        """This estimate and its alternatives, heaviest first."""
        return sorted([self, *self.alternatives], key=lambda e: -e.weight)


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
        return {
            "joint": self.joint, "joint_type": self.joint_type, "source": self.source,
            "q_current": self.q_current, "q_target": self.q_target,
            "axis_origin": self.axis_origin.tolist(), "axis_direction": self.axis_direction.tolist(),
            "grasp_pose": self.grasp_pose.tolist(), "waypoints": self.waypoints.tolist(),
        }


def plan_from_estimate(estimate: Estimate, joint: int, joint_type: str, q_target: float,
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


# --------------------------------------------------------------------------------------
# The true object
# --------------------------------------------------------------------------------------

@dataclass
class TrueObject:
    """A test image's true object compiled in MuJoCo, with its labels."""

    class_name: str
    joint_types: tuple[str, ...]
    q_ranges: tuple[tuple[float, float], ...]
    labels: dict  # label fields of the image (numpy, float64 where numeric)
    model: mujoco.MjModel
    info: ModelInfo
    urdf: str
    pose: dict  # x_m, y_m, z_m, yaw_rad
    config: object = None  # the split's GenerationConfig (camera, noise): for rendering the scene

    @property
    def n_joints(self) -> int:
        return len(self.joint_types)

    def truth(self) -> Estimate:
        L = self.labels
        return Estimate(L["axis_pose"].astype(np.float64), L["q"].astype(np.float64),
                        L["part_offset"].astype(np.float64), L["geometry"].astype(np.float64), source="truth")

    def clip_target(self, joint: int, q_target: float) -> float:
        lo, hi = self.q_ranges[joint]
        return float(min(max(q_target, lo), hi))


def read_split_labels(split_dir: str | Path) -> tuple[Path, dict, dict]:
    """``(split folder, manifest, {field: (N, ...) array})`` of every label field of a split
    (storage order; ``class`` decoded to str)."""
    from .format import Split, one_split_dir

    split = Split(one_split_dir(split_dir))
    if not split.shards:
        raise UserError(f"{split.path}: no shards (generation not finished?)")
    labels = split.labels()
    labels["class"] = np.array([c.decode() if isinstance(c, bytes) else str(c) for c in labels["class"]])
    return split.path, split.manifest, labels


def label_row(labels: dict, index: int) -> dict:
    """The labels of one image from :func:`read_split_labels`' arrays."""
    row = {k: v[index] for k, v in labels.items()}
    row["class"] = str(row["class"])
    return row


def split_row_labels(split_dir: str | Path, index: int) -> tuple[dict, dict]:
    """``(manifest, labels)`` of image ``index`` (0-based, storage order) of a split folder."""
    path, manifest, labels = read_split_labels(split_dir)
    n = len(labels["sample_id"])
    if not 0 <= index < n:
        raise UserError(f"--index {index} out of range: {path} has {n} images (0..{n - 1})")
    return manifest, label_row(labels, index)


def load_true_object(manifest: dict, labels: dict, camera=None) -> TrueObject:
    """Rebuild the true object of an image in MuJoCo.

    Geometry and chirality come from the split's generation config
    and the pose from the stored labels (:func:`~articulated_dataset.generation.stored_sample`:
    the pipeline redraws a pose whose view hides a part); the object is compiled as the
    pipeline compiles it (:func:`~articulated_dataset.generation.compile_object`).  The
    rebuilt model's axis labels are checked against the stored ones.  ``camera`` overrides
    the image size (for figures); the physics is the same.
    """
    from .generation import GenerationConfig, compile_object, stored_sample
    from .generation.templating import object_urdf

    config = GenerationConfig.from_dict(manifest["config"])
    if config.camera.mount != "fixed":
        raise UserError(f"{config.class_name}/{config.split} was generated with --camera {config.camera.mount}; "
                        "manipulation rebuilds objects upright in the camera frame (generate with --camera fixed)")
    obj_class = config.obj_class
    sample = stored_sample(config, int(labels["object_index"]), labels["object_pose"], labels["object_yaw"])
    pose = sample.pose
    urdf = object_urdf(obj_class, sample, config.table)
    obj = compile_object(obj_class, urdf, pose, camera or config.camera)
    model, info = obj.model, obj.info
    # check: the rebuilt object has the stored axes (float32 labels: ~1e-6 m)
    data = mujoco.MjData(model)
    set_configuration(model, data, info.joint_ids, np.zeros(obj_class.n_joints))
    rebuilt = read_object_labels(model, data, info, obj_class)
    err = float(np.abs(rebuilt["axis_pose"][:, :3] - labels["axis_pose"][:, :3]).max())
    if not math.isfinite(err):
        raise UserError(f"object {int(labels['object_index'])} of {config.class_name}/{config.split}: its stored axis "
                        f"labels are not finite (a damaged shard? run 'artdata verify')")
    if err > REBUILD_TOL_M:
        raise UserError(f"object {int(labels['object_index'])} of {config.class_name}/{config.split}: the rebuilt "
                        f"model's axes differ from the stored labels by {err:.4f} m (data from another version?)")
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    if not GRAVITY_ON:
        model.opt.gravity[:] = 0.0
    return TrueObject(config.class_name, obj_class.joint_types, tuple(config.table.q), dict(labels),
                      model, info, urdf, pose, config)


def _interval_overlap(centre: float, half: float, window_half: float) -> float:
    """Length (m) of [centre - half, centre + half] inside [-window_half, window_half]."""
    return max(0.0, min(centre + half, window_half) - max(centre - half, -window_half))


def finger_hold(grasp_pose, box_centre, box_rot, box_half_size, joint_type: str) -> tuple[bool, float, str]:
    """Do the fingers (``GRIPPER_STROKE_M``, ``FINGER_*``) closing at ``grasp_pose`` hold the box?

    Returns ``(held, offset along the closing axis from the grasp point to the box centre (m),
    why not)``.  The box's half-extent along a unit direction u is ``sum_i |u . R_i| h_i``.
    """
    frame = quat_to_matrix(_vec("grasp_pose", grasp_pose, 7)[3:])
    close, normal = frame[:, 0], outward_normal(grasp_pose, joint_type)
    across = np.cross(normal, close)
    r = np.asarray(box_centre, np.float64) - np.asarray(grasp_pose[:3], np.float64)
    R, h = np.asarray(box_rot), np.asarray(box_half_size)
    half = lambda u: float(np.abs(u @ R) @ h)  # noqa: E731
    offset = float(r @ close)
    if abs(offset) + half(close) > 0.5 * GRIPPER_STROKE_M:
        return False, offset, (f"the bar does not fit between the open jaws ({100 * (abs(offset) + half(close)):.1f} cm "
                               f"from the grasp point, stroke {100 * GRIPPER_STROKE_M:.1f} cm)")
    if _interval_overlap(float(r @ normal), half(normal), 0.5 * FINGER_PAD_DEPTH_M) < FINGER_MIN_CONTACT_M:
        return False, offset, f"the finger pads miss the bar along the approach ({100 * float(r @ normal):+.1f} cm)"
    if _interval_overlap(float(r @ across), half(across), 0.5 * FINGER_PAD_WIDTH_M) < FINGER_MIN_CONTACT_M:
        return False, offset, f"the finger pads miss the bar along it ({100 * float(r @ across):+.1f} cm)"
    return True, offset, ""


def handle_geom(obj: TrueObject, joint: int) -> int:
    """Model id of the handle geom (``*_handle``) of joint ``joint``'s part."""
    info = obj.info
    ids = np.nonzero((info.geom_part == MASK_FIRST_PART + joint) & info.geom_is_handle)[0]
    if len(ids) != 1:
        raise UserError(f"{obj.class_name}: the part of joint {joint} has {len(ids)} geoms named *{HANDLE_SUFFIX} "
                        "(simulated grasping needs exactly one handle)")
    return int(ids[0])


def point_box_distance(point, centre, rot, half_size) -> float:
    """Euclidean distance (m) from a point to a solid box (0 inside): ``|max(|R^T (p - c)| - h, 0)|``."""
    local = np.asarray(rot).T @ (np.asarray(point) - np.asarray(centre))
    return float(np.linalg.norm(np.maximum(np.abs(local) - np.asarray(half_size), 0.0)))


# --------------------------------------------------------------------------------------
# Execution
# --------------------------------------------------------------------------------------

@dataclass
class ExecutionResult:
    """What the simulated robot achieved with one plan on the true object."""

    joint: int
    joint_type: str
    q_start: float  # true configuration before the motion
    q_target: float
    q_reached: float
    grasped: bool
    grasp_error_m: float  # planned grasp point to the true handle bar (0 = on the bar)
    max_force_n: float
    max_torque_nm: float
    max_position_error_m: float  # planned pose vs grasped point of the part
    max_rotation_error_rad: float
    duration_s: float
    trace: dict = field(default_factory=dict, repr=False)  # time, q, force, grasp positions
    #: Why the fingers did not hold the handle (empty when they did, or when it was out of reach).
    grasp_failure: str = ""
    #: Depth images the controller used (0: truth labels; 1: one-image open loop; more: closed loop).
    images_used: int = 0
    #: Closed loop: one entry per image (when, where from, what it gave); see :func:`closed_loop_trial`.
    views: list = field(default_factory=list, repr=False)
    #: Closed loop with ``close_first``: whether the closed stop was felt, and the true q there.
    closed_stop: dict | None = None

    @property
    def error(self) -> float:
        return abs(self.q_reached - self.q_target)

    @property
    def reached(self) -> bool:
        return self.error <= success_tolerance(self.joint_type)

    @property
    def within_limits(self) -> bool:
        return self.max_force_n <= MAX_FORCE_N and self.max_torque_nm <= MAX_TORQUE_NM

    @property
    def success(self) -> bool:
        return self.grasped and self.reached and self.within_limits

    def failure_reason(self) -> str:
        if not self.grasped and not math.isfinite(self.grasp_error_m):
            return self.grasp_failure or "no grasp was planned"
        if not self.grasped:
            if self.grasp_error_m <= GRASP_CAPTURE_M and self.grasp_failure:
                return f"the fingers did not hold the handle: {self.grasp_failure}"
            return f"missed the handle by {100 * self.grasp_error_m:.1f} cm"
        reasons = []
        if not self.reached:
            reasons.append(f"reached {format_q(self.q_reached, self.joint_type, 2)}, target {format_q(self.q_target, self.joint_type, 2)}")
        if self.max_force_n > MAX_FORCE_N:
            reasons.append(f"force {self.max_force_n:.0f} N > {MAX_FORCE_N:.0f} N")
        if self.max_torque_nm > MAX_TORQUE_NM:
            reasons.append(f"torque {self.max_torque_nm:.1f} N m > {MAX_TORQUE_NM:.0f} N m")
        return "; ".join(reasons)

    def to_dict(self) -> dict:
        return {
            "joint": self.joint, "joint_type": self.joint_type, "q_start": self.q_start, "q_target": self.q_target,
            "q_reached": self.q_reached, "error": self.error, "grasped": self.grasped,
            "grasp_error_m": self.grasp_error_m, "max_force_n": self.max_force_n, "max_torque_nm": self.max_torque_nm,
            "max_position_error_m": self.max_position_error_m, "max_rotation_error_rad": self.max_rotation_error_rad,
            "duration_s": self.duration_s, "reached": self.reached, "within_limits": self.within_limits,
            "success": self.success, "failure": "" if self.success else self.failure_reason(),
            "images_used": self.images_used, "closed_stop": self.closed_stop,
        }


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk time scaling ``s = 10 tau^3 - 15 tau^4 + 6 tau^5`` for ``tau`` in [0, 1]."""
    t = np.clip(tau, 0.0, 1.0)
    return t**3 * (10.0 - 15.0 * t + 6.0 * t * t)


def motion_duration(waypoints: np.ndarray) -> float:
    """Duration (s) of the commanded motion: ``max(MIN_DURATION_S, sqrt(c L / a_max))`` with
    L the length of the waypoint polyline (m), c = :data:`MINJERK_PEAK_ACCEL` and
    a_max = :data:`PEAK_HANDLE_ACCEL_M_S2`."""
    length = float(np.linalg.norm(np.diff(waypoints[:, :3], axis=0), axis=1).sum())
    return max(MIN_DURATION_S, math.sqrt(MINJERK_PEAK_ACCEL * length / PEAK_HANDLE_ACCEL_M_S2))


def _interpolate(waypoints: np.ndarray, s: float) -> np.ndarray:
    """Pose at path parameter s in [0, 1]: linear in position, slerp in orientation,
    between the two waypoints around ``s (K - 1)``."""
    K = len(waypoints)
    if K == 1:
        return waypoints[0].copy()
    u = s * (K - 1)
    i = min(int(u), K - 2)
    f = u - i
    a, b = waypoints[i], waypoints[i + 1]
    out = np.empty(7)
    out[:3] = (1.0 - f) * a[:3] + f * b[:3]
    qb = b[3:] if np.dot(a[3:], b[3:]) >= 0 else -b[3:]
    vel = np.zeros(3)
    mujoco.mju_subQuat(vel, qb, a[3:])
    q = a[3:].copy()
    mujoco.mju_quatIntegrate(q, vel, f)
    out[3:] = q
    return out


class GripperController:
    """The simulated compliant gripper on the true object, step by step.

    :meth:`grasp` closes it at a pose (capture rule of :data:`GRASP_CAPTURE_M`), :meth:`track`
    moves the commanded pose along waypoints (minimum-jerk time scaling) while the
    Cartesian impedance (``GRIPPER_*``) acts on the grasped point, accumulating the peak
    force, torque and tracking errors over every call.  :func:`execute_plan` is one grasp
    and one track; the closed loop (:func:`closed_loop_trial`) tracks segment by segment,
    looking at the object in between.
    """

    def __init__(self, obj: TrueObject, joint: int, q_start: np.ndarray | None = None, record: bool = False):
        self.obj = obj
        self.model = obj.model
        self.data = mujoco.MjData(self.model)
        self.joint = joint
        self.q0 = np.asarray(obj.labels["q"], np.float64) if q_start is None else np.asarray(q_start, np.float64)
        set_configuration(self.model, self.data, obj.info.joint_ids, self.q0)
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        self.body = obj.info.part_bodies[joint]
        self.grasped = False
        self.grasp_error_m = float("nan")
        self.grasp_failure = ""
        self.tool_offset_local = np.zeros(3)
        self.max_f = self.max_t = self.max_pe = self.max_re = 0.0
        self.steps = 0
        self.record = record
        self.trace = {k_: [] for k_ in ("t", "q", "force", "grasp", "command")} if record else {}

    @property
    def q(self) -> np.ndarray:
        """The object's current configuration (label order)."""
        return self.data.qpos[self.obj.info.qpos_adr].astype(np.float64).copy()

    def grasp(self, pose: np.ndarray) -> bool:
        """Close at ``pose``: held if its point lies within :data:`GRASP_CAPTURE_M` of the handle bar's box."""
        model, data = self.model, self.data
        g = handle_geom(self.obj, self.joint)
        box = (data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g])
        self.grasp_error_m = point_box_distance(pose[:3], *box)
        if self.grasp_error_m > GRASP_CAPTURE_M:
            return False
        held, offset, self.grasp_failure = finger_hold(pose, *box, self.obj.joint_types[self.joint])
        if not held:
            return False
        # the jaws centre the bar: the hand holds the point `offset` along its closing axis
        close = quat_to_matrix(pose[3:])[:, 0]
        self.tool_offset_local = np.array([offset, 0.0, 0.0])  # in the hand's frame, carried along the plan
        held_point = pose[:3] + offset * close
        rot_b = data.xmat[self.body].reshape(3, 3)
        self.p_local = rot_b.T @ (held_point - data.xpos[self.body])
        q_inv_b = np.zeros(4)
        mujoco.mju_negQuat(q_inv_b, data.xquat[self.body])
        self.quat_local = quat_multiply(q_inv_b, pose[3:])
        self.grasped = True
        return True

    def grasp_pose(self) -> np.ndarray:
        """The hand's tool pose now (7,), as the arm's own kinematics knows it: the grasped
        point of the part minus the jaws' centring offset, and the grasp orientation."""
        data = self.data
        rot_b = data.xmat[self.body].reshape(3, 3)
        out = np.empty(7)
        out[:3] = data.xpos[self.body] + rot_b @ self.p_local
        gq = np.zeros(4)
        mujoco.mju_mulQuat(gq, data.xquat[self.body], self.quat_local)
        out[3:] = _canonical(gq)
        out[:3] -= quat_to_matrix(out[3:]) @ self.tool_offset_local
        return out

    def track(self, waypoints: np.ndarray, settle_s: float = SETTLE_S, stop_force_n: float | None = None) -> bool:
        """Follow ``waypoints`` over :func:`motion_duration` (minimum jerk), then hold the last for
        ``settle_s``.  A guarded move (``stop_force_n``) stops as soon as the gripper's force
        exceeds it; returns whether it stopped so."""
        model, data, body = self.model, self.data, self.body
        dt = model.opt.timestep
        duration = motion_duration(waypoints)
        n_move = int(math.ceil(duration / dt))
        n_total = n_move + int(math.ceil(settle_s / dt))
        s = minimum_jerk(np.arange(n_total + 1) * dt / duration)
        cmd = np.stack([_interpolate(waypoints, float(si)) for si in s])
        if np.any(self.tool_offset_local):  # the held point rides with the hand, offset from the tool point
            cmd[:, :3] += np.einsum("nij,j->ni", quat_to_matrix(cmd[:, 3:]), self.tool_offset_local)
        k, b = GRIPPER_STIFFNESS_N_PER_M, GRIPPER_DAMPING_N_S_PER_M
        kr, br = GRIPPER_ROT_STIFFNESS_NM_PER_RAD, GRIPPER_ROT_DAMPING_NM_S_PER_RAD
        jacp = np.zeros((3, model.nv))
        jacr = np.zeros((3, model.nv))
        rotvec = np.zeros(3)
        w_cmd = np.zeros(3)
        gq = np.zeros(4)
        mat = np.zeros(9)
        p_local, quat_local = self.p_local, self.quat_local
        trace = self.trace
        for i in range(n_total):
            # mj_step1 computes the kinematics of the current state; the gripper's wrench is
            # then set from it and mj_step2 integrates (MuJoCo's split step for state feedback)
            mujoco.mj_step1(model, data)
            rot_b = data.xmat[body].reshape(3, 3)
            gp = data.xpos[body] + rot_b @ p_local
            mujoco.mju_mulQuat(gq, data.xquat[body], quat_local)
            mujoco.mj_jac(model, data, jacp, jacr, gp, body)
            v = jacp @ data.qvel
            w = jacr @ data.qvel
            target, nxt = cmd[i], cmd[i + 1]
            v_cmd = (nxt[:3] - target[:3]) / dt
            tq = target[3:] if np.dot(target[3:], gq) >= 0 else -target[3:]
            mujoco.mju_subQuat(rotvec, tq, gq)  # local to the grasp frame
            mujoco.mju_normalize4(gq)
            mujoco.mju_quat2Mat(mat, gq)
            theta = mat.reshape(3, 3) @ rotvec
            mujoco.mju_subQuat(w_cmd, nxt[3:] if np.dot(nxt[3:], target[3:]) >= 0 else -nxt[3:], target[3:])
            mujoco.mju_quat2Mat(mat, target[3:] / np.linalg.norm(target[3:]))
            w_cmd_world = mat.reshape(3, 3) @ w_cmd / dt
            pos_err = target[:3] - gp
            force = k * pos_err + b * (v_cmd - v)
            torque = kr * theta + br * (w_cmd_world - w)
            data.qfrc_applied[:] = 0.0
            mujoco.mj_applyFT(model, data, force, torque, gp, body, data.qfrc_applied)
            f_norm = float(np.linalg.norm(force))
            self.max_f = max(self.max_f, f_norm)
            self.max_t = max(self.max_t, float(np.linalg.norm(torque)))
            self.max_pe = max(self.max_pe, float(np.linalg.norm(pos_err)))
            self.max_re = max(self.max_re, float(np.linalg.norm(theta)))
            if self.record:
                trace["t"].append((self.steps + i) * dt)
                trace["q"].append(data.qpos[self.obj.info.qpos_adr].copy())
                trace["force"].append(float(np.linalg.norm(force)))
                trace["grasp"].append(gp.copy())
                trace["command"].append(target[:3].copy())
            mujoco.mj_step2(model, data)
            if stop_force_n is not None and f_norm > stop_force_n:
                self.steps += i + 1
                return True
        self.steps += n_total
        return False

    def result(self, q_target: float) -> ExecutionResult:
        joint = self.joint
        base = dict(joint=joint, joint_type=self.obj.joint_types[joint], q_start=float(self.q0[joint]),
                    q_target=float(q_target), grasp_error_m=self.grasp_error_m)
        if not self.grasped:
            return ExecutionResult(q_reached=float(self.q0[joint]), grasped=False, max_force_n=0.0, max_torque_nm=0.0,
                                   max_position_error_m=0.0, max_rotation_error_rad=0.0, duration_s=0.0,
                                   grasp_failure=self.grasp_failure, **base)
        trace = {k_: np.asarray(v_) for k_, v_ in self.trace.items()} if self.record else {}
        return ExecutionResult(q_reached=float(self.data.qpos[int(self.obj.info.qpos_adr[joint])]), grasped=True,
                               max_force_n=self.max_f, max_torque_nm=self.max_t, max_position_error_m=self.max_pe,
                               max_rotation_error_rad=self.max_re, duration_s=self.steps * self.model.opt.timestep,
                               trace=trace, **base)


def no_plan_result(obj: TrueObject, joint: int, q_target: float, reason: str, images_used: int = 1) -> ExecutionResult:
    """The outcome of a trial whose estimator gave no estimate (e.g. too few object pixels):
    nothing moves, the trial fails with ``reason``."""
    q0 = float(np.asarray(obj.labels["q"], np.float64)[joint])
    return ExecutionResult(joint=joint, joint_type=obj.joint_types[joint], q_start=q0, q_target=float(q_target),
                           q_reached=q0, grasped=False, grasp_error_m=float("inf"), max_force_n=0.0, max_torque_nm=0.0,
                           max_position_error_m=0.0, max_rotation_error_rad=0.0, duration_s=0.0,
                           grasp_failure=f"no estimate: {reason}", images_used=images_used)


def execute_plan(obj: TrueObject, waypoints: np.ndarray, joint: int, q_target: float, *,
                 q_start: np.ndarray | None = None, record: bool = False) -> ExecutionResult:
    """Simulate a compliant gripper tracking ``waypoints`` on the true object.

    1. The object starts at ``q_start`` (default: the image's true configuration), at rest.
    2. Grasp: the gripper closes at ``waypoints[0]``; it holds the handle if that point lies
       within :data:`GRASP_CAPTURE_M` of the true handle bar's box (else the trial fails with
       nothing moved).  The grasped point and orientation are then fixed in the part's frame.
    3. The commanded pose follows the waypoints with a minimum-jerk time scaling over
       :func:`motion_duration`, then holds the last one for :data:`SETTLE_S`.  At every 2 ms
       physics step the gripper applies, at the grasped point ``g`` of the part,
       ``F = k (p_cmd - g) + b (v_cmd - v_g)`` and ``tau = k_r theta + b_r (w_cmd - w_g)``
       (``theta``: rotation vector from the grasp's orientation to the commanded one).
    4. Reported: the joint's final configuration, the peak |F| and |tau| and the peak
       position / rotation tracking error.
    """
    ctl = GripperController(obj, joint, q_start, record)
    if ctl.grasp(waypoints[0]):
        ctl.track(waypoints)
    return ctl.result(q_target)


def run_trial(obj: TrueObject, estimate: Estimate, joint: int, q_target: float | None = None, *,
              step_rad: float = DEFAULT_STEP_RAD, step_m: float = DEFAULT_STEP_M,
              record: bool = False) -> tuple[Plan, ExecutionResult]:
    """Plan with ``estimate`` (target default: :func:`default_target`, clipped to the joint's
    range) and execute on the true object from the image's true configuration."""
    if not 0 <= joint < obj.n_joints:
        raise UserError(f"joint {joint} out of range: {obj.class_name} has {obj.n_joints} joint(s)")
    joint_type = obj.joint_types[joint]
    target = obj.clip_target(joint, default_target(joint_type) if q_target is None else q_target)
    plan = plan_from_estimate(estimate, joint, joint_type, target, step_rad, step_m)
    return plan, execute_plan(obj, plan.waypoints, joint, target, record=record)


# --------------------------------------------------------------------------------------
# Predictions
# --------------------------------------------------------------------------------------

def load_prediction_estimates(path: str | Path, class_name: str) -> tuple[str, dict[int, Estimate]]:
    """``(method, {sample_id: Estimate})`` for one class of a predictions file
    (:func:`articulated_dataset.benchmark.predictions.read_predictions`)."""
    from .benchmark.predictions import read_predictions

    attrs, per_class = read_predictions(path)
    if class_name not in per_class:
        raise UserError(f"{path}: no predictions for class {class_name!r} (has {', '.join(per_class)})")
    p = per_class[class_name]
    method = str(attrs.get("method", Path(path).stem))
    out = {}
    for i, sid in enumerate(p["sample_id"]):
        out[int(sid)] = Estimate(
            axis_pose=p["axis_pose"][i], q=p["q"][i],
            part_offset=p["part_offset"][i] if "part_offset" in p else None,
            geometry=p["geometry"][i] if "geometry" in p else None, source=method,
        )
    return method, out


# --------------------------------------------------------------------------------------
# Estimating from depth images (a model) and looking at the simulated scene
# --------------------------------------------------------------------------------------

@dataclass
class DepthEstimator:
    """A model that turns one depth image of a ``class_name`` object into an :class:`Estimate`
    in that image's camera frame: ``estimator(depth_m, K)``.  Built by :func:`make_estimator`."""

    name: str  # display / method name (dense, MDN-small, ...)
    kind: str  # dense | mdn
    class_name: str
    _fn: object = field(repr=False, default=None)

    def __call__(self, depth_m: np.ndarray, K: np.ndarray) -> Estimate:
        return self._fn(np.asarray(depth_m, np.float32), np.asarray(K, np.float64))


def make_estimator(model: str, class_name: str) -> DepthEstimator:
    """The estimator of ``--model`` (a shipped name, ``dense`` or ``mdn-small``, or a checkpoint
    path of either kind) for ``class_name``.  Unknown names, a wrong class or an unreadable
    file are a :class:`UserError` (:func:`articulated_dataset.models.resolve_model`)."""
    from .models import resolve_model

    ref = resolve_model(model, class_name)
    name = ref.name if model not in ("dense", "mdn-small") else model
    if ref.kind == "dense":
        from .estimation import estimate

        path = str(ref.path)  # resolved (and checksummed) once

        def fn(depth, K):
            return estimate_with_alternatives(estimate(depth, K, class_name, model=path), name)

        return DepthEstimator(name, "dense", class_name, fn)
    return DepthEstimator(name, "mdn", class_name, _mdn_single_image(ref.path, class_name, name))


#: Mixture components lighter than this (of the image's total weight) are not planning hypotheses.
HYPOTHESIS_MIN_WEIGHT = 0.05


def estimate_with_alternatives(e, source: str) -> Estimate:
    """A planner's :class:`Estimate` from an :class:`articulated_dataset.estimation.Estimate`: the
    heaviest mixture component, with every other component of at least
    :data:`HYPOTHESIS_MIN_WEIGHT` as an alternative (decoded like the point estimate)."""
    from .targets import TargetLayout

    main = Estimate(e.axis_pose.astype(np.float64), e.q.astype(np.float64), e.part_offset_m.astype(np.float64),
                    e.geometry.astype(np.float64), source=source)
    w = e.mixture_weights
    if w is None or len(w) < 2:
        return main
    best = int(np.argmax(w))
    main.weight = float(w[best] / w.sum())
    others = [k for k in np.argsort(-w) if k != best and w[k] / w.sum() >= HYPOTHESIS_MIN_WEIGHT]
    if others:
        d = TargetLayout.for_class(e.class_name).decode(e.mixture_means[others])
        for i, k in enumerate(others):
            main.alternatives.append(Estimate(d["axis_pose"][i].astype(np.float64), d["q"][i].astype(np.float64),
                                              d["part_offset"][i].astype(np.float64), d["geometry"][i].astype(np.float64),
                                              source=source, weight=float(w[k] / w.sum())))
    return main


def _mdn_single_image(path: Path, class_name: str, name: str):
    """One-image inference of an MDN checkpoint (the ``mean-of-best`` point estimate, decoded
    as :func:`articulated_dataset.mdn.predict.predict_split` does for a split)."""
    import torch

    from .mdn.loss import point_estimate
    from .mdn.preprocess import InputConfig, assemble_inputs, preprocess_depth
    from .mdn.checkpoint import build_model_from_checkpoint, load_checkpoint
    from .mdn.data import expand_active, shift_anchored
    from .targets import NormStats, TargetLayout

    ckpt = load_checkpoint(path)
    layout = TargetLayout.for_class(class_name)
    names = list(layout.names)
    if names != list(ckpt["layout_names"]):
        raise UserError(f"{path}: the checkpoint's target layout differs from this version's {class_name!r} layout; retrain it")
    stats = NormStats.from_dict(ckpt["norm_stats"])
    net = build_model_from_checkpoint(ckpt, "cpu")
    input_config = InputConfig.from_dict(ckpt["input_config"])
    active = np.asarray(ckpt.get("active_columns", range(len(names))), np.int64)
    anchored = [tuple(c) for c in ckpt.get("anchored_columns", [])]

    def fn(depth, K):
        planes, scalars, anchor = preprocess_depth(depth[None], input_config, K)
        with torch.no_grad():
            logits, mu, sigma = net(assemble_inputs(planes, input_config), scalars)
            est = point_estimate(logits, mu, sigma, "mean-of-best").numpy()
        est = shift_anchored(stats.denormalize(expand_active(est, active, len(names), 0.0)), anchor.numpy(), anchored, 1.0)
        d = layout.decode(est)
        return Estimate(np.asarray(d["axis_pose"][0], np.float64), np.asarray(d["q"][0], np.float64),
                        np.asarray(d["part_offset"][0], np.float64), np.asarray(d["geometry"][0], np.float64), source=name)

    return fn


def stored_image(split_dir: str | Path, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depth_m (H, W) float32, K (3, 3), mask (H, W) uint8)`` of image ``index`` (storage order) of a split."""
    from .format import Split, one_split_dir

    with Split(one_split_dir(split_dir)) as split:
        start = 0
        for sh in split.shards:
            n = len(sh)
            if index < start + n:
                return (sh.read("depth", index - start).astype(np.float32), np.asarray(sh.K, np.float64),
                        sh.read("mask", index - start))
            start += n
    raise UserError(f"--index {index} out of range: {split.path} has {start} images")


def transform_estimate(estimate: Estimate, rot: np.ndarray, trans: np.ndarray) -> Estimate:
    """An estimate made in a camera at pose ``(rot, trans)`` (camera -> reference frame:
    ``p_ref = rot p + trans``) expressed in the reference frame.  Axis origins and frames move;
    q, part offsets (axis frame) and geometry do not."""
    pose = np.array(estimate.axis_pose, np.float64)
    rq = _canonical(mat_to_quat(rot))
    for j in range(len(pose)):
        pose[j, :3] = rot @ pose[j, :3] + trans
        pose[j, 3:] = _canonical(quat_multiply(rq, pose[j, 3:]))
    return Estimate(pose, np.array(estimate.q, np.float64),
                    None if estimate.part_offset is None else np.array(estimate.part_offset, np.float64),
                    None if estimate.geometry is None else np.array(estimate.geometry, np.float64), estimate.source,
                    estimate.weight, [transform_estimate(a, rot, trans) for a in estimate.alternatives])


def orbit_viewpoint(centre, angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose ``(rot, trans)`` (camera -> reference frame) of the reference camera swung by
    ``angle_rad`` about the vertical line (reference z) through ``centre``: the robot moved
    sideways around the object at the same distance, still looking at ``centre``."""
    c = _vec("centre", centre, 3)
    rot = quat_to_matrix(axis_angle_quat(np.array([0.0, 0.0, 1.0]), angle_rad))
    return rot, c - rot @ c


class SceneCamera:
    """Depth images of the simulated true object as the robot's camera would take them.

    Renders with the dataset's renderer (:func:`articulated_dataset.render.process_renderer`,
    the camera of the split's generation config) at the object's current configuration, from
    the reference camera or another viewpoint ``(rot, trans)`` (camera -> reference frame),
    then applies the split's sensor noise model (seeded by ``rng``) and depth quantisation
    as :func:`articulated_dataset.pipeline.render_object` does.
    """

    def __init__(self, obj: TrueObject, rng: np.random.Generator):
        from .generation.render import process_renderer
        from .generation.scene import CAMERA_NAME

        if obj.config is None:
            raise UserError(f"{obj.class_name}: no generation config, so no camera to render the scene with")
        self.obj = obj
        self.rng = rng
        self.camera = obj.config.camera
        self.renderer = process_renderer(self.camera)
        self.data = mujoco.MjData(obj.model)
        self.cam_id = mujoco.mj_name2id(obj.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self.cam_pos0 = obj.model.cam_pos[self.cam_id].copy()
        self.cam_quat0 = obj.model.cam_quat[self.cam_id].copy()

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        return self.camera.K

    def render(self, q: np.ndarray, viewpoint: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Depth (H, W) float32 metres of the object at configuration ``q``."""
        model = self.obj.model
        config = self.obj.config
        if viewpoint is not None:
            rot, trans = viewpoint
            model.cam_pos[self.cam_id] = rot @ self.cam_pos0 + trans
            model.cam_quat[self.cam_id] = _canonical(quat_multiply(mat_to_quat(rot), self.cam_quat0))
        try:
            self.renderer.bind(model)
            set_configuration(model, self.data, self.obj.info.joint_ids, np.asarray(q, np.float64))
            depth, _ = self.renderer.render(self.data)
            depth = depth.copy()
        finally:
            model.cam_pos[self.cam_id] = self.cam_pos0
            model.cam_quat[self.cam_id] = self.cam_quat0
        if config.noise != "none":
            from .real.noise import get_noise_model

            depth = get_noise_model(config.noise)(depth, self.K, self.rng)
        if config.depth_quantum_m > 0:
            depth = np.round(depth / config.depth_quantum_m) * config.depth_quantum_m
        return depth.astype(np.float32)


def depth_centroid(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Mean back-projected point (m, camera frame) of the valid pixels: where the object is."""
    from .camera import backproject

    pts = backproject(depth_m, K)
    if len(pts) == 0:
        raise UserError("the depth image has no valid pixel")
    return pts.mean(axis=0)


# --------------------------------------------------------------------------------------
# Fusing estimates and the closed loop
# --------------------------------------------------------------------------------------

def fuse_estimates(estimates: list[Estimate], source: str | None = None) -> Estimate:
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
        pose[j, 3:] = _canonical(mat_to_quat(turn @ rot))
    po = [e.part_offset for e in estimates if e.part_offset is not None]
    geo = [e.geometry for e in estimates if e.geometry is not None]
    return Estimate(pose, np.median([e.q for e in estimates], axis=0), np.median(po, axis=0) if po else None,
                    np.median(geo, axis=0) if geo else None, source or estimates[0].source)


#: Two hypotheses of a joint are the same axis when their directions (signed: a door hinged
#: on the other side turns about the opposite direction) are within HYPOTHESIS_SAME_ANGLE_DEG
#: and their origins within HYPOTHESIS_SAME_DISTANCE_M.
HYPOTHESIS_SAME_ANGLE_DEG = 45.0
HYPOTHESIS_SAME_DISTANCE_M = 0.3
#: Closed loop: at most this many axis hypotheses are checked with the wrist camera before
#: grasping, each only if its score (mean weight over the images) is at least HYPOTHESIS_MIN_SCORE.
MAX_HANDLE_LOOKS = 2
HYPOTHESIS_MIN_SCORE = 0.1


def same_axis(a: Estimate, b: Estimate, joint: int) -> bool:
    """Whether two hypotheses put joint ``joint``'s axis in the same place (see HYPOTHESIS_SAME_*)."""
    (oa, da), (ob, db) = a.axis(joint), b.axis(joint)
    return bool(da @ db >= math.cos(math.radians(HYPOTHESIS_SAME_ANGLE_DEG))
                and np.linalg.norm(oa - ob) <= HYPOTHESIS_SAME_DISTANCE_M)


def group_hypotheses(estimates: list[Estimate], joint: int) -> list[tuple[float, list[Estimate]]]:
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


def mirrored_hypothesis(estimate: Estimate, joint: int) -> Estimate | None:
    """The door's panel where the estimate puts it now, hinged on its other edge and closed
    (revolute joints; None for prismatic ones or without a part offset).

    With the estimate's axis origin ``o``, frame ``(x, y, z)`` at q = 0, radius ``r`` (the part
    centre's distance from the axis, :attr:`Estimate.part_offset`) and configuration ``q``, the
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
    pose[joint, 3:] = _canonical(mat_to_quat(np.column_stack([-x_q, y_q, -rot[:, 2]])))
    po = np.array(estimate.part_offset, np.float64)
    po[joint, 2] = -po[joint, 2]
    q = np.array(estimate.q, np.float64)
    q[joint] = 0.0
    return Estimate(pose, q, po, estimate.geometry, estimate.source, weight=0.0)


def consistent_hypothesis(estimate: Estimate, reference: Estimate, joint: int, joint_type: str = REVOLUTE) -> Estimate | None:
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


#: Hand-path axis fit (closed loop, doors): the hand holds the part, so the positions it measures
#: (its own kinematics) lie on the true arc.  The circle through them (centre and radius free;
#: the plane across the estimated axis direction, which images give well) moves the axis line;
#: the estimate's origin and radius are priors of HAND_FIT_PRIOR_STD_M each, the hand's positions
#: have HAND_FIT_POINT_STD_M.  Fitted once the hand has moved HAND_FIT_MIN_TRAVEL_M.
HAND_FIT_PRIOR_STD_M = 0.1
HAND_FIT_POINT_STD_M = 0.002
HAND_FIT_MIN_TRAVEL_M = 0.01
HAND_FIT_ITERATIONS = 20
#: Closed loop, doors: each segment is moved in sub-steps of at most this much rotation, the axis
#: refitted to the hand's path before each (an axis 10 cm off turns the hand ~6 degrees off the
#: door's arc: 1 cm of spring, 20 N, over 5 degrees of a 1.1 m door); SUBSTEP_SETTLE_S between them.
CLOSED_LOOP_SUBSTEP_RAD = math.radians(5.0)
CLOSED_LOOP_SUBSTEP_SETTLE_S = 0.05


def fit_axis_to_path(points, axis_origin, axis_direction) -> np.ndarray:
    """The axis origin (3,) moved onto the centre of the circle through ``points`` (K, 3), the
    hand's positions on a door's arc, in the plane across ``axis_direction``:

        min_{c, R}  sum_i ((|p_i - c| - R) / s_p)^2 + |c - c_0|^2 / s^2 + (R - R_0)^2 / s^2

    with ``p_i`` and ``c`` in that plane, ``c_0`` = ``axis_origin``, ``R_0`` = the first point's
    distance from it, ``s_p`` = :data:`HAND_FIT_POINT_STD_M`, ``s`` = :data:`HAND_FIT_PRIOR_STD_M`
    (Gauss-Newton from ``(c_0, R_0)``).  The origin keeps its position along the axis.  Points
    spanning less than :data:`HAND_FIT_MIN_TRAVEL_M` return ``axis_origin`` unchanged."""
    d = _given_unit("axis_direction", axis_direction)
    o = _vec("axis_origin", axis_origin, 3)
    P = np.asarray(points, np.float64).reshape(-1, 3)
    if len(P) < 2 or np.linalg.norm(np.ptp(P, axis=0)) < HAND_FIT_MIN_TRAVEL_M:
        return o
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    xy = np.stack([(P - o) @ e1, (P - o) @ e2], -1)
    r0 = float(np.linalg.norm(xy[0]))
    x = np.array([0.0, 0.0, r0])  # centre (2) and radius
    sp, s = HAND_FIT_POINT_STD_M, HAND_FIT_PRIOR_STD_M
    for _ in range(HAND_FIT_ITERATIONS):
        diff = xy - x[:2]
        dist = np.maximum(np.linalg.norm(diff, axis=1), ZERO_LENGTH)
        J = np.concatenate([np.column_stack([-diff / dist[:, None], -np.ones(len(xy))]) / sp, np.eye(3) / s])
        r = np.concatenate([(dist - x[2]) / sp, (x - [0.0, 0.0, r0]) / s])
        x = x - np.linalg.solve(J.T @ J, J.T @ r)
    return o + x[0] * e1 + x[1] * e2


def joint_displacement(joint_type: str, axis_origin, axis_direction, p_from, p_to) -> float:
    """How far a point carried by the part moved from ``p_from`` to ``p_to`` in joint units:
    the signed angle about the axis line (revolute) or the distance along it (prismatic)."""
    a = _given_unit("axis_direction", axis_direction)
    if joint_type == PRISMATIC:
        return float((np.asarray(p_to) - np.asarray(p_from)) @ a)
    o = np.asarray(axis_origin, np.float64)
    u = np.asarray(p_from) - o
    v = np.asarray(p_to) - o
    u, v = u - (u @ a) * a, v - (v @ a) * a
    return math.atan2(float(np.cross(u, v) @ a), float(u @ v))


#: Looking at the handle before grasping (closed loop): a wrist camera (the dataset's
#: intrinsics) HANDLE_LOOK_DISTANCE_M out along the estimated outward normal of the planned
#: grasp, looking back at it (4.7 mm per pixel there; the search disc fits the 54 degree
#: vertical field of view).  Within HANDLE_SEARCH_RADIUS_M of the
#: view's centre the panel is the plane with most points within HANDLE_PLANE_TOL_M
#: (RANSAC, HANDLE_RANSAC_ITERATIONS draws); handle candidates stand HANDLE_PROTRUSION_M
#: (min, max) in front of it (the bar is a 3 cm deep block, urdf_templates/common.xacro).
#: The connected candidate region nearest the view's centre that is bar-shaped (at most
#: HANDLE_MAX_EXTENT_M long and HANDLE_MAX_WIDTH_M wide, at least HANDLE_MIN_PIXELS pixels)
#: is the handle; the grasp moves to its centroid, HANDLE_STANDOFF_M / 2 back towards the
#: panel (the bar's centre, as in the grasp rule).  None found: the planned grasp is kept.
HANDLE_LOOK_DISTANCE_M = 0.5
HANDLE_SEARCH_RADIUS_M = 0.25
HANDLE_PLANE_TOL_M = 0.005
HANDLE_RANSAC_ITERATIONS = 200
HANDLE_PROTRUSION_M = (0.01, 0.045)
HANDLE_MAX_EXTENT_M = 0.25
HANDLE_MAX_WIDTH_M = 0.05
HANDLE_MIN_PIXELS = 10


def outward_normal(grasp_pose, joint_type: str) -> np.ndarray:
    """The panel's outward normal of a grasp pose (:func:`grasp_pose_from_estimate`): its frame's
    y axis for a door, z for a drawer."""
    _check_joint_type(joint_type)
    return quat_to_matrix(_vec("grasp_pose", grasp_pose, 7)[3:])[:, 1 if joint_type == REVOLUTE else 2]


def look_at_viewpoint(point, normal, distance_m: float = HANDLE_LOOK_DISTANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose ``(rot, trans)`` (camera -> reference frame; camera x forward, z up) at
    ``point + distance_m * normal`` looking back along ``-normal`` at ``point``, its up as close
    to the reference z (or, for a vertical normal, the reference x) as possible."""
    n = _given_unit("normal", normal)
    fwd = -n
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < math.cos(math.radians(10.0)) else np.array([1.0, 0.0, 0.0])
    up = up - (up @ fwd) * fwd
    up /= np.linalg.norm(up)
    rot = np.column_stack([fwd, np.cross(up, fwd), up])
    return rot, _vec("point", point, 3) + distance_m * n


def find_handle(depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """The handle bar's centre (m, in the frame of the camera that took ``depth_m``) near the
    image centre, or None; method and thresholds: ``HANDLE_*`` above (:func:`sight_handle`)."""
    seen = sight_handle(depth_m, K, rng)
    return None if seen is None else seen.centre_m


@dataclass
class HandleSighting:
    """A handle bar seen in a close-up (camera frame of the image it was found in)."""

    centre_m: np.ndarray  # (3,) the bar's centre
    panel_normal: np.ndarray  # (3,) unit normal of the panel it stands on, towards the camera
    panel_points_m: np.ndarray  # (K, 3) pixels of the image on the panel's plane (at most PANEL_MAX_POINTS)

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> "HandleSighting":
        """The same sighting in the frame where this camera's pose is ``(rot, trans)``."""
        return HandleSighting(rot @ self.centre_m + trans, rot @ self.panel_normal, self.panel_points_m @ rot.T + trans)

    def panel_extent(self, direction) -> tuple[float, float]:
        """How far (m) the seen panel runs from the handle against and along ``direction``
        (between :data:`PANEL_EXTENT_PERCENTILES` of its points)."""
        if not len(self.panel_points_m):
            return 0.0, 0.0
        lo, hi = np.percentile((self.panel_points_m - self.centre_m) @ np.asarray(direction, np.float64),
                               PANEL_EXTENT_PERCENTILES)
        return float(max(-lo, 0.0)), float(max(hi, 0.0))


#: A sighting keeps at most this many panel points (every k-th); its extent is read between these
#: percentiles of them.
PANEL_MAX_POINTS = 4096
PANEL_EXTENT_PERCENTILES = (2.0, 98.0)


def sight_handle(depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator,
                 search_radius_m: float = HANDLE_SEARCH_RADIUS_M) -> HandleSighting | None:
    """The handle bar nearest the image centre within ``search_radius_m`` of the view's axis
    (:class:`HandleSighting`, camera frame of ``depth_m``: camera z is up), or None; method and
    thresholds: ``HANDLE_*`` above.  The panel's extent is that of every pixel of the image
    within :data:`HANDLE_PLANE_TOL_M` of its plane, along the plane's horizontal direction."""
    from .camera import R_CAMERA_TO_OPTICAL
    from .errors import import_optional

    ndimage = import_optional("scipy.ndimage", "the handle close-up (manipulation.find_handle)")

    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W]
    z = depth_m.astype(np.float64)
    valid = z > 0
    pts = (np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1) @ R_CAMERA_TO_OPTICAL)
    lateral = np.hypot(pts[..., 1], pts[..., 2])
    near = valid & (lateral < search_radius_m)
    P = pts[near]
    if len(P) < 3 * HANDLE_MIN_PIXELS:
        return None
    # RANSAC, all draws at once: plane through 3 distinct random points, counted inliers
    idx = np.stack([rng.choice(len(P), 3, replace=False) for _ in range(HANDLE_RANSAC_ITERATIONS)])
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    length = np.linalg.norm(normals, axis=1)
    ok = length > ZERO_LENGTH
    if not ok.any():
        return None
    a, normals = a[ok], normals[ok] / length[ok, None]
    counts = (np.abs(P @ normals.T - np.einsum("ij,ij->i", a, normals)) < HANDLE_PLANE_TOL_M).sum(axis=0)
    k = int(np.argmax(counts))
    a, nrm = a[k], normals[k]
    if nrm[0] > 0:  # towards the camera (camera x is forward, so the camera side is -x)
        nrm = -nrm
    height = np.where(valid, (pts - a) @ nrm, -np.inf)  # how far in front of the panel
    cand = near & (height >= HANDLE_PROTRUSION_M[0]) & (height <= HANDLE_PROTRUSION_M[1])
    labels, n = ndimage.label(cand)
    found = []
    for k in range(1, n + 1):
        Q = pts[labels == k]
        if len(Q) < HANDLE_MIN_PIXELS:
            continue
        centred = Q - Q.mean(axis=0)
        ext = np.sort(np.ptp(centred @ np.linalg.svd(centred, full_matrices=False)[2].T, axis=0))[::-1]
        if ext[0] > HANDLE_MAX_EXTENT_M or ext[1] > HANDLE_MAX_WIDTH_M:
            continue
        centre = Q.mean(axis=0)
        found.append((float(np.hypot(centre[1], centre[2])), centre))
    if not found:
        return None
    centre = min(found, key=lambda f: f[0])[1]
    # the visible faces are the bar's front: its centre lies half the standoff nearer the panel
    centre = centre - 0.5 * HANDLE_STANDOFF_M * nrm
    panel = pts[valid & (np.abs(height) < HANDLE_PLANE_TOL_M)]
    return HandleSighting(centre, nrm, panel[:: max(1, -(-len(panel) // PANEL_MAX_POINTS))])


#: A sighted panel normal further than this from the hypothesis's (about its axis) is not used
#: to turn the hypothesis (the plane found then faces away from where the hypothesis's door can
#: face; the handle stands on the panel, so the plane is the door's; a door believed open 35
#: degrees and 25 degrees off in yaw is 60 off).
MAX_PANEL_TURN_DEG = 90.0
#: When no hypothesis's handle is in its close-up: one overview of the door from
#: HANDLE_OVERVIEW_DISTANCE_M (9.5 mm per pixel), searched within HANDLE_OVERVIEW_RADIUS_M.
HANDLE_OVERVIEW_DISTANCE_M = 1.0
HANDLE_OVERVIEW_RADIUS_M = 0.5


def anchor_to_handle(estimate: Estimate, joint: int, joint_type: str, handle_m, panel_normal) -> Estimate:
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
        n_est, n_seen = outward_normal(grasp, joint_type), _vec("panel_normal", panel_normal, 3)
        n_est, n_seen = n_est - (n_est @ d) * d, n_seen - (n_seen @ d) * d
        if np.linalg.norm(n_est) > ZERO_LENGTH and np.linalg.norm(n_seen) > ZERO_LENGTH:
            angle = math.atan2(float(np.cross(n_est, n_seen) @ d), float(n_est @ n_seen))
            if abs(angle) <= math.radians(MAX_PANEL_TURN_DEG):
                pose[joint, 3:] = _canonical(mat_to_quat(quat_to_matrix(axis_angle_quat(d, angle)) @ rot))
                grasp = grasp_pose_from_estimate(pose[joint], po, estimate.geometry, joint_type, q)
    pose[joint, :3] += _vec("handle_m", handle_m, 3) - grasp[:3]
    return replace(estimate, axis_pose=pose, alternatives=[])


def overview_hypothesis(hypotheses: list[Estimate], joint: int, joint_type: str, seen: HandleSighting) -> int:
    """Index of the hypothesis a handle seen in an overview belongs to.  A door's handle is near
    its free edge, so its hinge is on the side of the handle where the seen panel runs further
    (across the hypothesis's axis, in the panel: :meth:`HandleSighting.panel_extent`); among the
    hypotheses whose hinge is on that side (all, for a drawer or when none is) the one whose
    planned grasp is nearest the handle."""
    grasps = [grasp_pose_from_estimate(h.axis_pose[joint], None if h.part_offset is None else h.part_offset[joint],
                                       h.geometry, joint_type, float(h.q[joint]))[:3] for h in hypotheses]

    def hinge_on_the_long_side(h: Estimate) -> bool:
        o, d = h.axis(joint)
        u = np.cross(seen.panel_normal, d)
        if np.linalg.norm(u) < ZERO_LENGTH:
            return True
        before, beyond = seen.panel_extent(u)
        return bool(((o - seen.centre_m) @ u) * (beyond - before) > 0)

    ok = [k for k, h in enumerate(hypotheses) if joint_type != REVOLUTE or hinge_on_the_long_side(h)]
    return min(ok or range(len(hypotheses)), key=lambda k: float(np.linalg.norm(grasps[k] - seen.centre_m)))


#: Closed loop defaults.  Extra views before grasping: the reference camera swung by these
#: angles about the vertical through the object's depth centroid (the robot moving sideways
#: at the same distance; +-15 degrees keeps the object's apparent yaw near the training range).
CLOSED_LOOP_VIEW_ANGLES_DEG = (-15.0, 15.0)
#: The motion is cut into segments of at most this much joint motion; after each the robot
#: takes a depth image, re-estimates, and re-plans the rest from its own measured hand pose.
CLOSED_LOOP_SEGMENT_RAD = math.radians(15.0)
CLOSED_LOOP_SEGMENT_M = 0.05
#: Hold after each segment before the image is taken (s): the part comes to rest.
CLOSED_LOOP_LOOK_SETTLE_S = 0.2
#: Stop correcting once the estimated remaining motion is below this fraction of the
#: success tolerance (the estimate cannot resolve finer corrections).
CLOSED_LOOP_DONE_FRACTION = 0.25
#: Finding "closed" by touch (closed loop, ``close_first``): after grasping, the hand closes the
#: part in guarded segments of CLOSE_SEGMENT_RAD / CLOSE_SEGMENT_M about the axis estimate
#: (each from the measured hand pose) until the force exceeds GUARD_FORCE_N (60% of the
#: force limit: the true-axis motions of the benchmark peak at 16 N) or a segment moves the
#: hand less than half of what it commanded: the part is against its closed stop (q = 0 by
#: the label convention).  At most CLOSE_MAX_SEGMENTS segments (the whole range of any
#: built-in joint).
CLOSE_SEGMENT_RAD = math.radians(5.0)
CLOSE_SEGMENT_M = 0.02
GUARD_FORCE_N = 0.6 * MAX_FORCE_N
CLOSE_MAX_SEGMENTS = 40
#: Most images one closed-loop trial may use (the stored image included).
CLOSED_LOOP_MAX_IMAGES = 12


def closed_loop_trial(obj: TrueObject, estimator: DepthEstimator, joint: int, first_depth: np.ndarray, K: np.ndarray,
                      rng: np.random.Generator, q_target: float | None = None, *,
                      view_angles_deg=CLOSED_LOOP_VIEW_ANGLES_DEG, segment: float | None = None,
                      step_rad: float = DEFAULT_STEP_RAD, step_m: float = DEFAULT_STEP_M, look_at_handle: bool = True,
                      close_first: bool = True, fit_hand_path: bool = True,
                      max_images: int = CLOSED_LOOP_MAX_IMAGES, record: bool = False) -> tuple[Plan, ExecutionResult]:
    """Open joint ``joint`` using depth images of the simulated scene, as a mobile robot would.

    1. **Before grasping**: the estimate of ``first_depth`` (the observation, 1 image) and of
       ``len(view_angles_deg)`` renders from viewpoints swung about the object's depth
       centroid (:func:`orbit_viewpoint`) are mapped into the first camera's frame.  Every
       image's hypotheses (the estimate and its :attr:`Estimate.alternatives`, e.g. a closed
       door hinged on the left or on the right) are grouped by axis (:func:`group_hypotheses`)
       and each group fused (:func:`fuse_estimates`).  For the best groups in turn (at most
       :data:`MAX_HANDLE_LOOKS`, score at least :data:`HYPOTHESIS_MIN_SCORE`) the grasp is
       planned and a close-up from a wrist camera :data:`HANDLE_LOOK_DISTANCE_M` out along the
       planned grasp's outward normal (:func:`look_at_viewpoint`, 1 image each, not given to
       the model) is searched for the handle bar (:func:`find_handle`): the first hypothesis
       whose handle is found is taken, the grasp moves onto the bar and a door's axis moves
       with the panel (by the grasp's move along the panel's outward normal: the direction
       that turns the door's arc); if none is found the
       best hypothesis's planned grasp is kept.  It closes only if it lands within
       :data:`GRASP_CAPTURE_M` of the true handle (as open loop).  From then on every image's
       estimate is its hypothesis consistent with the chosen axis (:func:`consistent_hypothesis`).
    2. **Finding "closed" by touch** (``close_first``): guarded closing segments
       (``CLOSE_SEGMENT_*``, stop at :data:`GUARD_FORCE_N` or when the hand stops following)
       until the closed stop; from then on q is the hand's motion since the stop.
    3. **During the motion**: the robot moves at most ``segment`` (default 15 deg / 5 cm) of
       joint motion along the arc / line about the current axis estimate, starting at its
       own measured hand pose (an arm knows its pose from its joint encoders); holds
       :data:`CLOSED_LOOP_LOOK_SETTLE_S`; takes a depth image from the first viewpoint and
       re-estimates.  The axis is re-fused from every image so far; for a door
       (``fit_hand_path``) the segment is moved in sub-steps of at most
       :data:`CLOSED_LOOP_SUBSTEP_RAD`, before each of which the axis line is moved onto the
       circle through the hand's measured path since the grasp (:func:`fit_axis_to_path`: the
       hand holds the part, so its path is the true arc).  The current
       configuration is the hand's motion since the closed stop or, without it, the median
       over images of ``q_i + (the hand's rotation about / travel along the axis since
       image i)``.  It stops when the estimated remaining motion is below ``CLOSED_LOOP_DONE_FRACTION`` of the success tolerance or
       ``max_images`` images are used, then holds for :data:`SETTLE_S`.

    The success criterion, force/torque limits and gripper are those of :func:`execute_plan`;
    peaks are over the whole motion (the guarded closing included).  ``result.images_used``
    counts every image the controller used (the first and the handle close-up included);
    ``result.views`` lists them; ``result.closed_stop`` tells whether the stop was felt.
    """
    if not 0 <= joint < obj.n_joints:
        raise UserError(f"joint {joint} out of range: {obj.class_name} has {obj.n_joints} joint(s)")
    if max_images < 1:
        raise UserError(f"max_images must be >= 1, got {max_images}")
    jt = obj.joint_types[joint]
    target = obj.clip_target(joint, default_target(jt) if q_target is None else q_target)
    seg = (CLOSED_LOOP_SEGMENT_RAD if jt == REVOLUTE else CLOSED_LOOP_SEGMENT_M) if segment is None else float(segment)
    if not seg > 0:
        raise UserError(f"segment must be positive, got {segment}")
    camera = SceneCamera(obj, rng)
    views: list[dict] = []
    first = estimator(first_depth, K)
    estimates = [first]
    views.append({"when": "before grasp", "viewpoint_deg": 0.0, "q_estimate": float(first.q[joint])})
    centre = depth_centroid(first_depth, K)
    q_true0 = np.asarray(obj.labels["q"], np.float64)
    for angle in list(view_angles_deg)[: max(0, max_images - 1)]:
        rot, trans = orbit_viewpoint(centre, math.radians(angle))
        try:
            e = transform_estimate(estimator(camera.render(q_true0, (rot, trans)), camera.K), rot, trans)
        except UserError as exc:  # e.g. the object left the view: the image is spent, nothing learnt
            views.append({"when": "before grasp", "viewpoint_deg": float(angle), "error": str(exc)})
            continue
        estimates.append(e)
        views.append({"when": "before grasp", "viewpoint_deg": float(angle), "q_estimate": float(e.q[joint])})
    groups = group_hypotheses(estimates, joint)
    source = f"{estimator.name} closed loop"
    candidates = [(score, fuse_estimates(members, source=source))
                  for score, members in [g for g in groups[:MAX_HANDLE_LOOKS] if g[0] >= HYPOTHESIS_MIN_SCORE] or groups[:1]]
    mirror = mirrored_hypothesis(candidates[0][1], joint) if jt == REVOLUTE else None
    if mirror is not None and not any(same_axis(mirror, c, joint) for _, c in candidates):
        candidates.append((0.0, mirror))  # the door hinged on its other edge: looked at last
    n_images = len(views)
    plans = [plan_from_estimate(c, joint, jt, target, step_rad, step_m) for _, c in candidates]
    chosen = (candidates[0][1], plans[0])  # the best hypothesis unless a look finds another's handle
    sighting = None  # (hypothesis rank, handle centre, panel normal) in the reference frame
    for rank, ((score, _), plan_k) in enumerate(zip(candidates, plans)):
        if not look_at_handle or n_images >= max_images:
            break
        rot, trans = look_at_viewpoint(plan_k.grasp_pose[:3], outward_normal(plan_k.grasp_pose, jt))
        seen = sight_handle(camera.render(q_true0, (rot, trans)), camera.K, rng)
        n_images += 1
        view = {"when": "before grasp", "viewpoint_deg": None, "wrist": True, "hypothesis": rank,
                "hypothesis_score": score, "handle_found": seen is not None}
        views.append(view)
        if seen is not None:
            sighting = (rank, seen.transformed(rot, trans))
            break
    if look_at_handle and sighting is None and n_images < max_images:
        # no handle where any hypothesis put it: one overview of the best hypothesis's panel
        # (between its handle and its mirror's), the handle given to the hypothesis it is nearest
        ends = [p.grasp_pose[:3] for p in plans[:1]]
        mirror0 = mirrored_hypothesis(candidates[0][1], joint) if jt == REVOLUTE else None
        if mirror0 is not None:
            ends.append(plan_from_estimate(mirror0, joint, jt, target, step_rad, step_m).grasp_pose[:3])
        rot, trans = look_at_viewpoint(np.mean(ends, axis=0), outward_normal(plans[0].grasp_pose, jt),
                                       HANDLE_OVERVIEW_DISTANCE_M)
        seen = sight_handle(camera.render(q_true0, (rot, trans)), camera.K, rng, HANDLE_OVERVIEW_RADIUS_M)
        n_images += 1
        views.append({"when": "before grasp", "viewpoint_deg": None, "wrist": True, "overview": True,
                      "handle_found": seen is not None})
        if seen is not None:
            seen = seen.transformed(rot, trans)
            rank = overview_hypothesis([c for _, c in candidates] + ([mirror0] if mirror0 is not None else []),
                                       joint, jt, seen)
            if rank == len(candidates):  # the best hypothesis's mirror
                candidates.append((0.0, mirror0))
                plans.append(plan_from_estimate(mirror0, joint, jt, target, step_rad, step_m))
            sighting = (rank, seen)
    if sighting is not None:
        rank, seen = sighting
        anchored = anchor_to_handle(candidates[rank][1], joint, jt, seen.centre_m, seen.panel_normal)
        plan_k = plan_from_estimate(anchored, joint, jt, target, step_rad, step_m)
        views[-1]["grasp_moved_m"] = float(np.linalg.norm(plan_k.grasp_pose[:3] - plans[rank].grasp_pose[:3]))
        views[-1]["hypothesis"] = rank
        chosen = (anchored, plan_k)
    fused, plan = chosen
    grasp = plan.grasp_pose
    estimates = [c for c in (consistent_hypothesis(e, fused, joint, jt) for e in estimates) if c is not None] or [fused]
    ctl = GripperController(obj, joint, None, record)
    if not ctl.grasp(grasp):
        res = ctl.result(target)
        res.images_used, res.views = n_images, views
        return plan, res
    hand = ctl.grasp_pose()
    # every image's (q estimate, hand position when it was taken): q now = q_i + hand motion since
    seen = [(float(e.q[joint]), hand[:3].copy()) for e in estimates]
    axis_estimates = list(estimates)
    path = [hand[:3].copy()]  # the hand's measured positions while holding the part (doors: on the arc)
    closed_hand = None  # the hand's position with the part against its closed stop (q = 0), once felt
    if close_first:
        o, d = fused.axis(joint)
        close_seg = CLOSE_SEGMENT_RAD if jt == REVOLUTE else CLOSE_SEGMENT_M
        for _ in range(CLOSE_MAX_SEGMENTS):
            start = ctl.grasp_pose()
            wps = plan_waypoints(jt, o, d, 0.0, -close_seg, start, step_rad, step_m)
            stopped = ctl.track(wps, settle_s=CLOSED_LOOP_LOOK_SETTLE_S, stop_force_n=GUARD_FORCE_N)
            path.append(ctl.grasp_pose()[:3].copy())
            moved = -joint_displacement(jt, o, d, start[:3], ctl.grasp_pose()[:3])
            if stopped or moved < 0.5 * close_seg:
                closed_hand = ctl.grasp_pose()[:3].copy()
                break
        closed_found, closed_q_true = closed_hand is not None, float(ctl.q[joint])
    tol = success_tolerance(jt)
    last_cmd = hand

    def motion_axis(vision: Estimate) -> tuple[np.ndarray, np.ndarray]:
        o, d = vision.axis(joint)
        return (fit_axis_to_path(path, o, d) if jt == REVOLUTE and fit_hand_path else o), d

    while True:
        axis = fuse_estimates(axis_estimates)
        o, d = motion_axis(axis)
        hand = ctl.grasp_pose()
        if closed_hand is not None:  # felt: q is the hand's motion since the closed stop
            q_now = joint_displacement(jt, o, d, closed_hand, hand[:3])
        else:
            q_now = float(np.median([q_i + joint_displacement(jt, o, d, p_i, hand[:3]) for q_i, p_i in seen]))
        remaining = target - q_now
        if abs(remaining) <= CLOSED_LOOP_DONE_FRACTION * tol:
            break
        step = math.copysign(min(abs(remaining), seg), remaining)
        n_sub = max(1, math.ceil(abs(step) / CLOSED_LOOP_SUBSTEP_RAD - 1e-9)) if jt == REVOLUTE and fit_hand_path else 1
        for i in range(n_sub):
            if i:
                o, d = motion_axis(axis)
            wps = plan_waypoints(jt, o, d, 0.0, step / n_sub, ctl.grasp_pose(), step_rad, step_m)
            ctl.track(wps, settle_s=CLOSED_LOOP_LOOK_SETTLE_S if i == n_sub - 1 else CLOSED_LOOP_SUBSTEP_SETTLE_S)
            path.append(ctl.grasp_pose()[:3].copy())
        last_cmd = wps[-1]
        if n_images >= max_images:
            break
        n_images += 1
        try:
            e = consistent_hypothesis(estimator(camera.render(ctl.q), camera.K), axis, joint, jt)
        except UserError as exc:
            views.append({"when": "during motion", "viewpoint_deg": 0.0, "error": str(exc), "q_true": float(ctl.q[joint])})
            continue
        if e is None:  # no hypothesis of this image is the axis being moved about: nothing learnt
            views.append({"when": "during motion", "viewpoint_deg": 0.0, "error": "no hypothesis agrees with the axis",
                          "q_true": float(ctl.q[joint])})
            continue
        axis_estimates.append(e)
        seen.append((float(e.q[joint]), ctl.grasp_pose()[:3].copy()))
        views.append({"when": "during motion", "viewpoint_deg": 0.0, "q_estimate": float(e.q[joint]),
                      "q_true": float(ctl.q[joint])})
    ctl.track(last_cmd[None], settle_s=SETTLE_S)
    res = ctl.result(target)
    res.images_used, res.views = n_images, views
    if close_first:
        res.closed_stop = {"found": closed_found, "q_true_there": closed_q_true}
    return plan, res
