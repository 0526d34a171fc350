"""One capture in, one image at the training resolution out (:func:`ingest_capture`): load the
depth or cloud, the mask and the labels (or the part poses), and resample them to the training
camera."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from articulated_dataset.classes.registry import get_class
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.images.intrinsics import check_intrinsics, check_source_size, load_intrinsics
from articulated_dataset.core.images.resample import (
    DEFAULT_CROP_MARGIN,
    RESAMPLERS,
    crop_intrinsics,
    mask_fraction_inside,
    resample_depth,
)
from articulated_dataset.format import MASK_BODY
from articulated_dataset.ingest.captures import MASK_SUFFIX, CaptureFiles
from articulated_dataset.ingest.ground_truth import empty_labels, load_ground_truth
from articulated_dataset.ingest.readers import DEPTH_UNITS, load_cloud, load_depth, load_mask, rasterise_cloud

log = logging.getLogger(__name__)

#: Stored depth is rounded to multiples of 2**-13 m (0.12 mm), like generated depth.
DEPTH_QUANTUM_M = 2.0**-13
FITS = ("training", "crop")
CLOUD_FRAMES = ("optical", "camera")


class IngestOptionsRecord(TypedDict):
    """The conversion options an ingested split records in its manifest (``real.options``;
    :meth:`IngestOptions.to_dict`)."""

    fit: str  # one of FITS
    resample: str  # one of RESAMPLERS
    crop_margin: float  # fit "crop": added on each side of the mask's bounding box, fraction of its size
    depth_units: str  # one of DEPTH_UNITS
    cloud_frame: str  # one of CLOUD_FRAMES
    keep_background: bool


@dataclass
class IngestOptions:
    """How captures are converted (see :func:`ingest_capture`)."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    fit: str = "training"
    resample: str = "nearest"
    crop_margin: float = DEFAULT_CROP_MARGIN
    depth_units: str = "auto"
    cloud_frame: str = "optical"
    keep_background: bool = False
    intrinsics: np.ndarray | None = None  # K for every capture (overrides camera files)
    source_size: tuple[int, int] | None = None  # (W, H) of rasterised clouds without a size in the camera file

    def __post_init__(self) -> None:
        for value, allowed, what in ((self.fit, FITS, "fit"), (self.resample, RESAMPLERS, "resampling"),
                                     (self.depth_units, DEPTH_UNITS, "depth units"), (self.cloud_frame, CLOUD_FRAMES, "cloud frame")):
            if value not in allowed:
                raise UserError(f"unknown {what} {value!r}; choose from: {', '.join(allowed)}")
        if not 0.0 <= self.crop_margin < 10.0:
            raise UserError(f"crop margin must be in [0, 10), got {self.crop_margin}")

    def to_dict(self) -> IngestOptionsRecord:
        """The conversion options recorded in the ingested split's manifest (camera, intrinsics and source size
        excluded)."""
        return {"fit": self.fit, "resample": self.resample, "crop_margin": self.crop_margin, "depth_units": self.depth_units,
                "cloud_frame": self.cloud_frame, "keep_background": self.keep_background}


@dataclass
class Capture:
    """One ingested capture at the training resolution."""

    name: str
    depth: np.ndarray  # (H, W) float32 m
    mask: np.ndarray  # (H, W) uint8
    K: np.ndarray  # (3, 3)
    labels: dict  # float label arrays (NaN where unknown) + "object"
    mask_fraction_inside: float = 1.0
    has_labels: bool = False


