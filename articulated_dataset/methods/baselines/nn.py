"""Nearest-neighbour baseline (paper, Table 1 "NN"): the closest training depth image's labels.

Feature of a depth image (:func:`depth_features`)
-------------------------------------------------
1. normalisation (``normalization``):

   * ``"metric"`` (default): the z-depth in metres as stored; pixels without a return keep 0.
     Absolute depth carries the object's distance, which the axis position needs.
   * ``"median"``: each image's valid pixels minus the median valid depth (so the feature
     only sees shape, not distance); pixels without a return are set to
     :data:`MEDIAN_BACKGROUND_M`.

2. area downsampling by an integer factor ``block_px`` (default 4: 192x108 -> 48x27): the
   mean of each ``block_px x block_px`` block (rows/columns beyond a multiple of
   ``block_px`` are cropped), computed in float64 and stored as float32.  The feature is
   the flattened float32 image, ``D = (H // b) (W // b)`` values.

Search (:class:`ExactNearestNeighbour`)
---------------------------------------
The neighbour of a query ``a`` is ``argmin_j ||a - x_j||^2`` over the training features
``x_j`` (float32), with ties broken by the lowest training index: exact, not approximate.
Brute force in blocks: after centring both sides on the training mean ``mu`` (smaller norms,
smaller rounding), a float32 GEMM gives

    d~_ij = ||a_i||^2 + ||x_j||^2 - 2 a_i . x_j

for a block of queries against a block of training images (twice the speed of float64).
Its rounding is bounded (Higham's dot-product bound):
``|d~ - d| <= delta_i = SAFETY (2 gamma_D |a_i| B + 6 u (|a_i| + B)^2)`` with ``u = 2^-24``,
``gamma_D = D u / (1 - D u)`` and ``B = max_j ||x_j - mu||``.  Every true nearest neighbour
therefore has ``d~_ij <= min_j d~_ij + 2 delta_i``, and a fortiori ``<=`` the running
minimum over the blocks seen so far ``+ 2 delta_i``.  Every pair passing that test is
re-ranked with the exact float64 distance of the float32 features, and the running exact
best is kept.  Usually a handful of pairs per query pass (near-duplicates pass together).
``benchmarks/baseline_speed.py`` times it (16,000 queries against 160,000 training images).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.pool import process_map
from articulated_dataset.methods.baselines.common import (
    BaselineResult,
    check_compatible,
    open_split_checked,
    read_train_labels,
    usable_depth,
)

log = logging.getLogger(__name__)

METHOD = "NN"
#: Area-downsampling factor (pixels per block side): 192x108 -> 48x27 = 1,296 values.
BLOCK_PX = 4
NORMALIZATIONS = ("metric", "median")
DEFAULT_NORMALIZATION = "metric"
#: Background value (m) of the "median" normalisation: behind every object surface (objects
#: are at most ~1.5 m deep around their median depth).
MEDIAN_BACKGROUND_M = 2.0
#: Queries and training images per GEMM block (a 1024 x 16384 float32 block is 64 MiB).
QUERY_CHUNK = 1024
TRAIN_CHUNK = 16384
#: Unit roundoff of float32 (2^-24) and a safety factor on the rounding-error bound.
FLOAT32_UNIT_ROUNDOFF = 2.0**-24
BOUND_SAFETY = 2.0
#: Relative round-up of the float32 candidate threshold (covers its own rounding).
THRESHOLD_ROUND_UP = 1e-6
#: (query, training image) pairs per exact float64 distance batch.
PAIR_CHUNK = 8192


# --------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------

def normalize_depth(depth_m: np.ndarray, normalization: str = DEFAULT_NORMALIZATION) -> np.ndarray:
    """Normalised depth images ``(N, H, W)`` float64 (see the module docstring); NaN, infinite,
    negative and absurd depths are no return (:func:`~.common.usable_depth`)."""
    d = np.asarray(usable_depth(depth_m), np.float64)
    if d.ndim == 2:
        d = d[None]
    if normalization == "metric":
        return d
    if normalization == "median":
        valid = d > 0
        out = np.full_like(d, MEDIAN_BACKGROUND_M)
        for i in range(len(d)):
            v = d[i][valid[i]]
            if v.size:
                out[i][valid[i]] = v - np.median(v)
        return out
    raise ValueError(f"unknown normalization {normalization!r}; choose from {NORMALIZATIONS}")


def area_downsample(images: np.ndarray, block_px: int = BLOCK_PX) -> np.ndarray:
    """Block means ``(N, H // b, W // b)`` of images ``(N, H, W)`` (``b = block_px``; edges cropped)."""
    images = np.asarray(images, np.float64)
    n, h, w = images.shape
    hb, wb = h // block_px, w // block_px
    if hb == 0 or wb == 0:
        raise ValueError(f"image {w}x{h} is smaller than one {block_px}x{block_px} block")
    cropped = images[:, : hb * block_px, : wb * block_px]
    return cropped.reshape(n, hb, block_px, wb, block_px).mean(axis=(2, 4))


def depth_features(depth_m: np.ndarray, block_px: int = BLOCK_PX, normalization: str = DEFAULT_NORMALIZATION) -> np.ndarray:
    """Feature vectors ``(N, D)`` float32 of depth images ``(N, H, W)`` (metres)."""
    small = area_downsample(normalize_depth(depth_m, normalization), block_px)
    return small.reshape(len(small), -1).astype(np.float32)


def _shard_features(args) -> np.ndarray:
    """Pool task: features of every image of one shard file."""
    from articulated_dataset.format import Shard

    path, block_px, normalization = args
    sh = Shard(path)
    try:
        return depth_features(sh.read("depth"), block_px, normalization)
    finally:
        sh.close()


def check_block(block_px: int, image_size: tuple[int, int], n_images: int) -> None:
    """``block_px`` must be a positive integer no larger than the images (``(H, W)`` px), and
    the features of ``n_images`` images (float32, plus the float64 block means of one shard)
    must fit in this machine's memory; otherwise a one-line :class:`UserError`."""
    from articulated_dataset.core.safeio import check_memory

    h, w = image_size
    if isinstance(block_px, bool) or not isinstance(block_px, int) or block_px <= 0:
        raise UserError(f"{option('block_px')} must be a positive whole number of pixels, got {block_px!r}")
    if block_px > min(h, w):
        raise UserError(f"{option('block_px')} {block_px} is larger than the {w}x{h} px images (at most {min(h, w)})")
    check_memory(float(n_images) * (h // block_px) * (w // block_px) * np.dtype(np.float32).itemsize,
                 f"NN features of {n_images} images at {option('block_px')} {block_px}")


def split_features(split, block_px: int = BLOCK_PX, normalization: str = DEFAULT_NORMALIZATION,
                   workers: int = 1, progress: bool = False) -> np.ndarray:
    """Features of every image of a split (:class:`~.common.SplitInfo`), in storage order."""
    from tqdm import tqdm

    tasks = [(str(sh.path), block_px, normalization) for sh in split.shards]
    bar = tqdm(total=len(tasks), unit="shard", desc=f"features {split.class_name}/{split.path.name}",
               disable=not progress, dynamic_ncols=True)
    try:
        if workers <= 1 or len(tasks) == 1:
            out = []
            for t in tasks:
                out.append(_shard_features(t))
                bar.update()
        else:
            out = []
            for f in process_map(_shard_features, tasks, min(workers, len(tasks)), ordered=True):
                out.append(f)
                bar.update()
    finally:
        bar.close()
    return np.concatenate(out, axis=0)


# --------------------------------------------------------------------------------------
# Exact search
# --------------------------------------------------------------------------------------

class ExactNearestNeighbour:
    """Exact L2 nearest neighbour of float32 feature vectors (see the module docstring)."""

    def __init__(self, train_features: np.ndarray, *, query_chunk: int = QUERY_CHUNK, train_chunk: int = TRAIN_CHUNK):
        x = np.ascontiguousarray(train_features, dtype=np.float32)
        if x.ndim != 2 or len(x) == 0:
            raise ValueError(f"training features must be a non-empty (M, D) array, got shape {x.shape}")
        self.x = x
        self.mu = x.mean(axis=0, dtype=np.float64)
        self.xc = (x - self.mu).astype(np.float32)
        xc64_norm2 = np.einsum("ij,ij->i", self.xc, self.xc, dtype=np.float64)
        self.norm2 = xc64_norm2.astype(np.float32)
        self.max_norm = float(np.sqrt(xc64_norm2.max()))
        self.query_chunk = int(query_chunk)
        self.train_chunk = int(train_chunk)
        self.n_reranked = 0  # (query, training image) pairs whose distance was recomputed exactly

    @property
    def dim(self) -> int:
        """Dimension D of the feature vectors."""
        return self.x.shape[1]

    def error_bound(self, query_norm: np.ndarray) -> np.ndarray:
        """Bound ``delta_i`` on ``|d~_ij - d_ij|`` for centred query norms ``|a_i|`` (module docstring)."""
        u = FLOAT32_UNIT_ROUNDOFF
        gamma = self.dim * u / (1.0 - self.dim * u)
        b = self.max_norm
        return BOUND_SAFETY * (2.0 * gamma * query_norm * b + 6.0 * u * (query_norm + b) ** 2)

    def pair_distances(self, query: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Exact squared distances (float64) between ``query[rows]`` and training rows ``cols``."""
        out = np.empty(len(rows))
        for s in range(0, len(rows), PAIR_CHUNK):
            diff = self.x[cols[s: s + PAIR_CHUNK]].astype(np.float64) - query[rows[s: s + PAIR_CHUNK]].astype(np.float64)
            out[s: s + PAIR_CHUNK] = np.einsum("ij,ij->i", diff, diff)
        return out

    def query(self, features: np.ndarray, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Nearest training index ``(Q,)`` int64 and its exact squared distance ``(Q,)`` float64."""
        from tqdm import tqdm

        feats = np.ascontiguousarray(features, dtype=np.float32)
        if feats.ndim != 2 or feats.shape[1] != self.dim:
            raise ValueError(f"query features must be (Q, {self.dim}), got {feats.shape}")
        out_i = np.empty(len(feats), np.int64)
        out_d = np.empty(len(feats), np.float64)
        for qs in tqdm(range(0, len(feats), self.query_chunk), desc="NN search", unit="chunk",
                       disable=not progress, dynamic_ncols=True):
            a = feats[qs: qs + self.query_chunk]
            nq = len(a)
            ac = (a - self.mu).astype(np.float32)
            a_norm2 = np.einsum("ij,ij->i", ac, ac, dtype=np.float64)
            margin = 2.0 * self.error_bound(np.sqrt(a_norm2))
            approx_best = np.full(nq, np.inf)
            best_i = np.full(nq, -1, np.int64)
            best_d = np.full(nq, np.inf)
            for ts in range(0, len(self.x), self.train_chunk):
                g = ac @ self.xc[ts: ts + self.train_chunk].T  # float32 GEMM
                g *= -2.0
                g += a_norm2.astype(np.float32)[:, None]
                g += self.norm2[None, ts: ts + self.train_chunk]
                approx_best = np.minimum(approx_best, g.min(axis=1))
                # every j with d~_ij <= min_j d~_ij + 2 delta_i may be the nearest: re-rank exactly
                threshold = ((approx_best + margin) * (1.0 + THRESHOLD_ROUND_UP)).astype(np.float32)
                rows, cols = np.nonzero(g <= threshold[:, None])
                self.n_reranked += len(rows)
                exact = self.pair_distances(a, rows, cols + ts)
                order = np.lexsort((cols, exact, rows))  # per query: smallest distance, then lowest index
                rows, cols, exact = rows[order], cols[order], exact[order]
                first = np.unique(rows, return_index=True)[1]
                r, c, d = rows[first], cols[first] + ts, exact[first]
                better = d < best_d[r]  # later blocks hold higher indices: ties keep the earlier one
                best_i[r[better]], best_d[r[better]] = c[better], d[better]
            out_i[qs: qs + nq] = best_i
            out_d[qs: qs + nq] = best_d
        return out_i, out_d


# --------------------------------------------------------------------------------------
# Baseline
# --------------------------------------------------------------------------------------

def predict(train_dir, test_dir, *, mean_dir=None, workers: int = 1, progress: bool = False, block_px: int = BLOCK_PX,
            normalization: str = DEFAULT_NORMALIZATION) -> BaselineResult:
    """NN predictions for every image of the test split: the labels of its nearest training image.

    ``workers`` processes compute the features (one shard per task); ``mean_dir`` is unused.
    """
    train = open_split_checked(train_dir, "train")
    test = open_split_checked(test_dir, "test")
    try:
        check_compatible(train, test, same_image_size=True)
        check_block(block_px, train.image_size, train.n_images + test.n_images)
        train_labels = read_train_labels(train)  # damaged labels: one line before the search, not after
        t0 = time.perf_counter()
        x_train = split_features(train, block_px, normalization, workers, progress)
        x_test = split_features(test, block_px, normalization, workers, progress)
        t_feat = time.perf_counter() - t0
        index = ExactNearestNeighbour(x_train)
        t0 = time.perf_counter()
        nearest, dist2 = index.query(x_test, progress=progress)
        t_search = time.perf_counter() - t0
        log.info("NN: %s, %d queries x %d training images (D = %d): features %.1f s, search %.1f s, %.1f exact "
                 "re-rankings per query", train.class_name, len(x_test), len(x_train), index.dim, t_feat, t_search,
                 index.n_reranked / max(len(x_test), 1))
        preds = {"sample_id": test.read("sample_id").astype(np.int64)}
        for name, labels in train_labels.items():
            preds[name] = labels[nearest]
        attrs = {"train_split": str(train.path), "n_train_images": len(x_train), "block_px": block_px,
                 "normalization": normalization, "feature_dim": index.dim,
                 "features_s": round(t_feat, 3), "search_s": round(t_search, 3), "exact_reranked_pairs": index.n_reranked}
        extra = {"nearest_index": nearest, "nearest_sqdist": dist2}  # training row of each test image
        return BaselineResult(METHOD, train.class_name, preds, attrs, extra)
    finally:
        train.close()
        test.close()
