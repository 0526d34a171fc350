"""The generation pipeline: small stages composed per object, per shard and per split.

sample -> template -> compile -> render -> label -> write.  Executors (this module's local
process pool, or Ray in :mod:`articulated_dataset.executors`) only map
:func:`generate_shard` over shard indices; every shard is a pure function of the
:class:`GenerationConfig` and its index, so any executor produces identical bytes.
"""

from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

from . import FORMAT_VERSION, __version__  # noqa: F401  (FORMAT_VERSION re-exported)
from .camera import R_CAMERA_TO_OPTICAL
from .errors import DataFormatError, UserError
from .format.manifest import (  # noqa: F401  (re-exported: the generator's defaults are the format's)
    DEFAULT_DEPTH_QUANTUM_M,
    DEFAULT_IMAGES_PER_OBJECT,
    DEFAULT_MIN_PART_FRACTION,
    DEFAULT_OBJECTS_PER_SHARD,
    DEFAULT_SEED,
    MAX_SEED,
    SplitConfig,
)
from .labels import model_info, read_configuration, read_object_labels, visible_pixels
from .registry import JOINT_TYPES, MAX_REVOLUTE_Q_RAD, ObjectClass, check_table, get_class, resolve  # noqa: F401
from .render import DepthRenderer, process_renderer
from .safeio import (FULL_HINT, TMP_SUFFIX, WriteError, available_memory_bytes, check_free_space, ensure_dir, format_bytes,
                     fsync_dir, remove_created_dirs, translated)
from .sampling import ObjectSample, mean_object, object_rng, sample_id, sample_object, sample_pose
from .scene import ORIGIN_POSE, ObjectPlacer, build_model, set_configuration
from .format.schema import FIELDS, OPTIONAL_FIELDS
from .context_labels import VISIBLE_FRACTION_RANGE, visible_fraction
from .occluders import Context, occluders_record
from .scenes import context_builder, context_rngs, scene_record
from .shards import shard_name, write_shard
from .templating import render_urdf
from .viewpoint import CAMERA_STREAM, head_ranges, head_views, object_in_camera

log = logging.getLogger(__name__)

#: Pose redraws allowed per object before giving up (a table that never shows the part).
MAX_POSE_ATTEMPTS = 200


