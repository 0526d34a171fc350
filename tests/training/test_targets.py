"""Target-vector layout (encode/decode) and normalisation statistics against raw HDF5 labels."""

import json

import h5py
import numpy as np
import pytest

from articulated_dataset.classes.registry import all_classes, get_class
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split
from articulated_dataset.training.targets import (
    DEFAULT_STD_FLOOR,
    NormStats,
    TargetLayout,
    gram_schmidt,
    matrix_to_quat,
    quat_to_matrix,
)

CLASSES = [c.name for c in all_classes()]
LABELS = ("axis_pose", "axis_origin", "axis_direction", "q", "part_offset", "geometry")


def raw_labels(split_dir) -> dict:
    """Labels of every image of a split, read with plain h5py (independent of the loaders)."""
    _, shards = open_split(split_dir)
    parts = []
    for sh in shards:
        with h5py.File(sh.path, "r") as f:
            parts.append({k: f[k][()] for k in LABELS})
    return {k: np.concatenate([p[k] for p in parts]) for k in LABELS}


def test_layout_columns_hand_worked():
    lay = TargetLayout(class_name="x", n_joints=2)
    assert lay.dim == 30 == len(lay.names) == len(set(lay.names))
    assert lay.names[:13] == ["j0.origin.x", "j0.origin.y", "j0.origin.z", "j0.axis.x", "j0.axis.y", "j0.axis.z",
                              "j0.xaxis.x", "j0.xaxis.y", "j0.xaxis.z", "j0.q", "j0.offset.x", "j0.offset.y",
                              "j0.offset.z"]
    assert lay.names[13] == "j1.origin.x" and lay.names[22] == "j1.q"
    assert lay.names[26:] == ["geometry.depth", "geometry.width", "geometry.height", "geometry.chirality"]
    assert lay.slices["j1.q"] == slice(22, 23) and lay.slices["geometry"] == slice(26, 30)
    assert lay.slices["j0.xaxis"] == slice(6, 9)


@pytest.mark.parametrize("name", CLASSES)
def test_layout_for_every_class(name):
    lay = TargetLayout.for_class(name)
    J = get_class(name).n_joints
    assert lay.n_joints == J and lay.dim == 13 * J + 4
    covered = np.zeros(lay.dim, int)
    for sl in lay.slices.values():
        covered[sl] += 1
    assert np.all(covered == 1)  # groups tile the vector
    assert TargetLayout.from_dict(json.loads(json.dumps(lay.to_dict()))) == lay


def test_unknown_class_is_user_error():
    with pytest.raises(UserError, match="unknown object class"):
        TargetLayout.for_class("nope")


def test_encode_hand_worked_rotations():
    lay = TargetLayout("x", 1)
    h = np.sqrt(0.5)
    labels = {
        # identity, then 90 degrees about z: x -> +y, z stays +z
        "axis_pose": np.array([[[1, 2, 3, 1, 0, 0, 0]], [[0, 0, 0, h, 0, 0, h]]], np.float32),
        "q": np.array([[0.5], [0.25]], np.float32),
        "part_offset": np.array([[[0.1, 0.2, 0.3]], [[0, 0, 0]]], np.float32),
        "geometry": np.array([[0.4, 0.5, 0.6, 1], [1, 1, 1, 0]], np.float32),
    }
    vec = lay.encode(labels)
    assert vec.dtype == np.float32 and vec.shape == (2, 17)
    np.testing.assert_allclose(vec[0], [1, 2, 3, 0, 0, 1, 1, 0, 0, 0.5, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 1], atol=1e-6)
    np.testing.assert_allclose(vec[1, 3:9], [0, 0, 1, 0, 1, 0], atol=1e-6)
    # unbatched input gives one vector
    np.testing.assert_array_equal(lay.encode({k: v[1] for k, v in labels.items()}), vec[1])


@pytest.mark.parametrize("name", CLASSES)
def test_encode_matches_stored_labels_and_round_trips(tiny_root, name):
    raw = raw_labels(tiny_root / name / "train")
    lay = TargetLayout.for_class(name)
    vec = lay.encode(raw)
    for j in range(lay.n_joints):
        np.testing.assert_allclose(vec[:, lay.slices[f"j{j}.origin"]], raw["axis_origin"][:, j], atol=1e-6)
        # the axis column of the stored quaternion is the stored axis direction
        np.testing.assert_allclose(vec[:, lay.slices[f"j{j}.axis"]], raw["axis_direction"][:, j], atol=2e-6)
        x = vec[:, lay.slices[f"j{j}.xaxis"]]
        np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1, atol=1e-5)
        np.testing.assert_allclose(np.sum(x * raw["axis_direction"][:, j], axis=1), 0, atol=1e-5)
    dec = lay.decode(vec)
    for k in LABELS:
        np.testing.assert_allclose(dec[k], raw[k], atol=2e-6, err_msg=k)
    assert np.all(dec["axis_pose"][..., 3] >= 0)


