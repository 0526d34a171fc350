"""Mean baseline (paper, Table 1 "Mean"): every test image gets the training-split mean.

For each class, over all N training images (each object contributes its 16 images):

* axis position, ``part_offset``, ``q`` and ``geometry``: arithmetic means
  ``x_bar = (1/N) sum_i x_i`` (per joint; chirality becomes the fraction of right-hinged
  objects, which the scorer thresholds at 0.5);
* axis orientation: the chordal L2 mean of the rotations (per joint),
  ``R_bar = argmin_{R in SO(3)} sum_i ||R - R_i||_F^2``.  Since
  ``||R(p) - R(q)||_F^2 = 8 (1 - (p.q)^2)`` for unit quaternions, ``R_bar`` is the rotation
  of the unit quaternion maximising ``p^T M p`` with ``M = sum_i q_i q_i^T``: the eigenvector
  of ``M``'s largest eigenvalue (Markley et al., "Averaging quaternions", 2007).  It does not
  depend on the sign of any ``q_i`` (``q`` and ``-q`` are the same rotation) and equals the
  projection of the mean rotation matrix ``(1/N) sum_i R_i`` back onto SO(3).
"""

from __future__ import annotations

import logging

import numpy as np

from articulated_dataset.methods.baselines.common import (
    BaselineResult,
    broadcast_labels,
    check_compatible,
    open_split_checked,
    read_train_labels,
)

log = logging.getLogger(__name__)

METHOD = "Mean"


def rotation_mean_quat(quats: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of unit quaternions ``(N, 4)`` (w, x, y, z): a unit quaternion, w >= 0.

    Top eigenvector of ``M = sum_i q_i q_i^T`` (4x4, symmetric), computed in float64.
    """
    q = np.asarray(quats, np.float64).reshape(-1, 4)
    if len(q) == 0:
        raise ValueError("rotation mean of zero rotations")
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    m = q.T @ q
    _, vecs = np.linalg.eigh(m)  # ascending eigenvalues
    mean = vecs[:, -1]
    return mean if mean[0] >= 0 else -mean


def mean_labels(labels: dict) -> dict:
    """Mean of each predicted label over the leading (image) axis; see the module docstring.

    ``labels`` holds ``axis_pose (N, J, 7)``, ``q (N, J)``, ``geometry (N, 4)`` and
    ``part_offset (N, J, 3)``; returns the same keys without the image axis (float64).
    """
    pose = np.asarray(labels["axis_pose"], np.float64)
    J = pose.shape[1]
    axis_pose = np.zeros((J, 7))
    axis_pose[:, :3] = pose[:, :, :3].mean(axis=0)
    for j in range(J):
        axis_pose[j, 3:] = rotation_mean_quat(pose[:, j, 3:])
    return {
        "axis_pose": axis_pose,
        "q": np.asarray(labels["q"], np.float64).mean(axis=0),
        "geometry": np.asarray(labels["geometry"], np.float64).mean(axis=0),
        "part_offset": np.asarray(labels["part_offset"], np.float64).mean(axis=0),
    }


def fit(train_dir) -> dict:
    """The class's mean labels over the training split at ``train_dir``."""
    train = open_split_checked(train_dir, "train")
    try:
        return mean_labels(read_train_labels(train))
    finally:
        train.close()


def predict(train_dir, test_dir, *, mean_dir=None, workers: int = 1, progress: bool = False) -> BaselineResult:
    """Mean predictions for every image of the test split.

    ``mean_dir``, ``workers`` and ``progress`` are accepted for a common signature and unused
    (reading the labels takes well under a second per 100,000 images).
    """
    train = open_split_checked(train_dir, "train")
    test = open_split_checked(test_dir, "test")
    try:
        check_compatible(train, test)
        means = mean_labels(read_train_labels(train))
        sample_id = test.read("sample_id")
        preds = {"sample_id": sample_id.astype(np.int64), **broadcast_labels(means, len(sample_id))}
        log.info("Mean: %s, %d training images -> %d test images", train.class_name, train.n_images, len(sample_id))
        return BaselineResult(METHOD, train.class_name, preds, {"train_split": str(train.path), "n_train_images": train.n_images})
    finally:
        train.close()
        test.close()
