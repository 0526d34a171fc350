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
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from .errors import DataFormatError, UserError
from .safeio import ensure_dir, remove_created_dirs, translated
from .format import (
    FIELDS,
    FIELDS_BY_NAME,
    K_DATASET,
    LABEL_FIELDS,
    MANIFEST_NAME,
    R_DATASET,
    TMP_SUFFIX,
    Split,
    check_manifest_names,
    check_shard_file,
    find_split_dirs,
    read_json_object,
    reading,
    resolve_inside,
    resolve_shape,
)
from .shards import write_manifest, write_shard

log = logging.getLogger(__name__)

EXPORT_FORMAT = "articulated_dataset-exr"
EXPORT_FORMAT_VERSION = "1.0"
INDEX_NAME = "split.json"
DEPTH_CHANNEL = "Z"
DEPTH_SUFFIX = ".exr"
MASK_SUFFIX = ".mask.png"
LABEL_SUFFIX = ".json"
#: An image stem as :func:`sample_stem` writes it (read back from ``split.json``).
_STEM_RE = re.compile(r"o[0-9]{6,}_i[0-9]{3,}")


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


def _size_mismatch(path: Path, what: str, width: int, height: int, expect_hw) -> None:
    if expect_hw is not None and (height, width) != tuple(expect_hw):
        raise DataFormatError(f"{path}: {what} is {width}x{height} px, expected {expect_hw[1]}x{expect_hw[0]}")


def read_depth_exr(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read the float32 "Z" channel of an EXR file; anything else is a DataFormatError.

    ``expect_hw``: the (height, width) the image must have, checked from the header before
    any pixel is decoded (a hostile header cannot make us allocate its size)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing depth image")
    try:
        if expect_hw is not None:
            with _c_output_silenced(), OpenEXR.File(str(path), header_only=True) as f:
                lo, hi = f.header()["dataWindow"]
            _size_mismatch(path, "depth", int(hi[0]) - int(lo[0]) + 1, int(hi[1]) - int(lo[1]) + 1, expect_hw)
        with _c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if DEPTH_CHANNEL not in channels:
                raise DataFormatError(f"{path}: no {DEPTH_CHANNEL!r} channel (has {sorted(channels)})")
            pixels = channels[DEPTH_CHANNEL].pixels
    except (RuntimeError, ValueError, OSError, KeyError, TypeError) as exc:
        raise DataFormatError(f"{path}: not a readable OpenEXR file ({str(exc).splitlines()[0][:150]})") from None
    if pixels is None or pixels.dtype != np.float32 or pixels.ndim != 2:
        raise DataFormatError(f"{path}: channel {DEPTH_CHANNEL!r} must be 2-D float32 "
                              f"(got {getattr(pixels, 'dtype', None)}, {getattr(pixels, 'shape', None)})")
    return pixels


def write_mask_png(path: str | Path, mask: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(str(path), format="PNG")


def read_mask_png(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit greyscale PNG; ``expect_hw`` is checked before the pixels are decoded."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: missing mask image")
    try:
        with Image.open(path) as im:
            _size_mismatch(path, "mask", im.size[0], im.size[1], expect_hw)
            if im.mode != "L":
                raise DataFormatError(f"{path}: mask must be an 8-bit greyscale PNG, got mode {im.mode}")
            return np.asarray(im, dtype=np.uint8).copy()
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError) as exc:
        raise DataFormatError(f"{path}: not a readable PNG ({str(exc).splitlines()[0][:150]})") from None


# --------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------

def _check_target(path: Path, overwrite: bool, what: str, marker: str) -> None:
    """Refuse an output folder before any work: not a folder, a symbolic link, not empty
    without ``overwrite``, or (with ``overwrite``) not a folder this tool wrote (no ``marker``)."""
    if path.is_symlink():
        raise UserError(f"{what} {path} is a symbolic link; name the real folder")
    if path.exists() and not path.is_dir():
        raise UserError(f"{what} {path} exists and is not a directory")
    if path.is_dir() and any(path.iterdir()):
        if not overwrite:
            raise UserError(f"{what} {path} is not empty; pass --overwrite to replace it")
        if not (path / marker).is_file():
            raise UserError(f"{what} {path} holds no {marker}: not written by artdata, so --overwrite does not replace it")


@contextlib.contextmanager
def _staged_dir(final: Path, overwrite: bool, what: str, marker: str):
    """Yield a temporary sibling folder of ``final`` to write into; on success it replaces
    ``final`` (renamed into place; the old folder is removed only then), on failure it is
    removed and ``final`` is untouched."""
    _check_target(final, overwrite, what, marker)
    created = ensure_dir(final.parent)
    done = False
    tmp = None
    try:
        with translated(final):
            tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=TMP_SUFFIX, dir=final.parent))
            yield tmp
            _check_target(final, overwrite, what, marker)  # unchanged meanwhile
            old = None
            if final.is_dir() and any(final.iterdir()):
                old = final.with_name(f".{final.name}.old{TMP_SUFFIX}")
                os.rename(final, old)
            os.replace(tmp, final)  # onto a missing or empty folder
            done = True
            if old is not None:
                shutil.rmtree(old)
    finally:
        if tmp is not None and tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if not done:  # a run that wrote nothing leaves nothing
            remove_created_dirs(created)


