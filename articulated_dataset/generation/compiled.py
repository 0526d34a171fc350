"""Stage 3 of the pipeline (compile), as everyone who rebuilds an object calls it: URDF text
-> MuJoCo model -> :class:`~articulated_dataset.generation.labels.ModelInfo`.

:func:`compile_object` is the one place an object is compiled: the pipeline (every object it
renders), ``viz`` (``show --rgb`` rebuilds), ``urdf_import`` (measuring a third-party class)
and ``manipulation.load_true_object`` (the physics of a stored object).  The scene it builds
is :func:`~articulated_dataset.generation.mujoco_scene.build_model`'s (camera at the world origin,
the object's base at ``pose``).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco

from articulated_dataset.classes.base import ObjectClass
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.generation.labels import ModelInfo, model_info
from articulated_dataset.generation.mujoco_scene import build_model


@dataclass
class CompiledObject:
    """One object compiled in its scene: the MuJoCo model, its index tables and the URDF it
    was compiled from."""

    model: mujoco.MjModel
    info: ModelInfo
    urdf: str


def compile_object(obj_class: ObjectClass, urdf: str, pose: dict, camera: CameraConfig, add_context=None) -> CompiledObject:
    """Compile ``urdf`` (an object of ``obj_class``) with its base at ``pose`` (``x_m``,
    ``y_m``, ``z_m``, ``yaw_rad``; camera frame) for ``camera``, and index its joints, parts
    and geoms.  ``add_context(spec)`` adds scene and occluder bodies before compiling."""
    model = build_model(urdf, pose, camera, obj_class.base_link, add_context)
    return CompiledObject(model, model_info(model, obj_class), urdf)
