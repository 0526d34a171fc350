"""The scene around an object in one depth image: the large planes it stands on or against (floor,
walls, counter tops) and the depth-continuous regions of what is left.

A prompt's segmentation (:mod:`articulated_dataset.methods.prompts`) removes the scene's planes
before it joins pixels, so a fill from a click no longer runs from the object onto the counter it
stands on, and an object can be found without a prompt: the largest region left that is the size
of the class's objects (:func:`object_regions`).  Rules and limits: docs/robot_view.md.
"""

from __future__ import annotations

import numpy as np

#: A pixel lies on a plane when its distance to it is below this (m) ...
PLANE_TOL_ABS_M = 0.006
#: ... plus this fraction of its depth (sensor noise grows with distance).
PLANE_TOL_REL = 0.005
#: A plane's own noise (a depth sensor's) widens its tolerance to this many standard deviations
#: of its pixels' distances to it, estimated robustly (:data:`ROBUST_SIGMA` x their median) among
#: the pixels within :data:`PLANE_NOISE_WINDOW` tolerances of it.
PLANE_NOISE_FACTOR = 3.0
PLANE_NOISE_WINDOW = 4.0
#: The standard deviation of a normal distribution over the median of its absolute values.
ROBUST_SIGMA = 1.4826
#: Most planes drawn from one image (largest first).
MAX_PLANES = 6
#: Points of the image a plane is searched among (drawn at random, every valid pixel is scored after).
PLANE_SAMPLE_POINTS = 1000
#: Planes tried per plane found, each through a sampled pixel and its two neighbours
#: :data:`TRIPLE_STEP_FRACTION` of the image's shorter side away (right and down).
PLANE_HYPOTHESES = 64
#: See :data:`PLANE_HYPOTHESES`: far enough apart that sensor noise barely tilts the plane, near
#: enough that the three pixels mostly lie on one surface.
TRIPLE_STEP_FRACTION = 0.05
#: A plane holding fewer than this fraction of the sampled points ends the search.
MIN_PLANE_FRACTION = 0.02
#: A connected piece of a plane spanning more than the class's largest size times this is the
#: scene (a wall, the floor, a counter top), not a face of the object.
SCENE_SPAN_FACTOR = 1.1
#: Strips of a scene's plane narrower than this fraction of the image's shorter side (a
#: counter's front edge) are cut before the faces of objects flush with it are told apart.
STRIP_WIDTH_FRACTION = 0.04
#: Fewest pixels of a piece of a plane that is judged (smaller pieces stay as they are).
MIN_PIECE_PX = 20
#: Pieces of an object apart in the image (an open door beside its body) are joined when their
#: 3-D points come this close (m) ...
JOIN_DISTANCE_M = 0.03
#: ... plus this many pixels' width at the region's median depth (the surface near a hinge is
#: seen by few pixels).
JOIN_PIXELS = 6
#: ... or this fraction of the class's largest size, whichever is larger (the part of a door
#: near its hinge is often hidden by the door itself).
JOIN_EXTENT_FRACTION = 0.25
#: Points of a region a join is measured from, at most (drawn evenly).
JOIN_SAMPLE_POINTS = 4000
#: Seed of the generator :func:`scene_planes` draws with when none is given: the same image
#: always gives the same planes.
PLANE_SEED = 20191003


def depth_step_tolerance_m(depth_a: np.ndarray, depth_b: np.ndarray, abs_m: float, rel: float) -> np.ndarray:
    """The largest depth difference (m) of neighbouring pixels on one surface: ``abs_m`` plus
    ``rel`` times the nearer depth (a surface seen at a slant steps further between pixels the
    further away it is)."""
    return abs_m + rel * np.minimum(depth_a, depth_b)


