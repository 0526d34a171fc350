"""ICP baseline (paper, Table 1 "ICP"): register each test view to the class's mean object.

Model
-----
The class's mean object (``artdata generate --class C --mean``: every geometry and pose
parameter at the centre of its range) rendered at its 16 configurations.  Each image is
back-projected (pixels with mask > 0, the shard's K) to an organised camera-frame point
cloud; each point gets the unit normal ``n = (P[v, u+1] - P[v, u-1]) x (P[v+1, u] - P[v-1, u])``
of its pixel neighbourhood, turned towards the camera.  Points whose four neighbours are not
all object pixels within :data:`NORMAL_MAX_DEPTH_JUMP_M` in depth (silhouette and part edges)
have no reliable normal and are dropped; the rest is thinned to at most
:data:`MODEL_POINTS` points by a uniform stride over the pixels.

Registration of one test image
------------------------------
The observation ``O`` (back-projected like the model) is registered to every model cloud
``M_m`` from :data:`N_YAW_HYPOTHESES` initial poses each: the model rotated by ``theta_k``
(evenly spread over the class's yaw range, [-pi/4, pi/4] for every built-in class) about
the vertical axis through the mean object's base centre, then translated so that its
centroid meets the observation's.  Point-to-point ICP (Besl & McKay 1992) estimates the
rigid 6-DoF transform ``T(p) = R p + t`` taking observation points onto the model:

1. correspondences: each transformed observation point's nearest model point
   (``scipy.spatial.cKDTree``; all model clouds share one tree, each moved
   :data:`MODEL_SPACING_M` apart so that a hypothesis only ever matches its own model),
   searched within the stage's ``max_distance_m`` (farther points have none);
2. trimming: only the :data:`TRIM_FRACTION` closest correspondences enter the update
   (trimmed ICP, Chetverikov et al. 2002: the two views overlap only partly);
3. update: the least-squares rigid transform of the kept pairs (:func:`kabsch`);
4. convergence rule: a hypothesis stops when one update moves the observation's centroid by
   less than :data:`CONVERGED_TRANSLATION_M` and rotates it by less than
   :data:`CONVERGED_ROTATION_RAD`, or when the stage's iteration budget is spent.

(Point-to-plane ICP converges in fewer iterations but slides freely when a single plane
fills the view -- the closed door of a cabinet -- so it is not used.)

Successive halving over the ``16 x 16 = 256`` hypotheses (:data:`STAGES`): each stage
runs its iterations on its number of observation points (uniform stride over the pixels),
scores every hypothesis and passes the best ``keep`` on; the last stage iterates to
convergence (at most 20 iterations).

Fit score (lower is better), a truncated RMS residual:
``s = sqrt((1/N) sum_i min(r_i^2, tau^2))`` where ``r_i = (q_i - p_i) . n_i`` is the
point-to-plane residual of observation point ``i`` against its nearest model point ``q_i``
(normal ``n_i``) if that point is within ``tau`` = :data:`INLIER_DISTANCE_M`, else
``r_i = tau``.  It is the inlier RMS and the inlier fraction in one number: every outlier
costs ``tau^2``, so a fit that explains part of the view very well (a door matched with
the body left over) loses to one that explains all of it.  (The plain ratio
"inlier RMS / inlier fraction" preferred such partial fits in our tests.)

Prediction: for the best hypothesis (model image ``m``, transform ``T``), the mean model's
axis frames mapped into the observation, ``p = R^T (p_m - t)``, ``R_axis = R^T R_axis,m``;
``q`` = the configuration of model image ``m``; geometry and part offset = the mean
object's.  ICP finds a 6-DoF transform; the scorer compares rotations about z only, as in
the paper.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..camera import backproject
from ..executors import process_map
from ..format import MASK_BACKGROUND
from ..rotations import matrix_to_quat
from .common import BaselineResult, SplitInfo, check_compatible, open_split_checked

log = logging.getLogger(__name__)

METHOD = "ICP"
#: Initial yaw hypotheses per model image, evenly spread over the class's yaw range.
N_YAW_HYPOTHESES = 16
#: Most points kept per mean-model image (uniform pixel stride).
MODEL_POINTS = 2000
#: A pixel's normal is used only if its 4 neighbours are within this depth of it (m).
NORMAL_MAX_DEPTH_JUMP_M = 0.05


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


def stride_subsample(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` rows of ``points``, evenly spaced in storage (pixel) order; deterministic."""
    if len(points) <= n:
        return points
    idx = np.linspace(0, len(points) - 1, n).round().astype(np.int64)
    return points[idx]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    v = np.asarray(v, np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
        np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
        np.stack([-v[..., 1], v[..., 0], z], axis=-1),
    ], axis=-2)


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """``exp([w]x)`` ``(..., 3, 3)`` of rotation vectors ``w (..., 3)`` (rad): Rodrigues' formula
    ``I + sin(a) [k]x + (1 - cos(a)) [k]x^2`` with ``a = |w|``, ``k = w / a``."""
    w = np.asarray(w, np.float64)
    a = np.linalg.norm(w, axis=-1)
    k = w / np.where(a > 0, a, 1.0)[..., None]
    kx = skew(k)
    a = a[..., None, None]
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)


