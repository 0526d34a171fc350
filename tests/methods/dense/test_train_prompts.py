"""``artdata train --prompts``: in a split with a scene the dense model trains on each image's
object as a simulated prompt segments it (docs/robot_view.md), kinds taken in turn by sample id;
an isolated split keeps every pixel."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import open_split
from articulated_dataset.format.shards import Shard
from helpers_core import assert_one_line_error

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def kitchen(tmp_path_factory):
    root = tmp_path_factory.mktemp("train_prompts")
    for name, extra in (("plain", []), ("kitchen", ["--scene", "kitchen"])):
        r = CliRunner().invoke(main, ["generate", "--class", "microwave", "--n", "2", "--split", "train", "--seed", "5",
                                      "--out", str(root / name), "-q", *extra])
        assert r.exit_code == 0, r.output
    return root


def _stored(split):
    _, shards = open_split(split)
    sh = Shard(shards[0].path)
    try:
        return sh.read("depth"), sh.read("mask"), np.asarray(sh.K, np.float64), np.asarray(sh.read("sample_id"))
    finally:
        sh.close()


def test_kinds_are_taken_in_turn_by_sample_id(kitchen):
    """Each image of a kitchen split is segmented by the kind its sample id picks, exactly as that
    kind alone segments it; the network's input is the prompted depth, resized."""
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.prompts import class_extent_m, prompted_depth

    split = kitchen / "kitchen" / "microwave" / "train"
    depth, mask, K, sid = _stored(split)
    extent = class_extent_m("microwave")
    kinds = ("box", "point")
    hw = depth.shape[1:]
    both = load_dense_split(split, 1, hw, prompt=kinds, max_extent_m=extent, with_labels=False)
    for i in range(len(sid)):
        want = prompted_depth(depth[i], K, kinds[int(sid[i]) % 2], mask[i], max_extent_m=extent)
        row = int(np.nonzero(both.sample_id == sid[i])[0][0])
        assert ((both.depth_q[row] > 0) == (want > 0)).all(), i
    every = load_dense_split(split, 1, hw, with_labels=False)
    assert (every.depth_q > 0).sum() > (both.depth_q > 0).sum()  # the prompts left the scene out


def test_training_records_the_prompts_and_prompts_only_scenes(kitchen, tmp_path, monkeypatch):
    """Two steps on a plain and a kitchen split: the checkpoint records the kinds, and only the
    kitchen split is read through them."""
    import articulated_dataset.methods.dense.train as train_module
    from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint

    seen = {}
    real = train_module.load_dense_split

    def spy(split_dir, *args, **kwargs):
        seen[split_dir.parent.parent.name] = kwargs.get("prompt")
        return real(split_dir, *args, **kwargs)

    monkeypatch.setattr(train_module, "load_dense_split", spy)
    config = train_module.DenseTrainConfig(class_name="microwave", epochs=1, batch_size=8, width=4,
                                           val_fraction=0.0, prompts=("box", "point"))
    out = tmp_path / "p.pt"
    train_module.train_dense([kitchen / "plain" / "microwave" / "train", kitchen / "kitchen" / "microwave" / "train"],
                             out, config, progress=False, stop_after_steps=2, fit=False)
    assert seen == {"plain": None, "kitchen": ("box", "point")}
    assert tuple(load_dense_checkpoint(out)["train_config"]["prompts"]) == ("box", "point")


def test_bad_prompts_are_one_line(kitchen, tmp_path):
    split = str(kitchen / "kitchen" / "microwave" / "train")
    for args, needle in [(["--prompts", "click"], "--prompts must be kinds of point, box, mask, none"),
                         (["--prompts", "box", "--model", "mdn"], "--prompts belong to --model dense")]:
        model = [] if "--model" in args else ["--model", "dense"]
        assert_one_line_error(CliRunner().invoke(main, ["train", *model, "--class", "microwave", split, "--out",
                                                        str(tmp_path / "m.pt"), "-q", *args]), needle)
