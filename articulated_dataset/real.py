"""Real captures -> shards: ingest depth images or point clouds from a real sensor.

One *capture* is one depth observation of one object:

* depth: a 16-bit PNG in millimetres, a float EXR in metres (channel ``Z``, ``depth``, ``Y``,
  ``R`` or the only channel) or a ``.npy`` array in metres; or a point cloud (``.ply`` via
  trimesh, ``.pcd`` ASCII/binary) rasterised with the intrinsics (nearest point per pixel);
* intrinsics: fx, fy, cx, cy (OpenCV, pixel centres at integer coordinates) from options or a
  camera-info file (JSON/YAML: ``fx/fy/cx/cy``, ROS ``CameraInfo`` ``K``/``k``, or a ROS
  calibration file's ``camera_matrix``; ``width``/``height`` or ``image_width``/``image_height``);
* optional segmentation mask PNG of the same size: binary (0/255 or 0/1: object = body, label 1)
  or the dataset's labels (0 background, 1 body, 2 + j moving part j);
* optional ground truth JSON (:func:`load_ground_truth`).

Each capture is resampled to the training camera (:func:`resample_depth`): by default onto
exactly the training intrinsics (``fit="training"``: every training pixel reads its ray's
source pixel), or by cropping a window of the training aspect ratio around the mask and
scaling it to the training resolution (``fit="crop"``: K is rescaled; the shard stores it).
Depth is never interpolated: nearest neighbour, or the minimum depth of the source pixels
under the training pixel (``resample="min"``).  Outside a given mask the depth is set to 0,
as in the rendered training images (which have no background).

Labels a capture lacks are NaN (float fields) - see docs/real_data.md for the full list.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import FORMAT_VERSION, __version__
from .camera import R_CAMERA_TO_OPTICAL, CameraConfig
from .errors import UserError
from .format import FIELDS, MASK_BODY, MASK_FIRST_PART, SplitConfig, visible_pixels
from .registry import get_class
from .rotations import matrix_to_quat as mat_to_quat
from .rotations import quat_to_matrix
from .units import MM_PER_M, normalise

log = logging.getLogger(__name__)

REAL_SPLIT = "real"
DEPTH_SUFFIXES = (".png", ".exr", ".npy")
CLOUD_SUFFIXES = (".ply", ".pcd")
MASK_SUFFIX = ".mask.png"
LABELS_SUFFIX = ".labels.json"
CAMERA_SUFFIX = ".camera"  # <stem>.camera.json / .yaml: per-capture intrinsics
CAMERA_FILES = ("camera.json", "camera.yaml", "camera.yml")
#: Depths beyond this (m) are not plausible for an indoor sensor: a float image in metres with
#: larger values is most likely in millimetres (refused; pass the units).
MAX_PLAUSIBLE_DEPTH_M = 20.0
#: Depth sensors return nothing closer than about 0.1 m (Kinect v2: 0.5 m; RealSense D4xx:
#: 0.1-0.3 m): a capture whose median depth is below this is in other units than assumed.
MIN_PLAUSIBLE_DEPTH_M = 0.1
#: Fields of view (deg) a pinhole depth camera can have: intrinsics outside them (e.g.
#: fx = 1e308 px) are a mistake, not a lens.
MIN_PLAUSIBLE_FOV_DEG = 1.0
MAX_PLAUSIBLE_FOV_DEG = 170.0
#: Largest source frame accepted (pixels): ten times a 12-megapixel frame; larger is not a
#: depth sensor's image (and would exhaust memory when rasterised).
MAX_SOURCE_PIXELS = 120_000_000
#: Largest body dimension or part offset (m) of a labelled household object.
MAX_PLAUSIBLE_OBJECT_SIZE_M = 5.0
#: Ground-truth configurations may exceed the class's joint range by this much (rad for
#: revolute, m for prismatic joints): AR-tag / motion-capture labels of a closed or fully open
#: part are accurate to a few degrees or centimetres.
REAL_Q_TOLERANCE = {"revolute": math.radians(5.0), "prismatic": 0.02}
#: Allowed | |q| - 1 | of a given quaternion before it is normalised (labels written with a few
#: digits are not exactly unit); farther is a typo, not rounding.
QUAT_NORM_TOL = 1e-2
#: Allowed disagreement (rad) between a given ``object_yaw`` and the yaw of ``object_pose``.
YAW_AGREEMENT_RAD = 1e-3
#: Label fields of a real image that are NaN where the capture's labels do not give them.
REAL_LABEL_FIELDS = ("q", "axis_origin", "axis_direction", "axis_pose", "part_offset", "object_pose", "object_yaw",
                     "geometry")
#: Stored depth is rounded to multiples of 2**-13 m (0.12 mm), like generated depth.
DEPTH_QUANTUM_M = 2.0**-13
#: Margin added on each side of the mask's bounding box in ``fit="crop"`` (fraction of its size).
DEFAULT_CROP_MARGIN = 0.1
#: Images per shard (real splits are small; a shard per group of equal intrinsics).
MAX_IMAGES_PER_SHARD = 1024
FITS = ("training", "crop")
RESAMPLERS = ("nearest", "min")
DEPTH_UNITS = ("auto", "m", "mm")
CLOUD_FRAMES = ("optical", "camera")
GT_FRAMES = ("camera", "optical")


# --------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------

def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _numbers(value, what: str) -> np.ndarray:
    """``value`` (a number or nested lists of numbers, as read from JSON/YAML) as float64;
    strings, booleans, null and mappings are a :class:`UserError` (never converted)."""
    def ok(v) -> bool:
        return _is_number(v) or (isinstance(v, (list, tuple)) and all(ok(x) for x in v))
    if not ok(value):
        raise UserError(f"{what} must be numbers, got {str(value)[:80]}")
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError, OverflowError):  # ragged lists, integers beyond float64
        raise UserError(f"{what} must be a regular array of numbers, got {str(value)[:80]}") from None


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, where: str = "intrinsics") -> np.ndarray:
    """3x3 OpenCV K from focal lengths and principal point (px); checks they are usable."""
    vals = np.array([fx, fy, cx, cy], np.float64)
    if not np.isfinite(vals).all() or fx <= 0 or fy <= 0:
        raise UserError(f"{where}: focal lengths must be positive and all values finite, got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def check_intrinsics(K: np.ndarray, size: tuple[int, int], where: str) -> None:
    """Intrinsics ``K`` must describe a pinhole camera for a ``size`` = (W, H) image: both
    fields of view within [:data:`MIN_PLAUSIBLE_FOV_DEG`, :data:`MAX_PLAUSIBLE_FOV_DEG`] and
    the principal point inside the image (pixel k covers [k - 1/2, k + 1/2])."""
    W, H = size
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    for axis, f, n in (("horizontal", fx, W), ("vertical", fy, H)):
        fov = math.degrees(2.0 * math.atan(0.5 * n / f))
        if not MIN_PLAUSIBLE_FOV_DEG <= fov <= MAX_PLAUSIBLE_FOV_DEG:
            raise UserError(f"{where}: intrinsics fx={fx:g}, fy={fy:g} give a {axis} field of view of {fov:.3g} deg "
                            f"for a {W}x{H} image (a depth camera has {MIN_PLAUSIBLE_FOV_DEG:g}-"
                            f"{MAX_PLAUSIBLE_FOV_DEG:g} deg); check the focal lengths (px)")
    if not (-0.5 <= cx <= W - 0.5 and -0.5 <= cy <= H - 0.5):
        raise UserError(f"{where}: principal point ({cx:g}, {cy:g}) px lies outside the {W}x{H} image; check cx, cy")


def check_source_size(size: tuple[int, int], where: str) -> None:
    """A source frame of ``size`` = (W, H) pixels must be at most :data:`MAX_SOURCE_PIXELS`."""
    W, H = size
    if W <= 0 or H <= 0 or W * H > MAX_SOURCE_PIXELS:
        raise UserError(f"{where}: a {W}x{H} frame is not a depth sensor's image "
                        f"(at most {MAX_SOURCE_PIXELS:,} pixels)")


def _read_mapping(path: Path) -> dict:
    if not path.is_file():
        raise UserError(f"file not found: {path}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not UTF-8 text (byte {exc.start}); save it as UTF-8 JSON or YAML") from None
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError:
                raise UserError(f"{path}: reading YAML needs PyYAML (pip install pyyaml), or give the file as JSON") from None
            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except UserError:
        raise
    except Exception as exc:  # parse errors of either format are the user's
        raise UserError(f"cannot parse {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping (object) at the top level")
    return data


def load_intrinsics(path: str | Path) -> tuple[np.ndarray, tuple[int, int] | None]:
    """K (3x3) and the image size ``(width, height)`` (None if the file has none) of a
    camera-info JSON/YAML file.

    Accepted keys: ``fx, fy, cx, cy``; or ``K``/``k`` (ROS ``CameraInfo``, 9 numbers row-major
    or 3x3); or ``camera_matrix: {data: [9 numbers]}`` (ROS calibration YAML).  Size:
    ``width``/``height`` or ``image_width``/``image_height``.
    """
    path = Path(path)
    d = _read_mapping(path)
    if all(k in d for k in ("fx", "fy", "cx", "cy")):
        K = intrinsics_matrix(*(_scalar(d, k, path) for k in ("fx", "fy", "cx", "cy")), str(path))
    else:
        raw = d.get("K", d.get("k"))
        if raw is None and isinstance(d.get("camera_matrix"), dict):
            raw = d["camera_matrix"].get("data")
        if raw is None:
            raise UserError(f"{path}: no intrinsics found (expected fx/fy/cx/cy, K, k or camera_matrix.data)")
        m = _numbers(raw, f"{path}: camera matrix")
        if m.size != 9:
            raise UserError(f"{path}: camera matrix must have 9 numbers, got {m.size}")
        m = m.reshape(3, 3)
        if abs(m[0, 1]) > 0 or abs(m[1, 0]) > 0 or abs(m[2, 2] - 1.0) > 1e-9 or m[2, 0] != 0 or m[2, 1] != 0:
            raise UserError(f"{path}: camera matrix must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew)")
        K = intrinsics_matrix(m[0, 0], m[1, 1], m[0, 2], m[1, 2], str(path))
    w = d.get("width", d.get("image_width"))
    h = d.get("height", d.get("image_height"))
    size = None
    if w is not None or h is not None:
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (w, h)):
            raise UserError(f"{path}: image width and height must both be whole numbers of pixels, got {w!r} x {h!r}")
        size = (w, h)
        check_source_size(size, str(path))
        check_intrinsics(K, size, str(path))
    return K, size


def _scalar(d: dict, key: str, path: Path) -> float:
    a = _numbers(d[key], f"{path}: {key}")
    if a.ndim != 0:
        raise UserError(f"{path}: {key} must be one number, got {str(d[key])[:80]}")
    return float(a)


# --------------------------------------------------------------------------------------
# Depth, mask and point-cloud files
# --------------------------------------------------------------------------------------

def _check_units(units: str) -> None:
    if units not in DEPTH_UNITS:
        raise UserError(f"unknown depth units {units!r}; choose from: {', '.join(DEPTH_UNITS)}")


def _to_metres(raw: np.ndarray, units: str, path: Path) -> np.ndarray:
    """Depth in metres (float64) from ``raw`` in ``units``; NaN/inf become 0 (no return)."""
    depth = raw.astype(np.float64) / (MM_PER_M if units == "mm" else 1.0)
    depth[~np.isfinite(depth)] = 0.0
    if (depth < 0).any():
        raise UserError(f"{path}: {int((depth < 0).sum())} negative depth values")
    top = float(depth.max(initial=0.0))
    if top > MAX_PLAUSIBLE_DEPTH_M:
        hint = "; it looks like millimetres: pass --depth-units mm" if units == "m" else ""
        raise UserError(f"{path}: depth up to {top:.1f} m is not plausible for a depth sensor{hint}")
    returns = depth[depth > 0]
    median = float(np.median(returns)) if returns.size else 0.0
    if returns.size and median < MIN_PLAUSIBLE_DEPTH_M:
        as_m = median * (MM_PER_M if units == "mm" else 1.0)
        hint = ("; it looks like metres: pass --depth-units m" if units == "mm" and MIN_PLAUSIBLE_DEPTH_M <= as_m <= MAX_PLAUSIBLE_DEPTH_M
                else "; check the depth units (--depth-units)")
        raise UserError(f"{path}: median depth {1000 * median:.3g} mm read as {units_name(units)} is closer than any "
                        f"depth sensor measures ({MIN_PLAUSIBLE_DEPTH_M:g} m){hint}")
    return depth


def units_name(units: str) -> str:
    return "millimetres" if units == "mm" else "metres"


def _read_image(path: Path, what: str) -> tuple[np.ndarray, str]:
    """Pixels and PIL mode of an image file; an unreadable file is a one-line UserError."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            check_source_size(im.size, str(path))
            return np.array(im), im.mode
    except UserError:
        raise
    except Exception as exc:
        raise UserError(f"{path}: not a readable {what} ({str(exc).splitlines()[0]})") from None


