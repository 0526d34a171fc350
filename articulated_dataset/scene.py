"""Stage 3 of the pipeline: assemble a MuJoCo scene (camera + object at a pose) and compile it.

The camera is MuJoCo's world origin: it looks down +x with +z up, so MuJoCo world
coordinates *are* camera-frame coordinates (see :mod:`articulated_dataset.camera`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from .camera import CameraConfig
from .errors import UserError
from .sampling import yaw_quaternion

#: Name prefix of every element of the attached object (bodies, joints, geoms).
OBJECT_PREFIX = "object/"
CAMERA_NAME = "camera"
#: Near and far clipping distances of the depth buffer (m).  Nothing closer than 5 cm or
#: farther than 12 m is rendered (the tables place objects 0.3-4.3 m away).
NEAR_CLIP_M = 0.05
FAR_CLIP_M = 12.0
#: MuJoCo camera orientation: its x axis (image right) = world -y, its y axis (image up) =
#: world +z; it looks along its -z axis = world +x.
CAMERA_XYAXES = (0.0, -1.0, 0.0, 0.0, 0.0, 1.0)


def build_model(urdf_xml: str, pose: dict, camera: CameraConfig, base_link: str = "base") -> mujoco.MjModel:
    """Compile a scene holding the camera and the URDF object with its base at ``pose``.

    ``pose`` has ``x_m``, ``y_m``, ``z_m`` (base centre, camera frame) and ``yaw_rad``.
    """
    try:
        child = mujoco.MjSpec.from_string(urdf_xml)
    except Exception as exc:  # MuJoCo raises ValueError with the parser's message
        raise UserError(f"MuJoCo cannot load the URDF: {exc}") from None
    base = child.body(base_link)
    if base is None:
        raise UserError(f"URDF has no link named {base_link!r}")
    spec = mujoco.MjSpec()
    spec.stat.extent = 1.0  # so that znear/zfar below are in metres
    spec.visual.map.znear = NEAR_CLIP_M
    spec.visual.map.zfar = FAR_CLIP_M
    spec.visual.global_.offwidth = camera.width_px
    spec.visual.global_.offheight = camera.height_px
    # No multisampling: segmentation rendering disables it anyway (identical pixels), and
    # resolving a 4x offscreen buffer on every read-back cost 40% of the frame time.
    spec.visual.quality.offsamples = 0
    spec.worldbody.add_camera(name=CAMERA_NAME, pos=[0.0, 0.0, 0.0], xyaxes=list(CAMERA_XYAXES), fovy=camera.vfov_deg)
    spec.worldbody.add_light(name="key", pos=[0.0, 0.5, 1.0], dir=[1.0, -0.3, -0.6], type=int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL))
    frame = spec.worldbody.add_frame(
        pos=[pose["x_m"], pose["y_m"], pose["z_m"]], quat=list(yaw_quaternion(pose["yaw_rad"]))
    )
    frame.attach_body(base, OBJECT_PREFIX, "")
    return spec.compile()


def object_joint_ids(model: mujoco.MjModel, joint_names) -> np.ndarray:
    """Model joint ids of the object's articulated joints, in label order."""
    ids = []
    for name in joint_names:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, OBJECT_PREFIX + name)
        if jid < 0:
            raise UserError(f"joint {name!r} not found in the compiled model")
        ids.append(jid)
    return np.asarray(ids, dtype=np.int64)


def set_configuration(model: mujoco.MjModel, data: mujoco.MjData, joint_ids: np.ndarray, q) -> None:
    """Set the object's joints to ``q`` (label order) and update body and camera poses.

    (``mj_kinematics`` alone leaves camera frames unset; ``mj_camlight`` computes them.)
    """
    data.qpos[model.jnt_qposadr[joint_ids]] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)
