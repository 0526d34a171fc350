"""Table 1 baselines: Mean, exact NN, ICP to the mean object, and ``artdata baseline``."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark import metrics
from articulated_dataset.classes.registry import get_class
from articulated_dataset.cli import main
from articulated_dataset.core import rotations
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.methods.baselines import BASELINES, clouds, icp, icp_model, mean, nn
from articulated_dataset.methods.baselines.common import open_split_checked
from helpers_core import assert_one_line_error, run_cli, split_copy_with

pytest.importorskip("scipy")

#: Class of the ICP tests: its body is visible beside the door in the mean view, so the
#: object's yaw is observable (a cabinet's mean view is its door alone: yaw and door angle
#: trade off exactly, see docs/baselines.md).
ICP_CLASS = "microwave"
#: Yaw offset (rad) of the rendered test object: between two of the 16 initial hypotheses.
YAW_OFFSET_RAD = 0.2
LABELS = ("axis_pose", "q", "geometry", "part_offset")


def _quat_from_axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _yaw_deg(rot):
    """The object's yaw (deg) relative to the model, from ICP's obs -> model rotation ``R = R_z(yaw)^T``."""
    return math.degrees(math.atan2(rot[0, 1], rot[0, 0]))


# --------------------------------------------------------------------------------------
# Mean
# --------------------------------------------------------------------------------------

def test_rotation_mean_about_one_axis_is_circular_mean():
    # chordal L2 mean of rotations about z by 0, 0, 90 deg: maximises sum cos(phi - theta_i),
    # i.e. phi = atan2(sum sin, sum cos) = atan2(1, 2) = 26.565 deg (not the arithmetic 30 deg)
    quats = np.stack([_quat_from_axis_angle([0, 0, 1], a) for a in (0.0, 0.0, math.pi / 2)])
    quats[1] *= -1.0  # the sign of a quaternion must not matter
    m = mean.rotation_mean_quat(quats)
    assert m[0] >= 0
    np.testing.assert_allclose(m, _quat_from_axis_angle([0, 0, 1], math.atan2(1.0, 2.0)), atol=1e-12)
    # symmetric pair: +-40 deg about x averages to the identity
    pair = np.stack([_quat_from_axis_angle([1, 0, 0], s * math.radians(40)) for s in (1, -1)])
    np.testing.assert_allclose(mean.rotation_mean_quat(pair), [1, 0, 0, 0], atol=1e-12)


def test_rotation_mean_equals_projected_matrix_mean():
    rng = np.random.default_rng(3)
    base = _quat_from_axis_angle([0.3, -0.5, 0.8], 2.5)
    quats = rotations.quat_multiply(base, np.stack([_quat_from_axis_angle(rng.normal(size=3), rng.uniform(0, 0.8))
                                                  for _ in range(50)]))
    quats *= rng.choice([-1.0, 1.0], size=(50, 1))
    m = mean.rotation_mean_quat(quats)
    # independent reference: project the mean rotation matrix onto SO(3) with an SVD
    u, _, vt = np.linalg.svd(rotations.quat_to_matrix(quats).mean(axis=0))
    ref = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    np.testing.assert_allclose(rotations.quat_to_matrix(m), ref, atol=1e-10)


@pytest.mark.parametrize("class_name", ["drawer", "cabinet2"])
def test_mean_baseline_equals_analytic_mean(tiny_root, class_name):
    train, test = tiny_root / class_name / "train", tiny_root / class_name / "test"
    result = mean.predict(train, test)
    split = open_split_checked(train, "train")
    truth = {k: split.read(k).astype(np.float64) for k in LABELS}
    split.close()
    p = result.predictions
    test_split = open_split_checked(test, "test")
    np.testing.assert_array_equal(p["sample_id"], test_split.read("sample_id"))
    test_split.close()
    n, J = p["q"].shape
    assert result.method == "Mean" and result.class_name == class_name and J == get_class(class_name).n_joints
    for k in LABELS:  # the same prediction for every test image
        assert np.all(p[k] == p[k][:1])
    np.testing.assert_allclose(p["axis_pose"][0, :, :3], truth["axis_pose"][:, :, :3].mean(0), atol=1e-6)
    np.testing.assert_allclose(p["q"][0], truth["q"].mean(0), atol=1e-6)
    np.testing.assert_allclose(p["geometry"][0], truth["geometry"].mean(0), atol=1e-6)
    np.testing.assert_allclose(p["part_offset"][0], truth["part_offset"].mean(0), atol=1e-6)
    for j in range(J):
        u, _, vt = np.linalg.svd(rotations.quat_to_matrix(truth["axis_pose"][:, j, 3:]).mean(axis=0))
        ref = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
        np.testing.assert_allclose(rotations.quat_to_matrix(p["axis_pose"][0, j, 3:]), ref, atol=1e-5)


# --------------------------------------------------------------------------------------
# NN
# --------------------------------------------------------------------------------------

def test_depth_features_hand_worked():
    depth = np.zeros((1, 9, 10), np.float32)  # 9x10 -> two 4x4 blocks per row band, rest cropped
    depth[0, :4, :4] = 2.0
    depth[0, :4, 4:8] = 1.0
    depth[0, 0, 4] = 0.0  # a hole: the block mean counts it as 0
    depth[0, 8, :] = 5.0  # beyond the last full block row: cropped
    f = nn.depth_features(depth, block_px=4)
    np.testing.assert_allclose(f, [[2.0, 15 / 16, 0.0, 0.0]])
    med = nn.normalize_depth(np.array([[[0.0, 1.0], [2.0, 4.0]]]), "median")
    np.testing.assert_allclose(med, [[[nn.MEDIAN_BACKGROUND_M, -1.0], [0.0, 2.0]]])
    with pytest.raises(ValueError):
        nn.normalize_depth(depth, "nope")


def _brute_force(train, query):
    d = ((query.astype(np.float64)[:, None, :] - train.astype(np.float64)[None]) ** 2).sum(-1)
    return d.argmin(axis=1), d.min(axis=1)  # argmin: first (lowest) index among ties


def test_exact_nn_matches_brute_force_across_chunks():
    rng = np.random.default_rng(0)
    train = rng.normal(size=(301, 37)).astype(np.float32)
    train[150] = train[20]  # an exact duplicate: ties go to the lower index
    query = np.concatenate([rng.normal(size=(40, 37)), train[[20, 7, 300]] + 1e-6]).astype(np.float32)
    index = nn.ExactNearestNeighbour(train, query_chunk=7, train_chunk=13)
    got_i, got_d = index.query(query)
    ref_i, ref_d = _brute_force(train, query)
    np.testing.assert_array_equal(got_i, ref_i)
    np.testing.assert_allclose(got_d, ref_d, rtol=1e-12)
    assert got_i[40] == 20


def test_exact_nn_near_ties_are_decided_by_exact_distances():
    # points on a sphere around the query: float32 GEMM distances cannot order them, so all
    # of them are candidates and the exact float64 re-ranking decides
    rng = np.random.default_rng(1)
    u = rng.normal(size=(64, 16))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    radius = 1.0 + 1e-7 * rng.permutation(64)
    train = (u * radius[:, None]).astype(np.float32)
    query = np.zeros((1, 16), np.float32)
    index = nn.ExactNearestNeighbour(train, train_chunk=16)
    got_i, got_d = index.query(query)
    ref_i, ref_d = _brute_force(train, query)
    assert index.n_reranked > 16  # candidates from several blocks
    assert got_i[0] == ref_i[0] and got_d[0] == pytest.approx(ref_d[0], rel=1e-12)


def test_nn_duplicate_of_a_training_image_returns_its_labels(tiny_root):
    train = tiny_root / "toaster" / "train"
    result = nn.predict(train, train, workers=1)  # every query duplicates a training image
    split = open_split_checked(train, "train")
    n = split.n_images
    np.testing.assert_array_equal(result.extra["nearest_index"], np.arange(n))
    assert np.all(result.extra["nearest_sqdist"] == 0.0)
    for k in LABELS:
        np.testing.assert_array_equal(result.predictions[k], split.read(k))
    np.testing.assert_array_equal(result.predictions["sample_id"], split.read("sample_id"))
    split.close()


# --------------------------------------------------------------------------------------
# ICP
# --------------------------------------------------------------------------------------

def test_kabsch_recovers_a_known_transform_with_outliers_weighted_out():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(2, 50, 3))
    rot = np.stack([rotations.quat_to_matrix(_quat_from_axis_angle(rng.normal(size=3), a)) for a in (0.4, 3.0)])
    t = rng.normal(size=(2, 3))
    dst = np.einsum("hij,hnj->hni", rot, src) + t[:, None]
    w = np.ones((2, 50))
    dst[:, :5] += 10.0  # outliers, weight 0
    w[:, :5] = 0.0
    r_est, t_est = clouds.kabsch(src, dst, w)
    np.testing.assert_allclose(r_est, rot, atol=1e-10)
    np.testing.assert_allclose(t_est, t, atol=1e-10)


def test_matrix_to_quat_round_trip_including_half_turns():
    rng = np.random.default_rng(4)
    q = rng.normal(size=(200, 4))
    q[:3] = [[0, 1, 0, 0], [0, 0.6, -0.8, 0], [0, 0, 0, 1]]  # half-turns: w = 0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = rotations.matrix_to_quat(rotations.quat_to_matrix(q))
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", back, q)), 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def icp_objects(tmp_path_factory):
    """The ICP class's mean object at yaw 0 (the model) and rendered at yaw YAW_OFFSET_RAD."""
    root = tmp_path_factory.mktemp("icp")
    model_dir = generate_split(GenerationConfig(ICP_CLASS, mean=True, n_objects=1), root / "model")
    table = get_class(ICP_CLASS).table.override({"pose": {"yaw_rad": [YAW_OFFSET_RAD, YAW_OFFSET_RAD]}})
    yawed_dir = generate_split(GenerationConfig(ICP_CLASS, mean=True, n_objects=1, table=table), root / "yawed")
    mean_split = open_split_checked(model_dir, "mean")
    model = icp_model.MeanObjectModel.from_split(mean_split, tuple(get_class(ICP_CLASS).table.pose["yaw_rad"]))
    mean_split.close()
    return model_dir, yawed_dir, model


