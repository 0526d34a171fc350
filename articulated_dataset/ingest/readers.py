"""Depth, mask and point-cloud files of real captures: 16-bit PNG (mm), float EXR or ``.npy``
(m) depth images, segmentation mask PNGs, ``.ply``/``.pcd`` point clouds and their rasterisation
with the intrinsics (nearest point per pixel)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.images.intrinsics import check_source_size
from articulated_dataset.core.units import MM_PER_M
from articulated_dataset.format import MASK_BODY, MASK_FIRST_PART

DEPTH_SUFFIXES = (".png", ".exr", ".npy")
CLOUD_SUFFIXES = (".ply", ".pcd")
#: Depths beyond this (m) are not plausible for an indoor sensor: a float image in metres with
#: larger values is most likely in millimetres (refused; pass the units).
MAX_PLAUSIBLE_DEPTH_M = 20.0
#: Depth sensors return nothing closer than about 0.1 m (Kinect v2: 0.5 m; RealSense D4xx:
#: 0.1-0.3 m): a capture whose median depth is below this is in other units than assumed.
MIN_PLAUSIBLE_DEPTH_M = 0.1
DEPTH_UNITS = ("auto", "m", "mm")
#: Longest PLY header read (bytes): a header is a few lines of element and property
#: declarations and comments; a file without ``end_header`` within this many bytes is not a PLY.
MAX_PLY_HEADER_BYTES = 1 << 20


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
        hint = f"; it looks like millimetres: pass {option('depth_units')} mm" if units == "m" else ""
        raise UserError(f"{path}: depth up to {top:.4g} m is not plausible for a depth sensor{hint}")
    returns = depth[depth > 0]
    median = float(np.median(returns)) if returns.size else 0.0
    if returns.size and median < MIN_PLAUSIBLE_DEPTH_M:
        as_m = median * (MM_PER_M if units == "mm" else 1.0)
        hint = (f"; it looks like metres: pass {option('depth_units')} m"
                if units == "mm" and MIN_PLAUSIBLE_DEPTH_M <= as_m <= MAX_PLAUSIBLE_DEPTH_M
                else f"; check the depth units ({option('depth_units')})")
        raise UserError(f"{path}: median depth {1000 * median:.3g} mm read as {units_name(units)} is closer than any "
                        f"depth sensor measures ({MIN_PLAUSIBLE_DEPTH_M:g} m){hint}")
    return depth


def units_name(units: str) -> str:
    """``millimetres`` for ``mm``, else ``metres``."""
    return "millimetres" if units == "mm" else "metres"


#: PIL modes of a single-channel 16-bit PNG (a depth image in millimetres).
DEPTH_PNG_MODES = ("I;16", "I;16B", "I;16L", "I")


def _read_image(path: Path, what: str, modes: tuple[str, ...] | None = None) -> tuple[np.ndarray, str]:
    """Pixels and PIL mode of a PNG file (PNG content and a ``.png`` name, see
    :func:`~articulated_dataset.core.images.exr.read_png`) of at most
    :data:`~articulated_dataset.core.images.intrinsics.MAX_SOURCE_PIXELS` and, if given, of one of
    ``modes``, both checked from the header before any pixel is decoded; anything else is a
    one-line UserError."""
    from articulated_dataset.core.images.exr import read_png

    def check(path: Path, size: tuple[int, int], mode: str) -> None:
        check_source_size(size, str(path))
        if modes is not None and mode not in modes:
            raise UserError(f"{path}: depth PNG must be single-channel 16-bit (millimetres), got mode {mode}; "
                            f"units of 8-bit or colour PNGs are unknown")

    return read_png(path, what, check)


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
        raw, _ = _read_image(path, "depth", DEPTH_PNG_MODES)
        return _to_metres(raw, "mm" if units == "auto" else units, path)
    if suffix == ".exr":
        return _to_metres(_read_exr_depth(path), "m" if units == "auto" else units, path)
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
                raise UserError(f"{path}: integer depth array has unknown units; pass {option('depth_units')} mm or m")
            units = "m"
        return _to_metres(raw, units, path)
    raise UserError(f"{path}: unsupported depth file type {suffix!r} (expected {', '.join(DEPTH_SUFFIXES)})")


def _read_exr_depth(path: Path) -> np.ndarray:
    """The depth channel of an EXR file as an image of its display window (the image the
    intrinsics describe), float64: the stored pixels (the data window) in their place, NaN (no
    return) where the file stores none; both windows' sizes are checked from the header first."""
    import OpenEXR

    from articulated_dataset.core.images.exr import c_output_silenced, exr_windows, in_display_window, window_size

    def unreadable(exc: Exception) -> UserError:
        return UserError(f"{path}: not a readable EXR file ({(str(exc).splitlines() or [type(exc).__name__])[0]})")

    try:
        data, display = exr_windows(path)
    except Exception as exc:  # OpenEXR's errors on a damaged file have no common type
        raise unreadable(exc) from None
    for window in (data, display):  # before any pixel is decoded (a 300 KB file can declare 10^9)
        check_source_size(window_size(window), str(path))
    try:
        with c_output_silenced(), OpenEXR.File(str(path)) as f:
            channels = {c: np.asarray(v.pixels) for c, v in f.channels().items()}
    except Exception as exc:
        raise unreadable(exc) from None
    name = next((c for c in ("Z", "depth", "Y", "R") if c in channels), None)
    if name is None and len(channels) == 1:
        name = next(iter(channels))
    if name is None:
        raise UserError(f"{path}: no depth channel (expected Z, depth, Y or R; found {', '.join(sorted(channels))})")
    raw = channels[name]
    if raw.ndim != 2 or raw.dtype.kind not in "fiu":
        raise UserError(f"{path}: channel {name!r} has shape {raw.shape} and type {raw.dtype}, expected a "
                        f"single-channel numeric image")
    return in_display_window(raw, data, display)


