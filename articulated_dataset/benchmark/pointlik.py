"""The point-likelihood axis estimate (the paper's Table 2 procedure).

For a (real or simulated) observation, every back-projected point ``p`` of the segmented
object cloud is scored by its density under the predicted mixture's marginal over one
joint's axis origin, and the most likely point is taken as that joint's axis-origin estimate:

    log L(p) = logsumexp_m [ log w_m + sum_{k in x,y,z} log N(p_k | mu_{m,k}, s_{m,k}^2) ]
    origin   = argmax_p log L(p)

The marginal of a diagonal Gaussian mixture over a subset of its columns is the mixture of
the components' marginals over those columns (same weights), so only the three columns
``j{joint}.origin.x/y/z`` of the mixture are used.  The mixture is in label units (metres,
camera frame), as stored in ``predictions.h5`` (``mixture_means``/``mixture_scales`` are
means and standard deviations; see :mod:`articulated_dataset.benchmark.predictions`).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from articulated_dataset.core.camera import backproject
from articulated_dataset.core.errors import UserError

log = logging.getLogger(__name__)

#: Names of a joint's axis-origin columns in a mixture layout.
ORIGIN_COLUMNS = ("j{joint}.origin.x", "j{joint}.origin.y", "j{joint}.origin.z")
#: Points scored per block (bounds the (block, M, 3) temporaries to a few MB).
POINT_BLOCK = 16384
LOG_2PI = math.log(2.0 * math.pi)


def origin_columns(layout_names: list[str], joint: int) -> list[int]:
    """Indices of ``j{joint}.origin.x/y/z`` in ``layout_names`` (a :class:`UserError` if absent)."""
    names = [c.format(joint=joint) for c in ORIGIN_COLUMNS]
    missing = [n for n in names if n not in layout_names]
    if missing:
        raise UserError(f"mixture layout has no column(s) {', '.join(missing)} (joint {joint}); "
                        f"cannot score points by their likelihood")
    return [list(layout_names).index(n) for n in names]


def origin_log_likelihood(points_m: np.ndarray, weights: np.ndarray, means: np.ndarray, scales: np.ndarray,
                          layout_names: list[str], joint: int) -> np.ndarray:
    """Log density (P,) of each point (m, camera frame) under the mixture's marginal over
    joint ``joint``'s axis origin (formula in the module docstring)."""
    points = np.asarray(points_m, np.float64).reshape(-1, 3)
    w = np.asarray(weights, np.float64).reshape(-1)
    mu = np.asarray(means, np.float64)
    s = np.asarray(scales, np.float64)
    if mu.ndim != 2 or mu.shape != s.shape or mu.shape[0] != w.shape[0]:
        raise ValueError(f"mixture shapes do not match: weights {w.shape}, means {mu.shape}, scales {s.shape}")
    if mu.shape[1] != len(layout_names):
        raise ValueError(f"mixture has {mu.shape[1]} columns but the layout names {len(layout_names)}")
    if (w < 0).any() or not w.sum() > 0 or (s <= 0).any():
        raise ValueError("mixture weights must be >= 0 (not all 0) and scales > 0")
    cols = origin_columns(layout_names, joint)
    mu, s = mu[:, cols], s[:, cols]  # (M, 3)
    with np.errstate(divide="ignore"):
        log_w = np.log(w / w.sum())
    # per-component constant: log w - sum log s - 3/2 log 2 pi
    const = log_w - np.log(s).sum(axis=1) - 1.5 * LOG_2PI  # (M,)
    out = np.empty(points.shape[0])
    for start in range(0, points.shape[0], POINT_BLOCK):
        p = points[start : start + POINT_BLOCK]
        r = (p[:, None, :] - mu[None]) / s[None]  # (B, M, 3)
        comp = const[None] - 0.5 * np.einsum("bmk,bmk->bm", r, r)
        top = comp.max(axis=1, keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        out[start : start + POINT_BLOCK] = (top + np.log(np.exp(comp - top).sum(axis=1, keepdims=True)))[:, 0]
    return out


def snap_axis_origins(points_m: np.ndarray, weights: np.ndarray, means: np.ndarray, scales: np.ndarray,
                      layout_names: list[str], joint: int) -> np.ndarray:
    """The point of ``points_m`` (P, 3) most likely under the mixture's marginal over joint
    ``joint``'s origin columns: ``argmax_p log L(p)`` (module docstring). Returns (3,) metres.

    ``weights`` (M,), ``means``/``scales`` (M, D) in label units with column names
    ``layout_names``.  Ties go to the first point.  An empty cloud is a :class:`UserError`.
    """
    points = np.asarray(points_m, np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        raise UserError("the segmented point cloud is empty (no pixel of the mask has a depth return); "
                        "cannot snap the axis origin to it")
    ll = origin_log_likelihood(points, weights, means, scales, layout_names, joint)
    return points[int(np.argmax(ll))].copy()


def object_cloud(depth_m: np.ndarray, mask: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The segmented object cloud: back-projected pixels (camera frame, m) where ``mask > 0``
    (body or any part) and depth > 0."""
    return backproject(depth_m, K, np.asarray(mask) > 0)


def snap_batch(depths_m: np.ndarray, masks: np.ndarray, K: np.ndarray, weights: np.ndarray, means: np.ndarray,
               scales: np.ndarray, layout_names: list[str], n_joints: int,
               fallback: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Snap every joint's axis origin of N images to their segmented clouds.

    ``depths_m``/``masks`` (N, H, W), ``K`` (3, 3) or (N, 3, 3), ``weights`` (N, M),
    ``means``/``scales`` (N, M, D).  Returns ``(origins (N, J, 3) m, snapped (N,) bool)``.
    Images whose cloud is empty keep ``fallback[i]`` (N, J, 3) if given (``snapped`` False),
    else raise a :class:`UserError`.
    """
    depths_m = np.asarray(depths_m)
    N = depths_m.shape[0]
    Ks = np.broadcast_to(np.asarray(K, np.float64), (N, 3, 3))
    out = np.empty((N, n_joints, 3))
    snapped = np.ones(N, bool)
    for i in range(N):
        cloud = object_cloud(depths_m[i], masks[i], Ks[i])
        if cloud.shape[0] == 0:
            if fallback is None:
                raise UserError(f"image {i}: the segmented point cloud is empty; cannot snap the axis origin")
            out[i] = fallback[i]
            snapped[i] = False
            continue
        for j in range(n_joints):
            out[i, j] = snap_axis_origins(cloud, weights[i], means[i], scales[i], layout_names, j)
    if not snapped.all():
        log.warning("%d of %d images have an empty segmented cloud; kept the model's own origin", int((~snapped).sum()), N)
    return out, snapped


def snap_axis_poses(axis_pose: np.ndarray, origins_m: np.ndarray) -> np.ndarray:
    """Replace the position part (first 3 columns) of ``axis_pose`` (..., J, 7) by
    ``origins_m`` (..., J, 3); the orientation is kept."""
    out = np.array(axis_pose, np.float64, copy=True)
    out[..., :3] = origins_m
    return out
