"""The dense estimator: features, vote aggregation, training (overfit, resume), prediction, CLI."""

from __future__ import annotations

import json
import math
import os
import pickle

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402

from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.core.camera import CameraConfig, backproject  # noqa: E402
from articulated_dataset.methods.dense import aggregate as A
from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint  # noqa: E402
from articulated_dataset.methods.dense.features import (  # noqa: E402
    HOLE_MAX_SPREAD_M,
    backproject_torch,
    fill_holes,
    make_inputs,
    output_labels,
    resize_depth,
    scale_intrinsics,
    surface_normals,
)
from articulated_dataset.methods.dense.model import DenseConfig, DenseNet  # noqa: E402
from articulated_dataset.methods.dense.refine import REFINEMENT_VERSION  # noqa: E402
from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense  # noqa: E402
from helpers_core import PROGRESS_FRAME, assert_one_line_error  # noqa: E402

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _run(args):
    res = CliRunner().invoke(main, args, catch_exceptions=False)
    return res.exit_code, res.output


# ----------------------------------------------------------------------------- features
def test_backprojection_matches_the_camera_module():
    K = CameraConfig().K
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (108, 192)) * (rng.random((108, 192)) > 0.3)
    ref = backproject(depth, K)
    pts = backproject_torch(torch.tensor(depth)[None], torch.tensor(K)[None])[0]
    v, u = np.nonzero(depth > 0)
    assert np.allclose(pts[:, v, u].T.numpy(), ref, atol=1e-9)


def test_scaled_intrinsics_keep_the_rays_of_pixel_centres():
    K = CameraConfig().K
    K2 = scale_intrinsics(K, (108, 192), (54, 96))
    # the centre of low-res pixel (u2, v2) covers high-res pixels 2u2..2u2+1: its ray is their mean ray
    for u2, v2 in [(0, 0), (10, 7), (95, 53)]:
        ray2 = np.array([(u2 - K2[0, 2]) / K2[0, 0], (v2 - K2[1, 2]) / K2[1, 1]])
        ray = np.array([(2 * u2 + 0.5 - K[0, 2]) / K[0, 0], (2 * v2 + 0.5 - K[1, 2]) / K[1, 1]])
        assert np.allclose(ray2, ray)


def test_resize_never_blends_background_into_surfaces():
    d = torch.zeros(1, 4, 4)
    d[0, :2, :2] = 2.0
    d[0, 0, 0] = 0.0  # one missing return inside the surface
    r = resize_depth(d, (2, 2))
    assert r[0, 0, 0] == pytest.approx(2.0) and r[0, 1, 1] == 0.0


def test_a_sensors_dropped_returns_are_filled_and_give_their_neighbours_normals_back():
    """1% of a tilted plane's returns dropped at random (the Kinect v2 model's holes), apart from
    each other: every hole takes its four neighbours' mean (on this plane, its own depth to float
    rounding), so the network input has the normals of the hole-free image; two holes side by
    side, a gap at a depth edge (neighbours more than HOLE_MAX_SPREAD_M apart), the image's border
    and an image without holes are left as they are."""
    K = CameraConfig().K
    H, W = 108, 192
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    plane = (1.5 + 0.004 * u + 0.002 * v).astype(np.float32)  # depth linear in the pixel: exact means
    rng = np.random.default_rng(0)
    holes = rng.random((H, W)) < 0.01
    holes[:2], holes[-2:], holes[:, :2], holes[:, -2:] = False, False, False, False
    near = np.zeros_like(holes)  # holes with a hole beside them: dropped
    near[1:] |= holes[:-1]; near[:-1] |= holes[1:]; near[:, 1:] |= holes[:, :-1]; near[:, :-1] |= holes[:, 1:]  # noqa: E702
    holes &= ~near
    depth = torch.tensor(np.where(holes, 0.0, plane), dtype=torch.float32)[None]
    filled = fill_holes(depth)
    pair = depth.clone()
    pair[0, 50, 60:62] = 0.0
    assert (fill_holes(pair)[0, 50, 60:62] == 0).all()
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = True
    assert torch.allclose(filled[0][torch.tensor(holes & inner)], torch.tensor(plane[holes & inner]), atol=1e-5)
    assert (filled[0][0] == depth[0][0]).all() and (filled[0][:, 0] == depth[0][:, 0]).all()  # the border: no neighbours
    Kt = torch.tensor(K, dtype=torch.float32)[None]
    with_holes = make_inputs(depth, Kt)["x"][0, 4:7].norm(dim=0) > 0.5
    clean = make_inputs(torch.tensor(plane)[None], Kt)["x"][0, 4:7].norm(dim=0) > 0.5
    border = torch.zeros(H, W, dtype=torch.bool)
    border[:2], border[-2:], border[:, :2], border[:, -2:] = True, True, True, True
    assert holes.sum() > 100 and torch.equal(with_holes | border, clean | border)
    # a gap between two surfaces 5 cm apart is not a hole
    step = depth.clone()
    step[0, :, 100:] += 0.05
    step[0, 40, 100] = 0.0
    assert HOLE_MAX_SPREAD_M < 0.05 and fill_holes(step)[0, 40, 100] == 0.0
    # nothing to fill: the same tensor
    solid = torch.tensor(plane)[None]
    assert fill_holes(solid) is solid


def test_normals_of_a_plane_face_the_camera():
    K = CameraConfig().K
    H, W = 108, 192
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    # plane x = 2 - 0.5 y (camera frame): tilted about z; normal ~ -(1, 0.5, 0)/|.|
    xo = (u - K[0, 2]) / K[0, 0]
    depth = 2.0 / (1.0 - 0.5 * xo)  # y = -xo z  =>  z = 2 + 0.5 xo z
    n = surface_normals(backproject_torch(torch.tensor(depth)[None], torch.tensor(K)[None]), torch.ones(1, H, W, dtype=torch.bool))
    expect = -np.array([1.0, 0.5, 0.0]) / math.sqrt(1.25)
    inner = n[0, :, 1:-1, 1:-1].reshape(3, -1).T.numpy()
    assert np.allclose(inner, expect, atol=1e-5)


def test_output_labels_take_the_majority_part():
    mask = np.zeros((1, 8, 8), np.uint8)
    mask[0, :4, :4] = 1
    mask[0, :3, :3] = 2  # 9 of 16 pixels are the part
    mask[0, 4:, 4:] = 1
    lab = output_labels(mask, 1)
    assert lab.shape == (1, 2, 2)
    assert lab[0, 0, 0] == 2 and lab[0, 1, 1] == 1 and lab[0, 0, 1] == 0


# ----------------------------------------------------------------------------- aggregation
def _parts(votes_xyz, conf, J=1):
    """Fake network outputs whose origin votes are ``votes_xyz`` (N, 3) at zero points."""
    N = len(votes_xyz)
    H, W = 1, N
    off = torch.tensor(votes_xyz, dtype=torch.float32).T.reshape(1, 1, 3, H, W).expand(1, J, 3, H, W)
    c = torch.tensor(conf, dtype=torch.float32).reshape(1, 1, 1, H, W).expand(1, J, 3, H, W)
    rot6 = torch.tensor([0, 0, 1, 1, 0, 0], dtype=torch.float32).reshape(1, 1, 6, 1, 1).expand(1, J, 6, H, W)
    return {"offset": off, "conf": c, "rot6": rot6, "q": torch.zeros(1, J, H, W), "part_offset": torch.zeros(1, J, 3, H, W),
            "geometry": torch.zeros(1, 4, H, W), "geometry_conf": torch.zeros(1, H, W)}, torch.zeros(1, 3, H, W), torch.ones(1, H, W, dtype=torch.bool)


