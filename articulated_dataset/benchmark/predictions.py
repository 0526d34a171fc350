"""The ``predictions.h5`` format: what a method hands to ``artdata score``.

Layout (format version :data:`PREDICTIONS_FORMAT_VERSION`)::

    /                      attrs: format_version, method (+ free-form attrs of the writer)
    /<class>/              one group per object class; attr mixture_layout (JSON list) if mixtures
        sample_id          (N,)      int64    ground-truth ids of the predicted images (unique)
        axis_pose          (N, J, 7) float    axis position (m) + quaternion (w, x, y, z), camera frame
        q                  (N, J)    float    configuration (rad revolute, m prismatic)
        geometry           (N, 4)    float    optional: depth, width, height (m), chirality (0..1)
        part_offset        (N, J, 3) float    optional: part centre in the axis frame (m)
        mixture_weights    (N, M)    float    optional, with the next two: component weights (sum 1)
        mixture_means      (N, M, D) float    component means, label units (m, rad), NOT normalised
        mixture_scales     (N, M, D) float    component standard deviations (> 0), label units

Rows of every dataset of a group are aligned: row i describes image ``sample_id[i]``.  Rows
need not follow the truth's order and may cover part of the truth (partial coverage is
reported by the scorer).  Column d of the mixture datasets is named by
``mixture_layout[d]`` (see docs/scoring.md: ``j{j}.origin.x``, ``j{j}.axis.y``,
``j{j}.xaxis.z``, ``j{j}.q``, ``j{j}.offset.x``, ``geometry.depth`` ...).

:func:`write_predictions` validates and writes a file; :func:`read_predictions` validates a
file (shapes, dtypes, finite values within +-:data:`MAX_ABS_VALUE`, unit quaternions, unique
ids, sizes >= 0 and a chirality in [0, 1], mixture parameters, names, layout and size) and
raises :class:`~articulated_dataset.core.errors.DataFormatError` with one line naming the
dataset for anything wrong.  Non-unit quaternions are normalised with a logged warning;
zero-length ones are rejected.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import h5py
import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.core.safeio import atomic_write_h5, available_memory_bytes, format_bytes
from articulated_dataset.format import attr_value, open_h5
from articulated_dataset.format.shards import JSON_TEXT_ERRORS

log = logging.getLogger(__name__)

PREDICTIONS_FORMAT_VERSION = "1.0"
REQUIRED_DATASETS = ("sample_id", "axis_pose", "q")
OPTIONAL_DATASETS = ("geometry", "part_offset")
MIXTURE_DATASETS = ("mixture_weights", "mixture_means", "mixture_scales")
ALL_DATASETS = REQUIRED_DATASETS + OPTIONAL_DATASETS + MIXTURE_DATASETS
MIXTURE_LAYOUT_ATTR = "mixture_layout"
#: Columns of one axis pose: position (3, m) + quaternion (4).
POSE_WIDTH = 7
#: Columns of geometry: depth, width, height (m), chirality.
GEOMETRY_WIDTH = 4
#: Columns of geometry that are sizes (depth, width, height in m): never negative.
GEOMETRY_SIZE_COLUMNS = ("depth", "width", "height")
#: Column of geometry that holds the chirality: a probability of "hinge on the right" or a 0/1
#: label, so within CHIRALITY_RANGE.
CHIRALITY_COLUMN = 3
CHIRALITY_RANGE = (0.0, 1.0)
#: Quaternions shorter than this cannot be normalised (no rotation is defined): rejected.
MIN_QUATERNION_NORM = 1e-6
#: |norm - 1| above this is reported (a float32 unit quaternion is within ~1e-7 of 1).
QUATERNION_NORM_TOL = 1e-4
#: |sum(weights) - 1| above this is reported before renormalising.
WEIGHT_SUM_TOL = 1e-3
#: Largest magnitude accepted in any float dataset (label units: m, rad; weights; scales).
#: Objects are metres from the camera: a value past this is not an estimate but a bug, and
#: it keeps every metric (squares of differences, sums over 10^6 images) far from overflow.
MAX_ABS_VALUE = 1e6
#: Most mixture components per image (the dense model writes at most 5, the paper's MDN 20 by
#: default); checked from a dataset's shape before it is read (a file of a few kilobytes of
#: compressed zeros can declare gigabytes of components).
MAX_MIXTURE_COMPONENTS = 4096
#: Longest method name (it is a table label and appears in messages).
MAX_METHOD_CHARS = 100
#: A class group's name: a registry-style name (letters, digits, ``_ . -``; 1-32 characters).
_CLASS_GROUP_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,31}")
#: Largest sample id (ids are 63-bit: int64 >= 0).
MAX_SAMPLE_ID = np.iinfo(np.int64).max
#: Fraction of the available memory the datasets of one predictions file may take once read.
MAX_MEMORY_FRACTION = 0.5


def bounded_geometry(geometry) -> np.ndarray:
    """A method's geometry estimates (N, 4) as a predictions file holds them (float64): the
    chirality, a regression of a 0/1 label, clipped to :data:`CHIRALITY_RANGE`, and the sizes,
    which are never negative, clipped at 0 (a briefly trained network's estimate may fall below)."""
    g = np.array(geometry, np.float64)
    g[:, CHIRALITY_COLUMN] = np.clip(g[:, CHIRALITY_COLUMN], *CHIRALITY_RANGE)
    g[:, :CHIRALITY_COLUMN] = np.maximum(g[:, :CHIRALITY_COLUMN], 0.0)
    return g


def beyond_bounds(a: np.ndarray, *, nan_allowed: bool) -> np.ndarray:
    """Elementwise: the values of ``a`` that no label or prediction may hold: infinite, beyond
    +-:data:`MAX_ABS_VALUE`, or NaN unless ``nan_allowed`` (a truth label that is not given)."""
    a = np.asarray(a, np.float64)
    with np.errstate(invalid="ignore"):
        out = np.isinf(a) | (np.abs(a) > MAX_ABS_VALUE)
    return out if nan_allowed else out | np.isnan(a)


def _shape_str(shape) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _check_float(where: str, name: str, a: np.ndarray) -> np.ndarray:
    if a.dtype.kind != "f":
        raise DataFormatError(f"{where}/{name}: dtype {a.dtype}, expected a float type (float32 or float64)")
    a = np.asarray(a, np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        first = np.argwhere(bad)[0]
        raise DataFormatError(f"{where}/{name}: {int(bad.sum())} NaN/inf values (first at index {tuple(int(i) for i in first)})")
    huge = np.abs(a) > MAX_ABS_VALUE
    if huge.any():
        first = np.argwhere(huge)[0]
        raise DataFormatError(f"{where}/{name}: {int(huge.sum())} values beyond +/-{MAX_ABS_VALUE:g} (label units: m, rad; "
                              f"first {a[tuple(first)]:.3g} at index {tuple(int(i) for i in first)})")
    return a


def _check_geometry(where: str, g: np.ndarray) -> np.ndarray:
    """``g`` (N, 4) if its sizes are >= 0 and its chirality lies in :data:`CHIRALITY_RANGE`; else a
    :class:`DataFormatError` naming the first offending value (magnitudes are checked before)."""
    for c, name in enumerate(GEOMETRY_SIZE_COLUMNS):
        bad = np.flatnonzero(g[:, c] < 0)
        if bad.size:
            raise DataFormatError(f"{where}/geometry: {name} below 0 in {bad.size} row(s) (a size is >= 0; first "
                                  f"{g[bad[0], c]:.3g} m at row {int(bad[0])})")
    lo, hi = CHIRALITY_RANGE
    chirality = g[:, CHIRALITY_COLUMN]
    bad = np.flatnonzero((chirality < lo) | (chirality > hi))
    if bad.size:
        raise DataFormatError(f"{where}/geometry: chirality outside [{lo:g}, {hi:g}] in {bad.size} row(s) (a "
                              f"probability of the hinge on the right, or a 0/1 label; first {chirality[bad[0]]:.3g} "
                              f"at row {int(bad[0])})")
    return g


def _check_shape(where: str, name: str, a: np.ndarray, expected: tuple) -> None:
    """``expected`` holds ints or None (any size)."""
    ok = a.ndim == len(expected) and all(e is None or s == e for s, e in zip(a.shape, expected))
    if not ok:
        want = _shape_str("*" if e is None else e for e in expected)
        raise DataFormatError(f"{where}/{name}: shape {_shape_str(a.shape)}, expected {want}")


def _parse_layout(where: str, value) -> list[str]:
    if isinstance(value, bytes):
        try:
            value = value.decode()
        except UnicodeDecodeError:
            raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} is not UTF-8 text") from None
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except JSON_TEXT_ERRORS:
            raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} is not a JSON list of column names") from None
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, (str, bytes)) for v in value):
        raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} must be a list of column names")
    try:  # an array attribute of fixed-length byte strings: its elements are bytes, any bytes
        names = [v.decode() if isinstance(v, bytes) else v for v in value]
    except UnicodeDecodeError:
        raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} holds column names that are not UTF-8") from None
    if not names:  # a 0-column mixture has density 1 everywhere: NLL 0 with nothing predicted
        raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} names no column")
    if len(set(names)) != len(names):
        raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} repeats column names")
    return names


