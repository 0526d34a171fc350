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
#: A normal channel vector shorter than this is "no normal" (the input holds unit normals or 0).
MIN_NORMAL_NORM = 0.5
#: Neighbouring points further apart than this (m) are a depth edge: no normal there.
NORMAL_MAX_STEP_M = 0.1
#: Output pixels are this many input pixels wide.
OUTPUT_STRIDE = 4
#: Relative points (3), validity (1), normals (3), pixel coordinates ``u, v`` (2).
N_INPUT_CHANNELS = 9
POINT_CHANNELS = slice(0, 3)
VALIDITY_CHANNEL = 3
NORMAL_CHANNELS = slice(4, 7)
PIXEL_CHANNELS = slice(7, 9)
#: Mask codes of the shards: 0 background, 1 body, 2 + j moving part j.
MASK_BODY = 1
#: A pixel without a return whose four neighbours all have one, within this much of each other
#: (m), is a hole in a surface (a depth sensor's dropped return): :func:`fill_holes` fills it.
HOLE_MAX_SPREAD_M = 0.03


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


def fill_holes(depth_m: torch.Tensor) -> torch.Tensor:
    """(B, H, W) z-depth (0 = no return) with its holes filled: a pixel without a return whose four
    neighbours have returns within :data:`HOLE_MAX_SPREAD_M` of each other takes their mean.  A
    real sensor drops isolated returns (the Kinect v2 model's 1% random holes: ``real.noise``),
    and each hole costs its four neighbours their normals (central differences); a rendered image
    has next to none (in 512 images of each class's generated test split: 4, all on the
    refrigerator).  A hole beside another is left (its neighbour has no return), as is every
    other gap.  ``depth_m`` itself where there is nothing to fill, else a new tensor."""
    if depth_m.shape[-2] < 3 or depth_m.shape[-1] < 3:
        return depth_m
    v = depth_m > 0
    hole = ~v[:, 1:-1, 1:-1] & v[:, :-2, 1:-1] & v[:, 2:, 1:-1] & v[:, 1:-1, :-2] & v[:, 1:-1, 2:]
    if not bool(hole.any()):
        return depth_m
    b, i, j = hole.nonzero(as_tuple=True)
    i, j = i + 1, j + 1
    around = torch.stack([depth_m[b, i - 1, j], depth_m[b, i + 1, j], depth_m[b, i, j - 1], depth_m[b, i, j + 1]])
    fill = (around.amax(0) - around.amin(0)) < HOLE_MAX_SPREAD_M
    if not bool(fill.any()):
        return depth_m
    depth_m = depth_m.clone()
    depth_m[b[fill], i[fill], j[fill]] = around.mean(0)[fill]
    return depth_m


def backproject_torch(depth_m: torch.Tensor, K: torch.Tensor, *, out: torch.Tensor | None = None) -> torch.Tensor:
    """(B, H, W) z-depth and (B, 3, 3) intrinsics -> (B, 3, H, W) camera-frame points
    (x forward = z_optical, y left = -x_optical, z up = -y_optical); invalid pixels give 0.
    ``out``: a (B, 3, H, W) tensor (or view) to write them into."""
    B, H, W = depth_m.shape
    u = torch.arange(W, dtype=depth_m.dtype, device=depth_m.device)
    v = torch.arange(H, dtype=depth_m.dtype, device=depth_m.device)
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    # written channel by channel (no stack); -(a d) is computed as (-a) d, the same number
    pts = depth_m.new_empty(B, 3, H, W) if out is None else out
    if pts[:, 0].data_ptr() != depth_m.data_ptr():
        pts[:, 0] = depth_m
    torch.mul(-((u.view(1, 1, W) - cx) / fx), depth_m, out=pts[:, 1])
    torch.mul(-((v.view(1, H, 1) - cy) / fy), depth_m, out=pts[:, 2])
    return pts


def _flat_from(t: torch.Tensor, offset: int) -> torch.Tensor:
    """The contiguous ``t`` flattened, from element ``offset`` on: indexed with flat indices it
    reads or writes the elements ``offset`` further on (no index arithmetic per element)."""
    return t.view(-1)[offset:]


