"""Content checks of ``artdata verify``: the label invariants of a shard's arrays (finite
values, depth and mask, unit vectors and frames, limits of the sampling table, per-object labels,
generation order and sample ids; a real split's own rules).  See :mod:`articulated_dataset.tools.verify`."""

from __future__ import annotations

import math

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.format import MASK_BACKGROUND, MASK_FIRST_PART, object_on_border
from articulated_dataset.format.shards import json_list
from articulated_dataset.generation.context_labels import context_mask_codes
from articulated_dataset.generation.framing import shard_framing
from articulated_dataset.generation.viewpoint import is_head_mount

#: Allowed | |v| - 1 | of stored unit vectors and quaternions.  They are computed in
#: float64 and stored as float32 (relative rounding 6e-8 per component), so a correct
#: file is within ~2e-7; 1e-4 leaves a wide margin while catching any real scaling error.
UNIT_TOL = 1e-4
#: A realistic split's sizes lie within this many jitter standard deviations of a standard
#: size of some size class (the chance of a sample beyond it is ~2e-9 per dimension).
SHAPE_SD = 6.0
#: Allowed excess (rad or m) of a stored float32 value over a float64 table limit: half an
#: ulp of float32 at 16 is 1e-6; 1e-5 covers every range in the built-in tables.
LIMIT_TOL = 1e-5
#: Allowed angle (rad) between the z axis of ``axis_pose``'s quaternion and
#: ``axis_direction`` (float32 quaternion components: ~1e-7 rad expected).
FRAME_TOL_RAD = 1e-3
#: Images converted to float64 at a time for the depth checks (128 x 192 x 108 x 8 B = 21 MB).
DEPTH_BLOCK = 128
#: Datasets whose rows describe the object (identical for all of its images).
PER_OBJECT_FIELDS = ("axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw", "geometry")


def _where(bad: np.ndarray) -> str:
    """'k of N images (first: image i)' for a boolean per-image array."""
    idx = np.flatnonzero(bad)
    return f"{idx.size} of {bad.size} images (first: image {idx[0]})"


def _per_image(bad: np.ndarray) -> np.ndarray:
    return bad.reshape(bad.shape[0], -1).any(axis=1)  # type: ignore[return-value]  # any(axis=1) of 2-D: an array


def quat_rotate_z(quat_wxyz: np.ndarray) -> np.ndarray:
    """z axis of the rotation of unit quaternions (..., 4) (w, x, y, z): the third column of R
    (:func:`articulated_dataset.core.rotations.quat_to_matrix`)."""
    return quat_to_matrix(quat_wxyz)[..., :, 2]


