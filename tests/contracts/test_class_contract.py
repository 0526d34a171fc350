"""The class contract: what every registered object class gives, whatever its geometry.

Each test runs over :func:`articulated_dataset.classes.registry.class_names`, so a class added to
the registry is held to all of them without a line here: its generated labels explain its pixels
(each moving part's pixels, moved back by -q about the labelled axis, lie in the closed object's
box), the same seed gives the same arrays, its splits verify, a tiny model trains on its split and
its predictions of the test split are scored, the dense model trains on it, and the shipped dense
model predicts its test split.  The shared tiny dataset (``tiny_root``) is the data throughout.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from articulated_dataset.classes.registry import class_names, get_class
from articulated_dataset.format import open_split
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.tools.verify import verify_split
from helpers_core import IMAGE_CHECK_FIELDS, check_stored_images, run_cli

#: Pixels of the body the tiny training split must show (a class whose body is never seen cannot
#: be checked against its box).
MIN_BODY_PX = 1000
#: Share of the parts opened at least 30% whose unmoved pixels leave the closed box: the negative
#: control that makes the label check able to fail.  Below 1: a drawer opened by a third of its
#: travel may keep most of its visible pixels within the box's allowance for the handle in front.
MIN_DETECTED = 0.8
#: Every array a split stores per image, compared between two runs of one seed.
COMPARED_FIELDS = (*IMAGE_CHECK_FIELDS, "part_offset", "visible_pixels", "sample_id")
#: The smallest trainings the model tests run (a second or less each on a CPU): one epoch of one object.
TINY_DENSE = ["--model", "dense", "--epochs", "1", "--batch-size", "16", "--width", "4", "--val-fraction", "0",
              "--max-objects", "1"]
TINY_MDN = ["--model", "mdn", "--small", "--epochs", "1", "--batch-size", "16", "--components", "3",
            "--val-fraction", "0", "--max-objects", "1"]
#: Figures of the score report every class has (both joint types).
FIGURES = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error")


@pytest.mark.parametrize("class_name", class_names())
def test_labels_explain_the_stored_pixels(tiny_root, class_name):
    """Every image of the tiny training split: body pixels in the object's box, part pixels in the
    closed box once moved back by their labelled motion, and (the control) open parts' pixels not
    moved back outside it."""
    obj_class = get_class(class_name)
    _, shards = open_split(tiny_root / class_name / "train")
    counts = np.zeros(3, int)
    for sh in shards:
        counts += check_stored_images(obj_class, {k: sh.read(k) for k in IMAGE_CHECK_FIELDS}, np.asarray(sh.K))
        sh.close()
    checked, detected, n_body = counts
    assert checked > 0 and detected >= MIN_DETECTED * checked, (checked, detected)
    assert n_body > MIN_BODY_PX


@pytest.mark.parametrize("class_name", class_names())
def test_the_same_seed_gives_the_same_arrays(tiny_root, tmp_path, class_name):
    """Object 0 of the test split generated again, alone (one object, its own shard layout), holds
    the arrays the shared tiny split holds for it, byte for byte."""
    again = generate_split(GenerationConfig(class_name, split="test", n_objects=1), tmp_path)
    _, shards = open_split(tiny_root / class_name / "test")
    _, (alone,) = open_split(again)
    rows = shards[0].read("object_index") == 0
    assert rows.sum() == len(alone.read("object_index")) > 0
    for field in COMPARED_FIELDS:
        np.testing.assert_array_equal(alone.read(field), shards[0].read(field)[rows], err_msg=field)
    for sh in (*shards, alone):
        sh.close()


@pytest.mark.parametrize("class_name", class_names())
@pytest.mark.parametrize("split", ["train", "test"])
def test_generated_splits_verify(tiny_root, class_name, split):
    report = verify_split(tiny_root / class_name / split)
    assert report.ok, report.problems


def _predict_and_score(model, test, tmp_path, class_name) -> None:
    """``artdata predict`` of the test split with ``model`` and ``artdata score`` of it: every test
    image predicted and scored, every figure finite."""
    preds, report = tmp_path / "p.h5", tmp_path / "score.json"
    result = run_cli("predict", "--model", model, test, "--out", preds, "-q")
    assert result.exit_code == 0, result.output
    result = run_cli("score", preds, "--truth", test, "--json", report)
    assert result.exit_code == 0, result.output
    (row,) = json.loads(report.read_text())["rows"]
    assert row["class"] == class_name and row["complete"] and row["n_scored"] == row["n_truth"] > 0
    for name in FIGURES:
        assert np.isfinite(row["metrics"][name]["mean"]), (name, row["metrics"][name])


@pytest.mark.parametrize("class_name", class_names())
def test_a_tiny_model_trains_predicts_and_is_scored(tiny_root, tmp_path, class_name):
    """``artdata train`` of a tiny MDN on the class's tiny split, then its predictions of the test
    split scored."""
    model = tmp_path / "m.pt"
    result = run_cli("train", "--class", class_name, tiny_root / class_name / "train", "--out", model, "-q", *TINY_MDN)
    assert result.exit_code == 0, result.output
    _predict_and_score(model, tiny_root / class_name / "test", tmp_path, class_name)


@pytest.mark.parametrize("class_name", class_names())
def test_the_dense_model_trains_predicts_and_is_scored(tiny_root, tmp_path, class_name):
    """A dense network trained for a few steps predicts the test split (sizes it estimates below
    zero are written as 0, as a predictions file holds them) and is scored."""
    from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint

    model = tmp_path / "d.pt"
    result = run_cli("train", "--class", class_name, tiny_root / class_name / "train", "--out", model, "-q", *TINY_DENSE)
    assert result.exit_code == 0, result.output
    ckpt = load_dense_checkpoint(model)
    assert ckpt["class_name"] == class_name and ckpt["finished"]
    _predict_and_score(model, tiny_root / class_name / "test", tmp_path, class_name)


@pytest.mark.parametrize("class_name", class_names())
def test_the_shipped_dense_model_predicts_and_is_scored(tiny_root, tmp_path, class_name):
    _predict_and_score("dense", tiny_root / class_name / "test", tmp_path, class_name)
