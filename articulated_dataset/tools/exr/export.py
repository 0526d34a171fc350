"""Exporting a split to OpenEXR (:func:`export_split`): the output folder checked and staged,
every image written as files, ``split.json`` indexing them."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.images.exr import (
    DEPTH_CHANNEL,
    DEPTH_SUFFIX,
    EXPORT_FORMAT,
    EXPORT_FORMAT_VERSION,
    INDEX_NAME,
    LABEL_SUFFIX,
    MASK_SUFFIX,
    RGB_SUFFIX,
    json_value,
    sample_stem,
    write_depth_exr,
    write_mask_png,
    write_rgb_png,
)
from articulated_dataset.core.safeio import (
    check_name_length,
    ensure_dir,
    remove_created_dirs,
    temporary_name,
    translated,
)
from articulated_dataset.format import (
    FIELDS,
    FIELDS_BY_NAME,
    K_DATASET,
    LABEL_FIELDS,
    R_DATASET,
    TMP_SUFFIX,
    Split,
    reading,
)
from articulated_dataset.format.schema import RGB_FIELDS_BY_NAME


def _check_target(path: Path, overwrite: bool, what: str, marker: str) -> None:
    """Refuse an output folder before any work: not a folder, a symbolic link, not empty
    without ``overwrite``, or (with ``overwrite``) not a folder this tool wrote (no ``marker``)."""
    check_name_length(path)
    if path.is_symlink():
        raise UserError(f"{what} {path} is a symbolic link; name the real folder")
    if path.exists() and not path.is_dir():
        raise UserError(f"{what} {path} exists and is not a directory")
    if path.is_dir() and any(path.iterdir()):
        if not overwrite:
            raise UserError(f"{what} {path} is not empty; pass {option('overwrite')} to replace it")
        if not (path / marker).is_file():
            raise UserError(f"{what} {path} holds no {marker}: not written by "
                            f"artdata, so {option('overwrite')} does not replace it")


@contextlib.contextmanager
def staged_dir(final: Path, overwrite: bool, what: str, marker: str):
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
                old = final.with_name(temporary_name(f"{final.name}.old"))  # a new name: nothing planted there
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
    """Export one split folder to ``out_dir`` (EXR depth, PNG mask, JSON labels per image; an
    RGB PNG too for a ``--rgb`` split).

    The files are written to a temporary sibling folder that replaces ``out_dir`` only when
    complete; ``overwrite`` replaces only a folder holding an export (``split.json``).
    ``progress(n)`` is called after each shard with its image count.  Returns ``out_dir``.
    """
    split_dir, out_dir = Path(split_dir), Path(out_dir)
    split = Split(split_dir)
    with staged_dir(out_dir, overwrite, "export folder", INDEX_NAME) as tmp:
        _export_into(tmp, split.manifest, split.shards, progress)
    return out_dir


def _export_into(out_dir: Path, manifest: dict, shards: list, progress) -> None:
    index: dict[str, Any] = {
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
    if manifest.get("config", {}).get("rgb") is True:  # a --rgb split: its colour images too
        index["rgb"] = {"suffix": RGB_SUFFIX, "mode": "8-bit RGB", "meaning": RGB_FIELDS_BY_NAME["rgb"].description}
    written: dict[str, str] = {}  # stem -> where it came from: a stem seen twice would overwrite an image
    for sh in shards:
        f = sh.file
        with reading(sh.path):
            attrs = {k: json_value(f.attrs[k]) for k in f.attrs}
        K, R = sh.read(K_DATASET, ()), sh.read(R_DATASET, ())
        depth, mask = sh.read("depth"), sh.read("mask")
        rgb = sh.read("rgb") if "rgb" in index else None
        labels = sh.labels()
        stems = []
        for row in range(depth.shape[0]):
            stem = sample_stem(labels["object_index"][row], labels["image_index"][row])
            if stem in written or int(labels["object_index"][row]) < 0 or int(labels["image_index"][row]) < 0:
                raise UserError(f"{sh.path}: image {row} has object/image index {stem}"
                                + (f", as {written[stem]}" if stem in written else " (negative)")
                                + "; the split is damaged, run 'artdata verify' on it")
            written[stem] = f"image {row} of {sh.path.name}"
            stems.append(stem)
            write_depth_exr(out_dir / (stem + DEPTH_SUFFIX), depth[row],
                            {"sample_id": str(int(labels["sample_id"][row])), "depth_units": "m"})
            write_mask_png(out_dir / (stem + MASK_SUFFIX), mask[row])
            if rgb is not None:
                write_rgb_png(out_dir / (stem + RGB_SUFFIX), rgb[row])
            record = {name: json_value(labels[name][row]) for name in LABEL_FIELDS}
            record.update(shard=sh.path.name, row=row, K=K.tolist())
            (out_dir / (stem + LABEL_SUFFIX)).write_text(json.dumps(record) + "\n")
        index["shards"].append({"file": sh.path.name, "attrs": attrs, "K": K.tolist(), "R": R.tolist(), "samples": stems})
        sh.close()
        if progress is not None:
            progress(len(stems))
    # the index is written last: a folder without it is an incomplete export
    (out_dir / INDEX_NAME).write_text(json.dumps(index, indent=1) + "\n")
