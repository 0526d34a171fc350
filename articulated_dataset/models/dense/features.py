"""Depth image + intrinsics -> the dense network's input; labels -> per-pixel targets.

Input (at the model resolution ``H x W``, default 108 x 192, the dataset's native size):

* the depth is resized to ``H x W`` if needed by validity-weighted area averaging
  (``d = area(v d) / area(v)``, ``v = d > 0``) and ``K`` is rescaled with it
  (:func:`scale_intrinsics`), so images of any size and intrinsics are accepted;
* every valid pixel is back-projected to its camera-frame point ``p`` (x forward, y left,
  z up; :func:`backproject_torch`), and the image anchor ``a`` is the mean of the valid
  points;
* channels: ``(p - a) / POINT_SCALE_M`` (3, zero where invalid), validity (1), surface
  normals from central differences (3, zero where undefined), pixel coordinates ``u, v``
  in [-1, 1] (2): :data:`N_INPUT_CHANNELS` in all.

The network predicts at ``H / OUTPUT_STRIDE x W / OUTPUT_STRIDE``; each output pixel's
3-D point is the validity-weighted mean of the points under it
(:func:`output_points`), and its part label the majority label of the mask pixels under
it (:func:`output_labels`; 0 background, 1 body, 2 + j part j).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

#: Relative points are divided by this (m): objects span about +-1 m around their anchor.
POINT_SCALE_M = 0.5
#: Neighbouring points further apart than this (m) are a depth edge: no normal there.
NORMAL_MAX_STEP_M = 0.1
#: Output pixels are this many input pixels wide.
OUTPUT_STRIDE = 4
#: Relative points (3), validity (1), normals (3), pixel coordinates (2).
N_INPUT_CHANNELS = 9
#: Mask codes of the shards: 0 background, 1 body, 2 + j moving part j.
MASK_BODY = 1


def scale_intrinsics(K: np.ndarray, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics of an image resized from ``src_hw`` to ``dst_hw`` (pixel centres at
    integers: ``c' = (c + 0.5) s - 0.5``, ``f' = f s`` per axis)."""
    K = np.asarray(K, np.float64).copy()
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    K[0, 0] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def resize_depth(depth_m: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """(B, h, w) depth -> (B, H, W) by validity-weighted area averaging (down) or nearest (up)."""
    if tuple(depth_m.shape[-2:]) == tuple(hw):
        return depth_m
    v = (depth_m > 0).float()[:, None]
    d = (depth_m * v[:, 0])[:, None]
    if hw[0] <= depth_m.shape[-2] and hw[1] <= depth_m.shape[-1]:
        vs = F.adaptive_avg_pool2d(v, hw)
        ds = F.adaptive_avg_pool2d(d, hw)
    else:
        vs = F.interpolate(v, size=hw, mode="nearest")
        ds = F.interpolate(d, size=hw, mode="nearest")
    return torch.where(vs > 0, ds / vs.clamp_min(1e-12), torch.zeros_like(ds))[:, 0]


def backproject_torch(depth_m: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B, H, W) z-depth and (B, 3, 3) intrinsics -> (B, 3, H, W) camera-frame points
    (x forward = z_optical, y left = -x_optical, z up = -y_optical); invalid pixels give 0."""
    B, H, W = depth_m.shape
    u = torch.arange(W, dtype=depth_m.dtype, device=depth_m.device)
    v = torch.arange(H, dtype=depth_m.dtype, device=depth_m.device)
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    xo = (u.view(1, 1, W) - cx) / fx * depth_m
    yo = (v.view(1, H, 1) - cy) / fy * depth_m
    return torch.stack([depth_m, -xo, -yo], 1)


def surface_normals(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Unit normals (B, 3, H, W) facing the camera, from central differences of the points;
    0 where a neighbour is invalid or further than :data:`NORMAL_MAX_STEP_M`."""
    p = F.pad(points, (1, 1, 1, 1), mode="replicate")
    v = F.pad(valid.float()[:, None], (1, 1, 1, 1))
    dx = p[:, :, 1:-1, 2:] - p[:, :, 1:-1, :-2]
    dy = p[:, :, 2:, 1:-1] - p[:, :, :-2, 1:-1]
    ok = (v[:, 0, 1:-1, 2:] * v[:, 0, 1:-1, :-2] * v[:, 0, 2:, 1:-1] * v[:, 0, :-2, 1:-1]) > 0
    max_step2 = (2 * NORMAL_MAX_STEP_M) ** 2
    ok &= valid & ((dx * dx).sum(1) < max_step2) & ((dy * dy).sum(1) < max_step2)
    # cross product and normalisation written out: 5x faster than torch.cross / F.normalize on dim 1
    n = torch.stack([dx[:, 1] * dy[:, 2] - dx[:, 2] * dy[:, 1], dx[:, 2] * dy[:, 0] - dx[:, 0] * dy[:, 2],
                     dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]], 1)
    n = n * torch.rsqrt((n * n).sum(1, keepdim=True).clamp_min(1e-24))
    n = torch.where(n[:, :1] > 0, -n, n)  # the camera looks along +x: normals point back
    return n * ok[:, None]


def make_inputs(depth_m: torch.Tensor, K: torch.Tensor) -> dict:
    """Network input and geometry of a batch at the model resolution.

    ``depth_m`` (B, H, W) float32 metres (0 = no return), ``K`` (B, 3, 3).  Returns a dict:
    ``x`` (B, 9, H, W) input, ``anchor`` (B, 3) m, ``points_out`` (B, 3, h, w) mean point
    of each output pixel (m), ``weight_out`` (B, h, w) fraction of valid pixels under it.
    """
    valid = depth_m > 0
    pts = backproject_torch(depth_m, K)
    w = valid.float()[:, None]
    n_valid = w.sum((2, 3)).clamp_min(1.0)
    anchor = (pts * w).sum((2, 3)) / n_valid
    rel = (pts - anchor[:, :, None, None]) * w / POINT_SCALE_M
    B, H, W = depth_m.shape
    uu = torch.linspace(-1, 1, W, dtype=depth_m.dtype).view(1, 1, 1, W).expand(B, 1, H, W)
    vv = torch.linspace(-1, 1, H, dtype=depth_m.dtype).view(1, 1, H, 1).expand(B, 1, H, W)
    x = torch.cat([rel, w, surface_normals(pts, valid), uu, vv], 1)
    w_out = F.avg_pool2d(w, OUTPUT_STRIDE, ceil_mode=True)
    p_out = F.avg_pool2d(pts * w, OUTPUT_STRIDE, ceil_mode=True) / w_out.clamp_min(1e-6)
    return {"x": x, "anchor": anchor, "points_out": p_out, "weight_out": w_out[:, 0]}


def output_labels(mask: np.ndarray, n_joints: int) -> np.ndarray:
    """(B, H, W) uint8 mask -> (B, ceil(H/s), ceil(W/s)) majority label over each output
    pixel's foreground (0 if it has no foreground pixel)."""
    B, H, W = mask.shape
    s = OUTPUT_STRIDE
    Ho, Wo = -(-H // s), -(-W // s)
    m = np.zeros((B, Ho * s, Wo * s), np.uint8)
    m[:, :H, :W] = mask
    counts = np.stack([(m == c).reshape(B, Ho, s, Wo, s).sum((2, 4)) for c in range(MASK_BODY, MASK_BODY + 1 + n_joints)], 1)
    return np.where(counts.sum(1) > 0, counts.argmax(1) + MASK_BODY, 0).astype(np.uint8)
