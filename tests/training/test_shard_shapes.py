"""A shard whose image size or joint count differs from its split's manifest and class: the
loaders allocate their arrays from the manifest, so unchecked, a shard of another class (two joints
in a cabinet split) would end in ``ValueError: could not broadcast`` in ``ShardReader``,
``NormStats.from_split`` and the torch loaders, and ``artdata train --model dense`` in a
``RuntimeError`` inside its loss, and a shard of other images would be called damaged."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.training.loaders.reader import ShardReader
from articulated_dataset.training.targets import NormStats, TargetLayout
from helpers_core import assert_one_line_error

JOINT_FIELDS = ("q", "axis_origin", "axis_direction", "axis_pose", "part_offset")


def _replace(f: h5py.File, name: str, a: np.ndarray) -> None:
    chunks = f[name].chunks
    del f[name]
    f.create_dataset(name, data=a, chunks=chunks)


def _two_joints(f: h5py.File) -> None:
    """Every per-joint label doubled: a consistent shard of a two-joint class."""
    for name in JOINT_FIELDS:
        a = f[name][()]
        _replace(f, name, np.concatenate([a, a], axis=1))
    v = f["visible_pixels"][()]
    _replace(f, "visible_pixels", np.concatenate([v, v[:, 1:]], axis=1))
    f.attrs.update(n_joints=2, joint_types='["revolute", "revolute"]', joint_names='["a", "b"]')


def _half_size(f: h5py.File) -> None:
    for name in ("depth", "mask"):
        a = f[name][()][:, ::2, ::2]
        del f[name]
        f.create_dataset(name, data=a, chunks=(1,) + a.shape[1:])


@pytest.fixture(params=["two-joints", "half-size"])
def crafted(request, split_copy):
    copy = split_copy("cabinet", "train")
    with h5py.File(copy / "shard-00000.h5", "a") as f:
        (_two_joints if request.param == "two-joints" else _half_size)(f)
    return request.param, copy


def test_the_reader_names_a_shard_of_other_shapes(crafted):
    kind, copy = crafted
    needle = "joint" if kind == "two-joints" else "px"
    with pytest.raises(DataFormatError, match="does not belong"):
        ShardReader(copy)[0]
    with pytest.raises(DataFormatError, match="does not belong"):
        ShardReader(copy, fields=["q"]).get_batch([0, 1])
    with pytest.raises(DataFormatError, match=needle):
        NormStats.from_split(copy, TargetLayout.for_class("cabinet"))


def test_dense_training_on_a_shard_of_another_class_is_one_line(split_copy, tmp_path):
    copy = split_copy("cabinet", "train")
    with h5py.File(copy / "shard-00000.h5", "a") as f:
        _two_joints(f)
    out = tmp_path / "d.pt"
    result = CliRunner().invoke(main, ["train", "--model", "dense", "--class", "cabinet", str(copy),
                                       "--out", str(out), "--epochs", "1", "--width", "4", "--val-fraction", "0", "-q"])
    assert_one_line_error(result, "does not belong", ignore=("no validation objects",))
    assert not out.exists()