def test_icp_recovers_yaw_of_a_moved_model_cloud(icp_objects):
    _, _, model = icp_objects
    m = 5
    yaw = 0.3
    rot = clouds.rotation_about_axis(model.up, yaw)
    c = model.base_centre_m
    shift = np.array([0.12, -0.07, 0.03])
    obs = (model.clouds[m] - c) @ rot.T + c + shift
    fit = model.register(obs)
    assert fit.model_index == m
    assert abs(_yaw_deg(fit.rotation) - math.degrees(yaw)) < 0.1
    np.testing.assert_allclose(fit.rotation.T @ (model.clouds[m][0] - fit.translation_m), obs[0], atol=2e-3)


@pytest.mark.parametrize("image", [1, 4, 7])
def test_icp_recovers_a_rendered_yaw_offset_within_one_degree(icp_objects, image):
    _, yawed_dir, model = icp_objects
    split = open_split_checked(yawed_dir, "test")
    sh = split.shards[0]
    depth, mask, K = sh.read("depth", image), sh.read("mask", image), sh.K
    truth = sh.read("axis_pose", image).astype(np.float64)
    split.close()
    labels, fit = model.predict_image(depth, mask, K)
    assert fit.model_index == image  # same configuration as the rendered image
    assert abs(_yaw_deg(fit.rotation) - math.degrees(YAW_OFFSET_RAD)) < 1.0
    assert metrics.axis_rotation_error_deg(labels["axis_pose"][:, 3:], truth[:, 3:]).max() < 1.0
    assert metrics.axis_position_error_cm(labels["axis_pose"][:, :3], truth[:, :3]).max() < 2.0
    np.testing.assert_allclose(labels["q"], model.labels["q"][image])


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------

