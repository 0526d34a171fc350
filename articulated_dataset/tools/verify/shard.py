"""Shard checks of ``artdata verify``: checksum and size against the manifest, readable HDF5,
root attributes, every schema dataset with its dtype and shape, the camera datasets; then
(with ``content``) the label invariants of :mod:`.content`."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig
from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format import (
    FIELDS,
    K_DATASET,
    R_DATASET,
    ROOT_ATTRS,
    check_h5_layout,
    check_version,
    resolve_shape,
    sha256_file,
)
from articulated_dataset.format.shards import JSON_TEXT_ERRORS, json_list
from articulated_dataset.generation.context_labels import occlusion_problems
from articulated_dataset.generation.framing import shard_framing
from articulated_dataset.tools.verify.content import check_content, rgb_problems

#: Relative tolerance when comparing the stored intrinsics with the camera config's K.
K_RTOL = 1e-9


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
    rgb: bool | None = None  # the manifest's config says the split stores colour images (--rgb)
    framing: str | None = None  # the manifest's config's framing (--framing)


@dataclass
class ShardResult:
    """What checking one shard found: one-line problems, the image count and the sample ids read."""
    problems: list[str] = field(default_factory=list)
    n_images: int = 0
    sample_ids: np.ndarray | None = None


def one_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message (at most 200 characters), or its type name if empty."""
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
        p.append(f"not a readable HDF5 file ({one_line(exc)})")
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
        p.append(f"cannot read root attributes ({one_line(exc)})")
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
        N = len(names)  # type: ignore[arg-type]  # no message: names were read
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
            p.append(f"cannot open dataset {fd.name!r} ({one_line(exc)})")
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
            p.append(f"cannot read dataset {name!r} ({one_line(exc)})")
    table, msg = _table(attrs)
    if msg:
        p.append(msg)
    check_content(arrays, attrs, table, J=J, ipo=ipo, start=start, problems=p, capture_names=names)
    p.extend(occlusion_problems(f, attrs, arrays, J=J, N=N, H=H, W=W))  # format 1.1 (--scene, --occluders)
    p.extend(rgb_problems(f, attrs, arrays, N=N, H=H, W=W))  # format 1.2 (--rgb)
    if expect.rgb is not None and ("appearance" in attrs) != expect.rgb:
        p.append("the manifest's config has rgb = true but the shard has no attribute appearance" if expect.rgb
                 else "the shard has the attribute appearance (--rgb) but the manifest's config has no rgb = true")
    if expect.framing is not None and shard_framing(attrs) != expect.framing:
        p.append(f"attribute framing says {shard_framing(attrs)[:40]!r}, the manifest's config {expect.framing[:40]!r}")
    if "sample_id" in arrays:
        res.sample_ids = arrays["sample_id"]


def _is_real(attrs: dict) -> bool:
    """A shard of ingested real captures (``real = 1``)."""
    v = attrs.get("real", 0)
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and int(v) == 1


def _capture_names(attrs: dict) -> tuple[list | None, str | None]:
    """The ``capture_names`` attribute of a real shard (a JSON list of unique names), or a problem."""
    if "capture_names" not in attrs:
        return None, "real shard without attribute capture_names; cannot check the datasets"
    names = json_list(attrs["capture_names"])
    if names is None:
        return None, "attribute capture_names is not a JSON list; cannot check the datasets"
    if not names or not all(isinstance(n, str) and n for n in names):
        return None, "attribute capture_names must be a non-empty JSON list of names; cannot check the datasets"
    if len(set(names)) != len(names):
        return None, "attribute capture_names names a capture twice"
    return names, None


def _check_registry(attrs: dict, J: int, p: list) -> None:
    from articulated_dataset.classes.registry import get_class

    try:
        obj_class = get_class(str(attrs.get("class_name")))
    except UserError:
        return  # a class from another package: nothing to compare with
    if J != obj_class.n_joints:
        p.append(f"n_joints = {J}, class {obj_class.name} has {obj_class.n_joints}")
    listed = json_list(attrs.get("joint_types", "[]"))
    if listed is None:
        p.append("attribute joint_types is not a JSON list")
        return
    types = tuple(listed)
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
        p.append(f"cannot read {K_DATASET}/{R_DATASET} ({one_line(exc)})")
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
    from articulated_dataset.ingest.write import vfov_deg_of

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
    from articulated_dataset.core.tables import SamplingTable

    try:
        return SamplingTable.from_dict(json.loads(attrs["sampling_table"])), None
    except KeyError:
        return None, None  # already reported as a missing attribute
    except (*JSON_TEXT_ERRORS, ValueError, AttributeError, UserError) as exc:
        return None, f"attribute sampling_table is not a valid table ({one_line(exc)})"
