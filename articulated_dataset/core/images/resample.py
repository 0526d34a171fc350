"""Resampling a capture to the training camera: onto exactly the training intrinsics, or a
crop around the mask scaled to the training resolution; depth is never interpolated."""

from __future__ import annotations

import math

import numpy as np

from articulated_dataset.core.errors import UserError

#: Margin added on each side of the mask's bounding box in ``fit="crop"`` (fraction of its size).
DEFAULT_CROP_MARGIN = 0.1
RESAMPLERS = ("nearest", "min")


def crop_intrinsics(K: np.ndarray, mask: np.ndarray, out_size: tuple[int, int], margin: float = DEFAULT_CROP_MARGIN) -> np.ndarray:
    """Intrinsics of a window around the mask with the aspect ratio of ``out_size`` (W, H),
    scaled to that size.

    The window is the mask's bounding box grown by ``margin`` of its size on each side, then
    widened (or heightened) to the aspect ratio, centred on the box.  With window left/top
    edges ``(a, b)`` (continuous source coordinates; pixel k covers [k - 0.5, k + 0.5]) and
    scale ``s = W_out / window_width``: ``fx' = s fx``, ``fy' = s fy``,
    ``cx' = s (cx - a) - 0.5``, ``cy' = s (cy - b) - 0.5``.
    """
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        raise UserError("the mask is empty: nothing to crop around")
    W, H = out_size
    u0, u1 = xs.min() - 0.5, xs.max() + 0.5
    v0, v1 = ys.min() - 0.5, ys.max() + 0.5
    w, h = (u1 - u0) * (1 + 2 * margin), (v1 - v0) * (1 + 2 * margin)
    aspect = W / H
    if w / h < aspect:
        w = h * aspect
    else:
        h = w / aspect
    a, b = 0.5 * (u0 + u1) - 0.5 * w, 0.5 * (v0 + v1) - 0.5 * h
    s = W / w
    return np.array([[s * K[0, 0], 0.0, s * (K[0, 2] - a) - 0.5], [0.0, s * K[1, 1], s * (K[1, 2] - b) - 0.5], [0.0, 0.0, 1.0]])


def source_coordinates(K_src: np.ndarray, K_dst: np.ndarray, size_dst: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Source-image coordinates (u_s (W,), v_s (H,)) of the destination pixel centres.

    Both cameras share the optical centre and axes, so z-depth is unchanged and
    ``u_s = fx_s (u - cx_d) / fx_d + cx_s`` (same for v).
    """
    W, H = size_dst
    us = K_src[0, 0] * (np.arange(W) - K_dst[0, 2]) / K_dst[0, 0] + K_src[0, 2]
    vs = K_src[1, 1] * (np.arange(H) - K_dst[1, 2]) / K_dst[1, 1] + K_src[1, 2]
    return us, vs


def resample_depth(depth_m: np.ndarray, mask: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray,
                   size_dst: tuple[int, int], method: str = "nearest") -> tuple[np.ndarray, np.ndarray]:
    """Resample depth (m) and mask onto the camera ``K_dst`` of size ``size_dst`` (W, H).

    ``nearest``: each destination pixel takes the source pixel nearest its ray.  ``min``: the
    smallest non-zero depth among the source pixels whose centres fall in the destination
    pixel's footprint ``[u_s - r/2, u_s + r/2)`` (``r = fx_s / fx_d``; the nearest pixel if the
    footprint holds no centre), and that pixel's mask label.  Rays leaving the source image
    get depth 0 and label 0.  No depth is ever interpolated.
    """
    if method not in RESAMPLERS:
        raise UserError(f"unknown resampling {method!r}; choose from: {', '.join(RESAMPLERS)}")
    Hs, Ws = depth_m.shape
    W, H = size_dst
    us, vs = source_coordinates(K_src, K_dst, size_dst)
    if method == "nearest":
        iu, iv = np.rint(us).astype(np.int64), np.rint(vs).astype(np.int64)
        ok = (iu >= 0) & (iu < Ws), (iv >= 0) & (iv < Hs)
        depth = np.zeros((H, W))
        out_mask = np.zeros((H, W), np.uint8)
        sel = np.ix_(iv[ok[1]], iu[ok[0]])
        rows, cols = np.nonzero(ok[1])[0], np.nonzero(ok[0])[0]
        depth[np.ix_(rows, cols)] = depth_m[sel]
        out_mask[np.ix_(rows, cols)] = mask[sel]
        return depth, out_mask
    ru, rv = K_src[0, 0] / K_dst[0, 0], K_src[1, 1] / K_dst[1, 1]
    # per axis: candidate source indices k = ceil(start) + o, o = 0..n-1, valid while k < end
    def candidates(coords: np.ndarray, r: float, size: int):
        start, end = coords - 0.5 * r, coords + 0.5 * r
        first = np.ceil(start).astype(np.int64)
        n = max(1, int(math.ceil(r)) + 1)
        idx = first[:, None] + np.arange(n)[None]
        ok = (idx < end[:, None]) & (idx >= 0) & (idx < size)
        nearest = np.rint(coords).astype(np.int64)
        return idx, ok, nearest
    cu, oku, nu = candidates(us, ru, Ws)
    cv, okv, nv = candidates(vs, rv, Hs)
    best = np.full((H, W), np.inf)
    label = np.zeros((H, W), np.uint8)
    for a in range(cv.shape[1]):
        for b in range(cu.shape[1]):
            ok = okv[:, a][:, None] & oku[:, b][None, :]
            z = depth_m[np.clip(cv[:, a], 0, Hs - 1)][:, np.clip(cu[:, b], 0, Ws - 1)]
            m = mask[np.clip(cv[:, a], 0, Hs - 1)][:, np.clip(cu[:, b], 0, Ws - 1)]
            better = ok & (z > 0) & (z < best)
            best[better] = z[better]
            label[better] = m[better]
    # no valid depth in the footprint: nearest pixel (if inside the image)
    none = ~np.isfinite(best)
    inside = ((nv >= 0) & (nv < Hs))[:, None] & ((nu >= 0) & (nu < Ws))[None, :]
    near_d = depth_m[np.clip(nv, 0, Hs - 1)][:, np.clip(nu, 0, Ws - 1)]
    near_m = mask[np.clip(nv, 0, Hs - 1)][:, np.clip(nu, 0, Ws - 1)]
    depth = np.where(none, np.where(inside, near_d, 0.0), best)
    label = np.where(none, np.where(inside, near_m, 0), label).astype(np.uint8)
    return depth, label


def mask_fraction_inside(mask: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray, size_dst: tuple[int, int]) -> float:
    """Fraction of the mask's pixels whose rays fall inside the destination image."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return 1.0
    W, H = size_dst
    u = K_dst[0, 0] * (xs - K_src[0, 2]) / K_src[0, 0] + K_dst[0, 2]
    v = K_dst[1, 1] * (ys - K_src[1, 2]) / K_src[1, 1] + K_dst[1, 2]
    inside = (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5)
    return float(inside.mean())
