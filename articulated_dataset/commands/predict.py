"""``artdata predict``: run a trained MDN on a split and write predictions.h5."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ..errors import UserError
from .train import _prepare_torch


@click.command("predict")
@click.option("--model", "model_path", type=click.Path(dir_okay=False), required=True, help="Checkpoint from 'artdata train'.")
@click.option("--data", type=click.Path(), required=True, help="Split folder to predict, e.g. data/cabinet/test.")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="predictions.h5 to write (for 'artdata score').")
@click.option("--estimate", type=click.Choice(["mean-of-best", "mode"]), default="mean-of-best", show_default=True,
              help="Point estimate: mean of the heaviest component, or the mixture's mode (fixed-point search).")
@click.option("--snap-to-cloud", is_flag=True,
              help="Move each axis origin to the segmented depth point most likely under the mixture (paper, Table 2).")
@click.option("--method", default=None, help="Method name in the file and the score table (default: MDN or MDN-small).")
@click.option("--batch-size", type=int, default=256, show_default=True, help="Images per forward pass.")
@click.option("--device", default="auto", show_default=True, help="auto (GPU if present), cpu, cuda or cuda:N.")
@click.option("--threads", type=int, default=None, help="CPU threads for torch (default: all cores of this process).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or summary.")
def predict_cmd(model_path, data, out, estimate, snap_to_cloud, method, batch_size, device, threads, overwrite, quiet):
    """Predict axis poses, configurations, geometry and the full mixture for every image of a split."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as predictions.h5")
    _prepare_torch(threads)
    from ..mdn.predict import predict_split
    from ..mdn.train import load_checkpoint
    from ..predictions import write_predictions

    t0 = time.perf_counter()
    ckpt = load_checkpoint(model_path)
    preset = ckpt["train_config"].get("preset", "full")
    name = method or ("MDN" if preset == "full" else f"MDN-{preset}")
    class_name, arrays = predict_split(model_path, data, estimate=estimate, snap_to_cloud=snap_to_cloud,
                                       batch_size=batch_size, device=device, progress=not quiet)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_predictions(out, name, {class_name: arrays},
                      attrs={"model": str(model_path), "estimate": estimate, "snap_to_cloud": int(snap_to_cloud),
                             "epochs": int(ckpt["epoch"]), "preset": preset})
    if not quiet:
        n = len(arrays["sample_id"])
        click.echo(f"{out}: {n} {class_name} images predicted by {name} ({estimate}"
                   f"{', snapped to the cloud' if snap_to_cloud else ''}) in {time.perf_counter() - t0:.1f} s")


COMMANDS = [predict_cmd]
