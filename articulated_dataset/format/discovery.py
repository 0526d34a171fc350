"""Finding split folders: ``<class>/<split>/`` below a dataset root, a class folder, or the
split folder itself.  One definition for every command and reader."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import UserError
from .manifest import MANIFEST_NAME, read_manifest


def find_split_dirs(path: str | Path, *, marker: str = MANIFEST_NAME, what: str = "generated split") -> list[Path]:
    """Split folders (holding ``marker``) at ``path`` or one/two levels below (class/split layout)."""
    path = Path(path)
    if not path.is_dir():
        raise UserError(f"no such directory: {path}")
    if (path / marker).is_file():
        return [path]
    found = sorted(p.parent for p in path.glob(f"*/{marker}")) + sorted(p.parent for p in path.glob(f"*/*/{marker}"))
    if not found:
        raise UserError(f"{path}: no {what} found (expected {marker} in it or in <class>/<split>/ below it)")
    return found


def find_splits(paths) -> list[Path]:
    """Split folders at or below each of ``paths`` (one path or a non-empty list), in the order
    given, each once (folders reached twice, also through links, are listed once)."""
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not items:
        raise UserError("no split folders given")
    out: list[Path] = []
    seen: set = set()
    for p in items:
        for d in find_split_dirs(p):
            key = d.resolve()
            if key not in seen:
                seen.add(key)
                out.append(d)
    return out


def one_split_dir(path: str | Path) -> Path:
    """The one split folder at or below ``path``; none or several is a UserError."""
    dirs = find_split_dirs(path)
    if len(dirs) != 1:
        raise UserError(f"{path}: holds {len(dirs)} splits; pass one split folder (<root>/<class>/<split>): "
                        + ", ".join(str(d) for d in dirs[:4]))
    return dirs[0]


def splits_by_class(path: str | Path) -> dict[str, dict[str, Path]]:
    """``{class: {split name: split folder}}`` of the splits under ``path``.

    The class is the manifest's ``class_name``; the split name is the folder's name
    (``OUT/<class>/<split>``; ``mean`` for a mean object)."""
    found: dict[str, dict[str, Path]] = {}
    for d in find_split_dirs(path):
        found.setdefault(str(read_manifest(d)["class_name"]), {})[d.name] = d
    return found
