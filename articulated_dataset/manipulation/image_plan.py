"""One image's plan, as ``artdata plan`` makes it: the object, the kinematics, the plan, the outcome.

:func:`plan_image` takes image ``index`` of a split (generated, or an ingested real capture:
planning only), the kinematics to plan from (the truth labels, a predictions file matched by
``sample_id``, or a model run on the stored depth image) and the target, and returns an
:class:`ImagePlan` whose :attr:`ImagePlan.record` is the JSON record ``artdata plan --out``
writes.  :func:`simulate_image_plan` executes the plan on the true object (open loop) or runs
the closed loop, and adds the outcome to the record; :func:`write_plan_record` writes it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from articulated_dataset.classes.registry import REVOLUTE
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.units import parse_quantity
from articulated_dataset.manipulation.closed_loop import closed_loop_trial
from articulated_dataset.manipulation.execution import ExecutionResult, execute_plan
from articulated_dataset.manipulation.gripper import GRASP_CAPTURE_M, MAX_FORCE_N, MAX_TORQUE_NM
from articulated_dataset.manipulation.hypotheses import ObjectKinematics
from articulated_dataset.manipulation.planning import (
    DEFAULT_STEP_M,
    DEFAULT_STEP_RAD,
    Plan,
    check_grasp_rule,
    default_target,
    plan_from_estimate,
    success_tolerance,
)
from articulated_dataset.manipulation.sources import load_prediction_estimates, make_estimator
from articulated_dataset.manipulation.true_object import (
    PlannableObject,
    load_true_object,
    split_row_labels,
    stored_image,
)


class CapturedObject(PlannableObject):
    """An image of an ingested real split: its class's joints and its labels, no model to
    simulate (the same interface as :class:`~articulated_dataset.manipulation.TrueObject`
    for planning)."""

    def __init__(self, class_name: str, labels: dict):
        from articulated_dataset.classes.registry import get_class

        obj_class = get_class(class_name)
        check_grasp_rule(obj_class.name)
        self.class_name = obj_class.name
        self.joint_types = obj_class.joint_types
        self.q_ranges = tuple(obj_class.table.q)
        self.labels = labels
        self.n_joints = obj_class.n_joints


def usable_truth(estimate: ObjectKinematics, joint: int, where: str) -> ObjectKinematics:
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
                        f"capture's labels file); add them there or plan from {option('predictions_path')}")
    if not offset_ok:
        estimate.part_offset = None
    return estimate


@dataclass
class ImagePlan:
    """What :func:`plan_image` made of one image: the object (a :class:`TrueObject`, or a
    :class:`CapturedObject` for a real capture), its labels, the plan and its JSON record."""

    obj: PlannableObject
    manifest: dict
    labels: dict
    index: int
    joint: int
    joint_type: str
    q_target: float  # as asked (or the default), before clipping to the joint's range
    clipped: float  # the target planned for
    step: float  # waypoint spacing (rad or m)
    plan: Plan
    record: dict
    estimator: object = None  # the DepthEstimator of a --model plan
    depth: np.ndarray | None = None  # its stored depth image and K
    K: np.ndarray | None = None
    from_labels: bool = True  # planned from the truth labels (no image used)

    @property
    def sample_id(self) -> int:
        """The image's ``sample_id`` label."""
        return int(self.labels["sample_id"])


