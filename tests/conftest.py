"""Shared fixtures: small real datasets rendered once per pytest run, and the folders tests build on them."""

from __future__ import annotations

import shutil

import pytest

from articulated_dataset.classes.registry import class_names
from articulated_dataset.generation import GenerationConfig, generate_split

#: Objects per class in the shared tiny dataset (train) and its test split.
TINY_TRAIN_OBJECTS = 6
TINY_TEST_OBJECTS = 3


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory):
    """``root/<class>/{train,test}`` for every registered class (6 + 3 objects x 16 images).

    Read-only for tests: copy it if you need to modify files.
    """
    root = tmp_path_factory.mktemp("tiny")
    for name in class_names():
        generate_split(GenerationConfig(name, split="train", n_objects=TINY_TRAIN_OBJECTS, objects_per_shard=4), root)
        generate_split(GenerationConfig(name, split="test", n_objects=TINY_TEST_OBJECTS, objects_per_shard=4), root)
    return root


@pytest.fixture
def split_copy(tiny_root, tmp_path):
    """``split_copy(class_name="microwave", split="test")``: a writable copy of a tiny split at
    ``tmp_path/data/<class>/<split>``; its path."""
    def copy(class_name: str = "microwave", split: str = "test"):
        dst = tmp_path / "data" / class_name / split
        shutil.copytree(tiny_root / class_name / split, dst)
        return dst
    return copy


@pytest.fixture(scope="session")
def two_shard_split(tmp_path_factory):
    """A drawer train split of 2 objects x 2 images, one object per shard (so shard-00001.h5 is
    the second object), its EXR export and the Mean baseline's predictions of it:
    ``{"split", "export", "predictions"}``.  Small enough to copy into every case of a table.
    Read-only for tests."""
    from click.testing import CliRunner

    from articulated_dataset.cli import main
    from articulated_dataset.tools.exr import export_split

    root = tmp_path_factory.mktemp("two-shards")
    split = generate_split(GenerationConfig("drawer", n_objects=2, images_per_object=2, objects_per_shard=1), root / "gen")
    export = export_split(split, root / "exp" / "drawer" / "train")
    predictions = root / "mean.h5"
    result = CliRunner().invoke(main, ["baseline", "mean", "--train", str(split), "--test", str(split), "--out",
                                       str(predictions), "-q"])
    assert result.exit_code == 0, result.output
    return {"split": split, "export": export, "predictions": predictions}


@pytest.fixture
def guarded(tmp_path):
    """``tmp_path`` as a :class:`helpers_core.GuardedFolder`: canary files in ``victim/`` beside
    the case's inputs, and the check that a refused command changed nothing."""
    from helpers_core import GuardedFolder

    return GuardedFolder(tmp_path)