@dataclass(frozen=True)
class GenerationConfig(SplitConfig):
    """Everything that determines a split's bytes: a :class:`SplitConfig` (the manifest's
    schema, :mod:`articulated_dataset.format.manifest`) whose class is checked against the
    registry and whose table defaults to the class's."""

    def _validate(self) -> None:
        # UserError for unknown names.  A third-party class with its table given (e.g. read
        # back from a manifest) is not rebuilt here: its URDF files are needed only to render.
        obj_class = self.obj_class if self.third_party is None or self.table is None else None
        super()._validate()
        if self.table is None:
            object.__setattr__(self, "table", obj_class.table)
        if obj_class is not None:
            check_table(obj_class, self.table)

    @property
    def obj_class(self) -> ObjectClass:
        return resolve(self.class_name, self.third_party)


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
    head = config.camera.mount == "head"
    crng = camera_rng(config, sample.object_index) if head and not config.mean else None
    srng, orng = context_rngs(config, sample.object_index)
    alone = np.empty((n, 1 + J), np.int32) if config.has_context else None
    for attempt in range(1, MAX_POSE_ATTEMPTS + 1):
        if head:  # the object is built at the origin and placed in each image's camera frame
            sample = replace(sample, views=head_views(crng, sample.pose, sample.geometry, n))
            model = build_model(urdf, ORIGIN_POSE, config.camera, obj_class.base_link)
        elif config.has_context:  # scene (its layout may redraw the base height) and occluder slots
            sample, add_context = context_builder(config, sample, srng)
            if add_context is None:  # no layout fits this pose: redraw it
                rng = _redraw_pose(rng, obj_class, config, sample)
                sample = replace(sample, pose=sample_pose(rng, config.table))
                continue
            model = build_model(urdf, sample.pose, config.camera, obj_class.base_link, add_context)
        else:
            model = build_model(urdf, sample.pose, config.camera, obj_class.base_link)
        data = mujoco.MjData(model)
        info = model_info(model, obj_class)
        ctx = Context(model, info, config.occluders, orng) if config.has_context else None
        if head:
            placer = ObjectPlacer(model, info.base_body)
            per_image = [None] * n
        else:
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
            if head:  # this image's camera: labels are read from the model as placed for it
                placer.place(object_in_camera(sample.pose, sample.views[i]))
                per_image[i] = read_object_labels(model, data, info, obj_class)
            set_configuration(model, data, info.joint_ids, sample.q[i])
            if ctx is not None:
                counts = ctx.render(renderer, data, depth[i], mask[i], config.min_part_pixels)
                if counts is None:  # no occluder draw leaves every moving part identifiable
                    ok = False
                    break
                vis[i], alone[i] = counts
            else:
                _, geom_id = renderer.render(data, depth_out=depth[i])
                mask[i] = info.mask_from_geoms(geom_id)
                vis[i] = visible_pixels(mask[i], J)
            if check_visibility and vis[i, 1:].min() < config.min_part_pixels:
                ok = False
                break
            q[i] = read_configuration(data, info)
        if ok:
            break
        rng = _redraw_pose(rng, obj_class, config, sample)
        sample = replace(sample, pose=sample_pose(rng, config.table))
    else:
        raise UserError(
            f"{obj_class.name} object {sample.object_index}: no pose in the table shows every moving part "
            f"with >= {config.min_part_pixels} px after {MAX_POSE_ATTEMPTS} attempts; check the table"
            + (" or choose the joints that open with --joints (a hidden part cannot be labelled)"
               if config.third_party is not None else "")
            + (f" (and >= {VISIBLE_FRACTION_RANGE[0]:g} of its pixels unhidden by the scene and occluders; "
               "try fewer --occluders)" if config.has_context else "")
        )
    if config.noise != "none":
        from .real.noise import get_noise_model  # seeded per object: see noise_rng

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
    if head:
        stacked = {k: np.stack([np.asarray(per_image[i][k]) for i in range(n)]) for k in per_image[0]}
    else:
        stacked = {k: np.repeat(np.asarray(v)[None], n, 0) for k, v in labels.items()}
    arrays = {
        "depth": depth,
        "mask": mask,
        "q": q.astype(np.float32),
        "axis_origin": stacked["axis_origin"].astype(np.float32),
        "axis_direction": stacked["axis_direction"].astype(np.float32),
        "axis_pose": stacked["axis_pose"].astype(np.float32),
        "part_offset": stacked["part_offset"].astype(np.float32),
        "object_pose": stacked["object_pose"].astype(np.float32),
        "object_yaw": stacked["object_yaw"].astype(np.float32),
        "geometry": stacked["geometry"].astype(np.float32),
        "visible_pixels": vis,
        "object_index": np.full(n, sample.object_index, np.int64),
        "image_index": np.arange(n, dtype=np.int32),
        "sample_id": ids,
        "class": np.full(n, config.class_name.encode("ascii"), dtype="S32"),
    }
    if alone is not None:  # format 1.1: occlusion labels
        arrays["unoccluded_pixels"] = alone
        arrays["visible_fraction"] = visible_fraction(vis, alone)
    return arrays, sample, attempt


def _redraw_pose(rng, obj_class: ObjectClass, config: GenerationConfig, sample: ObjectSample) -> np.random.Generator:
    """The object's generator positioned for its next pose draw (after its other draws)."""
    if rng is None:
        _, rng = sample_object(obj_class, config.table, seed=sample.seed, split=sample.split,
                               object_index=sample.object_index, n_images=config.images_per_object)
    return rng


