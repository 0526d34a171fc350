"""Which triangles of an imported moving part are protrusions (handles, knobs) rather than its
panel: the labeller leaves them out of the part's extent and centre, as it leaves out the
``*_handle`` geoms of the built-in templates (:data:`articulated_dataset.generation.labels.HANDLE_SUFFIX`).

Third-party meshes carry no such names, so the processed model (:mod:`.process`) splits each
articulated link's geometry by shape, in the link's frame at q = 0 (every triangle weighted by
its area, placed at its centroid):

* **revolute part** (a door, a lid): the *panel* is the thinnest slab, perpendicular to the
  part's plane, that holds :data:`PANEL_AREA_FRACTION` of the part's area.  The part's
  triangles are projected onto the plane perpendicular to the joint axis; the slab's normal
  is the direction of least area-weighted spread there (refined once on the slab's own
  triangles).  A triangle whose centroid lies outside the slab (by more than
  :data:`SLAB_TOLERANCE` of the panel's width) is a protrusion: a handle stands off the
  door's face, a knob out of it.  A part that is not a panel (its slab thicker than
  :data:`MAX_PANEL_THICKNESS_RATIO` of its width) has no protrusions;
* **prismatic part** (a drawer): the *front* is the outermost plane, along the opening
  direction, of triangles facing that direction (within :data:`FACING_MAX_ANGLE_DEG`) that
  holds :data:`FRONT_MIN_AREA_FRACTION` of the part's area; triangles beyond it are protrusions.

A primitive (box, cylinder, sphere) is a protrusion as a whole when most of its area is.
"""

from __future__ import annotations

import math

import numpy as np

#: Share of a revolute part's area that its panel (the thinnest slab) holds: a door's two
#: faces hold nearly all of it, a handle or knob a few percent.
PANEL_AREA_FRACTION = 0.9
#: Thickest panel, relative to its width (the extent along the slab): thicker parts (a box-
#: shaped lid, a bin) are not panels and keep all their geometry.
MAX_PANEL_THICKNESS_RATIO = 0.25
#: Distance (relative to the panel's width, or the drawer's extent along its axis) a
#: triangle's centroid may lie outside the panel or beyond the front and still be part of it.
SLAB_TOLERANCE = 0.005
#: Largest angle (deg) between a triangle's normal and a drawer's opening direction for the
#: triangle to count as facing it (the front plane).
FACING_MAX_ANGLE_DEG = 10.0
#: Smallest share of a drawer's area its front plane holds (a handle's end faces hold less).
FRONT_MIN_AREA_FRACTION = 0.03
#: Share of a primitive's area that must protrude for the primitive to be a protrusion.
PRIMITIVE_PROTRUDING_FRACTION = 0.5


def _perpendicular_basis(axis: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors perpendicular to unit ``axis`` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(axis, e1)])


def _thinnest_interval(t: np.ndarray, w: np.ndarray, share: float) -> tuple[float, float]:
    """The shortest ``[t0, t1]`` holding at least ``share`` of the total weight ``w``."""
    order = np.argsort(t, kind="stable")
    ts, cum = t[order], np.concatenate([[0.0], np.cumsum(w[order])])
    need = share * cum[-1]
    # for each start i, the first end k (exclusive) with cum[k] - cum[i] >= need
    ends = np.searchsorted(cum, cum[:-1] + need, side="left")
    valid = ends <= len(ts)
    starts = np.nonzero(valid)[0]
    widths = ts[np.minimum(ends[starts], len(ts)) - 1] - ts[starts]
    best = int(starts[int(np.argmin(widths))])
    return float(ts[best]), float(ts[min(int(ends[best]), len(ts)) - 1])


def _revolute_protruding(centroids: np.ndarray, areas: np.ndarray, axis: np.ndarray) -> np.ndarray:
    xy = centroids @ _perpendicular_basis(axis).T  # (F, 2): projected along the axis
    inside = np.ones(len(areas), bool)
    for _ in range(2):  # the slab's normal from all triangles, then from the slab's own
        w = areas[inside]
        mean = (w[:, None] * xy[inside]).sum(0) / w.sum()
        d = xy[inside] - mean
        cov = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)
        _, vecs = np.linalg.eigh(cov)
        normal, along = vecs[:, 0], vecs[:, 1]
        t = xy @ normal
        t0, t1 = _thinnest_interval(t, areas, PANEL_AREA_FRACTION)
        s = xy @ along
        width = float(s[inside].max() - s[inside].min())
        tol = SLAB_TOLERANCE * width
        inside = (t >= t0 - tol) & (t <= t1 + tol)
    if width <= 0 or (t1 - t0) > MAX_PANEL_THICKNESS_RATIO * width:
        return np.zeros(len(areas), bool)
    return ~inside


def _prismatic_protruding(centroids: np.ndarray, areas: np.ndarray, normals: np.ndarray,
                          direction: np.ndarray) -> np.ndarray:
    t = centroids @ direction
    extent = float(t.max() - t.min())
    if extent <= 0:
        return np.zeros(len(areas), bool)
    tol = SLAB_TOLERANCE * extent
    facing = np.abs(normals @ direction) >= math.cos(math.radians(FACING_MAX_ANGLE_DEG))
    bins = np.floor((t - t.min()) / tol).astype(np.int64)
    per_bin = np.bincount(bins[facing], weights=areas[facing], minlength=int(bins.max()) + 2)
    plane = per_bin + np.concatenate([per_bin[1:], [0.0]])  # a plane may straddle two bins
    heavy = np.nonzero(plane >= FRONT_MIN_AREA_FRACTION * areas.sum())[0]
    if len(heavy) == 0:
        return np.zeros(len(areas), bool)
    front = t.min() + (int(heavy.max()) + 2) * tol  # the top of the front's two bins
    return t > front + tol


def protruding(pieces: list, axis, prismatic: bool) -> list:
    """For each piece of a moving link's geometry (trimesh meshes in the link frame at q = 0):
    a bool per triangle, True where it protrudes from the panel (see the module's rules).
    ``axis``: the joint's axis in the link frame (for a prismatic joint, its opening direction)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    sizes = [len(p.faces) for p in pieces]
    if sum(sizes) == 0:
        return [np.zeros(0, bool) for _ in pieces]
    centroids = np.concatenate([np.asarray(p.triangles_center, float) for p in pieces])
    areas = np.concatenate([np.asarray(p.area_faces, float) for p in pieces])
    if not areas.sum() > 0:
        return [np.zeros(n, bool) for n in sizes]
    if prismatic:
        normals = np.concatenate([np.asarray(p.face_normals, float) for p in pieces])
        out = _prismatic_protruding(centroids, areas, normals, a)
    else:
        out = _revolute_protruding(centroids, areas, a)
    return np.split(out, np.cumsum(sizes)[:-1])


def primitive_protrudes(mask: np.ndarray, piece) -> bool:
    """Whether a primitive (as a trimesh) protrudes as a whole, given its triangles' ``mask``."""
    areas = np.asarray(piece.area_faces, float)
    return bool(areas.sum() > 0 and areas[mask].sum() > PRIMITIVE_PROTRUDING_FRACTION * areas.sum())
