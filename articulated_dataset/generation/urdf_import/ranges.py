"""What an import derives from numbers alone: pose ranges that keep the object in view
(:func:`view_pose_ranges`), the joint re-parametrisation (:func:`reparametrize_range`), class
names and the processed-URDF cache folder (:func:`cache_root`)."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from articulated_dataset.classes.base import PRISMATIC, REVOLUTE
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format import MAX_CLASS_NAME_CHARS, is_class_name

#: Environment variable overriding the cache folder of processed URDF models.
CACHE_ENV = "ARTDATA_CACHE_DIR"
#: URDF joint types that can be articulated, and the dataset joint type each becomes.
MOVABLE_TYPES = {"revolute": REVOLUTE, "continuous": REVOLUTE, "prismatic": PRISMATIC}
#: Nearest-distance margin of the default pose table: at the nearest distance the object's
#: bounding sphere fills 1 / VIEW_MARGIN (80%) of the narrower field of view.
VIEW_MARGIN = 1.25
#: Farthest distance of the default pose table relative to the nearest one.
FAR_DISTANCE_RATIO = 1.5


def view_pose_ranges(box_lo, box_hi, camera: CameraConfig, yaw_rad: tuple[float, float]) -> dict:
    """Default pose ranges that keep an object's bounding box inside the image.

    ``box_lo``, ``box_hi``: corners (m) of the object's axis-aligned bounding box in its
    root-link frame (z up).  The yaw rotates the object about the root frame's z axis, so
    the rule uses the sphere centred on that axis at the box's mid-height ``c_z`` that
    holds the box: radius ``r = max |corner - (0, 0, c_z)|``.  With ``alpha`` the smaller
    half field of view (vertical or horizontal) and ``m`` = :data:`VIEW_MARGIN`:

    * ``x_m`` in ``[d, FAR_DISTANCE_RATIO d]`` with ``d = m r / sin(alpha)``: at distance
      ``d`` the sphere is ``m`` times smaller than the view cone;
    * ``y_m`` in ``[-s, s]`` and ``z_m`` in ``[-s - c_z, s - c_z]`` with
      ``s = d tan(alpha) - r / cos(alpha) = (m - 1) r / cos(alpha)``: the largest offset of
      the sphere's centre that keeps it inside the frustum's side planes at distance ``d``
      (a point at distance x and offset s is ``x sin(alpha) - s cos(alpha)`` from the plane),
      hence at every sampled distance;
    * ``yaw_rad`` as given.

    Returns ``{"x_m": (lo, hi), "y_m": ..., "z_m": ..., "yaw_rad": ...}`` (metres, radians).
    """
    c_z, r = yaw_sphere(box_lo, box_hi)
    alpha = half_fov(camera)
    d = VIEW_MARGIN * r / math.sin(alpha)
    s = (VIEW_MARGIN - 1.0) * r / math.cos(alpha)
    return {
        "x_m": (d, FAR_DISTANCE_RATIO * d),
        "y_m": (-s, s),
        "z_m": (-s - c_z, s - c_z),
        "yaw_rad": (float(yaw_rad[0]), float(yaw_rad[1])),
    }


def yaw_sphere(box_lo, box_hi) -> tuple[float, float]:
    """``(c_z, r)``: mid-height (m) and radius (m) of the sphere centred on the root z axis
    at the box's mid-height that holds the box (see :func:`view_pose_ranges`)."""
    lo, hi = np.asarray(box_lo, float), np.asarray(box_hi, float)
    c_z = 0.5 * (lo[2] + hi[2])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(c_z), float(np.max(np.linalg.norm(corners - np.array([0.0, 0.0, c_z]), axis=1)))


def half_fov(camera: CameraConfig) -> float:
    """The smaller half field of view (rad), vertical or horizontal."""
    half_v = math.radians(camera.vfov_deg) / 2
    return min(half_v, math.atan(math.tan(half_v) * camera.width_px / camera.height_px))


def reparametrize_range(lower: float, upper: float) -> tuple[tuple[float, float], bool, float]:
    """New range of a joint with URDF limits ``[lower, upper]``: q = 0 is closed, positive q opens.

    The closed pose is the limit nearer the URDF zero (the pose the meshes are modelled in,
    which PartNet-Mobility and most URDFs model closed); on a tie (``-lower == upper``) the
    lower limit.  Returns ``((0, upper - lower), flip, offset)``; URDF coordinate
    ``q_urdf = offset + s q`` with ``s = -1`` if ``flip`` else ``+1``:

    * closed at ``lower`` (``|lower| <= |upper|``): ``flip`` False, ``offset = lower``;
    * closed at ``upper`` (``|upper| < |lower|``): the axis flipped, ``offset = upper``
      (opening runs towards ``lower``, i.e. negative URDF coordinates).
    """
    if abs(upper) < abs(lower):
        return (0.0, upper - lower), True, upper
    return (0.0, upper - lower), False, lower


def joint_motion(urdf_type: str, axis: np.ndarray, q: float) -> np.ndarray:
    """4x4 motion of a joint's child frame at coordinate ``q`` (rad or m) along unit ``axis``."""
    import trimesh

    if MOVABLE_TYPES[urdf_type] == PRISMATIC:
        return trimesh.transformations.translation_matrix(q * axis)
    return trimesh.transformations.rotation_matrix(q, axis)


def sanitize_class_name(text: str) -> str:
    """Characters outside ``[A-Za-z0-9_.-]`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)


def default_class_name(urdf_path: str | Path) -> str:
    """``<folder>-<file stem>`` of the URDF, sanitised (``7128/mobility.urdf`` -> ``7128-mobility``)."""
    p = Path(urdf_path)
    return sanitize_class_name(f"{p.parent.name}-{p.stem}" if p.parent.name else p.stem)


def check_class_name(name: str) -> str:
    """A valid class name (:func:`articulated_dataset.format.is_class_name`); the registry
    refuses a built-in's name when the class is registered (:func:`articulated_dataset.classes.registry.register`)."""
    if not is_class_name(name):
        raise UserError(
            f"invalid class name {str(name)[:80]!r}: use 1-{MAX_CLASS_NAME_CHARS} characters from A-Z a-z 0-9 _ . -, "
            f"not starting with . or - (pass {option('urdf_class_name')})"
        )
    return name


def cache_root() -> Path:
    """Folder of processed models: ``$ARTDATA_CACHE_DIR``, else ``$XDG_CACHE_HOME/articulated_dataset``
    (default ``~/.cache/articulated_dataset``)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "articulated_dataset"
