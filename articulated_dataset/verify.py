"""Verify generated splits: manifest, checksums, file format and label invariants.

Every problem is reported as one line naming the file it was found in (``manifest.json``
or ``shard-NNNNN.h5``); nothing raises for bad data.  What is checked:

* **manifest**: readable JSON with the required keys, a readable format version and
  generation config; the shard list (each listed file exists, no unlisted shard file),
  per-shard byte sizes and sha256 checksums, and the counts (images, objects, shards;
  a split is complete when every expected shard is listed).
* **format** (per shard, via :mod:`articulated_dataset.schema`): readable HDF5, root
  attributes, every schema dataset with its declared dtype and shape, the ``K`` and
  ``R_camera_to_optical`` datasets, attributes consistent with the manifest.
* **content** (skipped with ``content=False``): finite values, and the label invariants

  - ``depth >= 0`` and a multiple of ``depth_quantum_m``; ``depth > 0`` exactly where
    ``mask > 0`` (noise-free data);
  - ``mask`` values in ``[0, 1 + J]``; ``visible_pixels`` equal to the mask's pixel counts
    and, for each moving part, at least ``min_part_pixels`` (sampled objects);
  - ``|axis_direction| = 1`` and the quaternions of ``axis_pose`` / ``object_pose``
    normalised (within :data:`UNIT_TOL`); ``axis_pose`` position = ``axis_origin`` and its
    z axis = ``axis_direction``;
  - ``q``, the object position and ``object_yaw`` within the sampling table's limits (root
    attribute ``sampling_table``); ``object_yaw`` = yaw of ``object_pose``; with a head
    camera (root attribute ``camera_mount``), the camera's pitch and roll read from the
    object's up axis within the head ranges and the object's level-frame pose within the
    table (:func:`articulated_dataset.viewpoint.level_pose_from_camera`);
  - ``K`` equal to the image size's paper camera, or its ``intrinsics`` preset;
  - per-object labels identical over the object's images (only ``geometry`` with a head
    camera, which moves per image); ``object_index`` /
    ``image_index`` in generation order; ``sample_id`` equal to
    :func:`articulated_dataset.sampling.sample_id` and unique over the split;
  - ``class`` = the shard's class; positive body dimensions; chirality 0 or 1.

**Real splits** (written by ``artdata ingest``: manifest key ``real``, shard attribute
``real = 1``) follow their own rules (docs/real_data.md): label values the capture does not
give are NaN (checked by :func:`articulated_dataset.real.ground_truth.real_label_problems`: never infinite,
NaN per group as a whole, q within the class's joint range, plausible positions and sizes);
``sample_id`` is :func:`articulated_dataset.real.write.real_sample_id` of the shard's
``capture_names``; objects and images are numbered by capture, not by generation order, and a
real object's pose differs between captures; the shard's K may be a crop's (it must be a
pinhole matrix agreeing with ``vfov_deg``); the manifest's counts come from its ``real``
record (objects, captures), not from a generation config.  Everything else (format,
checksums, depth, masks, unit vectors, frames) is checked as for generated data.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from .camera import R_CAMERA_TO_OPTICAL, CameraConfig
from .errors import DataFormatError, UserError
from .format import (FIELDS, K_DATASET, MANIFEST_NAME, MASK_BACKGROUND, MASK_FIRST_PART, R_DATASET, ROOT_ATTRS, TMP_SUFFIX,
                     check_h5_layout, check_version, find_split_dirs, resolve_shape, sha256_file, shard_name)
from .format.discovery import SHARD_GLOB
from .rotations import quat_to_matrix
from .context_labels import context_mask_codes, occlusion_problems
from .viewpoint import is_head_mount

log = logging.getLogger(__name__)

#: Allowed | |v| - 1 | of stored unit vectors and quaternions.  They are computed in
#: float64 and stored as float32 (relative rounding 6e-8 per component), so a correct
#: file is within ~2e-7; 1e-4 leaves a wide margin while catching any real scaling error.
UNIT_TOL = 1e-4
#: A realistic split's sizes lie within this many jitter standard deviations of a standard
#: size of some size class (the chance of a sample beyond it is ~2e-9 per dimension).
SHAPE_SD = 6.0
#: Allowed excess (rad or m) of a stored float32 value over a float64 table limit: half an
#: ulp of float32 at 16 is 1e-6; 1e-5 covers every range in the built-in tables.
LIMIT_TOL = 1e-5
#: Allowed angle (rad) between the z axis of ``axis_pose``'s quaternion and
#: ``axis_direction`` (float32 quaternion components: ~1e-7 rad expected).
FRAME_TOL_RAD = 1e-3
#: Relative tolerance when comparing the stored intrinsics with the camera config's K.
K_RTOL = 1e-9
#: Images converted to float64 at a time for the depth checks (128 x 192 x 108 x 8 B = 21 MB).
DEPTH_BLOCK = 128
#: Largest number of problems listed per shard before the rest are summarised.
MAX_PROBLEMS_PER_FILE = 20
#: Datasets whose rows describe the object (identical for all of its images).
PER_OBJECT_FIELDS = ("axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw", "geometry")
#: Manifest keys the generator writes and the checks below read.
MANIFEST_KEYS = ("format_version", "class_name", "split", "seed", "complete", "n_objects", "n_images",
                 "n_shards_expected", "config", "shards")
SHARD_RECORD_KEYS = ("file", "n_images", "bytes", "sha256", "object_start", "object_stop")


@dataclass(frozen=True)
class Problem:
    """One finding: ``where`` is a file name inside the split folder."""

    where: str
    message: str
    warning: bool = False

    def __str__(self) -> str:
        return f"{self.where}: {'warning: ' if self.warning else ''}{self.message}"


@dataclass
class SplitReport:
    """Result of verifying one split folder."""

    split_dir: Path
    problems: list[Problem] = field(default_factory=list)
    n_shards: int = 0
    n_images: int = 0
    content_checked: bool = True

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if not p.warning]

    @property
    def ok(self) -> bool:
        return not self.errors

    def to_dict(self) -> dict:
        return {"split_dir": str(self.split_dir), "ok": self.ok, "shards": self.n_shards, "images": self.n_images,
                "content_checked": self.content_checked,
                "problems": [{"file": p.where, "message": p.message, "warning": p.warning} for p in self.problems]}


# --------------------------------------------------------------------------------------
# Discovery
# --------------------------------------------------------------------------------------

def find_splits(path: str | Path) -> list[Path]:
    """Split folders at ``path`` or one/two levels below it (``<class>/<split>``).

    A folder counts if it holds a manifest or shard files, so a split whose manifest was
    lost is still found (and reported).  Nothing found is a :class:`UserError`.
    """
    return find_split_dirs(path, unlisted_shards=True)


# --------------------------------------------------------------------------------------
# Manifest
# --------------------------------------------------------------------------------------

def _load_manifest(split_dir: Path) -> tuple[dict | None, list[Problem]]:
    path = split_dir / MANIFEST_NAME
    if not path.is_file():
        return None, [Problem(MANIFEST_NAME, "missing (not a complete generated split; shards checked without it)")]
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        return None, [Problem(MANIFEST_NAME, f"corrupt JSON ({_one_line(exc)})")]
    except OSError as exc:
        return None, [Problem(MANIFEST_NAME, f"cannot read ({exc.strerror or exc})")]
    if not isinstance(manifest, dict):
        return None, [Problem(MANIFEST_NAME, "corrupt: top level is not a JSON object")]
    missing = [k for k in MANIFEST_KEYS if k not in manifest]
    if missing:
        return None, [Problem(MANIFEST_NAME, f"missing keys {missing}")]
    try:
        check_version(str(manifest["format_version"]))
    except DataFormatError as exc:
        return None, [Problem(MANIFEST_NAME, str(exc))]
    if not isinstance(manifest["shards"], list) or not all(_valid_record(r) for r in manifest["shards"]):
        return None, [Problem(MANIFEST_NAME, f"corrupt shard list (each entry needs {list(SHARD_RECORD_KEYS)}: "
                                             f"a plain file name, integer counts and a hex sha256)")]
    bad = [k for k in ("n_images", "n_objects", "n_shards_expected", "seed") if not _is_int(manifest[k])]
    if bad or not isinstance(manifest["config"], dict):
        return None, [Problem(MANIFEST_NAME, f"corrupt: {bad or 'config'} must be {'integers' if bad else 'an object'}")]
    return manifest, []


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _valid_record(r) -> bool:
    """A manifest shard record with the generator's keys and types."""
    return (isinstance(r, dict) and all(k in r for k in SHARD_RECORD_KEYS)
            and isinstance(r["file"], str) and r["file"] == Path(r["file"]).name and r["file"] not in ("", ".", "..")
            and isinstance(r["sha256"], str)
            and all(_is_int(r[k]) for k in ("n_images", "bytes", "object_start", "object_stop")))


