"""Pinhole camera of the dataset, its frames and (back-)projection.

Frames
------
* **camera frame** (all labels): origin at the camera centre, x forward (viewing direction),
  y left, z up.  This is also MuJoCo's world frame in every generated scene.
* **optical frame** (OpenCV): x right, y down, z forward.  ``p_optical = R_CAMERA_TO_OPTICAL @ p_camera``.

Intrinsics follow the OpenCV convention with pixel centres at integer coordinates, so the
principal point of a centred W x H image is ``((W - 1) / 2, (H - 1) / 2)``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: Rotation taking camera-frame vectors (x fwd, y left, z up) to optical-frame vectors
#: (x right, y down, z fwd).
R_CAMERA_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: Vertical field of view of the Kinect v2 colour camera used by default (degrees).
KINECT_V2_VFOV_DEG = 54.28
DEFAULT_WIDTH_PX = 192
DEFAULT_HEIGHT_PX = 108


@dataclass(frozen=True)
class CameraConfig:
    """Image size and vertical field of view; square pixels, centred principal point."""

    width_px: int = DEFAULT_WIDTH_PX
    height_px: int = DEFAULT_HEIGHT_PX
    vfov_deg: float = KINECT_V2_VFOV_DEG

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not 0.0 < self.vfov_deg < 180.0:
            raise ValueError(f"vertical field of view must be in (0, 180) degrees, got {self.vfov_deg}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: ``f = (H / 2) / tan(vfov / 2)``."""
        return (self.height_px / 2.0) / math.tan(math.radians(self.vfov_deg) / 2.0)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        """3x3 OpenCV intrinsic matrix (float64)."""
        f = self.focal_px
        return np.array(
            [[f, 0.0, (self.width_px - 1) / 2.0], [0.0, f, (self.height_px - 1) / 2.0], [0.0, 0.0, 1.0]]
        )

    def to_dict(self) -> dict:
        return asdict(self)


def backproject(depth_m: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Back-project a z-depth image to camera-frame points.

    ``z = depth[v, u]``; ``p_optical = ((u - cx) z / fx, (v - cy) z / fy, z)``;
    ``p_camera = R_CAMERA_TO_OPTICAL.T @ p_optical``.  Pixels with depth 0 (no return) and,
    if ``mask`` is given, pixels where ``mask`` is False are skipped.

    Returns an (N, 3) float64 array in metres, camera frame, in row-major pixel order.
    """
    depth_m = np.asarray(depth_m)
    valid = depth_m > 0
    if mask is not None:
        valid &= np.asarray(mask, dtype=bool)
    v, u = np.nonzero(valid)
    z = depth_m[v, u].astype(np.float64)
    x_opt = (u - K[0, 2]) * z / K[0, 0]
    y_opt = (v - K[1, 2]) * z / K[1, 1]
    p_opt = np.stack([x_opt, y_opt, z], axis=1)
    return p_opt @ R_CAMERA_TO_OPTICAL  # == (R^T p^T)^T


def project(points_camera: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points to pixels.

    Returns ``(uv, z)``: (N, 2) pixel coordinates (integer = pixel centre) and the (N,)
    optical depth in metres.  Points with ``z <= 0`` are behind the camera (uv is then NaN).
    """
    p = np.atleast_2d(np.asarray(points_camera, dtype=np.float64)) @ R_CAMERA_TO_OPTICAL.T
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    uv = np.stack([u, v], axis=1)
    uv[z <= 0] = np.nan
    return uv, z
