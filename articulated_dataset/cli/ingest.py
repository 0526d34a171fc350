"""``artdata ingest``: convert real depth captures into shards (split ``real``)."""

from __future__ import annotations

import click

from articulated_dataset.core.camera import DEFAULT_HEIGHT_PX, DEFAULT_WIDTH_PX, KINECT_V2_VFOV_DEG, CameraConfig
from articulated_dataset.core.errors import UserError


def _parse_size(text: str | None) -> tuple[int, int] | None:
    from articulated_dataset.core.images.intrinsics import check_source_size

    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--source-size must look like 512x424, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise UserError(f"--source-size must be positive, got {text!r}")
    check_source_size((w, h), "--source-size")
    return w, h


@click.command("ingest")
@click.argument("captures", nargs=-1, required=True, type=click.Path())
@click.option("--class", "class_name", required=True, help="Object class of the captured object.")
@click.option("--out", "out_root", type=click.Path(file_okay=False), default="data", show_default=True,
              help="Output root: shards go to OUT/<class>/<split>/.")
@click.option("--split", default="real", show_default=True, help="Split name (e.g. real, real-open).")
@click.option("--mask", "mask_path", type=click.Path(dir_okay=False), default=None,
              help="Segmentation mask PNG (one capture only; default NAME.mask.png next to it).")
@click.option("--labels", "labels_path", type=click.Path(dir_okay=False), default=None,
              help="Ground-truth JSON (one capture only; default NAME.labels.json next to it).")
@click.option("--intrinsics", "intrinsics_path", type=click.Path(dir_okay=False), default=None,
              help="Camera-info JSON/YAML for every capture (default NAME.camera.json or camera.json next to it).")
@click.option("--fx", type=float, default=None, help="Focal length x (px); with --fy --cx --cy instead of a file.")
@click.option("--fy", type=float, default=None, help="Focal length y (px).")
@click.option("--cx", type=float, default=None, help="Principal point x (px; pixel centres at integers).")
@click.option("--cy", type=float, default=None, help="Principal point y (px).")
@click.option("--source-size", default=None, help="Sensor image size WxH for point clouds (if the camera file has none).")
@click.option("--cloud-frame", type=click.Choice(["optical", "camera"]), default="optical", show_default=True,
              help="Frame of point-cloud coordinates: optical (x right, y down, z forward) or camera (x fwd, y left, z up).")
@click.option("--depth-units", type=click.Choice(["auto", "m", "mm"]), default="auto", show_default=True,
              help="Units of depth values (auto: PNG = mm, float EXR/npy = m).")
@click.option("--fit", type=click.Choice(["training", "crop"]), default="training", show_default=True,
              help="training: resample onto the training intrinsics; crop: crop around the mask and rescale K.")
@click.option("--resample", type=click.Choice(["nearest", "min"]), default="nearest", show_default=True,
              help="Depth resampling: nearest pixel, or minimum depth under each output pixel.")
@click.option("--crop-margin", type=float, default=0.1, show_default=True, help="Margin around the mask for --fit crop (fraction).")
@click.option("--keep-background", is_flag=True, help="Keep depth outside the mask (default: set it to 0 like rendered data).")
@click.option("--width", type=int, default=DEFAULT_WIDTH_PX, show_default=True, help="Training image width (px).")
@click.option("--height", type=int, default=DEFAULT_HEIGHT_PX, show_default=True, help="Training image height (px).")
@click.option("--vfov", type=float, default=KINECT_V2_VFOV_DEG, show_default=True, help="Training vertical field of view (deg).")
@click.option("--like", "like_path", type=click.Path(), default=None,
              help="Take the training camera (size, field of view) from this generated split instead.")
@click.option("--append", is_flag=True, help="Add the captures to an existing real split.")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing real split (one 'artdata ingest' wrote; any other split is refused).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def ingest_cmd(captures, class_name, out_root, split, mask_path, labels_path, intrinsics_path, fx, fy, cx, cy, source_size,
               cloud_frame, depth_units, fit, resample, crop_margin, keep_background, width, height, vfov, like_path,
               append, overwrite, quiet):
    """Convert real depth captures (CAPTURES: depth images, point clouds or folders of them)
    into labelled shards under OUT/<class>/<split>/.

    Next to NAME.png|.exr|.npy|.ply|.pcd the optional files NAME.mask.png, NAME.labels.json (or
    NAME.parts.json: part poses and masks, with objects.json in the folder) and NAME.camera.json
    (or camera.json in the folder) are picked up.  See docs/real_data.md.
    """
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.images.intrinsics import intrinsics_matrix, load_intrinsics
    from articulated_dataset.ingest.capture import IngestOptions
    from articulated_dataset.ingest.split import camera_like, check_training_camera, ingest_split

    get_class(class_name)
    given = [v is not None for v in (fx, fy, cx, cy)]
    if any(given) and not all(given):
        raise UserError("--fx, --fy, --cx and --cy go together (give all four or a camera file)")
    if all(given) and intrinsics_path:
        raise UserError("give either --intrinsics or --fx/--fy/--cx/--cy, not both")
    K = None
    size = _parse_size(source_size)
    if all(given):
        K = intrinsics_matrix(fx, fy, cx, cy, "--fx/--fy/--cx/--cy")
    elif intrinsics_path:
        K, file_size = load_intrinsics(intrinsics_path)
        size = size or file_size
    if like_path:
        camera = camera_like(like_path)
    else:
        try:
            camera = CameraConfig(width, height, vfov)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    check_training_camera(camera)
    options = IngestOptions(camera=camera, fit=fit, resample=resample, crop_margin=crop_margin, depth_units=depth_units,
                            cloud_frame=cloud_frame, keep_background=keep_background, intrinsics=K, source_size=size)
    split_dir, ingested = ingest_split(captures, class_name, out_root, options, split=split, mask_path=mask_path,
                                       labels_path=labels_path, append=append, overwrite=overwrite, progress=not quiet)
    if not quiet:
        n_gt = sum(c.has_labels for c in ingested)
        cut = [c.name for c in ingested if c.mask_fraction_inside < 1.0]
        click.echo(f"{split_dir}: {len(ingested)} captures ingested ({n_gt} with ground truth), "
                   f"{camera.width_px}x{camera.height_px} px, fit {fit}, resample {resample}")
        if cut:
            click.echo(f"warning: {len(cut)} captures are partly outside the training field of view "
                       f"(e.g. {cut[0]}); consider --fit crop", err=True)


COMMANDS = [ingest_cmd]
