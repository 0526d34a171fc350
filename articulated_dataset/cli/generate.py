"""``artdata generate``: render a class's objects into labelled HDF5 shards."""

from __future__ import annotations

import importlib.util
import os
import re
import time

import click

from articulated_dataset.cli.options import ClassChoice
from articulated_dataset.core.camera import (
    DEFAULT_HEIGHT_PX,
    DEFAULT_WIDTH_PX,
    INTRINSICS_PRESETS,
    KINECT_V2_VFOV_DEG,
    camera_from_options,
)
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.pool import EXECUTORS, get_executor
from articulated_dataset.format.manifest import (
    DEFAULT_FRAMING,
    DEFAULT_IMAGES_PER_OBJECT,
    DEFAULT_OBJECTS_PER_SHARD,
    DEFAULT_SEED,
    FRAMINGS,
    MAX_OCCLUDERS,
    SCENE_NAMES,
)
from articulated_dataset.generation import generate_split
from articulated_dataset.generation.request import DEFAULT_N_OBJECTS, UrdfOptions, config_from_options
from articulated_dataset.generation.viewpoint import CAMERA_MOUNTS


class _NoiseChoice(click.ParamType):
    """Noise models of :mod:`articulated_dataset.core.noise` (just ``none`` while it does not exist)."""

    name = "noise"

    @staticmethod
    def choices() -> list[str]:
        if importlib.util.find_spec("articulated_dataset.core.noise") is None:
            return ["none"]
        from articulated_dataset.core.noise import NOISE_MODELS

        names = list(NOISE_MODELS)
        return names if "none" in names else ["none", *names]

    def get_metavar(self, param, ctx=None):
        return "[" + "|".join(self.choices()) + "]"

    def convert(self, value, param, ctx):
        if value not in self.choices():
            self.fail(f"unknown noise model {value!r}; choose from: {', '.join(self.choices())}", param, ctx)
        return value


class _ScaleParam(click.ParamType):
    """``--scale``: a number, or ``auto:CLASS`` (kept as text; the importer checks the class)."""

    name = "scale"

    def convert(self, value, param, ctx):
        if isinstance(value, str) and value.strip().lower().startswith("auto:"):
            return value.strip()
        try:
            return float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number or auto:CLASS", param, ctx)


#: ``--address``: ``auto``, ``HOST:PORT`` or a Ray client address ``ray://HOST:PORT``.
_ADDRESS = re.compile(r"^(auto|(ray://)?[^\s:/]+:\d+)$")


@click.command("generate")
@click.option("--class", "class_name", type=ClassChoice(), default=None, help="Object class to generate (or --urdf).")
@click.option("--urdf", "urdf_path", type=click.Path(dir_okay=False), default=None,
              help="Generate a third-party articulated object from this URDF file instead of a --class (docs/third_party_urdf.md).")
@click.option("--joints", "joint_names", default=None, metavar="NAME,...",
              help="With --urdf: joints to articulate, in label order (default: every revolute/prismatic joint with a range; continuous ones only when named).")
@click.option("--class-name", "urdf_class_name", default=None,
              help="With --urdf: class name stored in the shards and used for OUT/<class>/ (default: <folder>-<file stem>).")
@click.option("--skip-missing-meshes", is_flag=True, help="With --urdf: drop mesh references whose file does not exist.")
@click.option("--scale", "urdf_scale", type=_ScaleParam(), default=None, metavar="S|auto:CLASS",
              help="With --urdf: multiply every length of the file (meshes, origins, prismatic limits) by S, or by the "
                   "factor that gives the body a standard size of the built-in CLASS (auto:cabinet; "
                   "docs/third_party_urdf.md)  [default: 1].")
@click.option("--mesh-root", "urdf_mesh_root", type=click.Path(file_okay=False), default=None,
              help="With --urdf: folder meshes may be read from  [default: the URDF's folder].")
@click.option("--n", "n_objects", type=int, default=None,
              help=f"Number of objects (each gives --images images)  [default: {DEFAULT_N_OBJECTS}; 1 with --mean]")
@click.option("--split", default="train", show_default=True, help="Split name (train, val, test...); splits never share objects.")
@click.option("--out", "out_root", type=click.Path(file_okay=False), default="data", show_default=True, help="Output root: shards go to OUT/<class>/<split>/.")
@click.option("--seed", type=int, default=DEFAULT_SEED, show_default=True, help="Dataset seed (object k depends only on seed, class, split, k).")
@click.option("--images", "images_per_object", type=int, default=DEFAULT_IMAGES_PER_OBJECT, show_default=True, help="Images (configurations) per object.")
@click.option("--objects-per-shard", type=int, default=DEFAULT_OBJECTS_PER_SHARD, show_default=True)
@click.option("--width", type=int, default=None, help=f"Image width (px)  [default: {DEFAULT_WIDTH_PX}, or the --intrinsics sensor's]")
@click.option("--height", type=int, default=None, help=f"Image height (px)  [default: {DEFAULT_HEIGHT_PX}, or the --intrinsics sensor's]")
@click.option("--resolution", default=None, metavar="WxH", help="Image size in pixels, e.g. 640x480 (instead of --width/--height).")
@click.option("--vfov", type=float, default=None, help=f"Vertical field of view (deg) of the paper's camera  [default: {KINECT_V2_VFOV_DEG}]")
@click.option("--intrinsics", type=click.Choice(list(INTRINSICS_PRESETS)), default=None,
              help="A depth sensor's intrinsics (fx, fy, cx, cy), scaled to the image size (default: the paper's camera).")