#: Extra SeedSequence word separating the noise stream from the object's sampling stream.
NOISE_STREAM = 1


def noise_rng(config: GenerationConfig, object_index: int) -> np.random.Generator:
    """Generator of the sensor noise of one object, independent of its sampling stream."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=NOISE_STREAM)


def camera_rng(config: GenerationConfig, object_index: int) -> np.random.Generator:
    """Generator of one object's head-camera views (:mod:`articulated_dataset.viewpoint`),
    independent of its sampling stream: an object is the same with either camera."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=CAMERA_STREAM)


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
    attrs = {
        "format_version": config.format_version,
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
    # Options added after the paper's setting: recorded only when used (a default shard's
    # attributes, and bytes, are as they were).
    if config.camera.intrinsics is not None:
        attrs["intrinsics"] = config.camera.intrinsics
    if config.camera.mount != "fixed":
        attrs["camera_mount"] = json.dumps({"mount": config.camera.mount, **head_ranges()}, sort_keys=True)
    if config.scene != "none":
        attrs["scene"] = scene_record(config.scene, config.class_name)
    if config.occluders:
        attrs["occluders"] = occluders_record(config.occluders)
    return attrs


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
    stored = FIELDS + (OPTIONAL_FIELDS if config.has_context else ())
    labels: dict[str, list] = {f.name: [] for f in stored if f.name not in images}
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
        "format_version": config.format_version,
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


# Files of a split folder that this package writes (the manifest, shards and their
# temporary siblings).  Nothing else in a split folder is ever deleted or replaced.
_OWN_FILE = re.compile(r"(manifest\.json|shard-([0-9]{5,})\.h5)(\.partial)?")
_SHARD_FILE = re.compile(r"shard-([0-9]{5,})\.h5")
#: Siblings of ``OUT/<class>/<split>`` (hidden): the lock held while a run writes the split,
#: the new split an ``--overwrite`` builds, and the old one while the two are swapped.
LOCK_SUFFIX = ".lock"
STAGING_SUFFIX = ".new"
RETIRED_SUFFIX = ".old"
#: Memory one image takes in a shard's buffers while it is generated (float32 depth + uint8
#: mask), and the renderer's own buffers (RGB, depth, GL colour/depth/stencil), per pixel.
SHARD_BUFFER_BYTES_PER_PIXEL = 5
RENDERER_BYTES_PER_PIXEL = 24
#: Memory of one worker process before its first shard (Python, NumPy, MuJoCo, the GL
#: driver; ~200-250 MB measured), counted for each worker process a run would start.
WORKER_PROCESS_BYTES = 250e6
#: Fraction of the available memory generation may plan to use (the rest: Python, MuJoCo,
#: the GL driver, other programs).
MEMORY_BUDGET_FRACTION = 0.5
#: A lower bound of a shard's size on disk per pixel: measured 0.08-0.10 byte/pixel (1.6-2.1
#: KB per 192x108 image); a split certainly needs more than this, so a run that would not fit
#: is refused before it starts.
MIN_DISK_BYTES_PER_PIXEL = 0.02


def _sibling(split_dir: Path, suffix: str) -> Path:
    return split_dir.parent / f".{split_dir.name}{suffix}"


def _own_entries(folder: Path) -> tuple[list[Path], list[Path]]:
    """``(ours, foreign)`` entries of ``folder``: regular files named as we name them, and
    everything else (other files, folders, symbolic links)."""
    ours, foreign = [], []
    for p in sorted(folder.iterdir()):
        own = _OWN_FILE.fullmatch(p.name) is not None and p.is_file() and not p.is_symlink()
        (ours if own else foreign).append(p)
    return ours, foreign


def _remove_own_folder(folder: Path) -> None:
    """Delete ``folder`` if it holds only files we write (else leave it and say so)."""
    if not folder.is_dir() or folder.is_symlink():
        return
    ours, foreign = _own_entries(folder)
    if foreign:
        raise UserError(f"{folder} holds files artdata did not write ({', '.join(p.name for p in foreign[:3])}); "
                        "move them away (nothing was deleted)")
    for p in ours:
        p.unlink()
    folder.rmdir()


class SplitLock:
    """Exclusive lock of one split folder while a run writes it: ``OUT/<class>/.<split>.lock``
    (``flock``, released by the kernel when the process dies, whatever kills it).

    The lock file is removed when released; a run that finds the file replaced after locking
    it locks the new one, so two runs never both hold the lock.
    """

    def __init__(self, split_dir: Path):
        self.split_dir = split_dir
        self.path = _sibling(split_dir, LOCK_SUFFIX)
        self._fd: int | None = None

    def acquire(self) -> None:
        try:
            import fcntl
        except ImportError:  # no flock (Windows): runs are not protected from each other
            log.warning("no file locking on this platform: do not run two generate commands on %s", self.split_dir)
            return
        while True:
            with translated(self.path, "create lock file"):
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise UserError(f"another artdata generate is writing {self.split_dir} (it holds {self.path}); "
                                "wait for it to finish or stop it") from None
            try:
                st, held = os.stat(self.path), os.fstat(fd)
                same = (st.st_dev, st.st_ino) == (held.st_dev, held.st_ino)
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                return
            os.close(fd)  # released and removed by the run that held it: lock the new file

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            os.unlink(self.path)
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None


@dataclass
class _Run:
    """What :func:`_begin` decided: where shards go and what already exists."""

    split_dir: Path
    target: Path  # split_dir, or its staging sibling with --overwrite
    records: dict[int, dict]
    created: list[Path]  # folders this run created (removed again if it writes nothing)
    lock: SplitLock


def _restore_interrupted_swap(split_dir: Path) -> None:
    """An ``--overwrite`` killed between its two renames left the old split as
    ``.<split>.old`` and no split: put the old split back (lock held)."""
    retired = _sibling(split_dir, RETIRED_SUFFIX)
    if retired.is_dir() and not retired.is_symlink() and not split_dir.exists() and not split_dir.is_symlink():
        os.rename(retired, split_dir)


def _remove_interrupted_siblings(split_dir: Path) -> None:
    """Remove the ``.new``/``.old`` siblings a killed ``--overwrite`` left (lock held, and
    only once this run proceeds)."""
    for suffix in (STAGING_SUFFIX, RETIRED_SUFFIX):
        _remove_own_folder(_sibling(split_dir, suffix))


def _begin(split_dir: Path, config: GenerationConfig, *, resume: bool, overwrite: bool) -> _Run:
    """Lock the split and decide what to do.  A refusal changes nothing on disk (and removes
    the folders and lock it created to find out)."""
    if split_dir.is_symlink():
        raise UserError(f"{split_dir} is a symbolic link; generate writes only into real folders "
                        "(give the link's target as --out, or remove the link)")
    if split_dir.exists() and not split_dir.is_dir():
        raise UserError(f"{split_dir} exists and is not a folder")
    created = ensure_dir(split_dir.parent)
    lock = SplitLock(split_dir)
    try:
        lock.acquire()
        _restore_interrupted_swap(split_dir)  # a restore, never a deletion
        ours, foreign = _own_entries(split_dir) if split_dir.is_dir() else ([], [])
        data = [p for p in ours if not p.name.endswith(TMP_SUFFIX)]
        stale = [p for p in ours if p.name.endswith(TMP_SUFFIX)]  # a killed run's; no run holds the lock
        names = ", ".join(p.name for p in foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        records: dict[int, dict] = {}
        target = split_dir
        if not data:
            if foreign:
                raise UserError(f"{split_dir} is not empty and holds no generated split ({names}); "
                                "choose another --out or --split")
        elif not (resume or overwrite):
            raise UserError(f"{split_dir} already holds generated data; pass --resume to continue it or --overwrite to replace it")
        elif overwrite:
            if foreign:
                raise UserError(f"{split_dir} holds files artdata did not write ({names}); --overwrite replaces "
                                "only generated splits: move them away first")
            target = _sibling(split_dir, STAGING_SUFFIX)
        else:
            records = _resume_records(split_dir, config)
        # Proceeding: now (and only now) remove what killed runs left.
        _remove_interrupted_siblings(split_dir)
        for p in stale:
            p.unlink()
        created += ensure_dir(target)
    except BaseException:
        lock.release()
        remove_created_dirs(created)
        raise
    return _Run(split_dir, target, records, created, lock)


def _resume_records(split_dir: Path, config: GenerationConfig) -> dict[int, dict]:
    """Records of the shards a run of ``config`` already completed in ``split_dir``; a
    manifest or shard of other settings is refused (never adopted)."""
    from .format import MANIFEST_NAME, Shard, read_manifest, sha256_file

    records: dict[int, dict] = {}
    manifest_path = split_dir / MANIFEST_NAME
    different = "--resume needs the same command (or use --overwrite)"
    if manifest_path.exists():
        old = read_manifest(split_dir)
        try:
            old_config = GenerationConfig.from_dict(old["config"])
            listed = [(_SHARD_FILE.fullmatch(rec["file"]), rec) for rec in old["shards"]]
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DataFormatError(f"{manifest_path}: corrupt manifest ({type(exc).__name__}: {exc}); "
                                  "use --overwrite") from None
        if old_config != config:
            raise UserError(f"{split_dir} was generated with different settings; {different}")
        for m, rec in listed:
            if m is None or int(m.group(1)) >= config.n_shards:
                raise DataFormatError(f"{manifest_path}: corrupt manifest (shard file {str(rec['file'])[:80]!r}); "
                                      "use --overwrite")
            records[int(m.group(1))] = rec
    # Shards listed but missing or of another size are generated again; shards on disk but
    # not in the manifest (killed between rename and manifest update) are complete by
    # construction (atomic rename) if they were written with these settings.
    for i, rec in list(records.items()):
        path = split_dir / rec["file"]
        if not path.is_file() or path.stat().st_size != rec.get("bytes"):
            del records[i]
    for path in sorted(split_dir.iterdir()):
        m = _SHARD_FILE.fullmatch(path.name)
        if m is None or int(m.group(1)) in records:
            continue
        i = int(m.group(1))
        if i >= config.n_shards:
            raise UserError(f"{path} is not a shard of this command ({config.n_shards} shards); {different}")
        sh = Shard(path)
        try:
            attrs, n = sh.attrs, len(sh)
        finally:
            sh.close()
        objects = config.shard_objects(i)
        for key, want in shard_attrs(config, objects).items():
            have = attrs.get(key)
            if key != "package_version" and have != want:
                raise UserError(f"{path} was generated with different settings ({key} = {str(have)[:60]}, "
                                f"this command: {str(want)[:60]}); {different}")
        records[i] = {"file": path.name, "n_images": n, "bytes": path.stat().st_size, "sha256": sha256_file(path),
                      "object_start": objects.start, "object_stop": objects.stop,
                      "pose_attempts": int(attrs.get("pose_attempts", 0))}
    return records


def _finish_overwrite(run: _Run) -> None:
    """Swap the complete new split (staging sibling) in for the old one."""
    retired = _sibling(run.split_dir, RETIRED_SUFFIX)
    with translated(run.split_dir, "replace"):
        os.rename(run.split_dir, retired)
        os.rename(run.target, run.split_dir)
    fsync_dir(run.split_dir.parent)
    _remove_own_folder(retired)


def _abandon(run: _Run) -> None:
    """After a failure: drop what cannot be continued, keep what ``--resume`` can."""
    if run.target != run.split_dir:  # an --overwrite: the old split stays as it was
        _remove_own_folder(run.target)
    elif run.target.is_dir():
        for p in run.target.iterdir():
            if p.name.endswith(TMP_SUFFIX) and _OWN_FILE.fullmatch(p.name):
                p.unlink(missing_ok=True)


def check_resources(config: GenerationConfig, split_dir: Path, *, workers: int, remote: bool = False,
                    done_images: int = 0) -> None:
    """Refuse (one line) a run whose shards cannot fit in this machine's memory or whose
    images cannot fit on the output's filesystem, before anything is allocated."""
    pixels = config.camera.width_px * config.camera.height_px
    per_shard = min(config.objects_per_shard, config.n_objects) * config.images_per_object
    if not remote:
        in_flight = max(1, min(workers, config.n_shards))
        process = WORKER_PROCESS_BYTES if in_flight > 1 else 0.0  # one worker runs in this process
        need = in_flight * (per_shard * pixels * SHARD_BUFFER_BYTES_PER_PIXEL + pixels * RENDERER_BYTES_PER_PIXEL + process)
        avail = available_memory_bytes()
        if avail is not None and need > MEMORY_BUDGET_FRACTION * avail:
            raise UserError(
                f"{in_flight} worker(s) with shards of {per_shard} images of {config.camera.width_px}x{config.camera.height_px} px "
                f"need {format_bytes(need)} of memory, more than half of the {format_bytes(avail)} available; "
                "lower --objects-per-shard, --images, --width/--height or --workers")
    remaining = config.n_objects * config.images_per_object - done_images
    check_free_space(split_dir.parent if not split_dir.exists() else split_dir,
                     remaining * pixels * MIN_DISK_BYTES_PER_PIXEL, f"{remaining} images of {pixels} px")


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

    Lifecycle (docs/security.md): the split is locked while a run writes it; a refused run
    changes nothing; ``overwrite`` builds the new split beside the old one and swaps them
    only when it is complete; a failed run keeps its complete shards for ``resume`` and
    leaves nothing if it completed none.
    """
    from tqdm import tqdm

    from .executors import local_executor
    from .shards import write_manifest

    if resume and overwrite:
        raise UserError("--resume and --overwrite are mutually exclusive")
    if executor is None:
        executor = local_executor(workers)
    split_dir = split_dir_for(out_root, config)
    remote = getattr(executor, "remote", False)  # Ray: shards are built in other machines' memory
    check_resources(config, split_dir, workers=workers, remote=remote)
    run = _begin(split_dir, config, resume=resume, overwrite=overwrite)
    records = run.records
    try:
        done_images = sum(r["n_images"] for r in records.values())
        if done_images:
            check_resources(config, split_dir, workers=workers, remote=remote, done_images=done_images)
        total_images = config.n_objects * config.images_per_object
        bar = tqdm(total=total_images, initial=done_images, unit="img", disable=not progress,
                   desc=f"{config.class_name}/{config.split}", dynamic_ncols=True)
        todo = ((config, i, run.target) for i in range(config.n_shards) if i not in records)
        try:
            for i, rec in executor.map_unordered(_run_shard, todo, progress=bar.update):
                records[i] = rec
                write_manifest(run.target, _manifest(config, records))
        finally:
            bar.close()
        write_manifest(run.target, _manifest(config, records))
        if run.target != split_dir:
            _finish_overwrite(run)
    except BaseException as exc:
        _abandon(run)
        run.lock.release()
        remove_created_dirs(run.created)  # only folders still empty: a run that wrote nothing leaves nothing
        if isinstance(exc, WriteError) and run.target == split_dir and records:
            raise WriteError(f"{str(exc).removesuffix(FULL_HINT)}; the {len(records)} complete shard(s) are kept: "
                             "run the same command with --resume once there is space", exc.path, exc.errno) from None
        raise
    run.lock.release()
    return split_dir
