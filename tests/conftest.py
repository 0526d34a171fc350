"""Shared fixtures: small real datasets rendered once per pytest run."""

from __future__ import annotations

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
