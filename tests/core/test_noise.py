"""The depth-noise models: statistics of what they produce checked against their parameters."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.noise import (
    KINECT2,
    KINECT2_DEPTH_STEP_M,
    KINECT2_RANDOM_HOLE_P,
    NOISE_MODELS,
    get_noise_model,
    incidence_angle_rad,
    kinect2_axial_sigma_m,
)

#: Quiet variant: every stage off (tests switch on the one they check).
QUIET = replace(KINECT2, lateral_sigma_native_px=0.0, axial_scale=0.0, flying_band_native_px=0.0,
                random_hole_p=0.0, grazing_start_deg=89.0, grazing_end_deg=89.5, depth_step_m=0.0)


def _K(f: float, W: int, H: int) -> np.ndarray:
    return np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _plane(K: np.ndarray, W: int, H: int, z0_m: float, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth of a plane through (0, 0, z0) (optical frame) rotated by ``tilt_deg`` about the
    image's vertical axis, and the exact incidence angle of every pixel's ray on it."""
    a = math.radians(tilt_deg)
    n = np.array([math.sin(a), 0.0, -math.cos(a)])
    v, u = np.mgrid[0:H, 0:W]
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], axis=-1)
    z = (n @ np.array([0.0, 0.0, z0_m])) / (ray @ n)
    theta = np.arccos(np.abs(ray @ n) / np.linalg.norm(ray, axis=-1))
    return z.astype(np.float32), theta


def test_registry_and_unknown_name():
    assert {"none", "kinect2"} <= set(NOISE_MODELS)
    assert get_noise_model("kinect2") is KINECT2
    with pytest.raises(UserError, match="unknown noise model 'kinect3'.*none.*kinect2"):
        get_noise_model("kinect3")


def test_none_is_identity_and_draws_nothing():
    rng = np.random.default_rng(3)
    state = rng.bit_generator.state
    depth = np.random.default_rng(0).random((7, 9)).astype(np.float32)
    out = get_noise_model("none")(depth, _K(100, 9, 7), rng)
    assert out.dtype == np.float32 and np.array_equal(out, depth)
    assert rng.bit_generator.state == state


def test_deterministic_per_seed():
    K = _K(105.0, 64, 48)
    depth, _ = _plane(K, 64, 48, 1.5, 30.0)
    depth[:, :20] = 0.0
    a = KINECT2(depth, K, np.random.default_rng(7))
    b = KINECT2(depth, K, np.random.default_rng(7))
    c = KINECT2(depth, K, np.random.default_rng(8))
    assert a.dtype == np.float32 and a.shape == depth.shape
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_incidence_angle_of_planes_matches_geometry():
    W, H = 120, 90
    K = _K(150.0, W, H)
    for tilt in (0.0, 25.0, 50.0):
        depth, theta = _plane(K, W, H, 2.0, tilt)
        est = incidence_angle_rad(depth, K)
        assert np.degrees(np.abs(est - theta)).max() < 0.05
    depth[:, :30] = 0.0  # no return: angle 0 there
    assert (incidence_angle_rad(depth, K)[:, :30] == 0).all()


@pytest.mark.parametrize("z0, tilt", [(1.0, 0.0), (2.5, 0.0), (4.0, 0.0), (1.5, 60.0)])
def test_axial_std_matches_sigma(z0, tilt):
    """Residual / sqrt(sigma_z(z, theta)^2 + step^2 / 12) has unit std (step = 1 mm quantisation)."""
    W, H = 240, 200
    K = _K(600.0, W, H)
    depth, theta = _plane(K, W, H, z0, tilt)
    model = replace(KINECT2, lateral_sigma_native_px=0.0, random_hole_p=0.0)
    out = model(depth, K, np.random.default_rng(1)).astype(np.float64)
    ok = out > 0
    assert ok.mean() > 0.99
    sigma = kinect2_axial_sigma_m(depth.astype(np.float64), theta)
    total = np.sqrt(sigma**2 + KINECT2_DEPTH_STEP_M**2 / 12.0)
    r = ((out - depth) / total)[ok]
    assert abs(r.std() - 1.0) < 0.03
    assert abs(r.mean()) < 0.03


def test_axial_sigma_formula_hand_values():
    # Fankhauser et al. 2015: 1.5 - 0.5 z + 0.3 z^2 mm at theta = 0
    assert kinect2_axial_sigma_m(1.0) == pytest.approx(1.3e-3)
    assert kinect2_axial_sigma_m(3.0) == pytest.approx(2.7e-3)
    # theta = pi/4: term 0.1 z^1.5 (pi/4)^2 / (pi/4)^2 = 0.1 mm at z = 1
    assert kinect2_axial_sigma_m(1.0, math.pi / 4) == pytest.approx(1.4e-3)


def test_random_holes_fraction():
    W, H = 200, 200
    K = _K(2000.0, W, H)  # narrow field of view: every ray nearly head-on
    depth = np.full((H, W), 1.5, np.float32)
    out = KINECT2(depth, K, np.random.default_rng(2))
    frac = (out == 0).mean()
    n = W * H
    assert abs(frac - KINECT2_RANDOM_HOLE_P) < 4 * math.sqrt(KINECT2_RANDOM_HOLE_P / n)


