"""The target-vector layout shared by the loaders and the reference MDN.

A sample's kinematic labels become one flat float32 vector of ``D = 13 J + 4`` columns.
For each joint ``j`` (registry order), 13 columns::

    j{j}.origin.{x,y,z}   axis_origin, m (camera frame)
    j{j}.axis.{x,y,z}     z column of the axis frame = axis_direction (unit)
    j{j}.xaxis.{x,y,z}    x column of the axis frame (unit, perpendicular to the axis)
    j{j}.q                configuration, rad (revolute) or m (prismatic)
    j{j}.offset.{x,y,z}   part_offset, m (axis frame)

then ``geometry.{depth,width,height}`` (m) and ``geometry.chirality`` (0/1).

The two columns ``axis`` and ``xaxis`` of the rotation matrix are the continuous 6-D
representation of the axis frame's orientation (Zhou et al., CVPR 2019): unlike a quaternion
or Euler angles it has no wrap-around and no sign ambiguity.  :meth:`TargetLayout.decode`
maps any 6-D vector back to a rotation by Gram-Schmidt::

    z = a / |a|,   x = (b - (b.z) z) / |b - (b.z) z|,   y = z x x,   R = [x y z]

and returns its quaternion (w, x, y, z) with w >= 0, the label convention.

:class:`NormStats` holds per-column mean and standard deviation (floored, so constant columns
such as the chirality of a one-sided class never divide by zero), computed from the training
split and stored in checkpoints through :meth:`NormStats.to_dict`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.core.rotations import matrix_to_quat, quat_to_matrix
from articulated_dataset.core.units import normalise

log = logging.getLogger(__name__)

#: Per-joint column groups and their widths, in layout order.
JOINT_GROUPS: tuple[tuple[str, int], ...] = (("origin", 3), ("axis", 3), ("xaxis", 3), ("q", 1), ("offset", 3))
JOINT_WIDTH = sum(w for _, w in JOINT_GROUPS)  # 13 columns per joint
GEOMETRY_NAMES = ("depth", "width", "height", "chirality")
GEOMETRY_GROUP = "geometry"
_XYZ = ("x", "y", "z")
#: Label fields that :meth:`TargetLayout.encode` reads.
TARGET_LABEL_FIELDS = ("axis_pose", "q", "part_offset", "geometry")
#: Smallest standard deviation used for normalisation, in the column's own unit (1 mm, 1 mrad
#: or 0.001 for unit vectors / chirality): below sensor and label precision, so a constant
#: column normalises to 0 and float noise in a near-constant column is not amplified.
DEFAULT_STD_FLOOR = 1e-3
#: Vectors shorter than this are treated as degenerate by Gram-Schmidt.
_EPS = 1e-9


# --------------------------------------------------------------------------------------
# Rotations (pure, vectorised over leading axes)
# --------------------------------------------------------------------------------------

def gram_schmidt(axis: np.ndarray, xaxis: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) ``[x y z]`` from the 6-D representation (axis, xaxis).

    ``z = axis / |axis|``; ``x = normalise(xaxis - (xaxis . z) z)``; ``y = z x x``.  A zero axis
    becomes +z and an xaxis parallel to the axis is replaced by the coordinate axis least
    aligned with z, so every input gives a proper rotation.
    """
    a = np.asarray(axis, dtype=np.float64)
    b = np.asarray(xaxis, dtype=np.float64)
    z, nz = normalise(a, min_norm=_EPS), np.linalg.norm(a, axis=-1)
    z = np.where((nz < _EPS)[..., None], np.array([0.0, 0.0, 1.0]), z)
    x_raw = b - np.sum(b * z, axis=-1, keepdims=True) * z
    x, nx = normalise(x_raw, min_norm=_EPS), np.linalg.norm(x_raw, axis=-1)
    degenerate = nx < _EPS
    if np.any(degenerate):
        fallback = np.eye(3)[np.argmin(np.abs(z), axis=-1)]
        fb = fallback - np.sum(fallback * z, axis=-1, keepdims=True) * z
        x = np.where(degenerate[..., None], normalise(fb), x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


# --------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------

class TargetLayout:
    """Column layout of the target vector of one object class (see the module docstring).

    Attributes: ``class_name``, ``n_joints`` (J), ``names`` (list of D column names), ``dim``
    (D = 13 J + 4), ``slices`` (group name such as ``'j0.origin'`` or ``'geometry'`` -> slice
    of columns) and ``fields`` (the label fields :meth:`encode` reads).
    """

    fields = TARGET_LABEL_FIELDS

    def __init__(self, class_name: str, n_joints: int):
        if n_joints < 0:
            raise ValueError(f"n_joints must be >= 0, got {n_joints}")
        self.class_name = class_name
        self.n_joints = int(n_joints)
        names: list[str] = []
        slices: dict[str, slice] = {}
        for j in range(self.n_joints):
            for group, width in JOINT_GROUPS:
                key = f"j{j}.{group}"
                slices[key] = slice(len(names), len(names) + width)
                names += [key] if width == 1 else [f"{key}.{c}" for c in _XYZ[:width]]
        slices[GEOMETRY_GROUP] = slice(len(names), len(names) + len(GEOMETRY_NAMES))
        names += [f"{GEOMETRY_GROUP}.{g}" for g in GEOMETRY_NAMES]
        self.names = names
        self.slices = slices
        self.dim = len(names)

    @classmethod
    def for_class(cls, class_name: str) -> "TargetLayout":
        """The layout of a registered class (J from the registry; unknown names: UserError)."""
        from articulated_dataset.classes.registry import get_class

        return cls(class_name, get_class(class_name).n_joints)

    def __repr__(self) -> str:
        return f"TargetLayout({self.class_name!r}, n_joints={self.n_joints}, dim={self.dim})"

    def __eq__(self, other) -> bool:
        return isinstance(other, TargetLayout) and (self.class_name, self.n_joints) == (other.class_name, other.n_joints)

    def __hash__(self) -> int:
        return hash((self.class_name, self.n_joints))

    def to_dict(self) -> dict:
        """The layout as a dict (class name, J, column names; stored in checkpoints)."""
        return {"class_name": self.class_name, "n_joints": self.n_joints, "names": list(self.names)}

    @classmethod
    def from_dict(cls, d: dict) -> "TargetLayout":
        """The layout of the stored class and joint count; stored column names other than this package's layout raise
        :class:`DataFormatError`."""
        layout = cls(str(d["class_name"]), int(d["n_joints"]))
        if "names" in d and list(d["names"]) != layout.names:
            raise DataFormatError(f"stored target layout of {layout.class_name!r} does not match this package's layout")
        return layout

    # ----------------------------------------------------------------------------------
    def _label(self, labels: dict, name: str, tail: tuple, batched: bool) -> np.ndarray:
        if name not in labels:
            raise UserError(f"target encoding needs the label {name!r} (got: {', '.join(sorted(labels)) or 'nothing'})")
        a = np.asarray(labels[name], dtype=np.float64)
        want = (a.shape[0],) + tail if batched else tail
        if a.shape != want:
            raise UserError(f"label {name!r} has shape {a.shape}, expected {want} for class {self.class_name!r} (J = {self.n_joints})")
        return a

    def encode(self, labels: dict) -> np.ndarray:
        """Target vectors ``(B, D)`` float32 from batched labels.

        ``labels`` holds ``axis_pose`` (B, J, 7), ``q`` (B, J), ``part_offset`` (B, J, 3) and
        ``geometry`` (B, 4) (other keys are ignored).  Unbatched labels (``q`` of shape (J,))
        give one vector (D,).
        """
        if "q" not in labels:
            raise UserError("target encoding needs the label 'q'")
        batched = np.ndim(labels["q"]) == 2
        J = self.n_joints
        pose = self._label(labels, "axis_pose", (J, 7), batched)
        q = self._label(labels, "q", (J,), batched)
        offset = self._label(labels, "part_offset", (J, 3), batched)
        geometry = self._label(labels, "geometry", (len(GEOMETRY_NAMES),), batched)
        if not batched:
            pose, q, offset, geometry = pose[None], q[None], offset[None], geometry[None]
        R = quat_to_matrix(pose[..., 3:])
        per_joint = np.concatenate([pose[..., :3], R[..., :, 2], R[..., :, 0], q[..., None], offset], axis=-1)
        vec = np.concatenate([per_joint.reshape(len(q), J * JOINT_WIDTH), geometry], axis=-1).astype(np.float32)
        return vec if batched else vec[0]

    def decode(self, vec: np.ndarray) -> dict:
        """Labels from target vectors ``(B, D)`` (or one vector ``(D,)``).

        Returns float32 arrays: ``axis_pose`` (B, J, 7) (orientation by Gram-Schmidt, quaternion
        w >= 0), ``axis_origin`` (B, J, 3), ``axis_direction`` (B, J, 3) (unit), ``axis_rotation``
        (B, J, 3, 3), ``q`` (B, J), ``part_offset`` (B, J, 3), ``geometry`` (B, 4) (chirality
        left as the raw column value; threshold it at 0.5 for a class label).
        """
        v = np.asarray(vec, dtype=np.float64)
        batched = v.ndim == 2
        if v.ndim not in (1, 2) or v.shape[-1] != self.dim:
            raise UserError(f"target vectors for {self.class_name!r} must have shape (B, {self.dim}), got {v.shape}")
        if not batched:
            v = v[None]
        B, J = len(v), self.n_joints
        per_joint = v[:, : J * JOINT_WIDTH].reshape(B, J, JOINT_WIDTH)
        cols = {}
        start = 0
        for group, width in JOINT_GROUPS:
            cols[group] = per_joint[..., start : start + width]
            start += width
        R = gram_schmidt(cols["axis"], cols["xaxis"])
        origin = cols["origin"]
        out = {
            "axis_pose": np.concatenate([origin, matrix_to_quat(R)], axis=-1),
            "axis_origin": origin,
            "axis_direction": R[..., :, 2],
            "axis_rotation": R,
            "q": cols["q"][..., 0],
            "part_offset": cols["offset"],
            "geometry": v[:, self.slices[GEOMETRY_GROUP]],
        }
        out = {k: np.ascontiguousarray(a, dtype=np.float32) for k, a in out.items()}
        return out if batched else {k: a[0] for k, a in out.items()}


# --------------------------------------------------------------------------------------
# Normalisation statistics
# --------------------------------------------------------------------------------------

@dataclass
class NormStats:
    """Per-column normalisation ``y_n = (y - mean) / std`` of target vectors.

    ``std`` is already floored: ``std = max(std_raw, std_floor)``.  ``names`` (the layout's
    column names) lets a checkpoint detect a layout mismatch.
    """

    mean: np.ndarray
    std: np.ndarray
    names: list[str] | None = None
    n_samples: int = 0
    std_floor: float = DEFAULT_STD_FLOOR
    class_name: str | None = None
    sources: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, dtype=np.float64).reshape(-1)
        self.std = np.asarray(self.std, dtype=np.float64).reshape(-1)
        if self.mean.shape != self.std.shape:
            raise DataFormatError(f"normalisation statistics: mean has {self.mean.size} columns, std {self.std.size}")
        if self.names is not None and len(self.names) != self.mean.size:
            raise DataFormatError(f"normalisation statistics: {len(self.names)} names for {self.mean.size} columns")
        if not (np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.std)) and np.all(self.std > 0)):
            raise DataFormatError("normalisation statistics must be finite with std > 0")

    @property
    def dim(self) -> int:
        """Number of target columns D."""
        return int(self.mean.size)

    @classmethod
    def from_targets(cls, targets: np.ndarray, layout: TargetLayout | None = None, *,
                     std_floor: float = DEFAULT_STD_FLOOR) -> "NormStats":
        """Statistics of already encoded target vectors ``(N, D)``: column mean and population
        standard deviation ``sqrt(mean((y - mean)^2))``, floored at ``std_floor``."""
        y = np.asarray(targets, dtype=np.float64)
        if y.ndim != 2 or len(y) == 0:
            raise UserError(f"normalisation statistics need a non-empty (N, D) array, got shape {y.shape}")
        if layout is not None and y.shape[1] != layout.dim:
            raise UserError(f"targets have {y.shape[1]} columns, the {layout.class_name!r} layout has {layout.dim}")
        if not math.isfinite(std_floor) or std_floor <= 0:
            raise UserError(f"std_floor must be positive, got {std_floor}")
        if not np.all(np.isfinite(y)):
            raise DataFormatError("target vectors contain NaN or infinite values")
        mean = y.mean(axis=0)
        std = np.maximum(y.std(axis=0), std_floor)
        return cls(mean=mean, std=std, names=list(layout.names) if layout is not None else None,
                   n_samples=len(y), std_floor=float(std_floor),
                   class_name=layout.class_name if layout is not None else None)

    @classmethod
    def from_split(cls, split_dirs, layout: TargetLayout, max_samples: int | None = None, *,
                   std_floor: float = DEFAULT_STD_FLOOR) -> "NormStats":
        """Statistics of the targets of every image in ``split_dirs`` (normally the TRAINING split).

        ``split_dirs``: one path or several (split folders, or folders holding them).  With
        ``max_samples``, an evenly spaced subset of that many images is used (deterministic).
        Only label datasets are read (no depth decoding).
        """
        from articulated_dataset.training.loaders.reader import ShardReader

        reader = ShardReader(split_dirs, fields=TARGET_LABEL_FIELDS)
        others = [c for c in reader.class_names if c != layout.class_name]
        if others:
            raise UserError(f"normalisation statistics for {layout.class_name!r} were given data of class(es) {', '.join(others)}")
        splits = sorted({d.name for d in reader.split_dirs})
        if splits != ["train"]:
            log.warning("normalisation statistics computed from split(s) %s; use the training split", ", ".join(splits))
        n = len(reader)
        if n == 0:
            raise UserError(f"no images in {', '.join(str(d) for d in reader.split_dirs)}")
        if max_samples is not None and max_samples <= 0:
            raise UserError(f"max_samples must be positive, got {max_samples}")
        if max_samples is None or max_samples >= n:
            idx = np.arange(n)
        else:
            idx = np.unique(np.linspace(0, n - 1, int(max_samples)).round().astype(np.int64))
        stats = cls.from_targets(layout.encode(reader.get_batch(idx)), layout, std_floor=std_floor)
        stats.sources = [str(d) for d in reader.split_dirs]
        return stats

    def _check(self, vec) -> np.ndarray:
        v = np.asarray(vec)
        if v.shape[-1:] != (self.dim,):
            raise UserError(f"vectors of shape {v.shape} do not match normalisation statistics of {self.dim} columns")
        return v

    def normalize(self, vec: np.ndarray) -> np.ndarray:
        """``(vec - mean) / std`` (float32; any leading shape)."""
        v = self._check(vec)
        return ((v - self.mean) / self.std).astype(np.float32)

    def denormalize(self, vec: np.ndarray) -> np.ndarray:
        """``vec * std + mean`` (float32; any leading shape)."""
        v = self._check(vec)
        return (v * self.std + self.mean).astype(np.float32)

    def to_dict(self) -> dict:
        """JSON-safe dictionary (plain lists and numbers) for checkpoints."""
        return {
            "mean": [float(x) for x in self.mean], "std": [float(x) for x in self.std],
            "names": list(self.names) if self.names is not None else None,
            "n_samples": int(self.n_samples), "std_floor": float(self.std_floor),
            "class_name": self.class_name, "sources": list(self.sources),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "NormStats":
        """Statistics from their stored dict; a missing ``mean`` or ``std`` raises :class:`DataFormatError`."""
        try:
            return cls(mean=d["mean"], std=d["std"], names=d.get("names"), n_samples=int(d.get("n_samples", 0)),
                       std_floor=float(d.get("std_floor", DEFAULT_STD_FLOOR)), class_name=d.get("class_name"),
                       sources=list(d.get("sources") or []))
        except KeyError as exc:
            raise DataFormatError(f"normalisation statistics lack {exc.args[0]!r}") from None

    def check_layout(self, layout: TargetLayout) -> None:
        """Raise :class:`DataFormatError` if these statistics were made for another layout."""
        if self.dim != layout.dim or (self.names is not None and list(self.names) != layout.names):
            raise DataFormatError(f"normalisation statistics ({self.dim} columns) do not match the {layout.class_name!r} target layout ({layout.dim} columns)")


__all__ = ["TargetLayout", "NormStats", "quat_to_matrix", "matrix_to_quat", "gram_schmidt",
           "TARGET_LABEL_FIELDS", "DEFAULT_STD_FLOOR", "JOINT_GROUPS", "GEOMETRY_NAMES"]

