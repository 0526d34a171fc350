"""Checks of the depth a method reads, shared by training, prediction and :func:`articulated_dataset.estimate`."""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.errors import UserError

#: Without a mask, an image with returns on more than this fraction of its pixels is a scene
#: (walls, floor), not an isolated object: a mask (or a prompt) is needed.
MAX_UNMASKED_VALID_FRACTION = 0.9


def valid_depth_images(depth_m: np.ndarray) -> np.ndarray:
    """(N,) bool: which images of ``depth_m`` (N, H, W) have a valid depth pixel (finite and > 0),
    the least :func:`articulated_dataset.methods.estimation.check_depth` asks of one image."""
    d = np.asarray(depth_m)
    with np.errstate(invalid="ignore"):
        return (np.isfinite(d) & (d > 0)).reshape(len(d), -1).any(axis=1)


def check_split_has_depth(split_dir, n_valid: int, n_images: int) -> None:
    """One line where none of a split's ``n_images`` selected images has a valid depth pixel (every
    one empty, zero or NaN): a model would train on, or predict from, nothing."""
    if n_images and not n_valid:
        raise UserError(f"{split_dir}: none of its {n_images} images has a valid depth pixel (every depth is "
                        f"empty, zero or NaN); there is nothing to train on or predict from")


def split_context(split_dir) -> tuple[str, int]:
    """The scene (``none``, ``kitchen``, ``room``) and the occluders per image a split was
    generated with, read from its manifest's record of how it was made (``none`` and 0 where the
    record lacks them)."""
    from articulated_dataset.format import read_manifest

    config = read_manifest(split_dir).get("config", {})
    config = config if isinstance(config, dict) else {}  # a record of how the split was made: only read here
    occluders = config.get("occluders", 0)
    return str(config.get("scene", "none")), int(occluders) if isinstance(occluders, int) else 0


def split_has_context(split_dir) -> bool:
    """Whether a split's images show a scene or occluders beside the object (:func:`split_context`)."""
    scene, occluders = split_context(split_dir)
    return scene != "none" or occluders > 0
