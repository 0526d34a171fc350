"""Stage 5 of the pipeline: read labels from the compiled MuJoCo model.

Labels are never recomputed from the sampled parameters: joint anchors and axes come from
MuJoCo's kinematics (``xanchor``, ``xaxis``), part extents from the compiled geoms, the
object pose from the base body, the configuration from ``qpos``.  All quantities are in
the camera frame (= MuJoCo world frame), metres and radians.

Definitions (see docs/format.md):

* part centre: centre of the axis-aligned box, in the part's body frame, bounding the
  part's non-handle geoms (geoms named ``*_handle`` are excluded), at q = 0.
* ``axis_origin``: revolute: the point on the joint axis nearest the part centre (for the
  built-in templates, the hinge line at the middle of the door's extent along the axis);
  prismatic: the centre of the part's leading face (extreme along +axis) at q = 0.
* ``axis_direction``: unit joint axis; positive q opens.
* ``axis_pose``: origin + quaternion (w, x, y, z) of the axis frame: z = direction;
  x = perpendicular from the axis towards the part centre (revolute) or the object's up
  direction made perpendicular to z (prismatic); y = z x x.
* ``part_offset``: part centre at q = 0 in the axis frame.
* ``geometry``: (depth, width, height) of the box bounding the body's geoms in the object
  frame, and chirality: 1 if joint 0's hinge line lies on the right (-y) of its part's centre,
  seen from the front, for sided classes (the built-in cabinet, microwave, refrigerator, and
  every third-party object) whose joint 0 is revolute with an axis within 45 deg of the
  object's up direction; else 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from articulated_dataset.classes.base import PRISMATIC, ObjectClass
from articulated_dataset.core.rotations import matrix_to_quat
from articulated_dataset.core.units import normalise
from articulated_dataset.format.schema import MASK_BACKGROUND, MASK_BODY, MASK_FIRST_PART, visible_pixels  # noqa: F401  (declared with the format)
from articulated_dataset.generation.mujoco_scene import OBJECT_PREFIX, object_joint_ids, set_configuration

HANDLE_SUFFIX = "_handle"
#: A hinge has a side (left or right, the chirality) when joint 0's axis is within 45 deg of the
#: object's up direction: a door's; a lid's or a drop-down door's horizontal hinge has none.
SIDE_MIN_VERTICAL_COS = float(np.cos(np.pi / 4))

_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


@dataclass
class ModelInfo:
    """Index tables of a compiled object model, built once per model."""

    joint_ids: np.ndarray  # (J,) model joint ids, label order
    joint_types: tuple[str, ...]
    qpos_adr: np.ndarray  # (J,)
    base_body: int
    geom_part: np.ndarray  # (ngeom,) uint8 mask value of each geom
    geom_is_handle: np.ndarray  # (ngeom,) bool
    part_bodies: list[int]  # (J,) body id of each moving part

    def mask_from_geoms(self, geom_id: np.ndarray) -> np.ndarray:
        """Map a geom-id image (-1 = background) to mask values (uint8)."""
        lut = np.concatenate([[MASK_BACKGROUND], self.geom_part]).astype(np.uint8)
        return lut[geom_id + 1]


def model_info(model: mujoco.MjModel, obj_class: ObjectClass) -> ModelInfo:
    """Index tables (:class:`ModelInfo`) of a compiled model of ``obj_class``: joint ids and qpos addresses, base
    body, each geom's mask value and handle flag, each moving part's body. A template joint whose type differs
    from the registry's, or a missing base link, raises ValueError."""
    joint_ids = object_joint_ids(model, [j.name for j in obj_class.joints])
    for jid, spec in zip(joint_ids, obj_class.joints):
        expected = mujoco.mjtJoint.mjJNT_SLIDE if spec.type == PRISMATIC else mujoco.mjtJoint.mjJNT_HINGE
        if model.jnt_type[jid] != expected:
            raise ValueError(f"joint {spec.name!r}: template type differs from registry type {spec.type!r}")
    base_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, OBJECT_PREFIX + obj_class.base_link)
    if base_body < 0:
        raise ValueError(f"base link {obj_class.base_link!r} not found in the model")
    part_of_body = np.zeros(model.nbody, np.uint8)
    body_joint = {int(model.jnt_bodyid[jid]): j for j, jid in enumerate(joint_ids)}
    for b in range(model.nbody):
        # walk up to the first ancestor moved by one of the object's joints
        a = b
        while a != 0 and a not in body_joint:
            a = model.body_parentid[a]
        if a in body_joint:
            part_of_body[b] = MASK_FIRST_PART + body_joint[a]
        elif _is_descendant(model, b, base_body):
            part_of_body[b] = MASK_BODY
    geom_part = part_of_body[model.geom_bodyid]
    names = [model.geom(i).name for i in range(model.ngeom)]
    geom_is_handle = np.array([n.endswith(HANDLE_SUFFIX) for n in names], dtype=bool)
    return ModelInfo(
        joint_ids=joint_ids,
        joint_types=obj_class.joint_types,
        qpos_adr=model.jnt_qposadr[joint_ids].copy(),
        base_body=base_body,
        geom_part=geom_part,
        geom_is_handle=geom_is_handle,
        part_bodies=[int(model.jnt_bodyid[j]) for j in joint_ids],
    )


