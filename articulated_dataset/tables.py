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
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from .errors import UserError

Range = tuple[float, float]

GEOMETRY_KEYS = ("depth_m", "width_m", "height_m")
POSE_KEYS = ("x_m", "y_m", "z_m", "yaw_rad")
TABLE_KEYS = ("geometry", "pose", "q", "chirality_p", "extra")

#: Sanity bounds of a table (not physics: they keep absurd values from reaching MuJoCo and
#: the renderer).  Object sides in metres: 1 mm (the smallest a third-party object is given,
#: see urdf_import.MIN_GEOMETRY_M) to 100 m.
MIN_SIZE_M = 1e-3
MAX_SIZE_M = 100.0
#: Largest |x|, |y|, |z| of an object's base in the camera frame (m) and |yaw| (rad).
MAX_POSITION_M = 1000.0
MAX_YAW_RAD = 2.0 * math.pi
#: Largest configuration (rad for revolute, m for prismatic joints; the pipeline checks
#: revolute ranges against one turn).
MAX_Q = 100.0
#: Largest table file read (bytes); tables are a few hundred bytes.
MAX_TABLE_FILE_BYTES = 1 << 20


def _number(name: str, v) -> float:
    """``v`` as a finite float; strings, booleans, lists... are the user's mistake."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise UserError(f"sampling table: {name} must be a number, got {_show(v)}")
    f = float(v)
    if not math.isfinite(f):
        raise UserError(f"sampling table: {name} must be finite, got {f}")
    return f


def _show(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_range(name: str, r, lo_min: float = -math.inf, hi_max: float = math.inf, unit: str = "") -> Range:
    if isinstance(r, (str, bytes, Mapping)) or not isinstance(r, Sequence) or len(r) != 2:
        raise UserError(f"sampling table: {name} must be a pair [low, high], got {_show(r)}")
    lo, hi = (_number(name, v) for v in r)
    if lo > hi:
        raise UserError(f"sampling table: {name} must satisfy low <= high, got [{lo}, {hi}]")
    if lo < lo_min or hi > hi_max:
        raise UserError(f"sampling table: {name} must lie in [{lo_min}, {hi_max}]{unit}, got [{lo}, {hi}]")
    return (lo, hi)


def _mapping(name: str, v) -> Mapping:
    if not isinstance(v, Mapping) or not all(isinstance(k, str) for k in v):
        raise UserError(f"sampling table: {name} must be a table of named ranges, got {_show(v)}")
    return v


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
        geometry, pose = _mapping("geometry", self.geometry), _mapping("pose", self.pose)
        for part, given, keys in (("geometry", geometry, GEOMETRY_KEYS), ("pose", pose, POSE_KEYS)):
            unknown = sorted(set(given) - set(keys))
            if unknown:
                raise UserError(f"sampling table: unknown {part} key {part}.{unknown[0]} (known: {', '.join(keys)})")
            missing = [k for k in keys if k not in given]
            if missing:
                raise UserError(f"sampling table: {part}.{missing[0]} is missing")
        geometry = {k: _check_range(f"geometry.{k}", geometry[k], MIN_SIZE_M, MAX_SIZE_M, " m") for k in GEOMETRY_KEYS}
        pose = {k: (_check_range(f"pose.{k}", pose[k], -MAX_YAW_RAD, MAX_YAW_RAD, " rad") if k == "yaw_rad" else
                    _check_range(f"pose.{k}", pose[k], -MAX_POSITION_M, MAX_POSITION_M, " m")) for k in POSE_KEYS}
        if isinstance(self.q, (str, bytes, Mapping)) or not isinstance(self.q, Sequence):
            raise UserError(f"sampling table: q must be a list of [low, high] pairs (one per joint), got {_show(self.q)}")
        # q = 0 is closed: configurations start at >= 0.
        q = tuple(_check_range(f"q[{j}]", r, 0.0, MAX_Q) for j, r in enumerate(self.q))
        chirality_p = _number("chirality_p", self.chirality_p)
        if not 0.0 <= chirality_p <= 1.0:
            raise UserError(f"sampling table: chirality_p must be in [0, 1], got {chirality_p}")
        extra = {k: _number(f"extra.{k}", v) for k, v in _mapping("extra", self.extra).items()}
        object.__setattr__(self, "geometry", geometry)
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "chirality_p", chirality_p)
        object.__setattr__(self, "extra", extra)

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
        """The table stored by :meth:`to_dict` (e.g. in a manifest); a malformed one is a
        :class:`UserError` naming the key."""
        d = _mapping("(top level)", d)
        for key in ("geometry", "pose", "q"):
            if key not in d:
                raise UserError(f"sampling table: {key} is missing")
        q = d["q"]
        return cls(
            geometry=d["geometry"], pose=d["pose"], q=tuple(q) if isinstance(q, list) else q,
            chirality_p=d.get("chirality_p", 0.0), extra=d.get("extra", {}),
        )

    def override(self, changes: Mapping) -> "SamplingTable":
        """Return a copy with the keys in ``changes`` (same layout as :meth:`to_dict`) replaced.

        Every key must be one the table has (``extra`` keys included: the class defines
        them); wrong types and out-of-range values are a :class:`UserError` naming the key.
        """
        changes = _mapping("(top level)", changes)
        unknown = sorted(set(changes) - set(TABLE_KEYS))
        if unknown:
            raise UserError(f"sampling table: unknown key {unknown[0]!r} (known: {', '.join(TABLE_KEYS)})")
        kwargs = {}
        for key in ("geometry", "pose", "extra"):
            if key in changes:
                given = _mapping(key, changes[key])
                if key == "extra":
                    unknown = sorted(set(given) - set(self.extra))
                    if unknown:
                        known = ", ".join(self.extra) or "none for this class"
                        raise UserError(f"sampling table: unknown extra key extra.{unknown[0]} (known: {known})")
                kwargs[key] = {**getattr(self, key), **dict(given)}
        if "q" in changes:
            q = changes["q"]
            if isinstance(q, (str, bytes, Mapping)) or not isinstance(q, Sequence):
                raise UserError(f"sampling table: q must be a list of [low, high] pairs (one per joint), got {_show(q)}")
            if len(q) != len(self.q):
                raise UserError(f"sampling table: q needs {len(self.q)} ranges (one per joint), got {len(q)}")
            kwargs["q"] = tuple(q)
        if "chirality_p" in changes:
            kwargs["chirality_p"] = changes["chirality_p"]
        return replace(self, **kwargs)


def load_table_file(path: str | Path) -> dict:
    """Read a (partial) table override from a ``.json`` or ``.toml`` file (UTF-8 text holding
    one table/object); any problem is a one-line :class:`UserError`."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"sampling table file not found: {path}")
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_TABLE_FILE_BYTES + 1)
    except OSError as exc:
        raise UserError(f"cannot read sampling table {path}: {exc.strerror or exc}") from None
    if len(raw) > MAX_TABLE_FILE_BYTES:
        raise UserError(f"sampling table {path} is larger than {MAX_TABLE_FILE_BYTES} bytes; not a table")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"sampling table {path} is not UTF-8 text (byte {exc.start})") from None
    try:
        if path.suffix.lower() == ".toml":
            import tomllib

            data = tomllib.loads(text)
        else:
            data = json.loads(text, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:  # parse errors of either format are the user's
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot parse sampling table {path}: {first}") from None
    if not isinstance(data, dict):
        raise UserError(f"sampling table {path} must hold one table (a JSON object), got {type(data).__name__}")
    return data


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number a table may hold")
