"""What an object class is, as data: its joints (:class:`JointSpec`) and its record
(:class:`ObjectClass`: template name, sampling table, joints).

The built-in classes are modules of :mod:`articulated_dataset.classes` that define one
``CLASS`` each from these types; :mod:`articulated_dataset.classes.registry` lists and loads them,
and registers third-party URDF classes the same way.  This module imports no registry, so
neither do the generators.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.tables import TABLE_NAMES, SamplingTable
from articulated_dataset.format.schema import JOINT_TYPES, PRISMATIC, REVOLUTE  # noqa: F401  (declared with the format)

#: Where an object of a class stands in a scene (:attr:`ObjectClass.placement`).
PLACEMENTS = ("floor", "under_counter", "under_counter_drawer", "on_counter")


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
    template: file name of the Xacro template in ``classes/`` (or an absolute path to
        a URDF/Xacro file elsewhere, e.g. a third-party object).
    table: default sampling table (the paper's Appendix A for the built-in classes).
    joints: articulated joints in label order (J = len(joints)).
    base_link: the URDF root link (its frame is the centre of the object's base).
    sided: True if the class has a chirality (hinge side) that the labeller reads from the
        model; False for classes whose chirality label is always 0.
    description: one line for docs and ``artdata classes``.
    order: listing order (the paper's order for the built-ins); ties broken by name.
    realistic_table: the joint size distribution of ``--table realistic`` (same pose, q
        and chirality as ``table``), or None where the class has none (third-party classes).
    varied_table: the table of ``--table varied`` (sizes, wider openings and the structure
        variables of :mod:`articulated_dataset.classes.varied`), or None where the class
        has none.
    varied_template: the Xacro template a sample with structure variables is built from
        (its arguments' defaults build the paper's structure); None without a varied table.
    placement: where an object of the class stands in ``artdata generate --scene``
        (:data:`PLACEMENTS`, :mod:`articulated_dataset.generation.scenes`): on the ``floor``,
        ``under_counter`` (a counter top rests on it), ``under_counter_drawer`` (the top drawer
        of a base unit under a counter) or ``on_counter`` (on a counter top or sideboard).
    mirror_joints: where the class's mirror image (the scene reflected left-right) is again an
        object of the class, the joint order of that image: its joint ``k`` is this object's
        joint ``mirror_joints[k]`` (the cabinet hinged on either side: ``(0,)``; the two-door
        cabinet, whose left door becomes the right one: ``(1, 0)``).  None where mirror images are
        not objects of the class (the microwave is always hinged on its left).  The dense
        estimator may average an image's estimate with its mirror image's
        (:mod:`articulated_dataset.methods.dense.mirror`).
    """

    name: str
    template: str
    table: SamplingTable
    joints: tuple[JointSpec, ...]
    base_link: str = "base"
    sided: bool = False
    description: str = ""
    order: int = 100
    realistic_table: SamplingTable | None = None
    varied_table: SamplingTable | None = None
    varied_template: str | None = None
    mirror_joints: tuple[int, ...] | None = None
    placement: str = "floor"

    def __post_init__(self) -> None:
        if self.placement not in PLACEMENTS:
            raise ValueError(f"placement must be one of {PLACEMENTS}, got {self.placement!r}")
        if self.mirror_joints is not None:
            perm = tuple(self.mirror_joints)
            if sorted(perm) != list(range(len(self.joints))) or any(perm[perm[k]] != k for k in range(len(perm))):
                raise ValueError(f"mirror_joints must pair the joints up (a permutation of 0..{len(self.joints) - 1} that "
                                 f"is its own inverse), got {self.mirror_joints!r}")
            object.__setattr__(self, "mirror_joints", perm)
        if (self.varied_table is None) != (self.varied_template is None):
            raise ValueError("a varied table and a varied template go together")
        if self.varied_table is not None and not self.varied_table.structure:
            raise ValueError("a varied table holds structure variables")
        if self.table.structure or (self.realistic_table is not None and self.realistic_table.structure):
            raise ValueError("structure variables belong to the varied table only")

    def named_table(self, name: str) -> SamplingTable:
        """The table ``artdata generate --table NAME`` picks: ``paper`` (the class's default
        table), ``realistic`` or ``varied``; anything else is a one-line :class:`UserError`."""
        if name == "paper":
            return self.table
        if name == "varied":
            if self.varied_table is None:
                having = ", ".join(builtin_classes_with_varied_template())
                raise UserError(f"class {self.name!r} has no varied table (classes with one: {having or 'none'}); "
                                f"give {option('table')} paper, realistic or a table file")
            return self.varied_table
        if name == "realistic":
            if self.realistic_table is None:
                raise UserError(f"class {self.name!r} has no realistic table (the built-in classes have one); "
                                f"give {option('table')} paper or a table file")
            return self.realistic_table
        raise UserError(f"unknown sampling table {name!r}; choose from: {', '.join(TABLE_NAMES)} "
                        f"(or a .json/.toml table file)")

    @property
    def n_joints(self) -> int:
        """Number of joints of the class."""
        return len(self.joints)

    @property
    def joint_types(self) -> tuple[str, ...]:
        """Type of each joint (``revolute`` or ``prismatic``), in joint order."""
        return tuple(j.type for j in self.joints)

    def check_structure(self, table: SamplingTable) -> None:
        """UserError unless ``table``'s structure variables are the varied table's (same
        names, same options): the varied template reads exactly those."""
        if not table.structure:
            return
        if self.varied_table is None:
            raise UserError(f"sampling table: class {self.name!r} has no structure variables "
                            f"(structure.{next(iter(table.structure))}); only a varied table holds them")
        known = self.varied_table.structure
        for name, value in table.structure.items():
            if name not in known:
                raise UserError(f"sampling table: unknown structure variable structure.{name} (known: {', '.join(known)})")
            if isinstance(value, dict) and set(value) != set(known[name]):
                raise UserError(f"sampling table: structure.{name} must weigh the options {', '.join(known[name])}")
        missing = [name for name in known if name not in table.structure]
        if missing:
            raise UserError(f"sampling table: structure.{missing[0]} is missing")

    def template_path(self, *, varied: bool = False) -> Path:
        """The template file (with ``varied``, the varied template): itself if absolute, else
        the built-in template of that name (:func:`builtin_template`)."""
        name = self.template
        if varied:
            if self.varied_template is None:
                raise UserError(f"class {self.name!r} has no varied template; its tables hold no structure variables")
            name = self.varied_template
        if Path(name).is_absolute():
            return Path(name)
        return builtin_template(name)


#: Suffix of a class's varied template beside its paper template (``cabinet_varied.urdf.xacro``).
VARIED_TEMPLATE_SUFFIX = "_varied"


def builtin_template(name: str) -> Path:
    """A built-in Xacro template by file name: ``<class>.urdf.xacro`` and
    ``<class>_varied.urdf.xacro`` live in the class's folder ``classes/<class>/``."""
    folder = name.split(".", 1)[0].removesuffix(VARIED_TEMPLATE_SUFFIX)
    return Path(str(resources.files("articulated_dataset.classes").joinpath(folder).joinpath(name)))


def builtin_classes_with_varied_template() -> list[str]:
    """The built-in class folders holding a varied template, by name (read from the folders:
    this module imports no registry)."""
    root = resources.files("articulated_dataset.classes")
    return sorted(folder.name for folder in root.iterdir()
                  if folder.is_dir() and folder.joinpath(f"{folder.name}{VARIED_TEMPLATE_SUFFIX}.urdf.xacro").is_file())


__all__ = ["JOINT_TYPES", "PRISMATIC", "REVOLUTE", "JointSpec", "ObjectClass"]
