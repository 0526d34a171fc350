"""One reader of a split folder: :class:`Split`.

Every consumer (scoring, baselines, ``artdata info``, manipulation, the loaders, the MDN)
opens a split through it, so the checks that refuse crafted data live in one place: the
manifest's version and names (:func:`~articulated_dataset.format.manifest.read_manifest`),
every shard path resolved inside the folder, and each shard's own checks
(:class:`~articulated_dataset.format.shards.Shard`: layout, version, sizes, schema).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.format.manifest import SplitConfig, read_manifest, shard_paths, split_config
from articulated_dataset.format.schema import IMAGE_FIELDS, JOINT_TYPES, LABEL_FIELDS
from articulated_dataset.format.shards import Shard, json_list


def check_inside(split_dir: Path, path: Path) -> None:
    """Refuse a shard path that leads outside ``split_dir`` once symbolic links are followed.

    :func:`~articulated_dataset.format.manifest.shard_paths` checks the manifest's names; this
    is a second check on the resolved paths, done before any shard is opened."""
    try:
        base, real = Path(split_dir).resolve(), Path(path).resolve()
    except (OSError, RuntimeError):  # a symbolic-link loop
        raise DataFormatError(f"{split_dir}: cannot resolve shard path {str(path)[:200]!r} (refused)") from None
    if real == base or not real.is_relative_to(base):
        raise DataFormatError(f"{split_dir}: the manifest names a shard outside the split folder "
                              f"({str(path)[:200]!r}; refused)")


class Split:
    """A split folder (``OUT/<class>/<split>``): its manifest, its shards and their labels.

    Opening reads and checks the manifest only; shards are opened on first use (once per
    process) and closed by :meth:`close` (or ``with Split(path) as split:``).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.manifest: dict = read_manifest(self.path)
        self.shard_paths: list[Path] = shard_paths(self.path, self.manifest)
        for p in self.shard_paths:
            check_inside(self.path, p)
        self.shards: list[Shard] = [Shard(p) for p in self.shard_paths]
        self._config: SplitConfig | None = None

    def __repr__(self) -> str:
        return f"Split({str(self.path)!r})"

    def __enter__(self) -> "Split":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close every shard's file."""
        for sh in self.shards:
            sh.close()

    # ----------------------------------------------------------------------------------
    # the manifest
    @property
    def name(self) -> str:
        """The split's name: its folder's name (``mean`` for a mean object)."""
        return self.path.name

    @property
    def class_name(self) -> str:
        """The object class of the split (from its manifest)."""
        return str(self.manifest["class_name"])

    @property
    def n_images(self) -> int:
        """Images the manifest lists (0 if it says nothing)."""
        return int(self.manifest.get("n_images", 0))

    @property
    def complete(self) -> bool:
        """False when the manifest marks the split incomplete (a manifest without the key is complete)."""
        return bool(self.manifest.get("complete", True))

    @property
    def shard_sizes(self) -> list[int]:
        """Images of each shard, from the manifest (checked counts)."""
        return [int(r.get("n_images", 0)) for r in self.manifest["shards"]]

    @property
    def config_dict(self) -> dict:
        """The manifest's ``config`` as stored (a dict; empty if absent)."""
        return self.manifest.get("config", {})

    @property
    def config(self):
        """The manifest's ``config`` as a :class:`~articulated_dataset.format.manifest.SplitConfig`
        (a corrupt one is a one-line DataFormatError)."""
        if self._config is None:
            self._config = split_config(self.manifest, str(self.path / "manifest.json"))
        return self._config

    @property
    def is_real(self) -> bool:
        """Ingested real captures (labels NaN where a capture does not give them)."""
        return "real" in self.manifest

    @property
    def is_mean_object(self) -> bool:
        """The class's mean object (``artdata generate --mean``)."""
        return self.config_dict.get("mean") is True

    # ----------------------------------------------------------------------------------
    # the shards' attributes
    @property
    def attrs(self) -> dict:
        """Root attributes of the first shard (empty if the split has none)."""
        return self.shards[0].attrs if self.shards else {}

    @property
    def n_joints(self) -> int:
        """Number of joints of the split's objects (from the first shard)."""
        return int(self.shards[0].attrs["n_joints"])

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        a = self.shards[0].attrs
        return int(a["image_height"]), int(a["image_width"])

    def joint_names(self) -> list[str]:
        """Joint names from the first shard's attributes (empty if unreadable)."""
        return json_list(self.attrs.get("joint_names", "[]")) or []

    def joint_types(self) -> tuple[str, ...]:
        """The joint types every shard declares; missing, unknown or differing types are a
        DataFormatError naming the shard."""
        joint_types: tuple[str, ...] | None = None
        for sh in self.shards:
            listed = json_list(sh.attrs.get("joint_types"))
            if listed is None:
                raise DataFormatError(f"{sh.path}: missing or invalid 'joint_types' attribute")
            types = tuple(listed)
            if any(t not in JOINT_TYPES for t in types):
                raise DataFormatError(f"{sh.path}: unknown joint type in {list(types)}")
            if joint_types is None:
                joint_types = types
            elif types != joint_types:
                raise DataFormatError(f"{sh.path}: joint types {list(types)} differ from the split's {list(joint_types)}")
        return joint_types if joint_types is not None else ()

    # ----------------------------------------------------------------------------------
    # data
    def read(self, name: str) -> np.ndarray:
        """One dataset concatenated over all shards, in storage order."""
        return np.concatenate([sh.read(name) for sh in self.shards], axis=0)

    def read_fields(self, names: Iterable[str], *, close: bool = True) -> dict[str, np.ndarray]:
        """``{name: array}`` of several datasets concatenated over all shards (storage order),
        read shard by shard; each shard is closed after it is read unless ``close`` is false.
        Fields of a split with no shards are absent."""
        names = tuple(names)
        parts: dict[str, list] = {k: [] for k in names}
        try:
            for sh in self.shards:
                for k in names:
                    parts[k].append(sh.read(k))
                if close:
                    sh.close()
        finally:
            if close:
                self.close()
        return {k: np.concatenate(v) for k, v in parts.items() if v}

    def labels(self) -> dict[str, np.ndarray]:
        """Every label field (everything but depth and mask), storage order."""
        return self.read_fields(k for k in LABEL_FIELDS if k not in IMAGE_FIELDS)


def open_split(split_dir: str | Path) -> tuple[dict, list[Shard]]:
    """The manifest of a split folder and its shards (complete ones, in order): the
    :class:`Split`'s ``manifest`` and ``shards``."""
    split = Split(split_dir)
    return split.manifest, split.shards
