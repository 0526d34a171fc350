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

from ..errors import UserError
from ..tables import SamplingTable

log = logging.getLogger(__name__)

#: Only files with this suffix (our own templates) go through xacro; any other URDF is read as is.
XACRO_SUFFIX = ".xacro"


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
    opening of each joint (``q_max_<j>``)."""
    m = {k: repr(float(v)) for k, v in sample.geometry.items()}
    m["chirality"] = str(int(sample.chirality))
    for j, (_, hi) in enumerate(table.q):
        m[f"q_max_{j}"] = repr(float(hi))
    return m


def object_urdf(obj_class, sample, table: SamplingTable) -> str:
    """Stage 2: the URDF text of a sampled object of ``obj_class`` (an
    :class:`~articulated_dataset.classes.ObjectClass`)."""
    return render_urdf(obj_class.template_path(), template_arguments(sample, table))