def validate_class(where: str, arrays: dict, *, normalise: bool = True) -> dict:
    """Validate one class's prediction arrays; return them as float64/int64 arrays.

    ``where`` names the group in messages (``file:/class``).  Quaternions are normalised
    (with a warning when off by more than :data:`QUATERNION_NORM_TOL`) if ``normalise``; mixture
    weights are renormalised the same way.  Raises :class:`DataFormatError`.
    """
    for name in REQUIRED_DATASETS:
        if name not in arrays:
            raise DataFormatError(f"{where}: missing dataset {name!r}")
    unknown = sorted(set(arrays) - set(ALL_DATASETS) - {MIXTURE_LAYOUT_ATTR})
    if unknown:
        raise DataFormatError(f"{where}: unknown dataset(s) {', '.join(map(repr, unknown))} (expected {', '.join(ALL_DATASETS)})")
    out: dict = {}

    ids = np.asarray(arrays["sample_id"])
    if ids.dtype.kind not in "iu":
        raise DataFormatError(f"{where}/sample_id: dtype {ids.dtype}, expected int64")
    _check_shape(where, "sample_id", ids, (None,))
    N = ids.shape[0]
    if N == 0:
        raise DataFormatError(f"{where}/sample_id: no predictions (0 rows)")
    if ids.dtype.kind == "u" and (ids > MAX_SAMPLE_ID).any():
        raise DataFormatError(f"{where}/sample_id: ids above {MAX_SAMPLE_ID} (sample ids are 63-bit)")
    ids = ids.astype(np.int64)
    uniq, counts = np.unique(ids, return_counts=True)
    if len(uniq) != N:
        dup = uniq[counts > 1]
        raise DataFormatError(f"{where}/sample_id: {len(dup)} duplicated ids (e.g. {int(dup[0])})")
    out["sample_id"] = ids

    pose = np.asarray(arrays["axis_pose"])
    _check_shape(where, "axis_pose", pose, (N, None, POSE_WIDTH))
    J = pose.shape[1]
    if J == 0:
        raise DataFormatError(f"{where}/axis_pose: zero joints")
    pose = _check_float(where, "axis_pose", pose).copy()
    quat = pose[..., 3:]
    norm = np.linalg.norm(quat, axis=-1)
    zero = norm < MIN_QUATERNION_NORM
    if zero.any():
        first = np.argwhere(zero)[0]
        raise DataFormatError(f"{where}/axis_pose: {int(zero.sum())} zero-length quaternions "
                              f"(first at row {int(first[0])}, joint {int(first[1])})")
    off = np.abs(norm - 1.0) > QUATERNION_NORM_TOL
    if normalise:
        if off.any():
            log.warning("%s/axis_pose: %d non-unit quaternions (norm %.4g..%.4g) normalised",
                        where, int(off.sum()), float(norm.min()), float(norm.max()))
        pose[..., 3:] = quat / norm[..., None]
    out["axis_pose"] = pose

    q = np.asarray(arrays["q"])
    _check_shape(where, "q", q, (N, J))
    out["q"] = _check_float(where, "q", q)

    if "geometry" in arrays:
        g = np.asarray(arrays["geometry"])
        _check_shape(where, "geometry", g, (N, GEOMETRY_WIDTH))
        out["geometry"] = _check_geometry(where, _check_float(where, "geometry", g))
    if "part_offset" in arrays:
        p = np.asarray(arrays["part_offset"])
        _check_shape(where, "part_offset", p, (N, J, 3))
        out["part_offset"] = _check_float(where, "part_offset", p)

    present = [n for n in MIXTURE_DATASETS if n in arrays]
    if present:
        missing = [n for n in MIXTURE_DATASETS if n not in arrays]
        if missing:
            raise DataFormatError(f"{where}: mixture datasets must come together; missing {', '.join(map(repr, missing))}")
        if MIXTURE_LAYOUT_ATTR not in arrays:
            raise DataFormatError(f"{where}: mixture datasets without the {MIXTURE_LAYOUT_ATTR!r} attribute")
        layout = _parse_layout(where, arrays[MIXTURE_LAYOUT_ATTR])
        w = np.asarray(arrays["mixture_weights"])
        _check_shape(where, "mixture_weights", w, (N, None))
        M = w.shape[1]
        if M > MAX_MIXTURE_COMPONENTS:
            raise DataFormatError(f"{where}/mixture_weights: {M} components per image (at most {MAX_MIXTURE_COMPONENTS})")
        if M == 0:
            raise DataFormatError(f"{where}/mixture_weights: zero components")
        mu = np.asarray(arrays["mixture_means"])
        _check_shape(where, "mixture_means", mu, (N, M, len(layout)))
        sigma = np.asarray(arrays["mixture_scales"])
        _check_shape(where, "mixture_scales", sigma, (N, M, len(layout)))
        w = _check_float(where, "mixture_weights", w)
        mu = _check_float(where, "mixture_means", mu)
        sigma = _check_float(where, "mixture_scales", sigma)
        if (w < 0).any():
            raise DataFormatError(f"{where}/mixture_weights: {int((w < 0).sum())} negative weights")
        total = w.sum(axis=1)
        if (total <= 0).any():
            raise DataFormatError(f"{where}/mixture_weights: {int((total <= 0).sum())} rows with all weights zero")
        if (sigma <= 0).any():
            raise DataFormatError(f"{where}/mixture_scales: {int((sigma <= 0).sum())} scales <= 0")
        if normalise:
            bad = np.abs(total - 1.0) > WEIGHT_SUM_TOL
            if bad.any():
                log.warning("%s/mixture_weights: %d rows do not sum to 1 (%.4g..%.4g); renormalised",
                            where, int(bad.sum()), float(total.min()), float(total.max()))
            w = w / total[:, None]
        out.update(mixture_weights=w, mixture_means=mu, mixture_scales=sigma)
        out[MIXTURE_LAYOUT_ATTR] = layout
    elif MIXTURE_LAYOUT_ATTR in arrays:
        raise DataFormatError(f"{where}: attribute {MIXTURE_LAYOUT_ATTR!r} without mixture datasets")
    return out


