"""Depth image -> network input (the MDN's input normalisation).

For a depth image ``d`` (metres, 0 = no return) with validity ``v = d > 0`` and median
``m`` of its valid depths:

* channel 0, relative depth: ``v * (d - m) / RELATIVE_DEPTH_SCALE_M`` (background 0), where
  ``m`` is ``torch.nanmedian`` of the valid depths (the lower middle value for an even count);
* channel 1, validity (optional, ``mask_channel``): ``v`` (after resizing: the fraction of
  valid source pixels under each output pixel);
* channels 2-3, pixel coordinates (optional, ``coord_channels``): ``u, v`` scaled to
  [-1, 1] across the image, so the convolutions can tell where in the image a surface is
  (the axis position depends on it);
* the scalars ``(m - MEDIAN_REFERENCE_M) / MEDIAN_SCALE_M`` and ``(a - (MEDIAN_REFERENCE_M, 0,
  0)) / MEDIAN_SCALE_M`` are given to the heads, where the anchor ``a`` is the centroid of the
  back-projected valid pixels (camera frame, metres; :func:`image_anchor`), so the absolute
  distance removed from channel 0 is not lost.  The network predicts axis origins
  relative to this anchor (see :mod:`articulated_dataset.methods.mdn.data`): a convolutional
  network with global pooling is good at shapes and poor at absolute image positions.

Resizing to the model resolution is validity-weighted area averaging:
``d_small = area(v * d) / area(v)`` where ``area(v) > 0``, so background zeros never blend
into surface depths.  The stored form (see :func:`preprocess_depth`) keeps channels 0-1 as
float16; :func:`assemble_inputs` adds the coordinate channels per batch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch.nn import functional as F

from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL

#: Relative depths are divided by this (m): object surfaces span about +-1 m around the median.
RELATIVE_DEPTH_SCALE_M = 0.5
#: Median depth normalisation for the heads' scalar input (m): objects stand 0.1-5 m away.
MEDIAN_REFERENCE_M = 1.5
MEDIAN_SCALE_M = 1.0
#: Median and anchor used for an image without any valid pixel (m); it carries no signal.
EMPTY_IMAGE_MEDIAN_M = MEDIAN_REFERENCE_M
EMPTY_IMAGE_ANCHOR_M = (MEDIAN_REFERENCE_M, 0.0, 0.0)
#: Per-image scalars given to the heads: the median depth and the anchor's x, y, z.
N_SCALARS = 4
STORED_CHANNELS = 2  # relative depth, validity


@dataclass(frozen=True)
class InputConfig:
    """Model input resolution and channels (stored in checkpoints)."""

    height_px: int
    width_px: int
    mask_channel: bool = True
    coord_channels: bool = True

    @property
    def channels(self) -> int:
        """Number of input channels: depth, plus the mask, plus two pixel-coordinate channels, as configured."""
        return 1 + int(self.mask_channel) + 2 * int(self.coord_channels)

    def to_dict(self) -> dict:
        """The input configuration as a dict (stored in checkpoints)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "InputConfig":
        """The input configuration from its :meth:`to_dict` form."""
        return cls(**d)


