"""Where an object may stand in the image (``artdata generate --framing``).

``table4`` (the default): the pose is drawn uniformly from the sampling table's ranges (the
paper's Table 4), whatever part of the object the image then cuts off.

``whole``: the paper's text, "we sampled object position uniformly from the view frustum of
the camera up to a maximum depth dependent upon object size" (Appendix A).  Poses are drawn
uniformly from the table's ranges with the depth range (``x_m``, the camera frame's forward
axis) extended to ``max(x_high, fit + FRAMING_DEPTH_MARGIN_M)``, where ``fit`` is the
smallest depth at which this object, in every one of its images' configurations, fits
inside the image at some position and yaw of the table's ranges (:func:`fit_depth_m`); a
draw is kept only if the whole object is in view in every image.  In view means:

* every point spanning the object's geoms (:func:`~articulated_dataset.generation.labels.geom_corners_world`:
  a box's corners, a mesh's vertices) in every image's configuration projects inside the
  image's interior, the pixels off its border rows and columns (:func:`in_view`, checked
  before anything is rendered), and
* no object pixel of a rendered image lies on a border row or column
  (:func:`articulated_dataset.format.schema.object_on_border`, checked after rendering).

The first condition implies the second up to rasterisation (a shape whose projection stays
0.5 px inside the outer pixels' centres covers none of them); both are kept, so the rule is
the one ``benchmarks/error_sources.py`` counts.  Rejected draws are redrawn from the
object's pose stream (:meth:`~articulated_dataset.generation.sampling.ObjectSample.pose_generator`),
as a pose that hides a moving part is, so object k stays a function of (seed, class, split, k).

Light: MuJoCo is imported only to build an object's points (:func:`extent_points`), so
``artdata verify`` reads a shard's framing (:func:`shard_framing`) without it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from articulated_dataset.classes.base import ObjectClass
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.tables import SamplingTable
from articulated_dataset.format.manifest import DEFAULT_FRAMING
from articulated_dataset.format.schema import MASK_BODY
from articulated_dataset.generation.sampling import sample_pose

#: Depth (m) added to an object's fitting depth (:func:`fit_depth_m`) to give its largest
#: depth, when that exceeds the table's: at the fitting depth itself only one position and
#: yaw keep the object in view, so the margin gives the draws room.
FRAMING_DEPTH_MARGIN_M = 0.5
#: Yaw values (evenly spaced over the table's yaw range) at which the fitting depth is
#: evaluated; its minimum over them is the object's fitting depth.
FIT_YAW_STEPS = 61
#: Pixels left out of the image's interior on each side: the border row or column (the
#: interior is ``u`` in ``[BORDER_PX - 0.5, W - 0.5 - BORDER_PX]``, pixel centres at integers).
BORDER_PX = 1.0
#: Pose draws per object before ``--framing whole`` gives up (each draw projects the object's
#: points, 400-1200 for the built-in classes, and renders nothing).
MAX_FRAMING_DRAWS = 20000


def framing_record(framing: str) -> str:
    """The shard attribute ``framing`` of ``--framing whole`` (JSON): the rule and its constants."""
    return json.dumps({"framing": framing, "depth_margin_m": FRAMING_DEPTH_MARGIN_M, "border_px": BORDER_PX},
                      sort_keys=True)


def shard_framing(attrs) -> str:
    """The framing a shard's root attributes record (``table4`` when they record none, or
    record it unreadably: the checks of ``whole`` then do not apply)."""
    text = attrs.get("framing") if hasattr(attrs, "get") else None
    if text is None:
        return DEFAULT_FRAMING
    try:
        value = json.loads(text).get("framing")
    except (TypeError, ValueError, AttributeError):
        return DEFAULT_FRAMING
    return value if isinstance(value, str) else DEFAULT_FRAMING


def extent_points(obj_class: ObjectClass, urdf: str, q: np.ndarray, camera: CameraConfig) -> np.ndarray:
    """Points (P, 3) spanning the object's rendered geoms (a box's corners, a mesh's vertices;
    the groups the renderer draws) in each configuration of ``q`` (n, J), in the frame of its
    pose (the object compiled at :data:`~articulated_dataset.generation.mujoco_scene.ORIGIN_POSE`)."""
    import mujoco

    from articulated_dataset.generation.compiled import compile_object
    from articulated_dataset.generation.labels import geom_corners_world
    from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, set_configuration

    obj = compile_object(obj_class, urdf, ORIGIN_POSE, camera)
    model, info = obj.model, obj.info
    drawn = np.asarray(mujoco.MjvOption().geomgroup, bool)  # the default render's geom groups
    groups = np.clip(model.geom_group, 0, len(drawn) - 1)
    geoms = np.nonzero((info.geom_part >= MASK_BODY) & drawn[groups])[0]
    data = mujoco.MjData(model)
    points = []
    for qi in np.atleast_2d(q):
        set_configuration(model, data, info.joint_ids, qi)
        points.append(geom_corners_world(model, data, geoms))
    return np.concatenate(points, axis=0)


def interior_slopes(camera: CameraConfig) -> tuple[float, float, float, float]:
    """``(left, right, up, down)``: the largest ``Y/X`` (left), ``-Y/X`` (right), ``Z/X`` (up)
    and ``-Z/X`` (down) of a camera-frame point (x forward, y left, z up) whose pixel lies in
    the image's interior, ``u`` in ``[BORDER_PX - 0.5, W - 0.5 - BORDER_PX]`` and ``v`` alike
    (pixel centres at integers: ``u = cx - fx Y / X``, ``v = cy - fy Z / X``)."""
    fx, fy, cx, cy = camera.intrinsics_px
    W, H = camera.width_px, camera.height_px
    lo = BORDER_PX - 0.5
    return (cx - lo) / fx, (W - 1.0 - lo - cx) / fx, (cy - lo) / fy, (H - 1.0 - lo - cy) / fy


def _rotated(points: np.ndarray, yaw_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z of ``points`` (P, 3) turned by each yaw about +z: arrays (..., P)."""
    c, s = np.cos(yaw_rad)[..., None], np.sin(yaw_rad)[..., None]
    px, py, pz = points[:, 0], points[:, 1], points[:, 2]
    return c * px - s * py, s * px + c * py, np.broadcast_to(pz, np.shape(c * px))