def _listed_normals(points: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, list]:
    """The normals of :func:`surface_normals` as a list: the flat indices (T,) into ``points`` of
    channel 0 of the pixels whose four neighbours are valid (objects cover a fraction of the image)
    and the normal's three components (T,) there (0 where a neighbour is too far), each computed
    with the same arithmetic as on the whole image.  ``points`` (B, C, H, W) contiguous, the points
    in channels 0-2 (the network input's first channels)."""
    B, C, H, W = points.shape
    P = H * W
    inner = valid[:, 1:-1, 2:] & valid[:, 1:-1, :-2] & valid[:, 2:, 1:-1] & valid[:, :-2, 1:-1] & valid[:, 1:-1, 1:-1]
    candidate = torch.zeros_like(valid)
    candidate[:, 1:-1, 1:-1] = inner
    b, p = candidate.flatten(1).nonzero(as_tuple=True)
    above = b * (C * P) + p - W  # the pixel above (channel 0): every listed pixel has one

    def point(c, dy, dx):  # channel c of the listed pixels' neighbour (dy, dx): read from a view that
        # starts that far on (index_select: faster than indexing with a tensor, and no index arithmetic)
        return _flat_from(points, c * P + (1 + dy) * W + dx).index_select(0, above)

    dx = [point(c, 0, 1) - point(c, 0, -1) for c in range(3)]
    dy = [point(c, 1, 0) - point(c, -1, 0) for c in range(3)]
    max_step2 = (2 * NORMAL_MAX_STEP_M) ** 2
    ok = (dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]) < max_step2
    ok &= (dy[0] * dy[0] + dy[1] * dy[1] + dy[2] * dy[2]) < max_step2
    return above + W, _facing_unit_normal(dx, dy, ok)[0]


def _facing_unit_normal(dx: list, dy: list, ok: torch.Tensor) -> tuple[list, torch.Tensor]:
    """The unit normal ``dx x dy`` (components (T,) each) facing the camera, 0 where not ``ok``, and
    the cross product's squared length.  The cross product and the normalisation written out: 5x
    faster than torch.cross / F.normalize on dim 1."""
    n = [dx[1] * dy[2] - dx[2] * dy[1], dx[2] * dy[0] - dx[0] * dy[2], dx[0] * dy[1] - dx[1] * dy[0]]
    norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    scale = torch.rsqrt(norm2.clamp_min(1e-24))
    # the camera looks along +x: normals point back; 0 where no normal is defined
    scale = torch.where(n[0] * scale > 0, -scale, scale) * ok
    return [nc * scale for nc in n], norm2


