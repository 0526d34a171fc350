"""The d435 (active stereo) and azure-kinect (time of flight) depth-noise models: what they
produce on rendered planes, boxes and corners, checked against their formulas and constants."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.noise import (
    AZURE_KINECT,
    D435,
    D435_BASELINE_M,
    D435_NATIVE_FOCAL_PX,
    KINECT2,
    NOISE_MODELS,
    concavity_m,
    get_noise_model,
    stereo_occlusion_mask,
)

#: The two models of this file, by registry name.
MODELS = {"d435": D435, "azure-kinect": AZURE_KINECT}
#: Quiet variants: no axial noise, holes, quantisation or grazing losses (tests switch on what they check).
QUIET_D435 = replace(D435, axial_scale=0.0, random_hole_p=0.0, depth_step_m=0.0, flying_band_native_px=0.0,
                     grazing_start_deg=89.0, grazing_end_deg=89.5)
QUIET_AZURE = replace(AZURE_KINECT, axial_scale=0.0, random_hole_p=0.0, depth_step_m=0.0, flying_band_native_px=0.0,
                      grazing_start_deg=89.0, grazing_end_deg=89.5, systematic_const_m=0.0, systematic_fraction=0.0,
                      multipath_gain=0.0)
#: Depths (m) of the noise-versus-distance checks, inside both sensors' ranges.
DISTANCES_M = (0.6, 1.0, 2.0, 3.5)
#: Azure Kinect DK hardware specification (NFOV unbinned): random error std <= 17 mm, systematic
#: error < 11 mm + 0.1% of the distance.
SPEC_RANDOM_STD_M = 0.017
SPEC_SYSTEMATIC_M, SPEC_SYSTEMATIC_FRACTION = 0.011, 0.001


def _K(f: float, W: int, H: int) -> np.ndarray:
    return np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _box_on_wall(W=240, H=160, near=1.0, far=2.0, box=(40, 120, 80, 160)):
    """z-depth of a fronto-parallel wall at ``far`` with a box face at ``near`` over rows
    ``box[0]:box[1]``, columns ``box[2]:box[3]``."""
    depth = np.full((H, W), far, np.float32)
    r0, r1, c0, c1 = box
    depth[r0:r1, c0:c1] = near
    return depth


def _binomial_ok(count: int, n: int, p: float) -> bool:
    """``count`` of ``n`` Bernoulli(p) draws within 4 standard deviations of ``n p``."""
    return abs(count - n * p) <= 4 * math.sqrt(n * p * (1 - p)) + 1


def _total_std_m(model, z_m: float, theta_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """Predicted std (m) of noisy - clean at depth ``z_m`` and incidence ``theta_rad``: the
    model's axial sigma and the uniform rounding error of its output step."""
    return np.sqrt(model.axial_sigma_m(z_m, theta_rad) ** 2 + model.depth_step_m**2 / 12.0)


def _fronto_parallel_incidence_rad(K: np.ndarray, W: int, H: int) -> np.ndarray:
    """Incidence angle of each pixel's ray on a plane facing the camera: the ray's angle to the
    optical axis."""
    v, u = np.mgrid[0:H, 0:W]
    return np.arctan(np.hypot((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]))


def test_registered_by_name():
    assert get_noise_model("d435") is D435 and get_noise_model("azure-kinect") is AZURE_KINECT
    assert get_noise_model("kinect2") is KINECT2
    assert list(NOISE_MODELS) == ["none", "kinect2", "d435", "azure-kinect"]
    with pytest.raises(UserError, match="unknown noise model 'realsense'.*kinect2, d435, azure-kinect"):
        get_noise_model("realsense")


def test_d435_rms_error_formula_hand_values():
    # Intel: RMS = z^2 subpixel / (f baseline); f = 424 / tan(43.5 deg) = 446.8 px at 848 x 480
    assert D435_NATIVE_FOCAL_PX == pytest.approx(446.80, abs=0.01)
    assert float(D435.axial_sigma_m(1.0)) == pytest.approx(0.08 / (446.80 * 0.050), rel=1e-4)  # 3.58 mm
    assert float(D435.axial_sigma_m(2.0)) == pytest.approx(4 * float(D435.axial_sigma_m(1.0)))
    # nearest depth: f B / 126 px of disparity search
    assert D435.min_range_m == pytest.approx(446.80 * 0.050 / 126, rel=1e-4)


