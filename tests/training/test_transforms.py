"""Shared numpy transforms: hand-worked crops/resizes, intrinsics through projection, seeding."""

import importlib.util

import numpy as np
import pytest

from articulated_dataset.core.camera import CameraConfig, project
from articulated_dataset.core.errors import UserError
from articulated_dataset.training.transforms import (
    CenterCrop,
    ClipDepth,
    Compose,
    Crop,
    PixelDropout,
    RandomCrop,
    Resize,
    SensorNoise,
    apply_to_batch,
    sample_rng,
)

H, W = 12, 16


def make_sample(rng=None):
    rng = rng or np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, size=(H, W)).astype(np.float32)
    depth[0, 0] = 0.0
    mask = (np.arange(H * W).reshape(H, W) % 3).astype(np.uint8)
    K = CameraConfig(width_px=W, height_px=H).K
    return {"depth": depth, "mask": mask, "K": K, "q": np.array([0.3], np.float32)}


def points_in_view(K, n=50, seed=0):
    """Camera-frame points (x forward) that project inside a W x H image."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(1, 3, n)
    uv = np.stack([rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)], axis=1)
    y = -(uv[:, 0] - K[0, 2]) * x / K[0, 0]  # optical x right = camera -y
    z = -(uv[:, 1] - K[1, 2]) * x / K[1, 1]
    return np.stack([x, y, z], axis=1), uv


def test_crop_values_and_intrinsics():
    s = make_sample()
    out = Crop(top_px=2, left_px=3, height_px=5, width_px=7)(s, np.random.default_rng(0))
    np.testing.assert_array_equal(out["depth"], s["depth"][2:7, 3:10])
    np.testing.assert_array_equal(out["mask"], s["mask"][2:7, 3:10])
    assert out["q"] is s["q"]  # labels untouched
    p, uv = points_in_view(s["K"])
    uv2, _ = project(p, out["K"])
    np.testing.assert_allclose(uv2, uv - [3, 2], atol=1e-9)  # a point's pixel moves with the window
    centre = CenterCrop(6, 8)(s, None)
    np.testing.assert_array_equal(centre["depth"], s["depth"][3:9, 4:12])


def test_resize_nearest_hand_worked_and_intrinsics():
    s = make_sample()
    up = Resize(2 * H, 2 * W)(s, None)
    np.testing.assert_array_equal(up["depth"], np.repeat(np.repeat(s["depth"], 2, 0), 2, 1))
    down = Resize(H // 2, W // 2)(s, None)
    # each output pixel centre (i + 1/2) * 2 falls in input pixel 2 i + 1
    np.testing.assert_array_equal(down["mask"], s["mask"][1::2, 1::2])
    p, uv = points_in_view(s["K"])
    for out, sx, sy in ((up, 2, 2), (down, 0.5, 0.5), (Resize(7, 20)(s, None), 20 / W, 7 / H)):
        uv2, _ = project(p, out["K"])
        np.testing.assert_allclose(uv2, np.stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5], 1),
                                   atol=1e-9)


def test_random_crop_is_seeded_and_in_bounds():
    s = make_sample()
    t = RandomCrop(5, 6)
    a, b = t(s, np.random.default_rng(3)), t(s, np.random.default_rng(3))
    np.testing.assert_array_equal(a["depth"], b["depth"])
    seen = set()
    for k in range(40):
        out = t(s, np.random.default_rng(k))
        top, left = int(s["K"][1, 2] - out["K"][1, 2]), int(s["K"][0, 2] - out["K"][0, 2])
        assert 0 <= top <= H - 5 and 0 <= left <= W - 6
        np.testing.assert_array_equal(out["depth"], s["depth"][top : top + 5, left : left + 6])
        seen.add((top, left))
    assert len(seen) > 10
    with pytest.raises(UserError, match="does not fit"):
        RandomCrop(H + 1, 2)(s, np.random.default_rng(0))
    with pytest.raises(UserError, match="does not fit"):
        Crop(0, 10, 4, 10)(s, None)
    with pytest.raises(UserError, match="positive"):
        Resize(0, 3)


def test_clip_depth():
    d = np.array([[0.0, 0.2, 1.0, 5.0]], np.float32)
    s = {"depth": d}
    np.testing.assert_array_equal(ClipDepth(0.5, 4.0)(s, None)["depth"], [[0, 0, 1, 0]])
    np.testing.assert_array_equal(ClipDepth(0.5, 4.0, clamp=True)(s, None)["depth"], [[0, 0.5, 1, 4]])
    with pytest.raises(UserError, match="depth range"):
        ClipDepth(3.0, 1.0)


def test_pixel_dropout():
    s = make_sample()
    assert np.array_equal(PixelDropout(0.0)(s, np.random.default_rng(0))["depth"], s["depth"])
    assert not PixelDropout(1.0)(s, np.random.default_rng(0))["depth"].any()
    big = {"depth": np.ones((200, 200), np.float32), "mask": np.ones((200, 200), np.uint8)}
    out = PixelDropout(0.3)(big, np.random.default_rng(1))
    assert abs((out["depth"] == 0).mean() - 0.3) < 0.01  # 40,000 Bernoulli draws: sd 0.0023
    np.testing.assert_array_equal(out["mask"], big["mask"])
    np.testing.assert_array_equal(out["depth"], PixelDropout(0.3)(big, np.random.default_rng(1))["depth"])
    with pytest.raises(UserError, match="probability"):
        PixelDropout(1.5)


@pytest.mark.skipif(importlib.util.find_spec("articulated_dataset.core.noise") is None,
                    reason="articulated_dataset.core.noise (sensor-noise models) is not available")
def test_sensor_noise_wraps_the_noise_model():
    from articulated_dataset.core.noise import get_noise_model

    s = make_sample()
    out = SensorNoise("kinect2")(s, np.random.default_rng(5))
    ref = get_noise_model("kinect2")(s["depth"], s["K"], np.random.default_rng(5))
    np.testing.assert_array_equal(out["depth"], ref)
    assert out["depth"].dtype == np.float32 and not np.array_equal(out["depth"], s["depth"])
    with pytest.raises(UserError, match="'K'"):
        SensorNoise("kinect2")({"depth": s["depth"]}, np.random.default_rng(0))
    with pytest.raises(UserError, match="unknown noise model"):
        SensorNoise("nope")(s, np.random.default_rng(0))


def test_apply_to_batch_seeding():
    rng = np.random.default_rng(0)
    samples = [make_sample(rng) for _ in range(4)]
    batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}
    t = Compose([RandomCrop(8, 8), PixelDropout(0.5)])
    idx = np.array([10, 11, 12, 13])
    a = apply_to_batch(t, batch, idx, seed=1, epoch=0)
    b = apply_to_batch(t, batch, idx, seed=1, epoch=0)
    c = apply_to_batch(t, batch, idx, seed=1, epoch=1)
    assert a["depth"].shape == (4, 8, 8) and a["K"].shape == (4, 3, 3)
    np.testing.assert_array_equal(a["depth"], b["depth"])
    assert not np.array_equal(a["depth"], c["depth"])
    # each sample's result depends only on (seed, epoch, its own index), not on its batch
    single = apply_to_batch(t, {k: v[2:3] for k, v in batch.items()}, idx[2:3], seed=1, epoch=0)
    np.testing.assert_array_equal(single["depth"][0], a["depth"][2])
    np.testing.assert_array_equal(t(samples[2], sample_rng(1, 0, 12))["depth"], a["depth"][2])


def test_apply_to_batch_per_sample_keys():
    """A dataset whose epoch was never set passes one key per sample (sample_rng's key form)."""
    rng = np.random.default_rng(0)
    samples = [make_sample(rng) for _ in range(3)]
    batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}
    t = PixelDropout(0.5)
    idx = np.array([4, 5, 6])
    keys = np.array([[7, 1, 2, 0, 0], [7, 1, 2, 0, 3], [7, 1, 2, 0, 0]])
    out = apply_to_batch(t, batch, idx, seed=1, epoch=keys)
    for b in range(3):
        np.testing.assert_array_equal(out["depth"][b], t(samples[b], sample_rng(1, keys[b], int(idx[b])))["depth"])
    # a key is not the epoch of the same number, and another visit is another augmentation
    assert not np.array_equal(out["depth"][0], apply_to_batch(t, batch, idx, seed=1, epoch=0)["depth"][0])
    again = apply_to_batch(t, batch, idx, seed=1, epoch=keys + np.array([0, 0, 0, 0, 1]))
    assert not np.array_equal(out["depth"][1], again["depth"][1])
    with pytest.raises(ValueError, match="keys"):
        apply_to_batch(t, batch, idx, seed=1, epoch=keys[:2])


def test_apply_to_batch_names_a_transform_that_returns_no_sample():
    """A user's transform that edits the sample in place and returns None (or returns other fields
    for some samples) is named in the error, not an AttributeError from inside the restacking."""
    rng = np.random.default_rng(0)
    samples = [make_sample(rng) for _ in range(2)]
    batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}

    def forgets_to_return(sample, rng):
        sample["depth"] = sample["depth"] * 2

    with pytest.raises(TypeError, match="forgets_to_return.* returned NoneType"):
        apply_to_batch(forgets_to_return, batch, np.array([0, 1]), seed=0, epoch=0)

    def drops_a_field_once(sample, rng):
        return {k: v for k, v in sample.items() if not (k == "K" and rng.random() < 0.5)}

    with pytest.raises(ValueError, match="different fields"):
        apply_to_batch(drops_a_field_once, {k: np.repeat(v[:1], 16, 0) for k, v in batch.items()}, np.arange(16),
                       seed=0, epoch=0)
