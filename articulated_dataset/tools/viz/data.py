"""What a gallery shows: a split opened for drawing (:class:`SplitView`), the samples chosen
from it, and the RGB preview rebuilt from the manifest's generation config."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError, option
from articulated_dataset.format import MASK_BACKGROUND, MASK_FIRST_PART, Shard, Split
from articulated_dataset.tools.viz.style import BODY_RGBA, PART_TINT_WHITE, joint_colour

log = logging.getLogger(__name__)

#: What a refused ``--rgb`` rebuild of a third-party object suggests instead.
RGB_REBUILD_HINT = f" (generate with {option('rgb')} to store its colour images)"


@dataclass
class SplitView:
    """A split folder opened for display (through :class:`articulated_dataset.format.Split`):
    manifest, shards and the class's joint info."""

    split_dir: Path
    manifest: dict
    shards: list[Shard]
    joint_names: list[str]
    joint_types: list[str]
    q_max: list[float]
    images_per_object: int
    #: Real (ingested) splits: images of each object (objects may have different numbers of
    #: captures; ``images_per_object`` is then the largest); None for generated splits.
    object_images: dict[int, int] | None = None

    @classmethod
    def open(cls, split_dir: str | Path) -> "SplitView":
        split_dir = Path(split_dir)
        split = Split(split_dir)  # manifest, names and shard paths checked
        manifest, shards = split.manifest, split.shards
        if not shards:
            raise DataFormatError(f"{split_dir}: the manifest lists no shards (nothing generated yet)")
        attrs = shards[0].attrs
        try:
            table = json.loads(attrs["sampling_table"])
            return cls(split_dir, manifest, shards, json.loads(attrs["joint_names"]), json.loads(attrs["joint_types"]),
                       [float(r[1]) for r in table["q"]], int(attrs["images_per_object"]),
                       _object_images(manifest))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise DataFormatError(f"{shards[0].path}: unreadable joint attributes ({exc})") from None

    @property
    def name(self) -> str:
        return f"{self.manifest['class_name']}/{self.split_dir.name}"

    @property
    def n_objects(self) -> int:
        return int(self.manifest["n_objects"])

    def locate(self, object_index: int) -> tuple[Shard, int]:
        """The shard holding ``object_index`` and the row of its first image."""
        for rec, sh in zip(self.manifest["shards"], self.shards):
            if rec["object_start"] <= object_index < rec["object_stop"]:
                if self.object_images is not None:
                    return sh, sum(self.object_images.get(o, 0) for o in range(rec["object_start"], object_index))
                return sh, (object_index - rec["object_start"]) * self.images_per_object
        raise UserError(f"object {object_index} is not in {self.name} (it holds objects 0..{self.n_objects - 1})")

    def sample(self, object_index: int, image_index: int) -> dict:
        sh, row = self.locate(object_index)
        s = sh.sample(row + image_index)
        if int(s["object_index"]) != object_index or int(s["image_index"]) != image_index:
            raise DataFormatError(f"{sh.path}: row {row + image_index} holds object {int(s['object_index'])} image "
                                  f"{int(s['image_index'])}, expected object {object_index} image {image_index}")
        s["K"] = sh.K
        return s

    def close(self) -> None:
        for sh in self.shards:
            sh.close()


def _object_images(manifest: dict) -> dict[int, int] | None:
    """{object: number of images} of a real split's manifest (its shards' ``object_images``), else None."""
    if "real" not in manifest:
        return None
    try:
        return {int(o): int(c) for rec in manifest["shards"] for o, c in rec.get("object_images", {}).items()}
    except (AttributeError, TypeError, ValueError) as exc:
        raise DataFormatError(f"manifest: unreadable object_images ({exc})") from None