def test_decode_gram_schmidt_against_scipy():
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(0)
    lay = TargetLayout("x", 2)
    vec = rng.normal(size=(500, lay.dim)).astype(np.float32)
    dec = lay.decode(vec)
    R = dec["axis_rotation"].astype(np.float64)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(R), 1, atol=1e-5)
    for j in range(2):
        a = vec[:, lay.slices[f"j{j}.axis"]].astype(np.float64)
        b = vec[:, lay.slices[f"j{j}.xaxis"]].astype(np.float64)
        z = a / np.linalg.norm(a, axis=1, keepdims=True)
        np.testing.assert_allclose(dec["axis_direction"][:, j], z, atol=1e-5)
        # x lies in the plane of (a, b), on b's side
        x = R[:, j, :, 0]
        assert np.all(np.sum(x * b, axis=1) >= -1e-6)
        np.testing.assert_allclose(np.sum(np.cross(a, b) * x, axis=1), 0, atol=1e-4)
        ref = Rotation.from_matrix(R[:, j]).as_quat(scalar_first=True)
        ref *= np.where(ref[:, :1] < 0, -1, 1)
        np.testing.assert_allclose(dec["axis_pose"][:, j, 3:], ref, atol=1e-5)


def test_quaternion_helpers_inverse():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(1000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1, 1)
    np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)
    # rotations by 180 degrees (w = 0) are the ill-conditioned case of the naive formula
    R = quat_to_matrix(np.array([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    np.testing.assert_allclose(np.abs(matrix_to_quat(R)), np.abs(np.eye(4)[1:]), atol=1e-12)


def test_decode_degenerate_inputs_give_rotations():
    R = gram_schmidt(np.array([[0, 0, 2.0], [0, 0, 0], [1, 1, 0]]), np.array([[0, 0, 5.0], [1, 0, 0], [2, 2, 0]]))
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1, atol=1e-12)
    np.testing.assert_allclose(R[0, :, 2], [0, 0, 1])


def test_encode_decode_bad_inputs():
    lay = TargetLayout("x", 2)
    labels = {"axis_pose": np.zeros((3, 1, 7)), "q": np.zeros((3, 1)), "part_offset": np.zeros((3, 1, 3)),
              "geometry": np.zeros((3, 4))}
    with pytest.raises(UserError, match="axis_pose"):
        lay.encode(labels)  # J = 1 data for a J = 2 layout
    with pytest.raises(UserError, match="geometry"):
        lay.encode({k: v for k, v in labels.items() if k != "geometry"} | {
            "axis_pose": np.zeros((3, 2, 7)), "q": np.zeros((3, 2)), "part_offset": np.zeros((3, 2, 3))})
    with pytest.raises(UserError, match="shape"):
        lay.decode(np.zeros((3, 29)))


def test_norm_stats_from_training_split(tiny_root):
    split = tiny_root / "cabinet" / "train"
    lay = TargetLayout.for_class("cabinet")
    stats = NormStats.from_split(split, lay)
    y = lay.encode(raw_labels(split)).astype(np.float64)
    np.testing.assert_allclose(stats.mean, y.mean(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(stats.std, np.maximum(y.std(axis=0), DEFAULT_STD_FLOOR), rtol=1e-12)
    assert stats.n_samples == len(y) and stats.names == lay.names
    # cabinet is sided; a drawer's chirality is constant 0: floored std, normalised to 0
    drawer = TargetLayout.for_class("drawer")
    dstats = NormStats.from_split(tiny_root / "drawer" / "train", drawer)
    col = drawer.names.index("geometry.chirality")
    assert dstats.std[col] == DEFAULT_STD_FLOOR and dstats.mean[col] == 0
    yn = stats.normalize(y)
    assert yn.dtype == np.float32
    np.testing.assert_allclose(yn.mean(axis=0)[y.std(axis=0) > DEFAULT_STD_FLOOR], 0, atol=1e-4)
    np.testing.assert_allclose(stats.denormalize(yn), y, atol=1e-5)
    again = NormStats.from_dict(json.loads(json.dumps(stats.to_dict())))
    np.testing.assert_array_equal(again.mean, stats.mean)
    np.testing.assert_array_equal(again.std, stats.std)
    assert again.names == stats.names
    sub = NormStats.from_split(split, lay, max_samples=10)
    assert sub.n_samples == 10
    np.testing.assert_allclose(NormStats.from_targets(y, lay).mean, stats.mean)


def test_norm_stats_bad_inputs(tiny_root):
    lay = TargetLayout.for_class("cabinet")
    with pytest.raises(UserError, match="drawer"):
        NormStats.from_split(tiny_root / "drawer" / "train", lay)
    stats = NormStats.from_split(tiny_root / "cabinet" / "train", lay, max_samples=8)
    with pytest.raises(UserError, match="columns"):
        stats.normalize(np.zeros((2, lay.dim + 1)))
    with pytest.raises(UserError, match="no such directory"):
        NormStats.from_split(tiny_root / "missing", lay)
