"""``artdata baseline {mean,nn,icp}``: the paper's Table 1 baselines, written as predictions.h5."""

from __future__ import annotations

import time

import click

from articulated_dataset.core.errors import UserError


def _common_options(fn):
    options = [
        click.option("--train", "train_dir", type=click.Path(), required=True,
                     help="Training split folder of the class, e.g. data/cabinet/train."),
        click.option("--test", "test_dir", type=click.Path(), required=True,
                     help="Test split folder of the same class, e.g. data/cabinet/test."),
        click.option("--out", type=click.Path(dir_okay=False), required=True,
                     help="predictions.h5 to write (for 'artdata score')."),
        click.option("--overwrite", is_flag=True, help="Replace an existing --out file."),
        click.option("--quiet", "-q", is_flag=True, help="No progress bars or summary."),
    ]
    for opt in reversed(options):
        fn = opt(fn)
    return fn


def _workers_option(fn):
    return click.option("--workers", type=int, default=None,
                        help="Worker processes (default: all cores).")(fn)


def _run(name: str, train_dir, test_dir, out, overwrite: bool, quiet: bool, workers=None, **options) -> None:
    from articulated_dataset.methods.baselines import run_baseline

    t0 = time.perf_counter()
    result = run_baseline(name, train_dir, test_dir, out, workers=workers, progress=not quiet, overwrite=overwrite,
                          **options)
    if not quiet:
        n = len(result.predictions["sample_id"])
        click.echo(f"{out}: {result.method} predictions for {n} {result.class_name} test images "
                   f"in {time.perf_counter() - t0:.1f} s")


@click.group("baseline")
def baseline_group():
    """Run a Table 1 baseline (Mean, NN, ICP) on one class; score the result with 'artdata score'."""


@baseline_group.command("mean")
@_common_options
def mean_cmd(train_dir, test_dir, out, overwrite, quiet):
    """Predict the training-set mean of every label (rotation: chordal L2 mean)."""
    _run("mean", train_dir, test_dir, out, overwrite, quiet, workers=1)


@baseline_group.command("nn")
@_common_options
@_workers_option
@click.option("--normalization", type=click.Choice(["metric", "median"]), default="metric", show_default=True,
              help="Depth normalisation before the L2 distance: metric depth, or minus each image's median depth.")
@click.option("--block", "block_px", type=int, default=4, show_default=True,
              help="Area-downsampling factor (pixels per block side; 192x108 -> 48x27 at 4).")
def nn_cmd(train_dir, test_dir, out, overwrite, quiet, workers, normalization, block_px):
    """Exact nearest neighbour in depth-image space: the closest training image's labels."""
    if block_px <= 0:
        raise UserError(f"--block must be positive, got {block_px}")
    _run("nn", train_dir, test_dir, out, overwrite, quiet, workers=workers, normalization=normalization, block_px=block_px)


@baseline_group.command("icp")
@_common_options
@_workers_option
@click.option("--mean-object", "mean_dir", type=click.Path(), default=None,
              help="Mean-object split of the class (default: <train>/../mean, else rendered once into "
                   "<train>/../.mean-object/).")
@click.option("--limit", type=int, default=None, help="Only the first N test images (quick looks, timing).")
def icp_cmd(train_dir, test_dir, out, overwrite, quiet, workers, mean_dir, limit):
    """Register each test point cloud to the mean object (16 configurations x 16 yaws) with ICP."""
    if limit is not None and limit <= 0:
        raise UserError(f"--limit must be positive, got {limit}")
    _run("icp", train_dir, test_dir, out, overwrite, quiet, workers=workers, mean_dir=mean_dir, limit=limit)


COMMANDS = [baseline_group]
