"""Shared plumbing of the baselines: reading splits, checking them, packing predictions.

Every baseline is a function ``predict(train_dir, test_dir, ...) -> BaselineResult`` whose
``predictions`` hold, for every test image (in the test split's storage order):

* ``sample_id`` (N,) int64 -- the test image's id;
* ``axis_pose`` (N, J, 7) -- axis position (m, camera frame) + quaternion (w, x, y, z);
* ``q`` (N, J) -- configuration (rad | m);
* ``geometry`` (N, 4) -- depth, width, height (m), chirality;
* ``part_offset`` (N, J, 3) -- part centre in the axis frame (m).

:func:`write_result` stores it with :func:`articulated_dataset.benchmark.predictions.write_predictions`
so that ``artdata score`` scores a baseline like any other submission.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format import Split

log = logging.getLogger(__name__)

#: The label fields a baseline predicts (the subset of the schema that is scored).
PREDICTED_FIELDS = ("axis_pose", "q", "geometry", "part_offset")


class SplitInfo(Split):
    """A generated split folder (:class:`articulated_dataset.format.Split`) with the facts the
    baselines need."""

    @property
    def yaw_range_rad(self) -> tuple[float, float]:
        """The yaw range (rad) of the split's sampling table (the class prior of object rotations)."""
        lo, hi = self.config.table.pose["yaw_rad"]
        return float(lo), float(hi)


def open_split_checked(path, role: str) -> SplitInfo:
    """Open the split folder ``path`` used as ``role`` (train/test/mean); one-line UserErrors."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{role} split folder not found: {path}")
    if not path.is_dir():
        raise UserError(f"{role} split must be a folder holding manifest.json, got a file: {path}")
    info = SplitInfo(path)
    manifest = info.manifest
    if not info.shards or info.n_images == 0:
        raise UserError(f"{role} split {path} holds no images")
    if role != "test" and info.is_real:
        info.close()
        raise UserError(f"{role} split {path} holds ingested real captures; the baselines learn from a generated "
                        f"split (real splits can only be the {option('test_dir')} split)")
    if role == "mean-object" and not info.is_mean_object:
        info.close()
        raise UserError(f"{path} is the {manifest.get('split')!r} split, not a mean object: the mean object is built "
                        f"from the class's training table ('artdata generate {option('class_name')} C "
                        f"{option('mean')}' or leave {option('mean_dir')} out)")
    if not manifest.get("complete", True):
        log.warning("%s split %s is incomplete (%d images); using what is there", role, path, manifest["n_images"])
    return info


def check_compatible(reference: SplitInfo, other: SplitInfo, *, same_image_size: bool = False) -> None:
    """Raise a UserError unless ``other`` is of the same class (and image size, if asked)."""
    if reference.class_name != other.class_name:
        raise UserError(
            f"class mismatch: {reference.path} holds {reference.class_name!r} but {other.path} holds {other.class_name!r}"
        )
    if reference.n_joints != other.n_joints:
        raise UserError(f"{other.path}: {other.n_joints} joints, {reference.path} has {reference.n_joints}")
    if same_image_size and reference.image_size != other.image_size:
        raise UserError(
            f"image size mismatch: {reference.path} is {reference.image_size[1]}x{reference.image_size[0]} px, "
            f"{other.path} is {other.image_size[1]}x{other.image_size[0]} px"
        )


def read_train_labels(split: SplitInfo, names=PREDICTED_FIELDS) -> dict:
    """The label fields ``names`` of a training split (storage order), every value checked: a NaN,
    infinite or absurd value (beyond the predictions format's bound) or a zero-length axis
    quaternion is a one-line :class:`UserError` naming the split.  (The baselines copy or
    average these labels: the Mean's rotation mean failed with a traceback, and otherwise the
    predictions writer refused the result naming --out, not the damaged input.)"""
    from articulated_dataset.benchmark.predictions import beyond_bounds

    out = {}
    for name in names:
        a = np.asarray(split.read(name))
        bad = beyond_bounds(a.reshape(len(a), -1), nan_allowed=False).any(axis=1)
        if name == "axis_pose" and a.ndim == 3:
            bad |= ~(np.linalg.norm(a[..., 3:].astype(np.float64), axis=-1) > 0).all(axis=1)
        if bad.any():
            raise UserError(f"training split {split.path}: {int(bad.sum())} image(s) have NaN, infinite, absurd or "
                            f"degenerate '{name}' labels (first: image {int(np.argmax(bad))}; a damaged split? run "
                            f"'artdata verify')")
        out[name] = a
    return out


#: Depths (m) beyond this are no sensor's return: read as no return, like NaN, infinite and
#: negative values (a damaged image; 'artdata verify' reports it).  Keeps float32 features finite.
MAX_RETURN_DEPTH_M = 1e3


def usable_depth(depth_m: np.ndarray) -> np.ndarray:
    """``depth_m`` with every NaN, infinite, negative or absurd (> :data:`MAX_RETURN_DEPTH_M`) value
    set to 0 (no return), as the dense model reads such pixels; the same dtype."""
    d = np.asarray(depth_m)
    ok = np.isfinite(d) & (d >= 0) & (d <= MAX_RETURN_DEPTH_M)
    return d if ok.all() else np.where(ok, d, 0).astype(d.dtype)


@dataclass
class BaselineResult:
    """Predictions of one baseline on one class's test split, plus run facts for the file's attrs."""

    method: str
    class_name: str
    predictions: dict
    attrs: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)  # diagnostics (not written), e.g. NN's chosen training rows

    def __post_init__(self) -> None:
        n = len(self.predictions["sample_id"])
        for name in PREDICTED_FIELDS:
            if name in self.predictions and len(self.predictions[name]) != n:
                raise ValueError(f"{self.method}: {name} has {len(self.predictions[name])} rows, expected {n}")


def broadcast_labels(labels: dict, n: int) -> dict:
    """Repeat one set of labels (no leading image axis) ``n`` times, float32."""
    return {k: np.repeat(np.asarray(v, np.float32)[None], n, axis=0) for k, v in labels.items()}


def write_result(result: BaselineResult, out_path, attrs: dict | None = None) -> Path:
    """Write ``result`` as a predictions file (``articulated_dataset.benchmark.predictions`` format)."""
    from articulated_dataset.benchmark.predictions import write_predictions

    out_path = Path(out_path)
    if out_path.is_dir():
        raise UserError(f"{option('out')} {out_path} is a directory; give a file name such as predictions.h5")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output folder {out_path.parent}: {exc.strerror}") from None
    all_attrs = {**{k: _attr(v) for k, v in result.attrs.items()}, **(attrs or {})}
    write_predictions(out_path, result.method, {result.class_name: result.predictions}, attrs=all_attrs)
    return out_path


def _attr(v):
    """HDF5-attribute-friendly value (dicts/lists/tuples become JSON strings)."""
    import json

    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    return v