def _manifest_config(manifest: dict):
    """The manifest's :class:`~articulated_dataset.format.SplitConfig` (checked against the
    class's registry entry for a registered class), or a problem message."""
    from .format import SplitConfig
    from .registry import check_table, get_class

    try:
        config = SplitConfig.from_dict(manifest["config"])
        if config.third_party is None:
            check_table(get_class(config.class_name), config.table)
        return config, None
    except UserError as exc:
        return None, f"invalid generation config ({exc})"
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        return None, f"corrupt generation config ({type(exc).__name__}: {_one_line(exc)})"


def _check_manifest_counts(manifest: dict, config) -> list[Problem]:
    out = []
    records = manifest["shards"]
    files = [r["file"] for r in records]
    if len(set(files)) != len(files):
        out.append(Problem(MANIFEST_NAME, "shard list names a file twice"))
    n_images = sum(int(r["n_images"]) for r in records)
    n_objects = sum(int(r["object_stop"]) - int(r["object_start"]) for r in records)
    if manifest["n_images"] != n_images:
        out.append(Problem(MANIFEST_NAME, f"n_images is {manifest['n_images']} but the shards hold {n_images}"))
    if manifest["n_objects"] != n_objects:
        out.append(Problem(MANIFEST_NAME, f"n_objects is {manifest['n_objects']} but the shards hold {n_objects}"))
    for key in ("class_name", "split", "seed"):
        if config is not None and manifest[key] != getattr(config, key):
            out.append(Problem(MANIFEST_NAME, f"{key} {manifest[key]!r} differs from its config's {getattr(config, key)!r}"))
    if config is None:
        return out
    if manifest["n_shards_expected"] != config.n_shards:
        out.append(Problem(MANIFEST_NAME, f"n_shards_expected is {manifest['n_shards_expected']}, config gives {config.n_shards}"))
    for r in records:
        try:
            index = int(Path(r["file"]).stem.split("-")[1])
        except (IndexError, ValueError):
            out.append(Problem(MANIFEST_NAME, f"unexpected shard file name {r['file']!r}"))
            continue
        objects = config.shard_objects(index)
        if r["file"] != shard_name(index) or (r["object_start"], r["object_stop"]) != (objects.start, objects.stop):
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: objects [{r['object_start']}, {r['object_stop']}) "
                                              f"do not match the config's [{objects.start}, {objects.stop})"))
        elif r["n_images"] != len(objects) * config.images_per_object:
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: {r['n_images']} images, config gives "
                                              f"{len(objects) * config.images_per_object}"))
    complete = len(records) == config.n_shards and n_objects == config.n_objects
    if not complete:
        out.append(Problem(MANIFEST_NAME, f"incomplete split: {len(records)} of {config.n_shards} shards "
                                          f"({n_objects} of {config.n_objects} objects); finish it with the same "
                                          f"'artdata generate' command plus --resume"))
    elif manifest["complete"] is not True:
        out.append(Problem(MANIFEST_NAME, "every shard is present but 'complete' is not true"))
    return out