def load_depth(path: str | Path, units: str = "auto") -> np.ndarray:
    """A depth image in metres, (H, W) float64, 0 = no return.

    ``units="auto"``: 16-bit PNG = millimetres; float EXR / float ``.npy`` = metres; an
    integer ``.npy`` has unknown units (refused: pass ``"mm"`` or ``"m"``).
    """
    path = Path(path)
    _check_units(units)
    if not path.is_file():
        raise UserError(f"depth file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".png":
        raw, mode = _read_image(path, "PNG")
        if mode not in ("I;16", "I;16B", "I;16L", "I") or raw.ndim != 2:
            raise UserError(f"{path}: depth PNG must be single-channel 16-bit (millimetres), got mode {mode}; "
                            f"units of 8-bit or colour PNGs are unknown")
        return _to_metres(raw, "mm" if units == "auto" else units, path)
    if suffix == ".exr":
        import OpenEXR

        try:
            channels = OpenEXR.File(str(path)).channels()
        except Exception as exc:
            raise UserError(f"{path}: not a readable EXR file ({str(exc).splitlines()[0]})") from None
        name = next((c for c in ("Z", "depth", "Y", "R") if c in channels), None)
        if name is None and len(channels) == 1:
            name = next(iter(channels))
        if name is None:
            raise UserError(f"{path}: no depth channel (expected Z, depth, Y or R; found {', '.join(sorted(channels))})")
        raw = np.asarray(channels[name].pixels)
        if raw.ndim != 2:
            raise UserError(f"{path}: channel {name!r} has shape {raw.shape}, expected a single-channel image")
        return _to_metres(raw, "m" if units == "auto" else units, path)
    if suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False, mmap_mode="r")
        except Exception as exc:
            raise UserError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0]})") from None
        if raw.ndim != 2 or raw.dtype.kind not in "fiu":
            raise UserError(f"{path}: expected a 2-D numeric depth array, got shape {raw.shape} dtype {raw.dtype}")
        check_source_size((raw.shape[1], raw.shape[0]), str(path))
        raw = np.array(raw)
        if units == "auto":
            if raw.dtype.kind != "f":
                raise UserError(f"{path}: integer depth array has unknown units; pass --depth-units mm or m")
            units = "m"
        return _to_metres(raw, units, path)
    raise UserError(f"{path}: unsupported depth file type {suffix!r} (expected {', '.join(DEPTH_SUFFIXES)})")


