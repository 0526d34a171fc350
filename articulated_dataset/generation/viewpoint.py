"""Where the camera stands: the paper's fixed camera, or a mobile manipulator's head camera.

``fixed`` (the default, the paper's setting): the camera is level and the sampling table's
pose (``x_m``, ``y_m``, ``z_m``, ``yaw_rad``) is the object's base in the camera frame.

``head`` (``artdata generate --camera head``): the table's pose is the object's base in the
*level frame* of a robot's head camera at the middle of the height range (x forward, y left,
z up, origin at the optical centre).  Every image then draws, from the object's own camera
stream (:data:`CAMERA_STREAM`), the camera's

* height above the floor, uniform in :data:`HEAD_HEIGHT_M`: the camera moves vertically by
  ``height - mid-range`` (a torso lift), the object stays where the table put it;
* pitch (tilt down): aimed at the centre of the object's box (as a robot's look-at
  controller does), plus a uniform offset within :data:`HEAD_AIM_JITTER_DEG`, clipped to
  :data:`HEAD_PITCH_DEG`;
* roll about the viewing direction, uniform in :data:`HEAD_ROLL_DEG` (heads pan and tilt
  only; roll comes from an uneven floor, the base's suspension and the camera's mounting).

Ranges and where they come from:

* Height 1.05-1.60 m.  Fetch (fetch_description URDF: torso_lift_joint at 0.377 m above
  base_link, lift 0-0.386 m; head_pan_joint 0.603 m and head_tilt_joint 0.058 m above it)
  tilts its head about an axis 1.04 m (torso down) to 1.42 m (torso up) above the floor,
  the camera a few centimetres higher; Kinova's MOVO (a Kinect v2 on a pan-tilt head over
  a linear-actuator torso) carries it at about 1.2-1.6 m.
* Pitch 0-60 deg down.  Fetch's head_tilt_joint allows -0.76..1.45 rad (43.5 deg up to
  83 deg down); a head camera looking at furniture a metre or more away tilts down by
  0-60 deg, and 0 keeps the paper's level view for objects at or above eye height.
* Roll within +-3 deg (a few degrees, as stated above).
* Aim offset +-10 deg: the object's centre stays within 10 deg of the optical axis, inside
  every preset's half field of view (27-30 deg vertically); the pipeline's visibility
  check still redraws a pose (and its views) that hides a moving part.

Labels stay in the camera frame: the object (not the camera) is moved in MuJoCo to its pose
in each image's camera frame, and every label is read from that model.
"""

from __future__ import annotations

import json
import math

import numpy as np

from articulated_dataset.core.camera import CAMERA_MOUNTS  # noqa: F401  (the mounts, declared with the camera)

#: Head camera height above the floor (m), pitch down and roll (deg), aim offset (deg).
HEAD_HEIGHT_M = (1.05, 1.60)
HEAD_PITCH_DEG = (0.0, 60.0)
HEAD_ROLL_DEG = (-3.0, 3.0)
HEAD_AIM_JITTER_DEG = 10.0
#: Extra SeedSequence word of the object's camera stream (the noise stream is 1).
CAMERA_STREAM = 2
#: Columns of a views array: one row per image.
VIEW_KEYS = ("height_m", "pitch_rad", "roll_rad")


def head_ranges() -> dict:
    """The head camera's ranges, as recorded in shards (``camera_mount`` attribute)."""
    return {"height_m": list(HEAD_HEIGHT_M), "pitch_deg": list(HEAD_PITCH_DEG), "roll_deg": list(HEAD_ROLL_DEG),
            "aim_jitter_deg": HEAD_AIM_JITTER_DEG}


def mid_height_m() -> float:
    """The middle of :data:`HEAD_HEIGHT_M`: the camera height the level frame (and the table's pose) refer to."""
    return 0.5 * (HEAD_HEIGHT_M[0] + HEAD_HEIGHT_M[1])


def aim_pitch_rad(pose: dict, geometry: dict, height_m: float) -> float:
    """Pitch (down, rad) that puts the centre of the object's box on the optical axis's
    vertical: the camera at ``height_m`` looks at ``(x, y, z + height / 2)`` of the level frame."""
    dz = pose["z_m"] + 0.5 * geometry["height_m"] - (height_m - mid_height_m())
    return math.atan2(-dz, pose["x_m"])