def _check_real_manifest(manifest: dict, config) -> tuple[list[Problem], dict]:
    """Counts of an ingested real split from its ``real`` record (objects, captures), and the
    captures each shard should hold (``{file: [names]}``; empty when the record is unusable)."""
    out = []
    rec = manifest["real"]
    if not isinstance(rec, dict):
        return [Problem(MANIFEST_NAME, "corrupt: 'real' must be an object with 'objects' and 'captures'")], {}
    objects, captures = rec.get("objects"), rec.get("captures")
    if not (isinstance(objects, list) and isinstance(captures, list)
            and all(isinstance(x, str) and x for x in objects + captures)):
        return [Problem(MANIFEST_NAME, "corrupt: real.objects and real.captures must be lists of names")], {}
    records = manifest["shards"]
    files = [r["file"] for r in records]
    if len(set(files)) != len(files):
        out.append(Problem(MANIFEST_NAME, "shard list names a file twice"))
    if len(set(captures)) != len(captures):
        out.append(Problem(MANIFEST_NAME, "real.captures names a capture twice"))
    if len(set(objects)) != len(objects):
        out.append(Problem(MANIFEST_NAME, "real.objects names an object twice"))
    n_images = sum(int(r["n_images"]) for r in records)
    for key, want, what in (("n_images", n_images, "the shards hold"), ("n_images", len(captures), "real.captures lists"),
                            ("n_objects", len(objects), "real.objects lists"),
                            ("n_shards_expected", len(records), "the shard list has")):
        if manifest[key] != want:
            out.append(Problem(MANIFEST_NAME, f"{key} is {manifest[key]} but {what} {want}"))
    for key in ("class_name", "split", "seed"):
        if config is not None and manifest[key] != getattr(config, key):
            out.append(Problem(MANIFEST_NAME, f"{key} {manifest[key]!r} differs from its config's {getattr(config, key)!r}"))
    captures_of, offset = {}, 0
    for k, r in enumerate(records):
        if r["file"] != shard_name(k):
            out.append(Problem(MANIFEST_NAME, f"shard {k} is {r['file']!r}, expected {shard_name(k)}"))
        if not 0 <= r["object_start"] < r["object_stop"] <= len(objects):
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: objects [{r['object_start']}, {r['object_stop']}) "
                                              f"outside the {len(objects)} objects of real.objects"))
        captures_of[r["file"]] = captures[offset:offset + int(r["n_images"])]
        offset += int(r["n_images"])
    if manifest["complete"] is not True:
        out.append(Problem(MANIFEST_NAME, "'complete' is not true (an ingest that did not finish)"))
    return out, (captures_of if offset == len(captures) else {})


# --------------------------------------------------------------------------------------
# Shards
# --------------------------------------------------------------------------------------

@dataclass
class ShardExpectation:
    """What the manifest says about one shard (all optional: None = unknown)."""

    n_images: int | None = None
    n_bytes: int | None = None
    sha256: str | None = None
    object_start: int | None = None
    object_stop: int | None = None
    class_name: str | None = None
    split: str | None = None
    seed: int | None = None
    camera: CameraConfig | None = None
    real: bool | None = None  # the manifest says the split holds ingested real captures
    capture_names: list | None = None  # real: the manifest's captures of this shard, in order


@dataclass
class ShardResult:
    problems: list[str] = field(default_factory=list)
    n_images: int = 0
    sample_ids: np.ndarray | None = None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__


