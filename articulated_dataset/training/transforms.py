"""Seeded sample transforms shared by the PyTorch and the JAX loaders (numpy only).

A transform is a callable ``transform(sample, rng) -> sample``: ``sample`` is one image's dict
of numpy arrays (``depth`` (H, W) float32 m, ``mask`` (H, W) uint8, optional ``K`` (3, 3) and
labels) and ``rng`` a ``numpy.random.Generator``; every random draw comes from ``rng``.  The
loaders call it with :func:`sample_rng` ``(seed, epoch, index)``, so a sample gets the same
augmentation in both frameworks, whatever the number of workers, and a new one every epoch.

Geometric transforms keep the 3-D labels valid (they are in the camera frame, which cropping
and resizing do not move) and update ``K`` when the sample carries it:

* crop by ``(top, left)``: ``cx' = cx - left``, ``cy' = cy - top``;
* resize by ``s_x = W'/W``, ``s_y = H'/H`` (pixel centres at integer coordinates):
  ``fx' = s_x fx``, ``cx' = s_x (cx + 1/2) - 1/2`` (same for y).

``visible_pixels`` keeps counting pixels of the full rendered image.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.format import IMAGE_FIELDS
from articulated_dataset.format.schema import RGB_FIELDS

#: Fields cropped and resized with the images: depth, mask and (``--rgb`` splits) rgb (H, W, 3).
SPATIAL_FIELDS = IMAGE_FIELDS + tuple(f.name for f in RGB_FIELDS)

#: Stream tag of the transform generators (independent of the shuffling stream).
TRANSFORM_STREAM = 0x5EED0003

Transform = Callable[[dict, np.random.Generator], dict]


def _epoch_words(epoch) -> list[int]:
    if isinstance(epoch, (int, np.integer)):
        return [int(epoch)]
    return [int(w) for w in epoch]


def sample_rng(seed: int, epoch, index: int) -> np.random.Generator:
    """The generator a loader passes to the transform of sample ``index`` in ``epoch``.

    ``epoch`` is the epoch number (an int), or, for a dataset whose epoch was never set (a stock
    DataLoader that calls only its sampler's ``set_epoch``), the key the dataset derived for
    this read of the sample (a sequence of non-negative ints; see docs/loaders.md)."""
    return np.random.default_rng([int(seed), *_epoch_words(epoch), int(index), TRANSFORM_STREAM])


def apply_to_batch(transform: Transform, batch: dict, indices: Sequence[int] | np.ndarray, *, seed: int,
                   epoch) -> dict:
    """Apply ``transform`` to every sample of ``batch`` (arrays stacked on axis 0) and restack.

    ``epoch``: one int for the whole batch, or one key per sample (a (B, k) array of
    non-negative ints, see :func:`sample_rng`)."""
    indices = np.asarray(indices, dtype=np.int64)
    per_sample = not isinstance(epoch, (int, np.integer))
    if per_sample and len(epoch) != len(indices):
        raise ValueError(f"{len(epoch)} epoch keys for {len(indices)} samples")
    out = []
    for b, index in enumerate(indices):
        sample = {k: v[b] for k, v in batch.items()}
        result = transform(sample, sample_rng(seed, epoch[b] if per_sample else epoch, int(index)))
        if not isinstance(result, dict):  # a transform that edits in place and forgets to return the sample
            raise TypeError(f"transform {transform!r} returned {type(result).__name__}, not the sample's dict "
                            f"(a transform returns the sample it was given, changed)")
        out.append(result)
    if not out:
        return batch
    keys = out[0].keys()
    if any(s.keys() != keys for s in out):
        raise ValueError(f"transform {transform!r} returned samples with different fields in one batch")
    return {k: np.stack([s[k] for s in out]) for k in keys}


def _positive_int(name: str, v) -> int:
    if not isinstance(v, (int, np.integer)) or v <= 0:
        raise UserError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


def _image_size(sample: dict) -> tuple[int, int]:
    for name in IMAGE_FIELDS:
        if name in sample:
            return tuple(np.shape(sample[name])[-2:])
    raise UserError("image transforms need 'depth' or 'mask' in the sample")


class Compose:
    """Apply transforms in order (each gets the same generator, drawing in sequence)."""

    def __init__(self, transforms: Sequence[Transform]):
        self.transforms = list(transforms)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample`` passed through each transform in order, all drawing from ``rng``."""
        for t in self.transforms:
            sample = t(sample, rng)
        return sample

    def __repr__(self) -> str:
        return f"Compose({self.transforms!r})"


def crop_sample(sample: dict, top_px: int, left_px: int, height_px: int, width_px: int) -> dict:
    """The window ``[top, top + height) x [left, left + width)`` of the image fields; ``K`` shifted."""
    H, W = _image_size(sample)
    if top_px < 0 or left_px < 0 or top_px + height_px > H or left_px + width_px > W:
        raise UserError(f"crop {width_px}x{height_px} at ({left_px}, {top_px}) does not fit a {W}x{H} image")
    out = dict(sample)
    for name in SPATIAL_FIELDS:
        if name in out:
            out[name] = np.ascontiguousarray(out[name][top_px : top_px + height_px, left_px : left_px + width_px])
    if "K" in out:
        K = np.array(out["K"], dtype=np.float64)
        K[0, 2] -= left_px
        K[1, 2] -= top_px
        out["K"] = K
    return out


class Crop:
    """Fixed crop of ``height_px x width_px`` at ``(top_px, left_px)``."""

    def __init__(self, top_px: int, left_px: int, height_px: int, width_px: int):
        if top_px < 0 or left_px < 0:
            raise UserError(f"crop offset must be >= 0, got ({top_px}, {left_px})")
        self.top_px, self.left_px = int(top_px), int(left_px)
        self.height_px, self.width_px = _positive_int("crop height", height_px), _positive_int("crop width", width_px)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """The fixed window of ``sample``'s image fields, ``K`` shifted."""
        return crop_sample(sample, self.top_px, self.left_px, self.height_px, self.width_px)

    def __repr__(self) -> str:
        return f"Crop(top_px={self.top_px}, left_px={self.left_px}, height_px={self.height_px}, width_px={self.width_px})"


class CenterCrop:
    """Central ``height_px x width_px`` window (offsets rounded down)."""

    def __init__(self, height_px: int, width_px: int):
        self.height_px, self.width_px = _positive_int("crop height", height_px), _positive_int("crop width", width_px)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """The central window of ``sample``'s image fields, ``K`` shifted."""
        H, W = _image_size(sample)
        return crop_sample(sample, (H - self.height_px) // 2, (W - self.width_px) // 2, self.height_px, self.width_px)

    def __repr__(self) -> str:
        return f"CenterCrop(height_px={self.height_px}, width_px={self.width_px})"


class RandomCrop:
    """``height_px x width_px`` window at a uniformly drawn offset (one draw per sample)."""

    def __init__(self, height_px: int, width_px: int):
        self.height_px, self.width_px = _positive_int("crop height", height_px), _positive_int("crop width", width_px)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """A window at an offset drawn from ``rng``, ``K`` shifted; a window larger than the image is the user's
        mistake."""
        H, W = _image_size(sample)
        if self.height_px > H or self.width_px > W:
            raise UserError(f"random crop {self.width_px}x{self.height_px} does not fit a {W}x{H} image")
        top = int(rng.integers(0, H - self.height_px + 1))
        left = int(rng.integers(0, W - self.width_px + 1))
        return crop_sample(sample, top, left, self.height_px, self.width_px)

    def __repr__(self) -> str:
        return f"RandomCrop(height_px={self.height_px}, width_px={self.width_px})"


def resize_indices(src: int, dst: int) -> np.ndarray:
    """Nearest source pixel of each destination pixel: ``floor((u' + 1/2) src / dst)``
    (the source pixel containing the destination pixel's centre)."""
    return np.minimum(((np.arange(dst) + 0.5) * (src / dst)).astype(np.int64), src - 1)


class Resize:
    """Nearest-neighbour resize to ``height_px x width_px``.

    Nearest neighbour never invents depths between a foreground and a background surface
    (interpolating would create flying pixels) and keeps mask labels valid.
    """

    def __init__(self, height_px: int, width_px: int):
        self.height_px, self.width_px = _positive_int("resize height", height_px), _positive_int("resize width", width_px)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample``'s image fields resized (nearest neighbour) to ``height_px x width_px``, ``K`` scaled to match."""
        H, W = _image_size(sample)
        rows, cols = resize_indices(H, self.height_px), resize_indices(W, self.width_px)
        out = dict(sample)
        for name in SPATIAL_FIELDS:
            if name in out:
                out[name] = np.ascontiguousarray(out[name][rows[:, None], cols[None, :]])
        if "K" in out:
            sx, sy = self.width_px / W, self.height_px / H
            K = np.array(out["K"], dtype=np.float64)
            K[0, 0] *= sx
            K[0, 1] *= sx
            K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
            K[1, 1] *= sy
            K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
            out["K"] = K
        return out

    def __repr__(self) -> str:
        return f"Resize(height_px={self.height_px}, width_px={self.width_px})"


class ClipDepth:
    """Sensor range: depths outside ``[min_m, max_m]`` become 0 (no return), or, with
    ``clamp=True``, are clamped to the range (0 stays 0 either way)."""

    def __init__(self, min_m: float = 0.0, max_m: float = math.inf, clamp: bool = False):
        if not (0.0 <= min_m < max_m):
            raise UserError(f"depth range must satisfy 0 <= min < max, got [{min_m}, {max_m}] m")
        self.min_m, self.max_m, self.clamp = float(min_m), float(max_m), bool(clamp)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample`` with depths (m) outside ``[min_m, max_m]`` set to 0, or clamped to it; float32."""
        d = np.asarray(sample["depth"])
        valid = d > 0
        if self.clamp:
            new = np.where(valid, np.clip(d, self.min_m, self.max_m), 0.0)
        else:
            new = np.where(valid & (d >= self.min_m) & (d <= self.max_m), d, 0.0)
        return {**sample, "depth": new.astype(np.float32)}

    def __repr__(self) -> str:
        return f"ClipDepth(min_m={self.min_m}, max_m={self.max_m}, clamp={self.clamp})"


class PixelDropout:
    """Each depth pixel independently becomes 0 (no return) with ``probability``; the mask is
    kept (it is the ground truth of what the pixel shows)."""

    def __init__(self, probability: float):
        if not 0.0 <= probability <= 1.0:
            raise UserError(f"dropout probability must be in [0, 1], got {probability}")
        self.probability = float(probability)

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample`` with each depth pixel set to 0 with ``probability`` (drawn from ``rng``); float32."""
        d = np.asarray(sample["depth"])
        drop = rng.random(d.shape) < self.probability
        return {**sample, "depth": np.where(drop, np.float32(0.0), d).astype(np.float32)}

    def __repr__(self) -> str:
        return f"PixelDropout(probability={self.probability})"


class SensorNoise:
    """A depth-sensor noise model of :mod:`articulated_dataset.core.noise` (``get_noise_model(name)``,
    looked up on first use) applied to ``depth`` with the sample's ``K``."""

    def __init__(self, model: str = "kinect2"):
        self.model = str(model)
        self._fn = None

    def _get(self):
        if self._fn is None:
            from articulated_dataset.core.noise import get_noise_model

            self._fn = get_noise_model(self.model)
        return self._fn

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample`` with the noise model applied to its depth (float32, m) using its ``K``; a sample without ``K``
        is the user's mistake."""
        if "K" not in sample:
            raise UserError("the sensor-noise transform needs the intrinsics 'K' in the sample (keep 'K' in fields)")
        depth = self._get()(np.asarray(sample["depth"], dtype=np.float32), np.asarray(sample["K"]), rng)
        return {**sample, "depth": np.asarray(depth, dtype=np.float32)}

    def __getstate__(self):
        return {"model": self.model, "_fn": None}

    def __repr__(self) -> str:
        return f"SensorNoise({self.model!r})"


__all__ = ["Compose", "Crop", "CenterCrop", "RandomCrop", "Resize", "ClipDepth", "PixelDropout", "SensorNoise",
           "sample_rng", "apply_to_batch", "crop_sample", "resize_indices", "TRANSFORM_STREAM"]
