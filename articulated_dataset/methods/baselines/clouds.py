"""Point clouds and rigid transforms for the ICP baseline: organised clouds back-projected from
depth, per-pixel normals, stride subsampling, rotations from vectors and axes, and the weighted
Kabsch fit."""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.camera import backproject
from articulated_dataset.methods.baselines.common import usable_depth

#: A pixel's normal is used only if its 4 neighbours are within this depth of it (m).
NORMAL_MAX_DEPTH_JUMP_M = 0.05


def stride_subsample(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` rows of ``points``, evenly spaced in storage (pixel) order; deterministic."""
    if len(points) <= n:
        return points
    idx = np.linspace(0, len(points) - 1, n).round().astype(np.int64)
    return points[idx]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    v = np.asarray(v, np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
        np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
        np.stack([-v[..., 1], v[..., 0], z], axis=-1),
    ], axis=-2)


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """``exp([w]x)`` ``(..., 3, 3)`` of rotation vectors ``w (..., 3)`` (rad): Rodrigues' formula
    ``I + sin(a) [k]x + (1 - cos(a)) [k]x^2`` with ``a = |w|``, ``k = w / a``."""
    w = np.asarray(w, np.float64)
    a = np.linalg.norm(w, axis=-1)
    k = w / np.where(a > 0, a, 1.0)[..., None]
    kx = skew(k)
    a = a[..., None, None]
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)


def rotation_about_axis(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` by ``angle_rad`` about the ``axis`` (normalised here)."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return rotation_from_vector(np.asarray(angle_rad, np.float64)[..., None] * k)


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transforms, batched: ``argmin_{R,t} sum_i w_i ||R s_i + t - d_i||^2``.

    ``src``/``dst`` ``(H, N, 3)``, ``weights`` ``(H, N)`` >= 0 (each row with a positive sum).
    ``R = V diag(1, 1, det(V U^T)) U^T`` from the SVD ``U S V^T`` of the weighted
    cross-covariance ``sum_i w_i (s_i - s_bar)(d_i - d_bar)^T`` (Umeyama 1991);
    ``t = d_bar - R s_bar``.  Returns ``R (H, 3, 3)``, ``t (H, 3)``.
    """
    w = weights / np.maximum(weights.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    s_bar = np.einsum("hn,hnc->hc", w, src)
    d_bar = np.einsum("hn,hnc->hc", w, dst)
    cov = np.einsum("hn,hni,hnj->hij", w, src - s_bar[:, None], dst - d_bar[:, None])
    u, _, vt = np.linalg.svd(cov)
    v = np.swapaxes(vt, 1, 2)
    ut = np.swapaxes(u, 1, 2)
    fix = np.ones((len(w), 3))
    fix[:, 2] = np.where(np.linalg.det(v @ ut) < 0, -1.0, 1.0)
    rot = (v * fix[:, None, :]) @ ut
    t = d_bar - np.einsum("hij,hj->hi", rot, s_bar)
    return rot, t


def rotation_angle_rad(rot: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices ``(..., 3, 3)``: ``acos((trace - 1) / 2)``, clipped."""
    tr = np.trace(rot, axis1=-2, axis2=-1)
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def organised_cloud(depth_m: np.ndarray, K: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(H, W, 3)`` of the ``valid`` pixels (0 elsewhere), via :func:`backproject`."""
    depth_m = usable_depth(depth_m)
    valid = np.asarray(valid, bool) & (depth_m > 0)
    grid = np.zeros(depth_m.shape + (3,))
    v, u = np.nonzero(valid)
    grid[v, u] = backproject(depth_m, K, valid)  # same row-major pixel order as np.nonzero
    return grid


def cloud_with_normals(depth_m: np.ndarray, K: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` and unit normals ``(N, 3)`` (towards the camera) of the pixels with a
    reliable normal (see the module docstring), in row-major pixel order."""
    depth_m = usable_depth(depth_m)
    valid = np.asarray(valid, bool) & (depth_m > 0)
    p = organised_cloud(depth_m, K, valid)
    z = np.asarray(depth_m, np.float64)
    ok = np.zeros_like(valid)
    inner = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    zc = z[1:-1, 1:-1]
    for zn in (z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]):
        inner &= np.abs(zn - zc) < NORMAL_MAX_DEPTH_JUMP_M
    ok[1:-1, 1:-1] = inner
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    n = np.zeros_like(p)
    n[1:-1, 1:-1] = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    flip = np.einsum("hwc,hwc->hw", n, p) > 0  # the camera is at the origin
    n[flip] *= -1.0
    return p[ok], n[ok]
