"""Scene context around an object (``artdata generate --scene kitchen|room``).

The paper renders objects in isolation (``--scene none``, the default, unchanged bytes).  A
scene adds boxes around the object, built in the *object frame* (origin at the centre of the
body's bottom face, x from the front to the back, y to the object's left, z up;
classes/common.xacro) and moved with it, so the class's pose ranges keep their
meaning: the object's base is where the table puts it, and the room is built around it.

Every scene has a floor and a wall behind the object.  Where the object stands depends on
its class (the class's ``placement``, :attr:`~articulated_dataset.classes.base.ObjectClass.placement`):

* ``floor`` (refrigerator, oven): on the floor;  ``--scene kitchen`` adds a base unit with a counter
  top on each side (backs against the wall, so a fridge deeper than 60 cm stands proud);
* ``under_counter`` (cabinet, cabinet2, dishwasher): on the floor, and with ``kitchen`` a counter top
  resting on it and a neighbouring unit on each side (same depth and height, fronts flush
  with the doors' closed faces, 3 mm apart);
* ``under_counter_drawer`` (drawer): with ``kitchen`` the drawer is the top drawer under a
  counter top, on a base cabinet down to the floor (counter top 86-94 cm above the floor),
  with neighbouring units; with ``room`` it is the top drawer of a chest 40-80 cm high;
* ``on_counter`` (microwave, toaster, lidded_box): on a counter top 86-94 cm above the floor with a base
  unit below (``kitchen``) or on a sideboard 70-95 cm high (``room``), front flush with the
  support's front edge (a bottom-hinged door swings down past it), the wall behind the
  counter's back (60-65 cm deep, or the object's depth + 2 cm if deeper).

Placement keeps the table's pose where physically possible: the camera (the origin of the
frame) must be at least :data:`MIN_CAMERA_HEIGHT_M` above the floor and clear of every box.
A pose whose floor would be higher gets its height redrawn, from the scene's own stream,
uniformly in the part of the table's ``z_m`` range that satisfies this (cabinets and
two-door cabinets: base 0.25-0.70 m below the camera instead of 0.3 m above to 0.7 m
below); a layout that puts the camera inside a box is redrawn the same way, and after
:data:`MAX_LAYOUT_TRIES` the pipeline redraws the object's pose as for a hidden part.

Randomness: one generator per object from its own SeedSequence stream
(:data:`SCENE_STREAM`), independent of the object's sampling stream (the same objects with
and without a scene).  Draws per layout, in order: wall gap, support height, counter
thickness, counter overhang, counter depth, left width, right width; then the base height
if it is redrawn.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from articulated_dataset.classes.registry import class_names, get_class
from articulated_dataset.format.manifest import SCENE_NAMES  # noqa: F401  (re-exported: declared with the split config)
from articulated_dataset.generation.context_labels import VISIBLE_FRACTION_RANGE
from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, yaw_quaternion
from articulated_dataset.generation.occluders import OCCLUDER_STREAM, add_occluder_slots
from articulated_dataset.generation.render import CONTEXT_GEOM_GROUP
from articulated_dataset.generation.sampling import object_rng
from articulated_dataset.generation.viewpoint import mid_height_m

#: Extra SeedSequence word of an object's scene stream (noise 1, head camera 2).
SCENE_STREAM = 3

#: Ranges (m) of the scene's sizes, uniform; recorded in every shard (attribute ``scene``).
SCENE_TABLE = {
    "wall_gap_m": (0.0, 0.05),  # object's back (or the counter's back) to the wall
    "counter_height_m": (0.86, 0.94),  # counter top above the floor (kitchen)
    "sideboard_height_m": (0.70, 0.95),  # sideboard top above the floor (room, on_counter)
    "chest_base_m": (0.40, 0.80),  # chest below a drawer (room)
    "counter_thickness_m": (0.03, 0.05),
    "counter_overhang_m": (0.01, 0.04),  # beyond the closed fronts (under_counter)
    "counter_depth_m": (0.60, 0.65),  # on_counter support depth
    "neighbour_width_m": (0.30, 0.90),  # each side (kitchen), or the support's margin each side
}
#: The highest an object's base stands above a scene's floor (m): the highest counter or sideboard top.
MAX_SUPPORT_HEIGHT_M = max(SCENE_TABLE["counter_height_m"][1], SCENE_TABLE["sideboard_height_m"][1])

#: Fixed sizes (m): floor and wall extents, wall height and thickness, gaps.
FLOOR_THICKNESS_M = 0.05
FLOOR_FRONT_M = 8.0  # the floor reaches this far in front of the object (past the camera)
ROOM_HALF_WIDTH_M = 4.0
WALL_HEIGHT_M = 2.6
WALL_THICKNESS_M = 0.10
GAP_M = 0.003  # between the object and its neighbours / the counter above it
#: Closed doors' and drawer fronts' thickness (classes/common.xacro, panel_m).
PANEL_M = 0.02
#: The camera is at least this high above the floor (a robot's or tripod's lowest camera).
MIN_CAMERA_HEIGHT_M = 0.25
#: ... and at least this far from every scene box (MuJoCo's near clipping plane + 1 cm).
CAMERA_CLEARANCE_M = 0.06
MAX_LAYOUT_TRIES = 20


@dataclass(frozen=True)
class Box:
    """An axis-aligned box of the scene in the object frame: centre and half sizes (m)."""

    name: str
    centre: tuple
    half: tuple

    @classmethod
    def span(cls, name: str, lo, hi) -> "Box":
        """The box spanning corners ``lo`` and ``hi`` (m, object frame)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return cls(name, tuple(0.5 * (lo + hi)), tuple(0.5 * (hi - lo)))

    def contains(self, p, margin: float = 0.0) -> bool:
        """True when point ``p`` (m, object frame) lies in the box grown by ``margin`` (m) on every side."""
        return bool(np.all(np.abs(np.asarray(p) - self.centre) <= np.asarray(self.half) + margin))