def export_split(split_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False, progress=None) -> Path:
    """Export one split folder to ``out_dir`` (EXR depth, PNG mask, JSON labels per image).

    The files are written to a temporary sibling folder that replaces ``out_dir`` only when
    complete; ``overwrite`` replaces only a folder holding an export (``split.json``).
    ``progress(n)`` is called after each shard with its image count.  Returns ``out_dir``.
    """
    split_dir, out_dir = Path(split_dir), Path(out_dir)
    split = Split(split_dir)
    with _staged_dir(out_dir, overwrite, "export folder", INDEX_NAME) as tmp:
        _export_into(tmp, split.manifest, split.shards, progress)
    return out_dir


def _export_into(out_dir: Path, manifest: dict, shards: list, progress) -> None:
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
        f = sh.file
        with reading(sh.path):
            attrs = {k: _json_value(f.attrs[k]) for k in f.attrs}
        K, R = sh.read(K_DATASET, ()), sh.read(R_DATASET, ())
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
    where = str(export_dir / INDEX_NAME)
    if not isinstance(index.get("manifest"), dict) or not isinstance(index["manifest"].get("class_name"), str):
        raise DataFormatError(f"{where}: corrupt export index (no source manifest with a class name)")
    check_manifest_names(index["manifest"], where)
    shards = index.get("shards")
    if not isinstance(shards, list) or not all(isinstance(s, dict) for s in shards):
        raise DataFormatError(f"{where}: corrupt export index (shards must be a list of objects)")
    for s in shards:
        check_shard_file(s.get("file"), where)
        samples = s.get("samples")
        if not isinstance(samples, list) or not all(isinstance(x, str) and _STEM_RE.fullmatch(x) for x in samples):
            bad = next((x for x in samples if not (isinstance(x, str) and _STEM_RE.fullmatch(x))), samples) \
                if isinstance(samples, list) else samples
            raise DataFormatError(f"{where}: invalid image stem {str(bad)[:80]!r} (expected o<object>_i<image>, "
                                  "e.g. o000012_i003)")
    return index


def target_dir(out_root: str | Path, index_or_manifest: dict, split: str) -> Path:
    """``out_root/<class>/<split>`` for a manifest (or an export index holding one), the class
    name checked and the path checked to stay inside ``out_root``."""
    manifest = index_or_manifest.get("manifest", index_or_manifest)
    return resolve_inside(out_root, f"{manifest['class_name']}/{split}", where=f"class {manifest['class_name']!r}")


def import_tree(path: str | Path, out_root: str | Path, *, overwrite: bool = False, progress=None) -> list[Path]:
    """Import every exported split at ``path`` into ``out_root/<class>/<split>/``."""
    out = []
    for d in find_exports(path):
        out.append(import_split(d, target_dir(out_root, load_index(d), d.name), overwrite=overwrite, progress=progress))
    return out


def _attr_ok(v) -> bool:
    """An attribute value the shard writer stores as the generator does: a string, a number,
    or a non-empty list of numbers or of strings."""
    if isinstance(v, (str, bool)) or (isinstance(v, (int, float)) and np.isfinite(v)):
        return True
    if isinstance(v, list) and v:
        return (all(isinstance(x, str) for x in v)
                or all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in v))
    return False


def _shard_spec(s: dict, records_by_file: dict, where: Path) -> tuple:
    """``(file, attrs, K, R, stems, manifest record)`` of one ``split.json`` shard entry, checked:
    the attributes are plain values with whole positive image sizes and joint count, K and R
    finite 3x3, the image list non-empty and as long as the source manifest says."""
    file = s["file"]
    attrs, stems, rec = s.get("attrs"), s["samples"], records_by_file.get(file)
    problem = None
    if not isinstance(attrs, dict) or not all(isinstance(k, str) and _attr_ok(v) for k, v in attrs.items()):
        problem = "attributes must be plain values (strings, numbers, lists of them)"
    elif not all(isinstance(attrs.get(k), int) and not isinstance(attrs.get(k), bool) and attrs[k] >= low
                 for k, low in (("n_joints", 0), ("image_height", 1), ("image_width", 1))):
        problem = "attributes n_joints, image_height, image_width must be whole numbers (sizes >= 1)"
    elif not stems:
        problem = "no images"
    elif rec is None or rec.get("n_images") != len(stems):
        problem = f"{len(stems)} images, the source manifest says {None if rec is None else rec.get('n_images')}"
    if problem is None:
        try:
            K, R = np.array(s["K"], np.float64), np.array(s["R"], np.float64)
        except (KeyError, TypeError, ValueError):
            K = R = np.zeros(0)
        if K.shape != (3, 3) or R.shape != (3, 3) or not (np.isfinite(K).all() and np.isfinite(R).all()):
            problem = "K and R must be finite 3x3 matrices"
    if problem is not None:
        raise DataFormatError(f"{where}: {file}: {problem}")
    return file, attrs, K, R, list(stems), rec


