"""OpenEXR interchange: export shards to per-image files and import them back exactly.

Layout of an exported split (``OUT/<class>/<split>/``, mirroring the shard layout)::

    split.json                 index: format, field table, source manifest, per-shard
                               attributes / K / R and the ordered list of image stems
    o000012_i003.exr           depth, float32, single channel "Z", metres, ZIP (lossless)
    o000012_i003.mask.png      mask, 8-bit greyscale PNG (values 0 .. 1 + J, lossless)
    o000012_i003.json          every label of the image (schema fields but depth/mask), K

The stem is ``o<object_index:06d>_i<image_index:03d>``.  Labels are written as JSON
numbers: a float32 value printed with Python's shortest round-trip repr and read back as
float64 then cast to float32 is the same float32, so labels, depth and mask round-trip
bit-exactly.  :func:`import_split` writes the shards with the same writer, attribute order
and manifest as the generator, so the re-imported shards are byte-identical files.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from .errors import DataFormatError, UserError
from .schema import FIELDS, FIELDS_BY_NAME, IMAGE_FIELDS, K_DATASET, R_DATASET, resolve_shape
from .shards import find_split_dirs, open_split, read_json_object, write_manifest, write_shard

log = logging.getLogger(__name__)

EXPORT_FORMAT = "articulated_dataset-exr"
EXPORT_FORMAT_VERSION = "1.0"
INDEX_NAME = "split.json"
DEPTH_CHANNEL = "Z"
DEPTH_SUFFIX = ".exr"
MASK_SUFFIX = ".mask.png"
LABEL_SUFFIX = ".json"
LABEL_FIELDS = tuple(f.name for f in FIELDS if f.name not in IMAGE_FIELDS)


def sample_stem(object_index: int, image_index: int) -> str:
    """File stem of one image: ``o<object:06d>_i<image:03d>``."""
    return f"o{int(object_index):06d}_i{int(image_index):03d}"


def _json_value(v):
    """numpy -> JSON-able Python values (exact for float32/float64, ints, bytes)."""
    if isinstance(v, np.ndarray):
        if v.dtype.kind == "S":
            return [x.decode("ascii") for x in v.tolist()]
        return v.tolist()
    if isinstance(v, bytes):
        return v.decode("ascii")
    if isinstance(v, np.generic):
        return v.item()
    return v


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------

@contextlib.contextmanager
def _c_output_silenced():
    """Point file descriptors 1 and 2 at /dev/null meanwhile: the OpenEXR C++ library prints
    its own diagnostics for damaged files there; we raise one clear error instead."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
        yield
    finally:
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)