def test_two_sided_votes_give_two_weighted_modes_not_their_average():
    rng = np.random.default_rng(1)
    left = rng.normal([1.5, 0.3, 0.0], 0.01, (60, 3))
    right = rng.normal([1.5, -0.3, 0.0], 0.01, (40, 3))
    parts, pts, valid = _parts(np.concatenate([left, right]), np.zeros(100))
    m = A.vote_modes(parts, pts, valid)
    w = m["weight"][0, 0].numpy()
    o = m["origin"][0, 0].numpy()
    assert w == pytest.approx([0.6, 0.4], abs=1e-5)
    assert np.allclose(o[0], left.mean(0), atol=1e-6) and np.allclose(o[1], right.mean(0), atol=1e-6)
    mean = A.weighted_mean(parts, pts, valid)["origin"][0, 0].numpy()
    assert abs(mean[1]) < 0.1  # the plain mean lands between the sides: what the modes avoid


def test_one_cluster_gives_one_mode_with_all_the_weight_and_its_spread():
    rng = np.random.default_rng(2)
    v = rng.normal([2.0, 0.0, 0.1], 0.02, (80, 3))
    parts, pts, valid = _parts(v, rng.normal(0, 1, 80))
    m = A.vote_modes(parts, pts, valid)
    assert m["weight"][0, 0].numpy() == pytest.approx([1.0, 0.0])
    assert np.all(m["origin_std"][0, 0, 0].numpy() < 0.04)


def test_split_factor_none_gives_one_mode_the_weighted_mean_of_every_vote():
    rng = np.random.default_rng(3)
    left = rng.normal([1.5, 0.3, 0.0], 0.01, (60, 3))
    right = rng.normal([1.5, -0.3, 0.0], 0.01, (40, 3))
    parts, pts, valid = _parts(np.concatenate([left, right]), rng.normal(0, 1, 100))
    one = A.vote_modes(parts, pts, valid, split_factor=None)
    assert one["weight"][0, 0].numpy() == pytest.approx([1.0, 0.0])
    mean = A.weighted_mean(parts, pts, valid)["origin"][0, 0].numpy()
    assert np.allclose(one["origin"][0, 0, 0].numpy(), mean, atol=1e-5)
    # a factor so large that no gap passes it is the same; the default keeps the two sides apart
    huge = A.vote_modes(parts, pts, valid, split_factor=1e6)
    assert torch.equal(huge["origin"], one["origin"]) and torch.equal(huge["weight"], one["weight"])
    assert A.vote_modes(parts, pts, valid)["weight"][0, 0, 1] > 0.3


def test_a_mode_voting_a_joint_closed_past_its_closed_state_reads_as_closed():
    """Every class's joints close at q = 0 (the templates' limits: each registered table's range
    starts there), so a vote mode's q below 0 comes out as 0, in the point estimate and in its
    mixture component; one above 0 and the other modes keep theirs."""
    from articulated_dataset.classes.registry import class_names, get_class
    from articulated_dataset.methods.dense.predict import Q_CLOSED, mixture_from_modes

    assert all(lo == Q_CLOSED for c in class_names() for lo, _ in get_class(c).table.q)
    N, J, M = 2, 1, 2
    m = {"weight": np.array([[[0.7, 0.3]], [[1.0, 0.0]]]), "q": np.array([[[-0.2, 0.4]], [[0.3, 0.0]]]),
         "q_std": np.full((N, J, M), 0.05)}
    for key in ("origin", "axis", "xaxis", "part_offset", "origin_std", "axis_std", "xaxis_std", "offset_std"):
        m[key] = np.tile(np.array([0.0, 0.0, 1.0]), (N, J, M, 1))
    m["geometry"], m["geometry_std"] = np.ones((N, 4)), np.full((N, 4), 0.1)
    out = mixture_from_modes(m, np.arange(N), J, M, None)
    assert out["q"][0, 0] == 0.0 and out["q"][1, 0] == pytest.approx(0.3)
    q_cols = out["mixture_means"][..., 9]  # joint 0's q column
    assert q_cols.min() >= 0.0 and np.isclose(q_cols[0], 0.4).any()


def test_refinement_records_its_split_factor_and_old_ones_read_the_default():
    from articulated_dataset.methods.dense.refine import Refinement, split_factor_of

    for f in (None, 3.0):
        ref = Refinement(frame=True, split_factor=f)
        assert Refinement.from_dict(ref.to_dict()) == ref and split_factor_of(ref.to_dict()) == f
    old = {"frame": True, "hinge_offset_m": 0.0, "min_door_px": None, "max_turn_deg": None, "version": 2}
    assert split_factor_of(old) == A.SPLIT_FACTOR == split_factor_of(None)


# ----------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def overfit_run(tiny_root, tmp_path_factory):
    torch.set_num_threads(2)
    out = tmp_path_factory.mktemp("dense") / "mw.pt"
    cfg = DenseTrainConfig("microwave", epochs=60, batch_size=16, lr=1e-2, width=8, val_fraction=0.0, max_objects=1)
    ckpt = train_dense(tiny_root / "microwave" / "train", out, cfg, progress=False)
    return out, ckpt, cfg


def test_tiny_training_run_overfits(overfit_run, tiny_root):
    from articulated_dataset.methods.dense.checkpoint import build_dense_model
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.predict import predict_arrays, quick_errors

    out, ckpt, _ = overfit_run
    d = load_dense_split(tiny_root / "microwave" / "train", 1, (108, 192), max_objects=1)
    idx = np.arange(len(d.sample_id))
    trained = quick_errors(predict_arrays(build_dense_model(ckpt), d, idx, joint_types=["revolute"], calibration=None), d, idx, ["revolute"])
    torch.manual_seed(0)
    fresh = DenseNet(DenseConfig(1, width=8)).eval()
    untrained = quick_errors(predict_arrays(fresh, d, idx, joint_types=["revolute"], calibration=None), d, idx, ["revolute"])
    assert trained["pos_cm"] < 0.5 * untrained["pos_cm"] and trained["pos_cm"] < 8.0
    assert trained["rot_deg"] < 0.25 * untrained["rot_deg"]
    assert ckpt["finished"] and ckpt["history"][-1]["train_loss"] < 0.2 * ckpt["history"][0]["train_loss"]