def check_content(a: dict, attrs: dict, table, *, J: int, ipo: int, start: int, problems: list,
                   capture_names: list | None = None) -> None:
    """Label invariants; ``capture_names`` (real shards only) switches to the real rules."""
    from articulated_dataset.ingest.ground_truth import REAL_LABEL_FIELDS

    p = problems
    real = capture_names is not None
    # labels are small: check them in float64; depth is checked in blocks of images
    f64 = {k: v.astype(np.float64) for k, v in a.items() if v.dtype.kind == "f" and k != "depth"}
    if real:
        _check_real_labels(f64, attrs, table, J, p)
    for name, v in f64.items():
        if real and name in REAL_LABEL_FIELDS:
            continue  # NaN = not available (infinite values reported above); NaN compares False below
        bad = _per_image(~np.isfinite(v))
        if bad.any():
            p.append(f"{name}: non-finite values in {_where(bad)}")
            f64[name] = np.nan_to_num(v)  # keep checking the other invariants
    noise_free = attrs.get("noise_model", "none") == "none"
    if "depth" in a:
        try:
            quantum = float(attrs.get("depth_quantum_m", 0) or 0)
        except (TypeError, ValueError):
            quantum = 0.0
        _check_depth(a["depth"], a.get("mask") if noise_free else None, quantum, p)
    if "mask" in a:
        m = a["mask"]
        top = MASK_FIRST_PART + J - 1
        bad = _per_image((m > top) & ~np.isin(m, context_mask_codes(attrs)))  # 254/255: occluders/scene (format 1.1)
        if bad.any():
            p.append(f"mask: values above {top} (1 + J) in {_where(bad)}")
        if shard_framing(attrs) == "whole":
            bad = object_on_border(m)
            if bad.any():
                p.append(f"mask: an object pixel on the image's border (framing whole) in {_where(bad)}")
        if "visible_pixels" in a:
            n, n_values = m.shape[0], max(int(m.max(initial=0)) + 1, MASK_FIRST_PART + J)
            # one bincount over (image, value) pairs: counts[i, v] = pixels of value v in image i
            flat = (np.arange(n, dtype=np.int64)[:, None] * n_values + m.reshape(n, -1)).ravel()
            counts = np.bincount(flat, minlength=n * n_values).reshape(n, n_values)[:, 1:MASK_FIRST_PART + J]
            bad = _per_image(counts != a["visible_pixels"])
            if bad.any():
                p.append(f"visible_pixels: differ from the mask's pixel counts in {_where(bad)}")
    if "visible_pixels" in a and not int(attrs.get("mean_object", 0)) and "min_part_pixels" in attrs and J:
        bad = _per_image(a["visible_pixels"][:, 1:] < int(attrs["min_part_pixels"]))
        if bad.any():
            p.append(f"visible_pixels: a moving part covers fewer than min_part_pixels = {attrs['min_part_pixels']} "
                     f"px in {_where(bad)}")
    if "axis_direction" in f64:
        bad = _per_image(np.abs(np.linalg.norm(f64["axis_direction"], axis=-1) - 1) > UNIT_TOL)
        if bad.any():
            err = np.abs(np.linalg.norm(f64["axis_direction"], axis=-1) - 1).max()
            p.append(f"axis_direction: not unit length in {_where(bad)} (max | |a| - 1 | = {err:.3g})")
    if "axis_pose" in f64:
        quat = f64["axis_pose"][..., 3:]
        bad = _per_image(np.abs(np.linalg.norm(quat, axis=-1) - 1) > UNIT_TOL)
        if bad.any():
            p.append(f"axis_pose: quaternion not normalised in {_where(bad)}")
        if "axis_origin" in f64:
            bad = _per_image(~_same(f64["axis_pose"][..., :3], f64["axis_origin"]))
            if bad.any():
                p.append(f"axis_pose: position differs from axis_origin in {_where(bad)}")
        if "axis_direction" in f64:
            qn = quat / np.maximum(np.linalg.norm(quat, axis=-1, keepdims=True), 1e-12)
            cos = np.sum(quat_rotate_z(qn) * f64["axis_direction"], axis=-1) / np.maximum(
                np.linalg.norm(f64["axis_direction"], axis=-1), 1e-12)
            bad = _per_image(cos < math.cos(FRAME_TOL_RAD))
            if bad.any():
                p.append(f"axis_pose: frame z axis differs from axis_direction in {_where(bad)}")
    if "object_pose" in f64:
        quat = f64["object_pose"][:, 3:]
        bad = np.abs(np.linalg.norm(quat, axis=-1) - 1) > UNIT_TOL
        if bad.any():
            p.append(f"object_pose: quaternion not normalised in {_where(bad)}")
        if "object_yaw" in f64:
            if is_head_mount(attrs):  # tilted: the heading of the object's x axis (labels.py)
                R = quat_to_matrix(quat)
                yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
            else:
                yaw = 2 * np.arctan2(quat[:, 3], quat[:, 0])
            diff = np.abs(np.angle(np.exp(1j * (yaw - f64["object_yaw"]))))
            bad = diff > FRAME_TOL_RAD
            if bad.any():
                p.append(f"object_yaw: differs from the yaw of object_pose in {_where(bad)}")
    if table is not None and not real:  # real: the class's joint range in _check_real_labels; any pose
        _check_limits(f64, table, J, attrs, p)
    if "geometry" in f64:
        g = f64["geometry"]
        bad = _per_image(g[:, :3] <= 0)
        if bad.any():
            p.append(f"geometry: non-positive body dimensions in {_where(bad)}")
        bad = ~np.isin(g[:, 3], (0.0, 1.0)) & ~np.isnan(g[:, 3])  # NaN: real data without geometry
        if bad.any():
            p.append(f"geometry: chirality not 0 or 1 in {_where(bad)}")
    if real:
        _check_real_order(a, attrs, capture_names, problems=p)  # type: ignore[arg-type]  # a real shard has them
    else:
        _check_order(a, attrs, J=J, ipo=ipo, start=start, problems=p)


