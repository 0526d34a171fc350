"""Occluders between the camera and the object (``artdata generate --occluders N``).

Every image gets ``N`` occluding shapes, drawn afresh for that image from the object's own
occluder stream (:data:`OCCLUDER_STREAM`, independent of its sampling stream).  Each is, with
equal probability, a box, a cylinder or an arm-like chain of three capsule links (a robot arm
reaching in front of the object), placed on the ray from the camera to a uniform point of the
bounding box of a moving part (chosen uniformly; the part's geoms at the image's
configuration), at a fraction ``depth_fraction`` of the depth of the object's nearest point.
Its size is then shrunk if needed so that all of it lies between the near clipping plane and
that nearest point: an occluder is always in front of the object, never inside it.

Occlusion labels (format 1.1, :data:`articulated_dataset.format.schema.OPTIONAL_FIELDS`):
``unoccluded_pixels`` counts the body's and each moving part's pixels in a second render of
the object alone (the same model with the scene and occluder geom group switched off: one
extra render per image, the cheapest exact way), and ``visible_fraction`` =
``visible_pixels / unoccluded_pixels``.  Visibility rejection: an image whose moving parts do
not all keep ``visible_fraction`` in :data:`~articulated_dataset.context_labels.VISIBLE_FRACTION_RANGE` and
``min_part_pixels`` visible pixels gets new occluders, at most ``max_tries`` times; then the
object's pose is redrawn as for any hidden part.  Draw t (0, 1, ...) multiplies the drawn
sizes by ``1 - t / max_tries``, so that many occluders (up to 8) still leave every part
identifiable: most images of one or two occluders pass at the first draw, unshrunk.  Draws per try, per occluder, in order: kind,
part, 3 target coordinates, depth fraction, then 3 half sizes and a quaternion (box), radius,
half length and a quaternion (cylinder) or per link a length, a radius and a direction (arm).
"""

from __future__ import annotations

import json
from typing import Any, cast

import mujoco
import numpy as np

from articulated_dataset.format.schema import MASK_FIRST_PART, MASK_OCCLUDER, MASK_SCENE, visible_pixels
from articulated_dataset.generation.context_labels import VISIBLE_FRACTION_RANGE, visible_fraction
from articulated_dataset.generation.render import CONTEXT_GEOM_GROUP

#: Extra SeedSequence word of an object's occluder stream (noise 1, head camera 2, scene 3).
OCCLUDER_STREAM = 4
KINDS = ("box", "cylinder", "arm")
#: The occluders' ranges (uniform), recorded in every shard (attribute ``occluders``).
OCCLUDER_TABLE: dict[str, Any] = {
    "depth_fraction": (0.35, 0.85),  # centre depth / depth of the object's nearest point
    "half_size_m": (0.03, 0.15),  # box half sizes, cylinder radius and half length
    "arm_link_length_m": (0.15, 0.35),
    "arm_link_radius_m": (0.025, 0.05),
    "max_tries": 25,  # occluder draws per image before the pose is redrawn
}
ARM_LINKS = 3
#: Geoms of one occluder slot: a box, a cylinder and the arm's capsules; the kind drawn for an
#: image shows its geoms, the others are moved to :data:`HIDDEN_GROUP` (never rendered).
SLOT_GEOMS = 2 + ARM_LINKS
HIDDEN_GROUP = 5
#: Clearance (m) between an occluder and the near plane / the object's nearest point.
CLEARANCE_M = 0.02
#: How much of a link direction points along the view (arms reach across the image).
ARM_DEPTH_SHRINK = 0.3
OCCLUDER_RGBA = (0.25, 0.35, 0.45, 1.0)


def occluders_record(n: int) -> str:
    """The shard attribute ``occluders``: the count, kinds and ranges (JSON)."""
    return json.dumps({"n": n, "kinds": list(KINDS), "arm_links": ARM_LINKS, "ranges": OCCLUDER_TABLE,
                       "visible_fraction": list(VISIBLE_FRACTION_RANGE)}, sort_keys=True)