@pytest.mark.slow
def test_resume_reaches_the_identical_state(tiny_root, tmp_path):
    torch.set_num_threads(1)
    cfg = DenseTrainConfig("drawer", epochs=2, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    whole = train_dense(tiny_root / "drawer" / "train", a, cfg, progress=False)
    part = train_dense(tiny_root / "drawer" / "train", b, cfg, progress=False, stop_after_steps=3)
    assert not part["finished"] and part["step"] == 3
    resumed = train_dense(tiny_root / "drawer" / "train", b, cfg, progress=False, resume=True)
    assert resumed["step"] == whole["step"]
    for k, v in whole["model_state"].items():
        assert torch.equal(v, resumed["model_state"][k]), k
    assert resumed["calibration"] == whole["calibration"]
    # the refinement is chosen on the validation objects at the end (dense.fit.fit_refinement)
    assert whole["refinement"]["version"] == REFINEMENT_VERSION and resumed["refinement"] == whole["refinement"]
    from articulated_dataset.methods.dense.fit import TURN_GATE_CANDIDATES_DEG

    gates = {f"box_frame_turn<={t:g}deg" for t in TURN_GATE_CANDIDATES_DEG if t is not None}
    assert set(whole["refinement_report"]["rotation_deg"]) == {"votes", "box_frame"} | gates
    # the vote modes' split factor is chosen there too, from the candidates, each one's error reported
    from articulated_dataset.methods.dense.predict import SPLIT_FACTOR_CANDIDATES

    assert whole["refinement"]["split_factor"] in SPLIT_FACTOR_CANDIDATES
    assert len(whole["refinement_report"]["split_factor_position_cm"]) == len(SPLIT_FACTOR_CANDIDATES)
    # and the box frame's pixel threshold (refinement version 6) with its normals (central
    # differences only or one-sided ones too, version 12), each pair's errors reported
    # then the body's strip (version 14) with the best pair, each elongation's errors reported
    from articulated_dataset.methods.dense.fit import (
        FRAME_ONE_SIDED_CANDIDATES,
        FRAME_PROB_CANDIDATES,
        FRAME_STRIP_CANDIDATES,
        FRAME_STRIP_MIN_GAIN,
    )

    assert whole["refinement"]["frame_min_prob"] in FRAME_PROB_CANDIDATES
    assert whole["refinement"]["frame_one_sided"] in FRAME_ONE_SIDED_CANDIDATES
    assert whole["refinement"]["frame_strip_elongation"] in (None,) + FRAME_STRIP_CANDIDATES
    report = whole["refinement_report"]["frame_min_prob"]
    pairs = len(FRAME_PROB_CANDIDATES) * len(FRAME_ONE_SIDED_CANDIDATES)
    assert len(report) == pairs + len(FRAME_STRIP_CANDIDATES)
    key = lambda e: (e["rotation_deg"], e["configuration"])  # noqa: E731
    best_pair = min(list(report.values())[:pairs], key=key)
    best_strip = min(list(report.values())[pairs:], key=key)
    best = best_strip if best_strip["rotation_deg"] < best_pair["rotation_deg"] * (1 - FRAME_STRIP_MIN_GAIN) else best_pair
    strip = whole["refinement"]["frame_strip_elongation"]
    name = ("all pixels" if whole["refinement"]["frame_min_prob"] is None
            else f"probability>{whole['refinement']['frame_min_prob']:g}") + \
        (", one-sided normals" if whole["refinement"]["frame_one_sided"] else "") + \
        ("" if strip is None else f", strip elongation {strip:g}")
    assert report[name] == best  # the choice with the lowest validation rotation error is the one kept
    # the strip candidates share the best pair's threshold and normals
    pair_name = name.split(", strip")[0]
    assert all(k.startswith(pair_name + ", strip elongation ") for k in list(report)[pairs:])


def test_noise_augmentation_corrupts_its_share_of_a_batch_the_same_way_on_every_run(tiny_root, tmp_path):
    """``--noise``: each image of a batch is corrupted with probability ``noise_fraction`` by the
    named model, with its own generator for the epoch (a resumed run draws the same), the rest
    untouched; a run with it resumes to the identical state and records the setting."""
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.train import noisy_depth

    data = load_dense_split(tiny_root / "drawer" / "train", 1, (108, 192), progress=False)
    idx = np.arange(min(16, len(data.sample_id)))
    clean = data.depth(idx).numpy()
    a = noisy_depth(clean, data.K[idx], idx, "kinect2", 0.5, seed=0, epoch=1)
    b = noisy_depth(clean, data.K[idx], idx, "kinect2", 0.5, seed=0, epoch=1)
    assert np.array_equal(a, b) and not np.shares_memory(a, clean)
    alone = noisy_depth(clean[3:4], data.K[idx[3:4]], idx[3:4], "kinect2", 0.5, seed=0, epoch=1)
    assert np.array_equal(alone[0], a[3])  # an image's draw does not depend on the rest of its batch
    changed = [not np.array_equal(a[i], clean[i]) for i in range(len(idx))]
    assert 0 < sum(changed) < len(idx)  # about half: some images corrupted, others as they were
    assert (noisy_depth(clean, data.K[idx], idx, "kinect2", 1.0, seed=5, epoch=0) != clean).any((1, 2)).all()  # every one
    torch.set_num_threads(1)
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3, noise="kinect2")
    whole = train_dense(tiny_root / "drawer" / "train", tmp_path / "a.pt", cfg, progress=False, fit=False)
    train_dense(tiny_root / "drawer" / "train", tmp_path / "b.pt", cfg, progress=False, stop_after_steps=1, fit=False)
    resumed = train_dense(tiny_root / "drawer" / "train", tmp_path / "b.pt", cfg, progress=False, resume=True, fit=False)
    assert whole["train_config"]["noise"] == "kinect2" and whole["train_config"]["noise_fraction"] == 0.5
    for k, v in whole["model_state"].items():
        assert torch.equal(v, resumed["model_state"][k]), k
    plain = train_dense(tiny_root / "drawer" / "train", tmp_path / "c.pt",
                        DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3),
                        progress=False, fit=False)
    assert any(not torch.equal(v, plain["model_state"][k]) for k, v in whole["model_state"].items())