def _verify_rebuilt(split_dir: Path, where: Path) -> None:
    """Run ``artdata verify``'s checks on the rebuilt (not yet visible) split: an export whose
    content does not make a valid split is refused before it replaces anything."""
    from .verify import verify_split

    report = verify_split(split_dir)
    if not report.ok:
        first = report.errors[0]
        raise DataFormatError(f"{where}: the rebuilt split fails verification ({len(report.errors)} problem(s); "
                              f"first: {first.where}: {first.message}); nothing was written")


def import_split(export_dir: str | Path, split_dir: str | Path, *, overwrite: bool = False, progress=None) -> Path:
    """Rebuild shards + manifest in ``split_dir`` from an exported folder (exact round trip).

    Every file is validated; a missing or malformed one is a :class:`DataFormatError`
    naming it.  ``progress(n)`` is called after each shard.  Returns ``split_dir``.
    """
    export_dir, split_dir = Path(export_dir), Path(split_dir)
    index = load_index(export_dir)
    where = export_dir / INDEX_NAME
    manifest = index["manifest"]
    records_by_file = {r["file"]: r for r in manifest.get("shards", [])}
    specs = [_shard_spec(s, records_by_file, where) for s in index["shards"]]
    files = [sp[0] for sp in specs]
    stems = [stem for sp in specs for stem in sp[4]]
    if len(set(files)) != len(files) or len(set(stems)) != len(stems) or set(files) != set(records_by_file):
        raise DataFormatError(f"{where}: corrupt export index (a shard or image is listed twice, or the shard list "
                              "differs from the source manifest's)")
    # Read and validate everything before writing anything.
    shards = []
    for file, attrs, K, R, stems, rec in specs:
        J, H, W = attrs["n_joints"], attrs["image_height"], attrs["image_width"]
        depth = mask = None
        labels = []
        for i, stem in enumerate(stems):
            inside = resolve_inside(export_dir, stem)  # a checked stem; its files must not be links leading out
            for suffix in (DEPTH_SUFFIX, MASK_SUFFIX, LABEL_SUFFIX):
                resolve_inside(export_dir, stem + suffix)
            d = read_depth_exr(inside.with_name(stem + DEPTH_SUFFIX), (H, W))
            m = read_mask_png(inside.with_name(stem + MASK_SUFFIX), (H, W))
            for what, a, suffix in (("depth", d, DEPTH_SUFFIX), ("mask", m, MASK_SUFFIX)):
                if a.shape != (H, W):
                    raise DataFormatError(f"{export_dir / (stem + suffix)}: {what} is {a.shape[1]}x{a.shape[0]} px, "
                                          f"expected {W}x{H}")
            if depth is None:  # allocated once an image has shown that the size is real
                depth, mask = np.empty((len(stems), H, W), np.float32), np.empty((len(stems), H, W), np.uint8)
            depth[i], mask[i] = d, m
            lab = read_json_object(export_dir / (stem + LABEL_SUFFIX), "label file")
            for name in LABEL_FIELDS:
                shape = resolve_shape(FIELDS_BY_NAME[name].shape[1:], N=0, J=J, H=H, W=W)
                if name not in lab:
                    raise DataFormatError(f"{export_dir / (stem + LABEL_SUFFIX)}: missing label {name!r}")
                try:
                    got = np.shape(lab[name])
                except ValueError:  # a ragged list
                    got = "ragged"
                if got != shape:
                    raise DataFormatError(f"{export_dir / (stem + LABEL_SUFFIX)}: label {name!r} has shape "
                                          f"{got}, expected {shape}")
            labels.append(lab)
        arrays = {"depth": depth, "mask": mask}
        for name in LABEL_FIELDS:
            arrays[name] = _label_array(labels, name, export_dir / file)
        shards.append((file, attrs, K, R, arrays, rec))
    new_records = []
    with _staged_dir(split_dir, overwrite, "output folder", MANIFEST_NAME) as tmp:
        for file, attrs, K, R, arrays, rec in shards:
            out = write_shard(resolve_inside(tmp, file), arrays, attrs, K, R)
            new_records.append({**rec, **out})
            if progress is not None:
                progress(len(arrays["depth"]))
        write_manifest(tmp, {**manifest, "shards": new_records})
        _verify_rebuilt(tmp, where)
    changed = [r["file"] for r, old in zip(new_records, (s[5] for s in shards)) if r["sha256"] != old["sha256"]]
    if changed:
        log.warning("%s: re-imported shards %s are not byte-identical to the originals (arrays are equal; "
                    "the HDF5 library or writer differs)", split_dir, ", ".join(changed))
    return split_dir
