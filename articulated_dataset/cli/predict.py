"""``artdata predict``: run a shipped model or a trained checkpoint on a split and write predictions.h5."""

from __future__ import annotations

import time
from pathlib import Path

import click

from articulated_dataset.cli.options import (
    no_mirror_option,
    precision_option,
    prepare_torch,
    resolve_split_folder,
    split_folder,
)
from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.prompts import PROMPT_KINDS


@click.command("predict")
@click.option("--model", "model_path", required=True,
              help="A shipped model (dense, dense-kinect2, mdn-small; see 'artdata models') or a checkpoint file from 'artdata train'.")
@split_folder
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="predictions.h5 to write (for 'artdata score').")
@click.option("--as-class", default=None,
              help="Read a third-party split (generate --urdf) as this built-in class: its joints must be the "
                   "class's, in order; the class's model predicts it and 'artdata score' compares with its labels.")
@click.option("--estimate", type=click.Choice(["mean-of-best", "mode"]), default="mean-of-best", show_default=True,
              help="MDN point estimate: mean of the heaviest component, or the mixture's mode (fixed-point search). "
                   "The dense model always gives its heaviest vote mode.")
@click.option("--snap-to-cloud", is_flag=True,
              help="MDN: move each axis origin to the segmented depth point most likely under the mixture (paper, Table 2).")
@click.option("--object-mask", is_flag=True,
              help="Dense model: keep only the object's pixels (the split's mask codes), as a robot's segmentation "
                   "would; for splits made with --scene or --occluders (the same as --prompt mask).")
@click.option("--prompt", type=click.Choice(PROMPT_KINDS), default=None,
              help="Dense model: segment each image's object from the prompt a robot would have, simulated from "
                   "the split's mask: a click (point), a detector's box (box), the mask itself, or none (the "
                   "object found in the depth; an image where none is found gets no prediction) "
                   "(docs/robot_view.md).")
@no_mirror_option
@precision_option
@click.option("--method", default=None, help="Method name in the file and the score table (default: dense, MDN or MDN-small).")
@click.option("--batch-size", type=int, default=None, help="Images per forward pass (default: MDN 256, dense 128).")
@click.option("--device", default="auto", show_default=True, help="auto (GPU if present), cpu, cuda or cuda:N.")
@click.option("--threads", type=int, default=None, help="CPU threads for torch (default: all cores of this process).")
@click.option("--workers", type=int, default=None,
              help="Dense model: processes that share the images, each with --threads divided among them "
                   "(default: one per thread for splits of 4,096 images or more, else 1: this process).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or summary.")
def predict_cmd(model_path, data_dir, data_option, out, as_class, estimate, snap_to_cloud, object_mask, prompt, no_mirror, precision, method, batch_size,
                device, threads, workers, overwrite, quiet):
    """Predict axis poses, configurations, geometry and the full mixture for every image of the split
    in DIR (a split folder, e.g. data/cabinet/test)."""
    from articulated_dataset.core.safeio import check_can_create, check_name_length, check_outputs_distinct

    data = resolve_split_folder(data_dir, data_option)

    out = Path(out)
    check_name_length(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as predictions.h5")
    from articulated_dataset.methods.mdn.data import resolve_split_dir

    # the checkpoint and the split read are never written over (beside the split, as data/p.h5, is fine)
    check_outputs_distinct([model_path], [out], input_folders=[resolve_split_dir(data)])
    check_can_create(out)  # before predicting: a parent that is a file, /proc, a read-only folder is one line now
    prepare_torch(threads)
    from articulated_dataset.methods.predict import predict_to_file

    t0 = time.perf_counter()
    run = predict_to_file(model_path, data, out, estimate=estimate, snap_to_cloud=snap_to_cloud, object_mask=object_mask,
                          method=method, batch_size=batch_size, device=device, mirror=not no_mirror,
                          workers=workers, precision=precision, progress=not quiet, as_class=as_class, prompt=prompt)
    if not quiet:
        click.echo(f"{out}: {run.n_images} {run.class_name} images predicted by {run.method}"
                   f"{' (snapped to the cloud)' if snap_to_cloud else ''} in {time.perf_counter() - t0:.1f} s")

COMMANDS = [predict_cmd]
