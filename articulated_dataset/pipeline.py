"""The generation pipeline: small stages composed per object, per shard and per split.

sample -> template -> compile -> render -> label -> write.  Executors (this module's local
process pool, or Ray in :mod:`articulated_dataset.executors`) only map
:func:`generate_shard` over shard indices; every shard is a pure function of the
:class:`GenerationConfig` and its index, so any executor produces identical bytes.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from . import FORMAT_VERSION, __version__
from .camera import R_CAMERA_TO_OPTICAL, CameraConfig
from .errors import UserError
from .labels import model_info, read_configuration, read_object_labels, visible_pixels
from .registry import JOINT_TYPES, ObjectClass, get_class
from .render import DepthRenderer, process_renderer
from .sampling import ObjectSample, mean_object, object_rng, sample_id, sample_object, sample_pose
from .scene import build_model, set_configuration
from .schema import FIELDS
from .shards import shard_name, write_shard
from .tables import SamplingTable
from .templating import render_urdf

log = logging.getLogger(__name__)

#: Depth values are rounded to multiples of 2**-13 m (0.122 mm), far below any depth
#: sensor's resolution; it makes float32 depth compress ~3x better losslessly.
DEFAULT_DEPTH_QUANTUM_M = 2.0**-13
#: A moving part must cover at least this fraction of the image in every view
#: (0.2% = 41 px at 192x108); otherwise the object's pose is redrawn.
DEFAULT_MIN_PART_FRACTION = 0.002
DEFAULT_IMAGES_PER_OBJECT = 16
DEFAULT_OBJECTS_PER_SHARD = 64
DEFAULT_SEED = 0
#: Pose redraws allowed per object before giving up (a table that never shows the part).
MAX_POSE_ATTEMPTS = 200


@dataclass(frozen=True)
class GenerationConfig:
    """Everything that determines a split's bytes."""

    class_name: str
    split: str = "train"
    n_objects: int = 100
    seed: int = DEFAULT_SEED
    images_per_object: int = DEFAULT_IMAGES_PER_OBJECT
    objects_per_shard: int = DEFAULT_OBJECTS_PER_SHARD
    camera: CameraConfig = field(default_factory=CameraConfig)
    table: SamplingTable | None = None  # None: the class's default table
    min_part_pixels: int | None = None  # None: DEFAULT_MIN_PART_FRACTION of the image
    depth_quantum_m: float = DEFAULT_DEPTH_QUANTUM_M
    mean: bool = False  # render the class's mean object (n_objects must be 1)
    noise: str = "none"  # depth sensor-noise model applied after rendering (articulated_dataset.noise)
    # Definition of a third-party URDF class (articulated_dataset.urdf_import), rebuilt in
    # every worker process; None for registry classes.
    third_party: dict | None = None

    def __post_init__(self) -> None:
        # UserError for unknown names.  A third-party class with its table given (e.g. read
        # back from a manifest) is not rebuilt here: its URDF files are needed only to render.
        obj_class = self.obj_class if self.third_party is None or self.table is None else None
        if self.n_objects <= 0:
            raise UserError(f"number of objects must be positive, got {self.n_objects}")
        if self.images_per_object <= 0:
            raise UserError(f"images per object must be positive, got {self.images_per_object}")
        if self.objects_per_shard <= 0:
            raise UserError(f"objects per shard must be positive, got {self.objects_per_shard}")
        if self.seed < 0:
            raise UserError(f"seed must be >= 0, got {self.seed}")
        if self.mean and self.n_objects != 1:
            raise UserError("--mean renders exactly one object (the class's mean object)")
        if not self.split or "/" in self.split or self.split.startswith("."):
            raise UserError(f"invalid split name {self.split!r}")
        if self.table is None:
            object.__setattr__(self, "table", obj_class.table)
        if self.min_part_pixels is None:
            area = self.camera.width_px * self.camera.height_px
            object.__setattr__(self, "min_part_pixels", int(math.ceil(DEFAULT_MIN_PART_FRACTION * area)))

    @property
    def obj_class(self) -> ObjectClass:
        if self.third_party is not None:
            from .urdf_import import class_from_definition

            return class_from_definition(self.third_party)
        return get_class(self.class_name)

    @property
    def n_shards(self) -> int:
        return -(-self.n_objects // self.objects_per_shard)

    def shard_objects(self, shard_index: int) -> range:
        start = shard_index * self.objects_per_shard
        return range(start, min(start + self.objects_per_shard, self.n_objects))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["table"] = self.table.to_dict()
        d["format_version"] = FORMAT_VERSION
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "GenerationConfig":
        d = {k: v for k, v in d.items() if k != "format_version"}
        d["camera"] = CameraConfig(**d["camera"])
        d["table"] = SamplingTable.from_dict(d["table"])
        return cls(**d)


def render_object(sample: ObjectSample, config: GenerationConfig, renderer: DepthRenderer, *, check_visibility: bool = True,
                  out: dict | None = None):
    """Template, compile, render and label one sampled object.

    Redraws the pose (from the object's own generator, after its other draws) while a moving
    part covers fewer than ``config.min_part_pixels`` in some view.  Returns
    ``(arrays, sample, attempts)`` where ``arrays`` holds every schema field for the
    object's images.  ``out`` may hold preallocated ``depth`` (n, H, W) float32 and ``mask``
    (n, H, W) uint8 arrays (views into a shard's buffers) to render into.
    """
    obj_class = config.obj_class
    urdf = render_urdf(obj_class.template_path(), sample.template_mappings(config.table))
    rng = None
    J = obj_class.n_joints
    n = config.images_per_object
    H, W = config.camera.height_px, config.camera.width_px
    for attempt in range(1, MAX_POSE_ATTEMPTS + 1):
        model = build_model(urdf, sample.pose, config.camera, obj_class.base_link)
        data = mujoco.MjData(model)
        info = model_info(model, obj_class)
        labels = read_object_labels(model, data, info, obj_class)
        renderer.bind(model)
        depth = out["depth"] if out is not None else np.empty((n, H, W), np.float32)
        mask = out["mask"] if out is not None else np.empty((n, H, W), np.uint8)
        q = np.empty((n, J), np.float64)
        vis = np.empty((n, 1 + J), np.int32)
        ok = True
        # Widest-open configurations first: they are the views that fail the visibility
        # check (doors edge-on or swung out of the frame), so a rejected pose costs few renders.
        for i in np.argsort(-sample.q.sum(axis=1), kind="stable"):
            set_configuration(model, data, info.joint_ids, sample.q[i])
            _, geom_id = renderer.render(data, depth_out=depth[i])
            mask[i] = info.mask_from_geoms(geom_id)
            vis[i] = visible_pixels(mask[i], J)
            if check_visibility and vis[i, 1:].min() < config.min_part_pixels:
                ok = False
                break
            q[i] = read_configuration(data, info)
        if ok:
            break
        if rng is None:
            _, rng = sample_object(obj_class, config.table, seed=sample.seed, split=sample.split,
                                   object_index=sample.object_index, n_images=n)
        sample = replace(sample, pose=sample_pose(rng, config.table))
    else:
        raise UserError(
            f"{obj_class.name} object {sample.object_index}: no pose in the table shows every moving part "
            f"with >= {config.min_part_pixels} px after {MAX_POSE_ATTEMPTS} attempts; check the table"
        )
    if config.noise != "none":
        from .noise import get_noise_model  # seeded per object: see noise_rng

        apply_noise = get_noise_model(config.noise)
        nrng = noise_rng(config, sample.object_index)
        K = config.camera.K
        for i in range(n):
            depth[i] = apply_noise(depth[i], K, nrng)
    if config.depth_quantum_m > 0:  # in place: depth may be a view into the shard's buffer
        np.divide(depth, config.depth_quantum_m, out=depth)
        np.round(depth, out=depth)
        np.multiply(depth, config.depth_quantum_m, out=depth)
    ids = np.array([sample_id(config.class_name, config.split, config.seed, sample.object_index, i) for i in range(n)], np.int64)
    arrays = {
        "depth": depth,
        "mask": mask,
        "q": q.astype(np.float32),
        "axis_origin": np.repeat(labels["axis_origin"][None], n, 0).astype(np.float32),
        "axis_direction": np.repeat(labels["axis_direction"][None], n, 0).astype(np.float32),
        "axis_pose": np.repeat(labels["axis_pose"][None], n, 0).astype(np.float32),
        "part_offset": np.repeat(labels["part_offset"][None], n, 0).astype(np.float32),
        "object_pose": np.repeat(labels["object_pose"][None], n, 0).astype(np.float32),
        "object_yaw": np.full(n, labels["object_yaw"], np.float32),
        "geometry": np.repeat(labels["geometry"][None], n, 0).astype(np.float32),
        "visible_pixels": vis,
        "object_index": np.full(n, sample.object_index, np.int64),
        "image_index": np.arange(n, dtype=np.int32),
        "sample_id": ids,
        "class": np.full(n, config.class_name.encode("ascii"), dtype="S32"),
    }
    return arrays, sample, attempt


#: Extra SeedSequence word separating the noise stream from the object's sampling stream.
NOISE_STREAM = 1


def noise_rng(config: GenerationConfig, object_index: int) -> np.random.Generator:
    """Generator of the sensor noise of one object, independent of its sampling stream."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=NOISE_STREAM)


def object_sample(config: GenerationConfig, object_index: int) -> ObjectSample:
    """Stage 1 for object ``object_index`` of the split (the mean object with ``config.mean``)."""
    if config.mean:
        return mean_object(config.obj_class, config.table, split=config.split, n_images=config.images_per_object)
    sample, _ = sample_object(config.obj_class, config.table, seed=config.seed, split=config.split,
                              object_index=object_index, n_images=config.images_per_object)
    return sample


def stored_sample(config: GenerationConfig, object_index: int, object_pose, object_yaw: float) -> ObjectSample:
    """The sample of object ``object_index`` as it was rendered and stored.

    :func:`object_sample` returns the object's *first* pose draw; the pipeline redraws the
    pose while a part is hidden, so code that rebuilds a stored object (figures, physics)
    must take the pose from the stored labels (``object_pose`` position, ``object_yaw``).
    """
    sample = object_sample(config, object_index)
    p = np.asarray(object_pose, dtype=np.float64)
    return replace(sample, pose={"x_m": float(p[0]), "y_m": float(p[1]), "z_m": float(p[2]), "yaw_rad": float(object_yaw)})


def shard_attrs(config: GenerationConfig, objects: range) -> dict:
    obj_class = config.obj_class
    assert set(obj_class.joint_types) <= set(JOINT_TYPES)
    return {
        "format_version": FORMAT_VERSION,
        "class_name": config.class_name,
        "split": config.split,
        "seed": config.seed,
        "n_objects": len(objects),
        "object_start": objects.start,
        "object_stop": objects.stop,
        "images_per_object": config.images_per_object,
        "n_joints": obj_class.n_joints,
        "joint_names": json.dumps([j.name for j in obj_class.joints]),
        "joint_types": json.dumps(list(obj_class.joint_types)),
        "image_width": config.camera.width_px,
        "image_height": config.camera.height_px,
        "vfov_deg": config.camera.vfov_deg,
        "depth_quantum_m": config.depth_quantum_m,
        "min_part_pixels": config.min_part_pixels,
        "mean_object": int(config.mean),
        "noise_model": config.noise,
        "sampling_table": config.table.to_json(),
        "package_version": __version__,
    }


def generate_shard(config: GenerationConfig, shard_index: int, split_dir: str | Path, progress=None) -> dict:
    """Generate shard ``shard_index`` of the split into ``split_dir``; returns its manifest record.

    ``progress(n_images)`` is called after each object, if given.
    """
    renderer = process_renderer(config.camera)
    objects = config.shard_objects(shard_index)
    n = config.images_per_object
    H, W = config.camera.height_px, config.camera.width_px
    # Images are rendered straight into the shard's buffers (no per-object copies).
    images = {"depth": np.empty((len(objects) * n, H, W), np.float32), "mask": np.empty((len(objects) * n, H, W), np.uint8)}
    labels: dict[str, list] = {f.name: [] for f in FIELDS if f.name not in images}
    attempts = 0
    for p, k in enumerate(objects):
        out = {name: buf[p * n:(p + 1) * n] for name, buf in images.items()}
        arrays, _, tries = render_object(object_sample(config, k), config, renderer, check_visibility=not config.mean, out=out)
        attempts += tries
        for name in labels:
            labels[name].append(arrays[name])
        if progress is not None:
            progress(n)
    arrays = {**images, **{name: np.concatenate(v, axis=0) for name, v in labels.items()}}
    attrs = shard_attrs(config, objects)
    attrs["pose_attempts"] = attempts
    record = write_shard(Path(split_dir) / shard_name(shard_index), arrays, attrs, config.camera.K, R_CAMERA_TO_OPTICAL)
    record.update(object_start=objects.start, object_stop=objects.stop, pose_attempts=attempts)
    return record


# --------------------------------------------------------------------------------------
# Split generation (local executor)
# --------------------------------------------------------------------------------------

def split_dir_for(out_root: str | Path, config: GenerationConfig) -> Path:
    """``OUT/<class>/<split>`` (``OUT/<class>/mean`` for the mean object)."""
    return Path(out_root) / config.class_name / ("mean" if config.mean else config.split)


def _manifest(config: GenerationConfig, records: dict[int, dict]) -> dict:
    shards = [records[i] for i in sorted(records)]
    complete = len(shards) == config.n_shards
    return {
        "format_version": FORMAT_VERSION,
        "package_version": __version__,
        "class_name": config.class_name,
        "split": config.split,
        "seed": config.seed,
        "complete": complete,
        "n_objects": sum(r["object_stop"] - r["object_start"] for r in shards),
        "n_images": sum(r["n_images"] for r in shards),
        "n_shards_expected": config.n_shards,
        "config": config.to_dict(),
        "shards": shards,
    }


def _prepare_output(split_dir: Path, config: GenerationConfig, *, resume: bool, overwrite: bool) -> dict[int, dict]:
    """Check/clean the output folder; return the records of shards already complete (resume)."""
    from .shards import MANIFEST_NAME, SHARD_PATTERN, TMP_SUFFIX, read_manifest, sha256_file

    if resume and overwrite:
        raise UserError("--resume and --overwrite are mutually exclusive")
    try:
        split_dir.mkdir(parents=True, exist_ok=True)
        probe = split_dir / f".write-test{TMP_SUFFIX}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"cannot write to output folder {split_dir}: {exc.strerror or exc}") from None
    existing = [p for p in split_dir.iterdir() if not p.name.endswith(TMP_SUFFIX)]
    for p in split_dir.glob(f"*{TMP_SUFFIX}"):
        p.unlink()  # leftovers of an interrupted write are never valid
    if not existing:
        return {}
    if overwrite:
        for p in existing:
            if p.is_file() and (p.name == MANIFEST_NAME or p.suffix == ".h5"):
                p.unlink()
        return {}
    if not resume:
        raise UserError(f"{split_dir} already holds generated data; pass --resume to continue it or --overwrite to replace it")
    records: dict[int, dict] = {}
    manifest_path = split_dir / MANIFEST_NAME
    if manifest_path.exists():
        old = read_manifest(split_dir)
        if GenerationConfig.from_dict(old["config"]) != config:
            raise UserError(f"{split_dir} was generated with different settings; --resume needs the same command (or use --overwrite)")
        for rec in old["shards"]:
            records[int(Path(rec["file"]).stem.split("-")[1])] = rec
    # Shards on disk but not yet in the manifest (killed between rename and manifest update)
    # are complete by construction (atomic rename); checksum them now.
    for i in range(config.n_shards):
        path = split_dir / SHARD_PATTERN.format(i)
        if i in records:
            if not path.exists() or path.stat().st_size != records[i]["bytes"]:
                del records[i]
            continue
        if path.exists():
            from .shards import Shard

            sh = Shard(path)
            try:
                attrs, n = sh.attrs, len(sh)
            finally:
                sh.close()
            objects = config.shard_objects(i)
            if attrs.get("object_start") != objects.start:
                continue
            records[i] = {"file": path.name, "n_images": n, "bytes": path.stat().st_size, "sha256": sha256_file(path),
                          "object_start": objects.start, "object_stop": objects.stop,
                          "pose_attempts": int(attrs.get("pose_attempts", 0))}
    return records


def _run_shard(args, progress=None):
    """Executor task: generate one shard; returns ``(shard_index, manifest_record)``."""
    config, index, split_dir = args
    return index, generate_shard(config, index, split_dir, progress=progress)


def generate_split(
    config: GenerationConfig,
    out_root: str | Path,
    *,
    workers: int = 1,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = False,
    executor=None,
) -> Path:
    """Generate every shard of ``config`` under ``out_root/<class>/<split>`` and its manifest.

    Shards are independent, so the result is byte-identical for any executor, any number of
    ``workers`` and across interruptions with ``resume``.  ``executor`` (see
    :mod:`articulated_dataset.executors`) defaults to local processes (``workers``).
    Returns the split folder.
    """
    from tqdm import tqdm

    from .executors import local_executor
    from .shards import write_manifest

    if executor is None:
        executor = local_executor(workers)

    split_dir = split_dir_for(out_root, config)
    records = _prepare_output(split_dir, config, resume=resume, overwrite=overwrite)
    todo = [i for i in range(config.n_shards) if i not in records]
    total_images = config.n_objects * config.images_per_object
    done_images = sum(r["n_images"] for r in records.values())
    write_manifest(split_dir, _manifest(config, records))
    bar = tqdm(total=total_images, initial=done_images, unit="img", disable=not progress,
               desc=f"{config.class_name}/{config.split}", dynamic_ncols=True)
    try:
        for i, rec in executor.map_unordered(_run_shard, [(config, i, split_dir) for i in todo], progress=bar.update):
            records[i] = rec
            write_manifest(split_dir, _manifest(config, records))
    finally:
        bar.close()
    return split_dir
