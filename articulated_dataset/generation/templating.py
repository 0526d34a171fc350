"""Stage 2 of the pipeline (template): a sampled object -> its class's Xacro arguments -> URDF.

The arguments are formatted here, from the sample and the table (:func:`template_arguments`);
stage 1 knows nothing of Xacro.  Templates are parsed once per process and cached; each
object re-runs only xacro's macro expansion on a copy of the parsed document.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import xacro

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.tables import SamplingTable

log = logging.getLogger(__name__)

#: Only files with this suffix (our own templates) go through xacro; any other URDF is read as is.
XACRO_SUFFIX = ".xacro"
#: Suffixes of structure variables that their Xacro argument drops (a flag, an option name).
STRUCTURE_ARGUMENT_SUFFIXES = ("_p", "_weights")


@functools.lru_cache(maxsize=64)
def _parsed(path: str):
    xacro.init_stacks(path)
    return xacro.parse(None, path)


def render_urdf(template_path: str | Path, mappings: dict[str, str]) -> str:
    """Expand ``template_path`` with xacro arguments ``mappings`` and return the URDF text.

    Only ``*.xacro`` templates are expanded; a plain ``.urdf`` file is returned unchanged."""
    path = str(template_path)
    if not Path(path).is_file():
        raise UserError(f"URDF template not found: {path}")
    if not path.endswith(XACRO_SUFFIX):
        # A plain URDF (a third-party object processed by urdf_import) is data: never expanded.
        return Path(path).read_text(encoding="utf-8")
    doc = _parsed(path).cloneNode(True)
    xacro.init_stacks(path)  # includes resolve relative to the template's folder
    try:
        xacro.process_doc(doc, mappings=dict(mappings))
    except xacro.XacroException as exc:
        raise UserError(f"xacro failed on {path}: {exc}") from None
    return doc.toxml()


def template_arguments(sample, table: SamplingTable) -> dict[str, str]:
    """Xacro arguments of an :class:`~articulated_dataset.generation.sampling.ObjectSample`'s
    class template (all strings, SI units): its geometry, chirality and the table's largest
    opening of each joint (``q_max_<j>``); with structure variables (``--table varied``), one
    argument each, named as the variable without a ``_p`` or ``_weights`` suffix (a flag
    ``0``/``1``, an option name; lengths and fractions keep their names)."""
    m = {k: repr(float(v)) for k, v in sample.geometry.items()}
    m["chirality"] = str(int(sample.chirality))
    for j, (_, hi) in enumerate(table.q):
        m[f"q_max_{j}"] = repr(float(hi))
    for name, value in (sample.structure or {}).items():
        m[structure_argument(name)] = value if isinstance(value, str) else repr(value)
    return m


def structure_argument(name: str) -> str:
    """The Xacro argument of structure variable ``name``: ``door_inset_p`` -> ``door_inset``,
    ``handle_weights`` -> ``handle``, ``plinth_height_m`` unchanged."""
    for suffix in STRUCTURE_ARGUMENT_SUFFIXES:
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def object_urdf(obj_class, sample, table: SamplingTable) -> str:
    """Stage 2: the URDF text of a sampled object of ``obj_class`` (an
    :class:`~articulated_dataset.classes.base.ObjectClass`): a sample with structure variables is
    built from the class's varied template."""
    path = obj_class.template_path(varied=sample.structure is not None)
    return render_urdf(path, template_arguments(sample, table))
