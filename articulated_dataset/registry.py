"""Registry of object classes.

One object class = one Xacro template (``urdf_templates/<name>.urdf.xacro``) + one sampling
table + one :func:`register` call (``generators/<name>.py``).  Everything else (sampling,
rendering, labelling, CLI choices, docs tables, contract tests) iterates over this registry.
"""

from __future__ import annotations

import importlib
import math
import pkgutil
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from .errors import UserError
from .format.schema import JOINT_TYPES, PRISMATIC, REVOLUTE  # noqa: F401  (declared with the format)
from .tables import SamplingTable

#: Largest configuration of a revolute joint (rad): one full turn.
MAX_REVOLUTE_Q_RAD = 2.0 * math.pi
#: Integer codes of joint types as stored in shards (``joint_type`` attribute / dataset).
JOINT_TYPE_CODES = {REVOLUTE: 0, PRISMATIC: 1}


@dataclass(frozen=True)
class JointSpec:
    """One articulated joint of a class, in label order.

    ``name`` is the joint's name in the URDF template; ``part`` the child link (moving part).
    """

    name: str
    type: str
    part: str

    def __post_init__(self) -> None:
        if self.type not in JOINT_TYPES:
            raise ValueError(f"joint type must be one of {JOINT_TYPES}, got {self.type!r}")


@dataclass(frozen=True)
class ObjectClass:
    """Everything the pipeline needs to know about one object class.

    Attributes
    ----------
    name: registry key (``artdata generate --class NAME``).
    template: file name of the Xacro template in ``urdf_templates/`` (or an absolute path to
        a URDF/Xacro file elsewhere, e.g. a third-party object).
    table: default sampling table (the paper's Appendix A for the built-in classes).
    joints: articulated joints in label order (J = len(joints)).
    base_link: the URDF root link (its frame is the centre of the object's base).
    sided: True if the class has a chirality (hinge side) that the labeller reads from the
        model; False for classes whose chirality label is always 0.
    description: one line for docs and ``artdata classes``.
    order: listing order (the paper's order for the built-ins); ties broken by name.
    """

    name: str
    template: str
    table: SamplingTable
    joints: tuple[JointSpec, ...]
    base_link: str = "base"
    sided: bool = False
    description: str = ""
    order: int = 100

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def joint_types(self) -> tuple[str, ...]:
        return tuple(j.type for j in self.joints)

    def template_path(self) -> Path:
        """The template file: ``template`` itself if absolute, else a file of ``urdf_templates/``."""
        if Path(self.template).is_absolute():
            return Path(self.template)
        path = resources.files("articulated_dataset.urdf_templates").joinpath(self.template)
        return Path(str(path))


_REGISTRY: dict[str, ObjectClass] = {}
_BUILTINS_LOADED = False


def register(obj_class: ObjectClass) -> ObjectClass:
    """Add a class to the registry (name must be new)."""
    if obj_class.name in _REGISTRY and _REGISTRY[obj_class.name] != obj_class:
        raise ValueError(f"object class {obj_class.name!r} is already registered")
    if len(obj_class.table.q) != obj_class.n_joints:
        raise ValueError(f"{obj_class.name}: table has {len(obj_class.table.q)} q ranges for {obj_class.n_joints} joints")
    _REGISTRY[obj_class.name] = obj_class
    return obj_class


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    pkg = importlib.import_module("articulated_dataset.generators")
    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{pkg.__name__}.{info.name}")
    ordered = sorted(_REGISTRY.values(), key=lambda c: (c.order, c.name))
    _REGISTRY.clear()
    _REGISTRY.update((c.name, c) for c in ordered)


def class_names() -> list[str]:
    """Registered class names, in registration order (built-ins sorted by module name)."""
    _load_builtins()
    return list(_REGISTRY)


def get_class(name: str) -> ObjectClass:
    """Look up a class; unknown names are a :class:`UserError` listing the valid ones."""
    _load_builtins()
    try:
        return _REGISTRY[name]
    except KeyError:
        folded = [n for n in _REGISTRY if isinstance(name, str) and n.lower() == name.strip().lower()]
        hint = f"did you mean {folded[0]!r}? " if folded else ""
        raise UserError(f"unknown object class {name!r}; {hint}choose from: {', '.join(_REGISTRY)}") from None


def all_classes() -> list[ObjectClass]:
    _load_builtins()
    return list(_REGISTRY.values())


def check_table(obj_class: ObjectClass, table: SamplingTable) -> None:
    """UserError unless ``table`` fits ``obj_class``: one q range per joint, a revolute joint
    opening at most one turn."""
    if len(table.q) != obj_class.n_joints:
        raise UserError(f"sampling table: q needs {obj_class.n_joints} ranges (one per joint), got {len(table.q)}")
    for j, (joint, (_, hi)) in enumerate(zip(obj_class.joints, table.q)):
        if joint.type == REVOLUTE and hi > MAX_REVOLUTE_Q_RAD:
            raise UserError(f"sampling table: q[{j}] (revolute joint {joint.name}) must be at most one turn "
                            f"({MAX_REVOLUTE_Q_RAD:.4f} rad), got {hi}")