def in_view(points: np.ndarray, pose: dict, camera: CameraConfig) -> bool:
    """Whether ``points`` (P, 3, in the frame of the object's pose: base at the origin, yaw
    0), placed at ``pose`` (``x_m``, ``y_m``, ``z_m``, ``yaw_rad``; the fixed camera's frame),
    all project inside the image's interior and lie beyond the near clipping plane."""
    from articulated_dataset.generation.mujoco_scene import NEAR_CLIP_M

    left, right, up, down = interior_slopes(camera)
    qx, qy, qz = _rotated(points, np.asarray(pose["yaw_rad"], np.float64))
    X, Y, Z = qx + pose["x_m"], qy + pose["y_m"], qz + pose["z_m"]
    return bool(np.all(X >= NEAR_CLIP_M) and np.all(Y <= left * X) and np.all(-Y <= right * X)
                and np.all(Z <= up * X) and np.all(-Z <= down * X))


def fit_depth_m(points: np.ndarray, table: SamplingTable, camera: CameraConfig) -> float:
    """The smallest base depth ``x_m`` at which ``points`` (P, 3, pose frame) fit in the
    image's interior (:func:`in_view`) at some ``y_m``, ``z_m`` and ``yaw_rad`` of ``table``'s
    ranges (yaw on :data:`FIT_YAW_STEPS` values).

    At a fixed yaw the conditions are linear in the base position and separate into a
    horizontal (x, y) and a vertical (x, z) pair.  Horizontally, ``y`` must lie in
    ``[y_lo, y_hi]`` and in ``[cL - right x, cU + left x]`` with ``cL = max(-right qx - qy)``,
    ``cU = min(left qx - qy)`` over the points ``q`` turned by the yaw; both intervals widen
    as ``x`` grows, so they meet for ``x >= max((cL - cU) / (left + right), (cL - y_hi) / right,
    (y_lo - cU) / left)``.  The vertical pair gives the same with ``up``, ``down``, ``z``; the
    near plane adds ``x >= NEAR_CLIP_M - min qx``.
    """
    from articulated_dataset.generation.mujoco_scene import NEAR_CLIP_M

    left, right, up, down = interior_slopes(camera)
    (y_lo, y_hi), (z_lo, z_hi) = table.pose["y_m"], table.pose["z_m"]
    yaw = np.linspace(*table.pose["yaw_rad"], FIT_YAW_STEPS)
    qx, qy, qz = _rotated(points, yaw)  # (steps, P)

    def pair(lateral, low_range, high_range, plus, minus):
        c_low = np.max(-minus * qx - lateral, axis=1)
        c_high = np.min(plus * qx - lateral, axis=1)
        return np.maximum.reduce([(c_low - c_high) / (plus + minus), (c_low - high_range) / minus,
                                  (low_range - c_high) / plus])

    need = np.maximum.reduce([pair(qy, y_lo, y_hi, left, right), pair(qz, z_lo, z_hi, up, down),
                              NEAR_CLIP_M - qx.min(axis=1)])
    return float(need.min())


def framed_table(table: SamplingTable, fit_m: float) -> SamplingTable:
    """``table`` with its depth range ``x_m`` reaching ``fit_m + FRAMING_DEPTH_MARGIN_M`` when
    the table's own upper bound is nearer (the other ranges as they are)."""
    lo, hi = table.pose["x_m"]
    far = max(hi, fit_m + FRAMING_DEPTH_MARGIN_M)
    return table if far == hi else replace(table, pose={**table.pose, "x_m": (lo, far)})


@dataclass(frozen=True)
class Framing:
    """One object's ``--framing whole`` rule: the points spanning its geometry in every image
    (pose frame) and the table its poses are drawn from (the depth range extended)."""

    points: np.ndarray  # (P, 3)
    table: SamplingTable
    camera: CameraConfig

    @classmethod
    def of(cls, points: np.ndarray, table: SamplingTable, camera: CameraConfig) -> "Framing":
        """The framing of an object spanned by ``points`` (P, 3, pose frame): ``table`` with its depth range extended
        so that the points fit in ``camera``'s view."""
        return cls(points, framed_table(table, fit_depth_m(points, table, camera)), camera)

    def draw(self, rng: np.random.Generator) -> tuple[dict | None, int]:
        """``(pose, draws)``: the first pose drawn from ``rng`` (uniform in :attr:`table`'s
        ranges) that keeps the whole object in view (:func:`in_view`), and how many poses
        were drawn; ``(None, MAX_FRAMING_DRAWS)`` when none of them does."""
        for k in range(1, MAX_FRAMING_DRAWS + 1):
            pose = sample_pose(rng, self.table)
            if in_view(self.points, pose, self.camera):
                return pose, k
        return None, MAX_FRAMING_DRAWS
