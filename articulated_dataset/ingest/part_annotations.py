"""Captures annotated with part poses: ``NAME.parts.json`` (each part's camera pose and mask in
one frame) and the object metadata file beside it (links, joints, part boxes), turned into the
ground truth a labels JSON gives (:func:`load_part_pose_ground_truth`).

Layout (docs/real_data.md, "Captures annotated with part poses"):

* frame file: ``{"frame": "camera"|"optical", "objects_file": NAME, "instances": [{"object":
  ID, "links": {LINK: 4x4 camera-from-link pose, m}, "masks": {LINK: COCO polygons or RLE}}]}``;
* object metadata (``objects.json`` beside the frame file, or the file ``objects_file`` names
  in the same folder): ``{"objects": {ID: {"class", "up", "links": {LINK: {"bbox": {"center",
  "size"}}}, "joints": [{"name", "type", "parent", "child", "axis": {"origin", "direction"},
  "rest_pose"}]}}}``.

The joints of type ``revolute``/``prismatic`` are the class's joints in label order; ``fixed``
joints attach rigid sub-parts (a handle) to their parent.  Every value is checked
(:class:`UserError`, one line): file sizes, finite numbers, rigid poses, masks inside the image,
known link and object names, the links forming one tree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articulated_dataset.classes.registry import get_class
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.images.intrinsics import read_mapping, read_numbers
from articulated_dataset.core.units import normalise
from articulated_dataset.format import MASK_BODY, MASK_FIRST_PART
from articulated_dataset.format.shards import resolve_inside
from articulated_dataset.ingest.coco_masks import MAX_POLYGON_TESTS, coco_mask
from articulated_dataset.ingest.ground_truth import (
    GT_FRAMES,
    MAX_OBJECT_NAME_CHARS,
    MAX_PLAUSIBLE_OBJECT_SIZE_M,
    REAL_LABEL_FIELDS,
    empty_labels,
    real_label_problems,
)
from articulated_dataset.ingest.part_poses import (
    PRISMATIC,
    REVOLUTE,
    PartPoseJoint,
    axis_frame_labels,
    joint_from_part_poses,
    rigid,
    rigid_problem,
)
from articulated_dataset.ingest.readers import MAX_PLAUSIBLE_DEPTH_M

log = logging.getLogger(__name__)

#: Object metadata file looked up beside a frame file that names none.
OBJECTS_FILE = "objects.json"
#: Largest frame file read (bytes): poses take a few hundred bytes per link; masks as
#: compressed RLE a few kB, as uncompressed counts or polygons some 100 kB per frame.
MAX_PARTS_FILE_BYTES = 4_000_000
#: Largest object metadata file read (bytes): about 1 kB per object (a thousand objects).
MAX_OBJECTS_FILE_BYTES = 4_000_000
#: Most instances one frame may list, and links (parts) one object may have.
MAX_INSTANCES = 256
MAX_LINKS = 256
FIXED = "fixed"
JOINT_TYPES = (REVOLUTE, PRISMATIC, FIXED)
#: The object's up direction in its root link's frame where the metadata gives none.
DEFAULT_UP = (0.0, 0.0, 1.0)
FRAME_KEYS = {"frame", "objects_file", "instances", "comment"}
INSTANCE_KEYS = {"object", "links", "masks", "comment"}
OBJECTS_KEYS = {"objects", "comment"}
OBJECT_KEYS = {"class", "up", "links", "joints", "comment"}
LINK_KEYS = {"bbox", "comment"}
BOX_KEYS = {"center", "size"}
JOINT_KEYS = {"name", "type", "parent", "child", "axis", "rest_pose", "comment"}
AXIS_KEYS = {"origin", "direction"}


def read_json_file(path: Path, max_bytes: int, what: str) -> dict:
    """A UTF-8 JSON file (a byte-order mark allowed) of at most ``max_bytes`` whose top level is
    a mapping (:func:`~articulated_dataset.core.images.intrinsics.read_mapping`); anything else a
    one-line :class:`UserError`."""
    if not path.is_file():
        raise UserError(f"{what} not found: {path}")
    return read_mapping(path, max_bytes, f"a {what}")


def _keys(d, allowed: set[str], where: str) -> dict:
    """``d`` checked to be a mapping with no key outside ``allowed``."""
    if not isinstance(d, dict):
        raise UserError(f"{where}: expected a JSON object, got {str(d)[:40]!r}")
    unknown = sorted(str(k) for k in set(d) - allowed)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(k[:40] for k in unknown[:5])}; "
                        f"expected {', '.join(sorted(allowed))}")
    return d


def _name(v, where: str) -> str:
    """A link, joint or object name: printable text of 1 to :data:`MAX_OBJECT_NAME_CHARS` characters."""
    if not (isinstance(v, str) and v.strip() and len(v) <= MAX_OBJECT_NAME_CHARS and v.isprintable()):
        raise UserError(f"{where}: expected a printable name of at most {MAX_OBJECT_NAME_CHARS} characters, "
                        f"got {str(v)[:40]!r}")
    return v


def _numbers(v, shape: tuple, where: str) -> np.ndarray:
    """``v`` as a finite float64 array of ``shape``."""
    a = read_numbers(v, where)
    if a.shape != shape:
        raise UserError(f"{where}: has shape {a.shape}, expected {shape}")
    if not np.isfinite(a).all():
        raise UserError(f"{where}: has NaN or infinite values")
    return a


def _pose(v, where: str) -> np.ndarray:
    """A rigid 4x4 transform (:func:`~.part_poses.rigid_problem`), made exactly rigid."""
    T = _numbers(v, (4, 4), where)
    problem = rigid_problem(T)
    if problem is not None:
        raise UserError(f"{where}: {problem}")
    return rigid(T)


@dataclass(frozen=True, eq=False)  # numpy fields: compared by identity
class Box:
    """A part's axis-aligned box in its link's frame (m)."""

    centre_m: np.ndarray
    size_m: np.ndarray


@dataclass(frozen=True, eq=False)  # numpy fields: compared by identity
class MetaJoint:
    """A joint of the object metadata; ``origin_m``/``direction`` in the parent link's frame,
    ``rest_pose`` the child's pose in it at q = 0 (None: identity)."""

    name: str
    joint_type: str
    parent: str
    child: str
    direction: np.ndarray | None
    origin_m: np.ndarray | None
    rest_pose: np.ndarray | None