def load_mask(path: str | Path, shape: tuple[int, int], n_joints: int) -> np.ndarray:
    """A segmentation mask as dataset labels (uint8: 0 background, 1 body, 2 + j part j).

    A mask whose values are all in {0, 255} or {0, 1} is binary (object = body).  Otherwise its
    values must be labels 0 .. 1 + J.  Its size must equal ``shape`` (H, W) of the depth.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"mask file not found: {path}")
    raw, mode = _read_image(path, "image")
    if raw.ndim != 2:
        raise UserError(f"{path}: mask must be a single-channel image, got mode {mode}")
    if raw.shape != tuple(shape):
        raise UserError(f"{path}: mask is {raw.shape[1]}x{raw.shape[0]} px but the depth is {shape[1]}x{shape[0]} px")
    values = set(np.unique(raw).tolist())
    if values <= {0, 255} or values <= {0, 1}:
        return (raw > 0).astype(np.uint8) * np.uint8(MASK_BODY)
    top = MASK_FIRST_PART + n_joints - 1
    if max(values) > top or min(values) < 0:
        raise UserError(f"{path}: mask values {sorted(values)[:8]} are neither binary (0/255) nor labels 0..{top}")
    return raw.astype(np.uint8)


def _read_pcd(path: Path) -> np.ndarray:
    """x, y, z columns (N, 3) of an ASCII or binary PCD file (binary_compressed is refused)."""
    data = path.read_bytes()
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = data.find(b"\n", offset)
        if end < 0:
            raise UserError(f"{path}: truncated PCD header")
        line = data[offset:end].decode("ascii", "replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        n = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        kind = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        raise UserError(f"{path}: malformed PCD header") from None
    if not {"x", "y", "z"} <= set(fields):
        raise UserError(f"{path}: PCD has no x, y, z fields (has {', '.join(fields)})")
    codes = {"F": "f", "I": "i", "U": "u"}
    sizes_ok = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
    if (not len(fields) == len(sizes) == len(types) == len(counts) or n < 0 or min(counts) < 1
            or not all(t in codes and z in sizes_ok[t] for t, z in zip(types, sizes))):
        raise UserError(f"{path}: malformed PCD header (FIELDS, SIZE, TYPE and COUNT must describe each field: "
                        f"TYPE F with SIZE 4 or 8, I/U with 1, 2, 4 or 8, COUNT >= 1, POINTS >= 0)")
    if kind == "ascii":
        try:
            rows = [r for r in data[offset:].decode("ascii").splitlines() if r.strip()]
            if not rows:
                return np.empty((0, 3))
            table = np.loadtxt(rows, ndmin=2)
        except (ValueError, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: malformed PCD data ({str(exc).splitlines()[0][:120]})") from None
        if table.shape[1] != sum(counts):
            raise UserError(f"{path}: PCD rows have {table.shape[1]} values, the header describes {sum(counts)}")
        cols = np.cumsum([0] + counts)
        return np.stack([table[:, cols[fields.index(a)]] for a in "xyz"], axis=1)[:n].reshape(-1, 3)
    if kind == "binary":
        dtype = np.dtype([(f"f{i}", f"<{codes[t]}{s}", (c,)) for i, (t, s, c) in enumerate(zip(types, sizes, counts))])
        if len(data) - offset < n * dtype.itemsize:
            raise UserError(f"{path}: PCD data is shorter than its header says ({n} points)")
        rec = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
        return np.stack([rec[f"f{fields.index(a)}"][:, 0] for a in "xyz"], axis=1).astype(np.float64)
    raise UserError(f"{path}: PCD DATA {kind!r} is not supported (save it as ascii or binary)")


def load_cloud(path: str | Path) -> np.ndarray:
    """Points (N, 3) float64, metres, of a ``.ply`` (trimesh) or ``.pcd`` file; NaN rows dropped."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"point cloud file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        import trimesh

        try:
            geom = trimesh.load(str(path), process=False)
        except Exception as exc:
            raise UserError(f"{path}: not a readable PLY file ({str(exc).splitlines()[0]})") from None
        points = np.asarray(getattr(geom, "vertices", np.empty((0, 3))), np.float64)
    elif suffix == ".pcd":
        points = _read_pcd(path)
    else:
        raise UserError(f"{path}: unsupported point cloud type {suffix!r} (expected {', '.join(CLOUD_SUFFIXES)})")
    points = points.reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if points.shape[0] == 0:
        raise UserError(f"{path}: the point cloud has no finite points")
    return points


