"""scripts/transplant_dense.py: another class's weights as a dense model's starting point."""


import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.methods.dense.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, build_dense_model  # noqa: E402
from articulated_dataset.methods.dense.model import GEOMETRY_CHANNELS, JOINT_CHANNELS, DenseConfig, DenseNet  # noqa: E402
from articulated_dataset.methods.dense.train import load_dense_checkpoint  # noqa: E402
from helpers_core import ROOT, load_script  # noqa: E402


def _script():
    return load_script(ROOT / "scripts" / "transplant_dense.py", "transplant_dense")


def _ckpt(class_name, joint_types, seed, width=4):
    torch.manual_seed(seed)
    net = DenseNet(DenseConfig(n_joints=len(joint_types), width=width))
    for p in net.parameters():  # every weight distinct from the other checkpoint's
        p.data.normal_()
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "class_name": class_name,
            "joint_types": list(joint_types), "model_config": net.config.to_dict(), "train_config": {"seed": 3},
            "model_state": net.state_dict(), "q_scale": [0.4] * len(joint_types), "finished": True,
            "step": 100}


def test_the_trunk_and_the_matching_head_rows_come_from_the_source(tmp_path):
    mod = _script()
    src = _ckpt("cabinet2", ["revolute", "revolute"], 0)
    like = _ckpt("cabinet", ["revolute"], 1)
    torch.save(src, tmp_path / "dense-cabinet2.pt")
    torch.save(like, tmp_path / "dense-cabinet.pt")
    assert mod.main(["--from", str(tmp_path / "dense-cabinet2.pt"), "--like", str(tmp_path / "dense-cabinet.pt"),
                     "--out", str(tmp_path / "init.pt")]) == 0
    out = load_dense_checkpoint(tmp_path / "init.pt")  # a dense checkpoint 'artdata train --init-from' reads
    assert out["class_name"] == "cabinet" and out["q_scale"] == like["q_scale"] and out["train_config"] == {}
    assert out["transplant"]["from"]["class_name"] == "cabinet2" and len(out["transplant"]["like"]["sha256"]) == 64
    net = build_dense_model(out).state_dict()
    s, d = src["model_state"], like["model_state"]
    for k in net:
        if not k.startswith("head."):
            assert torch.equal(net[k], s[k]), k
    w_src, w_out = s["head.weight"], net["head.weight"]
    assert torch.equal(w_out[:2], w_src[:2])  # body, part 0
    assert torch.equal(w_out[2:2 + JOINT_CHANNELS], w_src[3:3 + JOINT_CHANNELS])  # joint 0's channels
    assert torch.equal(w_out[-GEOMETRY_CHANNELS:], w_src[-GEOMETRY_CHANNELS:])  # geometry
    assert not torch.equal(w_out, d["head.weight"])


def test_head_rows_of_a_class_with_more_joints_keep_the_targets_own():
    mod = _script()
    src = _ckpt("cabinet", ["revolute"], 0)
    like = _ckpt("cabinet2", ["revolute", "revolute"], 1)
    out = mod.transplant(src, like)
    w = out["model_state"]["head.weight"]
    rows_src, rows_dst = mod.head_rows(1, 2)
    assert torch.equal(w[rows_dst], src["model_state"]["head.weight"][rows_src])
    others = [r for r in range(w.shape[0]) if r not in rows_dst]
    assert others and torch.equal(w[others], like["model_state"]["head.weight"][others])  # the second door's own


def test_another_width_is_refused():
    mod = _script()
    with pytest.raises(SystemExit, match="same --width"):
        mod.transplant(_ckpt("cabinet2", ["revolute", "revolute"], 0, width=8), _ckpt("cabinet", ["revolute"], 1))
