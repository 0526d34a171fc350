"""The data-format layer (``articulated_dataset.format``): importing it pulls in no simulator,
renderer or deep-learning framework, and its one split reader returns what the shard files
hold, as every consumer's reader does."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format import (
    IMAGE_FIELDS,
    LABEL_FIELDS,
    MANIFEST_NAME,
    Split,
    SplitConfig,
    find_splits,
    one_split_dir,
    splits_by_class,
)

HEAVY = ("mujoco", "OpenGL", "torch", "jax")
LABELS = tuple(k for k in LABEL_FIELDS if k not in IMAGE_FIELDS)


def heavy_modules_after_import(*modules: str) -> list[str]:
    """Which of :data:`HEAVY` a fresh interpreter holds after importing ``modules``."""
    code = ("import sys\n" + "".join(f"import {m}\n" for m in modules)
            + f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return [m for m in out.stdout.strip().split(",") if m]


@pytest.mark.parametrize("module", ["articulated_dataset.format", "articulated_dataset.benchmark",
                                    "articulated_dataset.benchmark.pointlik", "articulated_dataset.training.loaders",
                                    "articulated_dataset.methods.baselines.common", "articulated_dataset.format.summary",
                                    "articulated_dataset.cli.info",
                                    "articulated_dataset.tools.verify", "articulated_dataset.ingest.capture",
                                    "articulated_dataset.ingest.write", "articulated_dataset.tools.viz"])
def test_reading_imports_no_simulator_renderer_or_framework(module):
    assert heavy_modules_after_import(module) == []


def test_the_import_check_sees_mujoco():
    """The check above can fail: the generator's label reader does import MuJoCo."""
    assert "mujoco" in heavy_modules_after_import("articulated_dataset.generation.labels")


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    """``OUT/microwave/test`` written by the CLI: 2 objects x 16 images in 2 shards."""
    out = tmp_path_factory.mktemp("format") / "out"
    subprocess.run(["artdata", "generate", "--class", "microwave", "--n", "2", "--split", "test", "--seed", "0",
                    "--objects-per-shard", "1", "--out", str(out), "-q"], check=True, capture_output=True)
    return out / "microwave" / "test"


def raw_labels(split_dir: Path) -> dict:
    """Every label field as h5py reads it from the shards the manifest lists (storage order)."""
    manifest = json.loads((split_dir / MANIFEST_NAME).read_text())
    parts: dict = {k: [] for k in LABELS}
    for rec in manifest["shards"]:
        with h5py.File(split_dir / rec["file"], "r") as f:
            for k in LABELS:
                parts[k].append(f[k][()])
    return {k: np.concatenate(v) for k, v in parts.items()}


def assert_same(a: dict, b: dict, keys) -> None:
    for k in keys:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


def test_split_reads_the_shards_labels(generated):
    ref = raw_labels(generated)
    with Split(generated) as split:
        assert len(split.shards) == 2 and split.shard_sizes == [16, 16] and split.n_images == 32
        assert split.class_name == "microwave" and split.name == "test" and split.complete and not split.is_real
        assert split.joint_types() == ("revolute",) and split.joint_names() == ["door_hinge"] and split.n_joints == 1
        assert split.image_size == (108, 192)
        assert_same(split.labels(), ref, LABELS)
        assert_same({"q": split.read("q")}, ref, ["q"])


def test_every_consumer_reads_the_same_labels(generated):
    from articulated_dataset.benchmark.truth import load_truth_set
    from articulated_dataset.format import open_split
    from articulated_dataset.format.summary import summarize_split
    from articulated_dataset.manipulation import read_split_labels
    from articulated_dataset.methods.baselines.common import open_split_checked
    from articulated_dataset.training.loaders import ShardReader

    ref = raw_labels(generated)
    _, shards = open_split(generated)
    assert_same({k: np.concatenate([sh.read(k) for sh in shards]) for k in LABELS}, ref, LABELS)

    info = open_split_checked(generated, "test")
    assert_same({k: info.read(k) for k in LABELS}, ref, LABELS)
    info.close()

    _, _, labels = read_split_labels(generated)
    assert list(labels["class"]) == [c.decode() for c in ref["class"]]
    assert_same(labels, ref, [k for k in LABELS if k != "class"])

    reader = ShardReader(generated, fields=list(LABELS))
    assert_same(reader.get_batch(np.arange(len(reader))), ref, LABELS)

    truth = load_truth_set(generated)
    order = np.argsort(ref["sample_id"], kind="stable")
    assert np.array_equal(truth.arrays["sample_id"], ref["sample_id"][order])
    assert np.allclose(truth.arrays["q"], ref["q"][order]) and np.allclose(truth.arrays["geometry"], ref["geometry"][order])

    summary = summarize_split(generated)
    assert summary["images"] == 32 and summary["class"] == "microwave"
    assert summary["labels"]["q"]["max"] == [round(float(ref["q"].max()), 4)]


def test_split_config_is_the_generators_config(generated):
    from articulated_dataset.generation import GenerationConfig

    split = Split(generated)
    config = split.config
    assert type(config) is SplitConfig
    generator = GenerationConfig.from_dict(split.manifest["config"])
    assert generator.as_split_config() == config and generator.to_dict() == config.to_dict() == split.manifest["config"]
    assert (config.n_shards, config.shard_objects(1)) == (2, range(1, 2))


def test_split_refuses_what_the_old_readers_refused(generated, tmp_path):
    split_dir = tmp_path / "microwave" / "test"
    shutil.copytree(generated, split_dir)
    manifest = json.loads((split_dir / MANIFEST_NAME).read_text())
    bad = dict(manifest, config={**manifest["config"], "n_objects": 0})
    (split_dir / MANIFEST_NAME).write_text(json.dumps(bad))
    with pytest.raises(DataFormatError, match="invalid generation config .*number of objects must be positive"):
        Split(split_dir).config  # noqa: B018 - the property reads and checks
    bad = dict(manifest, shards=[dict(manifest["shards"][0], file="../x.h5")])
    (split_dir / MANIFEST_NAME).write_text(json.dumps(bad))
    with pytest.raises(DataFormatError, match="invalid shard file name"):
        Split(split_dir)
    (split_dir / MANIFEST_NAME).write_text(json.dumps(dict(manifest, format_version="9.0")))
    with pytest.raises(DataFormatError, match="format version 9.0 is not readable"):
        Split(split_dir)


def test_discovery(generated, tmp_path):
    out = generated.parent.parent
    assert find_splits([out, generated, out / "microwave"]) == [generated]
    assert splits_by_class(out) == {"microwave": {"test": generated}}
    assert one_split_dir(out) == generated
    shutil.copytree(generated, tmp_path / "microwave" / "test")
    shutil.copytree(generated, tmp_path / "microwave" / "train")
    with pytest.raises(UserError, match="holds 2 splits; pass one split folder"):
        one_split_dir(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no generated split found"):
        find_splits(tmp_path / "empty")


def test_json_list_reads_a_list_and_nothing_else():
    """format.shards.json_list: the one parser of a shard attribute's JSON list; text that is not
    JSON (malformed, not UTF-8, not text, nested past the parser's recursion limit) or another JSON
    value is None, never an exception."""
    from articulated_dataset.format.shards import json_list

    assert json_list('["revolute", "prismatic"]') == ["revolute", "prismatic"]
    assert json_list(b'["door"]') == ["door"] and json_list("[]") == []
    for bad in ('{"a": 1}', '"revolute"', "1", "null", "[1,", b"\xff\xfe", None, 3, "[" * 100_000):
        assert json_list(bad) is None, repr(bad)[:40]
