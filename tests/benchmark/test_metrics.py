"""Metric functions: hand-worked cases and independent brute-force references on random data."""

from __future__ import annotations

import numpy as np
import pytest

from articulated_dataset.benchmark import metrics as M
from articulated_dataset.benchmark.scoring import image_metrics
from articulated_dataset.classes.registry import PRISMATIC, REVOLUTE
from articulated_dataset.core import rotations


def quat_about(axis, angle_deg):
    """Unit quaternion (w, x, y, z) of a rotation by ``angle_deg`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = np.radians(angle_deg) / 2
    return np.concatenate([[np.cos(h)], np.sin(h) * axis])


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


Z = [0.0, 0.0, 1.0]


# ---------------------------------------------------------------- hand-worked cases

def test_position_error_3cm_shift_along_x():
    o = np.array([1.5, -0.2, 0.4])
    assert M.axis_position_error_cm(o + [0.03, 0, 0], o) == pytest.approx(3.0, abs=1e-9)
    assert M.axis_position_error_cm(o + [0.03, 0.04, 0], o) == pytest.approx(5.0, abs=1e-9)


@pytest.mark.parametrize("angle, expected", [(5.0, 5.0), (-5.0, 5.0), (179.0, 179.0), (200.0, 160.0), (360.0, 0.0), (-350.0, 10.0)])
def test_rotation_error_about_z(angle, expected):
    true = quat_about([1, 2, 0.5], 37.0)  # arbitrary true axis frame
    pred = rotations.quat_multiply(quat_about(Z, angle), true)  # rotated about the camera z axis
    assert M.axis_rotation_error_deg(pred, true) == pytest.approx(expected, abs=1e-9)
    # the sign of either quaternion does not matter
    assert M.axis_rotation_error_deg(-pred, true) == pytest.approx(expected, abs=1e-9)


# Axis frames of the generator's classes at yaw 0 (docs/format.md): columns x, y, z in the camera frame.
#: side-hinged door, hinge on the object's right: x (to the door) = +y_obj, y (opening) = -x_obj, z up
DOOR_RIGHT = rotations.matrix_to_quat(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
#: bottom-hinged door (toaster): x up (to the door), y = -x_obj (opening), z = -y_obj
TOASTER = rotations.matrix_to_quat(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))
#: drawer: x up, y = +y_obj, z = -x_obj (pulled towards the camera)
DRAWER = rotations.matrix_to_quat(np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
FRAMES = {"door": DOOR_RIGHT, "toaster": TOASTER, "drawer": DRAWER}
HALF_TURN = {"x": quat_about([1, 0, 0], 180.0), "y": quat_about([0, 1, 0], 180.0), "z": quat_about(Z, 180.0)}


def _yawed(quat, yaw_deg):
    return rotations.quat_multiply(quat_about(Z, yaw_deg), quat)


@pytest.mark.parametrize("frame", sorted(FRAMES))
def test_exact_mirror_scores_180(frame):
    """The truth turned half a turn about its own y axis (door on the other side of the same
    hinge line) scores 180 (metric version 1 scored 0: undefined twist)."""
    true = _yawed(FRAMES[frame], 23.0)
    mirror = rotations.quat_multiply(true, HALF_TURN["y"])
    assert M.axis_rotation_error_deg(mirror, true) == pytest.approx(180.0, abs=1e-9)
    assert M.axis_direction_error_deg(M.quat_axis_z(mirror), M.quat_axis_z(true)) == pytest.approx(0.0, abs=1e-9)  # folded


@pytest.mark.parametrize("frame", sorted(FRAMES))
def test_mirror_plus_small_noise_stays_near_180(frame):
    rng = np.random.default_rng(7)
    true = _yawed(FRAMES[frame], -31.0)
    for _ in range(20):
        noise = quat_about(rng.normal(size=3), 2.0)  # 2 deg about a random axis
        pred = rotations.quat_multiply(noise, rotations.quat_multiply(true, HALF_TURN["y"]))
        err = M.axis_rotation_error_deg(pred, true)
        assert 175.0 < err <= 180.0  # a 2 deg tilt moves a heading by at most ~2.9 deg at 45 deg from vertical


@pytest.mark.parametrize("frame", sorted(FRAMES))
def test_true_180_yaw_error(frame):
    true = _yawed(FRAMES[frame], 10.0)
    assert M.axis_rotation_error_deg(_yawed(true, 180.0), true) == pytest.approx(180.0, abs=1e-9)
    assert M.axis_rotation_error_deg(_yawed(true, 179.0), true) == pytest.approx(179.0, abs=1e-9)


@pytest.mark.parametrize("frame", sorted(FRAMES))
def test_reversed_axis_with_negated_q_is_the_same_joint(frame):
    true = _yawed(FRAMES[frame], 5.0)
    reversed_ = rotations.quat_multiply(true, HALF_TURN["x"])  # axis and y reversed, x kept
    quat, q = M.canonical_axis_sign(reversed_, np.array(-0.4), true)
    assert q == pytest.approx(0.4)
    assert M.axis_rotation_error_deg(quat, true) == pytest.approx(0.0, abs=1e-6)
    # with q >= 0 it is a different mechanism (the part opens the other way): not re-expressed, 180
    quat, q = M.canonical_axis_sign(reversed_, np.array(0.4), true)
    assert q == 0.4 and M.axis_rotation_error_deg(quat, true) == pytest.approx(180.0, abs=1e-9)
    # a mirror with negative q is not the same joint either (x changes side): not re-expressed
    mirror = rotations.quat_multiply(true, HALF_TURN["y"])
    quat, q = M.canonical_axis_sign(mirror, np.array(-0.4), true)
    assert q == -0.4 and np.allclose(quat, mirror)


def test_every_half_turn_about_a_horizontal_axis_scores_at_least_90():
    rng = np.random.default_rng(8)
    for frame in FRAMES.values():
        true = _yawed(frame, rng.uniform(-180, 180))
        for a in rng.uniform(0, 360, size=20):
            flip = quat_about([np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0], 180.0)
            assert M.axis_rotation_error_deg(rotations.quat_multiply(flip, true), true) >= 90.0 - 1e-9


def test_undefined_heading_scores_180():
    true = DOOR_RIGHT  # x horizontal
    pred = rotations.quat_multiply(DOOR_RIGHT, quat_about([0, 1, 0], -90.0))  # x turned up: vertical
    assert M.quat_axis_x(pred)[2] == pytest.approx(1.0)
    assert M.axis_rotation_error_deg(pred, true) == 180.0
    assert M.heading_error_deg(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])) == 180.0
    assert np.isnan(M.axis_rotation_error_deg(pred, np.full(4, np.nan)))  # undefined truth stays undefined


def test_configuration_error_units():
    prismatic = np.array([False, True])
    err = M.configuration_error(np.array([0.1, 0.35]), np.array([0.0, 0.30]), prismatic)
    assert err[0] == pytest.approx(np.degrees(0.1))
    assert err[1] == pytest.approx(5.0)


@pytest.mark.parametrize("theta, expected", [(0, 0), (30, 30), (90, 90), (120, 60), (180, 0), (179, 1)])
def test_direction_error_folded(theta, expected):
    t = np.radians(theta)
    d_true = np.array([0.0, 0.0, 1.0])
    d_pred = 2.5 * np.array([np.sin(t), 0.0, np.cos(t)])  # length does not matter
    assert M.axis_direction_error_deg(d_pred, d_true) == pytest.approx(expected, abs=1e-9)


def test_line_distance_parallel_offset_lines():
    d = np.array([0.0, 0.0, 1.0])
    assert M.line_distance_cm([0.0, 0.0, 0.0], d, [0.03, 0.04, 7.0], d) == pytest.approx(5.0)
    assert M.line_distance_cm([0.0, 0.0, 0.0], d, [0.03, 0.04, -2.0], -d) == pytest.approx(5.0)  # antiparallel
    assert M.line_distance_cm([0.0, 0.0, 0.0], d, [0.0, 0.0, 3.0], d) == pytest.approx(0.0)  # same line


def test_line_distance_skew_and_intersecting():
    # x axis and the line through (0, 0, 0.1) along y: common perpendicular is 10 cm along z
    assert M.line_distance_cm([5, 0, 0], [1, 0, 0], [0, -3, 0.1], [0, 1, 0]) == pytest.approx(10.0)
    assert M.line_distance_cm([0, 0, 0], [1, 0, 0], [0, 0, 0], [1, 1, 0]) == pytest.approx(0.0, abs=1e-12)
    # nearly parallel (1e-6 rad) but skew lines: far from the parallel formula, still well defined
    d2 = [np.sin(1e-6), 0.0, np.cos(1e-6)]
    assert M.line_distance_cm([0, 0, 0], Z, [0.0, 0.05, 0.0], d2) == pytest.approx(5.0, rel=1e-6)


def test_point_to_line_distance():
    assert M.point_to_line_distance_cm([0.03, 0.04, 9.0], [0, 0, 0], [0, 0, 2.0]) == pytest.approx(5.0)


def test_opd_success_thresholds():
    diag = np.array([1.0])  # 1 m diagonal -> origin threshold 25 cm
    assert M.opd_success(9.9, 24.9, diag, True) == 1.0
    assert M.opd_success(10.1, 0.0, diag, True) == 0.0
    assert M.opd_success(0.0, 25.1, diag, True) == 0.0
    assert M.opd_success(0.0, 300.0, diag, False) == 1.0  # prismatic: origin not checked
    assert M.opd_success(0.0, 0.0, diag, True, 0.0) == 0.0  # a mirrored door fails
    assert M.opd_success(0.0, 0.0, diag, True, 1.0) == 1.0
    assert M.opd_success(0.0, 0.0, diag, False, np.nan) == 1.0  # no side (prismatic): not checked
    assert M.object_diagonal_m([0.3, 0.4, 1.2, 1.0]) == pytest.approx(1.3)


def test_geometry_and_chirality():
    err = M.geometry_error_cm([0.5, 0.6, 0.7, 0.9], [0.52, 0.6, 0.65, 1.0])
    np.testing.assert_allclose(err, [2.0, 0.0, 5.0], atol=1e-9)
    assert M.chirality_correct([0, 0, 0, 0.9], [0, 0, 0, 1.0]) == 1.0
    assert M.chirality_correct([0, 0, 0, 0.2], [0, 0, 0, 1.0]) == 0.0
    assert M.chirality_correct([0, 0, 0, 0.0], [0, 0, 0, 0.0]) == 1.0
    assert np.isnan(M.chirality_correct([0, 0, 0, 0.0], [0, 0, 0, np.nan]))  # undefined truth: excluded, not "left"


def test_part_side_and_mechanism_side():
    true = _yawed(DOOR_RIGHT, 12.0)
    offset = np.array([0.3, 0.0, 0.1])  # 30 cm from the hinge, 10 cm along it
    side_t = M.part_side(true, offset)
    np.testing.assert_allclose(side_t, M.quat_axis_x(true), atol=1e-12)
    mirror = rotations.quat_multiply(true, HALF_TURN["y"])
    assert M.mechanism_side_correct(M.part_side(mirror, offset), side_t) == 0.0
    assert M.mechanism_side_correct(M.part_side(mirror), side_t) == 0.0  # no offset: the frame's x
    # the mirrored frame with the part placed at negative x: the same physical side
    assert M.mechanism_side_correct(M.part_side(mirror, offset * [-1, 1, 1]), side_t) == 1.0
    reversed_ = rotations.quat_multiply(true, HALF_TURN["x"])
    assert M.mechanism_side_correct(M.part_side(reversed_, offset * [1, 1, -1]), side_t) == 1.0
    # an offset along the axis (a drawer) has no side
    assert np.isnan(M.part_side(DRAWER, np.array([0.0, 0.0, -0.25]))).all()
    assert np.isnan(M.mechanism_side_correct(M.part_side(mirror), np.full(3, np.nan)))


def _pose(origin, quat):
    return np.concatenate([origin, quat])


def test_two_dof_object_averages_its_joints():
    q0 = quat_about(Z, 0.0)
    truth = {
        "axis_pose": np.array([[_pose([1, 0.3, 0], q0), _pose([1, -0.3, 0], q0)]]),
        "q": np.array([[0.2, 0.4]]),
        "geometry": np.array([[0.5, 0.8, 1.0, 0.0]]),
        "part_offset": np.zeros((1, 2, 3)),
    }
    pred = {
        "axis_pose": np.array([[_pose([1.02, 0.3, 0], quat_about(Z, 4.0)), _pose([1, -0.3, 0.04], quat_about(Z, -8.0))]]),
        "q": np.array([[0.2 + np.radians(1.0), 0.4 - np.radians(3.0)]]),
    }
    out, per_joint = image_metrics(pred, truth, (REVOLUTE, REVOLUTE))
    assert out["axis_position_error_cm"][0] == pytest.approx(3.0)  # (2 + 4) / 2
    assert out["axis_rotation_error_deg"][0] == pytest.approx(6.0)  # (4 + 8) / 2
    assert out["configuration_error"][0] == pytest.approx(2.0)  # (1 + 3) / 2
    np.testing.assert_allclose(per_joint["axis_position_error_cm"][0], [2.0, 4.0])
    # joint 0 is shifted perpendicular to its (vertical) axis by 2 cm; joint 1 along its axis: 0
    assert out["axis_line_distance_cm"][0] == pytest.approx(1.0)
    assert out["opd_success"][0] == 1.0


def test_prismatic_joint_in_image_metrics():
    q0 = quat_about([0, 1, 0], 90.0)  # axis along camera x (a drawer facing the camera)
    truth = {"axis_pose": np.array([[_pose([1, 0, 0], q0)]]), "q": np.array([[0.1]]),
             "geometry": np.array([[0.5, 0.5, 0.5, 0.0]]), "part_offset": np.zeros((1, 1, 3))}
    pred = {"axis_pose": np.array([[_pose([1, 0.5, 0], q0)]]), "q": np.array([[0.13]])}
    out, _ = image_metrics(pred, truth, (PRISMATIC,))
    assert out["configuration_error"][0] == pytest.approx(3.0)  # cm
    assert "axis_line_distance_cm" not in out  # no revolute joint
    assert out["opd_success"][0] == 1.0  # origin not checked for prismatic joints


# ---------------------------------------------------------------- brute-force references

def test_quaternion_helpers_match_scipy():
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(0)
    q = random_quats(rng, 50)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(rotations.quat_to_matrix(q), R, atol=1e-12)
    np.testing.assert_allclose(M.quat_axis_z(q), R[:, :, 2], atol=1e-12)
    np.testing.assert_allclose(M.quat_axis_x(q), R[:, :, 0], atol=1e-12)
    a, b = random_quats(rng, 50), random_quats(rng, 50)
    np.testing.assert_allclose(rotations.quat_to_matrix(rotations.quat_multiply(a, b)), rotations.quat_to_matrix(a) @ rotations.quat_to_matrix(b), atol=1e-12)


def test_rotation_error_matches_column_heading_angles():
    """Reference: headings as angles (degrees), differences wrapped by modulo, on yawed class frames
    (one vertical column, as generated) against random predictions."""
    rng = np.random.default_rng(1)
    for frame in FRAMES.values():
        qt = np.stack([_yawed(frame, y) for y in rng.uniform(-180, 180, 40)])
        qp = random_quats(rng, 40)
        got = M.axis_rotation_error_deg(qp, qt)
        Rp, Rt = rotations.quat_to_matrix(qp), rotations.quat_to_matrix(qt)
        for i in range(40):
            errs = []
            for k in range(3):
                if abs(Rt[i, 2, k]) > 0.99:  # the vertical column
                    continue
                hp = np.degrees(np.arctan2(Rp[i, 1, k], Rp[i, 0, k]))
                ht = np.degrees(np.arctan2(Rt[i, 1, k], Rt[i, 0, k]))
                errs.append(abs((hp - ht + 180.0) % 360.0 - 180.0))
            assert len(errs) == 2 and got[i] == pytest.approx(max(errs), abs=1e-9)


def test_direction_error_matches_arccos():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    cos = np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    theta = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    np.testing.assert_allclose(M.axis_direction_error_deg(a, b), np.minimum(theta, 180 - theta), atol=1e-9)


def _brute_line_distance(o1, d1, o2, d2):
    """min over (s, t) of ||o1 + s d1 - o2 - t d2||: dense grid, then a local minimisation."""
    from scipy.optimize import minimize

    s = np.linspace(-10, 10, 401)
    P1 = o1 + s[:, None] * d1
    P2 = o2 + s[:, None] * d2
    dist = np.linalg.norm(P1[:, None, :] - P2[None, :, :], axis=-1)
    i, j = np.unravel_index(np.argmin(dist), dist.shape)
    res = minimize(lambda x: np.sum((o1 + x[0] * d1 - o2 - x[1] * d2) ** 2), x0=[s[i], s[j]], method="BFGS",
                   options={"gtol": 1e-14})
    return 100.0 * np.sqrt(max(res.fun, 0.0))


def test_line_distance_matches_brute_force():
    pytest.importorskip("scipy")
    rng = np.random.default_rng(3)
    for k in range(30):
        o1, o2 = rng.normal(size=3), rng.normal(size=3)
        d1 = rng.normal(size=3)
        d1 /= np.linalg.norm(d1)
        # a third of the cases exactly parallel (or antiparallel)
        d2 = d1 * (-1) ** k if k % 3 == 0 else rng.normal(size=3)
        d2 /= np.linalg.norm(d2)
        got = M.line_distance_cm(o1, d1, o2, d2)
        assert got == pytest.approx(_brute_line_distance(o1, d1, o2, d2), abs=1e-4)


def _random_mixture(rng, n, m, d):
    w = rng.uniform(0.1, 1.0, size=(n, m))
    w /= w.sum(1, keepdims=True)
    mu = rng.normal(size=(n, m, d))
    sigma = rng.uniform(0.2, 1.5, size=(n, m, d))
    return w, mu, sigma


def test_mixture_nll_matches_direct_density():
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(4)
    w, mu, sigma = _random_mixture(rng, 20, 3, 4)
    y = rng.normal(size=(20, 4))
    density = np.sum(w * np.prod(stats.norm.pdf(y[:, None, :], mu, sigma), axis=-1), axis=-1)
    np.testing.assert_allclose(M.mixture_nll(y, w, mu, sigma), -np.log(density), rtol=1e-10)
    # far in the tail the product underflows, log-sum-exp does not
    assert np.isfinite(M.mixture_nll(y + 60.0, w, mu, sigma)).all()


def test_mixture_nll_single_gaussian_by_hand():
    # N(0; 0, 1) in 1-D: log sqrt(2 pi) = 0.918939 nats
    assert M.mixture_nll(np.zeros((1, 1)), np.ones((1, 1)), np.zeros((1, 1, 1)), np.ones((1, 1, 1)))[0] == pytest.approx(0.9189385332)


def test_mixture_interval_matches_root_finding_and_coverage():
    stats = pytest.importorskip("scipy.stats")
    from scipy.optimize import brentq

    rng = np.random.default_rng(5)
    w, mu, sigma = _random_mixture(rng, 6, 3, 2)
    lo, hi = M.mixture_marginal_interval(w, mu, sigma, 0.9)
    for i in range(6):
        for d in range(2):
            F = lambda x: np.sum(w[i] * stats.norm.cdf(x, mu[i, :, d], sigma[i, :, d]))  # noqa: E731
            assert lo[i, d] == pytest.approx(brentq(lambda x: F(x) - 0.05, -50, 50, xtol=1e-12), abs=1e-8)
            assert hi[i, d] == pytest.approx(brentq(lambda x: F(x) - 0.95, -50, 50, xtol=1e-12), abs=1e-8)
    # coverage by the PIT equals membership of the bisected interval
    y = rng.normal(scale=2.0, size=(6, 2))
    np.testing.assert_array_equal(M.interval_coverage(y, w, mu, sigma, 0.9), ((y >= lo) & (y <= hi)).astype(float))
    # single Gaussian: the central 50% interval is mu +/- 0.6745 sigma
    lo1, hi1 = M.mixture_marginal_interval(np.ones((1, 1)), np.zeros((1, 1, 1)), np.full((1, 1, 1), 2.0), 0.5)
    assert hi1[0, 0] == pytest.approx(2.0 * 0.6744897502, abs=1e-8) and lo1[0, 0] == pytest.approx(-hi1[0, 0])


def test_coverage_of_samples_from_the_mixture_is_calibrated():
    pytest.importorskip("scipy")
    rng = np.random.default_rng(6)
    n = 20000
    w, mu, sigma = _random_mixture(rng, 1, 3, 2)
    w, mu, sigma = (np.repeat(a, n, axis=0) for a in (w, mu, sigma))
    comp = np.array([rng.choice(3, p=w[0]) for _ in range(n)])
    y = mu[np.arange(n), comp] + sigma[np.arange(n), comp] * rng.normal(size=(n, 2))
    for mass in (0.5, 0.9):
        assert M.interval_coverage(y, w, mu, sigma, mass).mean() == pytest.approx(mass, abs=0.015)


def _door_case(pred_quat, pred_q, pred_offset=None, metric_version=M.METRIC_VERSION):
    """One image of a right-hinged door yawed by 20 deg, 0.6 m wide, opened 0.5 rad."""
    true_quat = _yawed(DOOR_RIGHT, 20.0)
    origin = np.array([1.5, 0.2, 0.1])
    truth = {"axis_pose": np.array([[_pose(origin, true_quat)]]), "q": np.array([[0.5]]),
             "geometry": np.array([[0.6, 0.6, 0.9, 1.0]]), "part_offset": np.array([[[0.3, 0.0, 0.0]]])}
    pred = {"axis_pose": np.array([[_pose(origin, pred_quat(true_quat))]]), "q": np.array([[pred_q]])}
    if pred_offset is not None:
        pred["part_offset"] = np.array([[pred_offset]])
    return image_metrics(pred, truth, (REVOLUTE,), metric_version=metric_version)[0]


def test_image_metrics_reversed_axis_with_negated_q_is_perfect():
    out = _door_case(lambda t: rotations.quat_multiply(t, HALF_TURN["x"]), -0.5, [0.3, 0.0, 0.0])
    for name in ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error",
                 "axis_direction_error_deg", "axis_line_distance_cm"):
        assert out[name][0] == pytest.approx(0.0, abs=1e-6), name
    assert out["opd_success"][0] == 1.0 and out["mechanism_side_accuracy"][0] == 1.0


def test_image_metrics_mirror_is_not_perfect():
    out = _door_case(lambda t: rotations.quat_multiply(t, HALF_TURN["y"]), 0.5, metric_version=2)
    assert out["axis_rotation_error_deg"][0] == pytest.approx(180.0)
    assert out["axis_direction_error_deg"][0] == pytest.approx(0.0, abs=1e-9)  # folded: same line
    assert out["axis_line_distance_cm"][0] == pytest.approx(0.0, abs=1e-9)
    assert out["mechanism_side_accuracy"][0] == 0.0 and out["opd_success"][0] == 0.0
    assert out["configuration_error"][0] == pytest.approx(0.0, abs=1e-9)  # q compared as labelled


def test_opd_success_of_version_3_is_opds_motion_criterion():
    """OPD's criterion sees the axis line only: a mirrored door on the true hinge line succeeds in
    version 3 (the side metric fails it), and failed in version 2, which also required the side."""
    out = _door_case(lambda t: rotations.quat_multiply(t, HALF_TURN["y"]), 0.5, metric_version=3)
    assert out["opd_success"][0] == 1.0 and out["mechanism_side_accuracy"][0] == 0.0
    assert out["accuracy_5deg_5cm"][0] == 1.0 and out["accuracy_10deg_10cm"][0] == 1.0
    assert "accuracy_5deg_5cm" not in _door_case(lambda t: t, 0.5, metric_version=2)


def test_opd_motion_success_thresholds_are_inclusive():
    diag = 1.0  # m: the origin may be 25 cm from the true axis line
    assert M.opd_motion_success(10.0, 25.0, diag, True) == 1.0
    assert M.opd_motion_success(10.0 + 1e-9, 0.0, diag, True) == 0.0
    assert M.opd_motion_success(0.0, 25.0 + 1e-9, diag, True) == 0.0
    assert M.opd_motion_success(0.0, 300.0, diag, False) == 1.0  # prismatic: origin not checked
    assert np.isnan(M.opd_motion_success(np.nan, 0.0, diag, True))
    assert np.isnan(M.opd_motion_success(0.0, np.nan, diag, True))
    assert M.opd_motion_success(0.0, np.nan, diag, False) == 1.0


def test_axis_accuracy_by_hand():
    # (direction deg, line cm, revolute?) -> 5/5 and 10/10
    cases = [((4.9, 4.9, True), (1.0, 1.0)), ((5.0, 5.0, True), (1.0, 1.0)), ((5.1, 1.0, True), (0.0, 1.0)),
             ((1.0, 7.0, True), (0.0, 1.0)), ((1.0, 10.5, True), (0.0, 0.0)), ((9.0, 80.0, False), (0.0, 1.0)),
             ((4.0, 80.0, False), (1.0, 1.0))]
    for (e_dir, d_line, revolute), want in cases:
        got = tuple(float(M.axis_accuracy(e_dir, d_line, revolute, a, b)) for a, b in M.ACCURACY_THRESHOLDS)
        assert got == want, (e_dir, d_line, revolute)
    assert np.isnan(M.axis_accuracy(np.nan, 0.0, True, 5.0, 5.0))
    assert np.isnan(M.axis_accuracy(1.0, np.nan, True, 5.0, 5.0))


def test_position_error_components_by_hand():
    # true axis along z; the prediction 3 cm up the axis and 4 cm beside it: 3 along, 4 across, 5 in all
    along, across = M.position_error_components_cm([0.04, 0.0, 1.03], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0])
    assert along == pytest.approx(3.0) and across == pytest.approx(4.0)
    assert np.hypot(along, across) == pytest.approx(M.axis_position_error_cm([0.04, 0.0, 1.03], [0.0, 0.0, 1.0]))
    along, _ = M.position_error_components_cm([0.0, 0.0, 0.97], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    assert along == pytest.approx(3.0)  # below the origin: the magnitude


def test_standard_error_of_mean_over_objects_by_hand():
    # two images of each of three objects: per-object means 1, 2, 6 -> mean 3, std(ddof=1) sqrt(7), SEM sqrt(7/3)
    values = np.array([0.0, 2.0, 2.0, 2.0, 5.0, 7.0])
    objects = np.array([0, 0, 1, 1, 2, 2])
    assert M.standard_error_of_mean(values, objects) == pytest.approx(np.sqrt(7.0 / 3.0))
    assert np.isnan(M.standard_error_of_mean(values, np.zeros(6)))  # one object: no spread to measure
    with_nan = np.array([0.0, 2.0, np.nan, 2.0, 5.0, 7.0])  # NaN left out: object 1's mean stays 2
    assert M.standard_error_of_mean(with_nan, objects) == pytest.approx(np.sqrt(7.0 / 3.0))
    assert M.standard_error_of_mean(np.array([1.0, np.inf, 1.0, 2.0]), np.array([0, 0, 1, 1])) == np.inf


def test_prismatic_joint_has_no_mechanism_side():
    truth = {"axis_pose": np.array([[_pose([1, 0, 0], DRAWER)]]), "q": np.array([[0.1]]),
             "geometry": np.array([[0.5, 0.5, 0.5, 0.0]]), "part_offset": np.array([[[0.0, 0.0, -0.25]]])}
    pred = {"axis_pose": np.array([[_pose([1, 0, 0], rotations.quat_multiply(DRAWER, HALF_TURN["x"]))]]),
            "q": np.array([[-0.1]])}
    out, _ = image_metrics(pred, truth, (PRISMATIC,))
    assert "mechanism_side_accuracy" not in out
    assert out["axis_rotation_error_deg"][0] == pytest.approx(0.0, abs=1e-6)  # reversed pull axis, negated q
    assert out["configuration_error"][0] == pytest.approx(0.0, abs=1e-9)


def test_opd_success_is_undefined_where_the_truth_gives_no_axis():
    got = M.opd_success(np.array([1.0, np.nan, 1.0, 1.0]), np.array([1.0, 1.0, np.nan, 99.0]),
                        np.array([1.0, 1.0, 1.0, 1.0]), np.array([True, True, True, True]))
    assert got[0] == 1.0 and np.isnan(got[1]) and np.isnan(got[2]) and got[3] == 0.0  # not 0: not a failure
    prismatic = M.opd_success(np.array([1.0]), np.array([np.nan]), np.array([np.nan]), np.array([False]))
    assert prismatic[0] == 1.0  # a prismatic origin is not checked
