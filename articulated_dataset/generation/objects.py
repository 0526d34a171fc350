"""The per-object stages of the pipeline, each one function from one input to one output:

* sample (stage 1): :func:`object_sample` -- config and object index -> :class:`ObjectSample`;
* template (stage 2): :func:`~articulated_dataset.generation.templating.object_urdf` -- sample -> URDF;
* arrange: :func:`arrange` -- sample -> where it is compiled (head-camera views drawn, or
  its scene laid out), or None when no scene layout fits its pose;
* compile (stage 3): :func:`~articulated_dataset.generation.compiled.compile_object` -- URDF
  at a pose -> model and its index tables;
* render (stage 4): :func:`render_images` -- compiled object -> :class:`Views` (depth, mask,
  configurations, visible pixels, the object's labels), or None when a part is hidden;
  :func:`apply_sensor` -- rendered depth -> depth as the sensor reports it (noise, quantum);
* label (stage 5): :func:`object_arrays` -- views -> every schema field of the object's images.

:func:`articulated_dataset.generation.pipeline.render_object` composes them, redrawing the
pose while a stage rejects it; writing (stage 6) is per shard.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypedDict, cast

import mujoco
import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format.manifest import check_stored_object_files, third_party_definition
from articulated_dataset.generation.appearance import Appearance
from articulated_dataset.generation.compiled import CompiledObject
from articulated_dataset.generation.config import GenerationConfig, appearance_rng, camera_rng, noise_rng
from articulated_dataset.generation.context_labels import visible_fraction
from articulated_dataset.generation.labels import read_configuration, read_object_labels, visible_pixels
from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, ObjectPlacer, set_configuration
from articulated_dataset.generation.occluders import Context
from articulated_dataset.generation.render import DepthRenderer
from articulated_dataset.generation.sampling import ObjectSample, mean_object, sample_id, sample_object
from articulated_dataset.generation.scenes import context_builder, context_rngs
from articulated_dataset.generation.viewpoint import head_views, object_in_camera

#: Label fields read from the compiled model (per object, or per image with the head camera).
OBJECT_LABEL_FIELDS = ("axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw", "geometry")

#: The fields every object has (a functional TypedDict: ``class`` is a keyword); n images, J
#: joints, P = 1 + J parts; dtypes and units as :data:`articulated_dataset.format.schema.FIELDS`.
_ObjectArraysFields = TypedDict("_ObjectArraysFields", {
    "depth": np.ndarray,  # (n, H, W) float32, m; 0: no return
    "mask": np.ndarray,  # (n, H, W) uint8: 0 background, 1 body, 2 + j part j
    "q": np.ndarray,  # (n, J) float32, rad (revolute) or m (prismatic)
    "axis_origin": np.ndarray,  # (n, J, 3) float32, m, camera frame
    "axis_direction": np.ndarray,  # (n, J, 3) float32, unit
    "axis_pose": np.ndarray,  # (n, J, 7) float32: position (m) and quaternion (w, x, y, z)
    "part_offset": np.ndarray,  # (n, J, 3) float32, m, axis frame
    "object_pose": np.ndarray,  # (n, 7) float32: position (m) and quaternion (w, x, y, z)
    "object_yaw": np.ndarray,  # (n,) float32, rad
    "geometry": np.ndarray,  # (n, 4) float32: depth, width, height (m) and chirality
    "visible_pixels": np.ndarray,  # (n, P) int32, px
    "object_index": np.ndarray,  # (n,) int64
    "image_index": np.ndarray,  # (n,) int32
    "sample_id": np.ndarray,  # (n,) int64
    "class": np.ndarray,  # (n,) S32, ASCII class name
})


class ObjectArrays(_ObjectArraysFields, total=False):
    """Every schema field of one object's n images (:func:`object_arrays`), concatenated over a
    shard's objects for :func:`~articulated_dataset.format.shards.write_shard`; the optional
    fields only where the split stores them."""

    rgb: np.ndarray  # (n, H, W, 3) uint8 (--rgb)
    unoccluded_pixels: np.ndarray  # (n, P) int32, px (a scene or occluders)
    visible_fraction: np.ndarray  # (n, P) float32 (a scene or occluders)


def object_sample(config: GenerationConfig, object_index: int) -> ObjectSample:
    """Stage 1 for object ``object_index`` of the split (the mean object with ``config.mean``).
    The sample keeps its generator's state for pose redraws (:meth:`ObjectSample.pose_generator`)."""
    if config.mean:
        return mean_object(config.obj_class, config.table,  # type: ignore[arg-type]  # GenerationConfig sets table
                           split=config.split, n_images=config.images_per_object)
    sample, _ = sample_object(config.obj_class, config.table,  # type: ignore[arg-type]  # GenerationConfig sets table
                              seed=config.seed, split=config.split,
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


def stored_object_config(config: Any, split_dir, what: str, hint: str = "", *, urdf=None,
                         mesh_root=None) -> GenerationConfig:
    """The :class:`GenerationConfig` a stored object is rebuilt from (by :func:`stored_sample`,
    :func:`object_sample` and the compiler), made of a manifest's ``config`` dict.

    A third-party URDF object (``generate --urdf``) is rebuilt from files.  Without ``urdf``, the
    paths its definition records must lie inside ``split_dir``, else a one-line refusal naming
    ``what`` and ending with ``hint``
    (:func:`~articulated_dataset.format.manifest.check_stored_object_files`).  With ``urdf`` (and
    ``mesh_root``, the folder its meshes are read from; default the URDF's folder), the object is
    rebuilt from these files, which the caller named, instead of the recorded paths; they are used
    only if their sha256 (URDF and meshes) is the one the split recorded, else one line.  A
    built-in class needs no files (``urdf`` given for one is refused)."""
    from articulated_dataset.generation.urdf_import.build import (
        SourceMismatchError,  # (imported when a rebuild needs it)
    )

    if urdf is None:
        if mesh_root is not None:
            raise UserError(f"a mesh folder ({mesh_root}) is used with the URDF it belongs to; name the URDF too")
        check_stored_object_files(config, split_dir, what, hint)
    else:
        definition = third_party_definition(config, split_dir)
        if definition is None:
            raise UserError(f"{split_dir or 'the split'} holds a built-in class, rebuilt from the package's own "
                            f"templates; the URDF {urdf} is not used (only a split generated from a URDF needs it)")
        named = {k: v for k, v in definition.items() if k != "mesh_root"}
        named["urdf"] = str(Path(urdf).expanduser().resolve())
        if mesh_root is not None:
            folder = Path(mesh_root).expanduser().resolve()
            if not folder.is_dir():
                raise UserError(f"the mesh folder {mesh_root} is not a folder")
            named["mesh_root"] = str(folder)
        config = {**config, "third_party": named}
    try:
        generation = GenerationConfig.from_dict(config)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DataFormatError(f"{split_dir or 'the split'}: manifest config cannot be read back "
                              f"({type(exc).__name__}: {exc}); {what} needs it") from None
    if urdf is not None:
        try:
            generation.obj_class  # noqa: B018 - builds the class: reads the named files, compares their sha256
        except SourceMismatchError:
            raise UserError(f"{urdf} is not the URDF this split was generated from (sha256 differs)") from None
    return generation


@dataclass(frozen=True)
class Streams:
    """One object's generators besides its sampling stream (None where unused): head-camera
    views, scene layout, occluders, colour appearance.  Made once per object and advanced by
    every attempt."""

    camera: np.random.Generator | None
    scene: np.random.Generator | None
    occluders: np.random.Generator | None
    appearance: np.random.Generator | None = None

    @classmethod
    def of(cls, config: GenerationConfig, object_index: int) -> "Streams":
        """The generators of object ``object_index`` under ``config``: camera views (head mount, not --mean), scene,
        occluders and colour appearance (--rgb), None where unused."""
        head = config.camera.mount == "head"
        crng = camera_rng(config, object_index) if head and not config.mean else None
        arng = appearance_rng(config, object_index) if config.rgb else None
        return cls(crng, *context_rngs(config, object_index), arng)


@dataclass(frozen=True)
class Arrangement:
    """What stage 3 compiles: the sample as placed (views drawn, base height fitted to its
    scene), the base pose given to the compiler and the hook that adds scene and occluders."""

    sample: ObjectSample
    pose: dict
    add_context: object = None  # callable(spec) or None


def arrange(sample: ObjectSample, config: GenerationConfig, streams: Streams) -> Arrangement | None:
    """Where the sample is compiled: with the head camera at the origin (placed per image,
    views drawn now), with a scene or occluders in its context, else at its pose.  None when
    no scene layout fits the pose (it must be redrawn)."""
    if config.camera.mount == "head":
        add_context = None
        if config.has_context:  # the scene's floor sets the base height; the scene moves with the object
            sample, add_context = context_builder(config, sample, streams.scene)
            if add_context is None:
                return None
        views = head_views(streams.camera, sample.pose, sample.geometry, config.images_per_object)
        return Arrangement(replace(sample, views=views), ORIGIN_POSE, add_context)
    if config.has_context:
        sample, add_context = context_builder(config, sample, streams.scene)
        return None if add_context is None else Arrangement(sample, sample.pose, add_context)
    return Arrangement(sample, sample.pose)


@dataclass
class Views:
    """Stage 4's output for one object: its images and what was read while rendering them."""

    depth: np.ndarray  # (n, H, W) float32, m
    mask: np.ndarray  # (n, H, W) uint8
    q: np.ndarray  # (n, J) configurations read back from the model
    visible: np.ndarray  # (n, 1 + J) visible pixels of the body and each part
    unoccluded: np.ndarray | None  # (n, 1 + J) the same without scene and occluders (context only)
    labels: dict  # OBJECT_LABEL_FIELDS -> (n, ...) arrays
    rgb: np.ndarray | None = None  # (n, H, W, 3) uint8 colour images (--rgb only)


def render_images(obj: CompiledObject, sample: ObjectSample, config: GenerationConfig, renderer: DepthRenderer,
                  streams: Streams, out: dict, *, check_visibility: bool = True) -> Views | None:
    """Render the object's images into ``out["depth"]``/``out["mask"]`` ((n, H, W) buffers),
    and with ``config.rgb`` its colour images into ``out["rgb"]`` ((n, H, W, 3) uint8; the
    model compiled with :func:`~articulated_dataset.generation.appearance.with_appearance_assets`).
    None (the pose is rejected) when a moving part covers fewer than
    ``config.min_part_pixels`` in some view (with ``check_visibility``) or no occluder draw
    leaves every part identifiable."""
    model, info, obj_class = obj.model, obj.info, config.obj_class
    n, J = config.images_per_object, obj_class.n_joints
    head = config.camera.mount == "head"
    data = mujoco.MjData(model)
    ctx = Context(model, info, config.occluders, streams.occluders) if config.has_context else None
    if head:  # the object (and its scene) is built at the origin and placed in each image's camera frame
        placers = [ObjectPlacer(model, info.base_body)]
        if ctx is not None and ctx.scene_body >= 0:
            placers.append(ObjectPlacer(model, ctx.scene_body))
        per_image: list = [None] * n
    else:
        labels = read_object_labels(model, data, info, obj_class)
    renderer.bind(model)
    depth, mask = out["depth"], out["mask"]
    look = None
    if config.rgb:  # materials drawn once per compiled model, after the context's mask codes
        look = Appearance(model, info.geom_part, J, streams.appearance)  # type: ignore[arg-type]  # made with --rgb
        look.dress()
    q = np.empty((n, J), np.float64)
    vis = np.empty((n, 1 + J), np.int32)
    alone = np.empty((n, 1 + J), np.int32) if ctx is not None else None
    # Widest-open configurations first: they are the views that fail the visibility
    # check (doors edge-on or swung out of the frame), so a rejected pose costs few renders.
    for i in np.argsort(-sample.q.sum(axis=1), kind="stable"):
        if head:  # this image's camera: labels are read from the model as placed for it
            T = object_in_camera(sample.pose, sample.views[i])  # type: ignore[index]  # set for the head mount
            for placer in placers:
                placer.place(T)
            per_image[i] = read_object_labels(model, data, info, obj_class)
        set_configuration(model, data, info.joint_ids, sample.q[i])
        if ctx is not None:
            counts = ctx.render(renderer, data, depth[i], mask[i], config.min_part_pixels)  # type: ignore[arg-type]  # set by SplitConfig
            if counts is None:  # no occluder draw leaves every moving part identifiable
                return None
            vis[i], alone[i] = counts  # type: ignore[index]  # made when ctx is
        else:
            _, geom_id = renderer.render(data, depth_out=depth[i])
            mask[i] = info.mask_from_geoms(geom_id)
            vis[i] = visible_pixels(mask[i], J)
        if check_visibility and vis[i, 1:].min() < config.min_part_pixels:
            return None
        if look is not None:  # the same state (occluders as drawn), lights drawn per image
            look.light(data)
            renderer.render_rgb(data, out["rgb"][i], context=ctx is not None)
        q[i] = read_configuration(data, info)
    if head:
        stacked = {k: np.stack([np.asarray(per_image[i][k]) for i in range(n)]) for k in per_image[0]}
    else:
        stacked = {k: np.repeat(np.asarray(v)[None], n, 0) for k, v in labels.items()}
    return Views(depth, mask, q, vis, alone, stacked, out["rgb"] if look is not None else None)


def apply_sensor(depth: np.ndarray, config: GenerationConfig, object_index: int) -> None:
    """Rendered depth (n, H, W) -> the depth stored, in place (it may be a view into a
    shard's buffer): the sensor-noise model (seeded per object, :func:`noise_rng`), then
    rounding to ``config.depth_quantum_m``."""
    if config.noise != "none":
        from articulated_dataset.core.noise import get_noise_model

        apply_noise = get_noise_model(config.noise)
        nrng = noise_rng(config, object_index)
        K = config.camera.K
        for i in range(len(depth)):
            depth[i] = apply_noise(depth[i], K, nrng)
    if config.depth_quantum_m > 0:
        np.divide(depth, config.depth_quantum_m, out=depth)
        np.round(depth, out=depth)
        np.multiply(depth, config.depth_quantum_m, out=depth)


def object_arrays(sample: ObjectSample, config: GenerationConfig, views: Views) -> ObjectArrays:
    """Stage 5: every schema field of the object's images (optional occlusion fields with a
    scene or occluders, format 1.1)."""
    n = config.images_per_object
    ids = np.array([sample_id(config.class_name, config.split, config.seed, sample.object_index, i) for i in range(n)], np.int64)
    arrays = {
        "depth": views.depth,
        "mask": views.mask,
        "q": views.q.astype(np.float32),
        **{k: views.labels[k].astype(np.float32) for k in OBJECT_LABEL_FIELDS},
        "visible_pixels": views.visible,
        "object_index": np.full(n, sample.object_index, np.int64),
        "image_index": np.arange(n, dtype=np.int32),
        "sample_id": ids,
        "class": np.full(n, config.class_name.encode("ascii"), dtype="S32"),
    }
    if views.rgb is not None:
        arrays["rgb"] = views.rgb
    if views.unoccluded is not None:
        arrays["unoccluded_pixels"] = views.unoccluded
        arrays["visible_fraction"] = visible_fraction(views.visible, views.unoccluded)
    return cast(ObjectArrays, arrays)  # (the label fields are added by name above)
