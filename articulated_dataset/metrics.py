"""Benchmark metrics: pure, vectorised numpy functions.

Every function takes arrays with arbitrary leading dimensions (images, joints...) and
returns one value per element of those dimensions; none of them averages.  Averaging over
joints (2-DoF objects) and over images is done by :mod:`articulated_dataset.scoring`.

Conventions (see docs/format.md and docs/scoring.md):

* positions in metres, in the camera frame (x forward, y left, z up);
* quaternions ``(w, x, y, z)`` of the axis frame, whose z column is the joint axis;
* configurations ``q`` in radians (revolute) or metres (prismatic);
* returned errors are in the units named by the function (``_cm``, ``_deg``).

The camera z axis (``up``) is the axis of the paper's "axis rotation error".
"""

from __future__ import annotations

import numpy as np

from .rotations import quat_conjugate, quat_multiply
#: Centimetres per metre (errors are reported in cm).
CM_PER_M = 100.0
#: Degrees per radian.
DEG_PER_RAD = 180.0 / np.pi
#: OPD-style success thresholds (Jiang et al., "OPD", 2022): axis direction within 10 degrees ...
OPD_MAX_DIRECTION_ERROR_DEG = 10.0
#: ... and the predicted origin within 0.25 object diagonals of the true axis line.
OPD_MAX_ORIGIN_ERROR_DIAGONALS = 0.25
#: Below this value of |d1 x d2| (unit directions, = sin of their angle) two lines are treated as
#: parallel: the common-perpendicular formula divides by it and loses all precision.
PARALLEL_SIN_TOL = 1e-9
#: Chirality predictions are thresholded at 0.5 (a probability or a 0/1 label).
CHIRALITY_THRESHOLD = 0.5
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


def twist_about_z_deg(q: np.ndarray) -> np.ndarray:
    """Signed twist angle (degrees, in ``(-180, 180]``) about the z axis of the rotation ``q``.

    Swing-twist decomposition ``q = q_twist * q_swing`` with ``q_twist`` a rotation about z and
    ``q_swing`` a rotation about an axis perpendicular to z: ``q_twist`` is the normalised
    projection ``(w, 0, 0, z)`` of ``q``, so ``twist = 2 atan2(q_z, q_w)`` wrapped to
    ``(-180, 180]``.  Equivalently, the twist is the angle ``theta`` maximising
    ``trace(R_z(theta)^T R(q))`` (the rotation about z closest to ``R(q)``).  The sign of ``q``
    does not matter.  When ``q_w = q_z = 0`` (a half-turn about a horizontal axis) the twist
    is undefined and 0 is returned.
    """
    q = np.asarray(q, np.float64)
    twist = 2.0 * np.arctan2(q[..., 3], q[..., 0]) * DEG_PER_RAD
    return 180.0 - np.mod(180.0 - twist, 360.0)


def axis_rotation_error_deg(quat_pred: np.ndarray, quat_true: np.ndarray) -> np.ndarray:
    """Axis rotation error (paper): ``|twist_z(R_pred R_true^T)|`` in degrees, in ``[0, 180]``.

    ``R_pred R_true^T`` is the relative rotation of the predicted axis frame with respect to
    the true one, expressed in the camera frame; its twist about the camera z axis (up) is
    taken by :func:`twist_about_z_deg`.  Quaternions ``(..., 4)`` (w, x, y, z), unit length.
    """
    rel = quat_multiply(quat_pred, quat_conjugate(quat_true))
    return np.abs(twist_about_z_deg(rel))


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

def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    n = np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    return v / np.where(n > 0, n, 1.0)


