"""Pinhole camera of the dataset, its frames and (back-)projection.

Frames
------
* **camera frame** (all labels): origin at the camera centre, x forward (viewing direction),
  y left, z up.  This is also MuJoCo's world frame in every generated scene.
* **optical frame** (OpenCV): x right, y down, z forward.  ``p_optical = R_CAMERA_TO_OPTICAL @ p_camera``.

Intrinsics follow the OpenCV convention with pixel centres at integer coordinates, so the
principal point of a centred W x H image is ``((W - 1) / 2, (H - 1) / 2)``.

The paper's camera (the default) has square pixels, a centred principal point and the
vertical field of view ``vfov_deg``.  An intrinsics preset (:data:`INTRINSICS_PRESETS`,
``artdata generate --intrinsics``) instead gives a real sensor's depth-camera matrix at its
native resolution, scaled to the image size as resizing the sensor's image would
(:meth:`CameraCalibration.scaled`).

:func:`camera_from_options` is the camera that ``artdata generate``'s options
(``--width/--height`` or ``--resolution``, ``--vfov`` or ``--intrinsics``, ``--camera``) name.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass

import numpy as np

#: Rotation taking camera-frame vectors (x fwd, y left, z up) to optical-frame vectors
#: (x right, y down, z fwd).
R_CAMERA_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: Vertical field of view of the Kinect v2 colour camera used by default (degrees).
KINECT_V2_VFOV_DEG = 54.28
#: Where the camera is: ``fixed`` (the paper's placement around the object) or ``head`` (a
#: robot's head camera: :mod:`articulated_dataset.generation.viewpoint`).
CAMERA_MOUNTS = ("fixed", "head")
DEFAULT_WIDTH_PX = 192
DEFAULT_HEIGHT_PX = 108
#: Largest image side: OpenGL drivers cap offscreen buffers (Mesa's llvmpipe at 16384 px);
#: larger sizes would fail inside the driver instead of with a message.
MAX_IMAGE_SIDE_PX = 16384


@dataclass(frozen=True)
class CameraCalibration:
    """A depth camera's pinhole intrinsics (px, OpenCV convention) at its native resolution."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    source: str

    def scaled(self, width_px: int, height_px: int) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` of the sensor's image resized to ``width_px`` x ``height_px``:
        pixel edges scale, so ``cx' = (cx + 0.5) W' / W - 0.5`` (pixel centres at integers)."""
        sx, sy = width_px / self.width_px, height_px / self.height_px
        return self.fx_px * sx, self.fy_px * sy, (self.cx_px + 0.5) * sx - 0.5, (self.cy_px + 0.5) * sy - 0.5


#: Depth-camera intrinsics presets (``artdata generate --intrinsics NAME``).  Each is one unit's
#: factory calibration as its SDK reports it; other units differ by about 1% in focal length
#: and a few pixels in principal point.  Lens distortion is not modelled (pinhole rendering).
INTRINSICS_PRESETS: dict[str, CameraCalibration] = {
    # Kinect v2 depth (IR) camera, 512x424: the factory IR parameters read by libfreenect2
    # (Freenect2Device::getIrCameraParams) that are widely reused for Kinect v2 data; field
    # of view 70.0 x 60.2 deg (Microsoft's specification: 70.6 x 60 deg).
    "kinect2": CameraCalibration(512, 424, 365.456, 365.456, 254.878, 205.395,
                                 "Kinect v2 depth camera, libfreenect2 factory IR parameters"),
    # Intel RealSense D435 depth stream at its native 1280x720: librealsense
    # rs2_intrinsics of a D435 (get_intrinsics() on the depth stream profile); field of view
    # 90 x 59 deg (Intel's D400-series datasheet: depth FOV 87 +- 3 x 58 +- 1 deg).
    "d435": CameraCalibration(1280, 720, 637.6, 637.6, 638.3, 370.5,
                              "Intel RealSense D435 depth stream 1280x720, librealsense rs2_intrinsics"),
    # Azure Kinect DK depth camera, NFOV unbinned mode 640x576: k4a_calibration_t
    # depth_camera_calibration intrinsics of one unit (Azure Kinect Sensor SDK); field of
    # view 64.8 x 59.3 deg of the full rectangle (Microsoft's hardware specification gives the
    # NFOV mode's hexagonal field as 75 x 65 deg).
    "azure-kinect": CameraCalibration(640, 576, 503.928, 503.979, 332.064, 325.881,
                                      "Azure Kinect DK depth camera NFOV unbinned 640x576, Azure Kinect Sensor SDK calibration"),
}


def parse_resolution(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)``; anything else (or a zero side) is a :class:`UserError`."""
    from articulated_dataset.core.errors import UserError, option

    m = re.fullmatch(r"\s*(\d{1,6})\s*[xX]\s*(\d{1,6})\s*", str(text))
    if m is None:
        raise UserError(f"{option('resolution')} must be WIDTHxHEIGHT in pixels (e.g. 192x108), got {str(text)[:40]!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if w <= 0 or h <= 0:
        raise UserError(f"{option('resolution')} must have positive sides, got {w}x{h}")
    return w, h


@dataclass(frozen=True)
class CameraConfig:
    """Image size and intrinsics of the camera, and how it is mounted.

    Without ``intrinsics`` (the paper's camera): square pixels, centred principal point and
    the vertical field of view ``vfov_deg``.  With ``intrinsics`` (a key of
    :data:`INTRINSICS_PRESETS`): that sensor's matrix scaled to the image size; ``vfov_deg``
    is then derived from it (the angle between the top and bottom image edges).

    ``mount``: ``"fixed"`` (the paper's camera: level, at the origin of the tables' frame) or
    ``"head"`` (a mobile manipulator's head camera: height, pitch and roll sampled per image,
    :mod:`articulated_dataset.generation.viewpoint`).
    """

    width_px: int = DEFAULT_WIDTH_PX
    height_px: int = DEFAULT_HEIGHT_PX
    vfov_deg: float = KINECT_V2_VFOV_DEG
    intrinsics: str | None = None
    mount: str = "fixed"

    def __post_init__(self) -> None:
        if isinstance(self.width_px, bool) or isinstance(self.height_px, bool) or self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if self.intrinsics is not None:
            if self.intrinsics not in INTRINSICS_PRESETS:
                raise ValueError(f"unknown intrinsics preset {str(self.intrinsics)[:40]!r}; "
                                 f"choose from: {', '.join(INTRINSICS_PRESETS)}")
            _, fy, _, cy = INTRINSICS_PRESETS[self.intrinsics].scaled(self.width_px, self.height_px)
            vfov = math.degrees(math.atan((cy + 0.5) / fy) + math.atan((self.height_px - 0.5 - cy) / fy))
            object.__setattr__(self, "vfov_deg", vfov)
        if not 0.0 < self.vfov_deg < 180.0:
            raise ValueError(f"vertical field of view must be in (0, 180) degrees, got {self.vfov_deg}")
        if self.mount not in CAMERA_MOUNTS:
            raise ValueError(f"unknown camera mount {str(self.mount)[:40]!r}; choose from: {', '.join(CAMERA_MOUNTS)}")

    @property
    def focal_px(self) -> float:
        """Vertical focal length in pixels (``(H / 2) / tan(vfov / 2)`` for the paper's camera)."""
        if self.intrinsics is not None:
            return self.intrinsics_px[1]
        return (self.height_px / 2.0) / math.tan(math.radians(self.vfov_deg) / 2.0)

    @property
    def intrinsics_px(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` in pixels."""
        if self.intrinsics is not None:
            return INTRINSICS_PRESETS[self.intrinsics].scaled(self.width_px, self.height_px)
        f = self.focal_px
        return f, f, (self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        """3x3 OpenCV intrinsic matrix (float64)."""
        fx, fy, cx, cy = self.intrinsics_px
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        """The fields as a dict; the options added after the paper's camera appear only when
        set, so a default camera's dict (and every manifest holding it) is as it was."""
        d = asdict(self)
        if self.intrinsics is None:
            del d["intrinsics"]
        if self.mount == "fixed":
            del d["mount"]
        return d


