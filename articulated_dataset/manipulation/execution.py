"""Simulated execution: a compliant gripper carries out a plan on the true object.

:func:`execute_plan` -- the TRUE object (rebuilt from a test split,
:func:`~articulated_dataset.manipulation.true_object.load_true_object`) is simulated in MuJoCo
while a compliant gripper (a Cartesian spring-damper between the planned pose and the grasped
point of the part, like an impedance-controlled arm) tracks the waypoints.  The reached
configuration, the gripper's force and torque and the tracking error are measured; success =
grasp on the handle (the finger rule, :func:`finger_hold`), final configuration within
:data:`~.planning.SUCCESS_TOL_RAD` / :data:`~.planning.SUCCESS_TOL_M` of the target, and
force/torque never above :data:`MAX_FORCE_N` / :data:`MAX_TORQUE_NM`.
:class:`GripperController` is the gripper step by step (the closed loop tracks segment by
segment with it); :func:`run_trial` plans from an estimate and executes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.rotations import quat_multiply, quat_to_matrix
from articulated_dataset.core.units import format_q
from articulated_dataset.generation.mujoco_scene import set_configuration
from articulated_dataset.manipulation.gripper import (
    GRASP_CAPTURE_M,
    GRIPPER_DAMPING_N_S_PER_M,
    GRIPPER_ROT_DAMPING_NM_S_PER_RAD,
    GRIPPER_ROT_STIFFNESS_NM_PER_RAD,
    GRIPPER_STIFFNESS_N_PER_M,
    MAX_FORCE_N,
    MAX_TORQUE_NM,
    SETTLE_S,
    finger_hold,
    interpolate_pose,
    minimum_jerk,
    motion_duration,
    point_box_distance,
)
from articulated_dataset.manipulation.hypotheses import ObjectKinematics
from articulated_dataset.manipulation.planning import (
    DEFAULT_STEP_M,
    DEFAULT_STEP_RAD,
    Plan,
    canonical_quat,
    default_target,
    plan_from_estimate,
    success_tolerance,
)
from articulated_dataset.manipulation.true_object import TrueObject, handle_geom


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
        """``|q_reached - q_target|`` (rad or m)."""
        return abs(self.q_reached - self.q_target)

    @property
    def reached(self) -> bool:
        """True when the configuration error is within the success tolerance of the joint type."""
        return self.error <= success_tolerance(self.joint_type)

    @property
    def within_limits(self) -> bool:
        """True when the peak force and torque stayed within :data:`MAX_FORCE_N` and :data:`MAX_TORQUE_NM`."""
        return self.max_force_n <= MAX_FORCE_N and self.max_torque_nm <= MAX_TORQUE_NM

    @property
    def success(self) -> bool:
        """True when the handle was grasped, the target reached, and the force and torque limits kept."""
        return self.grasped and self.reached and self.within_limits

    def failure_reason(self) -> str:
        """Why the trial failed, in words (no grasp, missed handle, target not reached, force or torque exceeded);
        empty when it succeeded."""
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
        """The result as plain JSON types (the trace and views excluded), with the derived error, reached,
        within_limits, success and failure."""
        return {
            "joint": self.joint, "joint_type": self.joint_type, "q_start": self.q_start, "q_target": self.q_target,
            "q_reached": self.q_reached, "error": self.error, "grasped": self.grasped,
            "grasp_error_m": self.grasp_error_m, "max_force_n": self.max_force_n, "max_torque_nm": self.max_torque_nm,
            "max_position_error_m": self.max_position_error_m, "max_rotation_error_rad": self.max_rotation_error_rad,
            "duration_s": self.duration_s, "reached": self.reached, "within_limits": self.within_limits,
            "success": self.success, "failure": "" if self.success else self.failure_reason(),
            "images_used": self.images_used, "closed_stop": self.closed_stop,
        }


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
        self.trace: dict[str, list] = {k_: [] for k_ in ("t", "q", "force", "grasp", "command")} if record else {}

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
        out[3:] = canonical_quat(gq)
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
        cmd = np.stack([interpolate_pose(waypoints, float(si)) for si in s])
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
        """The :class:`ExecutionResult` of the motion so far towards ``q_target``: the true q reached and the peak
        forces, torques and tracking errors (nothing moved if the grasp failed)."""
        joint = self.joint
        base: dict[str, Any] = dict(joint=joint, joint_type=self.obj.joint_types[joint], q_start=float(self.q0[joint]),
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


def run_trial(obj: TrueObject, estimate: ObjectKinematics, joint: int, q_target: float | None = None, *,
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
