"""The generation pipeline composed: the stages of :mod:`.objects` per object
(:func:`render_object`), and per shard (:func:`generate_shard`, stage 6's shard writing).

sample -> template -> compile -> render -> label -> write.  Each object's stages run until a
pose passes (a rejected pose is redrawn from the object's kept generator state); a shard is a
pure function of the :class:`GenerationConfig` and its index, which is all an executor maps
(:func:`run_shard`; :mod:`.split` runs a whole split).  Expensive setup happens once per
process: the renderer (:func:`~articulated_dataset.generation.render.process_renderer`) and
the parsed templates (:mod:`.templating`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import cast

import numpy as np

from articulated_dataset.classes.registry import JOINT_TYPES
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format.manifest import DEFAULT_FRAMING
from articulated_dataset.format.records import shard_attrs as format_shard_attrs
from articulated_dataset.format.schema import FIELDS, OPTIONAL_FIELDS, RGB_FIELDS, object_on_border
from articulated_dataset.format.shards import shard_name, write_shard
from articulated_dataset.generation.appearance import appearance_record, with_appearance_assets
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.config import GenerationConfig
from articulated_dataset.generation.context_labels import VISIBLE_FRACTION_RANGE
from articulated_dataset.generation.framing import MAX_FRAMING_DRAWS, Framing, extent_points, framing_record
from articulated_dataset.generation.objects import (
    ObjectArrays,
    Streams,
    apply_sensor,
    arrange,
    object_arrays,
    object_sample,
    render_images,
)
from articulated_dataset.generation.occluders import occluders_record
from articulated_dataset.generation.render import DepthRenderer, process_renderer
from articulated_dataset.generation.sampling import ObjectSample, sample_pose
from articulated_dataset.generation.scenes import scene_record
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.generation.viewpoint import head_ranges

log = logging.getLogger(__name__)

#: Pose redraws allowed per object before giving up (a table that never shows the part).
MAX_POSE_ATTEMPTS = 200


def render_object(sample: ObjectSample, config: GenerationConfig, renderer: DepthRenderer, *, check_visibility: bool = True,
                  out: dict | None = None) -> tuple[ObjectArrays, ObjectSample, int]:
    """Template, compile, render and label one sampled object.

    Redraws the pose (from the object's own generator, after its other draws: the state the
    sample keeps) while a moving part covers fewer than ``config.min_part_pixels`` in some
    view.  With ``config.framing`` ``whole`` every pose is drawn from that stream
    (:class:`~articulated_dataset.generation.framing.Framing`: the table's ranges, depth
    extended for the object's size, kept only with the whole object in view) and a render
    with an object pixel on the image's border is redrawn too.  Returns ``(arrays, sample,
    attempts)`` where ``arrays`` holds every schema field for the object's images, ``sample``
    is the one rendered and ``attempts`` counts the pose draws.  ``out`` may hold
    preallocated ``depth`` (n, H, W) float32 and ``mask`` (n, H, W) uint8 arrays (views into
    a shard's buffers) to render into.
    """
    obj_class = config.obj_class
    urdf = object_urdf(obj_class, sample, config.table)  # type: ignore[arg-type]  # GenerationConfig sets table
    n = config.images_per_object
    if out is None:
        out = image_buffers(config, n)
    streams = Streams.of(config, sample.object_index)
    poses = None  # the object's pose-redraw stream, made on the first rejection
    framing, draws = None, 0
    if config.framing == "whole":  # the first pose too comes from the framed ranges
        framing = Framing.of(extent_points(obj_class, urdf, sample.q, config.camera),
                             config.table, config.camera)  # type: ignore[arg-type]  # GenerationConfig sets table
        poses = sample.pose_generator()
        sample, draws = _framed_pose(sample, framing, poses, draws)
    for attempt in range(1, MAX_POSE_ATTEMPTS + 1):  # noqa: B007 - the count is returned
        placed = arrange(sample, config, streams)
        if placed is not None:  # else no scene layout fits this pose
            sample = placed.sample
            add = with_appearance_assets(placed.add_context, obj_class.n_joints) if config.rgb else placed.add_context
            obj = compile_object(obj_class, urdf, placed.pose, config.camera, add)
            views = render_images(obj, sample, config, renderer, streams, out, check_visibility=check_visibility)
            if views is not None and (framing is None or not object_on_border(views.mask).any()):
                break
        if poses is None:
            poses = sample.pose_generator()
        if framing is None:
            sample = replace(sample, pose=sample_pose(poses, config.table))  # type: ignore[arg-type]  # GenerationConfig sets table
        else:
            sample, draws = _framed_pose(sample, framing, poses, draws)
    else:
        raise UserError(
            f"{obj_class.name} object {sample.object_index}: no pose in the table shows every moving part "
            f"with >= {config.min_part_pixels} px"
            + (" and the whole object in view" if framing is not None else "")
            + f" after {MAX_POSE_ATTEMPTS} attempts; check the table"
            + (f" or choose the joints that open with {option('joints')} (a hidden part cannot be labelled)"
               if config.third_party is not None else "")
            + (f" (and >= {VISIBLE_FRACTION_RANGE[0]:g} of its pixels unhidden by the scene and occluders; "
               f"try fewer {option('occluders')})" if config.has_context else "")
        )
    apply_sensor(views.depth, config, sample.object_index)
    return object_arrays(sample, config, views), sample, attempt if framing is None else draws


def _framed_pose(sample: ObjectSample, framing: Framing, poses, draws: int) -> tuple[ObjectSample, int]:
    """``sample`` at the next pose of the stream ``poses`` that keeps it whole in view, and
    ``draws`` plus the poses drawn for it; one line when none does."""
    pose, k = framing.draw(poses)
    if pose is None:
        lo, hi = framing.table.pose["x_m"]
        raise UserError(f"{sample.class_name} object {sample.object_index}: no pose of the table's ranges "
                        f"(depth {lo:g}-{hi:.2f} m) keeps the whole object in view after {MAX_FRAMING_DRAWS} draws; "
                        f"check the table or use {option('framing')} table4")
    return replace(sample, pose=pose), draws + k


def shard_attrs(config: GenerationConfig, objects: range) -> dict:
    """A generated shard's root attributes (:func:`articulated_dataset.format.records.shard_attrs`)
    with the options beyond the paper's setting, recorded only when used (a default shard's
    attributes, and bytes, are as they were)."""
    obj_class = config.obj_class
    assert set(obj_class.joint_types) <= set(JOINT_TYPES)
    attrs = format_shard_attrs(config, obj_class, objects)
    if config.camera.intrinsics is not None:
        attrs["intrinsics"] = config.camera.intrinsics
    if config.camera.mount != "fixed":
        attrs["camera_mount"] = json.dumps({"mount": config.camera.mount, **head_ranges()}, sort_keys=True)
    if config.scene != "none":
        attrs["scene"] = scene_record(config.scene, config.class_name)
    if config.occluders:
        attrs["occluders"] = occluders_record(config.occluders)
    if config.rgb:
        attrs["appearance"] = appearance_record()
    if config.framing != DEFAULT_FRAMING:
        attrs["framing"] = framing_record(config.framing)
    return attrs


def image_buffers(config: GenerationConfig, n: int) -> dict:
    """Empty image arrays of ``n`` images: depth (n, H, W) float32, mask (n, H, W) uint8 and,
    with ``--rgb``, rgb (n, H, W, 3) uint8."""
    H, W = config.camera.height_px, config.camera.width_px
    out = {"depth": np.empty((n, H, W), np.float32), "mask": np.empty((n, H, W), np.uint8)}
    if config.rgb:
        out["rgb"] = np.empty((n, H, W, 3), np.uint8)
    return out


def generate_shard(config: GenerationConfig, shard_index: int, split_dir: str | Path, progress=None) -> dict:
    """Generate shard ``shard_index`` of the split into ``split_dir``; returns its manifest record.

    ``progress(n_images)`` is called after each object, if given.
    """
    renderer = process_renderer(config.camera)
    objects = config.shard_objects(shard_index)
    n = config.images_per_object
    # Images are rendered straight into the shard's buffers (no per-object copies).
    images = image_buffers(config, len(objects) * n)
    stored = FIELDS + (OPTIONAL_FIELDS if config.has_context else ()) + (RGB_FIELDS if config.rgb else ())
    labels: dict[str, list] = {f.name: [] for f in stored if f.name not in images}
    attempts = 0
    for p, k in enumerate(objects):
        out = {name: buf[p * n:(p + 1) * n] for name, buf in images.items()}
        arrays, _, tries = render_object(object_sample(config, k), config, renderer, check_visibility=not config.mean, out=out)
        attempts += tries
        for name in labels:
            labels[name].append(arrays[name])  # type: ignore[literal-required]  # a stored field's name
        if progress is not None:
            progress(n)
    # (the shard's images: every field of its objects' arrays, concatenated)
    arrays = cast(ObjectArrays, {**images, **{name: np.concatenate(v, axis=0) for name, v in labels.items()}})
    attrs = shard_attrs(config, objects)
    attrs["pose_attempts"] = attempts
    record = write_shard(Path(split_dir) / shard_name(shard_index), arrays, attrs, config.camera.K, R_CAMERA_TO_OPTICAL)
    record.update(object_start=objects.start, object_stop=objects.stop, pose_attempts=attempts)
    return record


def run_shard(args, progress=None):
    """Executor task: generate one shard; returns ``(shard_index, manifest_record)``."""
    config, index, split_dir = args
    return index, generate_shard(config, index, split_dir, progress=progress)
