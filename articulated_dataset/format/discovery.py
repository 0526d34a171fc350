"""Finding split folders: ``<class>/<split>/`` below a dataset root, a class folder, or the
split folder itself.  One definition for every command and reader."""

from __future__ import annotations

import os
from pathlib import Path

from articulated_dataset.core.errors import UserError
from articulated_dataset.format.manifest import MANIFEST_NAME, read_manifest

#: Shard files of a split folder (names as :data:`~articulated_dataset.format.shards.SHARD_PATTERN` writes them).
SHARD_GLOB = "shard-*.h5"


def find_split_dirs(path: str | os.PathLike, *, marker: str = MANIFEST_NAME, what: str = "generated split",
                    unlisted_shards: bool = False) -> list[Path]:
    """Split folders (holding ``marker``) at ``path`` or one/two levels below (class/split layout).

    With ``unlisted_shards``, a folder holding shard files but no ``marker`` counts too (a split
    whose manifest was lost, which ``artdata verify`` reports), and a file is refused as such.
    Nothing found is a :class:`UserError`.
    """
    path = Path(path)
    if not path.is_dir():
        if path.exists():  # (a predictions file or a shard given where a split folder is expected)
            raise UserError(f"expected a directory (split, class or output root), got a file: {path}")
        raise UserError(f"no such directory: {path}")

    def is_split(p: Path) -> bool:
        return (p / marker).is_file() or (unlisted_shards and any(p.glob(SHARD_GLOB)))

    if is_split(path):
        return [path]
    found = [p for level in ("*/", "*/*/") for p in sorted(p for p in path.glob(level) if is_split(p))]
    if not found:
        raise UserError(f"{path}: no {what} found (expected {marker}{' or shard files' if unlisted_shards else ''} "
                        f"in it or in <class>/<split>/ below it)")
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
