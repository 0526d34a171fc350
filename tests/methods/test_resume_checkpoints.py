"""``--resume`` of a checkpoint whose state is malformed: refused in one line naming the file, the
file kept as it was, for the MDN and the dense model.

The optimizer's parameter groups or moments: unchecked, a NaN learning rate, ``eps`` 0 or a
negative second moment would be trained on, exit 0 and replace the resumable checkpoint with one
of NaN weights that no reader loads ("model_state holds NaN or infinite weights"); text ``betas``
or a negative ``step`` would end in a TypeError / RuntimeError traceback.  An MDN training never
writes diverged weights.  The checkpoint's ``data`` record (which split it was trained on) that is
not a mapping: one line, not an ``AttributeError: 'list' object has no attribute 'get'``."""

from __future__ import annotations

import copy

import pytest

torch = pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402

from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.core.errors import UserError  # noqa: E402
from articulated_dataset.generation import GenerationConfig, generate_split  # noqa: E402
from articulated_dataset.methods.mdn.config import TrainConfig  # noqa: E402
from articulated_dataset.methods.mdn.train import train  # noqa: E402
from helpers_core import assert_one_line_error  # noqa: E402

TINY = dict(preset="small", width=4, blocks=(1, 1), height_px=27, width_px=48, n_components=3, batch_size=16,
            val_fraction=0.0)


@pytest.fixture(scope="module")
def small_train_split(tmp_path_factory):
    """A cabinet training split of 2 objects x 4 images: a training epoch takes a fraction of the
    tiny split's time (whose 16 images per object would make each case several times slower)."""
    return generate_split(GenerationConfig("cabinet", split="train", n_objects=2, images_per_object=4),
                          tmp_path_factory.mktemp("resume-data"))


@pytest.fixture(scope="module")
def unfinished(small_train_split, tmp_path_factory):
    """The small split and an MDN checkpoint stopped after epoch 1 of 2."""
    out = tmp_path_factory.mktemp("resume") / "part.pt"
    cfg = TrainConfig(class_name="cabinet", epochs=2, **TINY)
    train(small_train_split, out, cfg, progress=False, stop_after_epoch=1)
    return small_train_split, cfg, torch.load(out, weights_only=True)


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


# ---- the checkpoint's data record

MODELS = {"mdn": ["--small", "--epochs", "2", "--batch-size", "16", "--components", "3"],
          "dense": ["--model", "dense", "--epochs", "2", "--width", "4", "--batch-size", "16"]}
#: A warning a training without validation objects logs before it starts: not part of the error.
NO_VALIDATION = "no validation objects"


def _train_cli(data, out, model, *extra):
    return CliRunner().invoke(main, ["train", "--model", "mdn", "--class", "cabinet", str(data), "--out", str(out),
                                     "--val-fraction", "0", "-q", *MODELS[model], *extra])


@pytest.mark.parametrize("record", [[1, 2], "split", 7])
@pytest.mark.parametrize("model", list(MODELS))
def test_a_data_record_that_is_not_a_mapping_is_one_line(small_train_split, tmp_path, model, record):
    data = small_train_split
    out = tmp_path / "m.pt"
    assert _train_cli(data, out, model).exit_code == 0
    ckpt = torch.load(out, weights_only=True)
    ckpt.update(data=record, finished=False)
    ckpt["epoch" if model == "mdn" else "step"] = 1
    torch.save(ckpt, out)
    before = out.read_bytes()
    assert_one_line_error(_train_cli(data, out, model, "--resume"), "'data'", str(out), ignore=(NO_VALIDATION,))
    assert out.read_bytes() == before

