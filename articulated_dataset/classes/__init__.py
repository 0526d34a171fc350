"""Object classes, one folder each.

A built-in class is the folder ``classes/<name>/``: its Xacro template(s)
(``<name>.urdf.xacro`` and ``<name>_varied.urdf.xacro``), its module (``__init__.py``: the
sampling tables and ``CLASS``, an :class:`~articulated_dataset.classes.base.ObjectClass`), a
``README.md`` with the source of every range, and a ``CHANGELOG.md``.  Adding a class means
adding its folder and its name to :data:`articulated_dataset.classes.registry.BUILTIN_GENERATORS`.

Shared by the folders: :mod:`.base` (``ObjectClass``, ``JointSpec``), :mod:`.tables` (the
sampling-table type), :mod:`.common` (values several tables share), :mod:`.realistic` (the joint
size distributions of ``--table realistic``), :mod:`.varied` (the structure variables of
``--table varied``), ``common.xacro`` and ``varied.xacro``; :mod:`.registry` finds classes by name.

Numbers are the paper's Appendix A (Tables 3 and 4) converted to SI: geometry in metres (the
paper lists cm), prismatic configuration in metres (the paper lists cm).
"""

from articulated_dataset.classes.base import JOINT_TYPES, PRISMATIC, REVOLUTE, JointSpec, ObjectClass

__all__ = ["JOINT_TYPES", "PRISMATIC", "REVOLUTE", "JointSpec", "ObjectClass"]
