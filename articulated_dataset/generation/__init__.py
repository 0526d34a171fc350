"""Generation: an object class -> sampled objects -> depth images and labels -> a split folder.

The stages, each a small function from one input to one output (:mod:`.objects`):

1. sample (:mod:`.sampling`): the object's geometry, chirality, configurations and pose,
   from its own seeded generator (whose state the sample keeps for pose redraws);
2. template (:mod:`.templating`): the class's Xacro arguments -> URDF;
3. compile (:mod:`.compiled`, :mod:`.scene`): URDF -> MuJoCo model -> index tables
   (:func:`compile_object`, the one place any part of the package compiles an object); a
   scene and occluders (:mod:`.scenes`, :mod:`.occluders`) and head-camera views
   (:mod:`.viewpoint`) are arranged first;
4. render (:mod:`.render`): depth and the part mask of every image, then the sensor's noise
   and quantisation;
5. label (:mod:`.labels`, :mod:`.context_labels`): labels read from the compiled model;
6. write: shards (:mod:`.pipeline`, :func:`articulated_dataset.format.shards.write_shard`) and the
   split with its manifest (:mod:`.split`).

:mod:`.config` holds :class:`GenerationConfig` (a :class:`~articulated_dataset.format.SplitConfig`
checked against the registry).  Importing this package imports nothing heavy: the names
below load their module (and MuJoCo, for the rendering ones) when first used, so light
readers (verify, viz) can import :mod:`.viewpoint` or :mod:`.context_labels` alone.
"""

from __future__ import annotations

import importlib

#: Public names and the module that defines each.
_EXPORTS = {
    "GenerationConfig": "config", "split_dir_for": "config", "noise_rng": "config", "camera_rng": "config",
    "object_sample": "objects", "stored_sample": "objects",
    "compile_object": "compiled", "CompiledObject": "compiled",
    "render_object": "pipeline", "generate_shard": "pipeline", "shard_attrs": "pipeline",
    "generate_split": "split", "check_resources": "split",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
