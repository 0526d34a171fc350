"""Stage 2 of the pipeline: turn a class's Xacro template and sampled arguments into URDF.

Templates are parsed once per process and cached; each object re-runs only xacro's macro
expansion on a copy of the parsed document.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import xacro

from .errors import UserError

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