def load_mask(path: str | Path, shape: tuple[int, int], n_joints: int) -> np.ndarray:
    """A segmentation mask as dataset labels (uint8: 0 background, 1 body, 2 + j part j).

    A mask whose values are all in {0, 255}, {0, 65535} or {0, 1} is binary (object = body).  Otherwise its
    values must be labels 0 .. 1 + J.  Its size must equal ``shape`` (H, W) of the depth.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"mask file not found: {path}")
    raw, mode = _read_image(path, "mask")
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
        except UnicodeDecodeError as exc:
            raise UserError(f"{path}: malformed PCD data ({str(exc).splitlines()[0][:120]})") from None
        if not rows:  # refused by the caller: no finite points
            return np.empty((0, 3))
        if len(rows) != n:  # (a header declaring more points than the file holds was read as the rows there are)
            raise UserError(f"{path}: PCD data holds {len(rows):,} points, its header declares {n:,}")
        try:
            table = np.loadtxt(rows, ndmin=2)
        except ValueError as exc:
            raise UserError(f"{path}: malformed PCD data ({str(exc).splitlines()[0][:120]})") from None
        if table.shape[1] != sum(counts):
            raise UserError(f"{path}: PCD rows have {table.shape[1]} values, the header describes {sum(counts)}")
        cols = np.cumsum([0] + counts)
        return np.stack([table[:, cols[fields.index(a)]] for a in "xyz"], axis=1)
    if kind == "binary":
        dtype = np.dtype([(f"f{i}", f"<{codes[t]}{s}", (c,)) for i, (t, s, c) in enumerate(zip(types, sizes, counts))])
        if len(data) - offset < n * dtype.itemsize:
            raise UserError(f"{path}: PCD data is shorter than its header says ({n} points)")
        rec = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
        return np.stack([rec[f"f{fields.index(a)}"][:, 0] for a in "xyz"], axis=1).astype(np.float64)
    raise UserError(f"{path}: PCD DATA {kind!r} is not supported (save it as ascii or binary)")


def _check_ply_rows(path: Path) -> None:
    """An ASCII PLY's data must hold the rows its header declares (trimesh reads the rows there
    are: a header declaring 2e9 vertices over one line was read as a one-point cloud), counted
    before anything is parsed; a binary PLY's length is checked against its header by trimesh."""
    with open(path, "rb") as f:
        head = f.read(MAX_PLY_HEADER_BYTES)
        end = head.find(b"end_header")
        lines = [ln.split() for ln in head[:end].decode("ascii", "replace").lower().split("\n")]
        if end < 0 or "ply" not in " ".join(lines[0]):
            raise UserError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header in its first "
                            f"{MAX_PLY_HEADER_BYTES:,} bytes)")
        if len(lines) < 2 or "ascii" not in " ".join(lines[1]):  # trimesh's test of the format line
            return
        declared = 0
        for ln in lines[2:]:
            if ln and "element" in ln[0]:  # (as trimesh reads a header line)
                if len(ln) != 3 or not ln[2].isdigit():
                    raise UserError(f"{path}: malformed PLY header line {' '.join(ln)[:80]!r} "
                                    f"(expected 'element NAME COUNT')")
                declared += int(ln[2])
        f.seek(head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head))
        rows, last = 0, b"\n"
        for block in iter(lambda: f.read(1 << 20), b""):
            rows, last = rows + block.count(b"\n"), block[-1:]
        rows += last != b"\n"  # a last row without a newline
    if declared > rows:
        raise UserError(f"{path}: the PLY header declares {declared:,} rows of data, its data has {rows:,} lines")


def load_cloud(path: str | Path) -> np.ndarray:
    """Points (N, 3) float64, metres, of a ``.ply`` (trimesh) or ``.pcd`` file; NaN rows dropped."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"point cloud file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        import trimesh

        _check_ply_rows(path)
        try:
            # skip_materials: a colour texture the file names (``comment TextureFile``) is not
            # needed and never opened (it could name any file: a FIFO, one elsewhere, a non-image).
            geom = trimesh.load(str(path), file_type="ply", process=False, skip_materials=True)
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
