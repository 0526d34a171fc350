"""The true object of a test image: its labels read from the split, rebuilt in MuJoCo.

:func:`read_split_labels` / :func:`split_row_labels` read a split's labels (through
:class:`articulated_dataset.format.Split`), :func:`stored_image` one of its depth images, and
:func:`load_true_object` compiles the image's object as the generator did
(:func:`~articulated_dataset.generation.compile_object`) and checks its axes against the labels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format import MASK_FIRST_PART
from articulated_dataset.generation.labels import HANDLE_SUFFIX, ModelInfo, read_object_labels
from articulated_dataset.generation.mujoco_scene import set_configuration
from articulated_dataset.manipulation.hypotheses import ObjectKinematics
from articulated_dataset.manipulation.planning import check_grasp_rule

if TYPE_CHECKING:
    from articulated_dataset.generation.config import GenerationConfig

#: Gravity is ON (MuJoCo's default -9.81 m/s^2 along the camera's -z, which is the objects'
#: down): the gripper must also hold the toaster's drop-down door.  Contacts are disabled:
#: the gripper has no geometry and the object's parts only interact through their joints.
GRAVITY_ON = True


#: A rebuilt true object's axis origins must match the stored labels to 1 mm (float32
#: labels agree to ~1e-6 m; a larger gap means the data came from other templates).
REBUILD_TOL_M = 1e-3
#: Farthest stored object position (m) an object is rebuilt at (generated scenes span < 20 m).
MAX_OBJECT_DISTANCE_M = 100.0


class PlannableObject:
    """What planning needs of an object, for a :class:`TrueObject` and for a real capture's
    (:class:`~articulated_dataset.manipulation.image_plan.CapturedObject`): its labels
    (``self.labels``) as the truth, and its joints' ranges (``self.q_ranges``) for the target."""

    class_name: str
    labels: dict
    q_ranges: tuple[tuple[float, float], ...]

    def truth(self) -> ObjectKinematics:
        """The object's labels as an estimate (source ``truth``)."""
        L = self.labels
        return ObjectKinematics(L["axis_pose"].astype(np.float64), L["q"].astype(np.float64),
                        L["part_offset"].astype(np.float64), L["geometry"].astype(np.float64), source="truth")

    def clip_target(self, joint: int, q_target: float) -> float:
        """``q_target`` clipped to joint ``joint``'s range (rad or m)."""
        lo, hi = self.q_ranges[joint]
        return float(min(max(q_target, lo), hi))


@dataclass
class TrueObject(PlannableObject):
    """A test image's true object compiled in MuJoCo, with its labels."""

    class_name: str
    joint_types: tuple[str, ...]
    q_ranges: tuple[tuple[float, float], ...]
    labels: dict  # label fields of the image (numpy, float64 where numeric)
    model: mujoco.MjModel
    info: ModelInfo
    urdf: str
    pose: dict  # x_m, y_m, z_m, yaw_rad
    config: GenerationConfig | None = None  # the split's config (camera, noise): for rendering the scene

    @property
    def n_joints(self) -> int:
        """Number of joints of the object."""
        return len(self.joint_types)


def read_split_labels(split_dir: str | Path) -> tuple[Path, dict, dict]:
    """``(split folder, manifest, {field: (N, ...) array})`` of every label field of a split
    (storage order; ``class`` decoded to str)."""
    from articulated_dataset.format import Split, one_split_dir

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
        raise UserError(f"{option('index')} {index} out of range: {path} has {n} images (0..{n - 1})")
    return manifest, label_row(labels, index)


def load_true_object(manifest: dict, labels: dict, camera=None, split_dir: str | Path | None = None, *,
                     urdf: str | Path | None = None, mesh_root: str | Path | None = None, hint: str = "") -> TrueObject:
    """Rebuild the true object of an image in MuJoCo.

    Geometry and chirality come from the split's generation config
    and the pose from the stored labels (:func:`~articulated_dataset.generation.stored_sample`:
    the pipeline redraws a pose whose view hides a part); the object is compiled as the
    pipeline compiles it (:func:`~articulated_dataset.generation.compile_object`).  The
    rebuilt model's axis labels are checked against the stored ones.  ``camera`` overrides
    the image size (for figures); the physics is the same.  ``split_dir``: the split folder the
    manifest belongs to; a third-party object is rebuilt only from files inside it (else one line
    ending with ``hint``), or from ``urdf`` (and ``mesh_root``), files the caller names, when their
    sha256 is the one the split recorded
    (:func:`~articulated_dataset.generation.objects.stored_object_config`).
    """
    from articulated_dataset.generation import compile_object, stored_sample
    from articulated_dataset.generation.objects import stored_object_config
    from articulated_dataset.generation.templating import object_urdf

    config = stored_object_config(manifest.get("config"), split_dir, "plan", hint, urdf=urdf, mesh_root=mesh_root)
    check_grasp_rule(config.class_name)
    if config.camera.mount != "fixed":
        raise UserError(f"{config.class_name}/{config.split} was generated with {option('camera_mount')} "
                        f"{config.camera.mount}; manipulation rebuilds objects upright in the camera frame (generate "
                        f"with {option('camera_mount')} fixed)")
    obj_class = config.obj_class
    index = int(labels["object_index"])
    position = np.asarray(labels["object_pose"], np.float64).reshape(-1)[:3]
    yaw = float(np.asarray(labels["object_yaw"], np.float64).reshape(-1)[0])
    if index < 0 or not (np.isfinite(position).all() and math.isfinite(yaw)) \
            or np.abs(position).max() > MAX_OBJECT_DISTANCE_M:  # (else a ValueError deep in the rebuild: a traceback)
        raise UserError(f"object {index} of {config.class_name}/{config.split}: its stored object index or pose "
                        f"(object_index, object_pose, object_yaw) is not valid (a damaged shard? run 'artdata verify')")
    sample = stored_sample(config, index, labels["object_pose"], labels["object_yaw"])
    pose = sample.pose
    urdf = object_urdf(obj_class, sample, config.table)  # type: ignore[arg-type]  # GenerationConfig sets table
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
    return TrueObject(config.class_name, obj_class.joint_types, tuple(config.table.q), dict(labels),  # type: ignore[union-attr]  # (as above)
                      model, info, urdf, pose, config)


def handle_geom(obj: TrueObject, joint: int) -> int:
    """Model id of the handle geom (``*_handle``) of joint ``joint``'s part."""
    info = obj.info
    ids = np.nonzero((info.geom_part == MASK_FIRST_PART + joint) & info.geom_is_handle)[0]
    if len(ids) != 1:
        raise UserError(f"{obj.class_name}: the part of joint {joint} has {len(ids)} geoms named *{HANDLE_SUFFIX} "
                        "(simulated grasping needs exactly one handle)")
    return int(ids[0])


def stored_image(split_dir: str | Path, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depth_m (H, W) float32, K (3, 3), mask (H, W) uint8)`` of image ``index`` (storage order) of a split."""
    from articulated_dataset.format import Split, one_split_dir

    with Split(one_split_dir(split_dir)) as split:
        start = 0
        for sh in split.shards:
            n = len(sh)
            if index < start + n:
                return (sh.read("depth", index - start).astype(np.float32), np.asarray(sh.K, np.float64),
                        sh.read("mask", index - start))
            start += n
    raise UserError(f"{option('index')} {index} out of range: {split.path} has {start} images")
