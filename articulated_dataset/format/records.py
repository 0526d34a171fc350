"""What a writer of a split records: the shard attributes (:func:`shard_attrs`) and the
manifest (:func:`split_manifest`), built in one place for every writer (the generator,
:mod:`articulated_dataset.generation.pipeline`; real-capture ingestion,
:mod:`articulated_dataset.ingest.write`).

Both are plain dicts of JSON/HDF5 attribute values; docs/format.md describes each key.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from articulated_dataset import __version__
from articulated_dataset.format.manifest import SplitConfig

if TYPE_CHECKING:  # the class is read through its attributes: the format imports no class code
    from articulated_dataset.classes.base import ObjectClass


def shard_attrs(config: SplitConfig, obj_class: ObjectClass, objects: range, **extra) -> dict:
    """The root attributes of a shard holding ``objects`` of a split written with ``config``.

    ``extra`` adds attributes or replaces the config's values (a real split: its noise model
    ``real``, its per-shard field of view and image counts, the capture names)."""
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
        "sampling_table": config.table.to_json(),  # type: ignore[union-attr]  # filled in before shards are written
        "package_version": __version__,
    }
    attrs.update(extra)
    return attrs


def split_manifest(config: SplitConfig, shards: list[dict], *, n_objects: int | None = None,
                   n_shards_expected: int | None = None, **extra) -> dict:
    """The manifest of a split written with ``config`` whose complete shards' records are
    ``shards`` (in shard order).  ``n_objects`` defaults to the objects the shards hold,
    ``n_shards_expected`` to the config's shard count; ``extra`` adds keys (a real split's
    ``real`` record)."""
    expected = config.n_shards if n_shards_expected is None else n_shards_expected
    return {
        "format_version": config.format_version,
        "package_version": __version__,
        "class_name": config.class_name,
        "split": config.split,
        "seed": config.seed,
        "complete": len(shards) == expected,
        "n_objects": sum(r["object_stop"] - r["object_start"] for r in shards) if n_objects is None else n_objects,
        "n_images": sum(r["n_images"] for r in shards),
        "n_shards_expected": expected,
        "config": config.to_dict(),
        "shards": shards,
        **extra,
    }