def ingest_capture(files: CaptureFiles, class_name: str, options: IngestOptions) -> Capture:
    """Load one capture and resample it to the training camera (module docstring)."""
    obj_class = get_class(class_name)
    J = obj_class.n_joints
    if files.parts is not None and files.labels is not None:
        raise UserError(f"{files.data}: ground truth in both {files.labels.name} and {files.parts.name}; "
                        f"keep one of them")
    size = None
    if options.intrinsics is not None:
        K_src = np.asarray(options.intrinsics, np.float64)
    elif files.camera is not None:
        K_src, size = load_intrinsics(files.camera)
    else:
        raise UserError(f"{files.data}: intrinsics missing; pass {option('intrinsics_path')} FILE or "
                        f"{option('fx')}/{option('fy')}/{option('cx')}/{option('cy')}, or put camera.json next to it")
    if files.is_cloud:
        size = size or options.source_size
        if size is None:
            raise UserError(f"{files.data}: rasterising a point cloud needs the sensor's image size "
                            f"(width/height in the camera file, or {option('source_size')} WxH)")
        check_source_size(size, str(files.data))
        check_intrinsics(K_src, size, str(files.data))
        points = load_cloud(files.data)
        if options.cloud_frame == "camera":
            points = points @ R_CAMERA_TO_OPTICAL.T
        depth = rasterise_cloud(points, K_src, size)
        if not (depth > 0).any():
            raise UserError(f"{files.data}: no point projects into the {size[0]}x{size[1]} image "
                            f"(check {option('cloud_frame')} and the intrinsics)")
    else:
        depth = load_depth(files.data, options.depth_units)
        if size is not None and (depth.shape[1], depth.shape[0]) != tuple(size):
            raise UserError(f"{files.data}: depth is {depth.shape[1]}x{depth.shape[0]} px but the camera file "
                            f"{files.camera} says {size[0]}x{size[1]}")
        check_intrinsics(K_src, (depth.shape[1], depth.shape[0]), str(files.data))
    record = None
    if files.parts is not None:
        from articulated_dataset.ingest.part_annotations import load_part_pose_ground_truth

        record = load_part_pose_ground_truth(files.parts, class_name, depth.shape)
        if record.mask is not None and files.mask is not None:
            raise UserError(f"{files.data}: masks in both {files.mask.name} and {files.parts.name}; keep one of them")
    given = load_mask(files.mask, depth.shape, J) if files.mask is not None else None
    if given is None and record is not None:
        given = record.mask
    if given is not None:
        mask = given
        if not mask.any():
            raise UserError(f"{files.mask or files.parts}: the mask marks no object pixel")
        if not (depth[mask > 0] > 0).any():
            log.warning("%s: no pixel of the mask has a depth return; the segmented cloud is empty", files.data)
        if not options.keep_background:
            depth = np.where(mask > 0, depth, 0.0)
    else:
        mask = (depth > 0).astype(np.uint8) * np.uint8(MASK_BODY)
    cam = options.camera
    out_size = (cam.width_px, cam.height_px)
    if options.fit == "crop":
        if given is None:
            raise UserError(f"{files.data}: {option('fit')} crop needs a segmentation mask ({files.name}{MASK_SUFFIX})")
        K_dst = crop_intrinsics(K_src, mask > 0, out_size, options.crop_margin)
    else:
        K_dst = cam.K
    inside = mask_fraction_inside(mask > 0, K_src, K_dst, out_size)
    if inside == 0.0 and (mask > 0).any():
        raise UserError(f"{files.data}: the object lies outside the training camera's field of view; "
                        f"use {option('fit')} crop")
    if inside < 1.0:
        log.warning("%s: %.1f%% of the object's pixels fall outside the training camera's field of view",
                    files.data, 100.0 * (1.0 - inside))
    depth_r, mask_r = resample_depth(depth, mask, K_src, K_dst, out_size, options.resample)
    if given is not None and not options.keep_background:
        depth_r = np.where(mask_r > 0, depth_r, 0.0)
    if (depth[mask > 0] > 0).any() and not (depth_r[mask_r > 0] > 0).any():
        raise UserError(f"{files.data}: no depth return of the object survives resampling onto the "
                        f"{out_size[0]}x{out_size[1]} training camera (fx={K_src[0, 0]:g}, fy={K_src[1, 1]:g} px); "
                        f"check the intrinsics, or use {option('fit')} crop")
    depth_r = (np.round(depth_r / DEPTH_QUANTUM_M) * DEPTH_QUANTUM_M).astype(np.float32)
    if record is not None:
        labels = record.labels
    else:
        labels = load_ground_truth(files.labels, J, class_name) if files.labels is not None else empty_labels(J)
    return Capture(files.name, depth_r, mask_r, K_dst, labels, inside, files.labels is not None or record is not None)