@pytest.mark.slow
def test_noise_training_validates_and_fits_on_one_noisy_draw_of_the_validation_images(tiny_root, tmp_path):
    """With ``--noise`` every validation image passes through the noise model, drawn per sample
    (not per position: a refit, which reads only the validation objects, draws the same), its
    labels kept; the epoch's validation errors are those noisy images' and a refit gives what
    training's own fit gives."""
    from articulated_dataset.methods.dense.checkpoint import build_inference_model
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.predict import predict_arrays, quick_errors
    from articulated_dataset.methods.dense.train import noisy_validation, refit_inference
    from articulated_dataset.methods.mdn.data import split_by_object

    split = tiny_root / "drawer" / "train"
    data = load_dense_split(split, 1, (108, 192), max_objects=3, progress=False)
    va = np.arange(3, 11)
    sub, idx = noisy_validation(data, va, "kinect2", seed=0)
    assert idx.tolist() == list(range(len(va))) and np.array_equal(sub.sample_id, data.sample_id[va])
    assert np.array_equal(sub.origin, data.origin[va]) and np.array_equal(sub.labels_out, data.labels_out[va])
    assert (sub.depth(idx).numpy() != data.depth(va).numpy()).any((1, 2)).all()  # every image noisy
    later, _ = noisy_validation(data, va[4:], "kinect2", seed=0)
    assert np.array_equal(later.depth_q, sub.depth_q[4:])
    torch.set_num_threads(1)
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3, noise="kinect2")
    unfit = train_dense(split, tmp_path / "a.pt", cfg, progress=False, fit=False)
    whole = train_dense(split, tmp_path / "b.pt", cfg, progress=False)
    refit = refit_inference(tmp_path / "a.pt", split, tmp_path / "c.pt", progress=False)
    assert refit["refinement"] == whole["refinement"] and refit["calibration"] == whole["calibration"]
    assert refit["refit_of"]["validation_noise"] == "kinect2"
    # --clean: the same validation objects without the noise model (the intervals fitted to clean depth)
    # an output that cannot be written is one line before the fit, and leaves nothing behind
    (tmp_path / "folder.pt").mkdir()
    from articulated_dataset.core.errors import UserError

    with pytest.raises(UserError):
        refit_inference(tmp_path / "a.pt", split, tmp_path / "folder.pt", progress=False)
    assert not list(tmp_path.glob("*.partial")) and not any((tmp_path / "folder.pt").iterdir())
    clean = refit_inference(tmp_path / "a.pt", split, tmp_path / "d.pt", progress=False, clean=True)
    assert clean["refit_of"]["validation_noise"] is None and clean["calibration"] != refit["calibration"]
    _, val_mask = split_by_object(data.object_index, cfg.val_fraction, cfg.seed)
    va_idx = np.nonzero(val_mask)[0]
    joints = list(unfit["joint_types"])
    model = build_inference_model(unfit)
    noisy, nidx = noisy_validation(data, va_idx, "kinect2", seed=cfg.seed)
    on_noisy = quick_errors(predict_arrays(model, noisy, nidx, joint_types=joints, calibration=None), noisy, nidx, joints)
    on_clean = quick_errors(predict_arrays(model, data, va_idx, joint_types=joints, calibration=None), data, va_idx, joints)
    recorded = unfit["history"][-1]["val_pos_cm"]
    assert recorded == pytest.approx(round(on_noisy["pos_cm"], 4), abs=1e-4)
    assert recorded != pytest.approx(round(on_clean["pos_cm"], 4), abs=1e-4)


@pytest.mark.slow
def test_a_two_step_run_trains_records_its_data_and_machine_and_fits_later(tiny_root, tmp_path):
    """Two steps in all (OneCycleLR's warm-up would be empty); ``fit=False`` leaves
    the inference fit out, and refit_inference then gives what training's own fit gives."""
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.format import read_manifest
    from articulated_dataset.methods.dense.train import refit_inference

    torch.set_num_threads(1)
    split = tiny_root / "drawer" / "train"
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    unfit = train_dense(split, tmp_path / "a.pt", cfg, progress=False, fit=False)
    assert unfit["finished"] and unfit["step"] == 2 and unfit.get("calibration") is None and "refinement" not in unfit
    whole = train_dense(split, tmp_path / "b.pt", cfg, progress=False, device="cpu")
    for k, v in whole["model_state"].items():
        assert torch.equal(v, unfit["model_state"][k]), k
    refit = refit_inference(tmp_path / "a.pt", split, tmp_path / "c.pt", progress=False)
    assert refit["refinement"] == whole["refinement"] and refit["calibration"] == whole["calibration"]
    cfg_made = read_manifest(split)["config"]
    assert whole["data"]["generated"] == {"class_name": "drawer", "seed": cfg_made["seed"],
                                          "n_objects": cfg_made["n_objects"]}
    assert "PyTorch" in whole["machine"] and "cores" in whole["machine"] and whole["device"] == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="no CUDA GPU"):
            train_dense(split, tmp_path / "d.pt", cfg, progress=False, device="cuda")


def test_cli_train_predict_score_show(tiny_root, tmp_path, overfit_run):
    ckpt_path = overfit_run[0]
    preds = tmp_path / "p.h5"
    code, out = _run(["predict", "--model", str(ckpt_path), str(tiny_root / "microwave" / "test"),
                      "--out", str(preds), "-q"])
    assert code == 0, out
    code, out = _run(["score", str(preds), "--truth", str(tiny_root / "microwave" / "test"), "--json", str(tmp_path / "s.json")])
    assert code == 0, out
    row = json.loads((tmp_path / "s.json").read_text())["rows"][0]
    assert row["method"] == "dense" and row["n_scored"] == row["n_truth"] == 48
    assert 0.0 <= row["metrics"]["coverage_90"]["mean"] <= 1.0 and math.isfinite(row["metrics"]["nll"]["mean"])
    code, out = _run(["show", str(tiny_root / "microwave" / "test"), "--predictions", str(preds), "--n", "2",
                      "--out", str(tmp_path / "g.png"), "-q"])
    assert code == 0 and (tmp_path / "g.png").stat().st_size > 1000, out
    # wrong class: one line, exit 2
    code, out = _run(["predict", "--model", str(ckpt_path), str(tiny_root / "drawer" / "test"), "--out", str(tmp_path / "q.h5")])
    assert code == 2 and out.count("\n") == 1 and "'microwave' model" in out


def test_cli_train_dense_and_its_errors(tiny_root, tmp_path):
    out = tmp_path / "d.pt"
    code, text = _run(["train", "--model", "dense", "--class", "toaster", str(tiny_root / "toaster" / "train"),
                       "--out", str(out), "--epochs", "1", "--batch-size", "32", "--width", "4", "--max-objects", "2", "-q"])
    assert code == 0, text
    ckpt = load_dense_checkpoint(out)
    assert ckpt["class_name"] == "toaster" and ckpt["finished"] and ckpt["calibration"] is not None
    for extra, needle in [(["--lr", "nan"], "--lr"), (["--epochs", "0"], "--epochs"), (["--small"], "--model mdn"),
                          (["--class", "drawer"], "not 'drawer'"), (["--origin-weight", "0"], "--origin-weight"),
                          (["--origin-weight", "inf"], "--origin-weight"), (["--noise", "fog"], "fog"),
                          (["--noise", "kinect2", "--noise-fraction", "0"], "--noise-fraction"),
                          (["--lr", "1e9"], "--lr"), (["--seed", "-1"], "--seed"),
                          (["--seed", "99999999999999999999"], "--seed"), (["--width", "257"], "--width"),
                          (["--init-from", str(out)], "--init-from"),  # a toaster model: another configuration
                          (["--out", str(out / "x.pt")], "")]:  # a parent that is a file: before the training
        args = ["train", "--model", "dense", "--class", "toaster", str(tiny_root / "toaster" / "train"),
                "--out", str(tmp_path / "e.pt")]
        if extra[0] == "--class":
            args[args.index("--class") + 1] = "drawer"
        elif extra[0] == "--out":
            args[args.index("--out") + 1] = extra[1]
        else:
            args += extra
        # (without -q, a refusal after the split is read follows the loading bar's frames: not counted)
        assert_one_line_error(CliRunner().invoke(main, args), needle, ignore=(PROGRESS_FRAME,))
    assert load_dense_checkpoint(out)["finished"]  # untouched by the failures


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", b"PK\x03\x04garbage", pickle.dumps({"a": 1}, protocol=4)],
                         ids=["empty", "text", "a broken zip", "a bare pickle"])
def test_bad_checkpoint_files_are_one_line(tmp_path, tiny_root, content):
    """(A bare pickle also drew torch's warning about its protocol: three more lines.)"""
    bad = tmp_path / "bad.pt"
    bad.write_bytes(content)
    assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(bad), str(tiny_root / "drawer" / "test"), "--out", str(tmp_path / "p.h5")]))


