"""The point-likelihood axis estimate (Table 2 procedure) on simulated observations."""

from __future__ import annotations

import numpy as np
import pytest

from articulated_dataset.benchmark.pointlik import (
    object_cloud,
    origin_log_likelihood,
    snap_axis_origins,
    snap_axis_poses,
    snap_batch,
)
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split


def _layout(n_joints: int, rng: np.random.Generator) -> list[str]:
    names = [f"j{j}.{k}.{c}" for j in range(n_joints) for k in ("origin", "axis", "xaxis") for c in "xyz"]
    names += [f"j{j}.q" for j in range(n_joints)] + ["geometry.depth", "geometry.width"]
    return list(rng.permutation(names))


def _mixture(layout: list[str], centres: dict[str, float], rng: np.random.Generator, M: int = 5, spread_m: float = 0.0):
    """M components; column named in ``centres`` has mean centres[name] (+ spread), others random."""
    D = len(layout)
    means = rng.normal(size=(M, D))
    for name, value in centres.items():
        means[:, layout.index(name)] = value + spread_m * rng.normal(size=M)
    scales = rng.uniform(0.05, 0.3, size=(M, D))
    weights = rng.dirichlet(np.ones(M))
    return weights, means, scales


def _image(tiny_root, class_name: str, index: int = 3):
    manifest, shards = open_split(tiny_root / class_name / "test")
    sh = shards[0]
    return sh.sample(index), sh.K


@pytest.mark.parametrize("class_name", ["cabinet", "cabinet2", "drawer"])
def test_mixture_on_true_axis_picks_nearest_cloud_point(tiny_root, class_name):
    rng = np.random.default_rng(0)
    s, K = _image(tiny_root, class_name)
    cloud = object_cloud(s["depth"], s["mask"], K)
    assert cloud.shape[0] > 100
    J = s["q"].shape[0]
    layout = _layout(J, rng)
    for j in range(J):
        truth = s["axis_origin"][j].astype(np.float64)
        # every component centred on the true origin, isotropic over x/y/z, differing scales
        weights, means, scales = _mixture(layout, {f"j{j}.origin.{c}": truth[i] for i, c in enumerate("xyz")}, rng)
        cols = [layout.index(f"j{j}.origin.{c}") for c in "xyz"]
        scales[:, cols] = scales[:, cols[:1]]
        got = snap_axis_origins(cloud, weights, means, scales, layout, j)
        nearest = cloud[np.argmin(np.linalg.norm(cloud - truth, axis=1))]
        np.testing.assert_array_equal(got, nearest)
        # the snapped point is a cloud point near the hinge (which may be hidden behind the door)
        assert np.linalg.norm(got - truth) < 0.25


def test_other_joint_columns_are_ignored(tiny_root):
    rng = np.random.default_rng(1)
    s, K = _image(tiny_root, "refrigerator")
    cloud = object_cloud(s["depth"], s["mask"], K)
    layout = _layout(2, rng)
    t1 = s["axis_origin"][1].astype(np.float64)
    centres = {f"j1.origin.{c}": t1[i] for i, c in enumerate("xyz")}
    centres.update({f"j0.origin.{c}": 10.0 for c in "xyz"})  # joint 0's columns far away
    weights, means, scales = _mixture(layout, centres, rng, M=1)
    cols = [layout.index(f"j1.origin.{c}") for c in "xyz"]
    scales[:, cols] = 0.05
    got = snap_axis_origins(cloud, weights, means, scales, layout, 1)
    np.testing.assert_array_equal(got, cloud[np.argmin(np.linalg.norm(cloud - t1, axis=1))])


def test_log_likelihood_matches_scipy_reference():
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(2)
    layout = _layout(1, rng)
    weights, means, scales = _mixture(layout, {}, rng, M=4)
    weights[1] = 0.0
    weights /= weights.sum()
    points = rng.normal(size=(50, 3))
    cols = [layout.index(f"j0.origin.{c}") for c in "xyz"]
    ref = np.log(sum(w * stats.multivariate_normal(mean=m[cols], cov=np.diag(s[cols] ** 2)).pdf(points)
                     for w, m, s in zip(weights, means, scales)))
    np.testing.assert_allclose(origin_log_likelihood(points, weights, means, scales, layout, 0), ref, rtol=1e-10)


def test_far_points_do_not_underflow():
    layout = ["j0.origin.x", "j0.origin.y", "j0.origin.z"]
    means = np.array([[0.0, 0.0, 0.0]])
    scales = np.full((1, 3), 1e-4)
    points = np.array([[1.0, 0.0, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 1.1]])
    ll = origin_log_likelihood(points, np.ones(1), means, scales, layout, 0)
    assert np.isfinite(ll).all()
    np.testing.assert_array_equal(snap_axis_origins(points, np.ones(1), means, scales, layout, 0), points[1])


def test_bad_inputs():
    layout = ["j0.origin.x", "j0.origin.y", "j0.origin.z"]
    mix = (np.ones(1), np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(UserError, match="empty"):
        snap_axis_origins(np.empty((0, 3)), *mix, layout, 0)
    with pytest.raises(UserError, match="j1.origin.x"):
        snap_axis_origins(np.zeros((2, 3)), *mix, layout, 1)


def test_batch_helper_and_fallback(tiny_root):
    rng = np.random.default_rng(4)
    manifest, shards = open_split(tiny_root / "microwave" / "test")
    sh = shards[0]
    depth, mask = sh.read("depth", slice(0, 3)), sh.read("mask", slice(0, 3))
    origin = sh.read("axis_origin", slice(0, 3)).astype(np.float64)
    layout = _layout(1, rng)
    N, M = 3, 2
    weights = np.full((N, M), 0.5)
    means = rng.normal(size=(N, M, len(layout)))
    scales = np.full((N, M, len(layout)), 0.1)
    for c, name in enumerate("xyz"):
        means[:, :, layout.index(f"j0.origin.{name}")] = origin[:, 0, c][:, None]
    depth[2] = 0.0  # no returns: falls back
    fallback = np.full((N, 1, 3), 7.0)
    out, snapped = snap_batch(depth, mask, sh.K, weights, means, scales, layout, 1, fallback=fallback)
    assert snapped.tolist() == [True, True, False]
    np.testing.assert_array_equal(out[2], fallback[2])
    for i in range(2):
        cloud = object_cloud(depth[i], mask[i], sh.K)
        np.testing.assert_array_equal(out[i, 0], cloud[np.argmin(np.linalg.norm(cloud - origin[i, 0], axis=1))])
    with pytest.raises(UserError, match="image 2"):
        snap_batch(depth, mask, sh.K, weights, means, scales, layout, 1)
    pose = np.zeros((N, 1, 7))
    pose[..., 3] = 1.0
    snapped_pose = snap_axis_poses(pose, out)
    np.testing.assert_array_equal(snapped_pose[..., :3], out)
    np.testing.assert_array_equal(snapped_pose[..., 3:], pose[..., 3:])
