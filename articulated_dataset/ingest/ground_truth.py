"""Ground truth of real captures: the labels JSON (:func:`load_ground_truth`), the checks a real
image's labels must pass (:func:`real_label_problems`, also run by ``artdata verify``) and the NaN
labels of a capture without ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from articulated_dataset.classes.registry import get_class
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.images.intrinsics import read_mapping, read_numbers
from articulated_dataset.core.rotations import matrix_to_quat as mat_to_quat
from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.core.units import normalise
from articulated_dataset.ingest.readers import MAX_PLAUSIBLE_DEPTH_M

#: Largest body dimension or part offset (m) of a labelled household object.
MAX_PLAUSIBLE_OBJECT_SIZE_M = 5.0
#: Ground-truth configurations may exceed the class's joint range by this much (rad for
#: revolute, m for prismatic joints): AR-tag / motion-capture labels of a closed or fully open
#: part are accurate to a few degrees or centimetres.
REAL_Q_TOLERANCE = {"revolute": math.radians(5.0), "prismatic": 0.02}
#: Allowed | |q| - 1 | of a given quaternion before it is normalised (labels written with a few
#: digits are not exactly unit); farther is a typo, not rounding.
QUAT_NORM_TOL = 1e-2
#: Allowed disagreement (rad) between a given ``object_yaw`` and the yaw of ``object_pose``.
YAW_AGREEMENT_RAD = 1e-3
#: Label fields of a real image that are NaN where the capture's labels do not give them.
REAL_LABEL_FIELDS = ("q", "axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw",
                     "geometry")
GT_FRAMES = ("camera", "optical")


def _array(d: dict, key: str, shape: tuple, path: Path) -> np.ndarray | None:
    """``d[key]`` as a float64 array of ``shape``; None if absent or null (not available).
    NaN, infinite, non-numeric values or another shape are a :class:`UserError`."""
    if key not in d or d[key] is None:
        return None
    a = read_numbers(d[key], f"{path}: {key!r}")
    if a.shape != shape:
        raise UserError(f"{path}: {key!r} has shape {a.shape}, expected {shape}")
    if not np.isfinite(a).all():
        raise UserError(f"{path}: {key!r} has NaN or infinite values; leave the key out (or null) when it is "
                        f"not known")
    return a


def _label_unit(v: np.ndarray, what: str, path: Path, tol: float | None = None) -> np.ndarray:
    """``v`` (..., n) of a label file normalised row by row; zero length (or, with ``tol``, a
    norm farther than ``tol`` from 1) is a :class:`UserError`."""
    rows = normalise(v.reshape(-1, v.shape[-1]), min_norm=1e-9, what=f"{path}: {what}")
    if tol is not None:
        n = np.linalg.norm(v, axis=-1)
        if (np.abs(n - 1.0) > tol).any():
            raise UserError(f"{path}: {what} has norm {float(n.reshape(-1)[np.argmax(np.abs(n - 1.0))]):.4g}, "
                            f"expected a unit quaternion (w, x, y, z)")
    return rows.reshape(v.shape)


def _wrap_angle(a: float) -> float:
    """``a`` (rad) in (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def real_label_problems(labels: dict, joint_types, q_ranges, has_ground_truth=None) -> list[tuple[str, np.ndarray]]:
    """What is wrong with the labels of N real images: ``[(message, bad (N,) bool)]``.

    ``labels`` maps every field of :data:`REAL_LABEL_FIELDS` to an (N, ...) array (NaN where
    the capture does not give the value).  The rules (docs/real_data.md): no infinite values;
    each group (a joint's origin, direction, axis position, axis quaternion, part offset; the
    object position, the object quaternion, the geometry) is given or NaN as a whole, and
    ``axis_pose``'s position / quaternion are given exactly where ``axis_origin`` /
    ``axis_direction`` are; ``object_yaw`` is given where ``object_pose`` is; an image without
    ground truth (``has_ground_truth`` 0) has only NaN.  Given values: ``q`` within the class's
    joint range (``q_ranges``, widened by :data:`REAL_Q_TOLERANCE`), positions within
    :data:`MAX_PLAUSIBLE_DEPTH_M` of the camera, body dimensions and part offsets positive /
    within :data:`MAX_PLAUSIBLE_OBJECT_SIZE_M`, chirality 0 or 1, ``object_yaw`` in [-pi, pi].
    """
    out: list[tuple[str, np.ndarray]] = []
    L = {k: np.asarray(labels[k], np.float64) for k in REAL_LABEL_FIELDS}
    n = L["q"].shape[0]

    def flag(message: str, bad: np.ndarray | np.bool_) -> None:
        bad = np.asarray(bad, bool).reshape(n, -1).any(axis=1)
        if bad.any():
            out.append((message, bad))  # type: ignore[arg-type]  # any(axis=1) of a 2-D array: an array

    for k, v in L.items():
        flag(f"{k}: infinite values", np.isinf(v))
    groups = (("axis_origin", slice(None), ""), ("axis_direction", slice(None), ""), ("axis_pose", slice(0, 3), " position"),
              ("axis_pose", slice(3, 7), " quaternion"), ("part_offset", slice(None), ""),
              ("object_pose", slice(0, 3), " position"), ("object_pose", slice(3, 7), " quaternion"), ("geometry", slice(None), ""))
    for k, sl, part in groups:
        nan = np.isnan(L[k][..., sl])
        flag(f"{k}{part}: partly NaN (a value is given, or not available, as a whole)", nan.any(-1) & ~nan.all(-1))
    flag("axis_pose position and axis_origin: one is given without the other",
         np.isnan(L["axis_pose"][..., 0]) != np.isnan(L["axis_origin"][..., 0]))
    flag("axis_pose quaternion and axis_direction: one is given without the other",
         np.isnan(L["axis_pose"][..., 3]) != np.isnan(L["axis_direction"][..., 0]))
    flag("object_yaw: NaN although object_pose gives it", ~np.isnan(L["object_pose"][:, 3]) & np.isnan(L["object_yaw"]))
    if has_ground_truth is not None:
        given = np.stack([~np.isnan(v.reshape(n, -1)).all(axis=1) for v in L.values()], axis=1)
        flag("labels present although has_ground_truth is 0", (np.asarray(has_ground_truth) == 0)[:, None] & given)
    with np.errstate(invalid="ignore"):  # NaN (not available) compares False: only given values are checked
        for j, (jtype, (lo, hi)) in enumerate(zip(joint_types, q_ranges)):
            tol = REAL_Q_TOLERANCE[jtype]
            unit = "rad" if jtype == "revolute" else "m"
            flag(f"q[{j}]: outside the class's joint range [{lo:.4g}, {hi:.4g}] {unit} (by more than {tol:.3g} {unit})",
                 (L["q"][:, j] < lo - tol) | (L["q"][:, j] > hi + tol))
        for k, sl in (("axis_origin", slice(None)), ("object_pose", slice(0, 3))):
            flag(f"{k}: position farther than {MAX_PLAUSIBLE_DEPTH_M:g} m from the camera",
                 np.linalg.norm(L[k][..., sl], axis=-1) > MAX_PLAUSIBLE_DEPTH_M)
        flag(f"part_offset: longer than {MAX_PLAUSIBLE_OBJECT_SIZE_M:g} m",
             np.linalg.norm(L["part_offset"], axis=-1) > MAX_PLAUSIBLE_OBJECT_SIZE_M)
        dims = L["geometry"][:, :3]
        flag(f"geometry: body dimensions not in (0, {MAX_PLAUSIBLE_OBJECT_SIZE_M:g}] m",
             (dims <= 0) | (dims > MAX_PLAUSIBLE_OBJECT_SIZE_M))
        chir = L["geometry"][:, 3]
        flag("geometry: chirality not 0 or 1", ~np.isnan(chir) & ~np.isin(chir, (0.0, 1.0)))
        flag("object_yaw: outside [-pi, pi] rad", np.abs(L["object_yaw"]) > math.pi + YAW_AGREEMENT_RAD)
    return out


#: Camera-frame up (z) and forward (x) directions used to complete an axis frame from its z axis.
_UP = np.array([0.0, 0.0, 1.0])
_FORWARD = np.array([1.0, 0.0, 0.0])


def axis_frame_from_direction(a: np.ndarray) -> np.ndarray:
    """A rotation (columns x, y, z) with z = ``a`` (unit) and x = camera up made perpendicular
    to ``a`` (camera forward if ``a`` is vertical); used when ground truth gives only the axis
    line: only the z column is then meaningful."""
    ref = _UP if abs(float(a @ _UP)) < 0.9 else _FORWARD
    x = ref - (ref @ a) * a
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(a, x), a], axis=1)