def rotation_about_axis(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` by ``angle_rad`` about the ``axis`` (normalised here)."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return rotation_from_vector(np.asarray(angle_rad, np.float64)[..., None] * k)


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transforms, batched: ``argmin_{R,t} sum_i w_i ||R s_i + t - d_i||^2``.

    ``src``/``dst`` ``(H, N, 3)``, ``weights`` ``(H, N)`` >= 0 (each row with a positive sum).
    ``R = V diag(1, 1, det(V U^T)) U^T`` from the SVD ``U S V^T`` of the weighted
    cross-covariance ``sum_i w_i (s_i - s_bar)(d_i - d_bar)^T`` (Umeyama 1991);
    ``t = d_bar - R s_bar``.  Returns ``R (H, 3, 3)``, ``t (H, 3)``.
    """
    w = weights / np.maximum(weights.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    s_bar = np.einsum("hn,hnc->hc", w, src)
    d_bar = np.einsum("hn,hnc->hc", w, dst)
    cov = np.einsum("hn,hni,hnj->hij", w, src - s_bar[:, None], dst - d_bar[:, None])
    u, _, vt = np.linalg.svd(cov)
    v = np.swapaxes(vt, 1, 2)
    ut = np.swapaxes(u, 1, 2)
    fix = np.ones((len(w), 3))
    fix[:, 2] = np.where(np.linalg.det(v @ ut) < 0, -1.0, 1.0)
    rot = (v * fix[:, None, :]) @ ut
    t = d_bar - np.einsum("hij,hj->hi", rot, s_bar)
    return rot, t


def rotation_angle_rad(rot: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices ``(..., 3, 3)``: ``acos((trace - 1) / 2)``, clipped."""
    tr = np.trace(rot, axis1=-2, axis2=-1)
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def organised_cloud(depth_m: np.ndarray, K: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(H, W, 3)`` of the ``valid`` pixels (0 elsewhere), via :func:`backproject`."""
    valid = np.asarray(valid, bool) & (np.asarray(depth_m) > 0)
    grid = np.zeros(depth_m.shape + (3,))
    v, u = np.nonzero(valid)
    grid[v, u] = backproject(depth_m, K, valid)  # same row-major pixel order as np.nonzero
    return grid


def cloud_with_normals(depth_m: np.ndarray, K: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` and unit normals ``(N, 3)`` (towards the camera) of the pixels with a
    reliable normal (see the module docstring), in row-major pixel order."""
    valid = np.asarray(valid, bool) & (np.asarray(depth_m) > 0)
    p = organised_cloud(depth_m, K, valid)
    z = np.asarray(depth_m, np.float64)
    ok = np.zeros_like(valid)
    inner = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    zc = z[1:-1, 1:-1]
    for zn in (z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]):
        inner &= np.abs(zn - zc) < NORMAL_MAX_DEPTH_JUMP_M
    ok[1:-1, 1:-1] = inner
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    n = np.zeros_like(p)
    n[1:-1, 1:-1] = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    flip = np.einsum("hwc,hwc->hw", n, p) > 0  # the camera is at the origin
    n[flip] *= -1.0
    return p[ok], n[ok]


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
        from ..errors import import_optional

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
        return len(self.clouds)

    @classmethod
    def from_split(cls, mean: SplitInfo, yaw_range_rad: tuple[float, float], *, model_points: int = MODEL_POINTS,
                   **kwargs) -> "MeanObjectModel":
        """Build the model from a mean-object split folder (all its images)."""
        from ..benchmark.metrics import quat_axis_z

        clouds, normals = [], []
        for sh in mean.shards:
            K = sh.K
            for d, mk in zip(sh.read("depth"), sh.read("mask")):
                p, n = cloud_with_normals(d, K, mk != MASK_BACKGROUND)
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
        from ..rotations import quat_to_matrix

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
        """Labels for one depth image; an image without object pixels gets the mean model's first image."""
        obs = backproject(depth_m, K, mask != MASK_BACKGROUND)
        if len(obs) < MIN_OBSERVATION_POINTS:
            fit = None
            labels = {k: self.labels[k][0].astype(np.float64) for k in ("axis_pose", "q", "geometry", "part_offset")}
            return labels, fit
        fit = self.register(obs)
        return self.predict_labels(fit), fit


# --------------------------------------------------------------------------------------
# Running over a split (optionally in a spawned process pool)
# --------------------------------------------------------------------------------------

_WORKER_MODEL: MeanObjectModel | None = None


def _init_worker(mean_dir: str, yaw_range_rad) -> None:
    global _WORKER_MODEL
    mean = open_split_checked(mean_dir, "mean-object")
    try:
        _WORKER_MODEL = MeanObjectModel.from_split(mean, tuple(yaw_range_rad))
    finally:
        mean.close()


def _run_task(task) -> tuple[int, dict]:
    """Pool task: predictions for images [start, stop) of one shard; returns (global offset, arrays)."""
    from ..format import Shard

    offset, path, start, stop = task
    sh = Shard(path)
    try:
        depth, mask, K = sh.read("depth", slice(start, stop)), sh.read("mask", slice(start, stop)), sh.K
    finally:
        sh.close()
    return offset, _predict_arrays(_WORKER_MODEL, depth, mask, K)


def _predict_arrays(model: MeanObjectModel, depth, mask, K) -> dict:
    out = {k: [] for k in ("axis_pose", "q", "geometry", "part_offset", "score", "model_index")}
    for d, mk in zip(depth, mask):
        labels, fit = model.predict_image(d, mk, K)
        for k, v in labels.items():
            out[k].append(v)
        out["score"].append(np.inf if fit is None else fit.score)
        out["model_index"].append(-1 if fit is None else fit.model_index)
    return {k: np.asarray(v) for k, v in out.items()}


def predict(train_dir, test_dir, *, mean_dir=None, workers: int = 1, progress: bool = False,
            limit: int | None = None) -> BaselineResult:
    """ICP predictions for every image of the test split (the first ``limit`` images if given).

    ``train_dir`` supplies the class's yaw range (its sampling table) and the class check;
    ``mean_dir`` is the class's mean-object split (found or rendered by
    :func:`ensure_mean_object` when None); ``workers`` processes share the test images.
    """
    from tqdm import tqdm

    global _WORKER_MODEL
    mean_dir = ensure_mean_object(train_dir, mean_dir, workers=workers)
    train = open_split_checked(train_dir, "train")
    test = open_split_checked(test_dir, "test")
    mean = open_split_checked(mean_dir, "mean-object")
    try:
        check_compatible(train, test)
        check_compatible(train, mean)
        yaw_range = train.yaw_range_rad
        tasks, offset = [], 0
        n_total = test.n_images if limit is None else min(limit, test.n_images)
        for sh in test.shards:
            n = len(sh)
            for s in range(0, n, TASK_IMAGES):
                e = min(s + TASK_IMAGES, n)
                if offset >= n_total:
                    break
                e = min(e, s + n_total - offset)
                tasks.append((offset, str(sh.path), s, e))
                offset += e - s
        sample_id = test.read("sample_id")[:n_total].astype(np.int64)
        results: dict[int, dict] = {}
        t0 = time.perf_counter()
        bar = tqdm(total=n_total, unit="img", desc=f"ICP {test.class_name}", disable=not progress, dynamic_ncols=True)
        try:
            if workers <= 1 or len(tasks) <= 1:
                _init_worker(str(mean.path), yaw_range)
                for task in tasks:
                    off, arrays = _run_task(task)
                    results[off] = arrays
                    bar.update(len(arrays["q"]))
            else:
                for off, arrays in process_map(_run_task, tasks, min(workers, len(tasks)), initializer=_init_worker,
                                               initargs=(str(mean.path), yaw_range)):
                    results[off] = arrays
                    bar.update(len(arrays["q"]))
        finally:
            bar.close()
            _WORKER_MODEL = None
        seconds = time.perf_counter() - t0
        merged = {k: np.concatenate([results[o][k] for o in sorted(results)]) for k in results[min(results)]}
        preds = {"sample_id": sample_id}
        for k in ("axis_pose", "q", "geometry", "part_offset"):
            preds[k] = merged[k].astype(np.float32)
        log.info("ICP: %s, %d test images in %.1f s (%.1f ms/image, %d workers)", test.class_name, n_total, seconds,
                 1e3 * seconds / max(n_total, 1), workers)
        attrs = {"mean_object_split": str(mean.path), "n_yaw_hypotheses": N_YAW_HYPOTHESES,
                 "stages": [(st.points, st.iterations, st.keep) for st in STAGES], "trim_fraction": TRIM_FRACTION,
                 "inlier_distance_m": INLIER_DISTANCE_M, "seconds": round(seconds, 3), "workers": workers}
        extra = {"score": merged["score"], "model_index": merged["model_index"], "seconds": seconds}
        return BaselineResult(METHOD, test.class_name, preds, attrs, extra)
    finally:
        train.close()
        test.close()
        mean.close()


# --------------------------------------------------------------------------------------
# The mean object: found next to the training data, or rendered once into a cache
# --------------------------------------------------------------------------------------

#: Cache folder (next to the training split) where a missing mean object is rendered.
MEAN_CACHE_DIR = ".mean-object"


def default_mean_dir(train_dir) -> Path:
    """Where ``artdata generate --mean`` puts the class's mean object for ``OUT/<class>/train``: ``OUT/<class>/mean``."""
    return Path(train_dir).parent / "mean"


def ensure_mean_object(train_dir, mean_dir=None, *, workers: int = 1) -> Path:
    """The mean-object split folder for the training split at ``train_dir``.

    ``mean_dir`` if given (it must exist); else ``OUT/<class>/mean`` next to the training
    split if it holds the same class; else the mean object is rendered once (noise-free,
    with the training split's camera and sampling table) into
    ``<train_dir>/../.mean-object/<class>/mean`` and reused from there.
    """
    from ..format import MANIFEST_NAME, read_manifest
    from ..pipeline import GenerationConfig, generate_split, split_dir_for

    train = open_split_checked(train_dir, "train")
    try:
        class_name = train.class_name
        config = train.config
    finally:
        train.close()
    if mean_dir is not None:
        return Path(mean_dir)
    sibling = default_mean_dir(train_dir)
    if (sibling / MANIFEST_NAME).is_file() and read_manifest(sibling).get("class_name") == class_name:
        return sibling
    cfg = replace(GenerationConfig.from_dict(config.to_dict()), mean=True, n_objects=1, noise="none")
    cache_root = Path(train_dir).parent / MEAN_CACHE_DIR
    target = split_dir_for(cache_root, cfg)
    if (target / MANIFEST_NAME).is_file() and read_manifest(target).get("complete"):
        return target
    log.warning("ICP: no mean object of %s next to %s; rendering it once into %s", class_name, train_dir, target)
    return generate_split(cfg, cache_root, workers=workers, overwrite=True)