@pytest.mark.parametrize("field,value", [("format", "artdata-dense"), ("class_name", 5), ("model_state", [1]),
                                         ("model_config", {"n_joints": "x"}), ("joint_types", ["revolute", "revolute"])])
def test_checkpoints_with_bad_fields_are_one_line(overfit_run, tmp_path, tiny_root, field, value):
    ckpt = dict(load_dense_checkpoint(overfit_run[0]))
    if field == "format":
        ckpt["version"] = 99
    else:
        ckpt[field] = value
    bad = tmp_path / "bad.pt"
    torch.save(ckpt, bad)
    assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(bad), str(tiny_root / "microwave" / "test"), "--out", str(tmp_path / "p.h5")]))


def _state_changed(change):
    """A checkpoint change that edits a copy of its ``model_state`` with ``change(state)``."""
    def apply(ckpt):
        state = dict(ckpt["model_state"])
        change(state)
        return {**ckpt, "model_state": state}
    return apply


def _first(state, suffix):
    return next(k for k in state if k.endswith(suffix))


def _bad_checkpoint_contents():
    """(name, change, words) triples: each makes a dense checkpoint (one joint, the microwave) one
    that predict and estimate must refuse in one line naming ``words``."""
    def config(**kw):
        return lambda c: {**c, "model_config": {**c["model_config"], **kw}}
    return [
        ("NaN weights", _state_changed(lambda s: s.update({_first(s, "weight"): s[_first(s, "weight")] * float("nan")})),
         "NaN or infinite"),
        ("an infinite bias", _state_changed(lambda s: s.update({"head.bias": s["head.bias"] + float("inf")})),
         "NaN or infinite"),
        ("a negative variance", _state_changed(lambda s: s.update(
            {_first(s, "running_var"): -s[_first(s, "running_var")]})), "variance"),
        ("integer weights", _state_changed(lambda s: s.update({"head.weight": s["head.weight"].long()})),
         "not floating point"),
        ("a sparse weight", _state_changed(lambda s: s.update({"head.bias": s["head.bias"].to_sparse()})), "tensors"),
        ("a zero image height", config(height_px=0), "'height_px'"),
        ("a text image height", config(height_px="108"), "'height_px'"),
        ("a fractional image width", config(width_px=192.0), "'width_px'"),
        ("a huge image", config(height_px=10 ** 7), "'height_px'"),
        ("a zero network width", config(width=0), "'width'"),
        ("another class's joints", lambda c: {**c, "class_name": "cabinet2"}, "joint types"),
        ("an unknown class", lambda c: {**c, "class_name": "../../etc"}, "../../etc"),
        ("a drawer's joint on a microwave", lambda c: {**c, "joint_types": ["prismatic"]}, "joint types"),
        ("no step", lambda c: {k: v for k, v in c.items() if k != "step"}, "'step'"),
        ("a text finished", lambda c: {**c, "finished": "no"}, "'finished'"),
        ("a text step", lambda c: {**c, "step": "3"}, "'step'"),
        ("a text q scale", lambda c: {**c, "q_scale": ["a"]}, "'q_scale'"),
        ("a NaN q scale", lambda c: {**c, "q_scale": [float("nan")]}, "'q_scale'"),
        ("a negative q scale", lambda c: {**c, "q_scale": [-1.0]}, "'q_scale'"),
        ("an MDN's format with a list config", lambda c: {**c, "format": "artdata-mdn", "train_config": [1]}, "bad.pt"),
    ]


@pytest.mark.parametrize("name,change,words", _bad_checkpoint_contents(), ids=[n for n, _, _ in _bad_checkpoint_contents()])
def test_checkpoints_with_bad_contents_are_one_line(overfit_run, tmp_path, tiny_root, name, change, words):
    """Weights, network configuration, class, step and q scale of a dense checkpoint are checked
    when the file is read, not where they would fail (NaN weights inside an eigendecomposition, a
    zero image height inside the network, another class's name inside the refinement, a missing
    step after the whole split is predicted)."""
    from articulated_dataset.classes.registry import class_names

    changed = change(dict(load_dense_checkpoint(overfit_run[0])))
    bad = tmp_path / "bad.pt"
    torch.save(changed, bad)
    # the split of the class the file claims (a relabelled file must fail on its own, not on the data's class)
    split = str(tiny_root / (changed["class_name"] if changed["class_name"] in class_names() else "microwave") / "test")
    assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(bad), split, "--out", str(tmp_path / "p.h5")]), words)
    assert not (tmp_path / "p.h5").exists()


def _bad_calibrations():
    """(name, change) pairs: each makes a fitted calibration (17 columns, one joint) malformed."""
    def outlier(**kw):
        return lambda c: {**c, "outlier": {**c["outlier"], **kw}}
    return [("not a dict", lambda c: [1, 2]),
            ("short factors", lambda c: {**c, "spread_factor": c["spread_factor"][:3]}),
            ("a NaN floor", lambda c: {**c, "floor": [float("nan")] + c["floor"][1:]}),
            ("a text weight", outlier(weight="heavy")),
            ("weight 1", outlier(weight=1.0)),
            ("a zero scale", outlier(scale=[0.0] * 17)),
            ("scales of another layout", outlier(scale=[0.1] * 30)),
            ("an outlier list", lambda c: {**c, "outlier": [0.01]})]


@pytest.mark.parametrize("name,change", _bad_calibrations(), ids=[n for n, _ in _bad_calibrations()])
def test_a_malformed_calibration_is_one_line(overfit_run, tmp_path, tiny_root, name, change):
    """A checkpoint's calibration (the modes' scales and the outlier component) is checked when
    the file is read: predict and estimate say what is wrong in one line instead of failing
    inside the mixture's arithmetic."""
    from articulated_dataset.methods.dense.predict import OUTLIER_MIN_SCALES, _layout_names

    ckpt = dict(load_dense_checkpoint(overfit_run[0]))
    calibration = dict(ckpt["calibration"] or {"spread_factor": [1.0] * 17, "floor": [0.01] * 17})
    calibration.setdefault("outlier", {"weight": 0.01, "scale": [OUTLIER_MIN_SCALES[n.split(".")[1]]
                                                                  for n in _layout_names(1)]})
    good = tmp_path / "good.pt"
    torch.save({**ckpt, "calibration": calibration}, good)
    split = str(tiny_root / "microwave" / "test")
    assert _run(["predict", "--model", str(good), split, "--out", str(tmp_path / "g.h5"), "-q"])[0] == 0
    bad = tmp_path / "bad.pt"
    torch.save({**ckpt, "calibration": change(calibration)}, bad)
    assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(bad), split, "--out", str(tmp_path / "p.h5")]), "'calibration' is malformed")