@click.option("--camera", "camera_mount", type=click.Choice(list(CAMERA_MOUNTS)), default="fixed", show_default=True,
              help="fixed: the paper's level camera; head: a mobile manipulator's head camera (height, pitch, roll per image).")
@click.option("--table", "tables", multiple=True, metavar="paper|realistic|varied|FILE",
              help="Sampling table: paper (the paper's independent ranges; default), realistic (joint size distributions "
                   "from standard dimensions), varied (those sizes with varied structure: doors, plinths, handles...; "
                   "the classes that have one; docs/generation.md) or a JSON/TOML file overriding part of it; "
                   "repeat to combine a name with files (applied in order).")
@click.option("--framing", type=click.Choice(list(FRAMINGS)), default=DEFAULT_FRAMING, show_default=True,
              help="table4: poses drawn from the sampling table's ranges (the paper's Table 4; tall objects may be cut "
                   "off); whole: the paper's 'view frustum' sentence, only poses that keep the whole object in every "
                   "image, the depth range extended for large objects (docs/generation.md, Framing).")
@click.option("--workers", type=int, default=None,
              help="Worker processes (default: all cores); with --executor ray: most shard tasks in flight (default: 1024).")
@click.option("--executor", type=click.Choice(list(EXECUTORS)), default="local", show_default=True,
              help="local: processes on this machine; ray: one task per shard on a Ray cluster (docs/cluster.md).")
@click.option("--address", default=None, metavar="auto|HOST:PORT",
              help="With --executor ray: the cluster to join (default: RAY_ADDRESS, else a local Ray instance).")
@click.option("--scene", type=click.Choice(list(SCENE_NAMES)), default="none", show_default=True,
              help="Scene context: none (the paper's isolated objects), room (floor, wall, a support for appliances and "
                   "drawers) or kitchen (also counter tops and neighbouring units); docs/generation.md.")
@click.option("--occluders", type=int, default=0, show_default=True,
              help=f"Occluding shapes (boxes, cylinders, arm-like chains) between the camera and the object, per image "
                   f"(0-{MAX_OCCLUDERS}); occlusion fractions are stored as labels.")
@click.option("--rgb", is_flag=True,
              help="Also render colour images (same camera; randomised materials, textures and lights), stored as "
                   "the optional field rgb (format 1.2); docs/generation.md.")
@click.option("--noise", type=_NoiseChoice(), default="none", show_default=True,
              help="Depth sensor-noise model (docs/real_data.md, section \"Sensor noise models\").")
@click.option("--resume", is_flag=True, help="Continue an interrupted run of the same command.")
@click.option("--overwrite", is_flag=True, help="Replace existing data of this class and split (the new split is built beside it and swapped in when complete).")
@click.option("--mean", "mean_object", is_flag=True, help="Render the class's mean object (centre of every range) into OUT/<class>/mean/.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def generate_cmd(class_name, urdf_path, joint_names, urdf_class_name, skip_missing_meshes, urdf_scale, urdf_mesh_root,
                 n_objects, split, out_root, seed, images_per_object, objects_per_shard, width, height, resolution, vfov,
                 intrinsics, camera_mount, tables, framing, workers, executor, address, scene, occluders, rgb, noise, resume, overwrite,
                 mean_object, quiet):
    """Generate labelled depth images of one object class (or one URDF object) into HDF5 shards."""
    camera = camera_from_options(width, height, resolution, vfov, intrinsics, camera_mount)
    urdf = UrdfOptions(urdf_path, joint_names, urdf_class_name, skip_missing_meshes, urdf_scale, urdf_mesh_root)
    config = config_from_options(
        class_name, urdf, camera, tables, n_objects=n_objects, mean=mean_object, echo=None if quiet else click.echo,
        split=split, seed=seed, images_per_object=images_per_object, objects_per_shard=objects_per_shard, noise=noise,
        scene=scene, occluders=occluders, rgb=rgb, framing=framing,
    )
    if workers is not None and workers <= 0:
        raise UserError(f"--workers must be positive, got {workers}")
    if address is not None and not _ADDRESS.match(address):
        raise UserError(f"--address must be auto, HOST:PORT or ray://HOST:PORT, got {address!r}")
    if executor == "local" and workers is None:
        workers = os.cpu_count() or 1
    runner = get_executor(executor, workers, address)
    t0 = time.perf_counter()
    try:
        split_dir = generate_split(config, out_root, workers=workers or 1, resume=resume, overwrite=overwrite,
                                   progress=not quiet, executor=runner)
    except KeyboardInterrupt:
        if overwrite:
            raise click.ClickException("interrupted; the previous split is unchanged") from None
        raise click.ClickException(
            "interrupted; completed shards are kept. Continue with the same command plus --resume"
        ) from None
    seconds = time.perf_counter() - t0
    if not quiet:
        from articulated_dataset.format import read_manifest

        m = read_manifest(split_dir)
        n_bytes = sum(s["bytes"] for s in m["shards"])
        n_img = max(m["n_images"], 1)
        click.echo(
            f"{split_dir}: {m['n_objects']} objects, {m['n_images']} images in {seconds:.1f} s "
            f"({m['n_images'] / max(seconds, 1e-9):.0f} images/s, {n_bytes / n_img:.0f} bytes/image)"
        )


COMMANDS = [generate_cmd]
