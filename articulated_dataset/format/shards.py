"""The shard file: names checked before they become paths, HDF5 files opened safely, one
:class:`Shard` per file, and :func:`write_shard` (the one writer every split writer uses:
generation, EXR import, real ingestion).

Layout of a generated split::

    OUT/<class>/<split>/shard-00000.h5   objects [0, objects_per_shard) with all their images
    OUT/<class>/<split>/manifest.json    shards, counts, sha256 checksums, generation config

Every check that refuses a crafted file (names leading out of the folder, links and external
storage inside HDF5, sizes that do not fit, damaged chunks) lives here, with a one-line
:class:`~articulated_dataset.core.errors.DataFormatError`.

A shard becomes visible only when complete: :func:`write_shard` builds it in memory and
writes it under a temporary name, fsync'ed and atomically renamed
(:func:`articulated_dataset.core.safeio.atomic_write_h5`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.core.safeio import TMP_SUFFIX  # noqa: F401  (re-exported: one definition)
from articulated_dataset.format.schema import (
    FIELDS,
    FIELDS_BY_NAME,
    IMAGE_FIELDS,
    K_DATASET,
    OPTIONAL_FIELDS,
    OPTIONAL_FIELDS_BY_NAME,
    R_DATASET,
    RGB_FIELDS,
    RGB_FIELDS_BY_NAME,
    check_version,
    validate_arrays,
)

SHARD_PATTERN = "shard-{:05d}.h5"
#: Longest class name: the shards' ``class`` field is S32 (32 ASCII bytes).
MAX_CLASS_NAME_CHARS = 32
#: A class name (registry names, third-party ``--class-name``): it becomes a folder name, so
#: letters, digits, ``_ . -``, not starting with ``.`` or ``-``.
_CLASS_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
#: A shard file name as :data:`SHARD_PATTERN` writes it (5 or more digits).
_SHARD_FILE_RE = re.compile(r"shard-[0-9]{5,}\.h5")
#: Deepest group nesting accepted in an HDF5 file we read (shards are flat, predictions
#: have one level of class groups); also ends hard-link cycles between groups.
MAX_H5_GROUP_DEPTH = 4
#: Largest share of the available memory one read may take.
MAX_READ_MEMORY_FRACTION = 0.5
#: Fewest bytes one image takes in a shard: its depth and mask are separate chunks, each with
#: a chunk-index entry (>= 8 bytes) and deflate data (>= ~10 bytes).  A file declaring more
#: images than its size allows (unwritten chunks read as zeros) is refused before reading.
MIN_STORED_BYTES_PER_IMAGE = 16


def shard_name(index: int) -> str:
    """File name of shard ``index`` (:data:`SHARD_PATTERN`)."""
    return SHARD_PATTERN.format(index)


# --------------------------------------------------------------------------------------
# Names read from data files are names, not paths
# --------------------------------------------------------------------------------------

def is_class_name(name) -> bool:
    """True if ``name`` is a valid class name: 1-32 characters from ``A-Z a-z 0-9 _ . -``,
    not starting with ``.`` or ``-`` (so never ``..``, a path or an option)."""
    return isinstance(name, str) and len(name) <= MAX_CLASS_NAME_CHARS and _CLASS_NAME_RE.fullmatch(name) is not None


def check_class_name(name, where: str) -> str:
    """``name`` if :func:`is_class_name`, else a :class:`DataFormatError` naming ``where``
    (the file the name was read from)."""
    if not is_class_name(name):
        raise DataFormatError(f"{where}: invalid class name {str(name)[:80]!r} (expected 1-{MAX_CLASS_NAME_CHARS} "
                              "characters from A-Z a-z 0-9 _ . -, not starting with . or -)")
    return name


def check_shard_file(name, where: str) -> str:
    """``name`` if it is a shard file name (``shard-NNNNN.h5``), else a :class:`DataFormatError`."""
    if not isinstance(name, str) or _SHARD_FILE_RE.fullmatch(name) is None:
        raise DataFormatError(f"{where}: invalid shard file name {str(name)[:80]!r} (expected shard-NNNNN.h5)")
    return name


def resolve_inside(root: str | Path, name: str | Path, *, where: str | None = None) -> Path:
    """``root / name`` after checking that it stays inside ``root``.

    Use it for every path built from a name read from a data file (manifest, export index,
    label file): ``name`` must be a relative path (one or more components, none of them
    empty, ``.`` or ``..``, no NUL byte), and ``root / name`` with every symbolic link
    resolved must lie strictly below ``root`` with its links resolved (so a link inside the
    data folder pointing elsewhere is refused too).  ``root`` itself is the folder the
    user named and is trusted; it need not exist yet.

    Returns ``Path(root) / name`` (as the user spelled ``root``, not resolved).  Raises
    :class:`DataFormatError` naming ``where`` (default: ``root``) otherwise.
    """
    where = str(root) if where is None else where
    text = os.fspath(name) if isinstance(name, (str, os.PathLike)) else None
    parts = Path(text).parts if text else ()
    if (not text or "\0" in text or Path(text).is_absolute() or not parts
            or any(p in ("", ".", "..") for p in parts) or any(p in ("", ".", "..") for p in text.split("/"))):
        raise DataFormatError(f"{where}: {str(name)[:80]!r} is not a plain relative name inside {root} (refused)")
    path = Path(root) / text
    try:
        base, real = Path(root).resolve(), path.resolve()
    except (OSError, RuntimeError) as exc:  # a symbolic-link loop
        raise DataFormatError(f"{where}: cannot resolve {text[:80]!r} ({_short(exc)}; refused)") from None
    if real == base or not real.is_relative_to(base):
        raise DataFormatError(f"{where}: {text[:80]!r} leads outside {root} (to {real}; refused)")
    return path


def sha256_file(path: str | Path, chunk_bytes: int = 1 << 20) -> str:
    """Hex SHA-256 digest of the file at ``path``, read in blocks of ``chunk_bytes``."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk_bytes), b""):
            h.update(block)
    return h.hexdigest()