@pytest.mark.parametrize("z_m", DISTANCES_M)
def test_d435_std_on_a_flat_patch_follows_the_quadratic_formula(z_m):
    W, H = 240, 200
    K = _K(300.0, W, H)
    depth = np.full((H, W), z_m, np.float32)
    out = D435(depth, K, np.random.default_rng(11)).astype(np.float64)
    patch = out[20:-20, 60:-20]  # clear of the left border band (f B / z <= 25 px)
    ok = patch > 0
    assert ok.mean() > 0.97  # 1% random holes only
    r = (patch - z_m)[ok]
    assert r.std() == pytest.approx(float(_total_std_m(D435, z_m)), rel=0.03)
    assert abs(r.mean()) < 0.05 * r.std()


def test_d435_std_grows_with_the_square_of_distance():
    W, H = 240, 200
    K = _K(300.0, W, H)
    stds = []
    for z in (1.0, 3.0):
        out = D435(np.full((H, W), z, np.float32), K, np.random.default_rng(5)).astype(np.float64)[:, 60:]
        stds.append((out - z)[out > 0].std())
    assert stds[1] / stds[0] == pytest.approx(9.0, rel=0.05)


@pytest.mark.parametrize("z_m", DISTANCES_M)
def test_azure_std_on_a_flat_patch_follows_the_model_within_spec(z_m):
    W, H = 240, 200
    K = _K(300.0, W, H)
    out = AZURE_KINECT(np.full((H, W), z_m, np.float32), K, np.random.default_rng(12)).astype(np.float64)
    ok = out > 0
    assert ok.mean() > 0.97
    r = (out - z_m)[ok]
    # residual over the predicted std (the signal falls as cos(incidence) toward the image corners)
    unit = (r - r.mean()) / _total_std_m(AZURE_KINECT, z_m, _fronto_parallel_incidence_rad(K, W, H))[ok]
    assert unit.std() == pytest.approx(1.0, abs=0.02)
    assert r.std() <= SPEC_RANDOM_STD_M
    # the image's systematic offset is within the specification's bound
    assert abs(r.mean()) < SPEC_SYSTEMATIC_M + SPEC_SYSTEMATIC_FRACTION * z_m + 4 * r.std() / math.sqrt(r.size)


def test_azure_systematic_offset_is_drawn_per_image_within_the_bound():
    z = 2.0
    K = _K(100.0, 30, 20)
    means = []
    for seed in range(40):
        out = AZURE_KINECT(np.full((20, 30), z, np.float32), K, np.random.default_rng(seed))
        means.append((out[out > 0] - z).mean())  # random error of the mean: 8.8 mm / sqrt(~590) = 0.4 mm
    means = np.array(means)
    bound = SPEC_SYSTEMATIC_M + SPEC_SYSTEMATIC_FRACTION * z  # 13 mm
    assert float(AZURE_KINECT.systematic_bound_m(z)) == pytest.approx(bound)
    assert np.abs(means).max() < bound + 0.002
    assert means.std() > 0.4 * bound  # U(-1, 1) * bound: std 0.58 * bound


def test_d435_stereo_shadow_left_of_a_foreground_edge():
    W, H = 240, 160
    f = 300.0
    K = _K(f, W, H)
    near, far = 1.0, 2.0
    depth = _box_on_wall(W, H, near, far)
    out = QUIET_D435(depth, K, np.random.default_rng(0))
    band_px = f * D435_BASELINE_M * (1 / near - 1 / far)  # 7.5 px of wall hidden from the right imager
    border_px = f * D435_BASELINE_M / far  # 7.5 px lost at the left image border
    cols = np.arange(W)
    border = cols - border_px < -0.5  # falls left of the right image
    shadow = (cols < 80) & (cols > 80 - band_px)  # behind the box's left edge for the right imager
    assert border.sum() == 7 and shadow.sum() == 7
    expected = np.tile(border, (H, 1))
    expected[40:120] |= shadow
    assert np.array_equal(out == 0, expected)
    assert np.array_equal(stereo_occlusion_mask(depth, K, D435_BASELINE_M), expected)
    assert np.allclose(out[~expected], depth[~expected], rtol=1e-6, atol=0)


