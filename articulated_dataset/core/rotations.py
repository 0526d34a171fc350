"""Rotations shared by the whole package: quaternions (w, x, y, z) and matrices.

All functions are pure and vectorised over leading axes.  Label quaternions follow the
convention w >= 0 (:func:`matrix_to_quat`).

Why ours and not ``scipy.spatial.transform.Rotation``: scipy is an optional dependency (ICP, mixture scoring), while
generation, the format, the loaders and the metrics need these without it; and the labels of
every generated split are computed by :func:`matrix_to_quat`, so its exact arithmetic is part
of the dataset's bytes (``scripts/compare_generated_bytes.sh``).  The package keeps this one
copy (``quat_axis_z``/``quat_axis_x`` of :mod:`articulated_dataset.benchmark.metrics` compute
one column of :func:`quat_to_matrix` without the matrix, for scoring's speed);
``tests/benchmark/test_metrics.py`` checks them against scipy where it is installed.
"""

from __future__ import annotations

import numpy as np

#: Norms below this are treated as zero (degenerate quaternions/vectors).
_EPS = 1e-12


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in (w, x, y, z) order.

    The quaternion is normalised first.  ``R = I + 2 w [v]x + 2 [v]x^2`` with ``v = (x, y, z)``,
    written out element by element.
    """
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4), (w, x, y, z) with w >= 0, of rotation matrices (..., 3, 3).

    Shepperd's method: of the four candidates ``4w^2 = 1 + tr R``, ``4x^2 = 1 + R00 - R11 - R22``,
    ... the largest is computed from its square root and the others from the off-diagonal
    sums, which keeps the division well conditioned for every rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    best = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, best[..., None], axis=-1)[..., 0], _EPS))
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    options = np.stack([
        np.stack([s / 4, d21 / s, d02 / s, d10 / s], axis=-1),   # w largest
        np.stack([d21 / s, s / 4, s10 / s, s02 / s], axis=-1),   # x largest
        np.stack([d02 / s, s10 / s, s / 4, s21 / s], axis=-1),   # y largest
        np.stack([d10 / s, s02 / s, s21 / s, s / 4], axis=-1),   # z largest
    ], axis=-2)
    q = np.take_along_axis(options, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions ``(..., 4)`` in ``(w, x, y, z)`` order.

    The rotation matrix of ``a * b`` is ``R(a) @ R(b)`` (``b`` applied first).
    """
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate ``(w, -x, -y, -z)``: the inverse rotation of a unit quaternion."""
    q = np.asarray(q, np.float64)
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def axis_angle_quat(axis: np.ndarray, angle_rad) -> np.ndarray:
    """Quaternion ``(cos(a/2), sin(a/2) u)`` of a rotation by ``angle_rad`` about ``axis`` (normalised)."""
    u = np.asarray(axis, np.float64)
    u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), _EPS)
    half = 0.5 * np.asarray(angle_rad, np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * u], axis=-1)