def write_depth_exr(path: str | Path, depth_m: np.ndarray, header_extra: dict | None = None) -> None:
    """Write a float32 (H, W) depth image as a single-channel ("Z") ZIP-compressed EXR."""
    import OpenEXR

    depth_m = np.ascontiguousarray(depth_m, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(header_extra or {})
    with OpenEXR.File(header, {DEPTH_CHANNEL: depth_m}) as f:
        f.write(str(path))


def read_depth_exr(path: str | Path) -> np.ndarray:
    """Read the float32 "Z" channel of an EXR file; anything else is a DataFormatError."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing depth image")
    try:
        with _c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if DEPTH_CHANNEL not in channels:
                raise DataFormatError(f"{path}: no {DEPTH_CHANNEL!r} channel (has {sorted(channels)})")
            pixels = channels[DEPTH_CHANNEL].pixels
    except (RuntimeError, ValueError, OSError) as exc:
        raise DataFormatError(f"{path}: not a readable OpenEXR file ({str(exc).splitlines()[0][:150]})") from None
    if pixels is None or pixels.dtype != np.float32 or pixels.ndim != 2:
        raise DataFormatError(f"{path}: channel {DEPTH_CHANNEL!r} must be 2-D float32 "
                              f"(got {getattr(pixels, 'dtype', None)}, {getattr(pixels, 'shape', None)})")
    return pixels


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(str(path), format="PNG")


def read_mask_png(path: str | Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing mask image")
    try:
        with Image.open(path) as im:
            if im.mode != "L":
                raise DataFormatError(f"{path}: mask must be an 8-bit greyscale PNG, got mode {im.mode}")
            return np.asarray(im, dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DataFormatError(f"{path}: not a readable PNG ({str(exc).splitlines()[0][:150]})") from None


# --------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------

def _prepare_dir(path: Path, overwrite: bool, what: str) -> None:
    if path.exists() and not path.is_dir():
        raise UserError(f"{what} {path} exists and is not a directory")
    if path.is_dir() and any(path.iterdir()):
        if not overwrite:
            raise UserError(f"{what} {path} is not empty; pass --overwrite to replace it")
        shutil.rmtree(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {path}: {exc.strerror or exc}") from None


def export_split(split_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False, progress=None) -> Path:
    """Export one split folder to ``out_dir`` (EXR depth, PNG mask, JSON labels per image).

    ``progress(n)`` is called after each shard with its image count.  Returns ``out_dir``.
    """
    split_dir, out_dir = Path(split_dir), Path(out_dir)
    manifest, shards = open_split(split_dir)
    _prepare_dir(out_dir, overwrite, "export folder")
    index = {
        "format": EXPORT_FORMAT,
        "format_version": EXPORT_FORMAT_VERSION,
        "depth": {"suffix": DEPTH_SUFFIX, "channel": DEPTH_CHANNEL, "pixel_type": "FLOAT (float32)", "units": "m",
                  "compression": "ZIP", "meaning": FIELDS_BY_NAME["depth"].description},
        "mask": {"suffix": MASK_SUFFIX, "mode": "8-bit greyscale", "meaning": FIELDS_BY_NAME["mask"].description},
        "labels": {"suffix": LABEL_SUFFIX, "fields": {f.name: {"dtype": f.dtype, "shape": list(f.shape[1:]), "units": f.units,
                                                                 "frame": f.frame} for f in FIELDS if f.name in LABEL_FIELDS}},
        "manifest": manifest,
        "shards": [],
    }
    for sh in shards:
        attrs = {k: _json_value(sh.file.attrs[k]) for k in sh.file.attrs}
        K = sh.file[K_DATASET][()]
        R = sh.file[R_DATASET][()]
        depth, mask = sh.read("depth"), sh.read("mask")
        labels = sh.labels()
        stems = []
        for row in range(depth.shape[0]):
            stem = sample_stem(labels["object_index"][row], labels["image_index"][row])
            stems.append(stem)
            write_depth_exr(out_dir / (stem + DEPTH_SUFFIX), depth[row],
                            {"sample_id": str(int(labels["sample_id"][row])), "depth_units": "m"})
            write_mask_png(out_dir / (stem + MASK_SUFFIX), mask[row])
            record = {name: _json_value(labels[name][row]) for name in LABEL_FIELDS}
            record.update(shard=sh.path.name, row=row, K=K.tolist())
            (out_dir / (stem + LABEL_SUFFIX)).write_text(json.dumps(record) + "\n")
        index["shards"].append({"file": sh.path.name, "attrs": attrs, "K": K.tolist(), "R": R.tolist(), "samples": stems})
        sh.close()
        if progress is not None:
            progress(len(stems))
    # the index is written last: a folder without it is an incomplete export
    (out_dir / INDEX_NAME).write_text(json.dumps(index, indent=1) + "\n")
    return out_dir


# --------------------------------------------------------------------------------------
# Import
# --------------------------------------------------------------------------------------

def find_exports(path: str | Path) -> list[Path]:
    """Exported split folders (holding ``split.json``) at ``path`` or one/two levels below."""
    return find_split_dirs(path, marker=INDEX_NAME, what="exported split")


def _label_array(records: list[dict], name: str, where: Path) -> np.ndarray:
    """Stack one label over an export's images with the schema's dtype."""
    f = FIELDS_BY_NAME[name]
    values = [r[name] for r in records]
    try:
        if f.dtype.startswith("S"):
            return np.array([v.encode("ascii") for v in values], dtype=f.dtype)
        a = np.array(values)
        if f.dtype.startswith("int") and a.size and a.dtype.kind not in "iu":
            raise ValueError("expected integers")
        if a.size and a.dtype.kind not in "iuf":
            raise ValueError("expected numbers")
        return a.astype(f.dtype)
    except (ValueError, TypeError, AttributeError, UnicodeEncodeError) as exc:
        raise DataFormatError(f"{where}: label {name!r} has malformed values ({exc})") from None


def load_index(export_dir: str | Path) -> dict:
    """The ``split.json`` of an exported folder, checked for format and version."""
    export_dir = Path(export_dir)
    index = read_json_object(export_dir / INDEX_NAME, "export index")
    if index.get("format") != EXPORT_FORMAT:
        raise DataFormatError(f"{export_dir / INDEX_NAME}: not an articulated_dataset EXR export (format {index.get('format')!r})")
    if str(index.get("format_version", "")).split(".")[0] != EXPORT_FORMAT_VERSION.split(".")[0]:
        raise DataFormatError(f"{export_dir / INDEX_NAME}: export format version {index.get('format_version')} is not "
                              f"readable by this package (reads {EXPORT_FORMAT_VERSION.split('.')[0]}.x)")
    if not isinstance(index.get("manifest"), dict) or not isinstance(index["manifest"].get("class_name"), str):
        raise DataFormatError(f"{export_dir / INDEX_NAME}: corrupt export index (no source manifest with a class name)")
    return index


def import_tree(path: str | Path, out_root: str | Path, *, overwrite: bool = False, progress=None) -> list[Path]:
    """Import every exported split at ``path`` into ``out_root/<class>/<split>/``."""
    out = []
    for d in find_exports(path):
        cls = load_index(d)["manifest"]["class_name"]
        out.append(import_split(d, Path(out_root) / cls / d.name, overwrite=overwrite, progress=progress))
    return out


def import_split(export_dir: str | Path, split_dir: str | Path, *, overwrite: bool = False, progress=None) -> Path:
    """Rebuild shards + manifest in ``split_dir`` from an exported folder (exact round trip).

    Every file is validated; a missing or malformed one is a :class:`DataFormatError`
    naming it.  ``progress(n)`` is called after each shard.  Returns ``split_dir``.
    """
    export_dir, split_dir = Path(export_dir), Path(split_dir)
    index = load_index(export_dir)
    try:
        manifest, shard_specs = index["manifest"], index["shards"]
        records_by_file = {r["file"]: r for r in manifest["shards"]}
        specs = [(s["file"], s["attrs"], np.array(s["K"], np.float64), np.array(s["R"], np.float64), list(s["samples"]),
                  records_by_file[s["file"]]) for s in shard_specs]
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(f"{export_dir / INDEX_NAME}: corrupt export index ({type(exc).__name__}: {exc})") from None
    # Read and validate everything before writing anything.
    shards = []
    for file, attrs, K, R, stems, rec in specs:
        J, H, W = int(attrs.get("n_joints", -1)), int(attrs.get("image_height", -1)), int(attrs.get("image_width", -1))
        if K.shape != (3, 3) or R.shape != (3, 3):
            raise DataFormatError(f"{export_dir / INDEX_NAME}: {file}: K and R must be 3x3")
        depth = np.empty((len(stems), H, W), np.float32) if H > 0 and W > 0 else None
        if depth is None:
            raise DataFormatError(f"{export_dir / INDEX_NAME}: {file}: attributes image_height/image_width missing")
        mask = np.empty((len(stems), H, W), np.uint8)
        labels = []
        for i, stem in enumerate(stems):
            d = read_depth_exr(export_dir / (stem + DEPTH_SUFFIX))
            m = read_mask_png(export_dir / (stem + MASK_SUFFIX))
            for what, a, suffix in (("depth", d, DEPTH_SUFFIX), ("mask", m, MASK_SUFFIX)):
                if a.shape != (H, W):
                    raise DataFormatError(f"{export_dir / (stem + suffix)}: {what} is {a.shape[1]}x{a.shape[0]} px, "
                                          f"expected {W}x{H}")
            depth[i], mask[i] = d, m
            lab = read_json_object(export_dir / (stem + LABEL_SUFFIX), "label file")
            for name in LABEL_FIELDS:
                shape = resolve_shape(FIELDS_BY_NAME[name].shape[1:], N=0, J=J, H=H, W=W)
                if name not in lab:
                    raise DataFormatError(f"{export_dir / (stem + LABEL_SUFFIX)}: missing label {name!r}")
                if np.shape(lab[name]) != shape:
                    raise DataFormatError(f"{export_dir / (stem + LABEL_SUFFIX)}: label {name!r} has shape "
                                          f"{np.shape(lab[name])}, expected {shape}")
            labels.append(lab)
        arrays = {"depth": depth, "mask": mask}
        for name in LABEL_FIELDS:
            arrays[name] = _label_array(labels, name, export_dir / file)
        shards.append((file, attrs, K, R, arrays, rec))
    _prepare_dir(split_dir, overwrite, "output folder")
    new_records = []
    for file, attrs, K, R, arrays, rec in shards:
        out = write_shard(split_dir / file, arrays, attrs, K, R)
        new_records.append({**rec, **out})
        if progress is not None:
            progress(len(arrays["depth"]))
    write_manifest(split_dir, {**manifest, "shards": new_records})
    changed = [r["file"] for r, old in zip(new_records, (s[5] for s in shards)) if r["sha256"] != old["sha256"]]
    if changed:
        log.warning("%s: re-imported shards %s are not byte-identical to the originals (arrays are equal; "
                    "the HDF5 library or writer differs)", split_dir, ", ".join(changed))
    return split_dir
