"""Sampling tables: the per-class ranges of geometry, pose and configuration.

Every range is a closed interval ``(low, high)`` in SI units (metres, radians) sampled
uniformly and independently, as in the paper's Appendix A (Tables 3 and 4; the paper
gives geometry in cm and prismatic configuration in cm, converted here).

A table may instead give its geometry a joint distribution (``shape``, a
:class:`ShapeMixture` of correlated size classes): the realistic tables of
``artdata generate --table realistic`` (:mod:`articulated_dataset.classes.realistic`);
its ``geometry`` ranges are then the bounds that truncate the mixture.

A table may also hold structure variables (``structure``): how an object of a class is built
beyond its three sizes (door overlay or inset, plinth, countertop, handle kind...), the
tables of ``artdata generate --table varied`` (:mod:`articulated_dataset.classes.varied`).
A variable's kind is read from its name's suffix (:data:`STRUCTURE_KINDS`); each object draws
one value per variable from its own structure stream
(:data:`articulated_dataset.generation.sampling.STRUCTURE_STREAM`).

A table can be overridden from a JSON or TOML file holding any subset of the keys of
:meth:`SamplingTable.to_dict`, e.g. ``{"geometry": {"height_m": [1.5, 1.8]}}``;
:func:`table_from_options` is the table ``artdata generate --table`` names (a table name,
then files overriding it).

Why one module of ~500 lines: it is one data type,
the sampling table, with the two parts of its geometry (independent ranges, the shape
mixture), its structure variables and its file format (read, and chosen by ``--table``), all checked by the same
validators (``_number``, ``_check_range``, ``_mapping``) against the same sanity bounds.  The manifest, the
generators and third-party classes read and write tables as one ``to_dict`` /
``from_dict`` round trip; splitting the mixture into its own module would make those
validators and bounds cross a module border without giving either half a job of its own.
"""

from __future__ import annotations

import json
import math
import numbers
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.errors import option as option_name  # 'option' names a table's structure options

Range = tuple[float, float]

GEOMETRY_KEYS = ("depth_m", "width_m", "height_m")
POSE_KEYS = ("x_m", "y_m", "z_m", "yaw_rad")
TABLE_KEYS = ("geometry", "pose", "q", "chirality_p", "extra", "shape", "structure")
#: Named tables of a built-in class (``artdata generate --table NAME``): the paper's
#: Appendix A (independent uniform ranges), realistic joint distributions of the sizes, and
#: those sizes with varied structure (doors, plinths, handles...; the classes that have one).
TABLE_NAMES = ("paper", "realistic", "varied")
#: Kinds of structure variables, by the suffix of their name: a probability (a 0/1 flag
#: drawn), a range of lengths (m), a range of fractions (of a part's size, in [0, 1]), and
#: weights of named options (one option drawn, with probability proportional to its weight).
STRUCTURE_KINDS = ("_p", "_m", "_frac", "_weights")
#: Names of structure variables and of their options: a lower-case letter, then lower-case
#: letters, digits and underscores (they become Xacro arguments and string values).
_STRUCTURE_NAME = re.compile(r"^[a-z][a-z0-9_]{0,47}$")
_OPTION_NAME = re.compile(r"^[a-z0-9][a-z0-9_]{0,31}$")
#: Most structure variables in one table, and options of one variable.
MAX_STRUCTURE_VARIABLES = 64
MAX_STRUCTURE_OPTIONS = 16

#: Sanity bounds of a table (not physics: they keep absurd values from reaching MuJoCo and
#: the renderer).  Object sides in metres: 1 mm (the smallest a third-party object is given,
#: see urdf_import.build.MIN_GEOMETRY_M) to 100 m.
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
#: Limits of a shape mixture: components, standard values per dimension and per component,
#: jitter standard deviation (m), and draws of the jitter before a sample is clipped into the
#: table's geometry bounds (the realistic tables' components lie >= 3 sigma inside them).
MAX_SHAPE_COMPONENTS = 64
MAX_SHAPE_SIZES = 64
MAX_SHAPE_STD_M = 1.0
MAX_SHAPE_DRAWS = 32
#: Smallest eigenvalue of a component's jitter correlation (positive definite: a Cholesky
#: factor exists, so sampling is one well-defined linear map on every platform).
MIN_CORRELATION_EIGENVALUE = 1e-6
_COMPONENT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 _.,()/+-]{0,59}$")
_COMPONENT_KEYS = ("name", "weight", "sizes_m", "std_m", "corr")