def rasterise_cloud(points_optical_m: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Z-buffer an optical-frame cloud into a (H, W) depth image (m): each pixel keeps the
    nearest point projecting into it (``u = fx x / z + cx`` rounded); 0 where none does."""
    W, H = size
    p = np.asarray(points_optical_m, np.float64)
    p = p[p[:, 2] > 0]
    u = np.rint(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, z = u[inside], v[inside], p[inside, 2]
    depth = np.zeros((H, W))
    if z.size:
        pix = v * W + u
        order = np.lexsort((z, pix))  # by pixel, then nearest first
        first = np.unique(pix[order], return_index=True)[1]
        depth.flat[pix[order][first]] = z[order][first]
    return depth


# --------------------------------------------------------------------------------------
# Resampling to the training camera
# --------------------------------------------------------------------------------------

def crop_intrinsics(K: np.ndarray, mask: np.ndarray, out_size: tuple[int, int], margin: float = DEFAULT_CROP_MARGIN) -> np.ndarray:
    """Intrinsics of a window around the mask with the aspect ratio of ``out_size`` (W, H),
    scaled to that size.

    The window is the mask's bounding box grown by ``margin`` of its size on each side, then
    widened (or heightened) to the aspect ratio, centred on the box.  With window left/top
    edges ``(a, b)`` (continuous source coordinates; pixel k covers [k - 0.5, k + 0.5]) and
    scale ``s = W_out / window_width``: ``fx' = s fx``, ``fy' = s fy``,
    ``cx' = s (cx - a) - 0.5``, ``cy' = s (cy - b) - 0.5``.
    """
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        raise UserError("the mask is empty: nothing to crop around")
    W, H = out_size
    u0, u1 = xs.min() - 0.5, xs.max() + 0.5
    v0, v1 = ys.min() - 0.5, ys.max() + 0.5
    w, h = (u1 - u0) * (1 + 2 * margin), (v1 - v0) * (1 + 2 * margin)
    aspect = W / H
    if w / h < aspect:
        w = h * aspect
    else:
        h = w / aspect
    a, b = 0.5 * (u0 + u1) - 0.5 * w, 0.5 * (v0 + v1) - 0.5 * h
    s = W / w
    return np.array([[s * K[0, 0], 0.0, s * (K[0, 2] - a) - 0.5], [0.0, s * K[1, 1], s * (K[1, 2] - b) - 0.5], [0.0, 0.0, 1.0]])


def source_coordinates(K_src: np.ndarray, K_dst: np.ndarray, size_dst: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Source-image coordinates (u_s (W,), v_s (H,)) of the destination pixel centres.

    Both cameras share the optical centre and axes, so z-depth is unchanged and
    ``u_s = fx_s (u - cx_d) / fx_d + cx_s`` (same for v).
    """
    W, H = size_dst
    us = K_src[0, 0] * (np.arange(W) - K_dst[0, 2]) / K_dst[0, 0] + K_src[0, 2]
    vs = K_src[1, 1] * (np.arange(H) - K_dst[1, 2]) / K_dst[1, 1] + K_src[1, 2]
    return us, vs


def resample_depth(depth_m: np.ndarray, mask: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray,
                   size_dst: tuple[int, int], method: str = "nearest") -> tuple[np.ndarray, np.ndarray]:
    """Resample depth (m) and mask onto the camera ``K_dst`` of size ``size_dst`` (W, H).

    ``nearest``: each destination pixel takes the source pixel nearest its ray.  ``min``: the
    smallest non-zero depth among the source pixels whose centres fall in the destination
    pixel's footprint ``[u_s - r/2, u_s + r/2)`` (``r = fx_s / fx_d``; the nearest pixel if the
    footprint holds no centre), and that pixel's mask label.  Rays leaving the source image
    get depth 0 and label 0.  No depth is ever interpolated.
    """
    if method not in RESAMPLERS:
        raise UserError(f"unknown resampling {method!r}; choose from: {', '.join(RESAMPLERS)}")
    Hs, Ws = depth_m.shape
    W, H = size_dst
    us, vs = source_coordinates(K_src, K_dst, size_dst)
    if method == "nearest":
        iu, iv = np.rint(us).astype(np.int64), np.rint(vs).astype(np.int64)
        ok = (iu >= 0) & (iu < Ws), (iv >= 0) & (iv < Hs)
        depth = np.zeros((H, W))
        out_mask = np.zeros((H, W), np.uint8)
        sel = np.ix_(iv[ok[1]], iu[ok[0]])
        rows, cols = np.nonzero(ok[1])[0], np.nonzero(ok[0])[0]
        depth[np.ix_(rows, cols)] = depth_m[sel]
        out_mask[np.ix_(rows, cols)] = mask[sel]
        return depth, out_mask
    ru, rv = K_src[0, 0] / K_dst[0, 0], K_src[1, 1] / K_dst[1, 1]
    # per axis: candidate source indices k = ceil(start) + o, o = 0..n-1, valid while k < end
    def candidates(coords: np.ndarray, r: float, size: int):
        start, end = coords - 0.5 * r, coords + 0.5 * r
        first = np.ceil(start).astype(np.int64)
        n = max(1, int(math.ceil(r)) + 1)
        idx = first[:, None] + np.arange(n)[None]
        ok = (idx < end[:, None]) & (idx >= 0) & (idx < size)
        nearest = np.rint(coords).astype(np.int64)
        return idx, ok, nearest
    cu, oku, nu = candidates(us, ru, Ws)
    cv, okv, nv = candidates(vs, rv, Hs)
    best = np.full((H, W), np.inf)
    label = np.zeros((H, W), np.uint8)
    for a in range(cv.shape[1]):
        for b in range(cu.shape[1]):
            ok = okv[:, a][:, None] & oku[:, b][None, :]
            z = depth_m[np.clip(cv[:, a], 0, Hs - 1)][:, np.clip(cu[:, b], 0, Ws - 1)]
            m = mask[np.clip(cv[:, a], 0, Hs - 1)][:, np.clip(cu[:, b], 0, Ws - 1)]
            better = ok & (z > 0) & (z < best)
            best[better] = z[better]
            label[better] = m[better]
    # no valid depth in the footprint: nearest pixel (if inside the image)
    none = ~np.isfinite(best)
    inside = ((nv >= 0) & (nv < Hs))[:, None] & ((nu >= 0) & (nu < Ws))[None, :]
    near_d = depth_m[np.clip(nv, 0, Hs - 1)][:, np.clip(nu, 0, Ws - 1)]
    near_m = mask[np.clip(nv, 0, Hs - 1)][:, np.clip(nu, 0, Ws - 1)]
    depth = np.where(none, np.where(inside, near_d, 0.0), best)
    label = np.where(none, np.where(inside, near_m, 0), label).astype(np.uint8)
    return depth, label


def mask_fraction_inside(mask: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray, size_dst: tuple[int, int]) -> float:
    """Fraction of the mask's pixels whose rays fall inside the destination image."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return 1.0
    W, H = size_dst
    u = K_dst[0, 0] * (xs - K_src[0, 2]) / K_src[0, 0] + K_dst[0, 2]
    v = K_dst[1, 1] * (ys - K_src[1, 2]) / K_src[1, 1] + K_dst[1, 2]
    inside = (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5)
    return float(inside.mean())


# --------------------------------------------------------------------------------------
# Ground truth
# --------------------------------------------------------------------------------------

def _array(d: dict, key: str, shape: tuple, path: Path) -> np.ndarray | None:
    """``d[key]`` as a float64 array of ``shape``; None if absent or null (not available).
    NaN, infinite, non-numeric values or another shape are a :class:`UserError`."""
    if key not in d or d[key] is None:
        return None
    a = _numbers(d[key], f"{path}: {key!r}")
    if a.shape != shape:
        raise UserError(f"{path}: {key!r} has shape {a.shape}, expected {shape}")
    if not np.isfinite(a).all():
        raise UserError(f"{path}: {key!r} has NaN or infinite values; leave the key out (or null) when it is "
                        f"not known")
    return a


def _label_unit(v: np.ndarray, what: str, path: Path, tol: float | None = None) -> np.ndarray:
    """``v`` (..., n) of a label file normalised row by row; zero length (or, with ``tol``, a
    norm farther than ``tol`` from 1) is a :class:`UserError`."""
    rows = normalise(v.reshape(-1, v.shape[-1]), min_norm=1e-9, what=f"{path}: {what}")
    if tol is not None:
        n = np.linalg.norm(v, axis=-1)
        if (np.abs(n - 1.0) > tol).any():
            raise UserError(f"{path}: {what} has norm {float(n.reshape(-1)[np.argmax(np.abs(n - 1.0))]):.4g}, "
                            f"expected a unit quaternion (w, x, y, z)")
    return rows.reshape(v.shape)


def _wrap_angle(a: float) -> float:
    """``a`` (rad) in (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def real_label_problems(labels: dict, joint_types, q_ranges, has_ground_truth=None) -> list[tuple[str, np.ndarray]]:
    """What is wrong with the labels of N real images: ``[(message, bad (N,) bool)]``.

    ``labels`` maps every field of :data:`REAL_LABEL_FIELDS` to an (N, ...) array (NaN where
    the capture does not give the value).  The rules (docs/real_data.md): no infinite values;
    each group (a joint's origin, direction, axis position, axis quaternion, part offset; the
    object position, the object quaternion, the geometry) is given or NaN as a whole, and
    ``axis_pose``'s position / quaternion are given exactly where ``axis_origin`` /
    ``axis_direction`` are; ``object_yaw`` is given where ``object_pose`` is; an image without
    ground truth (``has_ground_truth`` 0) has only NaN.  Given values: ``q`` within the class's
    joint range (``q_ranges``, widened by :data:`REAL_Q_TOLERANCE`), positions within
    :data:`MAX_PLAUSIBLE_DEPTH_M` of the camera, body dimensions and part offsets positive /
    within :data:`MAX_PLAUSIBLE_OBJECT_SIZE_M`, chirality 0 or 1, ``object_yaw`` in [-pi, pi].
    """
    out: list[tuple[str, np.ndarray]] = []
    L = {k: np.asarray(labels[k], np.float64) for k in REAL_LABEL_FIELDS}
    n = L["q"].shape[0]

    def flag(message: str, bad: np.ndarray) -> None:
        bad = np.asarray(bad, bool).reshape(n, -1).any(axis=1)
        if bad.any():
            out.append((message, bad))

    for k, v in L.items():
        flag(f"{k}: infinite values", np.isinf(v))
    groups = (("axis_origin", slice(None), ""), ("axis_direction", slice(None), ""), ("axis_pose", slice(0, 3), " position"),
              ("axis_pose", slice(3, 7), " quaternion"), ("part_offset", slice(None), ""),
              ("object_pose", slice(0, 3), " position"), ("object_pose", slice(3, 7), " quaternion"), ("geometry", slice(None), ""))
    for k, sl, part in groups:
        nan = np.isnan(L[k][..., sl])
        flag(f"{k}{part}: partly NaN (a value is given, or not available, as a whole)", nan.any(-1) & ~nan.all(-1))
    flag("axis_pose position and axis_origin: one is given without the other",
         np.isnan(L["axis_pose"][..., 0]) != np.isnan(L["axis_origin"][..., 0]))
    flag("axis_pose quaternion and axis_direction: one is given without the other",
         np.isnan(L["axis_pose"][..., 3]) != np.isnan(L["axis_direction"][..., 0]))
    flag("object_yaw: NaN although object_pose gives it", ~np.isnan(L["object_pose"][:, 3]) & np.isnan(L["object_yaw"]))
    if has_ground_truth is not None:
        given = np.stack([~np.isnan(v.reshape(n, -1)).all(axis=1) for v in L.values()], axis=1)
        flag("labels present although has_ground_truth is 0", (np.asarray(has_ground_truth) == 0)[:, None] & given)
    with np.errstate(invalid="ignore"):  # NaN (not available) compares False: only given values are checked
        for j, (jtype, (lo, hi)) in enumerate(zip(joint_types, q_ranges)):
            tol = REAL_Q_TOLERANCE[jtype]
            unit = "rad" if jtype == "revolute" else "m"
            flag(f"q[{j}]: outside the class's joint range [{lo:.4g}, {hi:.4g}] {unit} (by more than {tol:.3g} {unit})",
                 (L["q"][:, j] < lo - tol) | (L["q"][:, j] > hi + tol))
        for k, sl in (("axis_origin", slice(None)), ("object_pose", slice(0, 3))):
            flag(f"{k}: position farther than {MAX_PLAUSIBLE_DEPTH_M:g} m from the camera",
                 np.linalg.norm(L[k][..., sl], axis=-1) > MAX_PLAUSIBLE_DEPTH_M)
        flag(f"part_offset: longer than {MAX_PLAUSIBLE_OBJECT_SIZE_M:g} m",
             np.linalg.norm(L["part_offset"], axis=-1) > MAX_PLAUSIBLE_OBJECT_SIZE_M)
        dims = L["geometry"][:, :3]
        flag(f"geometry: body dimensions not in (0, {MAX_PLAUSIBLE_OBJECT_SIZE_M:g}] m",
             (dims <= 0) | (dims > MAX_PLAUSIBLE_OBJECT_SIZE_M))
        chir = L["geometry"][:, 3]
        flag("geometry: chirality not 0 or 1", ~np.isnan(chir) & ~np.isin(chir, (0.0, 1.0)))
        flag("object_yaw: outside [-pi, pi] rad", np.abs(L["object_yaw"]) > math.pi + YAW_AGREEMENT_RAD)
    return out


#: Camera-frame up (z) and forward (x) directions used to complete an axis frame from its z axis.
_UP = np.array([0.0, 0.0, 1.0])
_FORWARD = np.array([1.0, 0.0, 0.0])


def axis_frame_from_direction(a: np.ndarray) -> np.ndarray:
    """A rotation (columns x, y, z) with z = ``a`` (unit) and x = camera up made perpendicular
    to ``a`` (camera forward if ``a`` is vertical); used when ground truth gives only the axis
    line: only the z column is then meaningful."""
    ref = _UP if abs(float(a @ _UP)) < 0.9 else _FORWARD
    x = ref - (ref @ a) * a
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(a, x), a], axis=1)