def _check_method(method, where: str) -> str:
    """The method name: a non-empty printable line of at most :data:`MAX_METHOD_CHARS` characters."""
    if not isinstance(method, str) or not method.strip():
        raise DataFormatError(f"{where}: missing or empty root attribute 'method'")
    if len(method) > MAX_METHOD_CHARS or not method.isprintable():
        raise DataFormatError(f"{where}: method name {method[:40]!r} must be one printable line of at most "
                              f"{MAX_METHOD_CHARS} characters")
    return method


def _check_class_group(name, where: str) -> str:
    """A class group name: 1-32 characters from ``A-Z a-z 0-9 _ . -``, not starting with ``.`` or ``-``."""
    if not isinstance(name, str) or _CLASS_GROUP_RE.fullmatch(name) is None:
        raise DataFormatError(f"{where}: invalid class group name {str(name)[:40]!r} (expected 1-32 characters "
                              "from A-Z a-z 0-9 _ . -, not starting with . or -)")
    return name


def write_predictions(path: str | Path, method: str, per_class: dict[str, dict[str, np.ndarray]],
                      attrs: dict | None = None) -> None:
    """Validate ``per_class`` and write it to ``path`` (replacing an existing file).

    ``per_class[class_name]`` maps dataset names (see the module docstring) to arrays and,
    with mixtures, ``"mixture_layout"`` to the list of the D column names.  Float datasets
    keep float32 or float64 as given (other numeric dtypes are stored as float64);
    ``sample_id`` is stored as int64.  ``attrs`` are extra root attributes (str/number; other
    values are stored as JSON).  Invalid input raises :class:`UserError`.  The file is built
    beside ``path`` and renamed into place when complete (:func:`safeio.atomic_write_h5`).
    """
    path = Path(path)
    try:
        _check_method(method, "write_predictions")
    except DataFormatError as exc:
        raise UserError(str(exc)) from None
    if not per_class:
        raise UserError("write_predictions: no classes to write")
    checked = {}
    for cls, arrays in per_class.items():
        _check_class_group(cls, "write_predictions")
        checked[cls] = validate_class(f"{path}:/{cls}", arrays, normalise=False)
    for k in attrs or {}:
        if k in ("format_version", "method"):
            raise UserError(f"write_predictions: attribute {k!r} is set by the writer")

    def build(f: h5py.File) -> None:
        f.attrs["format_version"] = PREDICTIONS_FORMAT_VERSION
        f.attrs["method"] = method
        for k, v in (attrs or {}).items():
            f.attrs[k] = v if isinstance(v, (str, int, float, np.integer, np.floating)) else json.dumps(v)
        for cls, arrays in per_class.items():
            grp = f.create_group(cls)
            for name in ALL_DATASETS:
                if name not in arrays:
                    continue
                a = np.asarray(arrays[name])
                if name == "sample_id":
                    a = a.astype(np.int64)
                elif a.dtype not in (np.float32, np.float64):
                    a = a.astype(np.float64)
                grp.create_dataset(name, data=a)
            if MIXTURE_LAYOUT_ATTR in checked[cls]:
                grp.attrs[MIXTURE_LAYOUT_ATTR] = json.dumps(checked[cls][MIXTURE_LAYOUT_ATTR])

    atomic_write_h5(path, build)