def _is_descendant(model: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body != 0:
        if body == ancestor:
            return True
        body = model.body_parentid[body]
    return ancestor == 0


def _geom_points_local(model: mujoco.MjModel, g: int) -> np.ndarray:
    """Points spanning geom ``g``'s extent in its own frame: a mesh's vertices (MuJoCo stores
    them in the geom frame), else the corners of the geom's local bounding box (exact for
    boxes, the primitives of the built-in classes)."""
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        mesh = model.geom_dataid[g]
        start = model.mesh_vertadr[mesh]
        return model.mesh_vert[start:start + model.mesh_vertnum[mesh]].astype(np.float64)
    centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
    return centre + _BOX_CORNERS * half


def geom_corners_world(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray) -> np.ndarray:
    """World coordinates of points spanning each geom's extent (see :func:`_geom_points_local`)."""
    out = [data.geom_xpos[g] + _geom_points_local(model, g) @ data.geom_xmat[g].reshape(3, 3).T for g in geoms]
    return np.concatenate(out, axis=0)


def _box_in_frame(points_world: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max corner of the points' bounding box expressed in frame (pos, rot)."""
    local = (points_world - pos) @ rot
    return local.min(axis=0), local.max(axis=0)


def _frame_unit(v: np.ndarray) -> np.ndarray:
    """An axis-frame vector normalised; zero length is a bug (a degenerate model), not the user's."""
    return normalise(v, min_norm=1e-12, what="degenerate axis frame: a vector", error=ValueError)


mat_to_quat = matrix_to_quat  # quaternion (w, x, y, z), w >= 0, of a rotation matrix


def read_object_labels(model: mujoco.MjModel, data: mujoco.MjData, info: ModelInfo, obj_class: ObjectClass) -> dict:
    """Per-object labels read at q = 0 (they do not change with q). Leaves ``data`` at q = 0."""
    J = len(info.joint_ids)
    set_configuration(model, data, info.joint_ids, np.zeros(J))
    base_pos = data.xpos[info.base_body].copy()
    base_rot = data.xmat[info.base_body].reshape(3, 3).copy()
    base_quat = data.xquat[info.base_body].copy()
    up = base_rot[:, 2]

    axis_origin = np.zeros((J, 3))
    axis_direction = np.zeros((J, 3))
    axis_pose = np.zeros((J, 7))
    part_offset = np.zeros((J, 3))
    centres = np.zeros((J, 3))
    for j, jid in enumerate(info.joint_ids):
        part = info.part_bodies[j]
        geoms = np.nonzero((info.geom_part == MASK_FIRST_PART + j) & ~info.geom_is_handle)[0]
        pos, rot = data.xpos[part], data.xmat[part].reshape(3, 3)
        lo, hi = _box_in_frame(geom_corners_world(model, data, geoms), pos, rot)
        centre = centres[j] = pos + rot @ (0.5 * (lo + hi))
        anchor, a = data.xanchor[jid].copy(), _frame_unit(data.xaxis[jid].copy())
        if info.joint_types[j] == PRISMATIC:
            # leading face: extreme of the part's box along +a (axis expressed in part frame)
            a_local = rot.T @ a
            half = 0.5 * (hi - lo)
            origin = centre + a * float(np.abs(a_local) @ half)
            x = _frame_unit(up - (up @ a) * a)
        else:
            origin = anchor + ((centre - anchor) @ a) * a
            x = _frame_unit(centre - origin)
        y = np.cross(a, x)
        r_axis = np.stack([x, y, a], axis=1)
        axis_origin[j], axis_direction[j] = origin, a
        axis_pose[j, :3], axis_pose[j, 3:] = origin, mat_to_quat(r_axis)
        part_offset[j] = r_axis.T @ (centre - origin)

    body_geoms = np.nonzero(info.geom_part == MASK_BODY)[0]
    lo, hi = _box_in_frame(geom_corners_world(model, data, body_geoms), base_pos, base_rot)
    size = hi - lo
    chirality = 0
    if obj_class.sided and info.joint_types[0] != PRISMATIC and abs(axis_direction[0] @ up) >= SIDE_MIN_VERTICAL_COS:
        # the hinge line's side of the part centre (both at q = 0), across the object (y)
        hinge_y = (axis_origin[0] - centres[0]) @ base_rot[:, 1]
        chirality = int(hinge_y < 0)
    return {
        "axis_origin": axis_origin,
        "axis_direction": axis_direction,
        "axis_pose": axis_pose,
        "part_offset": part_offset,
        "object_pose": np.concatenate([base_pos, base_quat]),
        "object_yaw": float(np.arctan2(base_rot[1, 0], base_rot[0, 0])),
        "geometry": np.array([size[0], size[1], size[2], chirality], dtype=np.float64),
    }


def read_configuration(data: mujoco.MjData, info: ModelInfo) -> np.ndarray:
    """The object's current configuration q (J,) from ``qpos``."""
    return data.qpos[info.qpos_adr].copy()
