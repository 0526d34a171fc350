"""The settings of a generated split (:class:`GenerationConfig`), where it goes, and the
per-object random streams besides the sampling one (sensor noise, head-camera views).

Light: no MuJoCo (the command line and the readers can build a config without a renderer).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articulated_dataset.classes.registry import ObjectClass, check_table, get_class, register, registered_third_party
from articulated_dataset.format.manifest import SplitConfig
from articulated_dataset.generation.sampling import object_rng
from articulated_dataset.generation.viewpoint import CAMERA_STREAM


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
        if self.table is None:  # (then obj_class was resolved above)
            object.__setattr__(self, "table", obj_class.table)  # type: ignore[union-attr]
        if obj_class is not None:
            check_table(obj_class, self.table)  # type: ignore[arg-type]  # set just above

    @property
    def obj_class(self) -> ObjectClass:
        """The object class generated: the registered class ``class_name``, or the third-party object's class."""
        return resolve(self.class_name, self.third_party)


def resolve(class_name: str, third_party: dict | None = None) -> ObjectClass:
    """The class of a split config: the registered class ``class_name``, or the third-party
    URDF class that ``third_party`` (its definition, as ``artdata generate --urdf`` writes it)
    defines, built once per process and registered
    (:func:`articulated_dataset.classes.registry.register`)."""
    if third_party is None:
        return get_class(class_name)
    found = registered_third_party(third_party)
    if found is None:
        from articulated_dataset.generation.urdf_import import class_from_definition  # trimesh, lxml: on use

        found = register(class_from_definition(third_party), definition=third_party)
    return found


def split_dir_for(out_root: str | Path, config: SplitConfig) -> Path:
    """``OUT/<class>/<split>`` (``OUT/<class>/mean`` for the mean object)."""
    return Path(out_root) / config.class_name / ("mean" if config.mean else config.split)


#: Extra SeedSequence word separating the noise stream from the object's sampling stream.
NOISE_STREAM = 1


def noise_rng(config: SplitConfig, object_index: int) -> np.random.Generator:
    """Generator of the sensor noise of one object, independent of its sampling stream."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=NOISE_STREAM)


def camera_rng(config: SplitConfig, object_index: int) -> np.random.Generator:
    """Generator of one object's head-camera views (:mod:`articulated_dataset.generation.viewpoint`),
    independent of its sampling stream: an object is the same with either camera."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=CAMERA_STREAM)


#: Extra SeedSequence word of an object's colour appearance stream (``--rgb``; noise 1, head
#: camera 2, scene 3, occluders 4).
APPEARANCE_STREAM = 5


def appearance_rng(config: SplitConfig, object_index: int) -> np.random.Generator:
    """Generator of one object's colour appearance (``--rgb``: materials, textures, lights;
    :mod:`articulated_dataset.generation.appearance`), independent of every other stream."""
    return object_rng(config.seed, config.class_name, config.split, object_index, stream=APPEARANCE_STREAM)