def placement(class_name: str) -> str:
    """Where objects of ``class_name`` stand in a scene: a built-in class's
    :attr:`~articulated_dataset.classes.base.ObjectClass.placement`; ``floor`` for any other class."""
    return get_class(class_name).placement if class_name in class_names() else "floor"


def scene_record(scene: str, class_name: str) -> str:
    """The shard attribute ``scene``: the scene, the class's placement and the ranges (JSON)."""
    return json.dumps({"scene": scene, "placement": placement(class_name), "ranges_m": SCENE_TABLE,
                       "min_camera_height_m": MIN_CAMERA_HEIGHT_M, "visible_fraction": list(VISIBLE_FRACTION_RANGE)},
                      sort_keys=True)


def _draws(rng: np.random.Generator) -> dict:
    keys = ("wall_gap_m", "counter_height_m", "counter_thickness_m", "counter_overhang_m", "counter_depth_m")
    d = {k: float(rng.uniform(*SCENE_TABLE[k])) for k in keys}
    d["left_m"], d["right_m"] = (float(rng.uniform(*SCENE_TABLE["neighbour_width_m"])) for _ in range(2))
    return d


def layout_boxes(scene: str, class_name: str, geometry: dict, d: dict) -> tuple[list[Box], float]:
    """The scene's boxes (object frame) and the floor's height in the object frame."""
    D, W, H = geometry["depth_m"], geometry["width_m"], geometry["height_m"]
    kitchen, where = scene == "kitchen", placement(class_name)
    xf = -D / 2 - PANEL_M  # closed fronts
    t, over = d["counter_thickness_m"], d["counter_overhang_m"]
    yl, yr = W / 2 + GAP_M + d["left_m"], -W / 2 - GAP_M - d["right_m"]
    boxes: list[Box] = []
    back = D / 2  # the object's (or its support's) back: the wall stands behind it

    def neighbours(z0: float, z1: float, x0: float = xf, x1: float = D / 2) -> None:
        boxes.append(Box.span("scene_left_unit", (x0, W / 2 + GAP_M, z0), (x1, yl, z1)))
        boxes.append(Box.span("scene_right_unit", (x0, yr, z0), (x1, -W / 2 - GAP_M, z1)))

    if where == "on_counter":
        top = d["counter_height_m"] if kitchen else float(np.interp(d["counter_height_m"], SCENE_TABLE["counter_height_m"],
                                                                     SCENE_TABLE["sideboard_height_m"]))
        depth = max(d["counter_depth_m"], D + 0.02)
        back = -D / 2 + depth
        floor = -top
        boxes.append(Box.span("scene_counter_top", (-D / 2, yr, -t), (back, yl, 0.0)))
        boxes.append(Box.span("scene_base_unit", (-D / 2 + 0.02, yr + 0.02, floor), (back, yl - 0.02, -t)))
    elif where == "under_counter_drawer":
        if kitchen:
            # a carcass as tall as the space under the counter (--table varied) stands on the floor
            floor = min(H + GAP_M + t - d["counter_height_m"], 0.0)
            boxes.append(Box.span("scene_counter_top", (xf - over, yr, H + GAP_M), (back, yl, H + GAP_M + t)))
            neighbours(floor, H + GAP_M)
        else:
            floor = -float(np.interp(d["counter_height_m"], SCENE_TABLE["counter_height_m"], SCENE_TABLE["chest_base_m"]))
        if floor < -GAP_M:
            boxes.append(Box.span("scene_base_unit", (xf, -W / 2, floor), (D / 2, W / 2, -GAP_M)))
    else:
        floor = 0.0
        if kitchen and where == "under_counter":
            boxes.append(Box.span("scene_counter_top", (xf - over, yr, H + GAP_M), (back, yl, H + GAP_M + t)))
            neighbours(0.0, H)
        elif kitchen:  # a refrigerator between two base units with counter tops, backs against the wall
            unit = d["counter_depth_m"]
            top = d["counter_height_m"]
            x0 = max(back - unit, xf)  # never proud of the fridge's doors (they swing past the units)
            neighbours(0.0, top - t, x0, back)
            boxes.append(Box.span("scene_left_counter", (x0, W / 2 + GAP_M, top - t), (back, yl, top)))
            boxes.append(Box.span("scene_right_counter", (x0, yr, top - t), (back, -W / 2 - GAP_M, top)))
    wall = back + d["wall_gap_m"]
    boxes.append(Box.span("scene_floor", (-FLOOR_FRONT_M, -ROOM_HALF_WIDTH_M, floor - FLOOR_THICKNESS_M),
                          (wall + WALL_THICKNESS_M, ROOM_HALF_WIDTH_M, floor)))
    boxes.append(Box.span("scene_wall", (wall, -ROOM_HALF_WIDTH_M, floor), (wall + WALL_THICKNESS_M, ROOM_HALF_WIDTH_M,
                                                                            floor + WALL_HEIGHT_M)))
    return boxes, floor


