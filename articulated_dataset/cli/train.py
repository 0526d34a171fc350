"""``artdata train``: train one class's estimator: the dense voting network (``--model dense``)
or the paper's ResNet-18 mixture density network (``--model mdn``, the default)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from articulated_dataset.cli.options import (
    ClassChoice,
    error_message,
    prepare_torch,
    resolve_split_folders,
    split_folders,
)
from articulated_dataset.core.errors import UserError


@click.command("train")
@click.option("--model", "model_kind", type=click.Choice(["dense", "mdn"]), default="dense", show_default=True,
              help="dense: the per-pixel voting network of the shipped models (docs/dense.md); mdn: the paper's "
                   "ResNet-18 mixture density network (docs/model.md).")
@click.option("--class", "class_name", type=ClassChoice(), required=True, help="Object class (one network per class).")
@split_folders
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="Checkpoint file (written after every epoch).")
@click.option("--small", is_flag=True, help="mdn: reduced network at 96x54 input: minutes per class on a 2-core CPU.")
@click.option("--epochs", type=int, default=None, help="Epochs (default: mdn 30, or 8 with --small; dense 2).")
@click.option("--batch-size", type=int, default=None, help="Images per step (default: mdn 128, or 64 with --small; dense 64).")
@click.option("--lr", type=float, default=None, help="Peak learning rate of AdamW (default: mdn 1e-3, or 2e-3 with --small; dense 3e-3).")
@click.option("--components", type=int, default=None, help="mdn: mixture components (default 20).")
@click.option("--width", type=int, default=None, help="dense: base channel width of the network (default 16).")
@click.option("--init-from", type=click.Path(dir_okay=False), default=None,
              help="dense: start from this checkpoint's weights with a fresh schedule (continue a finished training).")
@click.option("--origin-weight", type=float, default=None,
              help="dense: multiplies the axis-origin loss terms (default 1).")
@click.option("--noise", default=None,
              help="dense: a depth-noise model (kinect2, d435 or azure-kinect) applied to --noise-fraction of each batch's images, "
                   "drawn afresh every epoch (docs/real_data.md).")
@click.option("--noise-fraction", type=float, default=None, help="dense: the share of each batch --noise corrupts (default 0.5).")
@click.option("--prompts", default=None, metavar="KIND,...",
              help="dense: in splits with a scene or occluders, segment each image's object from a simulated "
                   "prompt of these kinds in turn (point, box, mask, none; as predict --prompt), as a robot's "
                   "images will be (docs/robot_view.md).")
@click.option("--val-fraction", type=float, default=None,
              help="Fraction of the training split's OBJECTS held out for validation (0: none; default: mdn 0.1, dense 0.05).")
@click.option("--mix-weights", default=None, metavar="W1,W2,...",
              help="dense, several DIRs: each batch draws its images from the splits in proportion to these "
                   "weights, one per DIR (default: to the splits' sizes).")
@click.option("--max-objects", type=int, default=None, help="Train on the first N objects of the split only.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initialisation, validation split and batch order.")
@click.option("--device", default="auto", show_default=True, help="auto (GPU if present), cpu, cuda or cuda:N.")
@click.option("--threads", type=int, default=None, help="CPU threads for torch (default: all cores of this process).")
@click.option("--resume", is_flag=True, help="Continue the interrupted training stored in --out (same options).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars or per-epoch lines.")
def train_cmd(model_kind, class_name, data_dirs, data_option, out, small, epochs, batch_size, lr, components, width, init_from,
              origin_weight, noise, noise_fraction, prompts, val_fraction, mix_weights, max_objects, seed, device, threads,
              resume, quiet):
    """Train one class's estimator on the training split in DIR (a split folder, e.g. data/cabinet/train;
    checkpoints after every epoch; --resume continues).  --model dense reads several DIRs as one
    mixture (weighted by --mix-weights)."""
    data = resolve_split_folders(data_dirs, data_option)
    weights = None if mix_weights is None else parse_weights(mix_weights)
    prepare_torch(threads)
    from articulated_dataset.methods.train import TrainingInterrupted, TrainSettings, train_model

    settings = TrainSettings(class_name=class_name, data=tuple(Path(d) for d in data), out=Path(out), small=small,
                             epochs=epochs, batch_size=batch_size, lr=lr, components=components, width=width,
                             init_from=init_from, origin_weight=origin_weight, noise=noise,
                             noise_fraction=noise_fraction, val_fraction=val_fraction, max_objects=max_objects,
                             seed=seed, device=device, mix_weights=None if weights is None else tuple(weights),
                             prompts=None if prompts is None else tuple(k.strip() for k in prompts.split(",")))
    t0 = time.perf_counter()
    try:
        run = train_model(model_kind, settings, resume=resume, progress=not quiet, echo=None if quiet else click.echo)
    except TrainingInterrupted as exc:
        raise click.ClickException(error_message(exc)) from None
    if not quiet:
        click.echo(f"{out}: {run.summary} in {time.perf_counter() - t0:.0f} s")


def parse_weights(text: str) -> list[float]:
    """``--mix-weights W1,W2,...`` as numbers (anything else is one line)."""
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise UserError(f"--mix-weights must be comma-separated numbers, got {text[:80]!r}") from None


COMMANDS = [train_cmd]
