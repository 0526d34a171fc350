"""Camera intrinsics of real captures: the matrix from fx, fy, cx, cy, the checks that they
are a plausible pinhole camera, and camera-info files (JSON/YAML: ``fx/fy/cx/cy``, ROS
``CameraInfo`` ``K``/``k``, a ROS calibration file's ``camera_matrix``)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import cast

import numpy as np

from articulated_dataset.core.errors import UserError

#: Fields of view (deg) a pinhole depth camera can have: intrinsics outside them (e.g.
#: fx = 1e308 px) are a mistake, not a lens.
MIN_PLAUSIBLE_FOV_DEG = 1.0
MAX_PLAUSIBLE_FOV_DEG = 170.0
#: Largest source frame accepted (pixels): 4096 x 4096, three times the largest depth
#: sensors' frames (structured-light cameras such as Zivid 2+: 2448 x 2048, 5 Mpx).  Larger is
#: not a depth sensor's image; the limit is checked from a file's header before its pixels are
#: decoded (a 230 KB PNG can declare 120 Mpx), and keeps reading and resampling one frame
#: under 1 GB of memory.
MAX_SOURCE_PIXELS = 4096 * 4096
#: Deepest nesting of a file's lists of numbers (labels nest 2 deep; numpy allows 32 dimensions; the
#: check recurses once per level, so 600 levels were a RecursionError).
MAX_NUMBER_NESTING = 32
#: Largest camera-info or label file read (bytes): a camera's intrinsics take a few hundred.
MAX_MAPPING_BYTES = 1_000_000


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def read_numbers(value, what: str) -> np.ndarray:
    """``value`` (a number or nested lists of numbers, as read from JSON/YAML) as float64;
    strings, booleans, null and mappings are a :class:`UserError` (never converted)."""
    def ok(v, depth: int = 0) -> bool:
        return _is_number(v) or (isinstance(v, (list, tuple)) and depth < MAX_NUMBER_NESTING
                                 and all(ok(x, depth + 1) for x in v))
    if not ok(value):
        raise UserError(f"{what} must be numbers (nested at most {MAX_NUMBER_NESTING} deep), got {str(value)[:80]}")
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


def pinhole_matrix(m: np.ndarray, where: str = "intrinsics") -> np.ndarray:
    """A 3x3 camera matrix ``m`` checked to be a pinhole camera's ``[[fx, 0, cx], [0, fy, cy],
    [0, 0, 1]]`` (no skew; finite; positive focal lengths), as float64 (:func:`intrinsics_matrix`);
    anything else (a transposed matrix, a scaled one) is a :class:`UserError`."""
    m = np.asarray(m, np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all():
        raise UserError(f"{where} must be a finite 3x3 matrix, got shape {m.shape}")
    if abs(m[0, 1]) > 0 or abs(m[1, 0]) > 0 or abs(m[2, 2] - 1.0) > 1e-9 or m[2, 0] != 0 or m[2, 1] != 0:
        raise UserError(f"{where} must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew), got {np.round(m, 3).tolist()}")
    return intrinsics_matrix(m[0, 0], m[1, 1], m[0, 2], m[1, 2], where)


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


def read_mapping(path: Path, max_bytes: int = MAX_MAPPING_BYTES, what: str = "a camera or label file") -> dict:
    """A camera-info or label file (``what``: JSON, or YAML by its suffix; UTF-8, a byte-order mark
    allowed) as a dict; a file above ``max_bytes``, one that does not parse, YAML aliases and a
    top level that is not a mapping are a :class:`UserError`."""
    if not path.is_file():
        raise UserError(f"file not found: {path}")
    try:
        if path.stat().st_size > max_bytes:
            raise UserError(f"{path}: {path.stat().st_size:,} bytes is not {what} (at most {max_bytes:,})")
        text = path.read_bytes().decode("utf-8-sig")
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
            data = yaml.load(text, Loader=_no_alias_loader(yaml))
        else:
            data = json.loads(text)
    except UserError:
        raise
    except Exception as exc:  # parse errors of either format are the user's
        raise UserError(f"cannot parse {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a mapping (object) at the top level")
    bad = [k for k in data if not isinstance(k, str)]
    if bad:  # YAML allows 1:, ~:, true: keys; every key we read is a name
        raise UserError(f"{path}: keys must be names (text), got {str(bad[0])[:40]!r}")
    return data


def _no_alias_loader(yaml):
    """PyYAML's SafeLoader refusing aliases (``*name``): a camera or label file never needs
    them, and nested aliases expand a few hundred bytes into billions of values (a hang)."""
    class NoAliasLoader(yaml.SafeLoader):  # type: ignore[name-defined]  # yaml: the module, passed in
        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                raise yaml.YAMLError("YAML aliases (*name) are not accepted")
            return super().compose_node(parent, index)
    return NoAliasLoader


def load_intrinsics(path: str | Path) -> tuple[np.ndarray, tuple[int, int] | None]:
    """K (3x3) and the image size ``(width, height)`` (None if the file has none) of a
    camera-info JSON/YAML file.

    Accepted keys: ``fx, fy, cx, cy``; or ``K``/``k`` (ROS ``CameraInfo``, 9 numbers row-major
    or 3x3); or ``camera_matrix: {data: [9 numbers]}`` (ROS calibration YAML).  Size:
    ``width``/``height`` or ``image_width``/``image_height``.
    """
    path = Path(path)
    d = read_mapping(path)
    if all(k in d for k in ("fx", "fy", "cx", "cy")):
        # (four scalars, then the place: mypy cannot count the unpacked generator)
        K = intrinsics_matrix(*(_scalar(d, k, path) for k in ("fx", "fy", "cx", "cy")), str(path))  # type: ignore[call-arg, arg-type]
    else:
        raw = d.get("K", d.get("k"))
        if raw is None and isinstance(d.get("camera_matrix"), dict):
            raw = d["camera_matrix"].get("data")
        if raw is None:
            raise UserError(f"{path}: no intrinsics found (expected fx/fy/cx/cy, K, k or camera_matrix.data)")
        m = read_numbers(raw, f"{path}: camera matrix")
        if m.size != 9:
            raise UserError(f"{path}: camera matrix must have 9 numbers, got {m.size}")
        K = pinhole_matrix(m.reshape(3, 3), f"{path}: camera matrix")
    w = d.get("width", d.get("image_width"))
    h = d.get("height", d.get("image_height"))
    size: tuple[int, int] | None = None
    if w is not None or h is not None:
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (w, h)):
            raise UserError(f"{path}: image width and height must both be whole numbers of pixels, got {w!r} x {h!r}")
        size = cast("tuple[int, int]", (w, h))  # both ints: checked just above
        check_source_size(size, str(path))
        check_intrinsics(K, size, str(path))
    return K, size


def _scalar(d: dict, key: str, path: Path) -> float:
    a = read_numbers(d[key], f"{path}: {key}")
    if a.ndim != 0:
        raise UserError(f"{path}: {key} must be one number, got {str(d[key])[:80]}")
    return float(a)