def test_d435_drops_edge_pixels_and_never_mixes_depths():
    W, H = 240, 400
    f = D435_NATIVE_FOCAL_PX / 2  # p_edge = 0.5
    K = _K(f, W, H)
    model = replace(QUIET_D435, flying_band_native_px=D435.flying_band_native_px)
    p = model.flying_probability(K)
    assert p == pytest.approx(0.5)
    depth = _box_on_wall(W, H, 1.0, 2.0, box=(0, H, 80, 160))
    out = model(depth, K, np.random.default_rng(3))
    on_a_surface = np.isclose(out, 0.0) | np.isclose(out, 1.0) | np.isclose(out, 2.0)
    assert on_a_surface.all()  # nothing between the surfaces
    right_edge = out[:, 159:161]  # box column 159 and wall column 160 across the right edge
    assert _binomial_ok(int((right_edge == 0).sum()), right_edge.size, p)
    assert np.allclose(out[:, 170:], 2.0)


def test_azure_flying_pixels_at_edges():
    W, H = 240, 400
    f = AZURE_KINECT.native_focal_px / 2
    K = _K(f, W, H)
    model = replace(QUIET_AZURE, flying_band_native_px=AZURE_KINECT.flying_band_native_px)
    p = model.flying_probability(K)
    assert p == pytest.approx(0.5)
    depth = _box_on_wall(W, H, 1.0, 2.0, box=(0, H, 80, 160))
    out = model(depth, K, np.random.default_rng(4))
    edges = np.concatenate([out[:, 79:81], out[:, 159:161]], axis=1)
    mixed = (edges > 1.0) & (edges < 2.0)
    dropped = edges == 0
    share = model.edge_mix_fraction
    assert 0 < share < 1 and mixed.any() and dropped.any()  # flying pixels, and invalidated ones
    assert _binomial_ok(int(mixed.sum()), edges.size, p * share)
    assert _binomial_ok(int(dropped.sum()), edges.size, p * (1 - share))
    rest = np.delete(out, [79, 80, 159, 160], axis=1)
    assert np.array_equal(rest, np.delete(depth, [79, 80, 159, 160], axis=1))


def _open_book(W: int, H: int, f: float, crease_m: float, half_angle_deg: float) -> np.ndarray:
    """z-depth of two planes meeting in a vertical crease at depth ``crease_m`` on the optical
    axis, each at ``half_angle_deg`` to the viewing direction (the inside of a corner)."""
    u = np.arange(W) - (W - 1) / 2
    slope = 1.0 / math.tan(math.radians(half_angle_deg))  # z = crease - slope |x|, x = u z / f
    z = crease_m / (1.0 + slope * np.abs(u) / f)
    return np.tile(z[None, :], (H, 1)).astype(np.float32)