class Shard:
    """Read access to one shard; the file is opened lazily on first use (once per process)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._file: h5py.File | None = None
        self._pid: int | None = None

    @property
    def file(self) -> h5py.File:
        """The open, checked HDF5 file (opened on first use, and again in a process other than the one that opened
        it)."""
        if self._file is None or self._pid != os.getpid():
            f = open_h5(self.path)
            try:
                with reading(self.path):
                    self._check(f)
            except BaseException:
                f.close()
                raise
            self._file, self._pid = f, os.getpid()
        return self._file

    def _check(self, f: h5py.File) -> None:
        where = str(self.path)
        if "format_version" not in f.attrs:
            raise DataFormatError(f"{where}: not an articulated_dataset shard (no format_version attribute)")
        check_version(str(f.attrs["format_version"]), where)
        shape = f["depth"].shape if isinstance(f.get("depth"), h5py.Dataset) else (0, 0, 0)
        if len(shape) != 3:
            raise DataFormatError(f"{where}: dataset 'depth' has shape {shape}, expected (images, height, width)")
        N, H, W = shape
        size = self.path.stat().st_size
        if N * MIN_STORED_BYTES_PER_IMAGE > size:
            raise DataFormatError(f"{where}: declares {N} images but holds only {size} bytes (every stored image "
                                  f"takes at least {MIN_STORED_BYTES_PER_IMAGE}); damaged or not written by artdata")
        J = attr_value(f.attrs.get("n_joints", 0))
        if not (isinstance(J, int) and not isinstance(J, bool) and J >= 0):
            raise DataFormatError(f"{where}: attribute 'n_joints' is {str(J)[:40]!r}, not a whole number >= 0")
        stored = {k: f[k] for k in (*FIELDS_BY_NAME, *OPTIONAL_FIELDS_BY_NAME, *RGB_FIELDS_BY_NAME) if k in f}
        for k, obj in stored.items():
            if not isinstance(obj, h5py.Dataset):
                raise DataFormatError(f"{where}: {k!r} is not a dataset (a group or a named type)")
        # Optional fields too: a 4-channel or float ``rgb`` would be read as uint8 (H, W, 3).
        validate_arrays(stored, N=N, J=J, H=H, W=W, where=where)
        for name in (K_DATASET, R_DATASET):  # the camera's 3x3 matrices, read by every reader of the images
            ds = f.get(name)
            if not isinstance(ds, h5py.Dataset):
                raise DataFormatError(f"{where}: missing dataset {name!r}")
            if ds.shape != (3, 3) or ds.dtype.kind != "f" or not np.isfinite(ds[()]).all():
                raise DataFormatError(f"{where}: dataset {name!r} is {ds.dtype} {ds.shape}, expected a finite "
                                      f"3x3 float matrix")

    @property
    def attrs(self) -> dict:
        """The shard file's attributes as plain Python values."""
        f = self.file
        with reading(self.path):
            return {k: attr_value(v) for k, v in f.attrs.items()}

    def __len__(self) -> int:
        return int(self.file["depth"].shape[0])

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        """Camera intrinsics (3, 3) of every image of the shard (OpenCV convention, pixel centres at integer
        coordinates)."""
        return self.read(K_DATASET, ())

    @property
    def R(self) -> np.ndarray:  # noqa: N802
        """Rotation (3, 3) from the camera frame to the optical frame (``p_optical = R p_camera``)."""
        return self.read(R_DATASET, ())

    def read(self, name: str, index=slice(None)) -> np.ndarray:
        """``dataset[index]``; a damaged file is a :class:`DataFormatError` (see :func:`reading`).

        A whole dataset larger than :data:`MAX_READ_MEMORY_FRACTION` of the available memory
        is refused before reading (a hostile shard can declare any size: unwritten chunks
        read as zeros)."""
        f = self.file
        if not isinstance(f.get(name), h5py.Dataset):  # an optional field (rgb) its manifest promises
            raise DataFormatError(f"{self.path}: missing dataset {name!r}")
        with reading(self.path, name):
            ds = f[name]
            _check_fits_memory(self.path, name, _selection_rows(index, ds.shape) * _row_bytes(ds))
            return ds[index]

    def sample(self, i: int) -> dict:
        """All fields of image ``i`` as numpy arrays."""
        return {f.name: self.read(f.name, i) for f in FIELDS}

    def labels(self) -> dict:
        """All label fields (everything but depth and mask) for every image."""
        return {f.name: self.read(f.name, ()) for f in FIELDS if f.name not in IMAGE_FIELDS}

    def close(self) -> None:
        """Close the shard's file if open (it reopens on next use)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __getstate__(self):  # picklable for spawn-based workers: reopen in the child
        return {"path": self.path}

    def __setstate__(self, state):
        self.__init__(state["path"])  # type: ignore[misc]  # this class's own: reopened lazily


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
    """Open an HDF5 file read-only; missing, truncated or non-HDF5 files are a DataFormatError,
    and so is a file whose layout reads data from elsewhere (see :func:`check_h5_layout`)."""
    path = Path(path)
    if not path.exists():
        raise DataFormatError(f"file not found: {path}")
    if path.is_dir():
        raise DataFormatError(f"expected an HDF5 file, got a directory: {path}")
    try:
        mode = path.stat().st_mode
    except OSError:
        mode = None  # unreadable: h5py names the problem below
    if mode is not None and not stat.S_ISREG(mode):  # opening a FIFO waits for a writer: a hang
        raise DataFormatError(f"{path}: not a regular file (a device, pipe or socket; refused)")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise DataFormatError(f"{path}: not a readable HDF5 file ({_short(exc)})") from None
    try:
        with reading(path):
            check_h5_layout(f, path)
    except BaseException:
        f.close()
        raise
    return f


def check_h5_layout(f: h5py.Group, path: str | Path, _depth: int = 0, _seen: dict | None = None) -> None:
    """Refuse an HDF5 file whose content lives outside it or loops.

    Every link must be a hard link (no soft, external or user-defined links: an external
    link reads another file, a soft link can loop), no dataset may use external raw storage
    (``dset.external``: bytes read from another file) or be virtual (``dset.is_virtual``:
    mapped from other files), groups nest at most :data:`MAX_H5_GROUP_DEPTH` deep, and no
    object is reached by two links (files written by artdata link every object once; a few
    hundred hard links to one group at each level make a 100 KB file whose walk visits 10^9
    paths: a hang).  Raises :class:`DataFormatError` naming the object; reads no data.
    """
    seen: dict = {} if _seen is None else _seen  # object address -> the first path that reached it
    if _seen is None:
        seen[h5py.h5o.get_info(f.id).addr] = f.name
    for name in f:  # link names: iterating does not follow the links
        link = f.get(name, getlink=True)
        where = f"{path}: {f.name.rstrip('/')}/{name}"
        if not isinstance(link, h5py.HardLink):
            kind = {h5py.SoftLink: "a soft link", h5py.ExternalLink: "an external link"}.get(type(link), "a user-defined link")
            raise DataFormatError(f"{where} is {kind}; only datasets stored in the file itself are read (refused)")
        obj = f[name]
        addr = h5py.h5o.get_info(obj.id).addr
        if addr in seen:
            raise DataFormatError(f"{where} is a second link to {seen[addr]} (hard-link aliases are refused)")
        seen[addr] = f"{f.name.rstrip('/')}/{name}"
        if isinstance(obj, h5py.Dataset):
            if obj.is_virtual:
                raise DataFormatError(f"{where} is a virtual dataset (data mapped from other files; refused)")
            if obj.external:
                raise DataFormatError(f"{where} uses external storage (data read from other files; refused)")
        elif isinstance(obj, h5py.Group):
            if _depth + 1 >= MAX_H5_GROUP_DEPTH:
                raise DataFormatError(f"{where}: groups nested deeper than {MAX_H5_GROUP_DEPTH} levels (refused)")
            check_h5_layout(obj, path, _depth + 1, seen)


def _row_bytes(ds) -> int:
    """Bytes of one row (first-axis entry) of dataset ``ds``."""
    return int(np.prod(ds.shape[1:], dtype=np.float64)) * ds.dtype.itemsize if ds.shape else ds.dtype.itemsize


def _selection_rows(index, shape) -> int:
    """How many first-axis rows ``dataset[index]`` reads (an upper bound)."""
    n = shape[0] if shape else 1
    if isinstance(index, tuple):
        if not index:
            return n
        index = index[0]
    if isinstance(index, slice):
        return len(range(*index.indices(n)))
    if isinstance(index, (int, np.integer)):
        return 1
    return int(np.size(index))


def _check_fits_memory(path: Path, name: str, nbytes: int) -> None:
    from articulated_dataset.core.safeio import available_memory_bytes, format_bytes

    avail = available_memory_bytes()
    if avail is not None and nbytes > MAX_READ_MEMORY_FRACTION * avail:
        raise DataFormatError(f"{path}: dataset {name!r} holds {format_bytes(nbytes)}, more than "
                              f"{MAX_READ_MEMORY_FRACTION:.0%} of the {format_bytes(avail)} of memory available")


@contextlib.contextmanager
def reading(path: str | Path, dataset: str | None = None):
    """Turn HDF5 read failures inside the block (a corrupt chunk: ``OSError: Can't
    synchronously read data``, a damaged heap...) into one :class:`DataFormatError` naming
    the file (and dataset) and pointing to ``artdata verify``."""
    try:
        yield
    except (OSError, RuntimeError) as exc:
        what = f"{path}" + (f": dataset {dataset!r}" if dataset else "")
        raise DataFormatError(f"{what}: cannot read ({_short(exc)}); the file is damaged, "
                              f"run 'artdata verify' on its split") from None


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:200]


#: What parsing a data file's JSON text raises when the text is not JSON: malformed text, bytes that
#: are not UTF-8, a value that is not text, or nesting deeper than the parser's recursion limit
#: (``'[[[[...'``: a ``RecursionError``).  Data, never a bug: readers turn these into their own error.
JSON_TEXT_ERRORS = (json.JSONDecodeError, UnicodeDecodeError, TypeError, RecursionError)


def json_list(text) -> list | None:
    """The JSON list in ``text`` (a shard attribute: ``joint_names``, ``joint_types``,
    ``capture_names``...), or None where ``text`` is not JSON text (:data:`JSON_TEXT_ERRORS`) or
    holds something else than a list."""
    try:
        value = json.loads(text)
    except JSON_TEXT_ERRORS:
        return None
    return value if isinstance(value, list) else None


def read_json_object(path: str | Path, what: str) -> dict:
    """A JSON object from ``path``; a missing, unparsable or non-object file is a DataFormatError
    naming ``what`` (e.g. "manifest")."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing {what}")
    try:
        data = json.loads(path.read_text())
    except RecursionError:  # '[[[[...' nested deeper than the parser's recursion limit
        raise DataFormatError(f"{path}: corrupt {what} (nested too deeply)") from None
    except JSON_TEXT_ERRORS as exc:
        raise DataFormatError(f"{path}: corrupt {what} ({exc})") from None
    if not isinstance(data, dict):
        raise DataFormatError(f"{path}: corrupt {what} (not a JSON object)")
    return data


#: Deflate level of the per-image depth/mask chunks.  Compression is the costliest step after
#: rendering: level 1 takes ~40% of level 4's time for ~1.4x its size, still well under the
#: 4 KB/image budget (benchmarks/generation.py prints bytes per image).
IMAGE_GZIP_LEVEL = 1
#: Deflate level of the (small) label datasets.
LABEL_GZIP_LEVEL = 4


def write_shard(path: str | Path, arrays: Mapping[str, Any], attrs: dict, K: np.ndarray, R: np.ndarray) -> dict:
    """Validate ``arrays`` against the schema and write them atomically to ``path``.

    Returns the shard's manifest record (file name, images, bytes, sha256).
    """
    path = Path(path)
    N, H, W = arrays["depth"].shape
    J = arrays["q"].shape[1]
    validate_arrays(arrays, N=N, J=J, H=H, W=W, where=str(path))
    from articulated_dataset.core.safeio import atomic_write_h5

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
