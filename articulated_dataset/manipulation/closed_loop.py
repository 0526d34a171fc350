"""The closed loop: opening a joint from depth images of the simulated scene, as a mobile robot would.

:func:`closed_loop_trial` takes extra views, checks its hypotheses by looking at the handle,
finds "closed" by touch and moves in segments, re-estimating after each and refitting a
door's axis to the hand's own path (:func:`fit_axis_to_path`, :func:`joint_displacement`).
"""

from __future__ import annotations

import math

import numpy as np

from articulated_dataset.classes.registry import PRISMATIC, REVOLUTE
from articulated_dataset.core.errors import UserError
from articulated_dataset.manipulation.execution import ExecutionResult, GripperController
from articulated_dataset.manipulation.gripper import MAX_FORCE_N, SETTLE_S
from articulated_dataset.manipulation.hypotheses import (
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
from articulated_dataset.manipulation.perception import (
    HandleSighting,
    SceneCamera,
    depth_centroid,
    look_at_viewpoint,
    orbit_viewpoint,
    sight_handle,
)
from articulated_dataset.manipulation.planning import (
    DEFAULT_STEP_M,
    DEFAULT_STEP_RAD,
    ZERO_LENGTH,
    Plan,
    checked_vector,
    default_target,
    given_unit,
    outward_normal,
    plan_from_estimate,
    plan_waypoints,
    success_tolerance,
)
from articulated_dataset.manipulation.sources import DepthEstimator
from articulated_dataset.manipulation.true_object import TrueObject

#: Closed loop: at most this many axis hypotheses are checked with the wrist camera before
#: grasping, each only if its score (mean weight over the images) is at least HYPOTHESIS_MIN_SCORE.
MAX_HANDLE_LOOKS = 2
HYPOTHESIS_MIN_SCORE = 0.1
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
    d = given_unit("axis_direction", axis_direction)
    o = checked_vector("axis_origin", axis_origin, 3)
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
    a = given_unit("axis_direction", axis_direction)
    if joint_type == PRISMATIC:
        return float((np.asarray(p_to) - np.asarray(p_from)) @ a)
    o = np.asarray(axis_origin, np.float64)
    u = np.asarray(p_from) - o
    v = np.asarray(p_to) - o
    u, v = u - (u @ a) * a, v - (v @ a) * a
    return math.atan2(float(np.cross(u, v) @ a), float(u @ v))


#: When no hypothesis's handle is in its close-up: one overview of the door from
#: HANDLE_OVERVIEW_DISTANCE_M (9.5 mm per pixel), searched within HANDLE_OVERVIEW_RADIUS_M.
HANDLE_OVERVIEW_DISTANCE_M = 1.0
HANDLE_OVERVIEW_RADIUS_M = 0.5


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
       image's hypotheses (the estimate and its :attr:`ObjectKinematics.alternatives`, e.g. a closed
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
    e: ObjectKinematics | None  # an image's estimate (None: no hypothesis agrees with the axis)
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
    sighting = None  # (hypothesis rank, HandleSighting in the reference frame)
    seen: HandleSighting | None | list[tuple[float, np.ndarray]]  # a look's sighting; then (q, hand position) per image
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
        mirror_plan = None if mirror is None else plan_from_estimate(mirror, joint, jt, target, step_rad, step_m)
        ends = [plans[0].grasp_pose[:3]] + ([mirror_plan.grasp_pose[:3]] if mirror_plan is not None else [])
        rot, trans = look_at_viewpoint(np.mean(ends, axis=0), outward_normal(plans[0].grasp_pose, jt),
                                       HANDLE_OVERVIEW_DISTANCE_M)
        seen = sight_handle(camera.render(q_true0, (rot, trans)), camera.K, rng, HANDLE_OVERVIEW_RADIUS_M)
        n_images += 1
        views.append({"when": "before grasp", "viewpoint_deg": None, "wrist": True, "overview": True,
                      "handle_found": seen is not None})
        if seen is not None:
            seen = seen.transformed(rot, trans)
            rank = overview_hypothesis([c for _, c in candidates] + ([mirror] if mirror is not None else []),
                                       joint, jt, seen)
            if rank == len(candidates):  # the best hypothesis's mirror (when it was not a candidate already)
                candidates.append((0.0, mirror))  # type: ignore[arg-type]  # the mirror was a choice: not None
                plans.append(mirror_plan)  # type: ignore[arg-type]  # (as the mirror)
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

    def motion_axis(vision: ObjectKinematics) -> tuple[np.ndarray, np.ndarray]:
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