def test_azure_multipath_pushes_the_inside_of_a_corner_away():
    W, H = 240, 60
    K = _K(300.0, W, H)
    corner = _open_book(W, H, 300.0, 1.5, 45.0)  # a 90 deg inside corner
    assert concavity_m(np.full((H, W), 1.5), K, AZURE_KINECT.multipath_radius_m).max() == 0.0
    # quiet but for the systematic offset s * bound(z) (s drawn per image) and the multipath
    model = replace(AZURE_KINECT, axial_scale=0.0, random_hole_p=0.0, depth_step_m=0.0, flying_band_native_px=0.0,
                    grazing_start_deg=89.0, grazing_end_deg=89.5)
    out = model(corner, K, np.random.default_rng(0)).astype(np.float64)
    bound = model.systematic_bound_m(corner)
    s = float(np.median(((out - corner) / bound)[:, :20]))  # far from the crease: no multipath
    assert abs(s) <= 1.0
    bias = out - corner - s * bound
    expected = model.multipath_offset_m(corner, K)
    assert np.allclose(bias, expected, atol=1e-6)
    crease = bias[:, W // 2 - 1 : W // 2 + 1]
    # about gain * radius / 2 at the crease (1 cm), nothing far from it
    assert crease.min() == pytest.approx(model.multipath_gain * model.multipath_radius_m / 2, rel=0.25)
    assert np.abs(bias[:, :20]).max() < 1e-6  # float32 output
    # a sharp corner is pushed beyond the systematic bound there: the sensor invalidates it
    sharp = _open_book(W, H, 300.0, 1.5, 15.0)
    lost = model.multipath_offset_m(sharp, K) > model.systematic_bound_m(sharp)
    assert lost.any() and not lost.all()
    assert np.array_equal(model(sharp, K, np.random.default_rng(0)) == 0, lost)


@pytest.mark.parametrize("name", MODELS)
def test_outside_the_operating_range_is_invalid(name):
    model = MODELS[name]
    K = _K(100.0, 40, 30)
    for z in (0.9 * model.min_range_m, 1.05 * model.max_range_m):
        assert (model(np.full((30, 40), z, np.float32), K, np.random.default_rng(0)) == 0).all()
    inside = model(np.full((30, 40), 0.5 * (model.min_range_m + min(model.max_range_m, 4.0)), np.float32), K,
                   np.random.default_rng(0))
    assert (inside[:, 20:] > 0).mean() > 0.95


@pytest.mark.parametrize("name", MODELS)
def test_deterministic_invalid_is_zero_and_quantised(name):
    model = MODELS[name]
    W, H = 120, 90
    K = _K(105.0, W, H)
    depth = _box_on_wall(W, H, 1.2, 2.1, box=(20, 70, 40, 90))
    depth[:, 100:] = 0.0  # no return
    a = model(depth, K, np.random.default_rng(7))
    b = model(depth, K, np.random.default_rng(7))
    c = model(depth, K, np.random.default_rng(8))
    assert a.dtype == np.float32 and a.shape == depth.shape
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.isfinite(a).all() and (a >= 0).all()
    assert (a[:, 100:] == 0).all()
    steps = a[a > 0].astype(np.float64) / model.depth_step_m
    assert np.abs(steps - np.rint(steps)).max() < 1e-3
    assert 0 < (a == 0)[:, :100].mean() < 0.5


@pytest.mark.parametrize("name", MODELS)
def test_sensor_noise_transform_by_name(name):
    from articulated_dataset.training.transforms import SensorNoise

    K = _K(105.0, 64, 48)
    sample = {"depth": _box_on_wall(64, 48, 1.0, 1.8, box=(10, 30, 20, 40)), "K": K}
    out = SensorNoise(name)(sample, np.random.default_rng(1))["depth"]
    assert np.array_equal(out, MODELS[name](sample["depth"], K, np.random.default_rng(1)))
    assert not np.array_equal(out, sample["depth"])


def test_cli_help_lists_every_model():
    from articulated_dataset.cli import main

    names = [n for n in NOISE_MODELS if n != "none"]
    for command in ("generate", "train"):
        text = " ".join(CliRunner().invoke(main, [command, "--help"]).output.split())
        assert all(n in text for n in names), (command, text)


@pytest.mark.parametrize("name", MODELS)
def test_generate_with_the_model_end_to_end(name, tmp_path):
    from articulated_dataset.cli import main
    from articulated_dataset.format import open_split

    args = ["generate", "--class", "microwave", "--n", "2", "--images", "2", "--workers", "1", "-q"]
    for noise, out in (("none", "clean"), (name, "noisy")):
        r = CliRunner().invoke(main, args + ["--noise", noise, "--out", str(tmp_path / out)])
        assert r.exit_code == 0, r.output
    (_, [clean]), (_, [noisy]) = (open_split(tmp_path / out / "microwave" / "train") for out in ("clean", "noisy"))
    assert noisy.attrs["noise_model"] == name
    assert np.array_equal(clean.read("mask"), noisy.read("mask"))
    da, db = clean.read("depth"), noisy.read("depth")
    both = (da > 0) & (db > 0)
    diff = (db - da)[both]
    assert np.abs(diff).max() > 0 and np.abs(np.median(diff)) < 0.015  # a few mm of noise, at most the offset
    assert ((da > 0) & (db == 0)).any()  # edge dropouts / invalidated pixels
    assert not ((da == 0) & (db > 0)).any()  # no depth appears where nothing was rendered