def load_ground_truth(path: str | Path, n_joints: int, class_name: str | None = None) -> dict:
    """Labels of one capture from a JSON file, converted to the camera frame.

    Keys (all optional; J = joints of the class):

    * ``frame``: ``"camera"`` (x forward, y left, z up; default) or ``"optical"`` (x right,
      y down, z forward): positions and orientations are converted with
      ``p_camera = R^T p_optical``, ``R_camera = R^T R_optical`` (``R = R_CAMERA_TO_OPTICAL``);
    * ``q`` (J,): rad (revolute) or m (prismatic);
    * ``axis_pose`` (J, 7): position + quaternion (w, x, y, z) of the axis frame (z = axis), or
      ``axis_origin`` (J, 3) + ``axis_direction`` (J, 3) (the stored frame's x axis is then
      :func:`axis_frame_from_direction`'s choice);
    * ``part_offset`` (J, 3) (axis frame); ``geometry`` (4: depth, width, height m, chirality);
    * ``object_pose`` (7) and/or ``object_yaw`` (rad, camera frame);
    * ``class`` (must match), ``object`` (name grouping captures of one object).

    Returns a dict of float64 arrays for every label field, NaN where not given, plus
    ``"object"`` (str or None).
    """
    path = Path(path)
    d = _read_mapping(path)
    if class_name is not None and d.get("class") not in (None, class_name):
        raise UserError(f"{path}: ground truth is for class {str(d.get('class'))[:80]!r}, not {class_name!r}")
    frame = d.get("frame", "camera")
    if not isinstance(frame, str) or frame not in GT_FRAMES:
        raise UserError(f"{path}: unknown frame {frame!r}; choose from: {', '.join(GT_FRAMES)}")
    unknown = set(d) - {"frame", "q", "axis_pose", "axis_origin", "axis_direction", "part_offset", "geometry",
                        "object_pose", "object_yaw", "class", "object", "comment"}
    if unknown:
        raise UserError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}")
    J = n_joints
    Rt = R_CAMERA_TO_OPTICAL.T if frame == "optical" else np.eye(3)
    out = empty_labels(J)
    q = _array(d, "q", (J,), path)
    if q is not None:
        out["q"] = q
    pose = _array(d, "axis_pose", (J, 7), path)
    origin = _array(d, "axis_origin", (J, 3), path)
    direction = _array(d, "axis_direction", (J, 3), path)
    if pose is not None:
        quat = _label_unit(pose[:, 3:], "axis_pose quaternion", path, QUAT_NORM_TOL)
        rots = np.stack([Rt @ quat_to_matrix(qq) for qq in quat])
        pos = pose[:, :3] @ Rt.T
        if origin is not None and np.abs(origin @ Rt.T - pos).max() > 1e-4:
            raise UserError(f"{path}: axis_origin disagrees with the position of axis_pose")
        if direction is not None and np.abs(_label_unit(direction, "axis_direction", path) @ Rt.T - rots[:, :, 2]).max() > 1e-4:
            raise UserError(f"{path}: axis_direction disagrees with the z axis of axis_pose")
        out["axis_pose"] = np.concatenate([pos, np.stack([mat_to_quat(r) for r in rots])], axis=1)
        out["axis_origin"], out["axis_direction"] = pos, rots[:, :, 2]
    else:
        if origin is not None:
            out["axis_origin"] = origin @ Rt.T
            out["axis_pose"][:, :3] = out["axis_origin"]
        if direction is not None:
            a = _label_unit(direction, "axis_direction", path) @ Rt.T
            out["axis_direction"] = a
            out["axis_pose"][:, 3:] = np.stack([mat_to_quat(axis_frame_from_direction(aj)) for aj in a])
    offset = _array(d, "part_offset", (J, 3), path)
    if offset is not None:
        out["part_offset"] = offset
    geometry = _array(d, "geometry", (4,), path)
    if geometry is not None:
        out["geometry"] = geometry
    obj_pose = _array(d, "object_pose", (7,), path)
    if obj_pose is not None:
        r = Rt @ quat_to_matrix(_label_unit(obj_pose[3:], "object_pose quaternion", path, QUAT_NORM_TOL))
        out["object_pose"] = np.concatenate([Rt @ obj_pose[:3], mat_to_quat(r)])
        out["object_yaw"] = np.array(math.atan2(r[1, 0], r[0, 0]))
    yaw = _array(d, "object_yaw", (), path)
    if yaw is not None:
        if frame != "camera":
            raise UserError(f"{path}: object_yaw is a camera-frame angle; give object_pose in the optical frame instead")
        yaw = _wrap_angle(float(yaw))
        if obj_pose is not None and abs(_wrap_angle(yaw - float(out["object_yaw"]))) > YAW_AGREEMENT_RAD:
            raise UserError(f"{path}: object_yaw {yaw:.4f} rad disagrees with the yaw of object_pose "
                            f"({float(out['object_yaw']):.4f} rad)")
        out["object_yaw"] = np.array(yaw)
    obj = d.get("object")
    if obj is not None and not (isinstance(obj, str) and obj.strip()):
        raise UserError(f"{path}: 'object' must be a non-empty name (string), got {str(obj)[:80]!r}")
    out["object"] = obj
    if class_name is not None:
        obj_class = get_class(class_name)
        problems = real_label_problems({k: np.asarray(out[k])[None] for k in REAL_LABEL_FIELDS},
                                       obj_class.joint_types, obj_class.table.q)
        if problems:
            raise UserError(f"{path}: {problems[0][0]}")
    return out


