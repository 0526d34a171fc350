"""``artdata train --model dense`` on a mixture of splits: weighted batches, per-split
validation objects, the splits recorded in the checkpoint and checked by ``--resume``."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402

from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.generation import GenerationConfig, generate_split  # noqa: E402
from articulated_dataset.methods.dense.data import mixture_order  # noqa: E402
from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense  # noqa: E402
from articulated_dataset.methods.mdn.data import split_identity  # noqa: E402
from helpers_core import assert_one_line_error  # noqa: E402

#: The second split of the mixture: its own seed and a few objects.
SECOND_SEED = 7
SECOND_OBJECTS = 3
#: The smallest training run: one epoch of a 4-channel network.
TINY_TRAIN = ["--epochs", "1", "--width", "4", "--batch-size", "16", "--val-fraction", "0.2", "-q"]


@pytest.fixture(scope="module")
def second_drawer_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("second")
    generate_split(GenerationConfig("drawer", split="train", n_objects=SECOND_OBJECTS, objects_per_shard=4,
                                    seed=SECOND_SEED), root)
    return root / "drawer" / "train"


def _train(*args):
    return CliRunner().invoke(main, ["train", "--model", "dense", *[str(a) for a in args]])


def test_batches_draw_from_the_splits_in_proportion_to_the_weights():
    pools = [np.arange(0, 10), np.arange(10, 1000), np.arange(1000, 1050)]
    weights = np.array([2.0, 1.0, 1.0])
    order = mixture_order(pools, weights, 40_000, np.random.default_rng(0))
    share = np.array([np.isin(order, p).mean() for p in pools])
    assert np.allclose(share, weights / weights.sum(), atol=0.01), share
    small = order[np.isin(order, pools[0])]  # a small split weighted high: every image, evenly
    assert np.bincount(small, minlength=10).min() >= len(small) // 10
    again = mixture_order(pools, weights, 40_000, np.random.default_rng(0))
    assert np.array_equal(order, again)


def test_two_splits_train_and_record_both_identities_and_weights(tiny_root, second_drawer_split, tmp_path):
    torch.set_num_threads(1)
    first = tiny_root / "drawer" / "train"
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2)
    ckpt = train_dense([first, second_drawer_split], tmp_path / "m.pt", cfg, progress=False, fit=False,
                       mix_weights=[1.0, 3.0])
    splits = ckpt["data"]["splits"]
    assert [s["split"] for s in splits] == [split_identity(first), split_identity(second_drawer_split)]
    assert [s["weight"] for s in splits] == [1.0, 3.0]
    assert all(s["n_train_images"] > 0 and s["n_val_images"] > 0 for s in splits)
    assert ckpt["data"]["n_train_images"] == sum(s["n_train_images"] for s in splits)
    record = ckpt["history"][-1]
    for key in ("val_pos_cm", "val_s0_pos_cm", "val_s1_pos_cm"):  # together and per split
        assert np.isfinite(record[key]), key
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.dense.train import refit_inference

    with pytest.raises(UserError, match="mixture"):  # its validation objects lie in several splits
        refit_inference(tmp_path / "m.pt", first, tmp_path / "r.pt", progress=False)


def test_resume_with_another_list_of_splits_is_one_line(tiny_root, second_drawer_split, tmp_path):
    torch.set_num_threads(1)
    first, out = tiny_root / "drawer" / "train", tmp_path / "m.pt"
    res = _train("--class", "drawer", first, second_drawer_split, "--mix-weights", "1,1", "--out", out, *TINY_TRAIN)
    assert res.exit_code == 0, res.output
    for other in (["--mix-weights", "1,2"], []):
        res = _train("--class", "drawer", first, second_drawer_split, *other, "--out", out, *TINY_TRAIN, "--resume")
        assert_one_line_error(res, "--resume", "weighted")
    res = _train("--class", "drawer", first, "--out", out, *TINY_TRAIN, "--resume")
    assert_one_line_error(res, "--resume", "2 split(s), not 1")
    res = _train("--class", "drawer", second_drawer_split, first, "--mix-weights", "1,1", "--out", out, *TINY_TRAIN,
                 "--resume")
    assert_one_line_error(res, "--resume")


def test_a_split_of_another_class_or_a_wrong_weight_list_is_one_line(tiny_root, tmp_path):
    first, other = tiny_root / "drawer" / "train", tiny_root / "microwave" / "train"
    res = _train("--class", "drawer", first, other, "--out", tmp_path / "m.pt", *TINY_TRAIN)
    assert_one_line_error(res, str(other), "microwave")
    res = _train("--class", "drawer", first, first, "--out", tmp_path / "m.pt", *TINY_TRAIN)
    assert_one_line_error(res, "given twice")
    res = _train("--class", "drawer", first, tiny_root / "drawer" / "test", "--mix-weights", "1", "--out",
                 tmp_path / "m.pt", *TINY_TRAIN)
    assert_one_line_error(res, "--mix-weights", "1 weight(s) for 2 split(s)")
    res = _train("--class", "drawer", first, tiny_root / "drawer" / "test", "--mix-weights", "1,x", "--out",
                 tmp_path / "m.pt", *TINY_TRAIN)
    assert_one_line_error(res, "--mix-weights")
    res = CliRunner().invoke(main, ["train", "--model", "mdn", "--class", "drawer", str(first),
                                    str(tiny_root / "drawer" / "test"), "--out", str(tmp_path / "n.pt")])
    assert_one_line_error(res, "--model mdn trains on one split")


def test_one_split_trains_as_before_and_records_no_mixture(tiny_root, tmp_path):
    """A list of one split is the split: the same weights, the same checkpoint fields."""
    torch.set_num_threads(1)
    split = tiny_root / "drawer" / "train"
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    alone = train_dense(split, tmp_path / "a.pt", cfg, progress=False, fit=False)
    listed = train_dense([split], tmp_path / "b.pt", cfg, progress=False, fit=False)
    assert "splits" not in alone["data"] and alone["data"].keys() == listed["data"].keys()
    for k, v in alone["model_state"].items():
        assert torch.equal(v, listed["model_state"][k]), k
    res = _train("--class", "drawer", split, "--mix-weights", "2", "--out", tmp_path / "c.pt", *TINY_TRAIN)
    assert_one_line_error(res, "--mix-weights", "two split folders")
