"""Depth, mask and point-cloud files of real captures: 16-bit PNG (mm), float EXR or ``.npy``
(m) depth images, segmentation mask PNGs, ``.ply``/``.pcd`` point clouds and their rasterisation
with the intrinsics (nearest point per pixel)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..format import MASK_BODY, MASK_FIRST_PART
from ..units import MM_PER_M
from .intrinsics import check_source_size

DEPTH_SUFFIXES = (".png", ".exr", ".npy")
CLOUD_SUFFIXES = (".ply", ".pcd")
#: Depths beyond this (m) are not plausible for an indoor sensor: a float image in metres with
#: larger values is most likely in millimetres (refused; pass the units).
MAX_PLAUSIBLE_DEPTH_M = 20.0
#: Depth sensors return nothing closer than about 0.1 m (Kinect v2: 0.5 m; RealSense D4xx:
#: 0.1-0.3 m): a capture whose median depth is below this is in other units than assumed.
MIN_PLAUSIBLE_DEPTH_M = 0.1
DEPTH_UNITS = ("auto", "m", "mm")


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
        raise UserError(f"{path}: depth up to {top:.4g} m is not plausible for a depth sensor{hint}")
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
        with warnings.catch_warnings():  # PIL warns above 89 million pixels; the size is checked below (120 million)
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
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

        from ..exr.files import c_output_silenced, exr_size

        try:
            size = exr_size(path)
        except Exception as exc:
            raise UserError(f"{path}: not a readable EXR file ({str(exc).splitlines()[0]})") from None
        check_source_size(size, str(path))  # before any pixel is decoded (a 300 KB file can declare 10^9)
        try:
            with c_output_silenced(), OpenEXR.File(str(path)) as f:
                channels = {c: np.asarray(v.pixels) for c, v in f.channels().items()}
        except Exception as exc:
            raise UserError(f"{path}: not a readable EXR file ({str(exc).splitlines()[0]})") from None
        name = next((c for c in ("Z", "depth", "Y", "R") if c in channels), None)
        if name is None and len(channels) == 1:
            name = next(iter(channels))
        if name is None:
            raise UserError(f"{path}: no depth channel (expected Z, depth, Y or R; found {', '.join(sorted(channels))})")
        raw = channels[name]
        if raw.ndim != 2:
            raise UserError(f"{path}: channel {name!r} has shape {raw.shape}, expected a single-channel image")
        return _to_metres(raw, "m" if units == "auto" else units, path)
    if suffix == ".npy":
        try:
            with np.errstate(over="ignore"):  # a header's shape whose size overflows: numpy's own error below
                raw = np.load(path, allow_pickle=False, mmap_mode="r")
        except Exception as exc:
            raise UserError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0]})") from None
        if not isinstance(raw, np.ndarray):  # np.load reads a .npz archive whatever its name
            getattr(raw, "close", lambda: None)()
            raise UserError(f"{path}: a .npz archive of arrays, not a .npy array; save the depth image with np.save")
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

    A mask whose values are all in {0, 255}, {0, 65535} or {0, 1} is binary (object = body).  Otherwise its
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
    unique = np.unique(raw)
    if not np.isfinite(unique).all() or (unique != np.round(unique)).any():  # a float image of fractions
        raise UserError(f"{path}: mask values must be whole numbers (0/255, 0/1 or labels), got "
                        f"{[float(v) for v in unique[unique != np.round(unique)][:4]]}")
    values = set(unique.tolist())
    if values <= {0, 255} or values <= {0, 1} or values <= {0, 65535}:  # binary (8- or 16-bit white)
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