def _bad_refinements():
    """(name, change) pairs: each makes a checkpoint's refinement (one joint) malformed."""
    return [("not a dict", lambda r: [1, 2]),
            ("a missing field", lambda r: {k: v for k, v in r.items() if k != "frame"}),
            ("a text threshold", lambda r: {**r, "frame_min_prob": "sure"}),
            ("a NaN offset", lambda r: {**r, "hinge_offset_m": float("nan")}),
            ("an infinite strip elongation", lambda r: {**r, "frame_strip_elongation": float("inf")}),
            ("a negative pixel count", lambda r: {**r, "min_door_px": -5}),
            ("a joint that is not there", lambda r: {**r, "mirror_joints": [3]}),
            ("one face offset", lambda r: {**r, "door_face_offsets_m": [0.0]}),
            ("a list gate", lambda r: {**r, "door_angle_gate_deg": [1, 2]}),
            ("a text switch", lambda r: {**r, "frame": "yes"}),
            ("a text gate", lambda r: {**r, "max_turn_deg": "20"}),
            ("a probability above 1", lambda r: {**r, "frame_min_prob": 5.0}),
            ("a negative gate", lambda r: {**r, "max_turn_deg": -20.0}),
            ("a gate beyond a half turn", lambda r: {**r, "door_angle_gate_deg": 400.0}),
            ("an offset of a kilometre", lambda r: {**r, "hinge_offset_m": 1000.0}),
            ("a version from the future", lambda r: {**r, "version": 999}),
            ("a fractional pixel count", lambda r: {**r, "min_door_px": 20.5}),
            ("a null switch", lambda r: {**r, "frame": None}),
            ("an unknown field", lambda r: {**r, "frame_sharpness": 3.0})]


@pytest.mark.parametrize("name,change", _bad_refinements(), ids=[n for n, _ in _bad_refinements()])
def test_a_malformed_refinement_is_one_line(overfit_run, tmp_path, tiny_root, name, change):
    """A checkpoint's refinement is checked when the file is read: predict says what is wrong in
    one line instead of a traceback from inside the refinement."""
    from articulated_dataset.methods.dense.refine import Refinement

    ckpt = dict(load_dense_checkpoint(overfit_run[0]))
    refinement = ckpt.get("refinement") or Refinement(frame=True).to_dict()
    split = str(tiny_root / "microwave" / "test")
    bad = tmp_path / "bad.pt"
    torch.save({**ckpt, "refinement": change(dict(refinement))}, bad)
    assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(bad), split, "--out", str(tmp_path / "p.h5")]), "'refinement' is malformed")


def _bad_training_states():
    """(name, change) pairs: each makes an unfinished checkpoint's training state one that
    --resume must refuse in one line (they ended in tracebacks, some after replacing the file)."""
    def moment(value):
        def change(c):
            opt = c["optimizer_state"]
            k = next(iter(opt["state"]))
            state = {**opt["state"], k: {**opt["state"][k], "exp_avg": value(opt["state"][k]["exp_avg"])}}
            return {**c, "optimizer_state": {**opt, "state": state}}
        return change
    return [("no history", lambda c: {**c, "history": None}),
            ("a text history", lambda c: {**c, "history": "abc"}),
            ("a text optimizer state", lambda c: {**c, "optimizer_state": "x"}),
            ("a moment of another shape", moment(lambda v: torch.zeros(3))),
            ("a NaN moment", moment(lambda v: torch.full_like(v, float("nan")))),
            ("a schedule past its end", lambda c: {**c, "scheduler_state": {**c["scheduler_state"], "last_epoch": 10 ** 9}}),
            ("a random state of another size", lambda c: {**c, "rng_state": torch.zeros(3, dtype=torch.uint8)}),
            ("a text CPU time", lambda c: {**c, "cpu_seconds": "x"}),
            ("a step past the training", lambda c: {**c, "step": 10 ** 6})]


@pytest.mark.parametrize("name,change", _bad_training_states(), ids=[n for n, _ in _bad_training_states()])
def test_a_malformed_training_state_is_not_resumed(tiny_root, tmp_path, name, change):
    torch.set_num_threads(1)
    cfg = DenseTrainConfig("drawer", epochs=2, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    out = tmp_path / "b.pt"
    train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False, stop_after_steps=1)
    ckpt = torch.load(out, weights_only=True)
    torch.save(change(ckpt), out)
    before = out.read_bytes()
    assert_one_line_error(CliRunner().invoke(main, ["train", "--model", "dense", "--class", "drawer",
                                                    str(tiny_root / "drawer" / "train"), "--out", str(out), "--resume",
                                                    "--epochs", "2", "--batch-size", "16", "--width", "4",
                                                    "--val-fraction", "0.2", "--max-objects", "3", "-q"]), str(out))
    assert out.read_bytes() == before  # the file is kept as it was


def test_a_diverging_training_keeps_its_last_checkpoint(tiny_root, tmp_path, monkeypatch):
    """Weights that turn non-finite stop the training in one line before a checkpoint is written:
    the last good one stays (a --resume would refuse diverged weights)."""
    from articulated_dataset.core.errors import UserError

    torch.set_num_threads(1)
    cfg = DenseTrainConfig("drawer", epochs=2, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    out = tmp_path / "b.pt"
    train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False, stop_after_steps=1)
    before = out.read_bytes()
    step = torch.optim.AdamW.step

    def diverging(self, *a, **kw):  # the update makes one weight NaN (an --lr too large would)
        result = step(self, *a, **kw)
        self.param_groups[0]["params"][0].data.fill_(float("nan"))
        return result
    monkeypatch.setattr(torch.optim.AdamW, "step", diverging)
    with pytest.raises(UserError, match="lower lr"):
        train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False, resume=True)
    assert out.read_bytes() == before


def test_nan_labels_are_refused_before_training(tiny_root, tmp_path):
    """A split whose labels hold NaN (a real split without full ground truth) is refused as its
    labels are read, not at the first step as "non-finite training loss ... lower --lr"."""
    import shutil

    import h5py

    from articulated_dataset.core.errors import UserError

    split = tmp_path / "drawer" / "train"
    shutil.copytree(tiny_root / "drawer" / "train", split)
    with h5py.File(sorted(split.glob("shard-*.h5"))[0], "a") as f:
        q = f["q"][()]
        q[1] = np.nan
        f["q"][...] = q
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    with pytest.raises(UserError, match=r"1 image\(s\) have NaN or infinite 'q' labels"):
        train_dense(split, tmp_path / "n.pt", cfg, progress=False)
    assert not (tmp_path / "n.pt").exists()


def test_outputs_that_are_inputs_are_refused(overfit_run, tiny_root, tmp_path):
    """predict and plan never write over what they read: the checkpoint, the predictions, a
    split's manifest or shard (they did, and exited 0)."""
    import shutil

    split = tmp_path / "data" / "microwave" / "test"
    shutil.copytree(tiny_root / "microwave" / "test", split)
    model = tmp_path / "m.pt"
    shutil.copy(overfit_run[0], model)
    preds = tmp_path / "p.h5"
    assert _run(["predict", "--model", str(model), str(split), "--out", str(preds), "-q"])[0] == 0
    kept = {p: p.read_bytes() for p in (model, preds, split / "manifest.json")}
    for args in (["predict", "--model", str(model), str(split), "--out", str(model), "--overwrite"],
                 ["predict", "--model", str(model), str(split), "--out", str(split / "manifest.json"), "--overwrite"],
                 ["plan", str(split), "--index", "0", "-q", "--model", str(model), "--out", str(model)],
                 ["plan", str(split), "--index", "0", "-q", "--predictions", str(preds), "--out", str(preds)],
                 ["plan", str(split), "--index", "0", "-q", "--out", str(split / "manifest.json")]):
        text = assert_one_line_error(CliRunner().invoke(main, args))
        assert "also an input" in text or "inside the input folder" in text, text
    assert all(p.read_bytes() == b for p, b in kept.items())
    # beside the split (the folder above it) is fine
    assert _run(["predict", "--model", str(model), str(tmp_path / "data"), "--out",
                 str(tmp_path / "data" / "q.h5"), "-q"])[0] == 0