@dataclass(frozen=True, eq=False)  # numpy fields: compared by identity
class ObjectModel:
    """One object of the metadata file: its links (with their boxes, where given), joints,
    root link and up direction (root link frame)."""

    name: str
    class_name: str | None
    up: np.ndarray
    boxes: dict[str, Box | None]
    joints: tuple[MetaJoint, ...]
    root: str

    @property
    def movable(self) -> list[MetaJoint]:
        """The revolute and prismatic joints: the class's joints in label order."""
        return [j for j in self.joints if j.joint_type != FIXED]

    def link_label(self, link: str) -> int:
        """Mask label of ``link``: ``2 + j`` where the nearest movable joint above it (itself
        the child, or up through fixed joints) is joint ``j``; 1 (body) where there is none."""
        parent_joint = {j.child: j for j in self.joints}
        movable = self.movable
        while link in parent_joint:
            joint = parent_joint[link]
            if joint.joint_type != FIXED:
                return MASK_FIRST_PART + movable.index(joint)
            link = joint.parent
        return MASK_BODY


def _box(v, where: str) -> Box:
    d = _keys(v, BOX_KEYS, where)
    if set(d) != BOX_KEYS:
        raise UserError(f"{where}: a bbox has 'center' and 'size' (m)")
    centre = _numbers(d["center"], (3,), f"{where}: 'center'")
    size = _numbers(d["size"], (3,), f"{where}: 'size'")
    if (size <= 0).any() or (size > MAX_PLAUSIBLE_OBJECT_SIZE_M).any() or (np.abs(centre) > MAX_PLAUSIBLE_OBJECT_SIZE_M).any():
        raise UserError(f"{where}: box sizes must be in (0, {MAX_PLAUSIBLE_OBJECT_SIZE_M:g}] m and its centre within "
                        f"{MAX_PLAUSIBLE_OBJECT_SIZE_M:g} m of the link's origin")
    return Box(centre, size)


