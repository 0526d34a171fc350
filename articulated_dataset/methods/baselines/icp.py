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

The clouds and rigid transforms are in :mod:`.clouds`, the model and the registration in
:mod:`.icp_model`; this module runs the baseline over a split and finds or renders the mean object.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import option
from articulated_dataset.core.pool import process_map
from articulated_dataset.methods.baselines.common import BaselineResult, check_compatible, open_split_checked
from articulated_dataset.methods.baselines.icp_model import (
    INLIER_DISTANCE_M,
    N_YAW_HYPOTHESES,
    STAGES,
    TASK_IMAGES,
    TRIM_FRACTION,
    MeanObjectModel,
)

log = logging.getLogger(__name__)


METHOD = "ICP"


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
    from articulated_dataset.format import Shard

    offset, path, start, stop = task
    sh = Shard(path)
    try:
        depth, mask, K = sh.read("depth", slice(start, stop)), sh.read("mask", slice(start, stop)), sh.K
    finally:
        sh.close()
    return offset, _predict_arrays(_WORKER_MODEL, depth, mask, K)  # type: ignore[arg-type]  # set by the initializer


def _predict_arrays(model: MeanObjectModel, depth, mask, K) -> dict:
    out: dict[str, list] = {k: [] for k in ("axis_pose", "q", "geometry", "part_offset", "score", "model_index")}
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
        # worker processes that run (not --workers: a number past int64 cannot be an HDF5 attribute)
        processes = min(workers, len(tasks)) if workers > 1 and len(tasks) > 1 else 1
        try:
            # built here first in any case: a damaged mean object is one line, not a worker that died
            _init_worker(str(mean.path), yaw_range)
            if processes == 1:
                for task in tasks:
                    off, arrays = _run_task(task)
                    results[off] = arrays
                    bar.update(len(arrays["q"]))
            else:
                for off, arrays in process_map(_run_task, tasks, processes, initializer=_init_worker,
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
                 1e3 * seconds / max(n_total, 1), processes)
        attrs = {"mean_object_split": str(mean.path), "n_yaw_hypotheses": N_YAW_HYPOTHESES,
                 "stages": [(st.points, st.iterations, st.keep) for st in STAGES], "trim_fraction": TRIM_FRACTION,
                 "inlier_distance_m": INLIER_DISTANCE_M, "seconds": round(seconds, 3), "workers": processes}
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
    from articulated_dataset.format import MANIFEST_NAME, read_manifest
    from articulated_dataset.generation import GenerationConfig, generate_split, split_dir_for

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
    from articulated_dataset.format.manifest import check_stored_object_files

    check_stored_object_files(config.to_dict(), train_dir, "the ICP baseline's mean object",
                              f" (render it with 'artdata generate {option('urdf_path')} FILE {option('mean')}' "
                              f"and pass {option('mean_dir')})")
    cfg = replace(GenerationConfig.from_dict(config.to_dict()), mean=True, n_objects=1, noise="none")
    cache_root = Path(train_dir).parent / MEAN_CACHE_DIR
    target = split_dir_for(cache_root, cfg)
    if (target / MANIFEST_NAME).is_file() and read_manifest(target).get("complete"):
        return target
    log.warning("ICP: no mean object of %s next to %s; rendering it once into %s", class_name, train_dir, target)
    return generate_split(cfg, cache_root, workers=workers, overwrite=True)