def camera_in_object_frame(pose: dict) -> np.ndarray:
    """The camera (the origin) in the object frame of a level pose (x_m, y_m, z_m, yaw_rad)."""
    c, s = np.cos(pose["yaw_rad"]), np.sin(pose["yaw_rad"])
    p = -np.array([pose["x_m"], pose["y_m"], pose["z_m"]])
    return np.array([c * p[0] + s * p[1], -s * p[0] + c * p[1], p[2]])


def scene_layout(scene: str, class_name: str, pose: dict, geometry: dict, z_range, rng: np.random.Generator,
                 *, head: bool = False):
    """``(pose, boxes)``: the object's pose (its height redrawn if the table's put the floor
    above the camera; with the ``head`` camera, its height set so that the floor lies
    :func:`~.viewpoint.mid_height_m` below the level frame) and the scene's boxes; ``None`` if
    no layout fits (module docstring)."""
    for _ in range(MAX_LAYOUT_TRIES):
        boxes, floor = layout_boxes(scene, class_name, geometry, _draws(rng))
        z_max = -MIN_CAMERA_HEIGHT_M - floor  # base height at which the floor is that far below the camera
        if head:  # the robot stands on the scene's floor: the camera's height is measured from it
            pose = {**pose, "z_m": float(-mid_height_m() - floor)}
        elif pose["z_m"] > z_max:
            lo, hi = z_range[0], min(z_range[1], z_max)
            if lo > hi:
                return None
            pose = {**pose, "z_m": float(rng.uniform(lo, hi))}
        cam = camera_in_object_frame(pose)
        if not any(b.contains(cam, CAMERA_CLEARANCE_M) for b in boxes):
            return pose, boxes
    return None


#: Colours (RGBA) of scene boxes in shaded previews.
SCENE_RGBA = (0.72, 0.70, 0.66, 1.0)


def add_scene(spec, pose: dict, boxes: list[Box]) -> None:
    """Add the scene to a MuJoCo spec: one body at the object's pose holding a box geom per
    :class:`Box` (in :data:`CONTEXT_GEOM_GROUP`, no collisions)."""
    body = spec.worldbody.add_body(name="scene", pos=[pose["x_m"], pose["y_m"], pose["z_m"]],
                                   quat=list(yaw_quaternion(pose["yaw_rad"])))
    for b in boxes:
        body.add_geom(name=b.name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(b.half), pos=list(b.centre),
                      group=CONTEXT_GEOM_GROUP, contype=0, conaffinity=0, rgba=list(SCENE_RGBA))


def context_rngs(config, object_index: int) -> tuple[np.random.Generator | None, np.random.Generator | None]:
    """Generators of one object's scene layout and occluders (None where not used), each its
    own stream: the object and its default images are the same with and without them."""
    def stream(used: bool, word: int):
        return object_rng(config.seed, config.class_name, config.split, object_index, stream=word) if used else None

    return stream(config.scene != "none", SCENE_STREAM), stream(config.occluders > 0, OCCLUDER_STREAM)


def context_builder(config, sample, srng):
    """``(sample, add_context)``: the sample placed in its scene (its base height redrawn
    where the table's is impossible) and the spec hook adding scene and occluder slots;
    ``add_context`` None when no scene layout fits the pose."""
    boxes = None
    head = config.camera.mount == "head"
    if config.scene != "none":
        placed = scene_layout(config.scene, config.class_name, sample.pose, sample.geometry, config.table.pose["z_m"], srng,
                              head=head)
        if placed is None:
            return sample, None
        sample, boxes = replace(sample, pose=placed[0]), placed[1]

    def add_context(spec):
        if boxes is not None:  # with the head camera, built with the object at the origin and moved with it per image
            add_scene(spec, ORIGIN_POSE if head else sample.pose, boxes)
        add_occluder_slots(spec, config.occluders)

    return sample, add_context