def _invoke(args):
    return CliRunner().invoke(main, ["baseline", *map(str, args)], catch_exceptions=False)


def test_cli_writes_predictions_the_scorer_accepts(tiny_root, tmp_path, icp_objects):
    from articulated_dataset.benchmark.scoring import score

    model_dir, _, _ = icp_objects
    runs = {
        "mean": ("drawer", []),
        "nn": ("drawer", ["--workers", 1]),
        "icp": (ICP_CLASS, ["--workers", 1, "--limit", 3, "--mean-object", model_dir]),
    }
    for name, (cls, extra) in runs.items():
        out = tmp_path / f"{name}.h5"
        res = _invoke([name, "--train", tiny_root / cls / "train", "--test", tiny_root / cls / "test",
                       "--out", out, *extra])
        assert res.exit_code == 0, res.output
        assert f"{out}:" in res.output
        report = score(out, tiny_root / cls / "test")
        (row,) = report.rows
        assert row.method == BASELINES[name][1]
        assert row.class_name == cls
        assert row.n_scored == (3 if name == "icp" else row.n_truth)
        assert all(math.isfinite(row.metrics[k][0]) for k in ("axis_position_error_cm", "configuration_error"))


def test_cli_icp_renders_a_missing_mean_object_once(tiny_root, tmp_path, caplog):
    for split in ("train", "test"):
        shutil.copytree(tiny_root / "toaster" / split, tmp_path / "toaster" / split)
    args = ["icp", "--train", tmp_path / "toaster" / "train", "--test", tmp_path / "toaster" / "test",
            "--out", tmp_path / "p.h5", "--workers", 1, "--limit", 1, "-q"]
    with caplog.at_level("WARNING"):
        res = _invoke(args)
    assert res.exit_code == 0, res.output
    cache = tmp_path / "toaster" / icp.MEAN_CACHE_DIR / "toaster" / "mean" / "manifest.json"
    assert cache.is_file()
    assert any("rendering it once" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level("WARNING"):
        res = _invoke([*args, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert not any("rendering it once" in r.getMessage() for r in caplog.records)  # reused


def test_cli_one_line_errors(tiny_root, tmp_path):
    train, test = tiny_root / "cabinet" / "train", tiny_root / "drawer" / "test"
    res = _invoke(["mean", "--train", train, "--test", test, "--out", tmp_path / "p.h5"])
    assert res.exit_code == 2
    assert "class mismatch" in res.output and "'cabinet'" in res.output and len(res.output.strip().splitlines()) == 1
    res = _invoke(["nn", "--train", tmp_path / "missing", "--test", test, "--out", tmp_path / "p.h5"])
    assert res.exit_code == 2 and "train split folder not found" in res.output
    res = _invoke(["mean", "--train", tiny_root / "drawer", "--test", test, "--out", tmp_path / "p.h5"])
    assert res.exit_code == 2 and "manifest" in res.output
    (tmp_path / "exists.h5").write_bytes(b"")
    res = _invoke(["mean", "--train", tiny_root / "drawer" / "train", "--test", test, "--out", tmp_path / "exists.h5"])
    assert res.exit_code == 2 and "--overwrite" in res.output


def test_icp_image_without_object_pixels_gets_the_mean_model_labels(icp_objects):
    _, _, model = icp_objects
    depth = np.zeros((108, 192), np.float32)
    labels, fit = model.predict_image(depth, np.zeros(depth.shape, np.uint8), np.eye(3))
    assert fit is None
    np.testing.assert_array_equal(labels["axis_pose"], model.labels["axis_pose"][0])


@pytest.mark.slow
def test_worker_processes_give_the_serial_results(tiny_root, icp_objects, monkeypatch):
    """NN features and ICP predictions through the process pool (executors.process_map) equal
    the serial ones, in the same order."""
    split = open_split_checked(tiny_root / "drawer" / "train", "train")
    try:
        assert len(split.shards) > 1
        np.testing.assert_array_equal(nn.split_features(split, workers=2), nn.split_features(split, workers=1))
    finally:
        split.close()
    model_dir, _, _ = icp_objects
    monkeypatch.setattr(icp, "TASK_IMAGES", 1)  # one task per image: the pool's results are reordered
    train, test = tiny_root / ICP_CLASS / "train", tiny_root / ICP_CLASS / "test"
    serial = icp.predict(train, test, mean_dir=model_dir, workers=1, limit=3)
    pooled = icp.predict(train, test, mean_dir=model_dir, workers=2, limit=3)
    for k in LABELS + ("sample_id",):
        np.testing.assert_array_equal(pooled.predictions[k], serial.predictions[k])


def test_run_baseline_refuses_before_it_runs(tmp_path):
    """The library refuses an existing output without overwrite and non-positive workers before it
    reads any split (the folders here do not exist), as 'artdata baseline' reports them."""
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.baselines import run_baseline

    out = tmp_path / "p.h5"
    out.write_bytes(b"keep")
    with pytest.raises(UserError, match="exists; pass overwrite"):
        run_baseline("mean", tmp_path / "none", tmp_path / "none", out, overwrite=False)
    assert out.read_bytes() == b"keep"
    with pytest.raises(UserError, match="workers must be positive"):
        run_baseline("mean", tmp_path / "none", tmp_path / "none", tmp_path / "q.h5", workers=0)
    res = CliRunner().invoke(main, ["baseline", "mean", "--train", str(tmp_path / "none"), "--test", str(tmp_path / "none"),
                                    "--out", str(out)])
    assert res.exit_code == 2 and "exists; pass --overwrite" in res.output and res.output.count("\n") == 1


def _damaged_train(tiny_root, tmp_path, field, value):
    return split_copy_with(tiny_root / "cabinet" / "train", tmp_path / "data" / "cabinet" / "train", field, value)


@pytest.mark.parametrize("method", ["mean", "nn"])
@pytest.mark.parametrize("field, value", [("axis_pose", np.inf), ("axis_pose", 0.0), ("q", np.nan), ("geometry", 3e38)],
                         ids=["pose-inf", "pose-zero-quaternion", "q-nan", "geometry-huge"])
def test_damaged_training_labels_are_one_line_naming_the_training_split(tiny_root, tmp_path, method, field, value):
    """An infinite or zero axis quaternion (on which the Mean's rotation mean would raise numpy's
    LinAlgError) and other damaged labels are refused naming the training split, not --out."""
    train = _damaged_train(tiny_root, tmp_path, field, value)
    out = tmp_path / "p.h5"
    res = _invoke([method, "--train", train, "--test", tiny_root / "cabinet" / "test", "--out", out, "-q"])
    line = assert_one_line_error(res, str(train), f"'{field}'")
    assert str(out) not in line, line
    assert not out.exists()


@pytest.mark.parametrize("value", [np.nan, np.inf, 3e38], ids=["nan", "inf", "huge"])
def test_damaged_depth_reads_as_no_return(tiny_root, icp_objects, value):
    """NaN, infinite or huge depth is no return, as for the dense model: NaN would make every
    distance NaN (NN returning training row -1, the last image's labels, exit 0); infinite or huge
    depth would overflow float32 (RuntimeWarnings on stderr) and stop ICP's KD-tree query with a
    traceback."""
    import warnings

    _, yawed_dir, model = icp_objects
    split = open_split_checked(yawed_dir, "test")
    sh = split.shards[0]
    depth, mask, K = sh.read("depth", 1), sh.read("mask", 1), sh.K
    split.close()
    damaged, zeroed = depth.copy(), depth.copy()
    rows = slice(0, depth.shape[0] // 2)  # the top half of the image (object pixels included)
    damaged[rows] = np.where(depth[rows] > 0, np.float32(value), 0)
    zeroed[rows] = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(nn.depth_features(damaged[None]), nn.depth_features(zeroed[None]))
        got, _ = model.predict_image(damaged, mask, K)
    want, _ = model.predict_image(zeroed, mask, K)
    for k in LABELS:
        np.testing.assert_array_equal(got[k], want[k])
    index = nn.ExactNearestNeighbour(nn.depth_features(np.stack([depth, zeroed])))
    nearest, _ = index.query(nn.depth_features(damaged[None]))
    assert nearest.tolist() == [1]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_mean_object_without_points_is_one_line(tiny_root, tmp_path, icp_objects, workers):
    """A mean-object split whose images hold no usable object pixel (mask all background, or NaN
    depth): a ValueError traceback from the model (workers 1) or 'a worker process died' (pool)."""
    import h5py

    model_dir = tmp_path / "mean"
    shutil.copytree(icp_objects[0], model_dir)
    for shard in model_dir.glob("shard-*.h5"):
        with h5py.File(shard, "r+") as f:
            f["mask"][...] = 0
    res = _invoke(["icp", "--train", tiny_root / ICP_CLASS / "train", "--test", tiny_root / ICP_CLASS / "test",
                   "--mean-object", model_dir, "--out", tmp_path / "p.h5", "--limit", 2, "--workers", workers, "-q"])
    assert_one_line_error(res, str(model_dir), "no object pixel")


def test_icp_workers_past_int64_is_not_a_traceback(tiny_root, tmp_path, icp_objects):
    """--workers 2**70: the pool is capped at the task count, but the value itself went into the
    file's attributes, and h5py raised a TypeError (a traceback) after the whole run."""
    import h5py

    out = tmp_path / "p.h5"
    res = _invoke(["icp", "--train", tiny_root / ICP_CLASS / "train", "--test", tiny_root / ICP_CLASS / "test",
                   "--mean-object", icp_objects[0], "--out", out, "--limit", 1, "--workers", 2**70, "-q"])
    assert res.exit_code == 0, res.output
    with h5py.File(out, "r") as f:
        assert int(f.attrs["workers"]) == 1  # the processes that ran: one task


@pytest.mark.parametrize("where", ["mean", ".mean-object"])
def test_icp_never_replaces_the_mean_object_it_finds(tiny_root, split_copy, tmp_path, where):
    """Without --mean-object, ICP reads <train>/../mean or its cache <train>/../.mean-object/: an
    --out there is refused, since replacing the mean object's shard with the predictions would make
    every later ICP run of the class fail until the cache is deleted by hand."""
    split = split_copy()
    train = split_copy("microwave", "train")
    args = ["baseline", "icp", "--train", train, "--test", split, "--limit", 1, "--workers", 1, "-q"]
    assert run_cli(*args, "--out", tmp_path / "first.h5").exit_code == 0  # renders the cache
    cache = train.parent / ".mean-object" / "microwave" / "mean"
    mean_object = cache if where == ".mean-object" else train.parent / "mean"
    if where == "mean":
        shutil.copytree(cache, mean_object)
    shard = next(mean_object.glob("shard-*.h5"))
    before = shard.read_bytes()
    assert_one_line_error(run_cli(*args, "--out", shard, "--overwrite"), "inside the input folder")
    assert shard.read_bytes() == before
