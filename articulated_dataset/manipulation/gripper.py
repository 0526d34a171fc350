"""The simulated gripper's model: its jaws, its impedance, its limits and its motion profile.

The grasp rule of the fingers (:func:`finger_hold`: a parallel-jaw gripper holds the handle
bar only if the bar lies between its open jaws and overlaps its pads), the capture rule
(:data:`GRASP_CAPTURE_M`, :func:`point_box_distance`), the Cartesian impedance and the
force/torque limits of a trial, and the minimum-jerk time scaling of a commanded motion
(:func:`motion_duration`, :func:`interpolate_pose`).  The controller that uses them is
:class:`~articulated_dataset.manipulation.execution.GripperController`.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.manipulation.planning import checked_vector, outward_normal

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


def _interval_overlap(centre: float, half: float, window_half: float) -> float:
    """Length (m) of [centre - half, centre + half] inside [-window_half, window_half]."""
    return max(0.0, min(centre + half, window_half) - max(centre - half, -window_half))


def finger_hold(grasp_pose, box_centre, box_rot, box_half_size, joint_type: str) -> tuple[bool, float, str]:
    """Do the fingers (``GRIPPER_STROKE_M``, ``FINGER_*``) closing at ``grasp_pose`` hold the box?

    Returns ``(held, offset along the closing axis from the grasp point to the box centre (m),
    why not)``.  The box's half-extent along a unit direction u is ``sum_i |u . R_i| h_i``.
    """
    frame = quat_to_matrix(checked_vector("grasp_pose", grasp_pose, 7)[3:])
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


def point_box_distance(point, centre, rot, half_size) -> float:
    """Euclidean distance (m) from a point to a solid box (0 inside): ``|max(|R^T (p - c)| - h, 0)|``."""
    local = np.asarray(rot).T @ (np.asarray(point) - np.asarray(centre))
    return float(np.linalg.norm(np.maximum(np.abs(local) - np.asarray(half_size), 0.0)))


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


def interpolate_pose(waypoints: np.ndarray, s: float) -> np.ndarray:
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
