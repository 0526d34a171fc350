"""``--resume`` of a checkpoint whose optimizer parameter groups or moments are malformed: the
state is refused in one line naming the file, the file is kept, and an MDN training never writes
diverged weights.  Unchecked, a NaN learning rate, ``eps`` 0 or a negative second moment would be
trained on, exit 0 and replace the resumable checkpoint with one of NaN weights that no reader
loads ("model_state holds NaN or infinite weights"); text ``betas`` or a negative ``step`` would
end in a TypeError / RuntimeError traceback."""

from __future__ import annotations

import copy

import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.core.errors import UserError  # noqa: E402
from articulated_dataset.generation import GenerationConfig, generate_split  # noqa: E402
from articulated_dataset.methods.mdn.config import TrainConfig  # noqa: E402
from articulated_dataset.methods.mdn.train import train  # noqa: E402

TINY = dict(preset="small", width=4, blocks=(1, 1), height_px=27, width_px=48, n_components=3, batch_size=16,
            val_fraction=0.0)


@pytest.fixture(scope="module")
def unfinished(tmp_path_factory):
    """A split and an MDN checkpoint stopped after epoch 1 of 2."""
    root = tmp_path_factory.mktemp("resume")
    data = generate_split(GenerationConfig("cabinet", split="train", n_objects=2, images_per_object=4), root)
    cfg = TrainConfig(class_name="cabinet", epochs=2, **TINY)
    out = root / "part.pt"
    train(data, out, cfg, progress=False, stop_after_epoch=1)
    return data, cfg, torch.load(out, weights_only=True)


def _group(**kw):
    def change(opt):
        opt["param_groups"][0].update(kw)
    return change


def _state(key, value):
    def change(opt):
        st = next(iter(opt["state"].values()))
        st[key] = value(st[key])
    return change


CHANGES = {
    "lr NaN": _group(lr=float("nan")),
    "initial_lr inf": _group(initial_lr=float("inf")),
    "eps zero": _group(eps=0.0),
    "betas text": _group(betas="ab"),
    "beta above 1": _group(betas=(2.0, 0.999)),
    "negative weight decay": _group(weight_decay=-1.0),
    "negative second moment": _state("exp_avg_sq", lambda v: -v - 1.0),
    "negative step": _state("step", lambda v: v * 0 - 5),
}


@pytest.mark.parametrize("name", list(CHANGES))
def test_a_malformed_optimizer_state_is_not_resumed(unfinished, tmp_path, name):
    data, cfg, ckpt = unfinished
    bad = copy.deepcopy(ckpt)
    CHANGES[name](bad["optimizer_state"])
    out = tmp_path / "bad.pt"
    torch.save(bad, out)
    before = out.read_bytes()
    with pytest.raises(UserError, match="optimizer_state"):
        train(data, out, cfg, progress=False, resume=True)
    assert out.read_bytes() == before


def test_an_mdn_training_never_writes_diverged_weights(unfinished, tmp_path, monkeypatch):
    data, cfg, ckpt = unfinished
    out = tmp_path / "part.pt"
    torch.save(ckpt, out)
    before = out.read_bytes()
    step = torch.optim.AdamW.step

    def diverging(self, *a, **kw):  # the update makes one weight NaN
        result = step(self, *a, **kw)
        self.param_groups[0]["params"][0].data.fill_(float("nan"))
        return result
    monkeypatch.setattr(torch.optim.AdamW, "step", diverging)
    with pytest.raises(UserError, match="keeps the last checkpoint"):
        train(data, out, cfg, progress=False, resume=True)
    assert out.read_bytes() == before


def test_an_mdn_training_refuses_nan_labels(unfinished, tmp_path):
    """NaN labels (a real split without full ground truth) are refused as they are read, not as a
    NaN loss from the first step with a message to lower --lr."""
    import shutil

    import h5py
    import numpy as np

    data, cfg, _ = unfinished
    split = tmp_path / "cabinet" / "train"
    shutil.copytree(data, split)
    with h5py.File(sorted(split.glob("shard-*.h5"))[0], "a") as f:
        pose = f["axis_pose"][()]
        pose[0, 0, 0] = np.nan
        f["axis_pose"][...] = pose
    with pytest.raises(UserError, match=r"1 image\(s\) have NaN or infinite labels"):
        train(split, tmp_path / "m.pt", cfg, progress=False)
    assert not (tmp_path / "m.pt").exists()
