"""Stage 6 of the pipeline: HDF5 shards and the per-split JSON manifest.

Layout::

    OUT/<class>/<split>/shard-00000.h5   objects [0, objects_per_shard) with all their images
    OUT/<class>/<split>/manifest.json    shards, counts, sha256 checksums, generation config

A shard becomes visible only when complete: it is written under a temporary name, flushed,
fsync'ed and atomically renamed.  The manifest is replaced atomically the same way.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import h5py
import numpy as np

from .errors import DataFormatError, UserError
from .schema import FIELDS, FIELDS_BY_NAME, IMAGE_FIELDS, K_DATASET, R_DATASET, check_version, validate_arrays

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
SHARD_PATTERN = "shard-{:05d}.h5"
TMP_SUFFIX = ".partial"
#: Deflate level of the per-image depth/mask chunks.  Compression is the costliest step after
#: rendering: level 1 takes ~40% of level 4's time for ~1.4x its size, still well under the
#: 4 KB/image budget (benchmarks/generation.py prints bytes per image).
IMAGE_GZIP_LEVEL = 1
#: Deflate level of the (small) label datasets.
LABEL_GZIP_LEVEL = 4


def shard_name(index: int) -> str:
    return SHARD_PATTERN.format(index)


def sha256_file(path: str | Path, chunk_bytes: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk_bytes), b""):
            h.update(block)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never a mix."""
    path = Path(path)
    tmp = path.with_name(path.name + TMP_SUFFIX)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def write_shard(path: str | Path, arrays: dict, attrs: dict, K: np.ndarray, R: np.ndarray) -> dict:
    """Validate ``arrays`` against the schema and write them atomically to ``path``.

    Returns the shard's manifest record (file name, images, bytes, sha256).
    """
    path = Path(path)
    N, H, W = arrays["depth"].shape
    J = arrays["q"].shape[1]
    validate_arrays(arrays, N=N, J=J, H=H, W=W, where=str(path))
    tmp = path.with_name(path.name + TMP_SUFFIX)
    # Fixed file-format bounds and no timestamps make identical inputs give identical bytes.
    with h5py.File(tmp, "w", libver=("v110", "v110"), track_order=False) as f:
        for field in FIELDS:
            a = arrays[field.name]
            if field.name in IMAGE_FIELDS:
                f.create_dataset(field.name, data=a, chunks=(1, H, W), shuffle=a.dtype.itemsize > 1,
                                 compression="gzip", compression_opts=IMAGE_GZIP_LEVEL, track_times=False)
            else:
                f.create_dataset(field.name, data=a, shuffle=a.dtype.itemsize > 1,
                                 compression="gzip", compression_opts=LABEL_GZIP_LEVEL, track_times=False)
            f[field.name].attrs["units"] = field.units
            f[field.name].attrs["frame"] = field.frame
        f.create_dataset(K_DATASET, data=np.asarray(K, np.float64), track_times=False)
        f.create_dataset(R_DATASET, data=np.asarray(R, np.float64), track_times=False)
        # Sorted: HDF5 bytes depend on attribute creation order, and every writer (generator,
        # EXR import, ingest) must give the same bytes for the same content.
        for k in sorted(attrs):
            f.attrs[k] = attrs[k]
        f.flush()
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return {"file": path.name, "n_images": int(N), "bytes": path.stat().st_size, "sha256": sha256_file(path)}


class Shard:
    """Read access to one shard; the file is opened lazily on first use (once per process)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._file: h5py.File | None = None
        self._pid: int | None = None

    @property
    def file(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():
            self._file = open_h5(self.path)
            self._pid = os.getpid()
            self._check()
        return self._file

    def _check(self) -> None:
        f = self._file
        where = str(self.path)
        if "format_version" not in f.attrs:
            raise DataFormatError(f"{where}: not an articulated_dataset shard (no format_version attribute)")
        check_version(str(f.attrs["format_version"]), where)
        N, H, W = f["depth"].shape if "depth" in f else (0, 0, 0)
        J = int(f.attrs.get("n_joints", 0))
        validate_arrays({k: f[k] for k in FIELDS_BY_NAME if k in f}, N=N, J=J, H=H, W=W, where=where)

    @property
    def attrs(self) -> dict:
        return {k: attr_value(v) for k, v in self.file.attrs.items()}

    def __len__(self) -> int:
        return int(self.file["depth"].shape[0])

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        return self.file[K_DATASET][()]

    def read(self, name: str, index=slice(None)) -> np.ndarray:
        return self.file[name][index]

    def sample(self, i: int) -> dict:
        """All fields of image ``i`` as numpy arrays."""
        return {f.name: self.file[f.name][i] for f in FIELDS}

    def labels(self) -> dict:
        """All label fields (everything but depth and mask) for every image."""
        return {f.name: self.file[f.name][()] for f in FIELDS if f.name not in IMAGE_FIELDS}

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __getstate__(self):  # picklable for spawn-based workers: reopen in the child
        return {"path": self.path}

    def __setstate__(self, state):
        self.__init__(state["path"])


def attr_value(v):
    """An HDF5 attribute as a plain Python value (str, list, int/float)."""
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def open_h5(path: str | Path) -> h5py.File:
    """Open an HDF5 file read-only; missing, truncated or non-HDF5 files are a DataFormatError."""
    path = Path(path)
    if not path.exists():
        raise DataFormatError(f"file not found: {path}")
    if path.is_dir():
        raise DataFormatError(f"expected an HDF5 file, got a directory: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise DataFormatError(f"{path}: not a readable HDF5 file ({_short(exc)})") from None


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:200]


def read_json_object(path: str | Path, what: str) -> dict:
    """A JSON object from ``path``; a missing, unparsable or non-object file is a DataFormatError
    naming ``what`` (e.g. "manifest")."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing {what}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"{path}: corrupt {what} ({exc})") from None
    if not isinstance(data, dict):
        raise DataFormatError(f"{path}: corrupt {what} (not a JSON object)")
    return data


def read_manifest(split_dir: str | Path) -> dict:
    split_dir = Path(split_dir)
    path = split_dir / MANIFEST_NAME
    if not path.is_file():
        raise DataFormatError(f"{split_dir}: no {MANIFEST_NAME} (not a generated split folder)")
    manifest = read_json_object(path, "manifest")
    check_version(manifest.get("format_version", "?"), str(path))
    return manifest


def write_manifest(split_dir: str | Path, manifest: dict) -> None:
    atomic_write_bytes(Path(split_dir) / MANIFEST_NAME, (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())


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


def open_split(split_dir: str | Path) -> tuple[dict, list[Shard]]:
    """The manifest of a split folder and its shards (complete ones, in order)."""
    split_dir = Path(split_dir)
    manifest = read_manifest(split_dir)
    return manifest, [Shard(split_dir / rec["file"]) for rec in manifest["shards"]]
