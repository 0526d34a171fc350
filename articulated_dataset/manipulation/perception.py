"""What the robot sees: depth images of the simulated scene and the handle found in them.

:class:`SceneCamera` renders the true object as the split's camera would (noise and
quantisation included) from the reference viewpoint or another one (:func:`orbit_viewpoint`,
:func:`look_at_viewpoint`); :func:`sight_handle` / :func:`find_handle` find the handle bar and
the panel it stands on in a close-up (:class:`HandleSighting`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.rotations import axis_angle_quat, quat_multiply, quat_to_matrix
from articulated_dataset.generation.labels import mat_to_quat
from articulated_dataset.generation.mujoco_scene import set_configuration
from articulated_dataset.manipulation.planning import (
    HANDLE_STANDOFF_M,
    ZERO_LENGTH,
    canonical_quat,
    checked_vector,
    given_unit,
)
from articulated_dataset.manipulation.true_object import TrueObject

if TYPE_CHECKING:
    from articulated_dataset.generation.config import GenerationConfig


def orbit_viewpoint(centre, angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose ``(rot, trans)`` (camera -> reference frame) of the reference camera swung by
    ``angle_rad`` about the vertical line (reference z) through ``centre``: the robot moved
    sideways around the object at the same distance, still looking at ``centre``."""
    c = checked_vector("centre", centre, 3)
    rot = quat_to_matrix(axis_angle_quat(np.array([0.0, 0.0, 1.0]), angle_rad))
    return rot, c - rot @ c