def head_views(rng: np.random.Generator | None, pose: dict, geometry: dict, n_images: int) -> np.ndarray:
    """Views (n_images, 3) = (height_m, pitch_rad, roll_rad) of one object's images.

    ``rng`` None gives the centre view (mid height, aimed pitch, no roll) for every image
    (the mean object).  Draws, in order: n heights, n aim offsets, n rolls.
    """
    lo, hi = (math.radians(a) for a in HEAD_PITCH_DEG)
    if rng is None:
        height = np.full(n_images, mid_height_m())
        jitter = np.zeros(n_images)
        roll = np.zeros(n_images)
    else:
        height = rng.uniform(*HEAD_HEIGHT_M, size=n_images)
        jitter = rng.uniform(-HEAD_AIM_JITTER_DEG, HEAD_AIM_JITTER_DEG, size=n_images)
        roll = rng.uniform(*HEAD_ROLL_DEG, size=n_images)
    pitch = np.array([aim_pitch_rad(pose, geometry, h) for h in height]) + np.radians(jitter)
    return np.stack([height, np.clip(pitch, lo, hi), np.radians(roll)], axis=1)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_in_level_frame(view) -> np.ndarray:
    """4x4 pose of the camera in the level frame: raised by ``height - mid-range``, pitched
    down about its y axis (left), then rolled about its x axis (viewing direction)."""
    height, pitch, roll = (float(v) for v in view)
    T = np.eye(4)
    T[:3, :3] = _rot_y(pitch) @ _rot_x(roll)
    T[2, 3] = height - mid_height_m()
    return T


def object_in_camera(pose: dict, view=None) -> np.ndarray:
    """4x4 pose of the object's base in the camera frame: the table's pose (level frame),
    seen from the camera of ``view`` (None: the fixed camera, i.e. the pose itself)."""
    T = np.eye(4)
    T[:3, :3] = _rot_z(pose["yaw_rad"])
    T[:3, 3] = (pose["x_m"], pose["y_m"], pose["z_m"])
    if view is None:
        return T
    return np.linalg.inv(camera_in_level_frame(view)) @ T


def is_head_mount(attrs) -> bool:
    """Whether a shard's root attributes say it was generated with the head camera."""
    text = attrs.get("camera_mount") if hasattr(attrs, "get") else None
    if text is None:
        return False
    try:
        return json.loads(text).get("mount") == "head"
    except (TypeError, ValueError, AttributeError):
        return False


def level_pose_from_camera(object_pose: np.ndarray) -> dict[str, np.ndarray]:
    """Undo a head camera's pitch and roll, given stored ``object_pose`` rows (N, 7).

    The object stands upright in the level frame, so its up axis seen from the camera is
    ``(-sin pitch, sin roll cos pitch, cos roll cos pitch)``.  Returns per image ``pitch_rad``,
    ``roll_rad`` and the object's pose in the level frame: ``x_m``, ``y_m``, ``yaw_rad`` and
    ``z_m`` (base height relative to *this image's* camera height: the table's z minus the
    camera's rise ``height - mid-range``)."""
    from articulated_dataset.core.rotations import quat_to_matrix

    p = np.atleast_2d(np.asarray(object_pose, np.float64))
    R = quat_to_matrix(p[:, 3:])
    up = R[:, :, 2]
    pitch = np.arcsin(np.clip(-up[:, 0], -1.0, 1.0))
    roll = np.arctan2(up[:, 1], up[:, 2])
    out = {"pitch_rad": pitch, "roll_rad": roll, "x_m": [], "y_m": [], "z_m": [], "yaw_rad": []}
    for k in range(len(p)):
        C = _rot_y(pitch[k]) @ _rot_x(roll[k])  # camera orientation in the level frame
        t, Rl = C @ p[k, :3], C @ R[k]
        out["x_m"].append(t[0])
        out["y_m"].append(t[1])
        out["z_m"].append(t[2])
        out["yaw_rad"].append(math.atan2(Rl[1, 0], Rl[0, 0]))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}