def _joint(v, links: dict, k: int, where: str) -> MetaJoint:
    d = _keys(v, JOINT_KEYS, f"{where} joint {k}")
    name = _name(d.get("name"), f"{where} joint {k}: 'name'")
    at = f"{where} joint {name!r}"
    jtype = d.get("type")
    if jtype not in JOINT_TYPES:
        raise UserError(f"{at}: type {str(jtype)[:40]!r}; choose from: {', '.join(JOINT_TYPES)}")
    parent = _name(d.get("parent"), f"{at}: 'parent'")
    child = _name(d.get("child"), f"{at}: 'child'")
    for link in (parent, child):
        if link not in links:
            raise UserError(f"{at}: unknown link {link!r} (the object's links: {', '.join(list(links)[:8])})")
    if parent == child:
        raise UserError(f"{at}: parent and child are the same link")
    direction = origin = None
    if jtype != FIXED:
        axis = _keys(d.get("axis"), AXIS_KEYS, f"{at}: 'axis'")
        if "direction" not in axis or (jtype == REVOLUTE and "origin" not in axis):
            raise UserError(f"{at}: 'axis' needs 'direction'" + (" and 'origin'" if jtype == REVOLUTE else "")
                            + " (in the parent link's frame)")
        direction = normalise(_numbers(axis["direction"], (3,), f"{at}: axis direction"), min_norm=1e-9,
                              what=f"{at}: axis direction")
        if axis.get("origin") is not None:
            origin = _numbers(axis["origin"], (3,), f"{at}: axis origin")
    rest = d.get("rest_pose")
    return MetaJoint(name, jtype, parent, child, direction, origin,
                     None if rest is None else _pose(rest, f"{at}: 'rest_pose'"))


def object_model(objects: dict, name: str, path: Path) -> ObjectModel:
    """The object ``name`` of the metadata file's ``objects`` mapping (read from ``path``), checked."""
    where = f"{path}: object {name!r}"
    d = _keys(objects[name], OBJECT_KEYS, where)
    class_name = d.get("class")
    if class_name is not None and not isinstance(class_name, str):
        raise UserError(f"{where}: 'class' must be a class name (text)")
    up = normalise(_numbers(d.get("up", DEFAULT_UP), (3,), f"{where}: 'up'"), min_norm=1e-9, what=f"{where}: 'up'")
    links = d.get("links")
    if not isinstance(links, dict) or not links or len(links) > MAX_LINKS:
        raise UserError(f"{where}: 'links' must map 1 to {MAX_LINKS} link names to their boxes")
    boxes: dict[str, Box | None] = {}
    for link, entry in links.items():
        at = f"{where} link {_name(link, f'{where}: link name')!r}"
        info = _keys(entry, LINK_KEYS, at)
        boxes[link] = None if info.get("bbox") is None else _box(info["bbox"], f"{at}: 'bbox'")
    joints_v = d.get("joints", [])
    if not isinstance(joints_v, list) or len(joints_v) > MAX_LINKS:
        raise UserError(f"{where}: 'joints' must be a list of at most {MAX_LINKS} joints")
    joints = tuple(_joint(v, links, k, where) for k, v in enumerate(joints_v))
    children = [j.child for j in joints]
    twice = sorted({c for c in children if children.count(c) > 1})
    if twice:
        raise UserError(f"{where}: link {twice[0]!r} is the child of more than one joint")
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise UserError(f"{where}: the links must form one tree with one root (a link no joint moves); "
                        f"found {len(roots)} roots")
    reached, todo = {roots[0]}, [roots[0]]
    while todo:
        link = todo.pop()
        for j in joints:
            if j.parent == link and j.child not in reached:
                reached.add(j.child)
                todo.append(j.child)
    if len(reached) != len(links):
        cut = sorted(set(links) - reached)
        raise UserError(f"{where}: link {cut[0]!r} is not connected to the root link {roots[0]!r} (a loop of joints)")
    for j in joints:
        if j.joint_type != FIXED and boxes[j.child] is None:
            raise UserError(f"{where}: link {j.child!r} (child of joint {j.name!r}) needs a 'bbox'")
    return ObjectModel(name, class_name, up, boxes, joints, roots[0])