def camera_from_options(width: int | None, height: int | None, resolution: str | None, vfov: float | None,
                        intrinsics: str | None, mount: str = "fixed") -> CameraConfig:
    """The camera of ``--width/--height`` or ``--resolution``, ``--vfov`` or ``--intrinsics``
    and ``--camera``; contradictions and impossible values are one-line UserErrors."""
    from articulated_dataset.core.errors import UserError, option

    if resolution is not None:
        if width is not None or height is not None:
            raise UserError(f"give either {option('resolution')} or {option('width')}/{option('height')}, not both")
        width, height = parse_resolution(resolution)
    if intrinsics is not None:
        if vfov is not None:
            raise UserError(f"{option('vfov')} is for the paper's camera; {option('intrinsics')} gives the sensor's own "
                            "field of view")
        native = INTRINSICS_PRESETS[intrinsics]
        width = native.width_px if width is None else width
        height = native.height_px if height is None else height
    width = DEFAULT_WIDTH_PX if width is None else width
    height = DEFAULT_HEIGHT_PX if height is None else height
    for name, px in ((option("width"), width), (option("height"), height)):
        if px > MAX_IMAGE_SIDE_PX:
            name = option("resolution") if resolution is not None else name
            raise UserError(f"{name} {px} px is larger than the renderer's largest image side ({MAX_IMAGE_SIDE_PX} px)")
    try:
        return CameraConfig(width, height, KINECT_V2_VFOV_DEG if vfov is None else vfov, intrinsics=intrinsics, mount=mount)
    except ValueError as exc:
        raise UserError(str(exc)) from None


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