def axis_direction_error_deg(dir_pred: np.ndarray, dir_true: np.ndarray) -> np.ndarray:
    """Folded axis direction angle ``min(theta, 180 - theta)`` in degrees, in ``[0, 90]``.

    ``theta = angle(d_pred, d_true)``; the sign of an axis is not observable from its line, so
    a flipped axis scores 0.  Computed as ``atan2(||d_pred x d_true||, |d_pred . d_true|)``
    (directions need not be unit), which is accurate near 0 and 90 degrees.
    """
    a, b = _unit(dir_pred), _unit(dir_true)
    cross = np.cross(a, b)
    sin = np.sqrt(np.einsum("...i,...i->...", cross, cross))
    cos = np.abs(np.einsum("...i,...i->...", a, b))
    return np.arctan2(sin, cos) * DEG_PER_RAD


def point_to_line_distance_cm(point_m: np.ndarray, origin_m: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distance (cm) from ``point`` to the line ``origin + t * direction``: ``100 ||(p - o) x d_hat||``."""
    w = np.asarray(point_m, np.float64) - np.asarray(origin_m, np.float64)
    c = np.cross(w, _unit(direction))
    return CM_PER_M * np.sqrt(np.einsum("...i,...i->...", c, c))


def line_distance_cm(origin1_m: np.ndarray, dir1: np.ndarray, origin2_m: np.ndarray, dir2: np.ndarray) -> np.ndarray:
    """Distance (cm) between the infinite lines ``o1 + s d1`` and ``o2 + t d2``.

    Non-parallel lines: ``|(o2 - o1) . n| / ||n||`` with ``n = d1 x d2`` (length of the common
    perpendicular).  Parallel lines (``||d1_hat x d2_hat|| < PARALLEL_SIN_TOL``): the distance
    from a point of one line to the other, ``||(o2 - o1) x d1_hat||`` -- their separation, not 0.
    """
    d1, d2 = _unit(dir1), _unit(dir2)
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


def opd_success(direction_error_deg: np.ndarray, origin_error_cm: np.ndarray, diagonal_m: np.ndarray,
                check_origin: np.ndarray) -> np.ndarray:
    """OPD-style success (float 0/1): direction error < 10 deg AND origin error < 0.25 diagonals.

    ``success = [e_dir < 10] * ([e_origin < 0.25 * 100 * diag] or not check_origin)``, with the
    origin error in cm and the diagonal in m.  As in OPD, the origin is checked only where
    ``check_origin`` is true (revolute joints); a prismatic axis has no meaningful position.
    """
    ok_dir = np.asarray(direction_error_deg) < OPD_MAX_DIRECTION_ERROR_DEG
    ok_origin = np.asarray(origin_error_cm) < OPD_MAX_ORIGIN_ERROR_DIAGONALS * CM_PER_M * np.asarray(diagonal_m)
    return (ok_dir & (ok_origin | ~np.asarray(check_origin, bool))).astype(np.float64)


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------

def geometry_error_cm(geometry_pred: np.ndarray, geometry_true: np.ndarray) -> np.ndarray:
    """Absolute errors ``100 |g_pred - g_true|`` (cm) of depth, width, height: ``(..., 3)``."""
    return CM_PER_M * np.abs(np.asarray(geometry_pred, np.float64)[..., :3] - np.asarray(geometry_true, np.float64)[..., :3])


def chirality_correct(geometry_pred: np.ndarray, geometry_true: np.ndarray) -> np.ndarray:
    """1.0 where ``[c_pred >= 0.5] == [c_true >= 0.5]`` (chirality = geometry[..., 3]), else 0.0.

    A predicted chirality may be a probability of "hinge on the right" or a 0/1 label.
    """
    p = np.asarray(geometry_pred, np.float64)[..., 3] >= CHIRALITY_THRESHOLD
    t = np.asarray(geometry_true, np.float64)[..., 3] >= CHIRALITY_THRESHOLD
    return (p == t).astype(np.float64)


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
    try:
        from scipy.special import ndtr
    except ImportError:
        from .errors import UserError

        raise UserError("scoring mixture calibration needs scipy: pip install scipy") from None
    return ndtr(x)


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