def test_grazing_and_range_holes():
    W, H = 200, 200
    K = _K(4000.0, W, H)
    mid = 0.5 * (KINECT2.grazing_start_deg + KINECT2.grazing_end_deg)
    depth, theta = _plane(K, W, H, 1.5, mid)
    model = replace(KINECT2, random_hole_p=0.0, lateral_sigma_native_px=0.0)
    out = model(depth, K, np.random.default_rng(4))
    expected = KINECT2.grazing_drop_probability(theta).mean()
    assert expected == pytest.approx(0.5, abs=0.02)
    assert abs((out == 0).mean() - expected) < 4 * math.sqrt(0.25 / (W * H))
    below, _ = _plane(K, W, H, 1.5, KINECT2.grazing_start_deg - 5)
    assert (model(below, K, np.random.default_rng(4)) > 0).all()
    for z in (KINECT2.min_range_m - 0.05, KINECT2.max_range_m + 0.1):
        assert (model(np.full((10, 10), z, np.float32), _K(100, 10, 10), np.random.default_rng(0)) == 0).all()


def test_quantisation_step():
    K = _K(300.0, 100, 80)
    depth, _ = _plane(K, 100, 80, 1.7, 20.0)
    out = KINECT2(depth, K, np.random.default_rng(5)).astype(np.float64)
    v = out[out > 0] / KINECT2_DEPTH_STEP_M
    assert np.abs(v - np.rint(v)).max() < 1e-3
    assert len(np.unique(np.rint(v))) > 3


def _step_edge(W=200, H=100, near=1.0, far=2.0):
    depth = np.full((H, W), far, np.float32)
    depth[:, : W // 2] = near
    return depth


def test_flying_pixels_at_discontinuities():
    W, H = 200, 100
    f = KINECT2.native_focal_px / 2  # half the native resolution: p_edge = 0.5
    K = _K(f, W, H)
    model = replace(QUIET, flying_band_native_px=KINECT2.flying_band_native_px)
    p = model.flying_probability(K)
    assert p == pytest.approx(0.5)
    depth = _step_edge(W, H)
    out = model(depth, K, np.random.default_rng(6))
    edge = out[:, W // 2 - 1 : W // 2 + 1]
    mixed = (edge > 1.0) & (edge < 2.0)
    assert abs(mixed.mean() - p) < 4 * math.sqrt(p * (1 - p) / edge.size)
    rest = np.delete(out, [W // 2 - 1, W // 2], axis=1)
    assert np.array_equal(rest, np.delete(depth, [W // 2 - 1, W // 2], axis=1))
    # next to no return: dropped instead of mixed
    holed = depth.copy()
    holed[:, W // 2 :] = 0.0
    out = model(holed, K, np.random.default_rng(6))
    col = out[:, W // 2 - 1]
    assert set(np.unique(col)) <= {0.0, 1.0}
    assert abs((col == 0).mean() - p) < 4 * math.sqrt(p * (1 - p) / col.size)


def test_lateral_noise_moves_edges_by_its_sigma():
    """A pixel k columns right of a step edge reads the left side when round(s n) <= -k,
    n ~ N(0, 1): probability Phi(-(k - 0.5) / s), s = 1.6 px at the native focal length."""
    from math import erf, sqrt

    W, H = 200, 400
    K = _K(KINECT2.native_focal_px, W, H)
    model = replace(QUIET, lateral_sigma_native_px=KINECT2.lateral_sigma_native_px)
    s = model.lateral_sigma_px(K)
    assert s == pytest.approx(1.6)
    out = model(_step_edge(W, H), K, np.random.default_rng(9))
    for k in (1, 2, 3):
        p = 0.5 * (1 + erf(-(k - 0.5) / s / sqrt(2)))
        col = out[:, W // 2 + k - 1]
        assert abs((col == 1.0).mean() - p) < 4 * math.sqrt(p * (1 - p) / H)


def test_pipeline_noise_is_seeded_and_keeps_labels(tmp_path):
    from articulated_dataset.format import open_split
    from articulated_dataset.generation import GenerationConfig, generate_split

    base = dict(class_name="microwave", split="test", n_objects=1, images_per_object=2)
    clean = generate_split(GenerationConfig(**base), tmp_path / "clean")
    noisy = generate_split(GenerationConfig(**base, noise="kinect2"), tmp_path / "noisy")
    again = generate_split(GenerationConfig(**base, noise="kinect2"), tmp_path / "again")
    (_, [a]), (_, [b]), (_, [c]) = open_split(clean), open_split(noisy), open_split(again)
    assert np.array_equal(b.read("depth"), c.read("depth"))
    assert np.array_equal(a.read("mask"), b.read("mask"))
    assert np.array_equal(a.read("axis_pose"), b.read("axis_pose"))
    da, db = a.read("depth"), b.read("depth")
    both = (da > 0) & (db > 0)
    diff = (db - da)[both]
    assert np.abs(diff).max() > 0 and np.abs(np.median(diff)) < 1e-3
    assert 0.5e-3 < diff.std() < 0.05  # a few mm plus the flying pixels
    assert b.attrs["noise_model"] == "kinect2"