def image_anchor(depth_m: torch.Tensor, K: np.ndarray) -> torch.Tensor:
    """Centroid (B, 3), metres, camera frame, of the back-projected valid pixels of each image.

    With ``z = d[v, u] > 0``: ``p_optical = ((u - cx) z / fx, (v - cy) z / fy, z)``,
    ``p_camera = R_CAMERA_TO_OPTICAL^T p_optical`` (as :func:`articulated_dataset.core.camera.backproject`)
    and the anchor is the mean of ``p_camera`` over the valid pixels; an image without any
    valid pixel gets ``EMPTY_IMAGE_ANCHOR_M``.
    """
    d = depth_m.double().flatten(1)  # (B, H*W)
    B = d.shape[0]
    H, W = depth_m.shape[1:]
    K = np.asarray(K, np.float64)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    n = (d > 0).sum(dim=1).double()
    # sum over valid pixels of (u z, v z, z): background pixels have z = 0 and add nothing
    sums = d @ torch.stack([u.flatten(), v.flatten(), torch.ones(H * W, dtype=torch.float64)], dim=1)  # (B, 3)
    mean_z = sums[:, 2] / n.clamp_min(1.0)
    mean_opt = torch.stack([(sums[:, 0] / n.clamp_min(1.0) - K[0, 2] * mean_z) / K[0, 0],
                            (sums[:, 1] / n.clamp_min(1.0) - K[1, 2] * mean_z) / K[1, 1], mean_z], dim=1)
    anchor = mean_opt @ torch.as_tensor(R_CAMERA_TO_OPTICAL)  # p_cam = R^T p_opt, row-vector form
    empty = torch.as_tensor(EMPTY_IMAGE_ANCHOR_M, dtype=torch.float64).expand(B, 3)
    return torch.where((n > 0)[:, None], anchor, empty).float()


def preprocess_depth(depth_m, config: InputConfig, K: np.ndarray | None = None):
    """Depth images (B, H, W) in metres -> stored inputs.

    Returns ``(planes, scalars, anchor_m)``: planes (B, 2, h, w) float16 = relative depth
    and validity at the model resolution ``(h, w) = (config.height_px, config.width_px)``;
    scalars (B, 4) float32 = normalised median depth and normalised anchor; anchor_m (B, 3)
    float32 = :func:`image_anchor` in metres (needs the intrinsics ``K``; without them the
    anchor is ``EMPTY_IMAGE_ANCHOR_M`` for every image).  Formulas in the module docstring.
    """
    d = torch.as_tensor(np.asarray(depth_m, dtype=np.float32))
    if d.dim() != 3:
        raise ValueError(f"expected depth images (B, H, W), got shape {tuple(d.shape)}")
    valid = d > 0
    median = torch.nanmedian(torch.where(valid, d, torch.nan).flatten(1), dim=1).values
    median = torch.where(torch.isnan(median), torch.full_like(median, EMPTY_IMAGE_MEDIAN_M), median)
    v = valid.float()
    rel = v * (d - median[:, None, None]) / RELATIVE_DEPTH_SCALE_M
    planes = torch.stack([rel, v], dim=1)
    size = (config.height_px, config.width_px)
    if tuple(d.shape[1:]) != size:
        planes = F.interpolate(planes, size=size, mode="area")
        frac = planes[:, 1:2]
        planes = torch.cat([torch.where(frac > 0, planes[:, :1] / frac.clamp_min(1e-12), 0.0), frac], dim=1)
    if K is None:
        anchor = torch.as_tensor(EMPTY_IMAGE_ANCHOR_M, dtype=torch.float32).expand(d.shape[0], 3).clone()
    else:
        anchor = image_anchor(d, K)
    reference = torch.as_tensor(EMPTY_IMAGE_ANCHOR_M, dtype=torch.float32)
    scalars = torch.cat([((median - MEDIAN_REFERENCE_M) / MEDIAN_SCALE_M)[:, None], (anchor - reference) / MEDIAN_SCALE_M], dim=1)
    return planes.to(torch.float16), scalars.float(), anchor


def coordinate_planes(height_px: int, width_px: int) -> torch.Tensor:
    """(2, h, w) pixel coordinates u (column) and v (row), each linearly spaced over [-1, 1]."""
    v, u = torch.meshgrid(torch.linspace(-1.0, 1.0, height_px), torch.linspace(-1.0, 1.0, width_px), indexing="ij")
    return torch.stack([u, v])


def assemble_inputs(planes: torch.Tensor, config: InputConfig) -> torch.Tensor:
    """Stored planes (B, 2, h, w) -> network input (B, config.channels, h, w) float32."""
    x = planes.float()
    if not config.mask_channel:
        x = x[:, :1]
    if config.coord_channels:
        coords = coordinate_planes(config.height_px, config.width_px).to(x.device)
        x = torch.cat([x, coords.expand(x.shape[0], -1, -1, -1)], dim=1)
    return x
