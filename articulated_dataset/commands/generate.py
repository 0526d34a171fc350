"""``artdata generate``: render a class's objects into labelled HDF5 shards."""

from __future__ import annotations

import os
import time

import click

from ..camera import DEFAULT_HEIGHT_PX, DEFAULT_WIDTH_PX, KINECT_V2_VFOV_DEG, CameraConfig
from ..errors import UserError
from ..pipeline import DEFAULT_IMAGES_PER_OBJECT, DEFAULT_OBJECTS_PER_SHARD, DEFAULT_SEED, GenerationConfig, generate_split
from ..registry import class_names, get_class
from ..tables import load_table_file


class _ClassChoice(click.ParamType):
    """Class names from the registry (validated lazily so --help lists them)."""

    name = "class"

    def get_metavar(self, param, ctx=None):
        return "[" + "|".join(class_names()) + "]"

    def convert(self, value, param, ctx):
        try:
            return get_class(value).name
        except UserError as exc:
            self.fail(str(exc), param, ctx)


@click.command("generate")
@click.option("--class", "class_name", type=_ClassChoice(), required=True, help="Object class to generate.")
@click.option("--n", "n_objects", type=int, default=100, show_default=True, help="Number of objects (each gives --images images).")
@click.option("--split", default="train", show_default=True, help="Split name (train, val, test...); splits never share objects.")
@click.option("--out", "out_root", type=click.Path(file_okay=False), default="data", show_default=True, help="Output root: shards go to OUT/<class>/<split>/.")
@click.option("--seed", type=int, default=DEFAULT_SEED, show_default=True, help="Dataset seed (object k depends only on seed, class, split, k).")
@click.option("--images", "images_per_object", type=int, default=DEFAULT_IMAGES_PER_OBJECT, show_default=True, help="Images (configurations) per object.")
@click.option("--objects-per-shard", type=int, default=DEFAULT_OBJECTS_PER_SHARD, show_default=True)
@click.option("--width", type=int, default=DEFAULT_WIDTH_PX, show_default=True, help="Image width (px).")
@click.option("--height", type=int, default=DEFAULT_HEIGHT_PX, show_default=True, help="Image height (px).")
@click.option("--vfov", type=float, default=KINECT_V2_VFOV_DEG, show_default=True, help="Vertical field of view (deg).")
@click.option("--table", "table_file", type=click.Path(dir_okay=False), default=None, help="JSON/TOML file overriding (part of) the class's sampling table.")
@click.option("--workers", type=int, default=None, help="Worker processes (default: all cores).")
@click.option("--resume", is_flag=True, help="Continue an interrupted run of the same command.")
@click.option("--overwrite", is_flag=True, help="Replace existing data of this class and split.")
@click.option("--mean", "mean_object", is_flag=True, help="Render the class's mean object (centre of every range) into OUT/<class>/mean/.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def generate_cmd(class_name, n_objects, split, out_root, seed, images_per_object, objects_per_shard, width, height,
                 vfov, table_file, workers, resume, overwrite, mean_object, quiet):
    """Generate labelled depth images of one object class into HDF5 shards."""
    obj_class = get_class(class_name)
    table = obj_class.table
    if table_file:
        table = table.override(load_table_file(table_file))
    try:
        camera = CameraConfig(width, height, vfov)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if mean_object:
        n_objects = 1
    if workers is None:
        workers = os.cpu_count() or 1
    if workers <= 0:
        raise UserError(f"--workers must be positive, got {workers}")
    config = GenerationConfig(
        class_name=class_name, split=split, n_objects=n_objects, seed=seed, images_per_object=images_per_object,
        objects_per_shard=objects_per_shard, camera=camera, table=table, mean=mean_object,
    )
    t0 = time.perf_counter()
    try:
        split_dir = generate_split(config, out_root, workers=workers, resume=resume, overwrite=overwrite, progress=not quiet)
    except KeyboardInterrupt:
        raise click.ClickException(
            "interrupted; completed shards are kept. Continue with the same command plus --resume"
        ) from None
    seconds = time.perf_counter() - t0
    if not quiet:
        from ..shards import read_manifest

        m = read_manifest(split_dir)
        n_bytes = sum(s["bytes"] for s in m["shards"])
        n_img = max(m["n_images"], 1)
        click.echo(
            f"{split_dir}: {m['n_objects']} objects, {m['n_images']} images in {seconds:.1f} s "
            f"({m['n_images'] / max(seconds, 1e-9):.0f} images/s, {n_bytes / n_img:.0f} bytes/image)"
        )


COMMANDS = [generate_cmd]