def _number(name: str, v) -> float:
    """``v`` as a finite float; strings, booleans, lists... are the user's mistake."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise UserError(f"sampling table: {name} must be a number, got {_show(v)}")
    try:
        f = float(v)
    except OverflowError:  # a JSON/TOML integer beyond a float (10**400): no finite value
        raise UserError(f"sampling table: {name} must be finite, got an integer of {len(str(abs(v)))} digits") from None
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
class ShapeComponent:
    """One size class of a :class:`ShapeMixture`.

    An object of this class takes, for each dimension, one of the standard values of
    ``sizes_m`` (uniformly, e.g. the 3-inch steps of cabinet widths), plus a jitter drawn
    from a normal with standard deviations ``std_m`` and correlation matrix ``corr`` (rows
    and columns in :data:`GEOMETRY_KEYS` order: depth, width, height).
    """

    name: str
    weight: float
    sizes_m: Mapping[str, tuple[float, ...]]
    std_m: Mapping[str, float]
    corr: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _COMPONENT_NAME.match(self.name):
            raise UserError(f"sampling table: shape component name must be 1-60 letters, digits or "
                            f"' _.,()/+-', got {_show(self.name)}")
        where = f"shape component {self.name!r}"
        weight = _number(f"{where} weight", self.weight)
        if not 0.0 < weight <= 1e6:
            raise UserError(f"sampling table: {where} weight must be in (0, 1e6], got {weight}")
        sizes, std = _mapping(f"{where} sizes_m", self.sizes_m), _mapping(f"{where} std_m", self.std_m)
        for part, given in (("sizes_m", sizes), ("std_m", std)):
            unknown = sorted(set(given) - set(GEOMETRY_KEYS))
            missing = [k for k in GEOMETRY_KEYS if k not in given]
            if unknown or missing:
                raise UserError(f"sampling table: {where} {part} needs exactly the keys {', '.join(GEOMETRY_KEYS)}")
        checked = {}
        for k in GEOMETRY_KEYS:
            values = sizes[k]
            if (isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence)
                    or not 1 <= len(values) <= MAX_SHAPE_SIZES):
                raise UserError(f"sampling table: {where} sizes_m.{k} must be a list of 1-{MAX_SHAPE_SIZES} sizes, "
                                f"got {_show(values)}")
            checked[k] = tuple(_number(f"{where} sizes_m.{k}", v) for v in values)
            if min(checked[k]) < MIN_SIZE_M or max(checked[k]) > MAX_SIZE_M:
                raise UserError(f"sampling table: {where} sizes_m.{k} must lie in [{MIN_SIZE_M}, {MAX_SIZE_M}] m")
        sd = {k: _number(f"{where} std_m.{k}", std[k]) for k in GEOMETRY_KEYS}
        if not all(0.0 <= v <= MAX_SHAPE_STD_M for v in sd.values()):
            raise UserError(f"sampling table: {where} std_m must lie in [0, {MAX_SHAPE_STD_M}] m, got {sd}")
        corr = self.corr
        n = len(GEOMETRY_KEYS)
        if (isinstance(corr, (str, bytes, Mapping)) or not isinstance(corr, Sequence) or len(corr) != n
                or any(isinstance(r, (str, bytes, Mapping)) or not isinstance(r, Sequence) or len(r) != n for r in corr)):
            raise UserError(f"sampling table: {where} corr must be a {n}x{n} matrix, got {_show(corr)}")
        c = np.array([[_number(f"{where} corr", v) for v in row] for row in corr])
        if not (np.allclose(np.diag(c), 1.0) and np.array_equal(c, c.T) and np.all(np.abs(c) <= 1.0)):
            raise UserError(f"sampling table: {where} corr must be symmetric with a unit diagonal and entries in [-1, 1]")
        if np.linalg.eigvalsh(c).min() < MIN_CORRELATION_EIGENVALUE:
            raise UserError(f"sampling table: {where} corr must be positive definite")
        object.__setattr__(self, "weight", weight)
        object.__setattr__(self, "sizes_m", checked)
        object.__setattr__(self, "std_m", sd)
        object.__setattr__(self, "corr", tuple(tuple(float(v) for v in row) for row in c))

    @property
    def mean_m(self) -> np.ndarray:
        """Mean (depth, width, height) of the class (m): the mean of its standard values."""
        return np.array([np.mean(self.sizes_m[k]) for k in GEOMETRY_KEYS])

    def jitter_factor(self) -> np.ndarray:
        """``L`` with ``L @ z`` (z standard normal) the class's jitter: diag(std) x Cholesky(corr)."""
        return np.diag([self.std_m[k] for k in GEOMETRY_KEYS]) @ np.linalg.cholesky(np.array(self.corr))

    def to_dict(self) -> dict:
        """The component as plain JSON types (sizes, std in metres; corr as nested lists)."""
        return {"name": self.name, "weight": self.weight, "sizes_m": {k: list(v) for k, v in self.sizes_m.items()},
                "std_m": dict(self.std_m), "corr": [list(r) for r in self.corr]}

    @classmethod
    def from_dict(cls, d) -> "ShapeComponent":
        """A component from its :meth:`to_dict` form; other or missing keys are the user's mistake."""
        d = _mapping("shape component", d)
        unknown = sorted(set(d) - set(_COMPONENT_KEYS))
        missing = [k for k in _COMPONENT_KEYS if k not in d]
        if unknown or missing:
            raise UserError(f"sampling table: a shape component needs exactly the keys {', '.join(_COMPONENT_KEYS)}"
                            f" ({'unknown ' + unknown[0] if unknown else 'missing ' + missing[0]})")
        return cls(d["name"], d["weight"], d["sizes_m"], d["std_m"], d["corr"])