def empty_labels(n_joints: int) -> dict:
    """Every float label field of one image filled with NaN (shapes without the image axis)."""
    J = n_joints
    return {
        "q": np.full(J, np.nan), "axis_origin": np.full((J, 3), np.nan), "axis_direction": np.full((J, 3), np.nan),
        "axis_pose": np.full((J, 7), np.nan), "part_offset": np.full((J, 3), np.nan), "object_pose": np.full(7, np.nan),
        "object_yaw": np.array(np.nan), "geometry": np.full(4, np.nan), "object": None,
    }


# --------------------------------------------------------------------------------------
# Captures
# --------------------------------------------------------------------------------------

@dataclass
class CaptureFiles:
    """The files of one capture (paths; None where absent)."""

    name: str
    data: Path  # depth image or point cloud
    mask: Path | None = None
    labels: Path | None = None
    camera: Path | None = None  # camera-info file (if intrinsics are not given otherwise)

    @property
    def is_cloud(self) -> bool:
        return self.data.suffix.lower() in CLOUD_SUFFIXES


@dataclass
class IngestOptions:
    """How captures are converted (see :func:`ingest_capture`)."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    fit: str = "training"
    resample: str = "nearest"
    crop_margin: float = DEFAULT_CROP_MARGIN
    depth_units: str = "auto"
    cloud_frame: str = "optical"
    keep_background: bool = False
    intrinsics: np.ndarray | None = None  # K for every capture (overrides camera files)
    source_size: tuple[int, int] | None = None  # (W, H) of rasterised clouds without a size in the camera file

    def __post_init__(self) -> None:
        for value, allowed, what in ((self.fit, FITS, "fit"), (self.resample, RESAMPLERS, "resampling"),
                                     (self.depth_units, DEPTH_UNITS, "depth units"), (self.cloud_frame, CLOUD_FRAMES, "cloud frame")):
            if value not in allowed:
                raise UserError(f"unknown {what} {value!r}; choose from: {', '.join(allowed)}")
        if not 0.0 <= self.crop_margin < 10.0:
            raise UserError(f"crop margin must be in [0, 10), got {self.crop_margin}")

    def to_dict(self) -> dict:
        return {"fit": self.fit, "resample": self.resample, "crop_margin": self.crop_margin, "depth_units": self.depth_units,
                "cloud_frame": self.cloud_frame, "keep_background": self.keep_background}


@dataclass
class Capture:
    """One ingested capture at the training resolution."""

    name: str
    depth: np.ndarray  # (H, W) float32 m
    mask: np.ndarray  # (H, W) uint8
    K: np.ndarray  # (3, 3)
    labels: dict  # float label arrays (NaN where unknown) + "object"
    mask_fraction_inside: float = 1.0
    has_labels: bool = False


def find_captures(paths: list[str | Path]) -> list[CaptureFiles]:
    """Captures named by ``paths``: depth/cloud files, or folders of them.

    Next to ``NAME.<png|exr|npy|ply|pcd>`` the optional files are ``NAME.mask.png``,
    ``NAME.labels.json`` and ``NAME.camera.json|yaml`` (else ``camera.json|yaml`` in the folder).
    """
    found: list[CaptureFiles] = []
    for p in map(Path, paths):
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.is_file() and _is_data_file(f))
            if not files:
                raise UserError(f"{p}: no captures found (expected depth images {', '.join(DEPTH_SUFFIXES)} "
                                f"or point clouds {', '.join(CLOUD_SUFFIXES)})")
            found.extend(_capture_files(f) for f in files)
        elif p.is_file():
            if not _is_data_file(p):
                raise UserError(f"{p}: not a depth image or point cloud ({', '.join(DEPTH_SUFFIXES + CLOUD_SUFFIXES)})")
            found.append(_capture_files(p))
        else:
            raise UserError(f"no such file or directory: {p}")
    names = [c.name for c in found]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UserError(f"capture names must be unique; repeated: {', '.join(dup[:5])}")
    return found


def _is_data_file(f: Path) -> bool:
    name = f.name.lower()
    if name.endswith(MASK_SUFFIX) or name.endswith(LABELS_SUFFIX) or name in CAMERA_FILES:
        return False
    return f.suffix.lower() in DEPTH_SUFFIXES + CLOUD_SUFFIXES


def _capture_files(f: Path) -> CaptureFiles:
    stem = f.name[: -len(f.suffix)]
    folder = f.parent
    mask = folder / (stem + MASK_SUFFIX)
    labels = folder / (stem + LABELS_SUFFIX)
    camera = next((c for c in (folder / f"{stem}{CAMERA_SUFFIX}.json", folder / f"{stem}{CAMERA_SUFFIX}.yaml",
                               *(folder / n for n in CAMERA_FILES)) if c.is_file()), None)
    return CaptureFiles(stem, f, mask if mask.is_file() else None, labels if labels.is_file() else None, camera)


def ingest_capture(files: CaptureFiles, class_name: str, options: IngestOptions) -> Capture:
    """Load one capture and resample it to the training camera (module docstring)."""
    obj_class = get_class(class_name)
    J = obj_class.n_joints
    size = None
    if options.intrinsics is not None:
        K_src = np.asarray(options.intrinsics, np.float64)
    elif files.camera is not None:
        K_src, size = load_intrinsics(files.camera)
    else:
        raise UserError(f"{files.data}: intrinsics missing; pass --intrinsics FILE or --fx/--fy/--cx/--cy, "
                        f"or put camera.json next to it")
    if files.is_cloud:
        size = size or options.source_size
        if size is None:
            raise UserError(f"{files.data}: rasterising a point cloud needs the sensor's image size "
                            f"(width/height in the camera file, or --source-size WxH)")
        check_source_size(size, str(files.data))
        check_intrinsics(K_src, size, str(files.data))
        points = load_cloud(files.data)
        if options.cloud_frame == "camera":
            points = points @ R_CAMERA_TO_OPTICAL.T
        depth = rasterise_cloud(points, K_src, size)
        if not (depth > 0).any():
            raise UserError(f"{files.data}: no point projects into the {size[0]}x{size[1]} image "
                            f"(check --cloud-frame and the intrinsics)")
    else:
        depth = load_depth(files.data, options.depth_units)
        if size is not None and (depth.shape[1], depth.shape[0]) != tuple(size):
            raise UserError(f"{files.data}: depth is {depth.shape[1]}x{depth.shape[0]} px but the camera file "
                            f"{files.camera} says {size[0]}x{size[1]}")
        check_intrinsics(K_src, (depth.shape[1], depth.shape[0]), str(files.data))
    if files.mask is not None:
        mask = load_mask(files.mask, depth.shape, J)
        if not mask.any():
            raise UserError(f"{files.mask}: the mask marks no object pixel")
        if not (depth[mask > 0] > 0).any():
            log.warning("%s: no pixel of the mask has a depth return; the segmented cloud is empty", files.data)
        if not options.keep_background:
            depth = np.where(mask > 0, depth, 0.0)
    else:
        mask = (depth > 0).astype(np.uint8) * np.uint8(MASK_BODY)
    cam = options.camera
    out_size = (cam.width_px, cam.height_px)
    if options.fit == "crop":
        if files.mask is None:
            raise UserError(f"{files.data}: --fit crop needs a segmentation mask ({files.name}{MASK_SUFFIX})")
        K_dst = crop_intrinsics(K_src, mask > 0, out_size, options.crop_margin)
    else:
        K_dst = cam.K
    inside = mask_fraction_inside(mask > 0, K_src, K_dst, out_size)
    if inside == 0.0 and (mask > 0).any():
        raise UserError(f"{files.data}: the object lies outside the training camera's field of view; use --fit crop")
    if inside < 1.0:
        log.warning("%s: %.1f%% of the object's pixels fall outside the training camera's field of view",
                    files.data, 100.0 * (1.0 - inside))
    depth_r, mask_r = resample_depth(depth, mask, K_src, K_dst, out_size, options.resample)
    if files.mask is not None and not options.keep_background:
        depth_r = np.where(mask_r > 0, depth_r, 0.0)
    if (depth[mask > 0] > 0).any() and not (depth_r[mask_r > 0] > 0).any():
        raise UserError(f"{files.data}: no depth return of the object survives resampling onto the "
                        f"{out_size[0]}x{out_size[1]} training camera (fx={K_src[0, 0]:g}, fy={K_src[1, 1]:g} px); "
                        f"check the intrinsics, or use --fit crop")
    depth_r = (np.round(depth_r / DEPTH_QUANTUM_M) * DEPTH_QUANTUM_M).astype(np.float32)
    labels = load_ground_truth(files.labels, J, class_name) if files.labels is not None else empty_labels(J)
    return Capture(files.name, depth_r, mask_r, K_dst, labels, inside, files.labels is not None)


# --------------------------------------------------------------------------------------
# Writing the split
# --------------------------------------------------------------------------------------

def real_sample_id(class_name: str, split: str, capture_name: str) -> int:
    """Stable 63-bit id of a real image: blake2b-64 of ``"{class}/{split}/{capture}"`` >> 1."""
    text = f"{class_name}/{split}/{capture_name}"
    return int.from_bytes(hashlib.blake2b(text.encode("utf-8"), digest_size=8).digest(), "little") >> 1


def vfov_deg_of(K: np.ndarray, height_px: int) -> float:
    """Vertical field of view (deg) of intrinsics ``K`` for images ``height_px`` rows high."""
    return math.degrees(2.0 * math.atan(0.5 * height_px / K[1, 1]))


def _appendable(manifest: dict, split_dir: Path) -> tuple[list, list, list, tuple[int, int]]:
    """``(shard records, object names, capture names, (W, H))`` of a real split's manifest,
    checked to be what :func:`write_real_split` writes (a :class:`UserError` otherwise)."""
    def names(v) -> bool:
        return isinstance(v, list) and all(isinstance(x, str) and x for x in v)

    try:
        real, cam, shards = manifest["real"], manifest["config"]["camera"], manifest["shards"]
        size = (cam["width_px"], cam["height_px"])
        ok = (isinstance(real, dict) and names(real.get("objects")) and names(real.get("captures"))
              and all(isinstance(v, int) and not isinstance(v, bool) for v in size) and isinstance(shards, list)
              and all(isinstance(r, dict) and isinstance(r.get("object_images", {}), dict)
                      and all(str(k).isdigit() and isinstance(c, int) and not isinstance(c, bool) and c > 0
                              for k, c in r.get("object_images", {}).items()) for r in shards))
    except (KeyError, TypeError):
        ok = False
    if not ok:
        raise UserError(f"{split_dir}/manifest.json: corrupt real-split record; cannot --append (run 'artdata verify')")
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
    from .safeio import ensure_dir, remove_created_dirs
    from .shards import MANIFEST_NAME, read_manifest, shard_name, write_manifest, write_shard

    if not captures:
        raise UserError("no captures to ingest")
    if not split or "/" in split or "\0" in split or split.startswith("."):
        raise UserError(f"invalid split name {split!r}")
    if append and overwrite:
        raise UserError("--append and --overwrite are mutually exclusive")
    obj_class = get_class(class_name)
    options = options or IngestOptions()
    camera = camera or options.camera
    split_dir = Path(out_root) / class_name / split
    if split_dir.is_symlink() or (split_dir.exists() and not split_dir.is_dir()):
        raise UserError(f"{split_dir} is a symbolic link or a file; give --out a folder where the split can be written")
    ours = [p for p in split_dir.iterdir() if _is_ours(p)] if split_dir.is_dir() else []
    foreign = [p.name for p in split_dir.iterdir() if not _is_ours(p)] if split_dir.is_dir() else []
    if foreign:
        raise UserError(f"{split_dir} holds files 'artdata ingest' did not write (e.g. {foreign[0]!r}); "
                        f"move them or choose another --split")
    existing = [p for p in ours if p.name == MANIFEST_NAME or p.suffix == ".h5"]
    old_shards: list[dict] = []
    objects: list[str] = []
    names: list[str] = []
    if existing:
        if overwrite:
            pass  # replaced below, once the new split is complete
        elif append:
            old = read_manifest(split_dir)
            if old.get("class_name") != class_name or "real" not in old:
                raise UserError(f"{split_dir} does not hold ingested real data of class {class_name}; cannot --append")
            old_shards, objects, names, old_size = _appendable(old, split_dir)
            if old_size != (camera.width_px, camera.height_px):
                raise UserError(f"{split_dir} holds {old_size[0]}x{old_size[1]} images; "
                                f"cannot --append {camera.width_px}x{camera.height_px}")
        else:
            raise UserError(f"{split_dir} already holds data; pass --append to add captures or --overwrite to replace them")
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

    def write_all(split_dir: Path) -> None:
        """Shards of ``captures`` from shard ``next_index`` on (paths added to ``written``),
        then the manifest, into ``split_dir``."""
        nonlocal next_index
        J = obj_class.n_joints
        H, W = camera.height_px, camera.width_px
        field_names = {f.name for f in FIELDS}
        for members in groups.values():
            for start in range(0, len(members), MAX_IMAGES_PER_SHARD):
                chunk = members[start : start + MAX_IMAGES_PER_SHARD]
                N = len(chunk)
                arrays = {
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
                attrs = {
                    "format_version": FORMAT_VERSION,
                    "class_name": class_name,
                    "split": split,
                    "seed": 0,
                    "n_objects": len(per_object),
                    "object_start": int(obj_idx.min()),
                    "object_stop": int(obj_idx.max()) + 1,
                    "images_per_object": max(per_object.values()),
                    "n_joints": J,
                    "joint_names": json.dumps([j.name for j in obj_class.joints]),
                    "joint_types": json.dumps(list(obj_class.joint_types)),
                    "image_width": W,
                    "image_height": H,
                    "vfov_deg": vfov_deg_of(K, H),
                    "depth_quantum_m": DEPTH_QUANTUM_M,
                    "min_part_pixels": 0,
                    "mean_object": 0,
                    "noise_model": "real",
                    "real": 1,
                    "capture_names": json.dumps([captures[i].name for i in chunk]),
                    "has_ground_truth": np.array([captures[i].has_labels for i in chunk], np.int8),
                    "sampling_table": obj_class.table.to_json(),
                    "package_version": __version__,
                }
                target = split_dir / shard_name(next_index)
                if target.exists():
                    raise UserError(f"{target} exists but the manifest does not list it; run 'artdata verify' on the split")
                written.append(target)
                rec = write_shard(target, arrays, attrs, K, R_CAMERA_TO_OPTICAL)
                rec.update(object_start=attrs["object_start"], object_stop=attrs["object_stop"], object_images=per_object)
                records.append(rec)
                names.extend(captures[i].name for i in chunk)
                next_index += 1
        n_images = sum(r["n_images"] for r in records)
        per_obj_total: dict[int, int] = {}
        for r in records:
            for o, n in r.get("object_images", {}).items():
                per_obj_total[int(o)] = per_obj_total.get(int(o), 0) + int(n)
        config = SplitConfig(class_name, split=split, n_objects=len(objects), seed=0, images_per_object=max(per_obj_total.values()),
                             objects_per_shard=len(objects), camera=camera, table=obj_class.table)
        manifest = {
            "format_version": FORMAT_VERSION,
            "package_version": __version__,
            "class_name": class_name,
            "split": split,
            "seed": 0,
            "complete": True,
            "n_objects": len(objects),
            "n_images": n_images,
            "n_shards_expected": len(records),
            "config": config.to_dict(),
            "shards": records,
            "real": {"objects": objects, "captures": names, "options": options.to_dict()},
        }
        write_manifest(split_dir, manifest)

    # Appending writes new shard files beside the old ones and then replaces the manifest;
    # anything else builds the split in a hidden sibling folder and swaps it in when complete,
    # so a failure (disk full, a bad capture) leaves the previous split as it was.
    in_place = bool(append and existing)
    work_dir = split_dir if in_place else split_dir.parent / f".{split}.ingest-{os.getpid()}"
    created = ensure_dir(work_dir)
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


def _is_ours(p: Path) -> bool:
    """A file ``artdata ingest`` writes in a split folder (manifest, shards, their partial files)."""
    from .shards import MANIFEST_NAME, TMP_SUFFIX

    name = p.name[: -len(TMP_SUFFIX)] if p.name.endswith(TMP_SUFFIX) else p.name
    return p.is_file() and not p.is_symlink() and (name == MANIFEST_NAME or re.fullmatch(r"shard-[0-9]{5,}\.h5", name) is not None)


def _swap_in(new_dir: Path, split_dir: Path) -> None:
    """Rename the complete ``new_dir`` to ``split_dir``; an old split there is moved aside
    first and its files removed afterwards (only files :func:`_is_ours`)."""
    old_dir = split_dir.parent / f".{split_dir.name}.old-{os.getpid()}"
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


