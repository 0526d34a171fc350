"""Stage 6 of the pipeline: writing HDF5 shards and the per-split JSON manifest.

Layout::

    OUT/<class>/<split>/shard-00000.h5   objects [0, objects_per_shard) with all their images
    OUT/<class>/<split>/manifest.json    shards, counts, sha256 checksums, generation config

A shard becomes visible only when complete: it is written under a temporary name, flushed,
fsync'ed and atomically renamed.  The manifest is replaced atomically the same way.

Reading lives in :mod:`articulated_dataset.format` (re-exported here so that existing imports
keep working).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np

from .format.discovery import find_split_dirs  # noqa: F401
from .format.manifest import MANIFEST_NAME, check_manifest_names, read_manifest, shard_paths  # noqa: F401
from .format.schema import FIELDS, IMAGE_FIELDS, K_DATASET, OPTIONAL_FIELDS, R_DATASET, RGB_FIELDS, validate_arrays
from .format.shards import (  # noqa: F401
    _CLASS_NAME_RE,
    _SHARD_FILE_RE,
    MAX_CLASS_NAME_CHARS,
    MAX_H5_GROUP_DEPTH,
    MAX_READ_MEMORY_FRACTION,
    MIN_STORED_BYTES_PER_IMAGE,
    SHARD_PATTERN,
    TMP_SUFFIX,
    Shard,
    _short,
    attr_value,
    check_class_name,
    check_h5_layout,
    check_shard_file,
    is_class_name,
    open_h5,
    read_json_object,
    reading,
    resolve_inside,
    sha256_file,
    shard_name,
)
from .format.split import Split, open_split  # noqa: F401

log = logging.getLogger(__name__)

#: Deflate level of the per-image depth/mask chunks.  Compression is the costliest step after
#: rendering: level 1 takes ~40% of level 4's time for ~1.4x its size, still well under the
#: 4 KB/image budget (benchmarks/generation.py prints bytes per image).
IMAGE_GZIP_LEVEL = 1
#: Deflate level of the (small) label datasets.
LABEL_GZIP_LEVEL = 4


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never a mix
    (:func:`articulated_dataset.safeio.atomic_write_bytes`: a full disk is one line)."""
    from .safeio import atomic_write_bytes as write

    write(path, data)


def write_shard(path: str | Path, arrays: dict, attrs: dict, K: np.ndarray, R: np.ndarray) -> dict:
    """Validate ``arrays`` against the schema and write them atomically to ``path``.

    Returns the shard's manifest record (file name, images, bytes, sha256).
    """
    path = Path(path)
    N, H, W = arrays["depth"].shape
    J = arrays["q"].shape[1]
    validate_arrays(arrays, N=N, J=J, H=H, W=W, where=str(path))
    from .safeio import atomic_write_h5

    def build(f: h5py.File) -> None:
        for field in FIELDS + tuple(f for f in OPTIONAL_FIELDS + RGB_FIELDS if f.name in arrays):  # optional: 1.1, 1.2
            a = arrays[field.name]
            if field.name in IMAGE_FIELDS or field in RGB_FIELDS:  # one chunk per image
                f.create_dataset(field.name, data=a, chunks=(1,) + a.shape[1:], shuffle=a.dtype.itemsize > 1,
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

    # Built in memory, written in one piece (a full disk never breaks HDF5's state).  Fixed
    # file-format bounds and no timestamps make identical inputs give identical bytes.
    atomic_write_h5(path, build, libver=("v110", "v110"), track_order=False)
    return {"file": path.name, "n_images": int(N), "bytes": path.stat().st_size, "sha256": sha256_file(path)}


def write_manifest(split_dir: str | Path, manifest: dict) -> None:
    atomic_write_bytes(Path(split_dir) / MANIFEST_NAME, (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())
