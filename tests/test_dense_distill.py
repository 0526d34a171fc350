"""``artdata train --model dense --distill-mirror``: one network pass learns what the teacher gives
averaged with its mirror image (refinement step 8)."""

import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.errors import UserError
from articulated_dataset.models.dense.model import DenseConfig, DenseNet, OFFSET_SCALE_M
from articulated_dataset.models.dense.train import (ORIGIN_SCALE_M, DenseTrainConfig, mirror_distill_loss,
                                                    train_dense)


def test_the_distillation_loss_is_zero_at_the_target_and_linear_in_each_difference():
    torch.manual_seed(0)
    model = DenseNet(DenseConfig(1, width=8))
    target = torch.randn(2, model.n_out, 4, 5)
    weight = torch.zeros(2, 4, 5)
    weight[0, 1, 2] = 1.0
    weight[1, 3, 3] = 0.5
    q_scale = torch.tensor([0.5])
    assert float(mirror_distill_loss(model, target.clone(), target, weight, q_scale)) == 0.0
    offset_x = 2 + 0  # body and part logits, then the joint's block: its offset first
    for delta in (0.1, 0.3):
        out = target.clone()
        out[0, offset_x, 1, 2] += delta  # raw units: OFFSET_SCALE_M m each
        # the pixel's offset moves delta * 0.5 m; divided by 5 cm; the weights sum to 1.5
        expected = delta * OFFSET_SCALE_M / ORIGIN_SCALE_M / 1.5
        assert float(mirror_distill_loss(model, out, target, weight, q_scale)) == pytest.approx(expected, rel=1e-5)
    out = target.clone()
    out[1, :, 0, 0] += 1.0  # a pixel of weight 0 costs nothing
    assert float(mirror_distill_loss(model, out, target, weight, q_scale)) == 0.0
    out[1, 0, 3, 3] += 2.0  # a part logit moved: the two distributions differ
    assert float(mirror_distill_loss(model, out, target, weight, q_scale)) > 0.01


@pytest.fixture(scope="module")
def drawer_teacher(tiny_root, tmp_path_factory):
    torch.set_num_threads(2)
    out = tmp_path_factory.mktemp("distill") / "teacher.pt"
    cfg = DenseTrainConfig("drawer", epochs=6, batch_size=16, lr=1e-2, width=8, val_fraction=0.0, max_objects=2)
    train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False)
    return out


def _distance_to_the_mirror_average(student_ckpt, teacher_path, tiny_root):
    """mirror_distill_loss of a checkpoint's network against the teacher's mirror-averaged outputs,
    on the first two objects' images (eval mode)."""
    from articulated_dataset.models.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.models.dense.data import load_dense_split
    from articulated_dataset.models.dense.features import make_inputs
    from articulated_dataset.models.dense.predict import network_outputs
    from articulated_dataset.registry import get_class

    teacher = build_dense_model(load_dense_checkpoint(teacher_path))
    student = build_dense_model(student_ckpt)
    d = load_dense_split(tiny_root / "drawer" / "train", 1, (108, 192), max_objects=2)
    idx = np.arange(len(d.sample_id))
    inputs = make_inputs(d.depth(idx), torch.from_numpy(d.K[idx]))
    with torch.no_grad():
        target = network_outputs(teacher, inputs["x"], get_class("drawer").mirror_joints)
        return float(mirror_distill_loss(student, student(inputs["x"]), target, inputs["weight_out"],
                                         torch.tensor(student_ckpt["q_scale"], dtype=torch.float32)))


def test_a_distilled_network_moves_towards_the_mirror_average_and_runs_once(drawer_teacher, tiny_root, tmp_path):
    from articulated_dataset.models.dense.checkpoint import load_dense_checkpoint

    teacher = load_dense_checkpoint(drawer_teacher)
    cfg = DenseTrainConfig("drawer", epochs=15, batch_size=16, lr=2e-3, width=8, val_fraction=0.34, max_objects=3,
                           init_from=str(drawer_teacher), distill_mirror=True)
    ckpt = train_dense(tiny_root / "drawer" / "train", tmp_path / "s.pt", cfg, progress=False)
    plain = train_dense(tiny_root / "drawer" / "train", tmp_path / "p.pt", replace(cfg, distill_mirror=False),
                        progress=False)
    # the same steps on the labels alone move the network further from the teacher's mirror average
    distilled = _distance_to_the_mirror_average(ckpt, drawer_teacher, tiny_root)
    labels_only = _distance_to_the_mirror_average(plain, drawer_teacher, tiny_root)
    assert distilled < 0.85 * labels_only, (distilled, labels_only,
                                           _distance_to_the_mirror_average(teacher, drawer_teacher, tiny_root))
    assert ckpt["distill"]["mirror"] and ckpt["distill"]["teacher"] == "teacher.pt"
    assert ckpt["refinement"]["mirror_joints"] is None  # the fit never adds the second pass
    assert "mirror_position_cm" not in ckpt["refinement_report"]
    assert all("train_distill" in h for h in ckpt["history"])

    # a resumed run must find the same teacher
    other = tmp_path / "other.pt"
    shutil.copy(drawer_teacher, other)
    with open(other, "ab") as f:
        f.write(b"\0")  # another file (torch ignores trailing bytes)
    stopped = tmp_path / "stopped.pt"
    moved = DenseTrainConfig("drawer", epochs=2, batch_size=16, lr=2e-3, width=8, val_fraction=0.0, max_objects=2,
                             init_from=str(other), distill_mirror=True)
    train_dense(tiny_root / "drawer" / "train", stopped, moved, progress=False, stop_after_steps=1)
    with open(other, "ab") as f:
        f.write(b"\0")
    with pytest.raises(UserError, match="not the teacher"):
        train_dense(tiny_root / "drawer" / "train", stopped, moved, progress=False, resume=True)


def test_distillation_needs_a_teacher_and_a_class_with_a_mirror_image(tiny_root, tmp_path):
    with pytest.raises(UserError, match="needs --init-from"):
        DenseTrainConfig("drawer", distill_mirror=True)
    with pytest.raises(UserError, match="mirror image of a microwave"):
        DenseTrainConfig("microwave", init_from="x.pt", distill_mirror=True)
    runner = CliRunner()
    res = runner.invoke(main, ["train", "--class", "drawer", "--data", str(tiny_root / "drawer" / "train"), "--out",
                               str(tmp_path / "m.pt"), "--small", "--distill-mirror"])
    assert res.exit_code == 2 and "belong to --model dense" in res.output and res.output.count("\n") == 1, res.output
    res = runner.invoke(main, ["train", "--model", "dense", "--class", "toaster", "--data",
                               str(tiny_root / "toaster" / "train"), "--out", str(tmp_path / "t.pt"), "--init-from",
                               str(tmp_path / "m.pt"), "--distill-mirror"])
    assert res.exit_code == 2 and "mirror image of a toaster" in res.output, res.output