def objects_path(frame: dict, path: Path) -> Path:
    """The object metadata file of the frame file ``path``: the name its ``objects_file`` gives
    (a file in the same folder: no folders, no ``..``, no link leading out of it,
    :func:`~articulated_dataset.format.shards.resolve_inside`), else :data:`OBJECTS_FILE` beside it."""
    name = frame.get("objects_file", OBJECTS_FILE)
    if (not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name
            or "\0" in name or not name.isprintable()):
        raise UserError(f"{path}: 'objects_file' must name a file in the same folder (no path), got {str(name)[:60]!r}")
    return resolve_inside(path.parent, name, where=str(path))


@dataclass(frozen=True, eq=False)  # numpy fields: compared by identity
class PartPoseRecord:
    """Ground truth of one capture from part poses: the label fields as
    :func:`~.ground_truth.load_ground_truth` returns them, the mask (None where the frame gives
    none) and each joint as read off the poses."""

    labels: dict
    mask: np.ndarray | None
    joints: tuple[PartPoseJoint, ...]


def _instance(frame: dict, objects: dict, class_name: str, path: Path, objects_file: Path) -> tuple[int, dict]:
    """The index and entry of the frame's one instance of ``class_name`` (an object of the
    metadata whose ``class`` is ``class_name`` or not given)."""
    instances = frame.get("instances")
    if not isinstance(instances, list) or not instances or len(instances) > MAX_INSTANCES:
        raise UserError(f"{path}: 'instances' must be a list of 1 to {MAX_INSTANCES} instances")
    found = []
    for i, inst in enumerate(instances):
        inst = _keys(inst, INSTANCE_KEYS, f"{path}: instance {i}")
        obj = _name(inst.get("object"), f"{path}: instance {i}: 'object'")
        if obj not in objects:
            raise UserError(f"{path}: instance {i}: object {obj!r} is not in {objects_file}")
        entry = objects[obj]
        if not isinstance(entry, dict):
            raise UserError(f"{objects_file}: object {obj!r}: expected a JSON object")
        if entry.get("class") in (None, class_name):
            found.append(i)
    if len(found) != 1:
        raise UserError(f"{path}: {len(found)} instances of class {class_name} (objects of {objects_file} whose "
                        f"'class' is {class_name} or not given); a capture is one object")
    return found[0], instances[found[0]]


