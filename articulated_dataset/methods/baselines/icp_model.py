"""The ICP baseline's model: the class's mean object at its configurations as clouds, and the
registration of one observation to them (yaw hypotheses, successive halving, trimmed
point-to-point ICP).  The method is described in :mod:`.icp`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articulated_dataset.core.camera import backproject
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.rotations import matrix_to_quat
from articulated_dataset.format import MASK_BACKGROUND
from articulated_dataset.methods.baselines.clouds import (
    cloud_with_normals,
    kabsch,
    rotation_about_axis,
    rotation_angle_rad,
    stride_subsample,
)
from articulated_dataset.methods.baselines.common import SplitInfo, usable_depth

#: Initial yaw hypotheses per model image, evenly spread over the class's yaw range.
N_YAW_HYPOTHESES = 16
#: Most points kept per mean-model image (uniform pixel stride).
MODEL_POINTS = 2000


@dataclass(frozen=True)
class Stage:
    """One round of successive halving: observation points, ICP iterations (or the most
    iterations, with ``converge``), hypotheses kept for the next round."""

    points: int
    iterations: int
    keep: int
    converge: bool = False
    max_distance_m: float = np.inf  # correspondences farther than this are dropped (and not searched for)


#: 256 hypotheses -> 32 -> 4 -> 1 (see the module docstring).
STAGES = (
    Stage(points=24, iterations=4, keep=32, max_distance_m=0.3),
    Stage(points=96, iterations=6, keep=4, max_distance_m=0.15),
    Stage(points=384, iterations=20, keep=1, converge=True, max_distance_m=0.1),
)
#: Fraction of closest correspondences that enter each update (trimmed ICP).
TRIM_FRACTION = 0.8
#: Correspondences closer than this are inliers of the fit score (m): ~2 pixels at 1.5 m.
INLIER_DISTANCE_M = 0.03
#: Convergence: centroid motion (m) and rotation (rad) of one update below these.
CONVERGED_TRANSLATION_M = 1e-5
CONVERGED_ROTATION_RAD = 1e-5
#: Model clouds are moved this far apart along x in the shared KD-tree (m); scenes span < 20 m.
MODEL_SPACING_M = 1000.0
#: Test images per task of the worker pool.
TASK_IMAGES = 64
#: Fewer object pixels than this cannot be registered (6 constrain a rigid transform);
#: such an image gets the first mean-model image's labels unchanged.
MIN_OBSERVATION_POINTS = 6


@dataclass
class IcpFit:
    """Best registration of one observation: model image, transform (obs -> model), score."""

    model_index: int
    rotation: np.ndarray  # (3, 3)
    translation_m: np.ndarray  # (3,)
    score: float
    inlier_fraction: float
    rms_m: float


class MeanObjectModel:
    """The mean object's point clouds and labels, and the registration of observations to it."""

    def __init__(self, clouds: list[np.ndarray], normals: list[np.ndarray], labels: dict, base_centre_m: np.ndarray,
                 up: np.ndarray, yaw_range_rad: tuple[float, float], *, n_yaw: int = N_YAW_HYPOTHESES,
                 stages: tuple[Stage, ...] = STAGES):
        from articulated_dataset.core.errors import import_optional

        cKDTree = import_optional("scipy.spatial", "the ICP baseline").cKDTree

        if not clouds or any(len(c) == 0 for c in clouds) or len(normals) != len(clouds):
            raise ValueError("every mean-model image needs points with normals")
        self.clouds = [np.asarray(c, np.float64) for c in clouds]
        self.labels = {k: np.asarray(v) for k, v in labels.items()}
        self.base_centre_m = np.asarray(base_centre_m, np.float64)
        self.up = np.asarray(up, np.float64) / np.linalg.norm(up)
        self.yaws_rad = np.linspace(yaw_range_rad[0], yaw_range_rad[1], n_yaw)
        self.stages = tuple(stages)
        self.centroids = np.stack([c.mean(axis=0) for c in self.clouds])
        self.offsets = np.zeros((len(self.clouds), 3))
        self.offsets[:, 0] = MODEL_SPACING_M * np.arange(len(self.clouds))
        self.points = np.concatenate([c + o for c, o in zip(self.clouds, self.offsets)])
        self.normals = np.concatenate([np.asarray(n, np.float64) for n in normals])
        self.point_model = np.concatenate([np.full(len(c), m) for m, c in enumerate(self.clouds)])
        self.tree = cKDTree(self.points)
        # hypotheses: (model image, yaw) pairs, model-major
        self.hyp_model = np.repeat(np.arange(len(self.clouds)), len(self.yaws_rad))
        self.hyp_yaw = np.tile(self.yaws_rad, len(self.clouds))

    @property
    def n_models(self) -> int:
        """Number of model point clouds."""
        return len(self.clouds)

    @classmethod
    def from_split(cls, mean: SplitInfo, yaw_range_rad: tuple[float, float], *, model_points: int = MODEL_POINTS,
                   **kwargs) -> "MeanObjectModel":
        """Build the model from a mean-object split folder (all its images)."""
        from articulated_dataset.benchmark.metrics import quat_axis_z

        clouds: list[np.ndarray] = []
        normals: list[np.ndarray] = []
        for sh in mean.shards:
            K = sh.K
            for d, mk in zip(sh.read("depth"), sh.read("mask")):
                p, n = cloud_with_normals(d, K, mk != MASK_BACKGROUND)
                if len(p) == 0:  # (else a ValueError from __init__: a traceback)
                    raise UserError(f"mean-object split {mean.path}: image {len(clouds)} has no object pixel with a "
                                    f"usable depth and normal (a damaged mean object? 'artdata verify'; render it again "
                                    f"with 'artdata generate {option('class_name')} C {option('mean')}')")
                idx = stride_subsample(np.arange(len(p)), model_points)
                clouds.append(p[idx])
                normals.append(n[idx])
        labels = {k: mean.read(k) for k in ("axis_pose", "q", "geometry", "part_offset")}
        pose = mean.read("object_pose")[0].astype(np.float64)
        return cls(clouds, normals, labels, pose[:3], quat_axis_z(pose[3:]), yaw_range_rad, **kwargs)

    # ----------------------------------------------------------------------------------
    def _correspond(self, obs: np.ndarray, rot: np.ndarray, t: np.ndarray, models: np.ndarray,
                    max_distance_m: float = np.inf):
        """Transformed observation points ``(H, N, 3)``, nearest model points and normals, distances
        (``inf`` where no model point is within ``max_distance_m``)."""
        moved = np.einsum("hij,nj->hni", rot, obs) + t[:, None, :]
        query = moved + self.offsets[models][:, None, :]
        dist, idx = self.tree.query(query.reshape(-1, 3), distance_upper_bound=max_distance_m)
        dist = dist.reshape(len(models), len(obs))
        idx = np.minimum(idx.reshape(len(models), len(obs)), len(self.points) - 1)  # n = "none found"
        dist[self.point_model[idx] != models[:, None]] = np.inf  # another model's point: impossible by spacing
        target = self.points[idx] - self.offsets[models][:, None, :]
        return moved, target, self.normals[idx], dist

    def _iterate(self, obs, rot, t, models, n_iter: int, converge: bool, max_distance_m: float = np.inf):
        """Up to ``n_iter`` trimmed point-to-point ICP updates of every hypothesis (in place)."""
        active = np.ones(len(models), bool)
        n_keep = min(len(obs), max(3, int(round(TRIM_FRACTION * len(obs)))))
        centroid = obs.mean(axis=0)
        for _ in range(n_iter):
            ia = np.nonzero(active)[0]
            moved, target, _, dist = self._correspond(obs, rot[ia], t[ia], models[ia], max_distance_m)
            order = np.argpartition(dist, n_keep - 1, axis=1)[:, :n_keep]
            w = np.zeros(dist.shape)
            np.put_along_axis(w, order, 1.0, axis=1)
            w[~np.isfinite(dist)] = 0.0
            stuck = w.sum(axis=1) < 3  # no usable correspondences: leave the hypothesis where it is
            w[stuck] = 1.0
            new_rot, new_t = kabsch(np.broadcast_to(obs, moved.shape), target, w)
            moved_c = np.einsum("hij,j->hi", new_rot - rot[ia], centroid) + new_t - t[ia]
            step_rot = rotation_angle_rad(new_rot @ np.swapaxes(rot[ia], 1, 2))
            new_rot[stuck], new_t[stuck] = rot[ia][stuck], t[ia][stuck]
            rot[ia], t[ia] = new_rot, new_t
            if converge:
                still = (np.linalg.norm(moved_c, axis=1) >= CONVERGED_TRANSLATION_M) | (step_rot >= CONVERGED_ROTATION_RAD)
                active[ia[~still]] = False
                if not active.any():
                    break
        return rot, t

    def _score(self, obs, rot, t, models):
        """Truncated RMS residual (m), inlier fraction and inlier RMS (m) of each hypothesis.

        ``s = sqrt((1/N) sum_i rho_i)`` with ``rho_i = ((q_i - p_i) . n_i)^2`` (point-to-plane)
        for inliers (nearest model point within ``tau`` = :data:`INLIER_DISTANCE_M`) and
        ``rho_i = tau^2`` for outliers.
        """
        moved, target, normal, dist = self._correspond(obs, rot, t, models, INLIER_DISTANCE_M)
        inlier = dist < INLIER_DISTANCE_M
        resid2 = np.minimum(np.einsum("hnc,hnc->hn", target - moved, normal) ** 2, INLIER_DISTANCE_M**2)
        score = np.sqrt(np.where(inlier, resid2, INLIER_DISTANCE_M**2).mean(axis=1))
        n_in = inlier.sum(axis=1)
        rms = np.sqrt(np.where(inlier, resid2, 0.0).sum(axis=1) / np.maximum(n_in, 1))
        return score, inlier.mean(axis=1), rms

    def initial_poses(self, obs_centroid_m: np.ndarray, models: np.ndarray, yaws: np.ndarray):
        """Obs -> model transforms of the hypotheses: model yawed about its base axis, centroids met.

        Hypothesis ``o = R_up(theta)(x - c) + c + s`` for model points ``x``; the inverse maps
        observation points onto the model with ``R = R_up(theta)^T`` and ``t`` chosen so that
        the observation's centroid lands on the model's (``R`` about the origin: ``c`` and
        ``s`` only shift ``t``).
        """
        rot = np.swapaxes(rotation_about_axis(self.up, yaws), 1, 2)
        t = self.centroids[models] - np.einsum("hij,j->hi", rot, obs_centroid_m)
        return rot, t

    def register(self, observation_m: np.ndarray) -> IcpFit:
        """Best fit of an observation cloud ``(N, 3)`` (camera frame, m) over all hypotheses."""
        obs = np.asarray(observation_m, np.float64)
        if len(obs) < MIN_OBSERVATION_POINTS:
            raise ValueError(f"an observation needs at least {MIN_OBSERVATION_POINTS} points, got {len(obs)}")
        models = self.hyp_model
        rot, t = self.initial_poses(obs.mean(axis=0), models, self.hyp_yaw)
        for stage in self.stages:
            pts = stride_subsample(obs, stage.points)
            rot, t = self._iterate(pts, rot, t, models, stage.iterations, stage.converge, stage.max_distance_m)
            score, frac, rms = self._score(pts, rot, t, models)
            best = np.argsort(score, kind="stable")[: stage.keep]
            rot, t, models = rot[best], t[best], models[best]
            score, frac, rms = score[best], frac[best], rms[best]
        return IcpFit(int(models[0]), rot[0], t[0], float(score[0]), float(frac[0]), float(rms[0]))

    def predict_labels(self, fit: IcpFit) -> dict:
        """Labels implied by a fit: the model image's axis frames mapped into the observation."""
        from articulated_dataset.core.rotations import quat_to_matrix

        m = fit.model_index
        pose = self.labels["axis_pose"][m].astype(np.float64)  # (J, 7)
        rt = fit.rotation.T
        pos = (pose[:, :3] - fit.translation_m) @ rt.T
        rot_axis = rt[None] @ quat_to_matrix(pose[:, 3:])
        axis_pose = np.concatenate([pos, matrix_to_quat(rot_axis)], axis=1)
        return {
            "axis_pose": axis_pose,
            "q": self.labels["q"][m].astype(np.float64),
            "geometry": self.labels["geometry"][m].astype(np.float64),
            "part_offset": self.labels["part_offset"][m].astype(np.float64),
        }

    def predict_image(self, depth_m: np.ndarray, mask: np.ndarray, K: np.ndarray) -> tuple[dict, IcpFit | None]:
        """Labels for one depth image; an image without object pixels gets the mean model's first image.
        NaN, infinite, negative and absurd depths are no return (:func:`~.common.usable_depth`)."""
        obs = backproject(usable_depth(depth_m), K, mask != MASK_BACKGROUND)
        if len(obs) < MIN_OBSERVATION_POINTS:
            fit = None
            labels = {k: self.labels[k][0].astype(np.float64) for k in ("axis_pose", "q", "geometry", "part_offset")}
            return labels, fit
        fit = self.register(obs)
        return self.predict_labels(fit), fit