def plan_image(data_dir, index: int, *, joint: int = 0, predictions_path=None, model: str | None = None,
               closed_loop: bool = False, simulate: bool = False, target: str | None = None, step: str | None = None,
               prepare_model: Callable[[], object] | None = None, urdf=None, mesh_root=None,
               hint: str = "") -> ImagePlan:
    """Plan the opening of joint ``joint`` of image ``index`` (storage order) of the split at
    ``data_dir``.  ``target`` and ``step`` are quantities with units (``60deg``, ``0.2m``; default
    :func:`default_target` clipped to the joint's range and 1 deg / 1 cm).  The kinematics come
    from ``model`` (run on the stored depth image; ``prepare_model`` is called before it is
    loaded), else ``predictions_path``, else the truth labels.  ``urdf`` / ``mesh_root``: the files a
    third-party URDF object is rebuilt from, and ``hint``: what ends the refusal without them
    (:func:`load_true_object`).  Mistakes are a :class:`UserError`."""
    manifest, labels = split_row_labels(data_dir, index)
    real = "real" in manifest
    if real and simulate:
        raise UserError(f"{data_dir}: image {index} is a real capture; there is no object model to simulate "
                        f"({option('simulate')} needs a generated split)")
    if real and urdf is not None:
        raise UserError(f"{data_dir}: image {index} is a real capture; there is no object model to rebuild from "
                        f"the URDF {urdf}")
    obj = (CapturedObject(manifest["class_name"], labels) if real else
           load_true_object(manifest, labels, split_dir=data_dir, urdf=urdf, mesh_root=mesh_root, hint=hint))
    if not 0 <= joint < obj.n_joints:
        raise UserError(f"{option('joint')} {joint} out of range: {obj.class_name} has {obj.n_joints} joint(s) "
                        f"(0..{obj.n_joints - 1})")
    joint_type = obj.joint_types[joint]

    def _quantity(text: str, quantity: str) -> float:
        value, kind = parse_quantity(text)
        if kind != joint_type:
            raise UserError(f"{quantity} {text!r} is a {kind} quantity but joint {joint} of {obj.class_name} "
                            f"is {joint_type}")
        return value

    q_target = default_target(joint_type) if target is None else _quantity(target, option("target"))
    if step is None:
        step_value = DEFAULT_STEP_RAD if joint_type == REVOLUTE else DEFAULT_STEP_M
    else:
        step_value = _quantity(step, option("step"))
        if step_value <= 0:
            raise UserError(f"{option('step')} must be positive, got {step!r}")
    clipped = obj.clip_target(joint, q_target)

    sample_id = int(labels["sample_id"])
    estimator = depth = K = None
    if model is not None:
        if prepare_model is not None:
            prepare_model()
        estimator = make_estimator(model, obj.class_name)
        depth, K, mask = stored_image(data_dir, index)
        if real:
            if mask.any():  # a capture's stored depth may show the scene around the object
                depth = np.where(mask > 0, depth, 0.0).astype(np.float32)
        estimate = estimator(depth, K)
        if estimate.q.shape[0] != obj.n_joints:
            raise UserError(f"{option('model')} {model}: {estimate.q.shape[0]} joints estimated for {obj.class_name} "
                            f"({obj.n_joints} expected)")
    elif predictions_path is None:
        estimate = usable_truth(obj.truth(), joint, f"image {index} of {obj.class_name}/{manifest['split']}")
    else:
        _method, estimates = load_prediction_estimates(predictions_path, obj.class_name)
        if sample_id not in estimates:
            raise UserError(f"{predictions_path}: no prediction for sample_id {sample_id} "
                            f"(image {index} of {obj.class_name}/{manifest['split']})")
        estimate = estimates[sample_id]
        if estimate.q.shape[0] != obj.n_joints:
            raise UserError(f"{predictions_path}: {estimate.q.shape[0]} joints predicted for {obj.class_name} "
                            f"({obj.n_joints} expected)")

    plan = plan_from_estimate(estimate, joint, joint_type, clipped, step_rad=step_value, step_m=step_value)
    record = {
        "class": obj.class_name, "split": manifest["split"], "data": str(Path(data_dir)), "index": index,
        "object_index": int(labels["object_index"]), "image_index": int(labels["image_index"]),
        "sample_id": sample_id, "predictions": None if predictions_path is None else str(predictions_path),
        "model": model, "closed_loop": bool(closed_loop),
        "units": {"position": "m (camera frame)", "quaternion": "w, x, y, z", "q": "rad (revolute) | m (prismatic)"},
        "step": step_value, "q_true": float(labels["q"][joint]) if np.isfinite(labels["q"][joint]) else None,
        **plan.to_dict(),
    }
    return ImagePlan(obj, manifest, labels, index, joint, joint_type, q_target, clipped, step_value, plan, record,
                     estimator, depth, K, from_labels=estimator is None and predictions_path is None)


def simulate_image_plan(image: ImagePlan, *, closed_loop: bool = False, touch: bool = True, seed: int = 0) -> ExecutionResult:
    """Execute ``image``'s plan on the true object (or, ``closed_loop``, open the joint with
    :func:`closed_loop_trial` from the model's image, its sensor noise seeded by ``seed``,
    finding "closed" by touch unless ``touch`` is False); the outcome and the limits it was
    judged by go into ``image.record`` (and a closed loop's plan replaces ``image.plan``)."""
    record, joint = image.record, image.joint
    if closed_loop:
        # (a closed loop runs a --model plan of a simulated object: a TrueObject, its estimator, depth and K)
        plan, result = closed_loop_trial(image.obj, image.estimator, joint, image.depth, image.K,  # type: ignore[arg-type]
                                         np.random.default_rng(seed), image.clipped,
                                         step_rad=image.step, step_m=image.step, close_first=touch)
        image.plan = plan
        record.update(plan.to_dict())
        record["closed_loop"] = result.views
    else:
        result = execute_plan(image.obj, image.plan.waypoints, joint, image.clipped)  # type: ignore[arg-type]  # a TrueObject
        result.images_used = 0 if image.from_labels else 1
    record["simulation"] = result.to_dict()
    record["limits"] = {"max_force_n": MAX_FORCE_N, "max_torque_nm": MAX_TORQUE_NM,
                        "tolerance": success_tolerance(image.joint_type), "grasp_capture_m": GRASP_CAPTURE_M}
    return result


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_plan_record(path, record: dict) -> None:
    """Write a plan's record as JSON (written to a temporary sibling, then renamed into place)."""
    from articulated_dataset.core.safeio import atomic_write_text, ensure_dir

    ensure_dir(Path(path).parent)
    atomic_write_text(path, json.dumps(record, indent=1, default=_json_default) + "\n")  # full disk: one line