def load_part_pose_ground_truth(path: str | Path, class_name: str, shape: tuple[int, int]) -> PartPoseRecord:
    """Ground truth of a capture from its part-pose frame file ``path`` (module docstring) for
    an (H, W) = ``shape`` depth image of class ``class_name``.

    Each movable joint ``j`` (in the metadata's order) gives the labels of the class's joint
    ``j``: :func:`~.part_poses.joint_from_part_poses` on the parent's and child's poses, then
    :func:`~.part_poses.axis_frame_labels` with the object's up direction (the root link's
    pose turns it into the camera frame).  Poses in the ``optical`` frame are converted with
    ``T_camera = diag(R^T, 1) T_optical`` (``R = R_CAMERA_TO_OPTICAL``).  A joint whose axis
    disagrees with the annotated one (:meth:`~.part_poses.PartPoseJoint.disagreements`) is
    logged as a warning.  The mask: each link's COCO segmentation, labelled
    (:meth:`ObjectModel.link_label`), body first and then the moving parts in joint order
    (where masks overlap, the later wins).  ``object_pose``, ``object_yaw`` and ``geometry``
    are NaN (not given); the labels pass the checks of real labels
    (:func:`~.ground_truth.real_label_problems`).
    """
    path = resolve_inside(Path(path).parent, Path(path).name)  # a link beside the capture leading out: refused
    obj_class = get_class(class_name)
    frame = _keys(read_json_file(path, MAX_PARTS_FILE_BYTES, "part-pose file"), FRAME_KEYS, str(path))
    frame_name = frame.get("frame", "camera")
    if not isinstance(frame_name, str) or frame_name not in GT_FRAMES:
        raise UserError(f"{path}: unknown frame {str(frame_name)[:40]!r}; choose from: {', '.join(GT_FRAMES)}")
    objects_file = objects_path(frame, path)
    meta = _keys(read_json_file(objects_file, MAX_OBJECTS_FILE_BYTES, "object metadata file"), OBJECTS_KEYS,
                 str(objects_file))
    objects = meta.get("objects")
    if not isinstance(objects, dict):
        raise UserError(f"{objects_file}: 'objects' must map object names to their links and joints")
    index, inst = _instance(frame, objects, class_name, path, objects_file)
    where = f"{path}: instance {index}"
    model = object_model(objects, inst["object"], objects_file)
    movable = model.movable
    J = obj_class.n_joints
    if len(movable) != J:
        raise UserError(f"{objects_file}: object {model.name!r} has {len(movable)} revolute or prismatic joints; "
                        f"class {class_name} has {J}")
    for j, jt in enumerate(movable):
        if jt.joint_type != obj_class.joint_types[j]:
            raise UserError(f"{objects_file}: object {model.name!r}: joint {jt.name!r} is {jt.joint_type}; "
                            f"joint {j} of class {class_name} is {obj_class.joint_types[j]}")

    links = inst.get("links")
    if not isinstance(links, dict):
        raise UserError(f"{where}: 'links' must map link names to 4x4 camera-from-link poses")
    to_camera = np.eye(4)
    if frame_name == "optical":
        to_camera[:3, :3] = R_CAMERA_TO_OPTICAL.T
    poses = {}
    for link, T in links.items():
        if link not in model.boxes:
            raise UserError(f"{where}: unknown link {str(link)[:60]!r} (object {model.name!r} has "
                            f"{', '.join(list(model.boxes)[:8])})")
        poses[link] = to_camera @ _pose(T, f"{where} link {link!r}: pose")
        if np.linalg.norm(poses[link][:3, 3]) > MAX_PLAUSIBLE_DEPTH_M:
            raise UserError(f"{where} link {link!r}: pose places the link farther than {MAX_PLAUSIBLE_DEPTH_M:g} m "
                            f"from the camera (positions are in metres)")
    needed = [lk for jt in movable for lk in (jt.parent, jt.child)]
    if any(jt.joint_type == PRISMATIC for jt in movable):
        needed.append(model.root)  # the object's up direction for the prismatic axis frame
    missing = [lk for lk in dict.fromkeys(needed) if lk not in poses]
    if missing:
        raise UserError(f"{where}: no pose of link {missing[0]!r} (needed for the joints' labels)")

    labels = empty_labels(J)
    joints = []
    up_cam = poses[model.root][:3, :3] @ model.up if model.root in poses else np.asarray(DEFAULT_UP)
    for j, jt in enumerate(movable):
        box = model.boxes[jt.child]
        assert box is not None and jt.direction is not None  # checked by object_model
        joint = joint_from_part_poses(poses[jt.parent], poses[jt.child], jt.joint_type, box.centre_m, box.size_m,
                                      jt.direction, jt.origin_m, jt.rest_pose)
        bad = joint.disagreements()
        if bad:
            log.warning("%s: joint %r of object %r disagrees with its annotation: %s", path, jt.name, model.name,
                        "; ".join(bad))
        axis_pose, offset = axis_frame_labels(joint, up_cam)
        labels["q"][j] = joint.q
        labels["axis_origin"][j], labels["axis_direction"][j] = joint.origin_m, joint.direction
        labels["axis_pose"][j], labels["part_offset"][j] = axis_pose, offset
        joints.append(joint)
    labels["object"] = model.name
    problems = real_label_problems({k: np.asarray(labels[k])[None] for k in REAL_LABEL_FIELDS},
                                   obj_class.joint_types, obj_class.table.q)
    if problems:
        raise UserError(f"{where}: {problems[0][0]}")
    return PartPoseRecord(labels, _mask(inst.get("masks"), model, shape, where), tuple(joints))


def _mask(masks, model: ObjectModel, shape: tuple[int, int], where: str) -> np.ndarray | None:
    """The label mask of an instance's ``masks`` (None where it gives none)."""
    if masks is None or masks == {}:
        return None
    if not isinstance(masks, dict):
        raise UserError(f"{where}: 'masks' must map link names to COCO segmentations")
    for link in masks:
        if link not in model.boxes:
            raise UserError(f"{where}: mask of unknown link {str(link)[:60]!r} (object {model.name!r} has "
                            f"{', '.join(list(model.boxes)[:8])})")
    out = np.zeros(shape, np.uint8)
    budget = MAX_POLYGON_TESTS
    for link in sorted(masks, key=model.link_label):  # body first, then the parts in joint order
        m, tests = coco_mask(masks[link], shape, f"{where} mask {link!r}", budget)
        budget -= tests
        out[m] = model.link_label(link)
    return out
