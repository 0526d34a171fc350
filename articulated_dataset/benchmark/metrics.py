"""Benchmark metrics: pure, vectorised numpy functions.

Every function takes arrays with arbitrary leading dimensions (images, joints...) and
returns one value per element of those dimensions; none of them averages.  Averaging over
joints (2-DoF objects) and over images is done by :mod:`articulated_dataset.benchmark.scoring`.

Conventions (see docs/format.md and docs/scoring.md):

* positions in metres, in the camera frame (x forward, y left, z up);
* quaternions ``(w, x, y, z)`` of the axis frame, whose z column is the joint axis;
* configurations ``q`` in radians (revolute) or metres (prismatic);
* returned errors are in the units named by the function (``_cm``, ``_deg``).

The camera z axis (``up``) is the axis of the paper's "axis rotation error": headings are
angles about it (see :func:`axis_rotation_error_deg`, metric version :data:`METRIC_VERSION`).
"""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.rotations import quat_multiply, quat_to_matrix
from articulated_dataset.core.units import CM_PER_M, DEG_PER_RAD, normalise, point_line_distance_m

#: Version of the metric definitions, reported with every score (JSON ``metric_version``, CSV,
#: table); docs/scoring.md lists what each version changed.  ``artdata score --metric-version``
#: picks one of :data:`METRIC_VERSIONS`.
METRIC_VERSION = 3
#: Versions the scorer still computes (numbers of one version are comparable only with the same one).
METRIC_VERSIONS = (2, 3)
#: Accuracy thresholds of category-level articulation work: (direction deg, axis line distance cm).
ACCURACY_THRESHOLDS = ((5.0, 5.0), (10.0, 10.0))
#: OPD-style success thresholds (Jiang et al., "OPD", 2022): axis direction within 10 degrees ...
OPD_MAX_DIRECTION_ERROR_DEG = 10.0
#: ... and the predicted origin within 0.25 object diagonals of the true axis line.
OPD_MAX_ORIGIN_ERROR_DIAGONALS = 0.25
#: Below this value of |d1 x d2| (unit directions, = sin of their angle) two lines are treated as
#: parallel: the common-perpendicular formula divides by it and loses all precision.
PARALLEL_SIN_TOL = 1e-9
#: Chirality predictions are thresholded at 0.5 (a probability or a 0/1 label).
CHIRALITY_THRESHOLD = 0.5
#: A vector whose horizontal projection is shorter than this (unit vectors) has no heading.
HEADING_MIN_HORIZONTAL = 1e-9
#: Rotation error of a predicted axis-frame column with no heading (vertical): the worst case.
UNDEFINED_HEADING_ERROR_DEG = 180.0
#: Half a turn about the axis frame's own x axis, (w, x, y, z): reverses the joint axis and y.
HALF_TURN_X_QUAT = np.array([0.0, 1.0, 0.0, 0.0])
#: A part centre closer than this (m) to its axis line has no side (part offset along the axis).
MIN_PART_SIDE_M = 1e-6
#: Bisection steps of :func:`mixture_marginal_interval`; each halves the bracket (2**-60 of it left).
BISECTION_STEPS = 60


# --------------------------------------------------------------------------------------
# Quaternions and frames
# --------------------------------------------------------------------------------------

def quat_axis_z(q: np.ndarray) -> np.ndarray:
    """Third column of ``R(q)`` (the frame's z axis = the joint axis direction), ``(..., 3)``.

    ``z = (2(xz + wy), 2(yz - wx), 1 - 2(x^2 + y^2))`` for a unit quaternion.
    """
    w, x, y, z = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def quat_axis_x(q: np.ndarray) -> np.ndarray:
    """First column of ``R(q)`` (the frame's x axis), ``(..., 3)``.

    ``x = (1 - 2(y^2 + z^2), 2(xy + wz), 2(xz - wy))`` for a unit quaternion.
    """
    w, x, y, z = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=-1)