def _read_attr(attrs, name: str, where: str):
    """One HDF5 attribute as a plain value; an unreadable or undecodable one is a DataFormatError."""
    try:
        return attr_value(attrs[name])
    except (OSError, RuntimeError, TypeError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        raise DataFormatError(f"{where}: attribute {name!r} cannot be read ({type(exc).__name__})") from None


def _read_dataset(ds: h5py.Dataset, where: str) -> np.ndarray:
    """A dataset's values; a damaged chunk is a DataFormatError naming it."""
    try:
        return ds[()]
    except (OSError, RuntimeError, TypeError, ValueError) as exc:
        reason = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        raise DataFormatError(f"{where}: cannot read ({reason}); the file is damaged") from None


def _check_memory(path: Path, f: h5py.File) -> None:
    """Refuse a file whose datasets, read as float64, would take more than
    :data:`MAX_MEMORY_FRACTION` of the available memory (shapes are read, no data)."""
    need = 0
    for grp in f.values():
        if isinstance(grp, h5py.Group):
            for ds in grp.values():
                if isinstance(ds, h5py.Dataset):
                    need += 8 * (int(np.prod(ds.shape, dtype=object)) if ds.shape else 1)
    available = available_memory_bytes()
    if available is not None and need > MAX_MEMORY_FRACTION * available:
        raise DataFormatError(f"{path}: its datasets need {format_bytes(need)} of memory to score; "
                              f"this machine has {format_bytes(available)} available")


def read_predictions(path: str | Path) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """Read and validate a predictions file: ``(root attrs, {class: {dataset: array}})``.

    Arrays come back as float64 (``sample_id`` int64) with unit quaternions and weights that
    sum to 1; ``"mixture_layout"`` (a list of str) is present with mixtures.  Any problem is a
    :class:`DataFormatError` (a :class:`UserError`) naming the file and dataset: besides the
    format (module docstring), values beyond :data:`MAX_ABS_VALUE`, a method name that is not
    one printable line, class group names that are not class names, files that are not
    regular files, files whose data would not fit in memory and damaged files.
    """
    path = Path(path)
    with open_h5(path) as f:  # (which refuses a missing file, a folder, a device, pipe or socket)
        attrs = {k: _read_attr(f.attrs, k, str(path)) for k in f.attrs}
        if "format_version" not in attrs:
            raise DataFormatError(f"{path}: not a predictions file (no format_version attribute)")
        major = str(attrs["format_version"]).split(".")[0]
        if major != PREDICTIONS_FORMAT_VERSION.split(".")[0]:
            raise DataFormatError(f"{path}: predictions format version {str(attrs['format_version'])[:40]!r} is not readable "
                                  f"(this package reads {PREDICTIONS_FORMAT_VERSION.split('.')[0]}.x)")
        _check_method(attrs.get("method"), str(path))
        _check_memory(path, f)
        per_class = {}
        for cls, grp in f.items():
            _check_class_group(cls, str(path))
            where = f"{path}:/{cls}"
            if not isinstance(grp, h5py.Group):
                raise DataFormatError(f"{where}: expected a class group, found a dataset")
            arrays: dict = {}
            for name, ds in grp.items():
                if not isinstance(ds, h5py.Dataset):
                    raise DataFormatError(f"{where}: {name[:40]!r} is a group, expected a dataset")
                if name not in ALL_DATASETS:
                    raise DataFormatError(f"{where}: unknown dataset {name[:40]!r} (expected {', '.join(ALL_DATASETS)})")
                if ds.dtype.kind not in "fiub":
                    raise DataFormatError(f"{where}/{name}: dtype {ds.dtype} is not numeric")
                if name in MIXTURE_DATASETS and len(ds.shape) >= 2 and ds.shape[1] > MAX_MIXTURE_COMPONENTS:
                    raise DataFormatError(f"{where}/{name}: {ds.shape[1]} components per image "
                                          f"(at most {MAX_MIXTURE_COMPONENTS})")
                arrays[name] = _read_dataset(ds, f"{where}/{name}")
            if MIXTURE_LAYOUT_ATTR in grp.attrs:
                arrays[MIXTURE_LAYOUT_ATTR] = _read_attr(grp.attrs, MIXTURE_LAYOUT_ATTR, where)
            per_class[cls] = validate_class(where, arrays)
    if not per_class:
        raise DataFormatError(f"{path}: no class groups (nothing predicted)")
    return attrs, per_class
