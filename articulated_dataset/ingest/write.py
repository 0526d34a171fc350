"""Writing ingested captures as a split (:func:`write_real_split`): shards per set of equal
intrinsics, the manifest, stable sample ids, appending to or replacing a real split."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from pathlib import Path

import numpy as np

from articulated_dataset.classes.registry import get_class
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format import FIELDS, SplitConfig, visible_pixels
from articulated_dataset.format.manifest import is_utf8
from articulated_dataset.format.records import shard_attrs, split_manifest
from articulated_dataset.ingest.capture import DEPTH_QUANTUM_M, Capture, IngestOptions

log = logging.getLogger(__name__)

REAL_SPLIT = "real"
#: Images per shard (real splits are small; a shard per group of equal intrinsics).
MAX_IMAGES_PER_SHARD = 1024


def real_sample_id(class_name: str, split: str, capture_name: str) -> int:
    """Stable 63-bit id of a real image: blake2b-64 of ``"{class}/{split}/{capture}"`` >> 1."""
    text = f"{class_name}/{split}/{capture_name}"
    return int.from_bytes(hashlib.blake2b(text.encode("utf-8"), digest_size=8).digest(), "little") >> 1


def vfov_deg_of(K: np.ndarray, height_px: int) -> float:
    """Vertical field of view (deg) of intrinsics ``K`` for images ``height_px`` rows high."""
    return math.degrees(2.0 * math.atan(0.5 * height_px / K[1, 1]))


def _appendable(manifest: dict, split_dir: Path) -> tuple[list, list, list, tuple[int, int, float]]:
    """``(shard records, object names, capture names, (W, H, vertical field of view in deg))`` of a
    real split's manifest,
    checked to be what :func:`write_real_split` writes (a :class:`UserError` otherwise)."""
    def names(v) -> bool:
        return isinstance(v, list) and all(isinstance(x, str) and x for x in v)

    try:
        real, cam, shards = manifest["real"], manifest["config"]["camera"], manifest["shards"]
        size = (cam["width_px"], cam["height_px"], cam["vfov_deg"])
        ok = (isinstance(real, dict) and names(real.get("objects")) and names(real.get("captures"))
              and all(isinstance(v, int) and not isinstance(v, bool) for v in size[:2])
              and isinstance(size[2], (int, float)) and not isinstance(size[2], bool) and isinstance(shards, list)
              and all(isinstance(r, dict) and isinstance(r.get("object_images", {}), dict)
                      and all(str(k).isdigit() and isinstance(c, int) and not isinstance(c, bool) and c > 0
                              for k, c in r.get("object_images", {}).items()) for r in shards))
    except (KeyError, TypeError):
        ok = False
    if not ok:
        raise UserError(f"{split_dir}/manifest.json: corrupt real-split record; cannot {option('append')} "
                        "(run 'artdata verify')")
    return list(shards), list(real["objects"]), list(real["captures"]), size


def write_real_split(captures: list[Capture], class_name: str, out_root: str | Path, *, split: str = REAL_SPLIT,
                     camera: CameraConfig | None = None, options: IngestOptions | None = None,
                     append: bool = False, overwrite: bool = False) -> Path:
    """Write ingested captures to ``out_root/<class>/<split>/`` (shards + manifest).

    Captures sharing intrinsics go to the same shard (one shard per distinct K, at most
    :data:`MAX_IMAGES_PER_SHARD` images each).  ``append`` adds shards to an existing real
    split (same camera; capture names must be new; captures naming a known object keep its
    index); ``overwrite`` replaces it.  Returns the split folder.
    """
    from articulated_dataset.core.safeio import (
        check_name_length,
        ensure_dir,
        remove_created_dirs,
        temporary_name,
        translated,
    )
    from articulated_dataset.format.manifest import MANIFEST_NAME, read_manifest, write_manifest
    from articulated_dataset.format.shards import shard_name, write_shard

    if not captures:
        raise UserError("no captures to ingest")
    if not split or "/" in split or "\0" in split or split.startswith(".") or not is_utf8(split):
        raise UserError(f"invalid split name {split!r}")
    if append and overwrite:
        raise UserError(f"{option('append')} and {option('overwrite')} are mutually exclusive")
    obj_class = get_class(class_name)
    options = options or IngestOptions()
    camera = camera or options.camera
    split_dir = Path(out_root) / class_name / split
    check_name_length(split_dir)
    if split_dir.is_symlink() or (split_dir.exists() and not split_dir.is_dir()):
        raise UserError(f"{split_dir} is a symbolic link or a file; give {option('out_root')} a folder where the split "
                        "can be written")
    ours = [p for p in split_dir.iterdir() if _is_ours(p)] if split_dir.is_dir() else []
    foreign = [p.name for p in split_dir.iterdir() if not _is_ours(p)] if split_dir.is_dir() else []
    if foreign:
        raise UserError(f"{split_dir} holds files 'artdata ingest' did not write (e.g. {foreign[0]!r}); "
                        f"move them or choose another {option('split')}")
    existing = [p for p in ours if p.name == MANIFEST_NAME or p.suffix == ".h5"]
    old_shards: list[dict] = []
    objects: list[str] = []
    names: list[str] = []
    if existing:
        if overwrite:  # replaced below, once the new split is complete; only a split ingest wrote
            if not _holds_real_split(split_dir, class_name):
                raise UserError(f"{split_dir} does not hold ingested real data of class {class_name} (a generated or "
                                f"imported split); {option('overwrite')} replaces only a real split: choose another "
                                f"{option('split')}")
        elif append:
            old = read_manifest(split_dir)
            if old.get("class_name") != class_name or "real" not in old:
                raise UserError(f"{split_dir} does not hold ingested real data of class {class_name}; "
                                f"cannot {option('append')}")
            old_shards, objects, names, old_size = _appendable(old, split_dir)
            if old_size[:2] != (camera.width_px, camera.height_px) or abs(old_size[2] - camera.vfov_deg) > 1e-9:
                raise UserError(f"{split_dir} holds {old_size[0]}x{old_size[1]} images of a {old_size[2]:g} deg "
                                f"training camera; cannot {option('append')} {camera.width_px}x{camera.height_px} at "
                                f"{camera.vfov_deg:g} deg (pass {option('like_path')} {split_dir})")
        else:
            raise UserError(f"{split_dir} already holds data; pass {option('append')} to add captures or "
                            f"{option('overwrite')} to replace them")
    clash = sorted(set(names) & {c.name for c in captures})
    if clash:
        raise UserError(f"{split_dir}: capture(s) already ingested: {', '.join(clash[:5])}")

    # object index of each capture: named objects keep their index; unnamed ones are one object
    default_object = f"{class_name}-{split}"
    obj_of = []
    for c in captures:
        obj = c.labels.get("object") or default_object
        if obj not in objects:
            objects.append(obj)
        obj_of.append(objects.index(obj))
    img_counter: dict[int, int] = {}
    for shard in old_shards:
        for o, n in shard.get("object_images", {}).items():
            img_counter[int(o)] = img_counter.get(int(o), 0) + int(n)

    groups: dict[bytes, list[int]] = {}
    for i, c in enumerate(captures):
        groups.setdefault(np.round(c.K, 9).tobytes(), []).append(i)
    records = list(old_shards)
    next_index = len(old_shards)
    written: list[Path] = []

    def split_config(images_per_object: int = 1) -> SplitConfig:
        """The real split's settings (the manifest's ``config``; a shard's attributes replace
        its per-split counts with their own)."""
        return SplitConfig(class_name, split=split, n_objects=len(objects), seed=0, images_per_object=images_per_object,
                           objects_per_shard=len(objects), camera=camera, table=obj_class.table,
                           depth_quantum_m=DEPTH_QUANTUM_M)

    def write_all(split_dir: Path) -> None:
        """Shards of ``captures`` from shard ``next_index`` on (paths added to ``written``),
        then the manifest, into ``split_dir``."""
        nonlocal next_index
        J = obj_class.n_joints
        H = camera.height_px
        field_names = {f.name for f in FIELDS}
        for members in groups.values():
            for start in range(0, len(members), MAX_IMAGES_PER_SHARD):
                chunk = members[start : start + MAX_IMAGES_PER_SHARD]
                N = len(chunk)
                arrays: dict[str, np.ndarray] = {
                    "depth": np.stack([captures[i].depth for i in chunk]).astype(np.float32),
                    "mask": np.stack([captures[i].mask for i in chunk]).astype(np.uint8),
                    "visible_pixels": np.stack([visible_pixels(captures[i].mask, J) for i in chunk]).astype(np.int32),
                    "object_index": np.array([obj_of[i] for i in chunk], np.int64),
                    "sample_id": np.array([real_sample_id(class_name, split, captures[i].name) for i in chunk], np.int64),
                    "class": np.full(N, class_name.encode("ascii"), dtype="S32"),
                }
                image_index = []
                for i in chunk:
                    o = obj_of[i]
                    image_index.append(img_counter.get(o, 0))
                    img_counter[o] = img_counter.get(o, 0) + 1
                arrays["image_index"] = np.array(image_index, np.int32)
                for key in ("q", "axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw", "geometry"):
                    arrays[key] = np.stack([np.asarray(captures[i].labels[key], np.float64) for i in chunk]).astype(np.float32)
                assert set(arrays) == field_names
                K = captures[chunk[0]].K
                obj_idx = arrays["object_index"]
                per_object = {str(int(o)): int(c) for o, c in zip(*np.unique(obj_idx, return_counts=True))}
                # The split's settings with this shard's own: its field of view, the real
                # "noise model", no visibility threshold, the captures it holds.
                attrs = shard_attrs(
                    split_config(), obj_class, range(int(obj_idx.min()), int(obj_idx.max()) + 1),
                    n_objects=len(per_object), images_per_object=max(per_object.values()), vfov_deg=vfov_deg_of(K, H),
                    min_part_pixels=0, noise_model="real", real=1,
                    capture_names=json.dumps([captures[i].name for i in chunk]),
                    has_ground_truth=np.array([captures[i].has_labels for i in chunk], np.int8))
                target = split_dir / shard_name(next_index)
                if target.exists():
                    raise UserError(f"{target} exists but the manifest does not list it; run 'artdata verify' on the split")
                written.append(target)
                rec = write_shard(target, arrays, attrs, K, R_CAMERA_TO_OPTICAL)
                rec.update(object_start=attrs["object_start"], object_stop=attrs["object_stop"], object_images=per_object)
                records.append(rec)
                names.extend(captures[i].name for i in chunk)
                next_index += 1
        per_obj_total: dict[int, int] = {}
        for r in records:
            for o, n in r.get("object_images", {}).items():
                per_obj_total[int(o)] = per_obj_total.get(int(o), 0) + int(n)
        manifest = split_manifest(split_config(max(per_obj_total.values())), records, n_objects=len(objects),
                                  n_shards_expected=len(records),
                                  real={"objects": objects, "captures": names, "options": options.to_dict()})
        write_manifest(split_dir, manifest)

    # Appending writes new shard files beside the old ones and then replaces the manifest;
    # anything else builds the split in a hidden sibling folder and swaps it in when complete,
    # so a failure (disk full, a bad capture) leaves the previous split as it was.
    in_place = bool(append and existing)
    created = ensure_dir(split_dir.parent)
    work_dir = split_dir
    if not in_place:  # a new folder under an unpredictable name: never an existing one, never a link
        work_dir = split_dir.parent / temporary_name(f"{split}.ingest")
        with translated(work_dir, "create folder"):
            work_dir.mkdir()
        created.append(work_dir)
    try:
        write_all(work_dir)
    except BaseException:
        for f in written:
            f.unlink(missing_ok=True)
        if not in_place:
            (work_dir / MANIFEST_NAME).unlink(missing_ok=True)
        remove_created_dirs(created)
        raise
    if not in_place:
        _swap_in(work_dir, split_dir)
    return split_dir


def _holds_real_split(split_dir: Path, class_name: str) -> bool:
    """Whether ``split_dir``'s manifest is a real split of ``class_name`` as
    :func:`write_real_split` writes it (an unreadable or missing manifest is not)."""
    from articulated_dataset.format.manifest import read_manifest

    try:
        manifest = read_manifest(split_dir)
    except UserError:
        return False
    return (isinstance(manifest, dict) and manifest.get("class_name") == class_name
            and isinstance(manifest.get("real"), dict))


def _is_ours(p: Path) -> bool:
    """A file ``artdata ingest`` writes in a split folder (manifest, shards, their partial files)."""
    from articulated_dataset.core.safeio import temporary_target
    from articulated_dataset.format import MANIFEST_NAME

    name = temporary_target(p.name) or p.name
    return p.is_file() and not p.is_symlink() and (name == MANIFEST_NAME or re.fullmatch(r"shard-[0-9]{5,}\.h5", name) is not None)


def _swap_in(new_dir: Path, split_dir: Path) -> None:
    """Rename the complete ``new_dir`` to ``split_dir``; an old split there is moved aside
    first and its files removed afterwards (only files :func:`_is_ours`)."""
    from articulated_dataset.core.safeio import temporary_name

    old_dir = split_dir.parent / temporary_name(f"{split_dir.name}.old")  # unpredictable: no link waits there
    if split_dir.is_dir():
        os.rename(split_dir, old_dir)
    os.rename(new_dir, split_dir)
    if old_dir.is_dir():
        for f in old_dir.iterdir():
            if _is_ours(f):
                f.unlink()
        try:
            old_dir.rmdir()
        except OSError:
            log.warning("%s: could not remove the replaced split's folder", old_dir)