@dataclass(frozen=True)
class ShapeMixture:
    """Joint distribution of an object's (depth, width, height): a mixture of size classes
    (:class:`ShapeComponent`), chosen with probability proportional to their weights."""

    components: tuple[ShapeComponent, ...]

    def __post_init__(self) -> None:
        comps = self.components
        if (isinstance(comps, (str, bytes, Mapping)) or not isinstance(comps, Sequence)
                or not 1 <= len(comps) <= MAX_SHAPE_COMPONENTS):
            raise UserError(f"sampling table: shape.components must be a list of 1-{MAX_SHAPE_COMPONENTS} components")
        comps = tuple(c if isinstance(c, ShapeComponent) else ShapeComponent.from_dict(c) for c in comps)
        names = [c.name for c in comps]
        if len(set(names)) != len(names):
            raise UserError("sampling table: shape component names must be distinct")
        object.__setattr__(self, "components", comps)

    @property
    def probabilities(self) -> np.ndarray:
        """Probability of each component: its weight over the sum of the weights."""
        w = np.array([c.weight for c in self.components])
        return w / w.sum()

    def mean_m(self) -> np.ndarray:
        """Mean (depth, width, height) of the mixture before truncation (m)."""
        return self.probabilities @ np.array([c.mean_m for c in self.components])

    def sample(self, rng: np.random.Generator, bounds: Mapping[str, Range]) -> tuple[dict, int]:
        """One object's geometry (``{depth_m, width_m, height_m}``) and its component index.

        Draws, from ``rng`` only: a component, one standard value per dimension, then the
        jitter until the sizes lie within ``bounds`` (at most :data:`MAX_SHAPE_DRAWS` times,
        then clipped into them).
        """
        cdf = np.cumsum(self.probabilities)
        index = min(int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right")), len(cdf) - 1)
        comp = self.components[index]
        nominal = np.array([v[min(int(rng.random() * len(v)), len(v) - 1)]
                            for v in (comp.sizes_m[k] for k in GEOMETRY_KEYS)])
        lo = np.array([bounds[k][0] for k in GEOMETRY_KEYS])
        hi = np.array([bounds[k][1] for k in GEOMETRY_KEYS])
        factor = comp.jitter_factor()
        for _ in range(MAX_SHAPE_DRAWS):
            x = nominal + factor @ rng.standard_normal(len(GEOMETRY_KEYS))
            if np.all((x >= lo) & (x <= hi)):
                break
        x = np.clip(x, lo, hi)
        return {k: float(v) for k, v in zip(GEOMETRY_KEYS, x)}, index

    def component_of(self, sizes_m, *, n_sd: float = 6.0, tol_m: float = 0.0) -> int | None:
        """The first size class explaining ``sizes_m`` (depth, width, height): each size within
        ``n_sd`` jitter standard deviations (+ ``tol_m``) of one of the class's standard
        values; None if no class does."""
        x = np.asarray(sizes_m, dtype=np.float64)
        for index, c in enumerate(self.components):
            if all(np.min(np.abs(np.array(c.sizes_m[k]) - x[i])) <= n_sd * c.std_m[k] + tol_m
                   for i, k in enumerate(GEOMETRY_KEYS)):
                return index
        return None

    def to_dict(self) -> dict:
        """The mixture as plain JSON types (``{"components": [...]}``)."""
        return {"components": [c.to_dict() for c in self.components]}

    @classmethod
    def from_dict(cls, d) -> "ShapeMixture":
        """A mixture from its :meth:`to_dict` form; any key but ``components`` is the user's mistake."""
        d = _mapping("shape", d)
        if set(d) != {"components"}:
            raise UserError("sampling table: shape must hold exactly one key, components")
        return cls(d["components"])


def structure_kind(name: str) -> str:
    """The kind (one of :data:`STRUCTURE_KINDS`) of the structure variable ``name``; a name
    without a known suffix is the user's mistake."""
    if not isinstance(name, str) or not _STRUCTURE_NAME.match(name):
        raise UserError(f"sampling table: structure variable names are 1-48 lower-case letters, digits or "
                        f"underscores, got {_show(name)}")
    for kind in STRUCTURE_KINDS:
        if name.endswith(kind):
            return kind
    raise UserError(f"sampling table: structure.{name} must end in one of {', '.join(STRUCTURE_KINDS)} "
                    f"(probability, lengths in m, fractions, option weights)")


def _structure_value(name: str, v):
    """One structure variable checked by the kind its name gives: a probability in [0, 1], a
    length range in [0, MAX_SIZE_M] m, a fraction range in [0, 1], or option weights
    (non-negative, not all zero; returned in option-name order)."""
    kind, where = structure_kind(name), f"structure.{name}"
    if kind == "_p":
        p = _number(where, v)
        if not 0.0 <= p <= 1.0:
            raise UserError(f"sampling table: {where} must be a probability in [0, 1], got {p}")
        return p
    if kind == "_m":
        return _check_range(where, v, 0.0, MAX_SIZE_M, " m")
    if kind == "_frac":
        return _check_range(where, v, 0.0, 1.0)
    weights = _mapping(where, v)
    if not 1 <= len(weights) <= MAX_STRUCTURE_OPTIONS:
        raise UserError(f"sampling table: {where} must weigh 1-{MAX_STRUCTURE_OPTIONS} options, got {len(weights)}")
    checked = {}
    for option, w in weights.items():
        if not _OPTION_NAME.match(option):
            raise UserError(f"sampling table: {where} option names are 1-32 lower-case letters, digits or "
                            f"underscores, got {_show(option)}")
        checked[option] = _number(f"{where}.{option}", w)
        if not 0.0 <= checked[option] <= 1e6:
            raise UserError(f"sampling table: {where}.{option} must be a weight in [0, 1e6], got {checked[option]}")
    if sum(checked.values()) <= 0.0:
        raise UserError(f"sampling table: {where} needs one option of positive weight")
    # options in name order: a table read back from a manifest (JSON, keys sorted) draws the same
    return {option: checked[option] for option in sorted(checked)}


def check_structure(structure) -> dict:
    """A table's structure variables checked (:func:`_structure_value`), keys in sorted order."""
    given = _mapping("structure", structure)
    if len(given) > MAX_STRUCTURE_VARIABLES:
        raise UserError(f"sampling table: structure holds at most {MAX_STRUCTURE_VARIABLES} variables, got {len(given)}")
    return {k: _structure_value(k, given[k]) for k in sorted(given)}


def _structure_to_dict(structure: Mapping) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else dict(v) if isinstance(v, Mapping) else v)
            for k, v in structure.items()}


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
    shape: None (the paper's tables: each geometry range sampled uniformly and independently)
        or a :class:`ShapeMixture`, the joint distribution of the three sizes, truncated to
        the ``geometry`` ranges (``--table realistic``).
    structure: structure variables (``--table varied``; empty for the paper's and the
        realistic tables): name -> probability, range or option weights, the kind given by
        the name's suffix (:data:`STRUCTURE_KINDS`).  The class's template reads one drawn
        value of each (:mod:`articulated_dataset.classes.varied`).
    """

    geometry: Mapping[str, Range]
    pose: Mapping[str, Range]
    q: tuple[Range, ...]
    chirality_p: float = 0.0
    extra: Mapping[str, float] = field(default_factory=dict)
    shape: ShapeMixture | None = None
    structure: Mapping[str, Any] = field(default_factory=dict)

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
        shape = self.shape
        if shape is not None:
            shape = shape if isinstance(shape, ShapeMixture) else ShapeMixture.from_dict(shape)
            for c in shape.components:
                for k in GEOMETRY_KEYS:
                    lo, hi = geometry[k]
                    if not all(lo <= v <= hi for v in c.sizes_m[k]):
                        raise UserError(f"sampling table: shape component {c.name!r} sizes_m.{k} must lie within "
                                        f"geometry.{k} [{lo}, {hi}]")
        object.__setattr__(self, "structure", check_structure(self.structure))
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "geometry", geometry)
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "chirality_p", chirality_p)
        object.__setattr__(self, "extra", extra)

    def to_dict(self) -> dict:
        """The table as plain JSON types; ``shape`` and ``structure`` only where the table has them."""
        return {
            "geometry": {k: list(v) for k, v in self.geometry.items()},
            "pose": {k: list(v) for k, v in self.pose.items()},
            "q": [list(r) for r in self.q],
            "chirality_p": self.chirality_p,
            "extra": dict(self.extra),
            # only a joint table stores one (the paper's tables, and their bytes, are unchanged)
            **({} if self.shape is None else {"shape": self.shape.to_dict()}),
            # only a varied table stores one (the paper's and realistic tables' bytes are unchanged)
            **({"structure": _structure_to_dict(self.structure)} if self.structure else {}),
        }

    def to_json(self) -> str:
        """:meth:`to_dict` as JSON text with sorted keys."""
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
            chirality_p=d.get("chirality_p", 0.0), extra=d.get("extra", {}), shape=d.get("shape"),
            structure=d.get("structure", {}),
        )

    @property
    def kind(self) -> str:
        """``"realistic"`` for a joint distribution of the sizes, else ``"uniform"``."""
        return "uniform" if self.shape is None else "realistic"

    def override(self, changes: Mapping) -> "SamplingTable":
        """Return a copy with the keys in ``changes`` (same layout as :meth:`to_dict`) replaced.

        Every key must be one the table has (``extra`` and ``structure`` variables included:
        the class defines them; a structure variable's options given replace its weights, those
        left out weighing 0); wrong types and out-of-range values are a :class:`UserError` naming the key.
        """
        changes = _mapping("(top level)", changes)
        unknown = sorted(set(changes) - set(TABLE_KEYS))
        if unknown:
            raise UserError(f"sampling table: unknown key {unknown[0]!r} (known: {', '.join(TABLE_KEYS)})")
        kwargs: dict[str, Any] = {}
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
        if "shape" in changes:  # a whole mixture, or null for independent uniform sizes
            kwargs["shape"] = changes["shape"]
        if "structure" in changes:
            given = _mapping("structure", changes["structure"])
            unknown = sorted(set(given) - set(self.structure))
            if unknown:
                known = ", ".join(self.structure) or f"none for this table; {option_name('table')} varied has them"
                raise UserError(f"sampling table: unknown structure variable structure.{unknown[0]} (known: {known})")
            structure = dict(self.structure)
            for name, value in given.items():
                if structure_kind(name) == "_weights":  # options left out weigh 0: {"knob": 1} forces one
                    value = _mapping(f"structure.{name}", value)
                    options = sorted(set(value) - set(structure[name]))
                    if options:
                        raise UserError(f"sampling table: structure.{name} has no option {options[0]!r} "
                                        f"(known: {', '.join(structure[name])})")
                    value = {option: value.get(option, 0.0) for option in structure[name]}
                structure[name] = value
            kwargs["structure"] = structure
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


#: Names ``--table`` reads as table files even when they do not exist (the error says so).
TABLE_FILE_SUFFIXES = (".json", ".toml")


def table_from_options(obj_class, values: Sequence[str]) -> SamplingTable:
    """The table of ``artdata generate --table`` values for ``obj_class`` (an
    :class:`~articulated_dataset.classes.base.ObjectClass`): at most one name of :data:`TABLE_NAMES`
    (default ``paper``), then table files overriding it in order; a value that is neither a
    name nor a file (an existing path or a ``.json``/``.toml`` name) is a one-line UserError."""
    names = [v for v in values if v in TABLE_NAMES]
    if len(names) > 1:
        table_flag = option_name("table")
        raise UserError(f"give one table name ({table_flag} {names[0]} or {table_flag} {names[1]}), not both")
    table = obj_class.named_table(names[0] if names else "paper")
    for value in values:
        if value in TABLE_NAMES:
            continue
        if not (Path(value).suffix.lower() in TABLE_FILE_SUFFIXES or Path(value).exists()):
            obj_class.named_table(value)  # the one-line "unknown sampling table" error
        try:
            table = table.override(load_table_file(value))
        except UserError as exc:
            message = exc.message
            raise UserError(message if str(value) in message else f"{value}: {message}") from None
    return table


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number a table may hold")
