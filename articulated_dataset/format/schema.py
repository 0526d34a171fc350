"""The shard schema: every stored field declared once (dtype, shape, units, frame).

Shapes use symbols: ``N`` images in the shard, ``J`` joints of the class, ``H``/``W`` image
height/width, ``P = 1 + J`` (body + parts).  The writer and the reader both validate
against :data:`FIELDS`; docs/format.md's field table is generated from the same table
(:func:`markdown_table`; ``tests/format/test_format_doc.py`` checks that they agree).  The mask
codes and the file-level dataset names are declared here too, so a reader needs nothing
from the generator.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from articulated_dataset import FORMAT_VERSION
from articulated_dataset.core.errors import DataFormatError


@dataclass(frozen=True)
class Field:
    """One field (dataset) of a shard: its name, dtype, shape (symbols ``N``, ``J``, ``H``, ``W``, ``P`` and ints),
    units, frame and description."""
    name: str
    dtype: str
    shape: tuple  # symbols ("N", "J", "H", "W", "P") and ints
    units: str
    frame: str
    description: str


FIELDS: tuple[Field, ...] = (
    Field("depth", "float32", ("N", "H", "W"), "m", "optical",
          "z-depth along the optical axis; 0 where nothing was hit. Values are multiples of the "
          "root attribute depth_quantum_m."),
    Field("mask", "uint8", ("N", "H", "W"), "-", "image",
          "0 background, 1 body, 2 + j moving part of joint j (handles belong to their part); "
          "format 1.1 adds 254 occluder, 255 scene (--occluders, --scene)."),
    Field("q", "float32", ("N", "J"), "rad | m", "joint",
          "configuration per joint: radians (revolute) or metres (prismatic); 0 = closed, >= 0."),
    Field("axis_origin", "float32", ("N", "J", 3), "m", "camera",
          "canonical point on the joint axis (revolute: on the hinge line at the middle of the part's "
          "extent along the axis; prismatic: centre of the part's front face at q = 0)."),
    Field("axis_direction", "float32", ("N", "J", 3), "-", "camera",
          "unit joint axis; positive q opens (right-hand rule for revolute joints)."),
    Field("axis_pose", "float32", ("N", "J", 7), "m, quaternion (w,x,y,z)", "camera",
          "axis frame: position = axis_origin; z = axis_direction; x towards the part centre (revolute) "
          "or the object's up direction (prismatic); y = z x x."),
    Field("part_offset", "float32", ("N", "J", 3), "m", "axis",
          "moving part's centre at q = 0 in the axis frame (x = radius of rotation for a door)."),
    Field("object_pose", "float32", ("N", 7), "m, quaternion (w,x,y,z)", "camera",
          "centre of the object's base and its orientation."),
    Field("object_yaw", "float32", ("N",), "rad", "camera", "rotation of the object about z (0 = front faces the camera)."),
    Field("geometry", "float32", ("N", 4), "m, m, m, -", "object",
          "body depth, width, height and chirality (0: hinge of joint 0 on the object's left; 1: right)."),
    Field("visible_pixels", "int32", ("N", "P"), "px", "image", "pixels of the body and of each moving part."),
    Field("object_index", "int64", ("N",), "-", "-", "index of the object within its split."),
    Field("image_index", "int32", ("N",), "-", "-", "index of the image within its object."),
    Field("sample_id", "int64", ("N",), "-", "-",
          "stable 63-bit id of the image: hash of (class, split, seed, object_index, image_index)."),
    Field("class", "S32", ("N",), "-", "-", "object class name (ASCII)."),
)
FIELDS_BY_NAME = {f.name: f for f in FIELDS}

#: Fields stored only by splits generated with ``--scene`` or ``--occluders`` (format 1.1):
#: readers of other splits never see them, and every loop over :data:`FIELDS` is unchanged.
OPTIONAL_FIELDS: tuple[Field, ...] = (
    Field("unoccluded_pixels", "int32", ("N", "P"), "px", "image",
          "pixels of the body and of each moving part in a render of the object alone (no scene, no occluders)."),
    Field("visible_fraction", "float32", ("N", "P"), "-", "image",
          "visible_pixels / unoccluded_pixels per body and moving part (1 where the part alone covers no pixel); "
          "the moving parts' values lie in the range of the shard attribute occluders (or scene)."),
)
OPTIONAL_FIELDS_BY_NAME = {f.name: f for f in OPTIONAL_FIELDS}
#: Format version of splits that store :data:`OPTIONAL_FIELDS` (and mask codes
#: :data:`MASK_SCENE`/:data:`MASK_OCCLUDER`); other splits keep FORMAT_VERSION (1.0).
CONTEXT_FORMAT_VERSION = "1.1"

#: Fields stored only by splits generated with ``--rgb`` (format 1.2; with or without the
#: context fields): readers of depth-only splits never see them.
RGB_FIELDS: tuple[Field, ...] = (
    Field("rgb", "uint8", ("N", "H", "W", 3), "-", "image",
          "colour image from the depth's camera (sRGB-ish 8-bit, row 0 at the top), randomised materials, "
          "textures and lights (shard attribute appearance); (0, 0, 0) exactly where depth hits nothing."),
)
RGB_FIELDS_BY_NAME = {f.name: f for f in RGB_FIELDS}
RGB_FORMAT_VERSION = "1.2"


def format_version_for(has_context: bool, rgb: bool = False) -> str:
    """The format version a split is written with: 1.2 with colour images, 1.1 with
    scene/occluders, else 1.0."""
    return RGB_FORMAT_VERSION if rgb else CONTEXT_FORMAT_VERSION if has_context else FORMAT_VERSION

#: Joint types (the shards' ``joint_types`` attribute), declared with the units of ``q``.
from articulated_dataset.core.units import JOINT_TYPES, PRISMATIC, REVOLUTE  # noqa: E402, F401

#: Mask values: 0 background, 1 body (everything not moved by a joint), 2 + j moving part j.
MASK_BACKGROUND = 0
MASK_BODY = 1
MASK_FIRST_PART = 2
#: Format 1.1 (``--scene``, ``--occluders``): scene geometry (floor, wall, counter, neighbouring
#: units) and occluding shapes; never a part code (at most 252 joints).
MASK_SCENE = 255
MASK_OCCLUDER = 254
CONTEXT_MASK_CODES = (MASK_OCCLUDER, MASK_SCENE)


def object_on_border(mask: np.ndarray) -> np.ndarray:
    """Per image of a mask stack (N, H, W) (or one (H, W) mask: a 0-d result), whether a pixel of
    the object (its body or a moving part: codes 1 to 253, not :data:`CONTEXT_MASK_CODES`) lies on
    the image's border rows or columns.  An image where it is False shows the whole object
    (``generate --framing whole``; ``benchmarks/error_sources.py``)."""
    mask = np.asarray(mask)
    obj = (mask >= MASK_BODY) & ~np.isin(mask, CONTEXT_MASK_CODES)
    # (mypy types any(-1) as an array or a numpy bool; one (H, W) mask gives the 0-d numpy bool)
    return obj[..., 0, :].any(-1) | obj[..., -1, :].any(-1) | obj[..., :, 0].any(-1) | obj[..., :, -1].any(-1)  # type: ignore[return-value]


def visible_pixels(mask: np.ndarray, n_joints: int) -> np.ndarray:
    """Pixel counts (1 + J,) of the body and of each moving part in a mask (the
    ``visible_pixels`` field)."""
    counts = np.bincount(mask.ravel(), minlength=MASK_FIRST_PART + n_joints)
    return counts[MASK_BODY : MASK_FIRST_PART + n_joints].astype(np.int32)
IMAGE_FIELDS = ("depth", "mask")
LABEL_FIELDS = tuple(f.name for f in FIELDS if f.name not in IMAGE_FIELDS)

#: File-level datasets (not per image).
K_DATASET = "K"  # (3, 3) float64, OpenCV intrinsics, pixel centres at integer coordinates
R_DATASET = "R_camera_to_optical"  # (3, 3) float64, p_optical = R p_camera

#: Root attributes every shard carries.
ROOT_ATTRS = (
    "format_version", "class_name", "split", "seed", "n_objects", "object_start", "object_stop",
    "images_per_object", "n_joints", "joint_names", "joint_types", "image_width", "image_height",
    "vfov_deg", "depth_quantum_m", "min_part_pixels", "sampling_table", "package_version",
)


def resolve_shape(shape: tuple, *, N: int, J: int, H: int, W: int) -> tuple[int, ...]:
    """``shape`` with its symbols replaced by sizes: ``N`` images, ``J`` joints, ``H`` x ``W`` pixels, ``P`` = 1 + J
    parts."""
    sizes = {"N": N, "J": J, "H": H, "W": W, "P": 1 + J}
    return tuple(sizes[s] if isinstance(s, str) else int(s) for s in shape)


def validate_arrays(arrays: Mapping[str, Any], *, N: int, J: int, H: int, W: int, where: str = "") -> None:
    """Check that ``arrays`` holds every field with the declared dtype and shape.

    Raises :class:`DataFormatError` naming the first offending field.
    """
    prefix = f"{where}: " if where else ""
    for f in FIELDS:
        if f.name not in arrays:
            raise DataFormatError(f"{prefix}missing dataset {f.name!r}")
        a = arrays[f.name]
        expected = resolve_shape(f.shape, N=N, J=J, H=H, W=W)
        if tuple(a.shape) != expected:
            raise DataFormatError(f"{prefix}dataset {f.name!r} has shape {tuple(a.shape)}, expected {expected}")
        if np.dtype(a.dtype) != np.dtype(f.dtype):
            raise DataFormatError(f"{prefix}dataset {f.name!r} has dtype {a.dtype}, expected {f.dtype}")
    for f in OPTIONAL_FIELDS + RGB_FIELDS:  # only where present
        if f.name in arrays:
            a = arrays[f.name]
            expected = resolve_shape(f.shape, N=N, J=J, H=H, W=W)
            if tuple(a.shape) != expected or np.dtype(a.dtype) != np.dtype(f.dtype):
                raise DataFormatError(f"{prefix}dataset {f.name!r} is {a.dtype} {tuple(a.shape)}, expected {f.dtype} {expected}")


def check_version(version: str, where: str = "") -> None:
    """Raise :class:`DataFormatError` when ``version``'s major number is not the one this package reads; ``where``
    prefixes the message."""
    major = str(version).split(".")[0]
    if major != FORMAT_VERSION.split(".")[0]:
        raise DataFormatError(
            f"{where + ': ' if where else ''}format version {version} is not readable by this package "
            f"(reads {FORMAT_VERSION.split('.')[0]}.x)"
        )


def markdown_table() -> str:
    """The schema as a Markdown table (used to build docs/format.md)."""
    rows = ["| dataset | dtype | shape | units | frame | meaning |", "|---|---|---|---|---|---|"]
    for f in FIELDS + OPTIONAL_FIELDS + RGB_FIELDS:
        shape = "(" + ", ".join(str(s) for s in f.shape) + ")"
        optional = (" (format 1.1, splits with --scene or --occluders only)" if f in OPTIONAL_FIELDS
                    else " (format 1.2, splits with --rgb only)" if f in RGB_FIELDS else "")
        cells = [f"`{f.name}`", f.dtype, shape, f.units, f.frame, f.description + optional]
        rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(rows)


if __name__ == "__main__":  # pragma: no cover - prints the field table for the docs
    print(markdown_table())
