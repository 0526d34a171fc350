"""From estimated kinematics to manipulation: grasp, waypoints, simulated execution and the closed loop.

The paper (Sec. 4.2) opens novel objects with a fixed grasp on the handle and end-effector
waypoints computed from the estimated kinematics; this package does the same and measures it
in simulation on the true object (formulas in docs/manipulation.md).  One job per module, in
the order a trial uses them:

* :mod:`.planning` -- the grasp rule (the handle's pose from an axis pose, part offset and
  configuration, as the Xacro templates place it), the waypoints along the arc or line, and
  :func:`plan_from_estimate` (a :class:`Plan`);
* :mod:`.estimates` -- :class:`ObjectKinematics` (one image's kinematics), moving and fusing estimates,
  and the closed loop's hypotheses (grouped by axis, the mirrored door, anchored to a seen handle);
* :mod:`.true_object` -- a test image's labels and the :class:`TrueObject` rebuilt in MuJoCo;
* :mod:`.gripper` -- the gripper's model: the finger and capture rules, its impedance, the
  force/torque limits and the motion profile;
* :mod:`.execution` -- :class:`GripperController`, :func:`execute_plan` and :func:`run_trial`
  (one image, open loop), :class:`ExecutionResult`;
* :mod:`.estimators` -- estimates from a predictions file or from a model on one depth image
  (:func:`make_estimator`);
* :mod:`.perception` -- :class:`SceneCamera` (depth images of the simulated scene), viewpoints,
  and the handle found in a close-up (:func:`sight_handle`);
* :mod:`.closed_loop` -- :func:`closed_loop_trial`: extra views, looking at the handle, closing
  by touch, and moving in segments about an axis refitted to the hand's path;
* :mod:`.image_plan` -- one image of a split planned (and simulated) as ``artdata plan`` does it,
  with its JSON record (:func:`plan_image`, :func:`simulate_image_plan`).

Poses are ``(7,)`` arrays: position (m, camera frame) + quaternion (w, x, y, z).  The names
below are the package's API (``from articulated_dataset import manipulation as M; M.run_trial``).
"""

