"""Stage 1 of the pipeline (sample): one object's parameters drawn from its class table.

Randomness is injected: every object gets its own ``numpy.random.Generator`` derived from
``SeedSequence([seed, class_key, split_key, object_index])`` only, so object k is the same
whichever process generates it and however the work is split, and splits never share a
random stream.  An object's structure variables (``--table varied``) come from a stream of
their own (:data:`STRUCTURE_STREAM`), so the sizes, configurations and poses of a table are
drawn the same with or without them.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from articulated_dataset.classes.base import ObjectClass
from articulated_dataset.core.tables import GEOMETRY_KEYS, POSE_KEYS, SamplingTable, structure_kind

SPLITS = ("train", "val", "test", "real")
#: Extra SeedSequence word of an object's structure stream (noise 1, head camera 2, scene 3,
#: occluders 4, appearance 5): the structure variables of ``--table varied``.
STRUCTURE_STREAM = 6


def stable_key(text: str) -> int:
    """A 32-bit integer derived from ``text`` that never changes across runs or platforms."""
    return int.from_bytes(hashlib.blake2b(text.encode("utf-8"), digest_size=4).digest(), "little")


def object_rng(seed: int, class_name: str, split: str, object_index: int, *, stream: int | None = None) -> np.random.Generator:
    """The random generator of one object: ``SeedSequence([seed, H(class), H(split), index])``.

    ``stream`` appends one more word, giving an independent generator for the same object
    (e.g. its sensor noise) that leaves the sampling stream untouched.
    """
    if seed < 0 or object_index < 0:
        raise ValueError("seed and object_index must be >= 0")
    words = [int(seed), stable_key(class_name), stable_key(split), int(object_index)]
    ss = np.random.SeedSequence(words if stream is None else words + [int(stream)])
    return np.random.Generator(np.random.PCG64(ss))


def sample_id(class_name: str, split: str, seed: int, object_index: int, image_index: int) -> int:
    """Stable 63-bit identifier of one image: a hash of (class, split, seed, object, image)."""
    text = f"{class_name}/{split}/{seed}/{object_index}/{image_index}"
    return int.from_bytes(hashlib.blake2b(text.encode("utf-8"), digest_size=8).digest(), "little") >> 1


def stratified_configurations(rng: np.random.Generator, q_ranges, n_images: int) -> np.ndarray:
    """Configurations of one object's images, shape (n_images, J).

    * J = 1: one uniform draw in each of ``n_images`` equal strata of the range, in order.
    * J >= 2 and ``n_images = g**J`` (16 = 4x4 for J = 2): a jittered g x ... x g grid, one
      uniform draw per cell, so the images cover the whole configuration square.
    * otherwise: a Latin hypercube (each joint's range is stratified, strata paired at random).
    """
    J = len(q_ranges)
    lo = np.array([r[0] for r in q_ranges])
    hi = np.array([r[1] for r in q_ranges])
    if J == 1:
        u = (np.arange(n_images) + rng.random(n_images)) / n_images
        return (lo + u[:, None] * (hi - lo)).astype(np.float64)
    g = round(n_images ** (1.0 / J))
    if g**J == n_images:
        cells = np.stack(np.meshgrid(*[np.arange(g)] * J, indexing="ij"), axis=-1).reshape(-1, J)
        u = (cells + rng.random((n_images, J))) / g
    else:
        u = np.stack([(rng.permutation(n_images) + rng.random(n_images)) / n_images for _ in range(J)], axis=1)
    return lo + u * (hi - lo)


@dataclass(frozen=True)
class ObjectSample:
    """Sampled parameters of one object (before rendering)."""

    class_name: str
    split: str
    seed: int
    object_index: int
    geometry: dict  # depth_m, width_m, height_m
    chirality: int
    q: np.ndarray  # (n_images, J)
    pose: dict  # x_m, y_m, z_m, yaw_rad
    # Head camera (CameraConfig.mount "head"): (n_images, 3) height_m, pitch_rad, roll_rad of
    # each image's camera (articulated_dataset.viewpoint), set by the pipeline; None: fixed.
    views: np.ndarray | None = None
    # Structure variables drawn from the table's ``structure`` (:func:`draw_structure`): name
    # -> 0/1 flag, length (m), fraction or option name; None for a table without them.
    structure: dict | None = None

    # State of the object's generator after these draws (``bit_generator.state``): a pose
    # rejected later is redrawn from it (:meth:`pose_generator`), never by replaying the draws.
    # None for the mean object, whose pose is never redrawn.
    rng_state: Mapping[str, Any] | None = field(default=None, compare=False, repr=False)

    def pose_generator(self) -> np.random.Generator:
        """A new generator positioned where this sample's draws left the object's generator:
        the stream of its pose redraws (:func:`sample_pose`).  Each call starts at the same
        state, so the sample can be rendered again with the same result."""
        if self.rng_state is None:
            raise ValueError("this sample keeps no generator state (the mean object, or built by hand)")
        rng = np.random.Generator(np.random.PCG64(0))  # its state replaced at once
        rng.bit_generator.state = self.rng_state
        return rng


def sample_pose(rng: np.random.Generator, table: SamplingTable) -> dict:
    """Base position (m) and yaw (rad), uniform in the table's ranges."""
    return {k: float(rng.uniform(*table.pose[k])) for k in POSE_KEYS}


def draw_structure(rng: np.random.Generator, structure) -> dict:
    """One value of each structure variable (name order), one uniform draw each from ``rng``
    whatever the variable's kind, so that forcing one variable (a probability of 1, one
    option) leaves the others' values unchanged: a probability ``_p`` -> 0/1; a range ``_m``
    or ``_frac`` -> a uniform value; option weights ``_weights`` -> an option name."""
    out: dict[str, Any] = {}
    for name in sorted(structure):
        value, u = structure[name], float(rng.random())
        kind = structure_kind(name)
        if kind == "_p":
            out[name] = int(u < value)
        elif kind == "_weights":
            options = list(value)
            cdf = np.cumsum([value[o] for o in options])
            out[name] = options[min(int(np.searchsorted(cdf, u * cdf[-1], side="right")), len(options) - 1)]
        else:
            lo, hi = value
            out[name] = float(lo + u * (hi - lo))
    return out


def centre_structure(structure) -> dict:
    """The mean object's structure: flags with probability >= 0.5 set, ranges at their centre,
    the heaviest option (the first of equals)."""
    out = {}
    for name in sorted(structure):
        value, kind = structure[name], structure_kind(name)
        if kind == "_p":
            out[name] = int(value >= 0.5)
        elif kind == "_weights":
            out[name] = max(value, key=lambda o: value[o])
        else:
            out[name] = 0.5 * (value[0] + value[1])
    return out


def sample_object(
    obj_class: ObjectClass,
    table: SamplingTable,
    *,
    seed: int,
    split: str,
    object_index: int,
    n_images: int,
    rng: np.random.Generator | None = None,
) -> tuple[ObjectSample, np.random.Generator]:
    """Draw geometry, chirality and configurations, then a first pose.

    Returns the sample and the object's generator, positioned after these draws; the sample
    keeps that position (:meth:`ObjectSample.pose_generator`), so that a rejected pose can be
    redrawn with :func:`sample_pose` deterministically.
    """
    if rng is None:
        rng = object_rng(seed, obj_class.name, split, object_index)
    if table.shape is None:  # the paper's independent uniform sizes
        geometry = {k: float(rng.uniform(*table.geometry[k])) for k in GEOMETRY_KEYS}
    else:  # a joint distribution of the sizes (--table realistic), from the same stream
        geometry, _ = table.shape.sample(rng, table.geometry)
    chirality = int(rng.random() < table.chirality_p)
    q = stratified_configurations(rng, table.q, n_images)
    pose = sample_pose(rng, table)
    structure = None
    if table.structure:
        srng = object_rng(seed, obj_class.name, split, object_index, stream=STRUCTURE_STREAM)
        structure = draw_structure(srng, table.structure)
    sample = ObjectSample(obj_class.name, split, seed, object_index, geometry, chirality, q, pose,
                          structure=structure, rng_state=rng.bit_generator.state)
    return sample, rng


def mean_object(obj_class: ObjectClass, table: SamplingTable, *, split: str, n_images: int) -> ObjectSample:
    """The class's mean object: every geometry and pose parameter at the centre of its range
    (a joint size distribution: its mean, within the bounds), chirality 0, configurations
    evenly spread (stratum centres / grid-cell centres)."""
    geometry = {k: 0.5 * (lo + hi) for k, (lo, hi) in table.geometry.items()}
    if table.shape is not None:
        geometry = {k: float(min(max(m, table.geometry[k][0]), table.geometry[k][1]))
                    for k, m in zip(GEOMETRY_KEYS, table.shape.mean_m())}
    pose = {k: 0.5 * (lo + hi) for k, (lo, hi) in table.pose.items()}

    class _Centre:  # a "generator" whose uniform draws are all 0.5: stratum/cell centres
        def random(self, size=None):
            return np.full(size, 0.5)

        def permutation(self, n):
            return np.arange(n)

    q = stratified_configurations(_Centre(), table.q, n_images)  # type: ignore[arg-type]  # the two methods it calls
    structure = centre_structure(table.structure) if table.structure else None
    return ObjectSample(obj_class.name, split, 0, 0, geometry, 0, q, pose, structure=structure)