def test_origin_weight_scales_only_the_origin_terms_of_the_loss(tiny_root):
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.features import make_inputs
    from articulated_dataset.methods.dense.train import dense_loss

    d = load_dense_split(tiny_root / "microwave" / "train", 1, (108, 192), max_objects=1)
    idx = np.arange(4)
    torch.manual_seed(0)
    model = DenseNet(DenseConfig(1, width=4)).eval()
    inputs = make_inputs(d.depth(idx), torch.from_numpy(d.K[idx]))
    with torch.no_grad():
        out = model(inputs["x"])
    q_scale = torch.ones(1)
    loss = [float(dense_loss(model, out, inputs, d, idx, q_scale, w)[0]) for w in (1.0, 2.0, 3.0)]
    assert loss[1] - loss[0] == pytest.approx(loss[2] - loss[1], rel=1e-4) and loss[1] > loss[0]
    assert float(dense_loss(model, out, inputs, d, idx, q_scale)[0]) == pytest.approx(loss[0])  # default 1


# ----------------------------------------------------------------------------- single image
def test_estimate_api_and_cli(overfit_run, tiny_root, tmp_path):
    import h5py
    from PIL import Image

    import articulated_dataset as ad

    with h5py.File(next((tiny_root / "microwave" / "test").glob("shard-*.h5")), "r") as f:
        depth, K = f["depth"][5], f["K"][()]
    est = ad.estimate(depth, K, "microwave", model=str(overfit_run[0]))
    assert est.axis_origin_m.shape == (1, 3) and np.allclose(np.linalg.norm(est.axis_direction, axis=1), 1.0)
    # the same image at twice the resolution gives the same estimate (intrinsics followed)
    K2 = scale_intrinsics(K, depth.shape, (2 * depth.shape[0], 2 * depth.shape[1]))
    est2 = ad.estimate(np.repeat(np.repeat(depth, 2, 0), 2, 1), K2, "microwave", model=str(overfit_run[0]))
    assert np.allclose(est2.axis_origin_m, est.axis_origin_m, atol=0.02)
    png = tmp_path / "d.png"
    Image.fromarray(np.round(depth * 1000).astype(np.uint16)).save(png)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}))
    code, text = _run(["estimate", str(png), "--class", "microwave", "--model", str(overfit_run[0]), "--json"])
    assert code == 0, text
    got = json.loads(text)
    assert np.allclose(got["joints"][0]["axis_origin_m"], est.axis_origin_m[0], atol=2e-3)
    # the borders the object reaches, read from the image's pixels (the one shard's mask, as rendered)
    with h5py.File(next((tiny_root / "microwave" / "test").glob("shard-*.h5")), "r") as f:
        seen = f["mask"][5] > 0
    want = [b for b, edge in zip(("top", "bottom", "left", "right"), (seen[0], seen[-1], seen[:, 0], seen[:, -1]))
            if edge.any()]
    assert est.cut_off == want and got["cut_off"] == want
    first = int(np.nonzero(seen.any(1))[0][0]) + 3  # the image cropped 3 rows into the object
    K_cut = K.copy()
    K_cut[1, 2] -= first
    top_cut = ad.estimate(depth[first:], K_cut, "microwave", model=str(overfit_run[0]))
    assert "top" in top_cut.cut_off and "reaches the image's top" in top_cut.summary()
    # millimetres given as metres, an empty mask, a scene without a mask, a wrong class
    np.save(tmp_path / "mm.npy", depth * 1000)
    (tmp_path / "mm.camera.json").write_text((tmp_path / "camera.json").read_text())
    Image.fromarray(np.zeros(depth.shape, np.uint8)).save(tmp_path / "empty.png")
    scene = np.where(depth > 0, depth, 3.0)  # the object before a wall: found without a prompt
    found = ad.estimate(scene, K, "microwave", model=str(overfit_run[0]))
    np.testing.assert_allclose(found.axis_origin_m, est.axis_origin_m, atol=1e-3)
    rows = np.arange(depth.shape[0], dtype=float)[:, None].repeat(depth.shape[1], 1)
    floor = 1.0 / (1.0 - (5.0 / 6.0) * rows / rows.max())  # inverse depth linear in the row: a plane 1-6 m away
    np.save(tmp_path / "scene.npy", floor)  # a floor and nothing of a microwave's size
    np.save(tmp_path / "tiny.npy", depth[:4, :4])
    (tmp_path / "tiny.camera.json").write_text((tmp_path / "camera.json").read_text())
    for args, needle in [([str(tmp_path / "mm.npy")], "millimetres"),
                         ([str(tmp_path / "tiny.npy")], "4x4 image is too small"),
                         ([str(png), "--mask", str(tmp_path / "empty.png")], "mask"),
                         ([str(tmp_path / "scene.npy"), "--camera", str(tmp_path / "camera.json")], "found no object"),
                         ([str(png), "--class", "drawer"], "'microwave' model")]:
        cls = [] if "--class" in args else ["--class", "microwave"]
        assert_one_line_error(CliRunner().invoke(main, ["estimate", *args, *cls, "--model", str(overfit_run[0])]), needle)


def _huge_exr(path, depth):
    """An EXR of ``depth`` whose header then declares a 20001 x 20001 data window (400 million
    pixels) in a few kilobytes."""
    import struct

    from articulated_dataset.core.images.exr import write_depth_exr

    write_depth_exr(path, depth)
    raw = bytearray(path.read_bytes())
    at = raw.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4  # after the attribute's size
    raw[at:at + 16] = struct.pack("<4i", 0, 0, 20000, 20000)
    path.write_bytes(bytes(raw))


