"""Registry of object classes: the one place a class name resolves.

One built-in object class = one Xacro template (``classes/<name>.urdf.xacro``) + one
module ``classes/<name>.py`` defining ``CLASS``, an :class:`ObjectClass` (template name,
sampling table, joints: data, importing no registry) + its name in :data:`BUILTIN_GENERATORS`,
from which the registry loads the built-ins on first use.  A third-party URDF class is
registered the same way (:func:`register`) when a split config that defines it is resolved
(:func:`resolve`), built from its definition by :mod:`articulated_dataset.generation.urdf_import`.
Everything else (sampling, rendering, labelling, CLI choices, docs tables, contract tests)
iterates over this registry.
"""

from __future__ import annotations

import importlib
import json
import math

from articulated_dataset.classes.base import JointSpec, ObjectClass  # noqa: F401  (re-exported: the registry's types)
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.tables import SamplingTable
from articulated_dataset.format.schema import JOINT_TYPES, PRISMATIC, REVOLUTE  # noqa: F401  (declared with the format)

#: Largest configuration of a revolute joint (rad): one full turn.
MAX_REVOLUTE_Q_RAD = 2.0 * math.pi
#: Integer codes of joint types as stored in shards (``joint_type`` attribute / dataset).
JOINT_TYPE_CODES = {REVOLUTE: 0, PRISMATIC: 1}
#: The paper's six classes (its Appendix A, Tables 1 and 2), in its order.
PAPER_CLASSES = ("cabinet", "drawer", "microwave", "toaster", "cabinet2", "refrigerator")
#: The built-in classes: modules of :mod:`articulated_dataset.classes` (each defines
#: ``CLASS``, named like its module): the paper's six in its order, then this package's own
#: classes (their tables are not the paper's).
BUILTIN_GENERATORS = PAPER_CLASSES + ("oven", "dishwasher", "lidded_box")
#: Package of the built-in generator modules.
GENERATORS_PACKAGE = "articulated_dataset.classes"

_REGISTRY: dict[str, ObjectClass] = {}
#: Third-party URDF classes by their definition (one name may be defined twice in a process,
#: e.g. one file imported at two scales: each definition keeps its own class).
_THIRD_PARTY: dict[str, ObjectClass] = {}
_BUILTINS_LOADED = False


def _definition_key(definition: dict) -> str:
    return json.dumps(definition, sort_keys=True)


def register(obj_class: ObjectClass, *, definition: dict | None = None) -> ObjectClass:
    """Add a class to the registry: a built-in's (``definition`` None; its name must be new)
    or a third-party URDF class's, under its ``definition`` (a built-in's name is refused)."""
    if len(obj_class.table.q) != obj_class.n_joints:
        raise ValueError(f"{obj_class.name}: table has {len(obj_class.table.q)} q ranges for {obj_class.n_joints} joints")
    if definition is not None:
        _load_builtins()
        if obj_class.name in _REGISTRY:
            raise UserError(f"class name {obj_class.name!r} is a built-in class; pass another {option('urdf_class_name')}")
        _THIRD_PARTY[_definition_key(definition)] = obj_class
        return obj_class
    if obj_class.name in _REGISTRY and _REGISTRY[obj_class.name] != obj_class:
        raise ValueError(f"object class {obj_class.name!r} is already registered")
    _REGISTRY[obj_class.name] = obj_class
    return obj_class


def _load_builtins() -> None:
    """Register the ``CLASS`` of every module of :data:`BUILTIN_GENERATORS` (once)."""
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    classes = []
    for name in BUILTIN_GENERATORS:
        obj_class = importlib.import_module(f"{GENERATORS_PACKAGE}.{name}").CLASS
        if not isinstance(obj_class, ObjectClass) or obj_class.name != name:
            raise ValueError(f"{GENERATORS_PACKAGE}.{name}: CLASS must be the ObjectClass named {name!r}")
        classes.append(obj_class)
    for obj_class in sorted(classes, key=lambda c: (c.order, c.name)):
        register(obj_class)


def registered_third_party(definition: dict) -> ObjectClass | None:
    """The third-party URDF class registered under ``definition`` (:func:`register`), or None."""
    return _THIRD_PARTY.get(_definition_key(definition))


def class_names() -> list[str]:
    """The built-in class names, in the paper's order."""
    _load_builtins()
    return list(_REGISTRY)


def get_class(name: str) -> ObjectClass:
    """Look up a class; unknown names are a :class:`UserError` listing the valid ones."""
    _load_builtins()
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):  # TypeError: an unhashable name (a list) from the Python API
        folded = [n for n in _REGISTRY if isinstance(name, str) and n.lower() == name.strip().lower()]
        hint = f"did you mean {folded[0]!r}? " if folded else ""
        raise UserError(f"unknown object class {name!r}; {hint}choose from: {', '.join(_REGISTRY)}") from None


def all_classes() -> list[ObjectClass]:
    """Every registered class (the built-in ones loaded first), in registration order."""
    _load_builtins()
    return list(_REGISTRY.values())


def check_table(obj_class: ObjectClass, table: SamplingTable) -> None:
    """UserError unless ``table`` fits ``obj_class``: one q range per joint, a revolute joint
    opening at most one turn, structure variables only the class's varied table has."""
    obj_class.check_structure(table)
    if len(table.q) != obj_class.n_joints:
        raise UserError(f"sampling table: q needs {obj_class.n_joints} ranges (one per joint), got {len(table.q)}")
    for j, (joint, (_, hi)) in enumerate(zip(obj_class.joints, table.q)):
        if joint.type == REVOLUTE and hi > MAX_REVOLUTE_Q_RAD:
            raise UserError(f"sampling table: q[{j}] (revolute joint {joint.name}) must be at most one turn "
                            f"({MAX_REVOLUTE_Q_RAD:.4f} rad), got {hi}")
