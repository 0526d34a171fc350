"""``artdata info``: counts, settings and label ranges of generated splits."""

from __future__ import annotations

import json

import click
import numpy as np

from ..errors import DataFormatError
from ..shards import MANIFEST_NAME, find_split_dirs, open_split

_SUMMARY_FIELDS = ("q", "axis_origin", "geometry", "object_yaw", "visible_pixels")


def summarize_split(split_dir) -> dict:
    """Counts, settings and min/mean/max of the main labels of one split folder."""
    manifest, shards = open_split(split_dir)
    stats: dict[str, list] = {k: [] for k in _SUMMARY_FIELDS}
    for sh in shards:
        for k in _SUMMARY_FIELDS:
            stats[k].append(sh.read(k))
        sh.close()
    try:
        summary = _manifest_summary(split_dir, manifest)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DataFormatError(f"{split_dir / MANIFEST_NAME}: corrupt manifest ({type(exc).__name__}: {exc})") from None
    for k, parts in stats.items():
        if not parts:
            continue
        a = np.concatenate(parts).astype(np.float64)
        a = a.reshape(a.shape[0], -1)
        summary["labels"][k] = {"min": a.min(0).round(4).tolist(), "mean": a.mean(0).round(4).tolist(), "max": a.max(0).round(4).tolist()}
    return summary


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
        "labels": {},
    }


def _fmt(v):
    return "[" + ", ".join(f"{x:.3f}" for x in v) + "]"


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
        for k, v in s["labels"].items():
            click.echo(f"  {k:15s} min {_fmt(v['min'])}  mean {_fmt(v['mean'])}  max {_fmt(v['max'])}")


COMMANDS = [info_cmd]