def add_occluder_slots(spec, n: int) -> None:
    """Add ``n`` occluder bodies (world children, :data:`SLOT_GEOMS` geoms each, hidden until
    :meth:`Occluders.draw` places them) to a MuJoCo spec."""
    types = [mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER] + [mujoco.mjtGeom.mjGEOM_CAPSULE] * ARM_LINKS
    for k in range(n):
        body = spec.worldbody.add_body(name=f"occluder_{k}", pos=[0.0, 0.0, 0.0])
        for g, t in enumerate(types):
            body.add_geom(name=f"occluder_{k}_{g}", type=t, size=[0.05, 0.05, 0.05], group=HIDDEN_GROUP,
                          contype=0, conaffinity=0, rgba=list(OCCLUDER_RGBA))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _quat_z_to(d: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) rotating +z onto the unit vector ``d``."""
    q = np.empty(4)
    mujoco.mju_quatZ2Vec(q, np.ascontiguousarray(d, dtype=np.float64))
    return q


class Context:
    """Scene and occluders of one compiled model: mask codes of their geoms, the occluder
    slots, and the per-image context render with its occlusion labels."""

    def __init__(self, model: mujoco.MjModel, info, n_occluders: int, rng: np.random.Generator | None):
        self.model, self.info, self.rng = model, info, rng
        names = [model.geom(i).name for i in range(model.ngeom)]
        self.scene_body = _body(model, "scene")  # -1 without a scene
        scene = model.geom_bodyid == self.scene_body  # no scene body: no geom
        self.slots = [np.array([names.index(f"occluder_{k}_{g}") for g in range(SLOT_GEOMS)]) for k in range(n_occluders)]
        self.slot_bodies = [_body(model, f"occluder_{k}") for k in range(n_occluders)]
        info.geom_part[scene] = MASK_SCENE
        for ids in self.slots:
            info.geom_part[ids] = MASK_OCCLUDER
        J = len(info.joint_ids)
        self.part_geoms = [np.nonzero(info.geom_part == MASK_FIRST_PART + j)[0] for j in range(J)]
        self.object_geoms = np.nonzero((info.geom_part >= 1) & (info.geom_part < MASK_OCCLUDER))[0]

    def draw(self, data: mujoco.MjData, scale: float = 1.0) -> None:
        """Place every occluder for the model's current configuration (kinematics up to date),
        its drawn sizes multiplied by ``scale``."""
        from articulated_dataset.generation.labels import geom_corners_world
        from articulated_dataset.generation.mujoco_scene import NEAR_CLIP_M

        m, rng = self.model, cast(np.random.Generator, self.rng)  # a model with occluders has their stream
        near_x = float(geom_corners_world(m, data, self.object_geoms)[:, 0].min())
        boxes: list = [geom_corners_world(m, data, g) for g in self.part_geoms]
        boxes = [(b.min(axis=0), b.max(axis=0)) for b in boxes]
        for body, geoms in zip(self.slot_bodies, self.slots):
            kind = KINDS[int(rng.integers(len(KINDS)))]
            lo, hi = boxes[int(rng.integers(len(boxes)))]
            target = lo + rng.random(3) * (hi - lo)
            cx = float(rng.uniform(*OCCLUDER_TABLE["depth_fraction"])) * near_x
            centre = target * (cx / target[0])
            room = max(min(near_x - cx, cx - NEAR_CLIP_M) - CLEARANCE_M, 0.005)  # radius that stays in front
            m.geom_group[geoms] = HIDDEN_GROUP
            m.body_pos[body], m.body_quat[body] = centre, (1.0, 0.0, 0.0, 0.0)
            if kind == "arm":
                self._arm(geoms[2:], room, scale)
                continue
            g = geoms[0] if kind == "box" else geoms[1]
            if kind == "box":
                size = rng.uniform(*OCCLUDER_TABLE["half_size_m"], size=3)  # type: ignore[call-overload]  # mypy: *Any and size=
            else:
                size = np.array([*rng.uniform(*OCCLUDER_TABLE["half_size_m"], size=2), 0.0])  # type: ignore[call-overload]  # mypy: *Any and size=
            quat = _unit(rng.normal(size=4))
            radius = float(np.linalg.norm(size[:3] if kind == "box" else size[:2]))
            m.geom_size[g] = size * min(scale, room / radius)
            m.geom_pos[g], m.geom_quat[g], m.geom_group[g] = 0.0, quat, CONTEXT_GEOM_GROUP
        mujoco.mj_kinematics(m, data)

    def _arm(self, geoms: np.ndarray, room: float, scale: float) -> None:
        """An arm-like chain of capsules from the slot's centre, shrunk to stay within ``room``."""
        m, rng = self.model, cast(np.random.Generator, self.rng)  # a model with occluders has their stream
        p, links = np.zeros(3), []
        for _ in geoms:
            length = float(rng.uniform(*OCCLUDER_TABLE["arm_link_length_m"]))
            radius = float(rng.uniform(*OCCLUDER_TABLE["arm_link_radius_m"]))
            d = _unit(rng.normal(size=3) * (ARM_DEPTH_SHRINK, 1.0, 1.0))
            links.append((p, p + length * d, radius, d))
            p = p + length * d
        reach = max(max(np.linalg.norm(a), np.linalg.norm(b)) + r for a, b, r, _ in links)
        s = min(scale, room / reach)
        for g, (a, b, r, d) in zip(geoms, links):
            m.geom_pos[g], m.geom_quat[g] = s * 0.5 * (a + b), _quat_z_to(d)
            m.geom_size[g] = (s * r, s * 0.5 * float(np.linalg.norm(b - a)), 0.0)
            m.geom_group[g] = CONTEXT_GEOM_GROUP

    def render(self, renderer, data: mujoco.MjData, depth_out: np.ndarray, mask_out: np.ndarray, min_part_pixels: int):
        """Render one image with its scene and occluders into ``depth_out``/``mask_out``.

        Returns ``(visible, unoccluded)`` pixel counts (1 + J,) or ``None`` if no occluder
        draw (within ``max_tries``) keeps every moving part visible enough."""
        J = len(self.part_geoms)
        _, geom_id = renderer.render(data, depth_out=depth_out)  # the object alone
        alone = visible_pixels(self.info.mask_from_geoms(geom_id), J)
        if alone[1:].min(initial=min_part_pixels) < min_part_pixels:
            return None
        lo_frac = VISIBLE_FRACTION_RANGE[0]
        tries = OCCLUDER_TABLE["max_tries"] if self.slots else 1
        for t in range(tries):
            if self.slots:  # each further draw shrinks the shapes: many occluders still fit
                self.draw(data, scale=1.0 - t / tries)
            _, geom_id = renderer.render(data, depth_out=depth_out, context=True)
            mask_out[...] = self.info.mask_from_geoms(geom_id)
            vis = visible_pixels(mask_out, J)
            frac = visible_fraction(vis, alone)
            if vis[1:].min(initial=min_part_pixels) >= min_part_pixels and frac[1:].min(initial=1.0) >= lo_frac:
                return vis, alone
        return None


def _body(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

