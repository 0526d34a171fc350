"""``artdata estimate``: one depth image in, the object's axis, configuration and size out."""

from __future__ import annotations

import json

import click

from articulated_dataset.cli.options import ClassChoice, no_mirror_option, precision_option, prepare_torch


@click.command("estimate")
@click.argument("depth", type=click.Path(dir_okay=False))
@click.option("--class", "class_name", type=ClassChoice(), required=True, help="Object class of the object in view.")
@click.option("--camera", "camera_path", type=click.Path(dir_okay=False), default=None,
              help="Camera-info JSON/YAML (fx, fy, cx, cy or K; as 'artdata ingest' reads it). "
                   "Default: DEPTH's NAME.camera.json or camera.json next to it.")
@click.option("--mask", "mask_path", type=click.Path(dir_okay=False), default=None,
              help="Object mask PNG (non-zero = object); needed when the image shows a scene around the object "
                   "(or --point / --box instead).")
@click.option("--point", default=None, metavar="U,V",
              help="A pixel on the object (column, row), as a click gives it: the object's pixels are segmented "
                   "from the depth around it (docs/robot_view.md).")
@click.option("--box", default=None, metavar="X0,Y0,X1,Y1",
              help="A box around the object (pixel columns and rows, inclusive), as a detector gives it: the "
                   "object's pixels are segmented from the depth inside it (docs/robot_view.md).")
@click.option("--depth-units", type=click.Choice(["auto", "m", "mm"]), default="auto", show_default=True,
              help="Units of the depth values (auto: 16-bit PNG = mm, float EXR/npy = m).")
@click.option("--model", default="dense", show_default=True,
              help="'dense' (shipped weights), 'dense-kinect2' (shipped weights for a real sensor's noisy depth) "
                   "or a dense checkpoint file.")
@no_mirror_option
@precision_option
@click.option("--json", "as_json", is_flag=True, help="Print the estimate as JSON.")
@click.option("--threads", type=int, default=1, show_default=True,
              help="CPU threads for torch (one image gains little from more, and loses much on a busy machine).")
def estimate_cmd(depth, class_name, camera_path, mask_path, point, box, depth_units, model, no_mirror, precision, as_json,
                 threads):
    """Estimate the articulation (axis origin and direction, q, size, uncertainty) of the object in DEPTH.

    DEPTH is a 16-bit PNG in millimetres, an EXR or a .npy in metres.  Results are in the
    camera frame (x forward, y left, z up) in metres; the summary prints a door's opening q in
    degrees, --json gives it in radians (a drawer's in metres in both).
    """
    from articulated_dataset.methods.estimation import estimate_file

    est = estimate_file(depth, class_name, camera_path=camera_path, mask_path=mask_path, depth_units=depth_units,
                        model=model, mirror=not no_mirror, precision=precision,
                        before_model=lambda: prepare_torch(threads), point=_coords(point), box=_coords(box))
    click.echo(json.dumps(est.to_dict(), indent=2) if as_json else est.summary())


def _coords(text: str | None):
    """``U,V`` or ``X0,Y0,X1,Y1`` as a tuple of ints; text that is not is passed on as it is, and the
    library's one-line error names the form it takes."""
    if text is None:
        return None
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        return text


COMMANDS = [estimate_cmd]