# --------------------------------------------------------------------------------------
# Paper metrics (Table 1 / Table 2)
# --------------------------------------------------------------------------------------

def axis_position_error_cm(origin_pred_m: np.ndarray, origin_true_m: np.ndarray) -> np.ndarray:
    """Axis position error ``e = 100 * ||o_pred - o_true||_2`` in cm (origins in metres, ``(..., 3)``)."""
    diff = np.asarray(origin_pred_m, np.float64) - np.asarray(origin_true_m, np.float64)
    return CM_PER_M * np.sqrt(np.einsum("...i,...i->...", diff, diff))


def heading_error_deg(v_pred: np.ndarray, v_true: np.ndarray) -> np.ndarray:
    """Heading difference (degrees, in ``[0, 180]``) about the camera z axis of two vectors ``(..., 3)``.

    The heading of ``v`` is the angle of its horizontal projection ``(v_x, v_y)``; the
    difference is ``|atan2(t_x p_y - t_y p_x, t_x p_x + t_y p_y)|`` (already wrapped, accurate
    at 0 and 180 degrees; lengths do not matter).  Where either projection is shorter than
    :data:`HEADING_MIN_HORIZONTAL` (a vertical vector: no heading) the error is
    :data:`UNDEFINED_HEADING_ERROR_DEG`, the worst case.  NaN input gives NaN.
    """
    p = np.asarray(v_pred, np.float64)
    t = np.asarray(v_true, np.float64)
    cross = t[..., 0] * p[..., 1] - t[..., 1] * p[..., 0]
    dot = t[..., 0] * p[..., 0] + t[..., 1] * p[..., 1]
    err = np.abs(np.arctan2(cross, dot)) * DEG_PER_RAD
    undefined = (np.hypot(p[..., 0], p[..., 1]) < HEADING_MIN_HORIZONTAL) | (np.hypot(t[..., 0], t[..., 1]) < HEADING_MIN_HORIZONTAL)
    return np.where(undefined, UNDEFINED_HEADING_ERROR_DEG, err)


def axis_rotation_error_deg(quat_pred: np.ndarray, quat_true: np.ndarray) -> np.ndarray:
    """Axis rotation error (paper's Table 1 column, metric version 2), degrees in ``[0, 180]``.

    ``e = max_{k in H} heading_error(R_pred e_k, R_true e_k)``: the largest heading difference
    about the camera z (up) axis of the axis-frame columns ``k`` in ``H``, the two columns of
    ``R_true`` that are most horizontal (all but the column with the largest ``|R_true[2, k]|``).
    For a side-hinged door (vertical joint axis) ``H = {x, y}``: x is the door's direction from
    the hinge, y its opening direction; for drawers and bottom-hinged doors (x vertical)
    ``H = {y, z}``.  Every truth column in ``H`` is at least 45 deg from vertical, so its
    heading is defined; a predicted column with no horizontal part scores 180
    (:func:`heading_error_deg`).  Quaternions ``(..., 4)`` (w, x, y, z).

    Properties: a prediction turned about the vertical by ``d`` scores ``|d|`` (the object's
    yaw error, as in the paper); a mirrored mechanism -- the truth turned half a turn about its
    own x or y axis (door on the other side of the hinge line, or opening the other way) --
    scores 180; any half-turn about a horizontal axis scores at least 90 when the truth has a
    vertical column (the heading errors of two perpendicular horizontal columns under such a
    half-turn are ``2a`` and ``180 - 2a``, so their maximum is at least 90).  Version 1
    (``|twist_z(R_pred R_true^T)|``) scored such half-turns 0, where the twist is undefined.
    Compare predictions in the truth's axis sign first (:func:`canonical_axis_sign`).
    """
    Rp, Rt = quat_to_matrix(quat_pred), quat_to_matrix(quat_true)
    err = heading_error_deg(np.swapaxes(Rp, -1, -2), np.swapaxes(Rt, -1, -2))  # (..., 3): one per column
    vertical = np.argmax(np.abs(Rt[..., 2, :]), axis=-1)
    dropped = np.arange(3) == vertical[..., None]
    return np.max(np.where(dropped, -np.inf, err), axis=-1)


