"""Importing an export back into shards (:func:`import_split`, ``artdata import-exr``): the
index and label files read as data, the shards written with the generator's writer (byte-identical
files) and verified."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.core.images.exr import (
    DEPTH_SUFFIX,
    EXPORT_FORMAT,
    EXPORT_FORMAT_VERSION,
    INDEX_NAME,
    LABEL_SUFFIX,
    MASK_SUFFIX,
    RGB_SUFFIX,
    STEM_RE,
    read_depth_exr,
    read_mask_png,
)
from articulated_dataset.core.safeio import check_memory
from articulated_dataset.format import (
    FIELDS_BY_NAME,
    LABEL_FIELDS,
    MANIFEST_NAME,
    check_manifest_names,
    check_shard_file,
    find_split_dirs,
    read_json_object,
    resolve_inside,
    resolve_shape,
)
from articulated_dataset.format.manifest import write_manifest
from articulated_dataset.format.shards import write_shard
from articulated_dataset.tools.exr.export import staged_dir

log = logging.getLogger(__name__)

#: Largest image import-exr reads (pixels; 4096 x 4096, a depth image of 64 MiB): an export
#: index declares its image size, and each image is decoded at that size.
MAX_IMPORT_PIXELS = 4096 * 4096


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
        with np.errstate(over="ignore", invalid="ignore"):  # 1e300 -> inf: verification names it
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
        if not isinstance(samples, list) or not all(isinstance(x, str) and STEM_RE.fullmatch(x) for x in samples):
            bad = next((x for x in samples if not (isinstance(x, str) and STEM_RE.fullmatch(x))), samples) \
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
    elif attrs["image_height"] * attrs["image_width"] > MAX_IMPORT_PIXELS:
        problem = (f"images of {attrs['image_width']}x{attrs['image_height']} px are larger than import-exr reads "
                   f"(at most {MAX_IMPORT_PIXELS:,} pixels)")
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
    from articulated_dataset.tools.verify import verify_split

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
    with_rgb = "rgb" in index  # a --rgb split's export: <stem>.rgb.png per image
    # Read and validate everything before writing anything.
    shards = []
    for file, attrs, K, R, stems, rec in specs:
        J, H, W = attrs["n_joints"], attrs["image_height"], attrs["image_width"]
        bytes_per_pixel = np.dtype(np.float32).itemsize + 1 + (3 if with_rgb else 0)  # depth, mask, colour
        check_memory(len(stems) * H * W * bytes_per_pixel, f"{where}: importing {file} ({len(stems)} images)")
        depth = mask = rgb = None
        labels = []
        for i, stem in enumerate(stems):
            inside = resolve_inside(export_dir, stem)  # a checked stem; its files must not be links leading out
            for suffix in (DEPTH_SUFFIX, MASK_SUFFIX, LABEL_SUFFIX):
                resolve_inside(export_dir, stem + suffix)
            d = read_depth_exr(inside.with_name(stem + DEPTH_SUFFIX), (H, W))
            m = read_mask_png(inside.with_name(stem + MASK_SUFFIX), (H, W))
            if with_rgb:
                resolve_inside(export_dir, stem + RGB_SUFFIX)
                c = read_mask_png(inside.with_name(stem + RGB_SUFFIX), (H, W), what="colour", mode="RGB")
                if rgb is None:
                    rgb = np.empty((len(stems), H, W, 3), np.uint8)
                rgb[i] = c
            for what, a, suffix in (("depth", d, DEPTH_SUFFIX), ("mask", m, MASK_SUFFIX)):
                if a.shape != (H, W):
                    raise DataFormatError(f"{export_dir / (stem + suffix)}: {what} is {a.shape[1]}x{a.shape[0]} px, "
                                          f"expected {W}x{H}")
            if depth is None:  # allocated once an image has shown that the size is real
                depth, mask = np.empty((len(stems), H, W), np.float32), np.empty((len(stems), H, W), np.uint8)
            depth[i], mask[i] = d, m  # type: ignore[index]  # allocated just above
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
        arrays: dict[str, Any] = {"depth": depth, "mask": mask}
        if rgb is not None:
            arrays["rgb"] = rgb
        for name in LABEL_FIELDS:
            arrays[name] = _label_array(labels, name, export_dir / file)
        shards.append((file, attrs, K, R, arrays, rec))
    new_records = []
    with staged_dir(split_dir, overwrite, "output folder", MANIFEST_NAME) as tmp:
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