#: Longest object name a ground-truth file may give (a name groups the captures of one object).
MAX_OBJECT_NAME_CHARS = 256


def load_ground_truth(path: str | Path, n_joints: int, class_name: str | None = None) -> dict:
    """Labels of one capture from a JSON file, converted to the camera frame.

    Keys (all optional; J = joints of the class):

    * ``frame``: ``"camera"`` (x forward, y left, z up; default) or ``"optical"`` (x right,
      y down, z forward): positions and orientations are converted with
      ``p_camera = R^T p_optical``, ``R_camera = R^T R_optical`` (``R = R_CAMERA_TO_OPTICAL``);
    * ``q`` (J,): rad (revolute) or m (prismatic);
    * ``axis_pose`` (J, 7): position + quaternion (w, x, y, z) of the axis frame (z = axis), or
      ``axis_origin`` (J, 3) + ``axis_direction`` (J, 3) (the stored frame's x axis is then
      :func:`axis_frame_from_direction`'s choice);
    * ``part_offset`` (J, 3) (axis frame); ``geometry`` (4: depth, width, height m, chirality);
    * ``object_pose`` (7) and/or ``object_yaw`` (rad, camera frame);
    * ``class`` (must match), ``object`` (name grouping captures of one object).

    Returns a dict of float64 arrays for every label field, NaN where not given, plus
    ``"object"`` (str or None).
    """
    path = Path(path)
    d = read_mapping(path)
    if class_name is not None and d.get("class") not in (None, class_name):
        raise UserError(f"{path}: ground truth is for class {str(d.get('class'))[:80]!r}, not {class_name!r}")
    frame = d.get("frame", "camera")
    if not isinstance(frame, str) or frame not in GT_FRAMES:
        raise UserError(f"{path}: unknown frame {frame!r}; choose from: {', '.join(GT_FRAMES)}")
    unknown = set(d) - {"frame", "q", "axis_pose", "axis_origin", "axis_direction", "part_offset", "geometry",
                        "object_pose", "object_yaw", "class", "object", "comment"}
    if unknown:
        raise UserError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}")
    J = n_joints
    Rt = R_CAMERA_TO_OPTICAL.T if frame == "optical" else np.eye(3)
    out = empty_labels(J)
    q = _array(d, "q", (J,), path)
    if q is not None:
        out["q"] = q
    pose = _array(d, "axis_pose", (J, 7), path)
    origin = _array(d, "axis_origin", (J, 3), path)
    direction = _array(d, "axis_direction", (J, 3), path)
    if pose is not None:
        quat = _label_unit(pose[:, 3:], "axis_pose quaternion", path, QUAT_NORM_TOL)
        rots = np.stack([Rt @ quat_to_matrix(qq) for qq in quat])
        pos = pose[:, :3] @ Rt.T
        if origin is not None and np.abs(origin @ Rt.T - pos).max() > 1e-4:
            raise UserError(f"{path}: axis_origin disagrees with the position of axis_pose")
        if direction is not None and np.abs(_label_unit(direction, "axis_direction", path) @ Rt.T - rots[:, :, 2]).max() > 1e-4:
            raise UserError(f"{path}: axis_direction disagrees with the z axis of axis_pose")
        out["axis_pose"] = np.concatenate([pos, np.stack([mat_to_quat(r) for r in rots])], axis=1)
        out["axis_origin"], out["axis_direction"] = pos, rots[:, :, 2]
    else:
        if origin is not None:
            out["axis_origin"] = origin @ Rt.T
            out["axis_pose"][:, :3] = out["axis_origin"]
        if direction is not None:
            a = _label_unit(direction, "axis_direction", path) @ Rt.T
            out["axis_direction"] = a
            out["axis_pose"][:, 3:] = np.stack([mat_to_quat(axis_frame_from_direction(aj)) for aj in a])
    offset = _array(d, "part_offset", (J, 3), path)
    if offset is not None:
        out["part_offset"] = offset
    geometry = _array(d, "geometry", (4,), path)
    if geometry is not None:
        out["geometry"] = geometry
    obj_pose = _array(d, "object_pose", (7,), path)
    if obj_pose is not None:
        r = Rt @ quat_to_matrix(_label_unit(obj_pose[3:], "object_pose quaternion", path, QUAT_NORM_TOL))
        out["object_pose"] = np.concatenate([Rt @ obj_pose[:3], mat_to_quat(r)])
        out["object_yaw"] = np.array(math.atan2(r[1, 0], r[0, 0]))
    yaw = _array(d, "object_yaw", (), path)
    if yaw is not None:
        if frame != "camera":
            raise UserError(f"{path}: object_yaw is a camera-frame angle; give object_pose in the optical frame instead")
        yaw_rad = _wrap_angle(float(yaw))
        if obj_pose is not None and abs(_wrap_angle(yaw_rad - float(out["object_yaw"]))) > YAW_AGREEMENT_RAD:
            raise UserError(f"{path}: object_yaw {yaw_rad:.4f} rad disagrees with the yaw of object_pose "
                            f"({float(out['object_yaw']):.4f} rad)")
        out["object_yaw"] = np.array(yaw_rad)
    obj = d.get("object")
    if obj is not None and not (isinstance(obj, str) and obj.strip()):
        raise UserError(f"{path}: 'object' must be a non-empty name (string), got {str(obj)[:80]!r}")
    if obj is not None and not (len(obj) <= MAX_OBJECT_NAME_CHARS and obj.isprintable()):
        # the name is stored in the manifest and printed: no newlines or terminal control sequences
        raise UserError(f"{path}: 'object' must be a printable name of at most {MAX_OBJECT_NAME_CHARS} characters, "
                        f"got {obj[:40]!r}{'...' if len(obj) > 40 else ''}")
    out["object"] = obj
    if class_name is not None:
        obj_class = get_class(class_name)
        problems = real_label_problems({k: np.asarray(out[k])[None] for k in REAL_LABEL_FIELDS},
                                       obj_class.joint_types, obj_class.table.q)
        if problems:
            raise UserError(f"{path}: {problems[0][0]}")
    return out


def empty_labels(n_joints: int) -> dict:
    """Every float label field of one image filled with NaN (shapes without the image axis)."""
    J = n_joints
    return {
        "q": np.full(J, np.nan), "axis_origin": np.full((J, 3), np.nan), "axis_direction": np.full((J, 3), np.nan),
        "axis_pose": np.full((J, 7), np.nan), "part_offset": np.full((J, 3), np.nan), "object_pose": np.full(7, np.nan),
        "object_yaw": np.array(np.nan), "geometry": np.full(4, np.nan), "object": None,
    }
