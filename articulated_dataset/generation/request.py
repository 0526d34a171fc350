"""What ``artdata generate``'s options ask for, as a checked :class:`GenerationConfig`.

The command parses its options, calls :func:`config_from_options` and prints.  The rules that
tie options together live here or beside what they configure: the camera
(:func:`articulated_dataset.core.camera.camera_from_options`), the sampling table
(:func:`articulated_dataset.core.tables.table_from_options`), a third-party URDF
(:func:`articulated_dataset.generation.urdf_import.import_urdf`).  A contradiction or an impossible
value is one :class:`~articulated_dataset.core.errors.UserError` line naming the options.

Light: no MuJoCo until a ``--urdf`` object is imported (it is measured with MuJoCo).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

from articulated_dataset.classes.registry import ObjectClass, get_class, register
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.tables import table_from_options
from articulated_dataset.generation.config import GenerationConfig

#: Objects generated without ``--n``.
DEFAULT_N_OBJECTS = 100


@dataclass(frozen=True)
class UrdfOptions:
    """``--urdf FILE`` and the options that only go with it (None / False: not given)."""

    path: str | None = None
    joints: str | None = None  # --joints NAME,NAME,...
    class_name: str | None = None  # --class-name
    skip_missing_meshes: bool = False
    scale: float | str | None = None  # a number or auto:CLASS
    mesh_root: str | None = None


def joint_names(text: str | None) -> list[str] | None:
    """``--joints NAME,NAME,...`` as a list (None when not given)."""
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise UserError(f"{option('joints')} needs at least one joint name (NAME,NAME,...)")
    return names


def object_class_from_options(class_name: str | None, urdf: UrdfOptions, camera: CameraConfig, *,
                              echo: Callable[[str], None] | None = None) -> tuple[ObjectClass, dict | None]:
    """The class ``--class NAME`` or ``--urdf FILE`` names, and the third-party definition of a
    URDF object (None for a built-in class).  A URDF object is imported and registered;
    ``echo`` receives the lines that summarise the import."""
    if urdf.path is not None:
        if class_name is not None:
            raise UserError(f"give either {option('class_name')} or {option('urdf_path')}, not both")
        from articulated_dataset.generation.urdf_import import import_urdf

        imported = import_urdf(urdf.path, joints=joint_names(urdf.joints), class_name=urdf.class_name,
                               skip_missing_meshes=urdf.skip_missing_meshes, camera=camera,
                               scale=1.0 if urdf.scale is None else urdf.scale, mesh_root=urdf.mesh_root)
        obj_class = register(imported.obj_class, definition=imported.definition)
        if echo is not None:
            for line in imported.summary():
                echo(line)
        return obj_class, imported.definition
    if class_name is None:
        raise UserError(f"missing {option('class_name')} NAME (or {option('urdf_path')} FILE)")
    unused = [name for name, v in (("joints", urdf.joints), ("urdf_class_name", urdf.class_name),
                                   ("skip_missing_meshes", urdf.skip_missing_meshes),
                                   ("scale", urdf.scale is not None), ("mesh_root", urdf.mesh_root)) if v]
    if unused:
        raise UserError(f"{option(unused[0])} is for {option('urdf_path')} objects")
    return get_class(class_name), None


def object_count(n_objects: int | None, mean: bool) -> int:
    """``--n`` with ``--mean`` (exactly one object) and its default."""
    if mean:
        if n_objects not in (None, 1):
            raise UserError(f"{option('mean')} renders exactly one object (the class's mean object); "
                            f"drop {option('n_objects')} {n_objects}")
        return 1
    return DEFAULT_N_OBJECTS if n_objects is None else n_objects


def config_from_options(class_name: str | None, urdf: UrdfOptions, camera: CameraConfig, tables: Sequence[str], *,
                        n_objects: int | None, mean: bool, echo: Callable[[str], None] | None = None,
                        **settings) -> GenerationConfig:
    """The :class:`GenerationConfig` of ``artdata generate``'s options: the class
    (:func:`object_class_from_options`), its table (``--table`` values), the number of objects
    (:func:`object_count`) and the other ``settings`` (``split``, ``seed``, ``images_per_object``,
    ``objects_per_shard``, ``noise``, ``scene``, ``occluders``, ``rgb``, ``framing``) as
    :class:`GenerationConfig` takes them."""
    obj_class, third_party = object_class_from_options(class_name, urdf, camera, echo=echo)
    table = table_from_options(obj_class, tables)
    return GenerationConfig(class_name=obj_class.name, n_objects=object_count(n_objects, mean), camera=camera,
                            table=table, mean=mean, third_party=third_party, **settings)
