"""What ``artdata info`` reports of a split: counts, settings and label ranges.

:func:`summarize_split` reads one split folder through :class:`~articulated_dataset.format.Split`
and returns a JSON-ready dict: the manifest's counts and settings (sampling table, scene,
occluders, camera, framing) and min/mean/max of the main labels per named column (with units).
"""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.core.mujoco_support import recorded_mujoco_version
from articulated_dataset.format.manifest import DEFAULT_FRAMING, MANIFEST_NAME
from articulated_dataset.format.shards import json_list
from articulated_dataset.format.split import Split

_SUMMARY_FIELDS = ("q", "axis_origin", "geometry", "object_yaw", "visible_pixels")
#: Summarised too where a split has a scene or occluders (format 1.1 stores it).
_CONTEXT_FIELDS = ("visible_fraction",)


def summarize_split(split_dir) -> dict:
    """Counts, settings and min/mean/max of the main labels of one split folder."""
    split = Split(split_dir)
    try:
        summary = _manifest_summary(split_dir, split.manifest)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        split.close()
        raise DataFormatError(f"{split_dir / MANIFEST_NAME}: corrupt manifest ({type(exc).__name__}: {exc})") from None
    context = summary["scene"] != "none" or summary["occluders"] > 0
    stats = split.read_fields(_SUMMARY_FIELDS + (_CONTEXT_FIELDS if context else ()))
    joint_names, joint_types = _joints(split)
    split.close()
    for k, a in stats.items():
        a = a.astype(np.float64)
        a = a.reshape(a.shape[0], -1)
        summary["labels"][k] = {**_column_stats(a), "columns": _columns(k, a.shape[1], joint_names, joint_types)}
    return summary


def _column_stats(a: np.ndarray) -> dict:
    """min/mean/max of each column over its labelled (non-NaN) values, and their count; None
    where a column has none (a real split's labels are NaN where a capture does not give them)."""
    labelled = ~np.isnan(a)
    out = {"min": [], "mean": [], "max": [], "n_labelled": labelled.sum(0).tolist()}
    for column, ok in zip(a.T, labelled.T):
        values = column[ok]
        for key, fn in (("min", np.min), ("mean", np.mean), ("max", np.max)):
            out[key].append(round(float(fn(values)), 4) if values.size else None)
    return out


def _joints(split: Split) -> tuple[list[str], list[str]]:
    """Joint names and types from the first shard's attributes (empty if unreadable)."""
    return split.joint_names(), json_list(split.attrs.get("joint_types", "[]")) or []


def _columns(field: str, width: int, names: list[str], types: list[str]) -> list[dict]:
    """Name and unit of every column of a summarised label (docs/format.md)."""
    J = len(names)
    if field == "q" and width == J:
        return [{"name": f"q {n}", "unit": "m" if t == "prismatic" else "rad"} for n, t in zip(names, types)]
    if field == "axis_origin" and width == 3 * J:
        return [{"name": f"origin {n}.{c}", "unit": "m"} for n in names for c in "xyz"]
    if field == "geometry" and width == 4:
        return [{"name": f"geometry {g}", "unit": u} for g, u in (("depth", "m"), ("width", "m"), ("height", "m"),
                                                                   ("chirality", "0: hinge left, 1: right"))]
    if field == "object_yaw" and width == 1:
        return [{"name": "object yaw", "unit": "rad"}]
    if field == "visible_pixels" and width == 1 + J:
        return [{"name": "visible body", "unit": "px"}] + [{"name": f"visible {n}", "unit": "px"} for n in names]
    if field == "visible_fraction" and width == 1 + J:
        return [{"name": f"visible fraction {n}", "unit": ""} for n in ["body", *names]]
    return [{"name": f"{field}[{i}]", "unit": ""} for i in range(width)]


#: Largest count or byte size a manifest may state (a 64-bit integer, as the shards store them).
MAX_MANIFEST_COUNT = 2**63 - 1


def _count(v, what: str) -> int:
    """A manifest count or size: a whole number in [0, 2**63) (10**400 is damage, not a size)."""
    n = int(v)
    if not 0 <= n <= MAX_MANIFEST_COUNT:
        raise ValueError(f"{what} {str(n)[:20]}{'...' if len(str(n)) > 20 else ''} is not a count")
    return n


def _manifest_summary(split_dir, manifest: dict) -> dict:
    return {
        "path": str(split_dir),
        "class": manifest["class_name"],
        "split": str(manifest["split"]),
        "seed": int(manifest["seed"]),
        "format_version": str(manifest["format_version"]),
        "mujoco_version": recorded_mujoco_version(manifest, str(split_dir / MANIFEST_NAME)),  # None: not recorded (real captures)
        "complete": manifest["complete"] is True,  # read_manifest checked it is a boolean
        "objects": _count(manifest["n_objects"], "n_objects"),
        "images": _count(manifest["n_images"], "n_images"),
        "shards": len(manifest["shards"]),
        "bytes": _count(sum(_count(s["bytes"], "bytes") for s in manifest["shards"]), "bytes"),
        "image_size": [_count(manifest["config"]["camera"]["width_px"], "width_px"),
                       _count(manifest["config"]["camera"]["height_px"], "height_px")],
        **_table_summary(manifest["config"]),
        **_context_summary(manifest["config"]),
        "labels": {},
    }


def _table_summary(config: dict) -> dict:
    """The sampling table's kind: ``paper`` (independent uniform sizes of a built-in class),
    ``uniform`` (a third-party class's) or ``realistic`` (``--table realistic``: a joint size
    distribution, whose size classes are listed)."""
    table = config.get("table")
    shape = table.get("shape") if isinstance(table, dict) else None
    if isinstance(shape, dict) and isinstance(shape.get("components"), list):
        names = [str(c.get("name", "?"))[:60] for c in shape["components"] if isinstance(c, dict)]
        return {"table": "realistic", "size_classes": names}
    return {"table": "uniform" if config.get("third_party") else "paper"}


def _context_summary(config: dict) -> dict:
    """Scene, occluders, camera and framing of the split (the manifest records them only when
    used; the paper's setting is scene none, 0 occluders, the fixed camera with its own
    intrinsics, framing table4)."""
    camera = config["camera"]
    intrinsics = camera.get("intrinsics")
    return {"scene": str(config.get("scene", "none")), "occluders": int(config.get("occluders", 0)),
            "framing": str(config.get("framing", DEFAULT_FRAMING)),
            "camera_mount": str(camera.get("mount", "fixed")), "intrinsics": None if intrinsics is None else str(intrinsics)}
