"""``artdata info``: counts, settings and label ranges of generated splits."""

from __future__ import annotations

import json

import click
import numpy as np

from ..errors import DataFormatError
from ..format import MANIFEST_NAME, Split, find_split_dirs

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
    try:
        attrs = split.attrs
        return list(json.loads(attrs.get("joint_names", "[]"))), list(json.loads(attrs.get("joint_types", "[]")))
    except (ValueError, TypeError):
        return [], []


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


def _manifest_summary(split_dir, manifest: dict) -> dict:
    return {
        "path": str(split_dir),
        "class": manifest["class_name"],
        "split": str(manifest["split"]),
        "seed": int(manifest["seed"]),
        "format_version": str(manifest["format_version"]),
        "complete": bool(manifest["complete"]),
        "objects": int(manifest["n_objects"]),
        "images": int(manifest["n_images"]),
        "shards": len(manifest["shards"]),
        "bytes": int(sum(int(s["bytes"]) for s in manifest["shards"])),
        "image_size": [int(manifest["config"]["camera"]["width_px"]), int(manifest["config"]["camera"]["height_px"])],
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
    """Scene, occluders and camera of the split (the manifest records them only when used;
    the paper's setting is scene none, 0 occluders, the fixed camera with its own intrinsics)."""
    camera = config["camera"]
    intrinsics = camera.get("intrinsics")
    return {"scene": str(config.get("scene", "none")), "occluders": int(config.get("occluders", 0)),
            "camera_mount": str(camera.get("mount", "fixed")), "intrinsics": None if intrinsics is None else str(intrinsics)}


def _settings_line(s: dict) -> str | None:
    """``scene kitchen, 2 occluders per image, camera head, intrinsics d435``: the options
    beyond the paper's setting, or None for the paper's."""
    parts = []
    if s["scene"] != "none":
        parts.append(f"scene {s['scene']}")
    if s["occluders"]:
        parts.append(f"{s['occluders']} occluder{'s' if s['occluders'] > 1 else ''} per image")
    if s["camera_mount"] != "fixed":
        parts.append(f"camera {s['camera_mount']}")
    if s["intrinsics"] is not None:
        parts.append(f"intrinsics {s['intrinsics']}")
    return ", ".join(parts) or None


def _cell(x: float | None, unit: str) -> str:
    if x is None:
        return "-"
    return f"{x:,.0f}" if unit == "px" else f"{x:.3f}"


@click.command("info")
@click.argument("path", type=click.Path(exists=False))
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def info_cmd(path, as_json):
    """Summarize generated data at PATH (a split folder, a class folder or an output root)."""
    summaries = [summarize_split(d) for d in find_split_dirs(path)]
    if as_json:
        click.echo(json.dumps(summaries, indent=1))
        return
    for s in summaries:
        state = "complete" if s["complete"] else "INCOMPLETE (resume with --resume)"
        click.echo(f"{s['path']}: class {s['class']}, split {s['split']}, seed {s['seed']}, format {s['format_version']}, {state}")
        click.echo(f"  {s['objects']} objects, {s['images']} images, {s['shards']} shards, "
                   f"{s['bytes'] / max(s['images'], 1):.0f} bytes/image, {s['image_size'][0]}x{s['image_size'][1]} px")
        settings = _settings_line(s)
        if settings is not None:
            click.echo(f"  {settings}")
        if s["table"] == "realistic":
            click.echo(f"  table realistic: {len(s['size_classes'])} size classes ({'; '.join(s['size_classes'])})")
        rows = [(f"{c['name']} ({c['unit']})" if c["unit"] else c["name"], c["unit"], v["min"][i], v["mean"][i], v["max"][i],
                 v["n_labelled"][i]) for v in s["labels"].values() for i, c in enumerate(v["columns"])]
        if rows:
            partial = any(n < s["images"] for *_, n in rows)  # a real split: say how many images give each label
            w = max(len(r[0]) for r in rows)
            click.echo(f"  {'label':{w}s}  {'min':>10s}  {'mean':>10s}  {'max':>10s}" + ("  labelled" if partial else ""))
            for name, unit, lo, mean, hi, n in rows:
                click.echo(f"  {name:{w}s}  {_cell(lo, unit):>10s}  {_cell(mean, unit):>10s}  {_cell(hi, unit):>10s}"
                           + (f"  {n:>8,d}" if partial else ""))


COMMANDS = [info_cmd]
