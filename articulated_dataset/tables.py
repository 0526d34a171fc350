"""Sampling tables: the per-class ranges of geometry, pose and configuration.

Every range is a closed interval ``(low, high)`` in SI units (metres, radians) sampled
uniformly and independently, as in the paper's Appendix A (Tables 3 and 4; the paper
gives geometry in cm and prismatic configuration in cm, converted here).

A table can be overridden from a JSON or TOML file holding any subset of the keys of
:meth:`SamplingTable.to_dict`, e.g. ``{"geometry": {"height_m": [1.5, 1.8]}}``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping

from .errors import UserError

Range = tuple[float, float]

GEOMETRY_KEYS = ("depth_m", "width_m", "height_m")
POSE_KEYS = ("x_m", "y_m", "z_m", "yaw_rad")


def _check_range(name: str, r) -> Range:
    try:
        lo, hi = (float(v) for v in r)
    except (TypeError, ValueError):
        raise UserError(f"sampling table: {name} must be a pair [low, high], got {r!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise UserError(f"sampling table: {name} must satisfy low <= high (finite), got [{lo}, {hi}]")
    return (lo, hi)


@dataclass(frozen=True)
class SamplingTable:
    """Uniform sampling ranges for one object class.

    Attributes
    ----------
    geometry: outer body dimensions ``depth_m``, ``width_m``, ``height_m`` (metres).
    pose: ``x_m``, ``y_m``, ``z_m`` of the centre of the object's base in the camera frame
        (metres) and ``yaw_rad``, the rotation about z (0 = front faces the camera).
    q: one configuration range per joint (radians for revolute, metres for prismatic).
    chirality_p: probability that an object is mirrored (hinge on its right, see docs).
    """

    geometry: Mapping[str, Range]
    pose: Mapping[str, Range]
    q: tuple[Range, ...]
    chirality_p: float = 0.0
    extra: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        geometry = {k: _check_range(f"geometry.{k}", self.geometry.get(k)) for k in GEOMETRY_KEYS}
        unknown = set(self.geometry) - set(GEOMETRY_KEYS)
        if unknown:
            raise UserError(f"sampling table: unknown geometry keys {sorted(unknown)}")
        pose = {k: _check_range(f"pose.{k}", self.pose.get(k)) for k in POSE_KEYS}
        unknown = set(self.pose) - set(POSE_KEYS)
        if unknown:
            raise UserError(f"sampling table: unknown pose keys {sorted(unknown)}")
        if any(v[0] <= 0 for v in geometry.values()):
            raise UserError("sampling table: geometry ranges must be positive")
        q = tuple(_check_range(f"q[{j}]", r) for j, r in enumerate(self.q))
        if any(lo < 0 for lo, _ in q):
            raise UserError("sampling table: configuration ranges must start at >= 0 (q = 0 is closed)")
        if not 0.0 <= float(self.chirality_p) <= 1.0:
            raise UserError(f"sampling table: chirality_p must be in [0, 1], got {self.chirality_p}")
        object.__setattr__(self, "geometry", geometry)
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "chirality_p", float(self.chirality_p))
        object.__setattr__(self, "extra", {k: float(v) for k, v in dict(self.extra).items()})

    def to_dict(self) -> dict:
        return {
            "geometry": {k: list(v) for k, v in self.geometry.items()},
            "pose": {k: list(v) for k, v in self.pose.items()},
            "q": [list(r) for r in self.q],
            "chirality_p": self.chirality_p,
            "extra": dict(self.extra),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping) -> "SamplingTable":
        return cls(
            geometry=d["geometry"], pose=d["pose"], q=tuple(d["q"]),
            chirality_p=d.get("chirality_p", 0.0), extra=d.get("extra", {}),
        )

    def override(self, changes: Mapping) -> "SamplingTable":
        """Return a copy with the keys in ``changes`` (same layout as :meth:`to_dict`) replaced."""
        unknown = set(changes) - {"geometry", "pose", "q", "chirality_p", "extra"}
        if unknown:
            raise UserError(f"sampling table: unknown keys {sorted(unknown)}")
        kwargs = {}
        for key in ("geometry", "pose", "extra"):
            if key in changes:
                kwargs[key] = {**getattr(self, key), **dict(changes[key])}
        if "q" in changes:
            if len(changes["q"]) != len(self.q):
                raise UserError(f"sampling table: q needs {len(self.q)} ranges (one per joint), got {len(changes['q'])}")
            kwargs["q"] = tuple(changes["q"])
        if "chirality_p" in changes:
            kwargs["chirality_p"] = changes["chirality_p"]
        return replace(self, **kwargs)


def load_table_file(path: str | Path) -> dict:
    """Read a (partial) table override from a ``.json`` or ``.toml`` file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"sampling table file not found: {path}")
    text = path.read_text()
    try:
        if path.suffix.lower() == ".toml":
            import tomllib

            return tomllib.loads(text)
        return json.loads(text)
    except Exception as exc:  # parse errors of either format are the user's
        raise UserError(f"cannot parse sampling table {path}: {exc}") from None
