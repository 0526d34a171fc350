"""Stage 3 of the pipeline (compile): a MuJoCo scene (camera + object at a pose), compiled.

The camera is MuJoCo's world origin: it looks down +x with +z up, so MuJoCo world
coordinates *are* camera-frame coordinates (see :mod:`articulated_dataset.core.camera`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.mujoco_support import check_supported_mujoco

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


def build_model(urdf_xml: str, pose: dict, camera: CameraConfig, base_link: str = "base", add_context=None) -> mujoco.MjModel:
    """Compile a scene holding the camera and the URDF object with its base at ``pose``.

    ``pose`` has ``x_m``, ``y_m``, ``z_m`` (base centre, camera frame) and ``yaw_rad``.
    ``add_context(spec)``, if given, adds scene and occluder bodies before compiling
    (:mod:`articulated_dataset.scenes`, :mod:`articulated_dataset.occluders`).  A MuJoCo release
    outside the supported range is a :class:`~articulated_dataset.core.errors.RenderError` (one line).
    """
    check_supported_mujoco()
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
    cam = spec.worldbody.add_camera(name=CAMERA_NAME, pos=[0.0, 0.0, 0.0], xyaxes=list(CAMERA_XYAXES), fovy=camera.vfov_deg)
    if camera.intrinsics is not None:
        _set_intrinsics(cam, camera)
    spec.worldbody.add_light(name="key", pos=[0.0, 0.5, 1.0], dir=[1.0, -0.3, -0.6], type=int(mujoco.mjtLightType.mjLIGHT_DIRECTIONAL))
    frame = spec.worldbody.add_frame(pos=[pose["x_m"], pose["y_m"], pose["z_m"]], quat=list(yaw_quaternion(pose["yaw_rad"])))
    frame.attach_body(base, OBJECT_PREFIX, "")
    if add_context is not None:
        add_context(spec)
    return spec.compile()


def yaw_quaternion(yaw_rad: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by ``yaw_rad`` about +z (MuJoCo's
    ``mju_axisAngle2Quat``: bit for bit what the package computed before by hand)."""
    quat = np.empty(4)
    mujoco.mju_axisAngle2Quat(quat, _Z_AXIS, float(yaw_rad))
    return quat


_Z_AXIS = np.array([0.0, 0.0, 1.0])


def _set_intrinsics(cam, camera: CameraConfig) -> None:
    """Give MuJoCo's camera the matrix K of ``camera`` (any fx, fy, cx, cy): a sensor of
    W x H length units (1 unit = 1 px), focal lengths fx, fy and the principal point's
    offset from the sensor centre.  MuJoCo counts that offset with the opposite sign of
    OpenCV's (cx - centre, cy - centre) in both axes (checked against projected points by
    tests/generation/test_robot_camera.py and every label test run with a preset)."""
    W, H = camera.width_px, camera.height_px
    fx, fy, cx, cy = camera.intrinsics_px
    cam.resolution = [W, H]
    cam.sensor_size = [float(W), float(H)]
    cam.focal_length = [fx, fy]
    cam.principal_length = [-(cx + 0.5 - W / 2.0), -(cy + 0.5 - H / 2.0)]


#: The pose ``build_model`` is given when the object is then placed per image (head camera).
ORIGIN_POSE = {"x_m": 0.0, "y_m": 0.0, "z_m": 0.0, "yaw_rad": 0.0}


class ObjectPlacer:
    """Moves a compiled object (built at :data:`ORIGIN_POSE`) to any pose in the camera
    frame by setting its root body's position and orientation in the model; the next
    :func:`set_configuration` updates every body, geom and label read from the model."""

    def __init__(self, model: mujoco.MjModel, base_body: int):
        if model.body_parentid[base_body] != 0:
            raise ValueError("the object's base body must be a child of the world body")
        self.model, self.body = model, base_body
        self._pos = model.body_pos[base_body].copy()  # the root's own offset in the object frame
        self._quat = model.body_quat[base_body].copy()

    def place(self, T_camera_object: np.ndarray) -> None:
        """Put the object frame at the 4x4 pose ``T_camera_object``."""
        from articulated_dataset.core.rotations import matrix_to_quat

        R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
        quat = np.empty(4)
        mujoco.mju_mulQuat(quat, matrix_to_quat(R), self._quat)
        self.model.body_pos[self.body] = t + R @ self._pos
        self.model.body_quat[self.body] = quat


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