def depth_components(depth: np.ndarray, allowed: np.ndarray, abs_m: float, rel: float) -> np.ndarray:
    """(H, W) int labels of the connected regions of ``allowed`` pixels, two 4-neighbours joined
    when their depths differ by less than :func:`depth_step_tolerance_m`; 0 outside ``allowed``,
    regions numbered from 1."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    h, w = depth.shape
    idx = np.arange(h * w).reshape(h, w)

    def edges(a, b, ok_a, ok_b, ia, ib):
        joined = ok_a & ok_b & (np.abs(a - b) < depth_step_tolerance_m(a, b, abs_m, rel))
        return ia[joined], ib[joined]

    r0, r1 = edges(depth[:, :-1], depth[:, 1:], allowed[:, :-1], allowed[:, 1:], idx[:, :-1], idx[:, 1:])
    d0, d1 = edges(depth[:-1], depth[1:], allowed[:-1], allowed[1:], idx[:-1], idx[1:])
    rows, cols = np.concatenate([r0, d0]), np.concatenate([r1, d1])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(h * w, h * w))
    _, comp = connected_components(graph, directed=False)
    comp = comp.reshape(h, w)
    # renumber: the allowed pixels' components from 1 in order of first appearance, 0 elsewhere
    labels = np.zeros((h, w), np.int64)
    if allowed.any():
        _, first, inverse = np.unique(comp[allowed], return_index=True, return_inverse=True)
        order = np.argsort(np.argsort(first))
        labels[allowed] = order[inverse] + 1
    return labels


def _plane_through(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (T, 3) and offsets (T,) of the planes through point triples ``p`` (T, 3, 3);
    degenerate triples get a zero normal."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    return n, -np.einsum("ij,ij->i", n, p[:, 0])


def _local_triples(points: np.ndarray, left: np.ndarray, flat: np.ndarray, step: int) -> np.ndarray:
    """(T, 3, 3): for each flat pixel index in ``flat``, its point and those ``step`` pixels to its
    right and below (or left and above at the image's edge); a triple with a pixel outside ``left``
    repeats its first point (a degenerate plane, never counted)."""
    h, w = left.shape
    r, c = np.divmod(flat, w)
    c2 = np.where(c + step < w, c + step, c - step).clip(0, w - 1)
    r2 = np.where(r + step < h, r + step, r - step).clip(0, h - 1)
    rows = np.stack([r, r, r2], 1)
    cols = np.stack([c, c2, c], 1)
    ok = left[rows, cols]
    rows = np.where(ok, rows, r[:, None])
    cols = np.where(ok, cols, c[:, None])
    return points[rows, cols]


def _in_plane_span_m(points: np.ndarray, normal: np.ndarray) -> float:
    """The largest extent (m) of ``points`` (N, 3) along the principal axes of their spread in the
    plane of ``normal`` (a rectangle's sides, not its diagonal)."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = np.stack([points @ a, points @ b], axis=1)
    axes = np.linalg.eigh(np.cov(uv, rowvar=False) if len(uv) > 1 else np.eye(2))[1]
    return float(np.ptp(uv @ axes, axis=0).max())


def _touches_border(mask: np.ndarray) -> bool:
    """Whether ``mask`` holds a pixel of the image's border."""
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def strip_radius_px(shape: tuple[int, ...]) -> int:
    """Half of :data:`STRIP_WIDTH_FRACTION` of an image's shorter side, in whole pixels (at least 1)."""
    return max(1, int(round(STRIP_WIDTH_FRACTION * min(shape[:2]) / 2)))


def without_strips(mask: np.ndarray) -> np.ndarray:
    """``mask`` opened (3x3, :func:`strip_radius_px` times): its strips narrower than
    :data:`STRIP_WIDTH_FRACTION` of the image's shorter side are gone."""
    from scipy import ndimage

    return ndimage.binary_opening(mask, structure=np.ones((3, 3), bool), iterations=strip_radius_px(mask.shape))


def _object_faces(plane: np.ndarray, points: np.ndarray, normal: np.ndarray, max_extent_m: float) -> np.ndarray:
    """The pixels of a scene's ``plane`` (H, W bool) that are faces of objects flush with it: the
    8-connected pieces left by an opening of :data:`STRIP_WIDTH_FRACTION` of the image's shorter
    side (which cuts the thin strips that join them, a counter's front edge flush with an object's
    front) that span at most :data:`SCENE_SPAN_FACTOR` x ``max_extent_m`` and do not touch the
    image's border (pieces of a wall or floor the objects cut apart do), grown back within the
    plane."""
    from scipy import ndimage

    radius = strip_radius_px(plane.shape)
    square = np.ones((3, 3), bool)
    parts, n_parts = ndimage.label(without_strips(plane), structure=square)
    faces = np.zeros_like(plane)
    for k in range(1, n_parts + 1):
        part = parts == k
        if not _touches_border(part) and part.sum() >= MIN_PIECE_PX and \
                _in_plane_span_m(points[part], normal) <= SCENE_SPAN_FACTOR * max_extent_m:
            faces |= part
    return ndimage.binary_dilation(faces, structure=square, iterations=radius) & plane if faces.any() else faces


def scene_planes(points: np.ndarray, valid: np.ndarray, max_extent_m: float,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """(H, W) bool: the pixels on the scene's large planes, walls, floor and counter tops.

    Planes are found largest first (RANSAC: :data:`PLANE_HYPOTHESES` planes through three of
    :data:`PLANE_SAMPLE_POINTS` valid points, the one holding most of them refitted by least
    squares), at most :data:`MAX_PLANES`, until one holds fewer than :data:`MIN_PLANE_FRACTION`
    of the sample.  A pixel is on a plane within :data:`PLANE_TOL_ABS_M` + :data:`PLANE_TOL_REL`
    x depth.  A plane whose pixels (those in 8-connected pieces of at least :data:`MIN_PIECE_PX`)
    reach the image's border and span more than :data:`SCENE_SPAN_FACTOR` x ``max_extent_m`` in
    the plane is the scene (a wall is one plane even where the object splits it in two; the
    scene runs on beyond the view, an object seen whole does not), but for the faces of objects flush with
    it (:func:`_object_faces`); a smaller plane is a face of an object and stays.  ``points``: (H, W, 3) optical-frame points; ``valid``: the pixels
    with depth; ``rng``: the draws (default: seeded with :data:`PLANE_SEED`)."""
    from scipy import ndimage

    rng = np.random.default_rng(np.random.SeedSequence(PLANE_SEED)) if rng is None else rng
    scene = np.zeros(valid.shape, bool)
    left = valid.copy()
    tol = PLANE_TOL_ABS_M + PLANE_TOL_REL * points[..., 2]
    step = max(1, int(round(TRIPLE_STEP_FRACTION * min(valid.shape))))
    for _ in range(MAX_PLANES):
        flat = np.flatnonzero(left)
        if len(flat) < 3:
            break
        sample = flat if len(flat) <= PLANE_SAMPLE_POINTS else rng.choice(flat, PLANE_SAMPLE_POINTS, replace=False)
        p = points.reshape(-1, 3)[sample]
        t = tol.reshape(-1)[sample]
        n, d = _plane_through(_local_triples(points, left, rng.choice(sample, PLANE_HYPOTHESES), step))
        counts = ((np.abs(p @ n.T + d) < t[:, None]) & (np.abs(n).sum(1) > 0)).sum(0)
        best = int(np.argmax(counts))
        if counts[best] < MIN_PLANE_FRACTION * len(p):
            break
        inl = p[np.abs(p @ n[best] + d[best]) < t]
        centre = inl.mean(0)
        normal = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]
        dist = np.abs((points - centre) @ normal)
        close = left & (dist < PLANE_NOISE_WINDOW * tol)
        noise_m = ROBUST_SIGMA * float(np.median(dist[close])) if close.any() else 0.0
        on = left & (dist < np.maximum(tol, PLANE_NOISE_FACTOR * noise_m))
        left &= ~on
        pieces, n_pieces = ndimage.label(on, structure=np.ones((3, 3), bool))
        sizes = np.bincount(pieces.ravel(), minlength=n_pieces + 1)
        big = np.isin(pieces, 1 + np.nonzero(sizes[1:] >= MIN_PIECE_PX)[0])
        if big.any() and _touches_border(big) and _in_plane_span_m(points[big], normal) > SCENE_SPAN_FACTOR * max_extent_m:
            scene |= big & ~_object_faces(big, points, normal, max_extent_m)
    return scene


def _sampled(points: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of ``points`` (N, 3), evenly spaced in their order."""
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).astype(np.int64)]


def joined_by_proximity(region: np.ndarray, labels: np.ndarray, points: np.ndarray, focal_px: float,
                        max_extent_m: float) -> np.ndarray:
    """``region`` (H, W bool) with every region of ``labels`` (from :func:`depth_components`) that
    comes within reach of it in 3-D added, repeated until nothing more joins: an open door apart
    from its body in the image meets it at the hinge, or hides the hinge from the camera.  The
    reach (m) is the larger of :data:`JOIN_DISTANCE_M` + :data:`JOIN_PIXELS` pixel widths (median
    depth of ``region`` / ``focal_px``) and :data:`JOIN_EXTENT_FRACTION` x ``max_extent_m``."""
    from scipy.spatial import cKDTree

    pixel_reach_m = JOIN_DISTANCE_M + JOIN_PIXELS * float(np.median(points[region][:, 2])) / focal_px
    reach_m = max(pixel_reach_m, JOIN_EXTENT_FRACTION * max_extent_m)
    flat_labels, flat_points = labels.ravel(), points.reshape(-1, 3)
    out = region.ravel().copy()
    others = np.flatnonzero((flat_labels > 0) & ~out)
    frontier = out
    while len(others):  # each round: the regions within reach of the ones added last
        near = flat_points[frontier]
        lo, hi = near.min(0) - reach_m, near.max(0) + reach_m
        close = others[np.all((flat_points[others] >= lo) & (flat_points[others] <= hi), axis=1)]
        dist, _ = cKDTree(_sampled(near, JOIN_SAMPLE_POINTS)).query(flat_points[close], k=1,
                                                                     distance_upper_bound=reach_m)
        hit = np.unique(flat_labels[close[np.isfinite(dist)]])
        if not len(hit):
            break
        frontier = np.isin(flat_labels, hit)
        out |= frontier
        others = others[~frontier[others]]
    return out.reshape(region.shape)