def _same(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Elementwise equality with NaN equal to NaN (real labels: both not available)."""
    return (x == y) | (np.isnan(x) & np.isnan(y))


def _check_real_labels(f64: dict, attrs: dict, table, J: int, p: list) -> None:
    """:func:`articulated_dataset.ingest.ground_truth.real_label_problems` on the shard's label arrays."""
    from articulated_dataset.ingest.ground_truth import REAL_LABEL_FIELDS, real_label_problems

    if not all(k in f64 for k in REAL_LABEL_FIELDS):
        return  # already reported as missing or malformed datasets
    n = f64["q"].shape[0]
    gt = attrs.get("has_ground_truth")
    gt = None if gt is None else np.asarray(gt).reshape(-1)
    if gt is None or gt.shape != (n,) or not np.isin(gt, (0, 1)).all():
        p.append(f"attribute has_ground_truth must hold {n} values 0 or 1")
        gt = None
    from articulated_dataset.classes.registry import get_class

    try:
        obj_class = get_class(str(attrs.get("class_name")))
        types, ranges = obj_class.joint_types, obj_class.table.q
    except UserError:  # a class from another package: the shard's own table and types
        types = tuple(json_list(attrs.get("joint_types")) or [])
        ranges = table.q if table is not None else ()
    if len(types) != J or len(ranges) != J:
        types, ranges = (), ()
    for message, bad in real_label_problems({k: f64[k] for k in REAL_LABEL_FIELDS}, types, ranges, gt):
        p.append(f"{message} in {_where(bad)}")


def _check_class(a: dict, attrs: dict, p: list) -> str:
    """Every image's ``class`` equals the shard's ``class_name`` (returned)."""
    cls = str(attrs.get("class_name", ""))
    if "class" in a:
        bad = a["class"] != cls.encode("ascii", "replace")
        if bad.any():
            p.append(f"class: differs from the shard's class {cls!r} in {_where(bad)}")
    return cls


def _check_real_order(a: dict, attrs: dict, capture_names: list, *, problems: list) -> None:
    """Real shards: objects and images numbered by capture; ``sample_id`` from the capture names."""
    from articulated_dataset.ingest.write import real_sample_id

    p = problems
    n = len(capture_names)
    try:
        start, stop = int(attrs["object_start"]), int(attrs["object_stop"])
    except (KeyError, TypeError, ValueError):
        return  # reported with the root attributes
    if "object_index" in a:
        bad = (a["object_index"] < start) | (a["object_index"] >= stop)
        if bad.any():
            p.append(f"object_index: outside the shard's objects [{start}, {stop}) in {_where(bad)}")
    if "image_index" in a:
        bad = a["image_index"] < 0
        if bad.any():
            p.append(f"image_index: negative in {_where(bad)}")
    if "object_index" in a and "image_index" in a:
        pairs = a["object_index"].astype(np.int64) * (1 << 32) + a["image_index"].astype(np.int64)
        uniq, counts = np.unique(pairs, return_counts=True)
        if (counts > 1).any():
            p.append(f"(object_index, image_index): {int((counts > 1).sum())} pairs repeated within the shard")
    cls = _check_class(a, attrs, p)
    if "sample_id" in a and a["sample_id"].shape == (n,):
        split = str(attrs.get("split", ""))
        want = np.array([real_sample_id(cls, split, name) for name in capture_names], np.int64)
        bad = a["sample_id"] != want
        if bad.any():
            p.append(f"sample_id: differs from real_sample_id(class, split, capture name) in {_where(bad)}")


def _check_depth(depth: np.ndarray, mask: np.ndarray | None, quantum_m: float, p: list) -> None:
    """Depth invariants, :data:`DEPTH_BLOCK` images at a time (bounded memory): finite,
    ``>= 0``, integer multiples of ``quantum_m`` (if > 0) and, given the mask (noise-free
    data), ``depth > 0`` exactly where ``mask > 0``."""
    n = depth.shape[0]
    bad = {"finite": np.zeros(n, bool), "negative": np.zeros(n, bool), "quantum": np.zeros(n, bool),
           "mask": np.zeros(n, bool)}
    for s in range(0, n, DEPTH_BLOCK):
        d = depth[s:s + DEPTH_BLOCK].astype(np.float64)
        finite = np.isfinite(d)
        bad["finite"][s:s + DEPTH_BLOCK] = _per_image(~finite)
        d = np.where(finite, d, 0.0)
        bad["negative"][s:s + DEPTH_BLOCK] = _per_image(d < 0)
        if quantum_m > 0:
            k = d / quantum_m
            bad["quantum"][s:s + DEPTH_BLOCK] = _per_image(k != np.round(k))
        if mask is not None:
            bad["mask"][s:s + DEPTH_BLOCK] = _per_image((mask[s:s + DEPTH_BLOCK] != MASK_BACKGROUND) != (d > 0))
    messages = {"finite": "depth: non-finite values in {}", "negative": "depth: negative values in {}",
                "quantum": f"depth: values not multiples of depth_quantum_m = {quantum_m:g} m in {{}}",
                "mask": "mask/depth: background pixels (mask 0) and pixels without depth differ in {}"}
    for key, flags in bad.items():
        if flags.any():
            p.append(messages[key].format(_where(flags)))


def _check_limits(f64: dict, table, J: int, attrs: dict, p: list) -> None:
    if "q" in f64 and len(table.q) == J:
        lo = np.array([r[0] for r in table.q]) - LIMIT_TOL
        hi = np.array([r[1] for r in table.q]) + LIMIT_TOL
        for j in range(J):
            bad = (f64["q"][:, j] < lo[j]) | (f64["q"][:, j] > hi[j])
            if bad.any():
                p.append(f"q[{j}]: outside the table's limits [{table.q[j][0]:.6g}, {table.q[j][1]:.6g}] in {_where(bad)}")
    elif "q" in f64:
        p.append(f"sampling_table has {len(table.q)} q ranges for {J} joints")
    if "geometry" in f64 and table.shape is not None:
        _check_shape(f64["geometry"], table, p, mean=bool(int(attrs.get("mean_object", 0))))
    if "object_pose" in f64 and is_head_mount(attrs):
        _check_head_limits(f64["object_pose"], table, p, scene="scene" in attrs)
        return
    if "object_pose" in f64:
        whole = shard_framing(attrs) == "whole"
        for axis, key in enumerate(("x_m", "y_m", "z_m")):
            lo, hi = table.pose[key]
            if whole and key == "x_m":  # --framing whole extends the depth range by each object's size
                hi = math.inf  # type: ignore[assignment]  # (the name held an array of q bounds above)
            v = f64["object_pose"][:, axis]
            bad = (v < lo - LIMIT_TOL) | (v > hi + LIMIT_TOL)
            if bad.any():
                p.append(f"object_pose: {key[0]} outside the table's [{lo:g}, {hi:g}] m in {_where(bad)}")
    if "object_yaw" in f64:
        lo, hi = table.pose["yaw_rad"]
        v = f64["object_yaw"]
        bad = (v < lo - LIMIT_TOL) | (v > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_yaw: outside the table's [{lo:.6g}, {hi:.6g}] rad in {_where(bad)}")


def _check_shape(geometry: np.ndarray, table, p: list, *, mean: bool = False) -> None:
    """A joint size table (``--table realistic``): every (depth, width, height) within the
    table's geometry bounds and explained by one of its size classes
    (:meth:`~articulated_dataset.core.tables.ShapeMixture.component_of`); a mean object's sizes
    (the mixture's mean, between its size classes) are its mean."""
    from articulated_dataset.core.tables import GEOMETRY_KEYS

    if geometry.ndim != 2 or geometry.shape[1] < len(GEOMETRY_KEYS):
        return  # the shape check of the schema reports it
    sizes = geometry[:, :len(GEOMETRY_KEYS)]
    for axis, key in enumerate(GEOMETRY_KEYS):
        lo, hi = table.geometry[key]
        bad = (sizes[:, axis] < lo - LIMIT_TOL) | (sizes[:, axis] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"geometry: {key} outside the table's [{lo:g}, {hi:g}] m in {_where(bad)}")
    if mean:
        lo, hi = (np.array([table.geometry[k][i] for k in GEOMETRY_KEYS]) for i in (0, 1))
        bad = np.any(np.abs(sizes - np.clip(table.shape.mean_m(), lo, hi)) > LIMIT_TOL, axis=1)
        if bad.any():
            p.append(f"geometry: a mean object's sizes differ from the table's mean sizes in {_where(bad)}")
        return
    unique, inverse = np.unique(sizes, axis=0, return_inverse=True)  # one row per object
    explained = np.array([table.shape.component_of(x, n_sd=SHAPE_SD, tol_m=LIMIT_TOL) is not None for x in unique])
    bad = ~explained[inverse.reshape(-1)]
    if bad.any():
        p.append(f"geometry: sizes no size class of the table explains (beyond {SHAPE_SD:g} sd of every class) in {_where(bad)}")


def _check_head_limits(object_pose: np.ndarray, table, p: list, *, scene: bool = False) -> None:
    """A head camera's images: the camera's pitch and roll (read from the object's up axis)
    within the head ranges, and the object's pose in the level frame within the table (its
    height relative to the camera also moves by up to half the camera-height range).  In a
    ``scene`` the robot stands on the scene's floor: the base's height is its support's above
    that floor (0 to :data:`~articulated_dataset.generation.scenes.MAX_SUPPORT_HEIGHT_M`) minus
    the camera's height (:data:`~articulated_dataset.generation.viewpoint.HEAD_HEIGHT_M`)."""
    from articulated_dataset.generation.viewpoint import (
        HEAD_HEIGHT_M,
        HEAD_PITCH_DEG,
        HEAD_ROLL_DEG,
        level_pose_from_camera,
    )

    level = level_pose_from_camera(object_pose)
    for key, (lo, hi) in (("pitch_rad", HEAD_PITCH_DEG), ("roll_rad", HEAD_ROLL_DEG)):
        lo, hi = math.radians(lo), math.radians(hi)
        bad = (level[key] < lo - LIMIT_TOL) | (level[key] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_pose: head camera {key[:-4]} outside [{math.degrees(lo):g}, {math.degrees(hi):g}] deg "
                     f"in {_where(bad)}")
    rise = 0.5 * (HEAD_HEIGHT_M[1] - HEAD_HEIGHT_M[0])
    for key in ("x_m", "y_m", "z_m", "yaw_rad"):
        lo, hi = table.pose[key]
        if key == "z_m" and scene:
            from articulated_dataset.generation.scenes import MAX_SUPPORT_HEIGHT_M

            lo, hi = -HEAD_HEIGHT_M[1], MAX_SUPPORT_HEIGHT_M - HEAD_HEIGHT_M[0]
        elif key == "z_m":
            lo, hi = lo - rise, hi + rise
        bad = (level[key] < lo - LIMIT_TOL) | (level[key] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_pose: level-frame {key} outside the table's [{lo:.6g}, {hi:.6g}] in {_where(bad)}")


def _check_order(a: dict, attrs: dict, *, J: int, ipo: int, start: int, problems: list) -> None:
    from articulated_dataset.generation.sampling import sample_id

    p = problems
    n = next(iter(a.values())).shape[0] if a else 0
    obj = start + np.arange(n) // max(ipo, 1)
    img = np.arange(n) % max(ipo, 1)
    if "object_index" in a:
        bad = a["object_index"] != obj
        if bad.any():
            p.append(f"object_index: not in generation order in {_where(bad)}")
    if "image_index" in a:
        bad = a["image_index"] != img
        if bad.any():
            p.append(f"image_index: not in generation order in {_where(bad)}")
    # A head camera moves per image: only the object's own geometry is the same in all its images.
    for name in (("geometry",) if is_head_mount(attrs) else PER_OBJECT_FIELDS):
        if name not in a or n == 0:
            continue
        v = a[name].reshape(n, -1)
        first = v[(np.arange(n) // max(ipo, 1)) * max(ipo, 1)]
        bad = ~np.all((v == first) | (np.isnan(v) & np.isnan(first)) if v.dtype.kind == "f" else v == first, axis=1)
        if bad.any():
            p.append(f"{name}: differs between images of the same object in {_where(bad)}")
    cls = _check_class(a, attrs, p)
    if "sample_id" in a:
        ids = a["sample_id"]
        split, seed = str(attrs.get("split", "")), attrs.get("seed")
        if isinstance(seed, int) and seed >= 0:
            want = np.array([sample_id(cls, split, seed, int(o), int(i)) for o, i in zip(obj, img)], np.int64)
            bad = ids != want
            if bad.any():
                p.append(f"sample_id: differs from sample_id(class, split, seed, object, image) in {_where(bad)}")
        uniq, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            p.append(f"sample_id: {int((counts > 1).sum())} ids repeated within the shard (e.g. {int(uniq[counts > 1][0])})")


def rgb_problems(f, attrs: dict, arrays: dict, *, N: int, H: int, W: int) -> list[str]:
    """Problems of a shard's colour images (format 1.2, ``generate --rgb``; ``f``: the open
    HDF5 file): present exactly when the shard records its ``appearance``, uint8 (N, H, W, 3),
    in a format 1.2 shard, and (noise-free depth) not black exactly where the depth hit something."""
    from articulated_dataset.format.schema import RGB_FIELDS, RGB_FORMAT_VERSION
    from articulated_dataset.generation.context_labels import optional_field_problems

    recorded = "appearance" in attrs
    p = optional_field_problems(f, RGB_FIELDS, recorded, "the shard records its appearance, a --rgb split stores it",
                                "a shard without the attribute appearance", N=N, J=0, H=H, W=W)
    if "rgb" not in f or p:
        return p
    if str(attrs.get("format_version")) != RGB_FORMAT_VERSION:
        p.append(f"dataset 'rgb' in a shard of format {attrs.get('format_version')}, expected {RGB_FORMAT_VERSION}")
    depth, ds = arrays.get("depth"), f["rgb"]
    if depth is None or attrs.get("noise_model", "none") != "none":
        return p
    bad = np.zeros(N, bool)
    for s in range(0, N, DEPTH_BLOCK):
        lit = ds[s:s + DEPTH_BLOCK].max(axis=-1) > 0
        bad[s:s + DEPTH_BLOCK] = _per_image(lit != (depth[s:s + DEPTH_BLOCK] > 0))
    if bad.any():
        p.append(f"rgb/depth: black pixels (0, 0, 0) and pixels without depth differ in {_where(bad)}")
    return p