def canonical_axis_sign(quat_pred: np.ndarray, q_pred: np.ndarray, quat_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A predicted joint re-expressed with the truth's axis sign where it is the same joint.

    A joint frame ``R`` at configuration ``q`` and ``(R R_x(pi), -q)`` (axis and y reversed,
    x kept) move the part identically: the same joint written with the other axis sign.  The
    label convention picks ``q >= 0`` opening; a prediction whose axis points against the
    truth's (``z_p . z_t < 0``) while its x keeps the truth's side (``x_p . x_t > 0``) and whose
    ``q < 0`` is that other writing, and is returned as ``(quat_pred * (0, 1, 0, 0), -q_pred)``;
    every other joint is returned unchanged.  Quaternions ``(..., 4)``, ``q`` ``(...)``.
    """
    qp = np.asarray(quat_pred, np.float64)
    q = np.asarray(q_pred, np.float64)
    zp, zt = quat_axis_z(qp), quat_axis_z(quat_true)
    xp, xt = quat_axis_x(qp), quat_axis_x(quat_true)
    flip = (np.einsum("...i,...i->...", zp, zt) < 0) & (np.einsum("...i,...i->...", xp, xt) > 0) & (q < 0)
    turned = quat_multiply(qp, np.broadcast_to(HALF_TURN_X_QUAT, qp.shape))
    return np.where(flip[..., None], turned, qp), np.where(flip, -q, q)


def configuration_error(q_pred: np.ndarray, q_true: np.ndarray, prismatic: np.ndarray) -> np.ndarray:
    """Configuration error ``|q_pred - q_true|`` in degrees (revolute) or cm (prismatic).

    ``q`` in radians / metres ``(..., J)``; ``prismatic`` is a boolean ``(J,)`` (broadcast)
    selecting the conversion factor: ``180/pi`` for revolute joints, 100 for prismatic ones.
    """
    scale = np.where(np.asarray(prismatic, bool), CM_PER_M, DEG_PER_RAD)
    return scale * np.abs(np.asarray(q_pred, np.float64) - np.asarray(q_true, np.float64))


# --------------------------------------------------------------------------------------
# Standard metrics of later work
# --------------------------------------------------------------------------------------

def axis_direction_error_deg(dir_pred: np.ndarray, dir_true: np.ndarray) -> np.ndarray:
    """Folded axis direction angle ``min(theta, 180 - theta)`` in degrees, in ``[0, 90]``.

    ``theta = angle(d_pred, d_true)``; the sign of an axis is not observable from its line, so
    a flipped axis scores 0.  Computed as ``atan2(||d_pred x d_true||, |d_pred . d_true|)``
    (directions need not be unit), which is accurate near 0 and 90 degrees.
    """
    a, b = normalise(dir_pred), normalise(dir_true)
    cross = np.cross(a, b)
    sin = np.sqrt(np.einsum("...i,...i->...", cross, cross))
    cos = np.abs(np.einsum("...i,...i->...", a, b))
    return np.arctan2(sin, cos) * DEG_PER_RAD


def point_to_line_distance_cm(point_m: np.ndarray, origin_m: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distance (cm) from ``point`` to the line ``origin + t * direction``: ``100 ||(p - o) x d_hat||``."""
    return CM_PER_M * point_line_distance_m(point_m, origin_m, direction)


def line_distance_cm(origin1_m: np.ndarray, dir1: np.ndarray, origin2_m: np.ndarray, dir2: np.ndarray) -> np.ndarray:
    """Distance (cm) between the infinite lines ``o1 + s d1`` and ``o2 + t d2``.

    Non-parallel lines: ``|(o2 - o1) . n| / ||n||`` with ``n = d1 x d2`` (length of the common
    perpendicular).  Parallel lines (``||d1_hat x d2_hat|| < PARALLEL_SIN_TOL``): the distance
    from a point of one line to the other, ``||(o2 - o1) x d1_hat||`` -- their separation, not 0.
    """
    d1, d2 = normalise(dir1), normalise(dir2)
    w = np.asarray(origin2_m, np.float64) - np.asarray(origin1_m, np.float64)
    n = np.cross(d1, d2)
    n_norm = np.sqrt(np.einsum("...i,...i->...", n, n))
    parallel = n_norm < PARALLEL_SIN_TOL
    skew = np.abs(np.einsum("...i,...i->...", w, n)) / np.where(parallel, 1.0, n_norm)
    c = np.cross(w, d1)
    sep = np.sqrt(np.einsum("...i,...i->...", c, c))
    return CM_PER_M * np.where(parallel, sep, skew)


def object_diagonal_m(geometry: np.ndarray) -> np.ndarray:
    """Diagonal ``sqrt(depth^2 + width^2 + height^2)`` (m) of the object's box; ``geometry (..., >=3)`` in m."""
    g = np.asarray(geometry, np.float64)[..., :3]
    return np.sqrt(np.einsum("...i,...i->...", g, g))


def part_side(quat: np.ndarray, part_offset: np.ndarray | None = None) -> np.ndarray:
    """Unit direction ``(..., 3)``, perpendicular to the joint axis, from the axis line to the part centre.

    ``s = R (p_x, p_y, 0) / ||(p_x, p_y)||`` with ``p`` the part offset (axis frame, m), i.e. the
    part centre ``o + R p`` with its component along the axis removed, seen from the axis;
    without a part offset, the frame's x axis ``R e_x`` (which the label convention points at
    the part).  NaN where the part centre is within :data:`MIN_PART_SIDE_M` of the axis line
    (e.g. a drawer, whose offset lies along its axis) or the offset is NaN.
    """
    if part_offset is None:
        return quat_axis_x(quat)
    R = quat_to_matrix(quat)
    p = np.asarray(part_offset, np.float64)
    perp = np.stack([p[..., 0], p[..., 1], np.zeros_like(p[..., 0])], axis=-1)
    length = np.hypot(p[..., 0], p[..., 1])
    side = np.einsum("...ij,...j->...i", R, perp) / np.where(length > 0, length, 1.0)[..., None]
    return np.where((length >= MIN_PART_SIDE_M)[..., None], side, np.nan)


def mechanism_side_correct(side_pred: np.ndarray, side_true: np.ndarray) -> np.ndarray:
    """1.0 where the predicted part lies on the truth's side of the axis (``s_pred . s_true > 0``), else 0.0.

    Sides from :func:`part_side`; NaN where either is undefined.  Unlike the folded direction
    error this is not invariant to a mirror: a door predicted on the other side of the true
    hinge line (the truth turned half a turn about its y axis) scores 0.
    """
    dot = np.einsum("...i,...i->...", np.asarray(side_pred, np.float64), np.asarray(side_true, np.float64))
    return np.where(np.isnan(dot), np.nan, (dot > 0).astype(np.float64))


def opd_success(direction_error_deg: np.ndarray, origin_error_cm: np.ndarray, diagonal_m: np.ndarray,
                check_origin: np.ndarray, side_correct: np.ndarray | None = None) -> np.ndarray:
    """Metric version 2's OPD-style success (float 0/1): direction error < 10 deg AND origin error < 0.25 diagonals AND right side.

    Version 3 scores OPD's own criterion, :func:`opd_motion_success` (thresholds inclusive, no side).

    ``success = [e_dir < 10] * ([e_origin < 0.25 * 100 * diag] or not check_origin) * [side != 0]``,
    with the origin error in cm and the diagonal in m.  As in OPD, the origin is checked only
    where ``check_origin`` is true (revolute joints); a prismatic axis has no meaningful
    position.  ``side_correct`` (:func:`mechanism_side_correct`; NaN = undefined, not checked)
    fails a mirrored door, which the folded direction and the origin-to-line test cannot see.
    NaN (undefined, left out of the means as every metric's undefined values are) where the
    direction error is NaN (the truth gives no axis) or, where the origin is checked, its error or
    the diagonal is (no axis position or geometry): such an image is neither a success nor a failure.
    """
    ok_dir = np.asarray(direction_error_deg) < OPD_MAX_DIRECTION_ERROR_DEG
    ok_origin = np.asarray(origin_error_cm) < OPD_MAX_ORIGIN_ERROR_DIAGONALS * CM_PER_M * np.asarray(diagonal_m)
    ok_side = True if side_correct is None else np.asarray(side_correct) != 0.0  # NaN != 0: not checked
    success = (ok_dir & (ok_origin | ~np.asarray(check_origin, bool)) & ok_side).astype(np.float64)
    undefined = np.isnan(np.asarray(direction_error_deg, np.float64))
    undefined = undefined | (np.asarray(check_origin, bool)
                             & np.isnan(np.asarray(origin_error_cm, np.float64) + np.asarray(diagonal_m, np.float64)))
    return np.where(undefined, np.nan, success)


def opd_motion_success(direction_error_deg: np.ndarray, origin_to_line_cm: np.ndarray, diagonal_m: np.ndarray,
                       check_origin: np.ndarray) -> np.ndarray:
    """OPD's motion criterion (float 0/1; metric version 3's ``opd_success``).

    ``success = [e_dir <= 10] * ([d_origin <= 0.25 * 100 * diag] or not check_origin)``: the
    folded axis direction error ``e_dir`` (deg) within :data:`OPD_MAX_DIRECTION_ERROR_DEG`, and,
    where ``check_origin`` is true (revolute joints; a prismatic axis has no position), the
    distance ``d_origin`` (cm) of the predicted origin from the true axis line within
    :data:`OPD_MAX_ORIGIN_ERROR_DIAGONALS` of the diagonal ``diag`` (m) of the object's box.
    The hinge side is not part of it (reported as the mechanism side accuracy).  NaN where the
    direction error is NaN or, where the origin is checked, the distance or the diagonal is.
    """
    e_dir = np.asarray(direction_error_deg, np.float64)
    d_origin = np.asarray(origin_to_line_cm, np.float64)
    diag = np.asarray(diagonal_m, np.float64)
    check = np.asarray(check_origin, bool)
    ok_origin = d_origin <= OPD_MAX_ORIGIN_ERROR_DIAGONALS * CM_PER_M * diag
    success = ((e_dir <= OPD_MAX_DIRECTION_ERROR_DEG) & (ok_origin | ~check)).astype(np.float64)
    undefined = np.isnan(e_dir) | (check & np.isnan(d_origin + diag))
    return np.where(undefined, np.nan, success)


def axis_accuracy(direction_error_deg: np.ndarray, line_distance_cm: np.ndarray, check_line: np.ndarray,
                  max_direction_deg: float, max_distance_cm: float) -> np.ndarray:
    """Accuracy at a threshold (float 0/1): ``[e_dir <= a] * ([d_line <= b] or not check_line)``.

    ``e_dir`` is the folded axis direction error (deg), ``d_line`` the distance between the
    predicted and true axis lines (cm), ``a``/``b`` the thresholds (the "5 deg / 5 cm" and
    "10 deg / 10 cm" of category-level articulation papers).  The line distance is checked only
    where ``check_line`` is true (revolute joints): a prismatic joint is judged by its direction.
    NaN where an input that is checked is NaN.
    """
    e_dir = np.asarray(direction_error_deg, np.float64)
    d_line = np.asarray(line_distance_cm, np.float64)
    check = np.asarray(check_line, bool)
    success = ((e_dir <= max_direction_deg) & ((d_line <= max_distance_cm) | ~check)).astype(np.float64)
    undefined = np.isnan(e_dir) | (check & np.isnan(d_line))
    return np.where(undefined, np.nan, success)


def position_error_components_cm(origin_pred_m: np.ndarray, origin_true_m: np.ndarray,
                                 direction_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis position error split along and across the true axis (cm), ``(along, across)``.

    With ``e = o_pred - o_true`` and the unit true direction ``d``: ``along = 100 |e . d|`` and
    ``across = 100 ||e x d||``, so ``along^2 + across^2`` is the squared axis position error.
    Along a hinge is where an image that cuts the object off leaves the origin unmeasured;
    across it is the error a robot's grasp on the moving part feels.
    """
    e = np.asarray(origin_pred_m, np.float64) - np.asarray(origin_true_m, np.float64)
    d = normalise(direction_true)
    along = CM_PER_M * np.abs(np.einsum("...i,...i->...", e, d))
    c = np.cross(e, d)
    return along, CM_PER_M * np.sqrt(np.einsum("...i,...i->...", c, c))


def standard_error_of_mean(values: np.ndarray, groups: np.ndarray) -> float:
    """Standard error of the mean of ``values`` over independent ``groups`` (objects).

    The images of one object share its shape and pose, so they are not independent draws: the
    values are first averaged per group, ``m_g = mean_{i in g} v_i``, and
    ``SEM = std(m_g, ddof=1) / sqrt(G)`` over the ``G`` groups.  NaN values are left out; NaN
    where fewer than two groups have a value, infinite where a value is infinite.
    """
    v = np.asarray(values, np.float64)
    g = np.asarray(groups)
    keep = ~np.isnan(v)
    v, g = v[keep], g[keep]
    if not np.isfinite(v).all():
        return float("inf")
    labels, inverse = np.unique(g, return_inverse=True)
    if len(labels) < 2:
        return float("nan")
    means = np.bincount(inverse, weights=v) / np.bincount(inverse)
    return float(np.std(means, ddof=1) / np.sqrt(len(labels)))


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------

def geometry_error_cm(geometry_pred: np.ndarray, geometry_true: np.ndarray) -> np.ndarray:
    """Absolute errors ``100 |g_pred - g_true|`` (cm) of depth, width, height: ``(..., 3)``."""
    return CM_PER_M * np.abs(np.asarray(geometry_pred, np.float64)[..., :3] - np.asarray(geometry_true, np.float64)[..., :3])


def chirality_correct(geometry_pred: np.ndarray, geometry_true: np.ndarray) -> np.ndarray:
    """1.0 where ``[c_pred >= 0.5] == [c_true >= 0.5]`` (chirality = geometry[..., 3]), else 0.0; NaN where ``c_true`` is NaN.

    A predicted chirality may be a probability of "hinge on the right" or a 0/1 label.  An
    undefined true chirality (NaN, real captures without it) is excluded by the scorer like
    any other undefined truth, instead of counting as "left" (``NaN >= 0.5`` is False).
    """
    c_true = np.asarray(geometry_true, np.float64)[..., 3]
    p = np.asarray(geometry_pred, np.float64)[..., 3] >= CHIRALITY_THRESHOLD
    return np.where(np.isnan(c_true), np.nan, (p == (c_true >= CHIRALITY_THRESHOLD)).astype(np.float64))


# --------------------------------------------------------------------------------------
# Diagonal Gaussian mixtures (MDN outputs)
# --------------------------------------------------------------------------------------

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def mixture_nll(y: np.ndarray, weights: np.ndarray, means: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Negative log-likelihood (nats) of ``y (..., D)`` under a diagonal Gaussian mixture.

    ``NLL = -log sum_m w_m prod_d N(y_d; mu_md, sigma_md)``
    ``    = -logsumexp_m [log w_m - sum_d (log sigma_md + log sqrt(2 pi) + (y_d - mu_md)^2 / (2 sigma_md^2))]``

    ``weights (..., M)`` sum to 1; ``means``/``scales`` ``(..., M, D)``, scales > 0, in the
    units of ``y`` (the density is per unit of each column, so the NLL depends on them).
    """
    y = np.asarray(y, np.float64)[..., None, :]
    mu, sigma = np.asarray(means, np.float64), np.asarray(scales, np.float64)
    z = (y - mu) / sigma
    log_comp = -np.sum(np.log(sigma) + _LOG_SQRT_2PI + 0.5 * z * z, axis=-1)
    with np.errstate(divide="ignore"):
        log_w = np.log(np.asarray(weights, np.float64))
    return -np.logaddexp.reduce(log_w + log_comp, axis=-1)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF ``Phi(x)`` (scipy's ``ndtr``; scipy is needed only for mixtures)."""
    from articulated_dataset.core.errors import import_optional

    return import_optional("scipy.special", "scoring mixture calibration").ndtr(x)


def mixture_marginal_cdf(y: np.ndarray, weights: np.ndarray, means: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """CDF of each 1-D marginal of a diagonal Gaussian mixture at ``y``: ``(..., D)``.

    ``F_d(y_d) = sum_m w_m Phi((y_d - mu_md) / sigma_md)`` (the marginal of a diagonal mixture
    along column d is the mixture of the components' marginals with the same weights).
    """
    y = np.asarray(y, np.float64)[..., None, :]
    cdf = _normal_cdf((y - np.asarray(means, np.float64)) / np.asarray(scales, np.float64))
    return np.einsum("...m,...md->...d", np.asarray(weights, np.float64), cdf)


def mixture_marginal_interval(weights: np.ndarray, means: np.ndarray, scales: np.ndarray,
                              mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Central interval ``[F_d^-1((1 - p)/2), F_d^-1((1 + p)/2)]`` of each 1-D marginal, ``p = mass``.

    ``F_d`` is strictly increasing, so each quantile is found by bisection on
    ``F_d(x) - level`` inside the bracket ``[min_m(mu - 40 sigma), max_m(mu + 40 sigma)]``
    (:data:`BISECTION_STEPS` halvings).  Returns ``(lower, upper)``, each ``(..., D)``.
    """
    if not 0.0 < mass < 1.0:
        raise ValueError(f"interval mass must be in (0, 1), got {mass}")
    bracket_sigmas = 40.0  # Phi(-40) underflows to 0: the quantile is inside this bracket
    mu, sigma = np.asarray(means, np.float64), np.asarray(scales, np.float64)
    lo0 = np.min(mu - bracket_sigmas * sigma, axis=-2)
    hi0 = np.max(mu + bracket_sigmas * sigma, axis=-2)
    out = []
    for level in (0.5 * (1.0 - mass), 0.5 * (1.0 + mass)):
        lo, hi = lo0.copy(), hi0.copy()
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            below = mixture_marginal_cdf(mid, weights, means, scales) < level
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        out.append(0.5 * (lo + hi))
    return out[0], out[1]


def interval_coverage(y: np.ndarray, weights: np.ndarray, means: np.ndarray, scales: np.ndarray,
                      mass: float) -> np.ndarray:
    """1.0 where ``y_d`` lies inside the central ``mass`` interval of marginal d, else 0.0: ``(..., D)``.

    Because ``F_d`` is increasing, ``y in [F^-1((1-p)/2), F^-1((1+p)/2)]`` is the same as
    ``|F_d(y_d) - 1/2| <= p/2`` (probability integral transform): no quantiles are needed.
    :func:`mixture_marginal_interval` computes the interval itself (used to check this).
    """
    u = mixture_marginal_cdf(y, weights, means, scales)
    return (np.abs(u - 0.5) <= 0.5 * mass).astype(np.float64)