def one_sided_normals(x: torch.Tensor, at: torch.Tensor, allowed: torch.Tensor | None = None,
                      allowed_at: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals (3, T) facing the camera from one-sided differences, and where one is defined
    (T,), at the pixels ``at`` (flat indices of channel 0) of a network input ``x`` (B, C, H, W)
    contiguous (:func:`make_inputs`: relative points in channels 0-2, validity in channel 3).

    Along each image axis the difference to the neighbour on either side is taken: of the two,
    the shorter whose neighbour is valid, within :data:`NORMAL_MAX_STEP_M` and, with ``allowed``
    (a flat bool tensor of images' pixels, row by row: (B * H * W,) for the batch's, or any images'
    with ``allowed_at``, (T,), each listed pixel's index into it), allowed; a pixel needs one along
    each axis.  The input's central differences (:func:`surface_normals`) need both neighbours on each
    axis, so a face seen as a strip one or two pixels wide has no normal there (a cabinet's side
    wall beside its door: on seed-14 cabinet images with 101-499 body pixels, 97 of the body's
    303 pixels have one on average)."""
    B, C, H, W = x.shape
    P = H * W
    flat = x.view(-1)
    last = flat.numel() - 1
    pix = at % P
    col, row = pix % W, pix // W
    if allowed is not None and allowed_at is None:
        allowed_at = at // (C * P) * P + pix
    point = lambda off: [flat.index_select(0, (at + (c * P + off)).clamp(0, last)) for c in range(3)]  # noqa: E731
    here = point(0)
    max_step2 = (NORMAL_MAX_STEP_M / POINT_SCALE_M) ** 2

    def tangent(offset: int, forward_ok: torch.Tensor, backward_ok: torch.Tensor):
        best, best_len2 = None, None
        for off, inside in ((offset, forward_ok), (-offset, backward_ok)):
            valid = inside & (flat.index_select(0, (at + (VALIDITY_CHANNEL * P + off)).clamp(0, last)) > 0)
            if allowed is not None:
                # (allowed_at is set above whenever allowed is)
                valid &= allowed.index_select(0, (allowed_at + off).clamp(0, allowed.numel() - 1))  # type: ignore[operator, union-attr]
            d = [a - b for a, b in zip(point(off), here)] if off > 0 else [b - a for a, b in zip(point(off), here)]
            len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            len2 = torch.where(valid & (len2 < max_step2), len2, torch.full_like(len2, float("inf")))
            if best is None:
                best, best_len2 = d, len2
            else:
                # (best_len2 is set with best, on the first pass)
                take = len2 < best_len2  # type: ignore[operator]
                best = [torch.where(take, a, b) for a, b in zip(d, best)]
                best_len2 = torch.where(take, len2, best_len2)  # type: ignore[arg-type]
        return best, torch.isfinite(best_len2)  # type: ignore[arg-type]

    dx, ok_x = tangent(1, col < W - 1, col > 0)
    dy, ok_y = tangent(W, row < H - 1, row > 0)
    n, norm2 = _facing_unit_normal(dx, dy, ok_x & ok_y)
    ok = ok_x & ok_y & (norm2 > 1e-24)
    return torch.stack(n) * ok, ok


def _write_listed(t: torch.Tensor, first_channel: int, at: torch.Tensor, values: list) -> None:
    """Write ``values[c]`` (T,) into channel ``first_channel + c`` of the contiguous ``t`` at the flat
    indices ``at`` of channel 0."""
    P = t.shape[-2] * t.shape[-1]
    for c, v in enumerate(values):
        _flat_from(t, (first_channel + c) * P).index_copy_(0, at, v)


def surface_normals(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Unit normals (B, 3, H, W) facing the camera, from central differences of the points;
    0 where a neighbour is invalid or further than :data:`NORMAL_MAX_STEP_M` (so 0 on the image
    border).  Computed at the pixels with four valid neighbours only (:func:`_listed_normals`)."""
    B, _, H, W = points.shape
    out = points.new_zeros(B, 3, H, W)
    if H >= 3 and W >= 3:
        at, n = _listed_normals(points.contiguous(), valid)
        _write_listed(out, 0, at, n)
    return out


def make_inputs(depth_m: torch.Tensor, K: torch.Tensor, *, out: torch.Tensor | None = None) -> dict:
    """Network input and geometry of a batch at the model resolution.

    ``depth_m`` (B, H, W) float32 metres (0 = no return; its holes filled first: :func:`fill_holes`),
    ``K`` (B, 3, 3).  Returns a dict:
    ``x`` (B, 9, H, W) input, ``anchor`` (B, 3) m, ``points_out`` (B, 3, h, w) mean point
    of each output pixel (m), ``weight_out`` (B, h, w) fraction of valid pixels under it.
    ``out``: a (B, 9, H, W) tensor to write ``x`` into (a batch loop passes the previous batch's
    ``x`` once it is done with it: a fresh 95 MB tensor costs more in page faults than filling it).

    The channels are written into one tensor (no concatenation): the back-projection straight into
    channels 0-2, which are pooled (with the validity, channel 3) to the output pixels' means, give
    the normals, and are then turned into relative points in place; the normals are computed at the
    pixels with four valid neighbours only (:func:`_listed_normals`).  Every number as the
    whole-image formulas give it.
    """
    depth_m = fill_holes(depth_m)
    B, H, W = depth_m.shape
    shape = (B, N_INPUT_CHANNELS, H, W)
    x = out if out is not None and tuple(out.shape) == shape and out.dtype == depth_m.dtype and out.is_contiguous() \
        else depth_m.new_empty(shape)
    valid = depth_m > 0
    w = x[:, VALIDITY_CHANNEL]
    w.copy_(valid)  # the validity channel (1.0 / 0.0)
    # the points of the depth with the invalid pixels' zeroed (the same as back-projecting the depth
    # and multiplying by the validity), written into channels 0-2
    pts = backproject_torch(torch.mul(depth_m, w, out=x[:, POINT_CHANNELS.start]), K, out=x[:, POINT_CHANNELS])
    n_valid = w.sum((1, 2)).clamp_min(1.0)[:, None]
    anchor = pts.sum((2, 3)) / n_valid
    w_out, p_out = _output_means(x)
    x[:, NORMAL_CHANNELS].zero_()
    if H >= 3 and W >= 3:
        at, n = _listed_normals(x, valid)
        _write_listed(x, NORMAL_CHANNELS.start, at, n)
    # (p - a) / s at the valid pixels, 0 elsewhere, in place
    # (multiplying by the validity leaves -0.0 at some invalid pixels: equal to 0, and the same to the network)
    pts.sub_(anchor[:, :, None, None]).div_(POINT_SCALE_M).mul_(w[:, None])
    x[:, PIXEL_CHANNELS.start] = torch.linspace(-1, 1, W, dtype=depth_m.dtype, device=depth_m.device).view(1, 1, W)
    x[:, PIXEL_CHANNELS.start + 1] = torch.linspace(-1, 1, H, dtype=depth_m.dtype, device=depth_m.device).view(1, H, 1)
    return {"x": x, "anchor": anchor, "points_out": p_out, "weight_out": w_out}


def _output_means(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``avg_pool2d(w, s, ceil_mode=True)`` (B, h, w) and ``avg_pool2d(p w, s, ceil_mode=True) /
    max(that, 1e-6)`` (B, 3, h, w) for the stride :data:`OUTPUT_STRIDE`, from the input ``x``
    (B, C, H, W) contiguous holding the zeroed points ``p w`` in channels 0-2 and ``w`` in
    channel 3.  Where ``s`` divides the image, the windows' pixel counts are summed (integers: any
    order is exact) and the points summed only over the windows with a valid pixel, each window's
    pixels in the pooling's order (row by row), from 0, and divided by the window's size, as the
    pooling does (whose strided kernel is several times slower)."""
    B, C, H, W = x.shape
    s = OUTPUT_STRIDE
    if H % s or W % s:
        pooled = F.avg_pool2d(x[:, 0:4], s, ceil_mode=True)
        return pooled[:, 3].contiguous(), pooled[:, 0:3] / pooled[:, 3:4].clamp_min(1e-6)
    h, w = H // s, W // s
    counts = x[:, 3].unflatten(2, (w, s)).sum(-1).unflatten(1, (h, s)).sum(2)  # (B, h, w)
    w_out = counts / (s * s)
    window = (counts > 0).view(-1).nonzero()[:, 0]  # flat (b, i, j) of the windows with a valid pixel
    b, ij = window // (h * w), window % (h * w)
    first = b * (C * H * W) + ij // w * (s * W) + ij % w * s  # the window's top-left pixel, channel 0
    first = (first[:, None] + torch.arange(3, device=x.device) * (H * W)).view(-1)  # (n * 3,): channels 0-2
    flat = x.view(-1)
    total = flat.index_select(0, first)  # index_select: faster than indexing with a tensor
    for dy in range(s):  # the window's other pixels, row by row
        for dx in range(s):
            if dy or dx:
                total += flat.index_select(0, first + (dy * W + dx))
    sums = x.new_zeros(B * h * w, 3)
    sums[window] = total.view(-1, 3)
    p_out = (sums.view(B, h, w, 3).permute(0, 3, 1, 2) / (s * s)) / w_out[:, None].clamp_min(1e-6)
    return w_out, p_out.contiguous()


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
