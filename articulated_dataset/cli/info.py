"""``artdata info``: counts, settings and label ranges of generated splits."""

from __future__ import annotations

import json

import click

from articulated_dataset.format import find_split_dirs
from articulated_dataset.format.manifest import DEFAULT_FRAMING, printable
from articulated_dataset.format.summary import summarize_split


def _settings_line(s: dict) -> str | None:
    """``scene kitchen, 2 occluders per image, camera head, intrinsics d435, framing whole``: the options
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
    if s.get("framing", DEFAULT_FRAMING) != DEFAULT_FRAMING:
        parts.append(f"framing {s['framing']}")
    return ", ".join(parts) or None


def _echo(line: str) -> None:
    """Print one line of the summary; names read from the data (split, joint and size-class
    names, folder names) may hold control characters, which are escaped."""
    click.echo(printable(line))


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
        mujoco = f", MuJoCo {s['mujoco_version']}" if s["mujoco_version"] is not None else ""
        _echo(f"{s['path']}: class {s['class']}, split {s['split']}, seed {s['seed']}, format {s['format_version']}{mujoco}, {state}")
        _echo(f"  {s['objects']} objects, {s['images']} images, {s['shards']} shards, "
              f"{s['bytes'] / max(s['images'], 1):.0f} bytes/image, {s['image_size'][0]}x{s['image_size'][1]} px")
        settings = _settings_line(s)
        if settings is not None:
            _echo(f"  {settings}")
        if s["table"] == "realistic":
            _echo(f"  table realistic: {len(s['size_classes'])} size classes ({'; '.join(s['size_classes'])})")
        rows = [(printable(f"{c['name']} ({c['unit']})" if c["unit"] else c["name"]), c["unit"], v["min"][i], v["mean"][i], v["max"][i],
                 v["n_labelled"][i]) for v in s["labels"].values() for i, c in enumerate(v["columns"])]
        if rows:
            partial = any(n < s["images"] for *_, n in rows)  # a real split: say how many images give each label
            w = max(len(r[0]) for r in rows)
            _echo(f"  {'label':{w}s}  {'min':>10s}  {'mean':>10s}  {'max':>10s}" + ("  labelled" if partial else ""))
            for name, unit, lo, mean, hi, n in rows:
                _echo(f"  {name:{w}s}  {_cell(lo, unit):>10s}  {_cell(mean, unit):>10s}  {_cell(hi, unit):>10s}"
                      + (f"  {n:>8,d}" if partial else ""))


COMMANDS = [info_cmd]