from articulated_dataset.manipulation.closed_loop import (
    CLOSE_MAX_SEGMENTS,
    CLOSE_SEGMENT_M,
    CLOSE_SEGMENT_RAD,
    CLOSED_LOOP_DONE_FRACTION,
    CLOSED_LOOP_LOOK_SETTLE_S,
    CLOSED_LOOP_MAX_IMAGES,
    CLOSED_LOOP_SEGMENT_M,
    CLOSED_LOOP_SEGMENT_RAD,
    CLOSED_LOOP_SUBSTEP_RAD,
    CLOSED_LOOP_SUBSTEP_SETTLE_S,
    CLOSED_LOOP_VIEW_ANGLES_DEG,
    GUARD_FORCE_N,
    HAND_FIT_ITERATIONS,
    HAND_FIT_MIN_TRAVEL_M,
    HAND_FIT_POINT_STD_M,
    HAND_FIT_PRIOR_STD_M,
    HANDLE_OVERVIEW_DISTANCE_M,
    HANDLE_OVERVIEW_RADIUS_M,
    HYPOTHESIS_MIN_SCORE,
    MAX_HANDLE_LOOKS,
    closed_loop_trial,
    fit_axis_to_path,
    joint_displacement,
)
from articulated_dataset.manipulation.execution import (
    ExecutionResult,
    GripperController,
    execute_plan,
    no_plan_result,
    run_trial,
)
from articulated_dataset.manipulation.gripper import (
    FINGER_MIN_CONTACT_M,
    FINGER_PAD_DEPTH_M,
    FINGER_PAD_WIDTH_M,
    GRASP_CAPTURE_M,
    GRIPPER_DAMPING_N_S_PER_M,
    GRIPPER_DAMPING_REFERENCE_MASS_KG,
    GRIPPER_ROT_DAMPING_NM_S_PER_RAD,
    GRIPPER_ROT_STIFFNESS_NM_PER_RAD,
    GRIPPER_STIFFNESS_N_PER_M,
    GRIPPER_STROKE_M,
    MAX_FORCE_N,
    MAX_TORQUE_NM,
    MIN_DURATION_S,
    MINJERK_PEAK_ACCEL,
    PEAK_HANDLE_ACCEL_M_S2,
    SETTLE_S,
    finger_hold,
    minimum_jerk,
    motion_duration,
    point_box_distance,
)
from articulated_dataset.manipulation.hypotheses import (
    HYPOTHESIS_SAME_ANGLE_DEG,
    HYPOTHESIS_SAME_DISTANCE_M,
    MAX_PANEL_TURN_DEG,
    ObjectKinematics,
    anchor_to_handle,
    consistent_hypothesis,
    fuse_estimates,
    group_hypotheses,
    mirrored_hypothesis,
    overview_hypothesis,
    same_axis,
    transform_estimate,
)
from articulated_dataset.manipulation.image_plan import (
    CapturedObject,
    ImagePlan,
    plan_image,
    simulate_image_plan,
    usable_truth,
    write_plan_record,
)
from articulated_dataset.manipulation.perception import (
    HANDLE_LOOK_DISTANCE_M,
    HANDLE_MAX_EXTENT_M,
    HANDLE_MAX_WIDTH_M,
    HANDLE_MIN_PIXELS,
    HANDLE_PLANE_TOL_M,
    HANDLE_PROTRUSION_M,
    HANDLE_RANSAC_ITERATIONS,
    HANDLE_SEARCH_RADIUS_M,
    PANEL_EXTENT_PERCENTILES,
    PANEL_MAX_POINTS,
    HandleSighting,
    SceneCamera,
    depth_centroid,
    find_handle,
    look_at_viewpoint,
    orbit_viewpoint,
    sight_handle,
)
from articulated_dataset.manipulation.planning import (
    DEFAULT_STEP_M,
    DEFAULT_STEP_RAD,
    DEFAULT_TARGET_M,
    DEFAULT_TARGET_RAD,
    GRASP_RULE_CLASSES,
    HANDLE_INSET_M,
    HANDLE_STANDOFF_M,
    MAX_WAYPOINTS,
    PANEL_THICKNESS_M,
    STEP_COUNT_SLACK,
    SUCCESS_TOL_M,
    SUCCESS_TOL_RAD,
    ZERO_LENGTH,
    Plan,
    axis_frame,
    default_target,
    grasp_pose_from_estimate,
    handle_offset_in_axis_frame,
    move_pose,
    outward_normal,
    part_offset_from_geometry,
    plan_from_estimate,
    plan_waypoints,
    quat_angle,
    success_tolerance,
    waypoint_configurations,
)
from articulated_dataset.manipulation.sources import (
    HYPOTHESIS_MIN_WEIGHT,
    DepthEstimator,
    estimate_with_alternatives,
    load_prediction_estimates,
    make_estimator,
)
from articulated_dataset.manipulation.true_object import (
    GRAVITY_ON,
    REBUILD_TOL_M,
    PlannableObject,
    TrueObject,
    handle_geom,
    label_row,
    load_true_object,
    read_split_labels,
    split_row_labels,
    stored_image,
)