class SceneCamera:
    """Depth images of the simulated true object as the robot's camera would take them.

    Renders with the dataset's renderer (:func:`articulated_dataset.generation.render.process_renderer`,
    the camera of the split's generation config) at the object's current configuration, from
    the reference camera or another viewpoint ``(rot, trans)`` (camera -> reference frame),
    then applies the split's sensor noise model (seeded by ``rng``) and depth quantisation
    as the generator does (:func:`articulated_dataset.generation.objects.apply_sensor`).
    """

    def __init__(self, obj: TrueObject, rng: np.random.Generator):
        from articulated_dataset.generation.mujoco_scene import CAMERA_NAME
        from articulated_dataset.generation.render import process_renderer

        if obj.config is None:
            raise UserError(f"{obj.class_name}: no generation config, so no camera to render the scene with")
        self.obj = obj
        self.rng = rng
        self.camera = obj.config.camera
        self.renderer = process_renderer(self.camera)
        self.data = mujoco.MjData(obj.model)
        self.cam_id = mujoco.mj_name2id(obj.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self.cam_pos0 = obj.model.cam_pos[self.cam_id].copy()
        self.cam_quat0 = obj.model.cam_quat[self.cam_id].copy()

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        """Intrinsics (3, 3) of the images taken."""
        return self.camera.K

    def render(self, q: np.ndarray, viewpoint: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Depth (H, W) float32 metres of the object at configuration ``q``."""
        model = self.obj.model
        config: GenerationConfig = self.obj.config  # type: ignore[assignment]  # not None: refused in __init__
        if viewpoint is not None:
            rot, trans = viewpoint
            model.cam_pos[self.cam_id] = rot @ self.cam_pos0 + trans
            model.cam_quat[self.cam_id] = canonical_quat(quat_multiply(mat_to_quat(rot), self.cam_quat0))
        try:
            self.renderer.bind(model)
            set_configuration(model, self.data, self.obj.info.joint_ids, np.asarray(q, np.float64))
            depth, _ = self.renderer.render(self.data)
            depth = depth.copy()
        finally:
            model.cam_pos[self.cam_id] = self.cam_pos0
            model.cam_quat[self.cam_id] = self.cam_quat0
        if config.noise != "none":
            from articulated_dataset.core.noise import get_noise_model

            depth = get_noise_model(config.noise)(depth, self.K, self.rng)
        if config.depth_quantum_m > 0:
            depth = np.round(depth / config.depth_quantum_m) * config.depth_quantum_m
        return depth.astype(np.float32)


def depth_centroid(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Mean back-projected point (m, camera frame) of the valid pixels: where the object is."""
    from articulated_dataset.core.camera import backproject

    pts = backproject(depth_m, K)
    if len(pts) == 0:
        raise UserError("the depth image has no valid pixel")
    return pts.mean(axis=0)


#: Looking at the handle before grasping (closed loop): a wrist camera (the dataset's
#: intrinsics) HANDLE_LOOK_DISTANCE_M out along the estimated outward normal of the planned
#: grasp, looking back at it (4.7 mm per pixel there; the search disc fits the 54 degree
#: vertical field of view).  Within HANDLE_SEARCH_RADIUS_M of the
#: view's centre the panel is the plane with most points within HANDLE_PLANE_TOL_M
#: (RANSAC, HANDLE_RANSAC_ITERATIONS draws); handle candidates stand HANDLE_PROTRUSION_M
#: (min, max) in front of it (the bar is a 3 cm deep block, classes/common.xacro).
#: The connected candidate region nearest the view's centre that is bar-shaped (at most
#: HANDLE_MAX_EXTENT_M long and HANDLE_MAX_WIDTH_M wide, at least HANDLE_MIN_PIXELS pixels)
#: is the handle; the grasp moves to its centroid, HANDLE_STANDOFF_M / 2 back towards the
#: panel (the bar's centre, as in the grasp rule).  None found: the planned grasp is kept.
HANDLE_LOOK_DISTANCE_M = 0.5
HANDLE_SEARCH_RADIUS_M = 0.25
HANDLE_PLANE_TOL_M = 0.005
HANDLE_RANSAC_ITERATIONS = 200
HANDLE_PROTRUSION_M = (0.01, 0.045)
HANDLE_MAX_EXTENT_M = 0.25
HANDLE_MAX_WIDTH_M = 0.05
HANDLE_MIN_PIXELS = 10


def look_at_viewpoint(point, normal, distance_m: float = HANDLE_LOOK_DISTANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose ``(rot, trans)`` (camera -> reference frame; camera x forward, z up) at
    ``point + distance_m * normal`` looking back along ``-normal`` at ``point``, its up as close
    to the reference z (or, for a vertical normal, the reference x) as possible."""
    n = given_unit("normal", normal)
    fwd = -n
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < math.cos(math.radians(10.0)) else np.array([1.0, 0.0, 0.0])
    up = up - (up @ fwd) * fwd
    up /= np.linalg.norm(up)
    rot = np.column_stack([fwd, np.cross(up, fwd), up])
    return rot, checked_vector("point", point, 3) + distance_m * n


def find_handle(depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """The handle bar's centre (m, in the frame of the camera that took ``depth_m``) near the
    image centre, or None; method and thresholds: ``HANDLE_*`` above (:func:`sight_handle`)."""
    seen = sight_handle(depth_m, K, rng)
    return None if seen is None else seen.centre_m


@dataclass
class HandleSighting:
    """A handle bar seen in a close-up (camera frame of the image it was found in)."""

    centre_m: np.ndarray  # (3,) the bar's centre
    panel_normal: np.ndarray  # (3,) unit normal of the panel it stands on, towards the camera
    panel_points_m: np.ndarray  # (K, 3) pixels of the image on the panel's plane (at most PANEL_MAX_POINTS)

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> "HandleSighting":
        """The same sighting in the frame where this camera's pose is ``(rot, trans)``."""
        return HandleSighting(rot @ self.centre_m + trans, rot @ self.panel_normal, self.panel_points_m @ rot.T + trans)

    def panel_extent(self, direction) -> tuple[float, float]:
        """How far (m) the seen panel runs from the handle against and along ``direction``
        (between :data:`PANEL_EXTENT_PERCENTILES` of its points)."""
        if not len(self.panel_points_m):
            return 0.0, 0.0
        lo, hi = np.percentile((self.panel_points_m - self.centre_m) @ np.asarray(direction, np.float64),
                               PANEL_EXTENT_PERCENTILES)
        return float(max(-lo, 0.0)), float(max(hi, 0.0))


#: A sighting keeps at most this many panel points (every k-th); its extent is read between these
#: percentiles of them.
PANEL_MAX_POINTS = 4096
PANEL_EXTENT_PERCENTILES = (2.0, 98.0)


def sight_handle(depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator,
                 search_radius_m: float = HANDLE_SEARCH_RADIUS_M) -> HandleSighting | None:
    """The handle bar nearest the image centre within ``search_radius_m`` of the view's axis
    (:class:`HandleSighting`, camera frame of ``depth_m``: camera z is up), or None; method and
    thresholds: ``HANDLE_*`` above.  The panel's extent is that of every pixel of the image
    within :data:`HANDLE_PLANE_TOL_M` of its plane, along the plane's horizontal direction."""
    from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL
    from articulated_dataset.core.errors import import_optional

    ndimage = import_optional("scipy.ndimage", "the handle close-up (manipulation.find_handle)")

    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W]
    z = depth_m.astype(np.float64)
    valid = z > 0
    pts = (np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1) @ R_CAMERA_TO_OPTICAL)
    lateral = np.hypot(pts[..., 1], pts[..., 2])
    near = valid & (lateral < search_radius_m)
    P = pts[near]
    if len(P) < 3 * HANDLE_MIN_PIXELS:
        return None
    # RANSAC, all draws at once: plane through 3 distinct random points, counted inliers
    idx = np.stack([rng.choice(len(P), 3, replace=False) for _ in range(HANDLE_RANSAC_ITERATIONS)])
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    length = np.linalg.norm(normals, axis=1)
    ok = length > ZERO_LENGTH
    if not ok.any():
        return None
    a, normals = a[ok], normals[ok] / length[ok, None]
    counts = (np.abs(P @ normals.T - np.einsum("ij,ij->i", a, normals)) < HANDLE_PLANE_TOL_M).sum(axis=0)
    k = int(np.argmax(counts))
    a, nrm = a[k], normals[k]
    if nrm[0] > 0:  # towards the camera (camera x is forward, so the camera side is -x)
        nrm = -nrm
    height = np.where(valid, (pts - a) @ nrm, -np.inf)  # how far in front of the panel
    cand = near & (height >= HANDLE_PROTRUSION_M[0]) & (height <= HANDLE_PROTRUSION_M[1])
    labels, n = ndimage.label(cand)
    found = []
    for k in range(1, n + 1):
        Q = pts[labels == k]
        if len(Q) < HANDLE_MIN_PIXELS:
            continue
        centred = Q - Q.mean(axis=0)
        ext = np.sort(np.ptp(centred @ np.linalg.svd(centred, full_matrices=False)[2].T, axis=0))[::-1]
        if ext[0] > HANDLE_MAX_EXTENT_M or ext[1] > HANDLE_MAX_WIDTH_M:
            continue
        centre = Q.mean(axis=0)
        found.append((float(np.hypot(centre[1], centre[2])), centre))
    if not found:
        return None
    centre = min(found, key=lambda f: f[0])[1]
    # the visible faces are the bar's front: its centre lies half the standoff nearer the panel
    centre = centre - 0.5 * HANDLE_STANDOFF_M * nrm
    panel = pts[valid & (np.abs(height) < HANDLE_PLANE_TOL_M)]
    return HandleSighting(centre, nrm, panel[:: max(1, -(-len(panel) // PANEL_MAX_POINTS))])