def select_samples(n_objects: int, images_per_object: int, n: int, objects=None, images=None,
                   object_images: dict[int, int] | None = None) -> list[tuple[int, int]]:
    """``n`` (object, image) pairs spread over the candidates.

    Objects are taken evenly spaced over ``objects`` (default: all) and images evenly
    spaced over ``images`` (default: all), so a gallery runs from closed to open.  With
    fewer candidate pairs than ``n``, all of them are returned.  ``object_images`` (real
    splits: images of each object) leaves out the pairs an object does not have.
    """
    objects = list(range(n_objects)) if objects is None else list(objects)
    images = list(range(images_per_object)) if images is None else list(images)
    pairs = [(o, i) for o in objects for i in images if object_images is None or i < object_images.get(o, 0)]
    if len(pairs) <= n:
        return pairs
    if len(objects) >= n:
        objs = [objects[(k * len(objects)) // n] for k in range(n)]
    else:
        objs = [objects[k % len(objects)] for k in range(n)]
    if n == 1:
        return [(objs[0], images[0]) if (objs[0], images[0]) in pairs else pairs[0]]
    imgs = [images[round(k * (len(images) - 1) / (n - 1))] for k in range(n)]
    out, seen, candidates = [], set(), set(pairs)
    for p in zip(objs, imgs):
        if p in candidates and p not in seen:
            seen.add(p)
            out.append(p)
    for p in pairs:  # fill duplicates (few objects, few images) from the remaining pairs
        if len(out) >= n:
            break
        if p not in seen:
            seen.add(p)
            out.append(p)
    return sorted(out)


def preview_rgb(manifest: dict, object_index: int, image_indices, stored_depth: dict | None = None,
                split_dir: str | Path | None = None, *, urdf=None, mesh_root=None,
                hint: str = RGB_REBUILD_HINT) -> dict[int, np.ndarray]:
    """Shaded colour renders (H, W, 3) uint8 of one object's images, from its rebuilt scene.

    The object is re-sampled from the manifest's config (``object_sample``), rendered with
    :func:`~articulated_dataset.generation.render_object` to get the final pose (visibility redraws included),
    then recompiled with geom colours by part and rendered with ``render_rgb``.  If
    ``stored_depth`` ({image_index: depth}) is given, a mismatch with the re-rendered
    depth is logged as a warning (the stored data came from another package version).
    ``split_dir``: the split folder the manifest belongs to; a third-party object is rebuilt only
    from files inside it (else one line ending with ``hint``), or from ``urdf`` (and ``mesh_root``),
    files the caller names, when their sha256 is the one the split recorded
    (:func:`~articulated_dataset.generation.objects.stored_object_config`).
    """
    import mujoco

    from articulated_dataset.generation import compile_object, object_sample, render_object
    from articulated_dataset.generation.objects import stored_object_config
    from articulated_dataset.generation.render import process_renderer
    from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, ObjectPlacer, set_configuration
    from articulated_dataset.generation.templating import object_urdf
    from articulated_dataset.generation.viewpoint import object_in_camera
    from matplotlib.colors import to_rgba

    config = stored_object_config(manifest.get("config"), split_dir, option("rgb"), hint, urdf=urdf,
                                  mesh_root=mesh_root)
    renderer = process_renderer(config.camera)
    sample0 = object_sample(config, object_index)
    arrays, sample, _ = render_object(sample0, config, renderer, check_visibility=not config.mean)
    obj_class = config.obj_class
    if stored_depth:
        for i, d in stored_depth.items():
            if not np.array_equal(arrays["depth"][i], d):
                log.warning("%s object %d image %d: re-rendered depth differs from the stored image; the RGB preview "
                            "may not match (data from another package version?)", config.class_name, object_index, i)
                break
    head = sample.views is not None  # a head camera: the object is placed in each image's camera frame
    obj = compile_object(obj_class, object_urdf(obj_class, sample, config.table),  # type: ignore[arg-type]  # GenerationConfig sets table
                         ORIGIN_POSE if head else sample.pose,
                         config.camera)
    model, info = obj.model, obj.info
    placer = ObjectPlacer(model, info.base_body) if head else None
    for g in range(model.ngeom):
        part = int(info.geom_part[g])
        if part >= MASK_FIRST_PART:
            c = np.array(to_rgba(joint_colour(part - MASK_FIRST_PART)))
            model.geom_rgba[g] = (1 - PART_TINT_WHITE) * c + PART_TINT_WHITE * np.ones(4)
        elif part != MASK_BACKGROUND:
            model.geom_rgba[g] = BODY_RGBA
    data = mujoco.MjData(model)
    renderer.bind(model)
    out = {}
    for i in image_indices:
        if placer is not None:
            placer.place(object_in_camera(sample.pose, sample.views[i]))
        set_configuration(model, data, info.joint_ids, sample.q[i])
        out[i] = renderer.render_rgb(data)
    return out