def _attr(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    return v


def check_shard(path: str | Path, expect: ShardExpectation | None = None, *, content: bool = True) -> ShardResult:
    """Check one shard file; problems are one-line messages (without the file name)."""
    path = Path(path)
    expect = expect or ShardExpectation()
    res = ShardResult()
    p = res.problems
    if not path.is_file():
        p.append("listed in the manifest but missing")
        return res
    size = path.stat().st_size
    if expect.n_bytes is not None and size != expect.n_bytes:
        p.append(f"size {size} bytes differs from the manifest's {expect.n_bytes} (truncated or replaced?)")
    if expect.sha256 is not None:
        digest = sha256_file(path)
        if digest != expect.sha256:
            p.append(f"sha256 {digest[:12]}... differs from the manifest's {expect.sha256[:12]}... (file modified or corrupted)")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        p.append(f"not a readable HDF5 file ({_one_line(exc)})")
        return res
    try:
        try:  # content stored elsewhere (external storage, links, virtual datasets) is never read
            check_h5_layout(f, path)
        except UserError as exc:
            p.append(str(exc).replace(f"{path}: ", "", 1))
            return res
        _check_open_shard(f, expect, res, content)
    finally:
        try:
            f.close()
        except OSError:  # closing a damaged file can fail after everything was reported
            pass
    return res


def _check_open_shard(f: h5py.File, expect: ShardExpectation, res: ShardResult, content: bool) -> None:
    p = res.problems
    try:
        attrs = {k: _attr(f.attrs[k]) for k in f.attrs}
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as exc:  # unreadable/unsupported attribute
        p.append(f"cannot read root attributes ({_one_line(exc)})")
        return
    if "format_version" not in attrs:
        p.append("not an articulated_dataset shard (no format_version attribute)")
        return
    try:
        check_version(str(attrs["format_version"]))
    except DataFormatError as exc:
        p.append(str(exc))
        return
    missing = [k for k in ROOT_ATTRS if k not in attrs]
    if missing:
        p.append(f"missing root attributes {missing}")
    try:
        J = int(attrs["n_joints"])
        H, W = int(attrs["image_height"]), int(attrs["image_width"])
        ipo = int(attrs["images_per_object"])
        start, stop = int(attrs["object_start"]), int(attrs["object_stop"])
    except (KeyError, TypeError, ValueError):
        p.append("root attributes n_joints, image_height, image_width, images_per_object, object_start, "
                 "object_stop must all be integers; cannot check the datasets")
        return
    real = _is_real(attrs)
    names = None
    if expect.real is not None and real != expect.real:
        p.append("attribute real = 1 but the manifest has no 'real' record" if real
                 else "the manifest describes ingested real data but the shard has no attribute real = 1")
    if real:
        names, msg = _capture_names(attrs)
        if msg:
            p.append(msg)
            return
        N = len(names)
        if expect.capture_names is not None and names != expect.capture_names:
            p.append("attribute capture_names differs from the manifest's captures of this shard")
    else:
        N = (stop - start) * ipo
    res.n_images = N
    for key, want in (("class_name", expect.class_name), ("split", expect.split), ("seed", expect.seed),
                      ("object_start", expect.object_start), ("object_stop", expect.object_stop)):
        if want is not None and attrs.get(key) != want:
            p.append(f"attribute {key} = {attrs.get(key)!r}, manifest says {want!r}")
    if expect.n_images is not None and N != expect.n_images:
        p.append(f"holds {N} images by its attributes, manifest says {expect.n_images}")
    if expect.camera is not None and (expect.camera.width_px, expect.camera.height_px) != (W, H):
        p.append(f"image size {W}x{H} differs from the manifest's {expect.camera.width_px}x{expect.camera.height_px}")
    _check_registry(attrs, J, p)

    # Structure: every schema dataset with its dtype and shape.
    good = []
    for fd in FIELDS:
        try:
            ds = f[fd.name] if fd.name in f else None
        except (OSError, KeyError, RuntimeError, ValueError) as exc:
            p.append(f"cannot open dataset {fd.name!r} ({_one_line(exc)})")
            continue
        if ds is None:
            p.append(f"missing dataset {fd.name!r}")
            continue
        if not isinstance(ds, h5py.Dataset):
            p.append(f"{fd.name!r} is a group, expected a dataset")
            continue
        shape = resolve_shape(fd.shape, N=N, J=J, H=H, W=W)
        if tuple(ds.shape) != shape:
            p.append(f"dataset {fd.name!r} has shape {tuple(ds.shape)}, expected {shape}")
        elif np.dtype(ds.dtype) != np.dtype(fd.dtype):
            p.append(f"dataset {fd.name!r} has dtype {ds.dtype}, expected {fd.dtype}")
        else:
            good.append(fd.name)
    _check_camera(f, attrs, W, H, p, real)
    if not content:
        return

    arrays = {}
    for name in good:
        try:
            arrays[name] = f[name][()]
        except (OSError, RuntimeError, ValueError) as exc:
            p.append(f"cannot read dataset {name!r} ({_one_line(exc)})")
    table, msg = _table(attrs)
    if msg:
        p.append(msg)
    _check_content(arrays, attrs, table, J=J, ipo=ipo, start=start, problems=p, capture_names=names)
    p.extend(occlusion_problems(f, attrs, arrays, J=J, N=N, H=H, W=W))  # format 1.1 (--scene, --occluders)
    if "sample_id" in arrays:
        res.sample_ids = arrays["sample_id"]


def _is_real(attrs: dict) -> bool:
    """A shard of ingested real captures (``real = 1``)."""
    v = attrs.get("real", 0)
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and int(v) == 1


def _capture_names(attrs: dict) -> tuple[list | None, str | None]:
    """The ``capture_names`` attribute of a real shard (a JSON list of unique names), or a problem."""
    try:
        names = json.loads(attrs["capture_names"])
    except KeyError:
        return None, "real shard without attribute capture_names; cannot check the datasets"
    except (json.JSONDecodeError, TypeError):
        return None, "attribute capture_names is not a JSON list; cannot check the datasets"
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        return None, "attribute capture_names must be a non-empty JSON list of names; cannot check the datasets"
    if len(set(names)) != len(names):
        return None, "attribute capture_names names a capture twice"
    return names, None


def _check_registry(attrs: dict, J: int, p: list) -> None:
    from .registry import get_class

    try:
        obj_class = get_class(str(attrs.get("class_name")))
    except UserError:
        return  # a class from another package: nothing to compare with
    if J != obj_class.n_joints:
        p.append(f"n_joints = {J}, class {obj_class.name} has {obj_class.n_joints}")
    try:
        types = tuple(json.loads(attrs.get("joint_types", "[]")))
    except (json.JSONDecodeError, TypeError):
        p.append("attribute joint_types is not a JSON list")
        return
    if types != obj_class.joint_types:
        p.append(f"joint_types {list(types)} differ from class {obj_class.name}'s {list(obj_class.joint_types)}")


def _check_camera(f: h5py.File, attrs: dict, W: int, H: int, p: list, real: bool = False) -> None:
    try:
        for name in (K_DATASET, R_DATASET):
            if name not in f or not isinstance(f[name], h5py.Dataset) or f[name].shape != (3, 3):
                p.append(f"missing or malformed dataset {name!r} (expected 3x3)")
                return
        K, R = f[K_DATASET][()].astype(np.float64), f[R_DATASET][()].astype(np.float64)
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as exc:
        p.append(f"cannot read {K_DATASET}/{R_DATASET} ({_one_line(exc)})")
        return
    if not np.array_equal(R, R_CAMERA_TO_OPTICAL):
        p.append(f"{R_DATASET} differs from the package's camera-to-optical rotation")
    if real:  # the training camera, or a crop's intrinsics (``--fit crop``): a pinhole K agreeing with vfov_deg
        _check_real_K(K, attrs, H, p)
        return
    try:
        preset = attrs.get("intrinsics")  # present only for generate --intrinsics
        want = CameraConfig(W, H, float(attrs["vfov_deg"]), intrinsics=None if preset is None else str(preset)).K
    except (KeyError, TypeError, ValueError):
        p.append("cannot rebuild K: attributes image_width/image_height/vfov_deg/intrinsics invalid")
        return
    if not np.allclose(K, want, rtol=K_RTOL, atol=0.0):
        what = f"intrinsics preset {preset}" if preset is not None else f"vfov {attrs['vfov_deg']} deg"
        p.append(f"{K_DATASET} does not match image size {W}x{H} and {what}")


def _check_real_K(K: np.ndarray, attrs: dict, H: int, p: list) -> None:
    from .real.write import vfov_deg_of

    pinhole = (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and K[0, 1] == 0 and K[1, 0] == 0
               and np.array_equal(K[2], [0.0, 0.0, 1.0]))
    if not pinhole:
        p.append(f"{K_DATASET} is not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
        return
    try:
        vfov = float(attrs["vfov_deg"])
    except (KeyError, TypeError, ValueError):
        p.append("attribute vfov_deg missing or not a number")
        return
    if not math.isclose(vfov, vfov_deg_of(K, H), rel_tol=K_RTOL):
        p.append(f"{K_DATASET} gives a vertical field of view of {vfov_deg_of(K, H):.6g} deg, attribute vfov_deg "
                 f"says {vfov:.6g}")


def _table(attrs: dict):
    from .tables import SamplingTable

    try:
        return SamplingTable.from_dict(json.loads(attrs["sampling_table"])), None
    except KeyError:
        return None, None  # already reported as a missing attribute
    except (json.JSONDecodeError, TypeError, ValueError, AttributeError, UserError) as exc:
        return None, f"attribute sampling_table is not a valid table ({_one_line(exc)})"


def _where(bad: np.ndarray) -> str:
    """'k of N images (first: image i)' for a boolean per-image array."""
    idx = np.flatnonzero(bad)
    return f"{idx.size} of {bad.size} images (first: image {idx[0]})"


def _per_image(bad: np.ndarray) -> np.ndarray:
    return bad.reshape(bad.shape[0], -1).any(axis=1)


def quat_rotate_z(quat_wxyz: np.ndarray) -> np.ndarray:
    """z axis of the rotation of unit quaternions (..., 4) (w, x, y, z): the third column of R,
    ``(2(xz + wy), 2(yz - wx), 1 - 2(x^2 + y^2))``."""
    w, x, y, z = (quat_wxyz[..., i] for i in range(4))
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def _check_content(a: dict, attrs: dict, table, *, J: int, ipo: int, start: int, problems: list,
                   capture_names: list | None = None) -> None:
    """Label invariants; ``capture_names`` (real shards only) switches to the real rules."""
    from .real.ground_truth import REAL_LABEL_FIELDS

    p = problems
    real = capture_names is not None
    # labels are small: check them in float64; depth is checked in blocks of images
    f64 = {k: v.astype(np.float64) for k, v in a.items() if v.dtype.kind == "f" and k != "depth"}
    if real:
        _check_real_labels(f64, attrs, table, J, p)
    for name, v in f64.items():
        if real and name in REAL_LABEL_FIELDS:
            continue  # NaN = not available (infinite values reported above); NaN compares False below
        bad = _per_image(~np.isfinite(v))
        if bad.any():
            p.append(f"{name}: non-finite values in {_where(bad)}")
            f64[name] = np.nan_to_num(v)  # keep checking the other invariants
    noise_free = attrs.get("noise_model", "none") == "none"
    if "depth" in a:
        try:
            quantum = float(attrs.get("depth_quantum_m", 0) or 0)
        except (TypeError, ValueError):
            quantum = 0.0
        _check_depth(a["depth"], a.get("mask") if noise_free else None, quantum, p)
    if "mask" in a:
        m = a["mask"]
        top = MASK_FIRST_PART + J - 1
        bad = _per_image((m > top) & ~np.isin(m, context_mask_codes(attrs)))  # 254/255: occluders/scene (format 1.1)
        if bad.any():
            p.append(f"mask: values above {top} (1 + J) in {_where(bad)}")
        if "visible_pixels" in a:
            n, n_values = m.shape[0], max(int(m.max(initial=0)) + 1, MASK_FIRST_PART + J)
            # one bincount over (image, value) pairs: counts[i, v] = pixels of value v in image i
            flat = (np.arange(n, dtype=np.int64)[:, None] * n_values + m.reshape(n, -1)).ravel()
            counts = np.bincount(flat, minlength=n * n_values).reshape(n, n_values)[:, 1:MASK_FIRST_PART + J]
            bad = _per_image(counts != a["visible_pixels"])
            if bad.any():
                p.append(f"visible_pixels: differ from the mask's pixel counts in {_where(bad)}")
    if "visible_pixels" in a and not int(attrs.get("mean_object", 0)) and "min_part_pixels" in attrs and J:
        bad = _per_image(a["visible_pixels"][:, 1:] < int(attrs["min_part_pixels"]))
        if bad.any():
            p.append(f"visible_pixels: a moving part covers fewer than min_part_pixels = {attrs['min_part_pixels']} "
                     f"px in {_where(bad)}")
    if "axis_direction" in f64:
        bad = _per_image(np.abs(np.linalg.norm(f64["axis_direction"], axis=-1) - 1) > UNIT_TOL)
        if bad.any():
            err = np.abs(np.linalg.norm(f64["axis_direction"], axis=-1) - 1).max()
            p.append(f"axis_direction: not unit length in {_where(bad)} (max | |a| - 1 | = {err:.3g})")
    if "axis_pose" in f64:
        quat = f64["axis_pose"][..., 3:]
        bad = _per_image(np.abs(np.linalg.norm(quat, axis=-1) - 1) > UNIT_TOL)
        if bad.any():
            p.append(f"axis_pose: quaternion not normalised in {_where(bad)}")
        if "axis_origin" in f64:
            bad = _per_image(~_same(f64["axis_pose"][..., :3], f64["axis_origin"]))
            if bad.any():
                p.append(f"axis_pose: position differs from axis_origin in {_where(bad)}")
        if "axis_direction" in f64:
            qn = quat / np.maximum(np.linalg.norm(quat, axis=-1, keepdims=True), 1e-12)
            cos = np.sum(quat_rotate_z(qn) * f64["axis_direction"], axis=-1) / np.maximum(
                np.linalg.norm(f64["axis_direction"], axis=-1), 1e-12)
            bad = _per_image(cos < math.cos(FRAME_TOL_RAD))
            if bad.any():
                p.append(f"axis_pose: frame z axis differs from axis_direction in {_where(bad)}")
    if "object_pose" in f64:
        quat = f64["object_pose"][:, 3:]
        bad = np.abs(np.linalg.norm(quat, axis=-1) - 1) > UNIT_TOL
        if bad.any():
            p.append(f"object_pose: quaternion not normalised in {_where(bad)}")
        if "object_yaw" in f64:
            if is_head_mount(attrs):  # tilted: the heading of the object's x axis (labels.py)
                R = quat_to_matrix(quat)
                yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
            else:
                yaw = 2 * np.arctan2(quat[:, 3], quat[:, 0])
            diff = np.abs(np.angle(np.exp(1j * (yaw - f64["object_yaw"]))))
            bad = diff > FRAME_TOL_RAD
            if bad.any():
                p.append(f"object_yaw: differs from the yaw of object_pose in {_where(bad)}")
    if table is not None and not real:  # real: the class's joint range in _check_real_labels; any pose
        _check_limits(f64, table, J, attrs, p)
    if "geometry" in f64:
        g = f64["geometry"]
        bad = _per_image(g[:, :3] <= 0)
        if bad.any():
            p.append(f"geometry: non-positive body dimensions in {_where(bad)}")
        bad = ~np.isin(g[:, 3], (0.0, 1.0)) & ~np.isnan(g[:, 3])  # NaN: real data without geometry
        if bad.any():
            p.append(f"geometry: chirality not 0 or 1 in {_where(bad)}")
    if real:
        _check_real_order(a, attrs, capture_names, problems=p)
    else:
        _check_order(a, attrs, J=J, ipo=ipo, start=start, problems=p)


def _same(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Elementwise equality with NaN equal to NaN (real labels: both not available)."""
    return (x == y) | (np.isnan(x) & np.isnan(y))


def _check_real_labels(f64: dict, attrs: dict, table, J: int, p: list) -> None:
    """:func:`articulated_dataset.real.ground_truth.real_label_problems` on the shard's label arrays."""
    from .real.ground_truth import REAL_LABEL_FIELDS, real_label_problems

    if not all(k in f64 for k in REAL_LABEL_FIELDS):
        return  # already reported as missing or malformed datasets
    n = f64["q"].shape[0]
    gt = attrs.get("has_ground_truth")
    gt = None if gt is None else np.asarray(gt).reshape(-1)
    if gt is None or gt.shape != (n,) or not np.isin(gt, (0, 1)).all():
        p.append(f"attribute has_ground_truth must hold {n} values 0 or 1")
        gt = None
    from .registry import get_class

    try:
        obj_class = get_class(str(attrs.get("class_name")))
        types, ranges = obj_class.joint_types, obj_class.table.q
    except UserError:  # a class from another package: the shard's own table and types
        types = tuple(_json_list(attrs.get("joint_types")))
        ranges = table.q if table is not None else ()
    if len(types) != J or len(ranges) != J:
        types, ranges = (), ()
    for message, bad in real_label_problems({k: f64[k] for k in REAL_LABEL_FIELDS}, types, ranges, gt):
        p.append(f"{message} in {_where(bad)}")


def _json_list(text) -> list:
    try:
        v = json.loads(text)
    except (json.JSONDecodeError, TypeError):
        return []
    return v if isinstance(v, list) else []


def _check_class(a: dict, attrs: dict, p: list) -> str:
    """Every image's ``class`` equals the shard's ``class_name`` (returned)."""
    cls = str(attrs.get("class_name", ""))
    if "class" in a:
        bad = a["class"] != cls.encode("ascii", "replace")
        if bad.any():
            p.append(f"class: differs from the shard's class {cls!r} in {_where(bad)}")
    return cls


def _check_real_order(a: dict, attrs: dict, capture_names: list, *, problems: list) -> None:
    """Real shards: objects and images numbered by capture; ``sample_id`` from the capture names."""
    from .real.write import real_sample_id

    p = problems
    n = len(capture_names)
    try:
        start, stop = int(attrs["object_start"]), int(attrs["object_stop"])
    except (KeyError, TypeError, ValueError):
        return  # reported with the root attributes
    if "object_index" in a:
        bad = (a["object_index"] < start) | (a["object_index"] >= stop)
        if bad.any():
            p.append(f"object_index: outside the shard's objects [{start}, {stop}) in {_where(bad)}")
    if "image_index" in a:
        bad = a["image_index"] < 0
        if bad.any():
            p.append(f"image_index: negative in {_where(bad)}")
    if "object_index" in a and "image_index" in a:
        pairs = a["object_index"].astype(np.int64) * (1 << 32) + a["image_index"].astype(np.int64)
        uniq, counts = np.unique(pairs, return_counts=True)
        if (counts > 1).any():
            p.append(f"(object_index, image_index): {int((counts > 1).sum())} pairs repeated within the shard")
    cls = _check_class(a, attrs, p)
    if "sample_id" in a and a["sample_id"].shape == (n,):
        split = str(attrs.get("split", ""))
        want = np.array([real_sample_id(cls, split, name) for name in capture_names], np.int64)
        bad = a["sample_id"] != want
        if bad.any():
            p.append(f"sample_id: differs from real_sample_id(class, split, capture name) in {_where(bad)}")


def _check_depth(depth: np.ndarray, mask: np.ndarray | None, quantum_m: float, p: list) -> None:
    """Depth invariants, :data:`DEPTH_BLOCK` images at a time (bounded memory): finite,
    ``>= 0``, integer multiples of ``quantum_m`` (if > 0) and, given the mask (noise-free
    data), ``depth > 0`` exactly where ``mask > 0``."""
    n = depth.shape[0]
    bad = {"finite": np.zeros(n, bool), "negative": np.zeros(n, bool), "quantum": np.zeros(n, bool),
           "mask": np.zeros(n, bool)}
    for s in range(0, n, DEPTH_BLOCK):
        d = depth[s:s + DEPTH_BLOCK].astype(np.float64)
        finite = np.isfinite(d)
        bad["finite"][s:s + DEPTH_BLOCK] = _per_image(~finite)
        d = np.where(finite, d, 0.0)
        bad["negative"][s:s + DEPTH_BLOCK] = _per_image(d < 0)
        if quantum_m > 0:
            k = d / quantum_m
            bad["quantum"][s:s + DEPTH_BLOCK] = _per_image(k != np.round(k))
        if mask is not None:
            bad["mask"][s:s + DEPTH_BLOCK] = _per_image((mask[s:s + DEPTH_BLOCK] != MASK_BACKGROUND) != (d > 0))
    messages = {"finite": "depth: non-finite values in {}", "negative": "depth: negative values in {}",
                "quantum": f"depth: values not multiples of depth_quantum_m = {quantum_m:g} m in {{}}",
                "mask": "mask/depth: background pixels (mask 0) and pixels without depth differ in {}"}
    for key, flags in bad.items():
        if flags.any():
            p.append(messages[key].format(_where(flags)))


def _check_limits(f64: dict, table, J: int, attrs: dict, p: list) -> None:
    if "q" in f64 and len(table.q) == J:
        lo = np.array([r[0] for r in table.q]) - LIMIT_TOL
        hi = np.array([r[1] for r in table.q]) + LIMIT_TOL
        for j in range(J):
            bad = (f64["q"][:, j] < lo[j]) | (f64["q"][:, j] > hi[j])
            if bad.any():
                p.append(f"q[{j}]: outside the table's limits [{table.q[j][0]:.6g}, {table.q[j][1]:.6g}] in {_where(bad)}")
    elif "q" in f64:
        p.append(f"sampling_table has {len(table.q)} q ranges for {J} joints")
    if "geometry" in f64 and table.shape is not None:
        _check_shape(f64["geometry"], table, p, mean=bool(int(attrs.get("mean_object", 0))))
    if "object_pose" in f64 and is_head_mount(attrs):
        _check_head_limits(f64["object_pose"], table, p)
        return
    if "object_pose" in f64:
        for axis, key in enumerate(("x_m", "y_m", "z_m")):
            lo, hi = table.pose[key]
            v = f64["object_pose"][:, axis]
            bad = (v < lo - LIMIT_TOL) | (v > hi + LIMIT_TOL)
            if bad.any():
                p.append(f"object_pose: {key[0]} outside the table's [{lo:g}, {hi:g}] m in {_where(bad)}")
    if "object_yaw" in f64:
        lo, hi = table.pose["yaw_rad"]
        v = f64["object_yaw"]
        bad = (v < lo - LIMIT_TOL) | (v > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_yaw: outside the table's [{lo:.6g}, {hi:.6g}] rad in {_where(bad)}")


def _check_shape(geometry: np.ndarray, table, p: list, *, mean: bool = False) -> None:
    """A joint size table (``--table realistic``): every (depth, width, height) within the
    table's geometry bounds and explained by one of its size classes
    (:meth:`~articulated_dataset.tables.ShapeMixture.component_of`); a mean object's sizes
    (the mixture's mean, between its size classes) are its mean."""
    from .tables import GEOMETRY_KEYS

    if geometry.ndim != 2 or geometry.shape[1] < len(GEOMETRY_KEYS):
        return  # the shape check of the schema reports it
    sizes = geometry[:, :len(GEOMETRY_KEYS)]
    for axis, key in enumerate(GEOMETRY_KEYS):
        lo, hi = table.geometry[key]
        bad = (sizes[:, axis] < lo - LIMIT_TOL) | (sizes[:, axis] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"geometry: {key} outside the table's [{lo:g}, {hi:g}] m in {_where(bad)}")
    if mean:
        lo, hi = (np.array([table.geometry[k][i] for k in GEOMETRY_KEYS]) for i in (0, 1))
        bad = np.any(np.abs(sizes - np.clip(table.shape.mean_m(), lo, hi)) > LIMIT_TOL, axis=1)
        if bad.any():
            p.append(f"geometry: a mean object's sizes differ from the table's mean sizes in {_where(bad)}")
        return
    unique, inverse = np.unique(sizes, axis=0, return_inverse=True)  # one row per object
    explained = np.array([table.shape.component_of(x, n_sd=SHAPE_SD, tol_m=LIMIT_TOL) is not None for x in unique])
    bad = ~explained[inverse.reshape(-1)]
    if bad.any():
        p.append(f"geometry: sizes no size class of the table explains (beyond {SHAPE_SD:g} sd of every class) in {_where(bad)}")


def _check_head_limits(object_pose: np.ndarray, table, p: list) -> None:
    """A head camera's images: the camera's pitch and roll (read from the object's up axis)
    within the head ranges, and the object's pose in the level frame within the table (its
    height relative to the camera also moves by up to half the camera-height range)."""
    from .viewpoint import HEAD_HEIGHT_M, HEAD_PITCH_DEG, HEAD_ROLL_DEG, level_pose_from_camera

    level = level_pose_from_camera(object_pose)
    for key, (lo, hi) in (("pitch_rad", HEAD_PITCH_DEG), ("roll_rad", HEAD_ROLL_DEG)):
        lo, hi = math.radians(lo), math.radians(hi)
        bad = (level[key] < lo - LIMIT_TOL) | (level[key] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_pose: head camera {key[:-4]} outside [{math.degrees(lo):g}, {math.degrees(hi):g}] deg "
                     f"in {_where(bad)}")
    rise = 0.5 * (HEAD_HEIGHT_M[1] - HEAD_HEIGHT_M[0])
    for key in ("x_m", "y_m", "z_m", "yaw_rad"):
        lo, hi = table.pose[key]
        if key == "z_m":
            lo, hi = lo - rise, hi + rise
        bad = (level[key] < lo - LIMIT_TOL) | (level[key] > hi + LIMIT_TOL)
        if bad.any():
            p.append(f"object_pose: level-frame {key} outside the table's [{lo:.6g}, {hi:.6g}] in {_where(bad)}")


def _check_order(a: dict, attrs: dict, *, J: int, ipo: int, start: int, problems: list) -> None:
    from .sampling import sample_id

    p = problems
    n = next(iter(a.values())).shape[0] if a else 0
    obj = start + np.arange(n) // max(ipo, 1)
    img = np.arange(n) % max(ipo, 1)
    if "object_index" in a:
        bad = a["object_index"] != obj
        if bad.any():
            p.append(f"object_index: not in generation order in {_where(bad)}")
    if "image_index" in a:
        bad = a["image_index"] != img
        if bad.any():
            p.append(f"image_index: not in generation order in {_where(bad)}")
    # A head camera moves per image: only the object's own geometry is the same in all its images.
    for name in (("geometry",) if is_head_mount(attrs) else PER_OBJECT_FIELDS):
        if name not in a or n == 0:
            continue
        v = a[name].reshape(n, -1)
        first = v[(np.arange(n) // max(ipo, 1)) * max(ipo, 1)]
        bad = ~np.all((v == first) | (np.isnan(v) & np.isnan(first)) if v.dtype.kind == "f" else v == first, axis=1)
        if bad.any():
            p.append(f"{name}: differs between images of the same object in {_where(bad)}")
    cls = _check_class(a, attrs, p)
    if "sample_id" in a:
        ids = a["sample_id"]
        split, seed = str(attrs.get("split", "")), attrs.get("seed")
        if isinstance(seed, int) and seed >= 0:
            want = np.array([sample_id(cls, split, seed, int(o), int(i)) for o, i in zip(obj, img)], np.int64)
            bad = ids != want
            if bad.any():
                p.append(f"sample_id: differs from sample_id(class, split, seed, object, image) in {_where(bad)}")
        uniq, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            p.append(f"sample_id: {int((counts > 1).sum())} ids repeated within the shard (e.g. {int(uniq[counts > 1][0])})")


# --------------------------------------------------------------------------------------
# Splits
# --------------------------------------------------------------------------------------

def _check_shard_task(args):
    """Executor task (top-level, picklable): ``(path, ShardResult)``."""
    path, expect, content = args
    return path, check_shard(path, expect, content=content)


def _plan_split(split_dir: Path, content: bool) -> tuple[SplitReport, list]:
    """Manifest-level checks of one split and the shard tasks still to run."""
    report = SplitReport(split_dir, content_checked=content)
    manifest, problems = _load_manifest(split_dir)
    report.problems += problems
    on_disk = sorted(p.name for p in split_dir.glob(SHARD_GLOB))
    for leftover in sorted(split_dir.glob(f"*{TMP_SUFFIX}")):
        report.problems.append(Problem(leftover.name, "leftover temporary file of an interrupted write "
                                                      "(removed by 'artdata generate ... --resume')", warning=True))
    if manifest is None:
        return report, [(split_dir / name, None, content) for name in on_disk]
    config, msg = _manifest_config(manifest)
    if msg:
        report.problems.append(Problem(MANIFEST_NAME, msg))
    real = "real" in manifest
    captures_of = {}
    if real:
        problems, captures_of = _check_real_manifest(manifest, config)
        report.problems += problems
    else:
        report.problems += _check_manifest_counts(manifest, config)
    listed = [r["file"] for r in manifest["shards"]]
    for name in on_disk:
        if name not in listed:
            report.problems.append(Problem(name, "shard file not listed in the manifest (interrupted run? "
                                                 "finish it with 'artdata generate ... --resume')"))
    tasks = []
    for r in manifest["shards"]:
        expect = ShardExpectation(
            n_images=r["n_images"], n_bytes=r["bytes"], sha256=r["sha256"], object_start=r["object_start"],
            object_stop=r["object_stop"], class_name=manifest["class_name"], split=manifest["split"],
            seed=manifest["seed"], camera=config.camera if config is not None else None, real=real,
            capture_names=captures_of.get(r["file"]))
        tasks.append((split_dir / r["file"], expect, content))
    return report, tasks


def _finish_split(report: SplitReport, tasks: list, results: dict) -> SplitReport:
    all_ids = []
    for path, _, _ in tasks:
        res = results[path]
        report.n_shards += 1
        report.n_images += res.n_images
        shown = res.problems[:MAX_PROBLEMS_PER_FILE]
        report.problems += [Problem(path.name, m) for m in shown]
        if len(res.problems) > len(shown):
            report.problems.append(Problem(path.name, f"... and {len(res.problems) - len(shown)} more problems"))
        if res.sample_ids is not None:
            all_ids.append(res.sample_ids)
    if len(all_ids) > 1:
        ids = np.concatenate(all_ids)
        uniq, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            report.problems.append(Problem(report.split_dir.name, f"sample_id: {int((counts > 1).sum())} ids appear in "
                                                                  f"more than one shard of the split "
                                                                  f"(e.g. {int(uniq[counts > 1][0])})"))
    return report


def verify_splits(split_dirs, *, content: bool = True, workers: int = 1, progress=None) -> list[SplitReport]:
    """Verify split folders (manifest, checksums, format and, with ``content``, the label
    invariants), checking shards in ``workers`` processes.  ``progress(n)`` is called after
    each shard.  Never raises for bad data: problems are in the returned reports."""
    plans = [_plan_split(Path(d), content) for d in split_dirs]
    tasks = [t for _, ts in plans for t in ts]
    results = dict(_map(tasks, workers, progress))
    return [_finish_split(report, ts, results) for report, ts in plans]


def verify_split(split_dir: str | Path, *, content: bool = True, workers: int = 1, progress=None) -> SplitReport:
    """:func:`verify_splits` for one split folder."""
    return verify_splits([split_dir], content=content, workers=workers, progress=progress)[0]


def _map(tasks: list, workers: int, progress):
    if workers <= 1 or len(tasks) <= 1:
        for t in tasks:
            out = _check_shard_task(t)
            if progress is not None:
                progress(1)
            yield out
        return
    from .executors import process_map

    for out in process_map(_check_shard_task, tasks, min(workers, len(tasks)), ordered=True):
        if progress is not None:
            progress(1)
        yield out


def count_shards(split_dirs) -> int:
    """Shards that :func:`verify_split` will open (listed in the manifest, else on disk)."""
    total = 0
    for d in split_dirs:
        manifest, _ = _load_manifest(Path(d))
        total += len(manifest["shards"]) if manifest is not None else len(list(Path(d).glob(SHARD_GLOB)))
    return total


__all__ = ["Problem", "SplitReport", "ShardExpectation", "check_shard", "verify_split", "verify_splits", "find_splits", "count_shards",
           "quat_rotate_z", "UNIT_TOL", "LIMIT_TOL"]
