"""The truth side of scoring: the labels of one split of one class (:class:`TruthSet`), the
choice of one truth split per predicted class (:func:`select_truth`) and the alignment of
predictions to the truth by ``sample_id`` (:func:`align`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError, option
from articulated_dataset.format import Split, splits_by_class

#: Truth split chosen when a class has several and no ``split`` is given.
DEFAULT_SPLIT = "test"
#: Label fields the scorer reads from the truth shards.
#: Label fields the scorer reads; ``object_index`` groups images for the standard errors.
TRUTH_FIELDS = ("sample_id", "axis_pose", "q", "geometry", "part_offset", "object_index")
#: Integer identifiers among them (kept as int64, never checked as label values).
ID_FIELDS = ("sample_id", "object_index")


# --------------------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------------------

@dataclass
class TruthSet:
    """The labels of one split of one class, sorted by ``sample_id``."""

    class_name: str
    split: str
    path: Path
    joint_types: tuple[str, ...]
    complete: bool
    arrays: dict[str, np.ndarray]

    @property
    def n_images(self) -> int:
        """Number of labelled images in the split."""
        return int(self.arrays["sample_id"].shape[0])


def load_truth_set(split_dir: str | Path) -> TruthSet:
    """Read the label fields the scorer needs from every shard of a split folder."""
    split_dir = Path(split_dir)
    split = Split(split_dir)  # checks the manifest and that every shard path stays inside the folder
    if not split.shards:
        raise DataFormatError(f"{split_dir}: the split has no shards")
    joint_types = split.joint_types()  # every shard's, known and equal
    arrays = split.read_fields(TRUTH_FIELDS)
    ids = arrays["sample_id"].astype(np.int64)
    order = np.argsort(ids, kind="stable")
    arrays = {k: np.asarray(v[order], np.float64) if k not in ID_FIELDS else np.asarray(v[order], np.int64)
              for k, v in arrays.items()}
    if arrays["axis_pose"].shape[1] != len(joint_types):
        raise DataFormatError(f"{split_dir}: {arrays['axis_pose'].shape[1]} joints in axis_pose but {len(joint_types)} joint types")
    dup = arrays["sample_id"][1:] == arrays["sample_id"][:-1]
    if dup.any():
        raise DataFormatError(f"{split_dir}: {int(dup.sum())} duplicated sample ids in the truth")
    _check_truth_values(split_dir, arrays)
    quat = arrays["axis_pose"][..., 3:]
    with np.errstate(all="ignore"):  # a NaN or zero quaternion (undefined truth) stays NaN
        arrays["axis_pose"][..., 3:] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return TruthSet(class_name=split.class_name, split=split_dir.name, path=split_dir,
                    joint_types=joint_types, complete=split.complete, arrays=arrays)


def _check_truth_values(split_dir: Path, arrays: dict) -> None:
    """Truth labels are NaN where not given (real captures) and otherwise what a predictions file
    may hold (:func:`.predictions.validate_class`): finite, within +-MAX_ABS_VALUE and with
    quaternions of non-zero length.  An infinite, absurd or zero-length label is a damaged split
    (``artdata verify`` reports it): a DataFormatError, never a score of ``inf`` or 10^40 cm."""
    from articulated_dataset.benchmark.predictions import MAX_ABS_VALUE, MIN_QUATERNION_NORM, beyond_bounds

    for name, a in arrays.items():
        if name in ID_FIELDS:
            continue
        bad = beyond_bounds(a, nan_allowed=True)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise DataFormatError(f"{split_dir}: truth label {name!r} holds {int(bad.sum())} infinite or absurd values "
                                  f"(beyond +/-{MAX_ABS_VALUE:g}; first {a[first]:.3g} at {first}); run 'artdata verify' "
                                  f"on the split")
    quat = arrays["axis_pose"][..., 3:]
    with np.errstate(invalid="ignore"):
        zero = np.linalg.norm(quat, axis=-1) < MIN_QUATERNION_NORM  # NaN (not given) compares False
    if zero.any():
        raise DataFormatError(f"{split_dir}: truth label 'axis_pose' holds {int(zero.sum())} zero-length quaternions; "
                              f"run 'artdata verify' on the split")


def available_truth(truth_path: str | Path) -> dict[str, dict[str, Path]]:
    """``{class: {split name: split folder}}`` of the splits under ``truth_path``
    (:func:`articulated_dataset.format.splits_by_class`)."""
    return splits_by_class(truth_path)


def select_truth(truth_path: str | Path, classes, split: str | None = None,
                 sources: dict[str, str] | None = None) -> dict[str, TruthSet]:
    """Load one truth split for each class in ``classes``.

    With ``split`` given, the split folder of that name; otherwise the only split of the class
    or, among several, :data:`DEFAULT_SPLIT`.  A class without truth, an ambiguous choice or
    a missing split is a :class:`UserError`.  ``sources[class]`` names the predictions file of a
    class in messages.
    """
    found = available_truth(truth_path)
    out = {}
    for cls in classes:
        splits = found.get(cls)
        if not splits:
            have = ", ".join(sorted(found)) or "none"
            where = f"{sources[cls]}:/{cls}" if sources and cls in sources else f"class {cls!r}"
            raise UserError(f"{where}: predictions for a class with no truth under {truth_path} (classes there: {have})")
        if split is not None:
            if split not in splits:
                raise UserError(f"class {cls!r} has no split {split!r} under {truth_path} (splits: {', '.join(sorted(splits))})")
            chosen = split
        elif len(splits) == 1:
            chosen = next(iter(splits))
        elif DEFAULT_SPLIT in splits:
            chosen = DEFAULT_SPLIT
        else:
            raise UserError(f"class {cls!r} has several splits under {truth_path} ({', '.join(sorted(splits))}); "
                            f"choose one with {option('split')}")
        out[cls] = load_truth_set(splits[chosen])
    return out


def align(pred_ids: np.ndarray, truth_ids: np.ndarray, where: str, truth_where: str = "") -> np.ndarray:
    """Index into the sorted ``truth_ids`` of each prediction id; unknown ids are a DataFormatError."""
    idx = np.searchsorted(truth_ids, pred_ids)
    idx_c = np.minimum(idx, len(truth_ids) - 1)
    unknown = truth_ids[idx_c] != pred_ids
    if unknown.any():
        raise DataFormatError(f"{where}/sample_id: {int(unknown.sum())} of {len(pred_ids)} ids are not in the truth set "
                              f"{truth_where} (e.g. {int(pred_ids[unknown][0])})")
    return idx_c