def test_estimate_refuses_files_and_arrays_it_cannot_use(overfit_run, tiny_root, tmp_path):
    """Files and arrays that could hang it, exhaust memory or give a wrong answer silently: a YAML
    camera file's aliases (nested, a few hundred bytes expand to billions of numbers), a camera
    file of megabytes, an EXR header declaring 400 million pixels (its size is checked before a
    pixel is decoded), boolean or complex depth, a transposed or scaled K; a camera file with a
    byte-order mark is read; a float TIFF mask of fractions (0.5 must not become "no object
    pixel"; masks are PNG files, which hold whole numbers only)."""
    import h5py

    import articulated_dataset as ad
    from articulated_dataset.core.errors import UserError

    with h5py.File(next((tiny_root / "microwave" / "test").glob("shard-*.h5")), "r") as f:
        depth, K = f["depth"][5], f["K"][()]
    np.save(tmp_path / "d.npy", depth)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    model = ["--class", "microwave", "--model", str(overfit_run[0])]
    (tmp_path / "alias.yaml").write_text(f"f: &f {fx}\nfx: *f\nfy: *f\ncx: {cx}\ncy: {cy}\n")
    (tmp_path / "plain.yaml").write_text(f"fx: {fx}\nfy: {fy}\ncx: {cx}\ncy: {cy}\n")
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy}).encode())
    (tmp_path / "big.json").write_text(json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy, "pad": "x" * 2_000_000}))
    _huge_exr(tmp_path / "huge.exr", depth)
    from PIL import Image

    Image.fromarray(np.where(depth > 0, 0.5, 0.0).astype(np.float32), mode="F").save(tmp_path / "half.tiff")
    (tmp_path / "huge.camera.json").write_text(json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy}))
    for camera in ("plain.yaml", "bom.json"):
        code, text = _run(["estimate", str(tmp_path / "d.npy"), "--camera", str(tmp_path / camera), *model])
        assert code == 0, text
    Image.fromarray(np.where(depth > 0, 65535, 0).astype(np.uint16)).save(tmp_path / "white16.png")  # binary, 16-bit
    code, text = _run(["estimate", str(tmp_path / "d.npy"), "--camera", str(tmp_path / "plain.yaml"), "--mask",
                       str(tmp_path / "white16.png"), *model])
    assert code == 0, text
    for args, needle in [([str(tmp_path / "d.npy"), "--camera", str(tmp_path / "alias.yaml")], "aliases"),
                         ([str(tmp_path / "d.npy"), "--camera", str(tmp_path / "big.json")], "bytes"),
                         ([str(tmp_path / "huge.exr")], "not a depth sensor's image"),
                         ([str(tmp_path / "d.npy"), "--camera", str(tmp_path / "plain.yaml"), "--mask",
                           str(tmp_path / "half.tiff")], "must be a PNG file")]:
        assert_one_line_error(CliRunner().invoke(main, ["estimate", *args, *model]), needle)
    for depth_, K_, needle in [(depth > 0, K, "real numbers"), (depth.astype(complex), K, "real numbers"),
                               (depth, K.T, "no skew"), (depth, 2 * K, "no skew"), (depth, K + [[0, 50, 0], [0] * 3, [0] * 3], "no skew"),
                               (depth, K.astype(complex), "real numbers")]:
        with pytest.raises(UserError, match=needle):
            ad.estimate(depth_, K_, "microwave", model=str(overfit_run[0]))
    with pytest.raises(UserError, match="checkpoint's path"):
        ad.estimate(depth, K, "microwave", model=None)


def test_predict_with_the_dense_model_refuses_mdn_options(overfit_run, tiny_root, tmp_path):
    split = str(tiny_root / "microwave" / "test")
    for extra, needle in [(["--device", "cuda"], "--device"), (["--estimate", "mode"], "--estimate")]:
        assert_one_line_error(CliRunner().invoke(main, ["predict", "--model", str(overfit_run[0]), split, "--out", str(tmp_path / "p.h5"), *extra]), needle)
    code, text = _run(["predict", "--model", str(overfit_run[0]), split, "--out", str(tmp_path / "p.h5"),
                       "--device", "cpu", "-q"])
    assert code == 0, text


def test_init_from_continues_a_finished_training(overfit_run, tiny_root, tmp_path):
    src, ckpt, cfg = overfit_run
    cont = DenseTrainConfig("microwave", epochs=1, batch_size=16, lr=1e-12, width=8, val_fraction=0.0, max_objects=1,
                            init_from=str(src))
    out = train_dense(tiny_root / "microwave" / "train", tmp_path / "c.pt", cont, progress=False)
    for k, v in ckpt["model_state"].items():
        if v.is_floating_point() and "running" not in k:
            assert torch.allclose(v, out["model_state"][k], atol=1e-6), k
    wrong = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=8, val_fraction=0.0, max_objects=1, init_from=str(src))
    with pytest.raises(Exception, match="init_from"):
        train_dense(tiny_root / "drawer" / "train", tmp_path / "d.pt", wrong, progress=False)


@pytest.mark.slow
def test_a_split_read_in_two_processes_is_the_same_arrays(tiny_root):
    """load_dense_split(workers=2) reads the shards in processes: the arrays, their order and the
    object selection are those of the one-process read."""
    from articulated_dataset.methods.dense.data import load_dense_split

    split = tiny_root / "drawer" / "train"
    one = load_dense_split(split, 1, (108, 192), max_objects=5, workers=1)
    two = load_dense_split(split, 1, (108, 192), max_objects=5, workers=2)
    assert len(np.unique(one.shard_of)) == 2 and set(np.unique(one.object_index)) == set(range(5))
    for name in one.__dataclass_fields__:
        a, b = getattr(one, name), getattr(two, name)
        assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), name


def test_a_split_read_for_some_objects_is_the_full_reads_images_of_them(tiny_root):
    """load_dense_split(objects=...) (a refit's validation objects) gives exactly the full read's
    rows of those objects, in order; split_object_indices lists the full read's object indices."""
    from articulated_dataset.methods.dense.data import load_dense_split, split_object_indices

    split = tiny_root / "drawer" / "train"
    full = load_dense_split(split, 1, (108, 192), max_objects=5, workers=1)
    assert np.array_equal(split_object_indices(split, max_objects=5), full.object_index)
    wanted = np.array([3, 1])
    some = load_dense_split(split, 1, (108, 192), max_objects=5, objects=wanted, workers=1)
    rows = np.isin(full.object_index, wanted)
    assert set(np.unique(some.object_index)) == {1, 3} and len(some.sample_id) == rows.sum()
    for name in full.__dataclass_fields__:
        a, b = getattr(full, name), getattr(some, name)
        assert (a is None and b is None) or np.array_equal(a[rows], b), name
    from articulated_dataset.core.errors import UserError

    with pytest.raises(UserError, match="no images selected"):
        load_dense_split(split, 1, (108, 192), max_objects=5, objects=np.array([7]), workers=1)


def test_depth_quantisation_rounds_to_the_store_quantum_and_drops_what_it_cannot_hold():
    """quantise_depth scales float32 depths in float32 (exact: the quantum is a power of two); the
    result is the float64 formula's, edge cases included."""
    from articulated_dataset.methods.dense.data import DEPTH_STORE_QUANTUM_M, quantise_depth

    def reference(d):
        d = np.nan_to_num(np.asarray(d, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        q = np.rint(d / DEPTH_STORE_QUANTUM_M)
        q[(q < 0) | (q > 65535)] = 0
        return q.astype(np.uint16)

    rng = np.random.default_rng(0)
    d = (rng.random((40, 50)) * 9 - 0.5).astype(np.float32)  # beyond the 8 m range and negative too
    d[0, :6] = [np.nan, np.inf, -np.inf, -1.0, 1e30, -0.0]
    d[1, :3] = [1.5 * DEPTH_STORE_QUANTUM_M, 2.5 * DEPTH_STORE_QUANTUM_M, 65535.5 * DEPTH_STORE_QUANTUM_M]  # ties
    for a in (d, d.astype(np.float64), rng.random((9, 9)) * 8.1):
        q = quantise_depth(a)
        assert q.dtype == np.uint16 and np.array_equal(q, reference(a))
    assert quantise_depth(np.float32([1.5, 2.5]) * DEPTH_STORE_QUANTUM_M).tolist() == [2, 2]  # half to even
    assert quantise_depth(np.float32([np.nan, 8.5, -0.1, 1.0])).tolist() == [0, 0, 0, 8192]
