"""``artdata predict --object-mask``: the dense model sees only the object's pixels of a split made
with a scene (as a robot's segmentation leaves them); without it a scene split is warned about."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark.predictions import read_predictions
from articulated_dataset.cli import main


@pytest.fixture(scope="module")
def room_and_plain(tmp_path_factory):
    root = tmp_path_factory.mktemp("objmask")
    for name, extra in (("plain", []), ("room", ["--scene", "room"])):
        r = CliRunner().invoke(main, ["generate", "--class", "microwave", "--n", "1", "--split", "test", "--seed", "3",
                                      "--out", str(root / name), "-q", *extra])
        assert r.exit_code == 0, r.output
    return root


def _predict(root, name, tmp_path, *extra):
    out = tmp_path / f"{name}{len(extra)}.h5"
    r = CliRunner().invoke(main, ["predict", "--model", "dense", str(root / name / "microwave" / "test"),
                                  "--out", str(out), "--threads", "1", "-q", *extra])
    assert r.exit_code == 0, r.output
    return read_predictions(out)[1]["microwave"]


def test_object_mask_sees_exactly_the_isolated_object(room_and_plain, tmp_path, caplog):
    """In a room the object is the plain split's object (its own streams); with --object-mask the
    model sees what it sees without a room, so the predictions are the plain split's."""
    plain = _predict(room_and_plain, "plain", tmp_path)
    with caplog.at_level(logging.WARNING):
        raw = _predict(room_and_plain, "room", tmp_path)
    assert any("--object-mask" in rec.getMessage() for rec in caplog.records)
    masked = _predict(room_and_plain, "room", tmp_path, "--object-mask")
    assert np.allclose(masked["axis_pose"], plain["axis_pose"], atol=1e-5)
    assert np.allclose(masked["q"], plain["q"], atol=1e-5)
    assert not np.allclose(raw["axis_pose"][..., :3], plain["axis_pose"][..., :3], atol=0.05)  # the room misleads it


def test_object_mask_is_for_the_dense_model(room_and_plain, tmp_path):
    r = CliRunner().invoke(main, ["predict", "--model", "mdn-small", str(room_and_plain / "room" / "microwave" / "test"),
                                  "--out", str(tmp_path / "p.h5"), "--object-mask", "-q"])
    assert r.exit_code == 2 and r.output.strip() == "artdata: error: --object-mask applies to the dense model"
