"""``artdata plan``: grasp + waypoints that open one test object, optionally simulated."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np

from ..errors import UserError
from ..units import format_q, parse_quantity


def _fmt_vec(v, digits: int = 4) -> str:
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


class _CapturedObject:
    """An image of an ingested real split: its class's joints and its labels, no model to
    simulate (the same interface as :class:`~articulated_dataset.manipulation.TrueObject`
    for planning)."""

    def __init__(self, class_name: str, labels: dict):
        from ..registry import get_class

        obj_class = get_class(class_name)
        self.class_name = obj_class.name
        self.joint_types = obj_class.joint_types
        self.q_ranges = tuple(obj_class.table.q)
        self.labels = labels
        self.n_joints = obj_class.n_joints

    def truth(self):
        from .. import manipulation as M

        L = self.labels
        return M.Estimate(L["axis_pose"].astype(np.float64), L["q"].astype(np.float64),
                          L["part_offset"].astype(np.float64), L["geometry"].astype(np.float64), source="truth")

    def clip_target(self, joint: int, q_target: float) -> float:
        lo, hi = self.q_ranges[joint]
        return float(min(max(q_target, lo), hi))


def _usable_truth(estimate, joint: int, where: str):
    """The truth labels of ``joint`` with every field planning needs, else a :class:`UserError`
    naming those that are NaN (real captures: not given in their labels file).  A NaN
    ``part_offset`` with a known ``geometry`` places the handle from the geometry."""
    missing = []
    if not np.isfinite(estimate.axis_pose[joint]).all():
        missing.append("axis_pose")
    if not np.isfinite(estimate.q[joint]):
        missing.append("q")
    offset_ok = estimate.part_offset is not None and np.isfinite(estimate.part_offset[joint]).all()
    geometry_ok = estimate.geometry is not None and np.isfinite(estimate.geometry).all()
    if not (offset_ok or geometry_ok):
        missing.append("part_offset (or geometry)")
    if missing:
        raise UserError(f"{where}: the truth labels of joint {joint} lack {', '.join(missing)} (NaN: not in the "
                        f"capture's labels file); add them there or plan from --predictions")
    if not offset_ok:
        estimate.part_offset = None
    return estimate


@click.command("plan")
@click.option("--data", "data_dir", type=click.Path(), required=True,
              help="A generated split folder (<root>/<class>/<split>) holding the object.")
@click.option("--index", type=int, required=True, help="Image index in the split (0-based, storage order).")
@click.option("--joint", type=int, default=0, show_default=True, help="Joint to actuate (label order).")
@click.option("--predictions", "predictions_path", type=click.Path(), default=None,
              help="Plan from this predictions.h5 (matched by sample_id) instead of the truth labels.")
@click.option("--model", "model", default=None,
              help="Estimate the kinematics from the image's stored depth with this model: a shipped model "
                   "(dense, mdn-small) or a checkpoint from 'artdata train'.")
@click.option("--closed-loop", is_flag=True,
              help="With --model and --simulate: look again while opening (extra views before grasping, one image "
                   "after each segment of the motion) and correct the plan; reports the images used.")
@click.option("--no-touch", is_flag=True,
              help="Closed loop without first closing the part by touch (configuration from the images only).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the sensor noise of the closed loop's rendered images (splits generated with --noise).")
@click.option("--threads", type=int, default=None, help="CPU threads for the model (default: torch's).")
@click.option("--target", default=None,
              help="Target configuration with units: 60deg, 1.0rad (revolute), 0.2m, 20cm (prismatic). "
                   "Default 60deg / 0.2m; clipped to the joint's range.")
@click.option("--step", default=None, help="Waypoint spacing with units (default 1deg / 1cm).")
@click.option("--simulate", is_flag=True, help="Execute the waypoints on the true object in MuJoCo and report the outcome.")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), default=None, help="Write the plan (and outcome) as JSON.")
@click.option("--quiet", "-q", is_flag=True, help="Do not list the waypoints.")
def plan_cmd(data_dir, index, joint, predictions_path, model, closed_loop, no_touch, seed, threads, target, step,
             simulate, out_path, quiet):
    """Plan end-effector waypoints that open joint JOINT of image INDEX's object.

    The handle's grasp pose is estimated from the (true or predicted) axis pose, part offset
    and configuration; the waypoints carry it along the arc (revolute) or line (prismatic) to
    the target.  See docs/manipulation.md.
    """
    from .. import manipulation as M
    from ..registry import REVOLUTE

    if index < 0:
        raise UserError(f"--index must be >= 0, got {index}")
    if model is not None and predictions_path is not None:
        raise UserError("give either --model (estimate from the image) or --predictions (a predictions file), not both")
    if closed_loop and (model is None or not simulate):
        raise UserError("--closed-loop needs --model (it re-estimates from new images) and --simulate (the scene it looks at)")
    if out_path:
        from ..safeio import check_can_create

        check_can_create(out_path)  # before any work: a read-only or missing place is one line now
    if model is not None and threads is not None and threads <= 0:
        raise UserError(f"--threads must be positive, got {threads}")
    manifest, labels = M.split_row_labels(data_dir, index)
    real = "real" in manifest
    if real and simulate:
        raise UserError(f"{data_dir}: image {index} is a real capture; there is no object model to simulate "
                        f"(--simulate needs a generated split)")
    obj = _CapturedObject(manifest["class_name"], labels) if real else M.load_true_object(manifest, labels)
    if not 0 <= joint < obj.n_joints:
        raise UserError(f"--joint {joint} out of range: {obj.class_name} has {obj.n_joints} joint(s) (0..{obj.n_joints - 1})")
    joint_type = obj.joint_types[joint]

    def _quantity(text: str, option: str) -> float:
        value, kind = parse_quantity(text)
        if kind != joint_type:
            raise UserError(f"{option} {text!r} is a {kind} quantity but joint {joint} of {obj.class_name} is {joint_type}")
        return value

    q_target = M.default_target(joint_type) if target is None else _quantity(target, "--target")
    if step is None:
        step_value = M.DEFAULT_STEP_RAD if joint_type == REVOLUTE else M.DEFAULT_STEP_M
    else:
        step_value = _quantity(step, "--step")
        if step_value <= 0:
            raise UserError(f"--step must be positive, got {step!r}")
    clipped = obj.clip_target(joint, q_target)

    sample_id = int(labels["sample_id"])
    estimator = depth = K = None
    if model is not None:
        from .options import prepare_torch

        prepare_torch(threads)
        estimator = M.make_estimator(model, obj.class_name)
        depth, K, mask = M.stored_image(data_dir, index)
        if real:
            if mask.any():  # a capture's stored depth may show the scene around the object
                depth = np.where(mask > 0, depth, 0.0).astype(np.float32)
        estimate = estimator(depth, K)
        if estimate.q.shape[0] != obj.n_joints:
            raise UserError(f"--model {model}: {estimate.q.shape[0]} joints estimated for {obj.class_name} "
                            f"({obj.n_joints} expected)")
    elif predictions_path is None:
        estimate = _usable_truth(obj.truth(), joint, f"image {index} of {obj.class_name}/{manifest['split']}")
    else:
        _method, estimates = M.load_prediction_estimates(predictions_path, obj.class_name)
        if sample_id not in estimates:
            raise UserError(f"{predictions_path}: no prediction for sample_id {sample_id} "
                            f"(image {index} of {obj.class_name}/{manifest['split']})")
        estimate = estimates[sample_id]
        if estimate.q.shape[0] != obj.n_joints:
            raise UserError(f"{predictions_path}: {estimate.q.shape[0]} joints predicted for {obj.class_name} "
                            f"({obj.n_joints} expected)")

    plan = M.plan_from_estimate(estimate, joint, joint_type, clipped,
                                step_rad=step_value, step_m=step_value)
    fq = lambda v: format_q(v, joint_type, 2)  # noqa: E731
    click.echo(f"{obj.class_name}/{manifest['split']} image {index} (object {int(labels['object_index'])}, "
               f"view {int(labels['image_index'])}, sample_id {sample_id}), joint {joint} ({joint_type}); "
               f"kinematics: {plan.source}")
    click.echo(f"axis: origin {_fmt_vec(plan.axis_origin)} m, direction {_fmt_vec(plan.axis_direction)}")
    click.echo(f"grasp: position {_fmt_vec(plan.grasp_pose[:3])} m, quaternion {_fmt_vec(plan.grasp_pose[3:])}")
    note = "" if clipped == q_target else f" (clipped from {fq(q_target)} to the joint range)"
    click.echo(f"q: {fq(plan.q_current)} -> {fq(plan.q_target)}{note}: {len(plan.waypoints)} waypoints, "
               f"step {fq(step_value)}")
    if not quiet:
        click.echo("    k      x_m      y_m      z_m       qw       qx       qy       qz")
        for k, wp in enumerate(plan.waypoints):
            click.echo(f"{k:5d} " + " ".join(f"{x:8.4f}" for x in wp))

    record = {
        "class": obj.class_name, "split": manifest["split"], "data": str(Path(data_dir)), "index": index,
        "object_index": int(labels["object_index"]), "image_index": int(labels["image_index"]),
        "sample_id": sample_id, "predictions": None if predictions_path is None else str(predictions_path),
        "model": model, "closed_loop": bool(closed_loop),
        "units": {"position": "m (camera frame)", "quaternion": "w, x, y, z", "q": "rad (revolute) | m (prismatic)"},
        "step": step_value, "q_true": float(labels["q"][joint]) if np.isfinite(labels["q"][joint]) else None,
        **plan.to_dict(),
    }
    if simulate and closed_loop:
        plan, result = M.closed_loop_trial(obj, estimator, joint, depth, K, np.random.default_rng(seed), clipped,
                                           step_rad=step_value, step_m=step_value, close_first=not no_touch)
        record.update(plan.to_dict())
        record["closed_loop"] = result.views
        wrist = [v for v in result.views if v.get("wrist")]
        look = "" if not wrist else (f"; the handle close-up moved the grasp {100 * wrist[0]['grasp_moved_m']:.1f} cm"
                                     if wrist[0]["handle_found"] else "; no handle found in the close-up")
        click.echo(f"closed loop: {result.images_used} depth images used "
                   f"({sum(v['when'] == 'before grasp' for v in result.views)} before grasping, "
                   f"{sum(v['when'] == 'during motion' for v in result.views)} during the motion){look}"
                   + ("" if result.closed_stop is None else
                      "; closed stop felt" if result.closed_stop["found"] else "; closed stop not found"))
    elif simulate:
        result = M.execute_plan(obj, plan.waypoints, joint, clipped)
        result.images_used = 0 if estimator is None and predictions_path is None else 1
    if simulate:
        record["simulation"] = result.to_dict()
        record["limits"] = {"max_force_n": M.MAX_FORCE_N, "max_torque_nm": M.MAX_TORQUE_NM,
                            "tolerance": M.success_tolerance(joint_type), "grasp_capture_m": M.GRASP_CAPTURE_M}
        verdict = "SUCCESS" if result.success else f"FAILURE ({result.failure_reason()})"
        click.echo(f"simulation: true q {fq(result.q_start)} -> reached {fq(result.q_reached)} "
                   f"(target {fq(result.q_target)}, error {fq(result.error)}, tolerance {fq(M.success_tolerance(joint_type))}); "
                   f"grasp {100 * result.grasp_error_m:.1f} cm from the handle; max force {result.max_force_n:.1f} N "
                   f"(limit {M.MAX_FORCE_N:.0f}), max torque {result.max_torque_nm:.2f} N m (limit {M.MAX_TORQUE_NM:.0f}), "
                   f"max tracking error {100 * result.max_position_error_m:.2f} cm / "
                   f"{math.degrees(result.max_rotation_error_rad):.2f} deg: {verdict}")
    if out_path:
        from ..safeio import atomic_write_text, ensure_dir

        ensure_dir(Path(out_path).parent)
        atomic_write_text(out_path, json.dumps(record, indent=1, default=_json_default) + "\n")  # full disk: one line
        click.echo(f"wrote {out_path}")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


COMMANDS = [plan_cmd]