__all__ = [
    "CLOSED_LOOP_DONE_FRACTION", "CLOSED_LOOP_LOOK_SETTLE_S", "CLOSED_LOOP_MAX_IMAGES", "CLOSED_LOOP_SEGMENT_M",
    "CLOSED_LOOP_SEGMENT_RAD", "CLOSED_LOOP_SUBSTEP_RAD", "CLOSED_LOOP_SUBSTEP_SETTLE_S",
    "CLOSED_LOOP_VIEW_ANGLES_DEG", "CLOSE_MAX_SEGMENTS", "CLOSE_SEGMENT_M", "CLOSE_SEGMENT_RAD", "CapturedObject",
    "DEFAULT_STEP_M", "DEFAULT_STEP_RAD", "DEFAULT_TARGET_M", "DEFAULT_TARGET_RAD", "DepthEstimator", "ObjectKinematics",
    "ExecutionResult", "FINGER_MIN_CONTACT_M", "FINGER_PAD_DEPTH_M", "FINGER_PAD_WIDTH_M", "GRASP_CAPTURE_M",
    "GRAVITY_ON", "GRIPPER_DAMPING_N_S_PER_M", "GRIPPER_DAMPING_REFERENCE_MASS_KG", "GRIPPER_ROT_DAMPING_NM_S_PER_RAD",
    "GRIPPER_ROT_STIFFNESS_NM_PER_RAD", "GRIPPER_STIFFNESS_N_PER_M", "GRIPPER_STROKE_M", "GUARD_FORCE_N",
    "GRASP_RULE_CLASSES", "GripperController", "HANDLE_INSET_M", "HANDLE_LOOK_DISTANCE_M", "HANDLE_MAX_EXTENT_M", "HANDLE_MAX_WIDTH_M",
    "HANDLE_MIN_PIXELS", "HANDLE_OVERVIEW_DISTANCE_M", "HANDLE_OVERVIEW_RADIUS_M", "HANDLE_PLANE_TOL_M",
    "HANDLE_PROTRUSION_M", "HANDLE_RANSAC_ITERATIONS", "HANDLE_SEARCH_RADIUS_M", "HANDLE_STANDOFF_M",
    "HAND_FIT_ITERATIONS", "HAND_FIT_MIN_TRAVEL_M", "HAND_FIT_POINT_STD_M", "HAND_FIT_PRIOR_STD_M",
    "HYPOTHESIS_MIN_SCORE", "HYPOTHESIS_MIN_WEIGHT", "HYPOTHESIS_SAME_ANGLE_DEG", "HYPOTHESIS_SAME_DISTANCE_M",
    "HandleSighting", "ImagePlan", "MAX_FORCE_N", "MAX_HANDLE_LOOKS", "MAX_PANEL_TURN_DEG", "MAX_TORQUE_NM",
    "MAX_WAYPOINTS", "MINJERK_PEAK_ACCEL", "MIN_DURATION_S", "PANEL_EXTENT_PERCENTILES", "PANEL_MAX_POINTS",
    "PANEL_THICKNESS_M", "PEAK_HANDLE_ACCEL_M_S2", "Plan", "PlannableObject", "REBUILD_TOL_M", "SETTLE_S",
    "STEP_COUNT_SLACK", "SUCCESS_TOL_M", "SUCCESS_TOL_RAD", "SceneCamera", "TrueObject", "ZERO_LENGTH",
    "anchor_to_handle", "axis_frame", "closed_loop_trial", "consistent_hypothesis", "default_target", "depth_centroid",
    "estimate_with_alternatives", "execute_plan", "find_handle", "finger_hold", "fit_axis_to_path", "fuse_estimates",
    "grasp_pose_from_estimate", "group_hypotheses", "handle_geom", "handle_offset_in_axis_frame", "joint_displacement",
    "label_row", "load_prediction_estimates", "load_true_object", "look_at_viewpoint", "make_estimator",
    "minimum_jerk", "mirrored_hypothesis", "motion_duration", "move_pose", "no_plan_result", "orbit_viewpoint",
    "outward_normal", "overview_hypothesis", "part_offset_from_geometry", "plan_from_estimate", "plan_image",
    "plan_waypoints", "point_box_distance", "quat_angle", "read_split_labels", "run_trial", "same_axis",
    "sight_handle", "simulate_image_plan", "split_row_labels", "stored_image", "success_tolerance",
    "transform_estimate", "usable_truth", "waypoint_configurations", "write_plan_record",
]


def __getattr__(name):
    """``Estimate``, :class:`ObjectKinematics`'s name before 0.2, until 0.3 (with a warning)."""
    if name == "Estimate":
        from articulated_dataset.manipulation import hypotheses

        return hypotheses.Estimate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
