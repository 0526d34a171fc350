"""Finding captures: a depth image or point cloud and, beside it, its optional mask, labels
(or part-pose) and camera-info files."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from articulated_dataset.core.errors import UserError
from articulated_dataset.ingest.readers import CLOUD_SUFFIXES, DEPTH_SUFFIXES

MASK_SUFFIX = ".mask.png"
LABELS_SUFFIX = ".labels.json"
PARTS_SUFFIX = ".parts.json"  # <stem>.parts.json: part poses and masks (ingest.part_annotations)
CAMERA_SUFFIX = ".camera"  # <stem>.camera.json / .yaml: per-capture intrinsics
CAMERA_FILES = ("camera.json", "camera.yaml", "camera.yml")


@dataclass
class CaptureFiles:
    """The files of one capture (paths; None where absent)."""

    name: str
    data: Path  # depth image or point cloud
    mask: Path | None = None
    labels: Path | None = None
    camera: Path | None = None  # camera-info file (if intrinsics are not given otherwise)
    parts: Path | None = None  # part-pose frame file (ground truth instead of ``labels``)

    @property
    def is_cloud(self) -> bool:
        """True when the capture's data file is a point cloud (by its suffix)."""
        return self.data.suffix.lower() in CLOUD_SUFFIXES


def find_captures(paths: list[str | Path]) -> list[CaptureFiles]:
    """Captures named by ``paths``: depth/cloud files, or folders of them.

    Next to ``NAME.<png|exr|npy|ply|pcd>`` the optional files are ``NAME.mask.png``,
    ``NAME.labels.json`` or ``NAME.parts.json`` and ``NAME.camera.json|yaml`` (else
    ``camera.json|yaml`` in the folder).
    """
    found: list[CaptureFiles] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.is_file() and _is_data_file(f))
            if not files:
                raise UserError(f"{p}: no captures found (expected depth images {', '.join(DEPTH_SUFFIXES)} "
                                f"or point clouds {', '.join(CLOUD_SUFFIXES)})")
            found.extend(capture_files(f) for f in files)
        elif p.is_file():
            if not _is_data_file(p):
                raise UserError(f"{p}: not a depth image or point cloud ({', '.join(DEPTH_SUFFIXES + CLOUD_SUFFIXES)})")
            found.append(capture_files(p))
        else:
            raise UserError(f"no such file or directory: {p}")
    names = [c.name for c in found]
    from articulated_dataset.format.manifest import is_utf8

    for c in found:
        if not is_utf8(c.name):
            raise UserError(f"{c.data}: capture names must be UTF-8 text (the name is stored and hashed); "
                            f"rename the file")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"capture names must be unique; repeated: {', '.join(dup[:5])}")
    return found


def _is_data_file(f: Path) -> bool:
    name = f.name.lower()
    if name.endswith(MASK_SUFFIX) or name.endswith(LABELS_SUFFIX) or name in CAMERA_FILES:
        return False
    return f.suffix.lower() in DEPTH_SUFFIXES + CLOUD_SUFFIXES


def capture_files(f: Path) -> CaptureFiles:
    """The files of the capture whose data file is ``f``: the mask, labels, part-pose and camera file beside it,
    None where absent."""
    stem = f.name[: -len(f.suffix)]
    folder = f.parent
    mask = folder / (stem + MASK_SUFFIX)
    labels = folder / (stem + LABELS_SUFFIX)
    camera = next((c for c in (_companion(folder / f"{stem}{CAMERA_SUFFIX}.json", "camera file"),
                               _companion(folder / f"{stem}{CAMERA_SUFFIX}.yaml", "camera file"),
                               *(_companion(folder / n, "camera file") for n in CAMERA_FILES)) if c is not None), None)
    parts = _companion(folder / (stem + PARTS_SUFFIX), "part-pose file")
    return CaptureFiles(stem, f, _companion(mask, "mask"), _companion(labels, "labels file"), camera, parts)


def _companion(path: Path, what: str) -> Path | None:
    """``path`` where it is a regular file, None where nothing is there; anything else by that name
    (a folder, a FIFO, a device, a dangling link) is a one-line :class:`UserError`: taking it for
    "no file" would ingest the capture without what the user put beside it."""
    if path.is_file():
        return path
    if not os.path.lexists(path):
        return None
    raise UserError(f"{path}: not a regular file; a capture's {what} must be one")
