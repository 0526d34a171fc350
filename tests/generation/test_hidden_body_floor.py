"""benchmarks/hidden_body_floor.py: the posterior on a hand-worked case, the turned object against
rendered pixels and labels, and the script as a user runs it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.format import Split
from articulated_dataset.generation import GenerationConfig
from articulated_dataset.generation.labels import read_object_labels
from articulated_dataset.generation.render import process_renderer
from articulated_dataset.generation.viewpoint import object_in_camera
from helpers_core import ROOT, generated_split, load_script

#: Seed 7's three cabinets show four images without a body pixel (and many with thousands).
SEED = 7


@pytest.fixture(scope="module")
def bench():
    return load_script(ROOT / "benchmarks" / "hidden_body_floor.py", "hidden_body_floor")


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return generated_split(tmp_path_factory.mktemp("hb"), "cabinet", 3, seed=SEED)


def _images(split):
    with Split(split) as s:
        config = GenerationConfig.from_dict(s.manifest["config"])
        keys = ("object_index", "object_pose", "object_yaw", "axis_pose", "q", "visible_pixels", "mask", "depth")
        arrays = {k: np.concatenate([sh.read(k) for sh in s.shards]) for k in keys}
    return config, arrays


def _turned(bench, config, a, i):
    return bench.TurnedObject(config, int(a["object_index"][i]), a["object_pose"][i],
                              float(np.ravel(a["object_yaw"][i])[0]), a["axis_pose"][i, 0, :3].astype(np.float64),
                              process_renderer(config.camera))


def test_the_posterior_on_a_hand_worked_case(bench):
    # q uniform on 10, 20, 30 deg: the median 20, its mean absolute deviation (10 + 0 + 10) / 3
    expected, realised = bench.posterior_error(np.radians([10.0, 20.0, 30.0]), math.radians(10.0))
    assert math.degrees(expected) == pytest.approx(20.0 / 3.0)
    assert math.degrees(realised) == pytest.approx(10.0)
    expected, realised = bench.posterior_error(np.radians([42.0]), math.radians(42.0))
    assert expected == 0.0 and realised == 0.0


def test_the_turned_object_keeps_the_hinge_and_the_door(bench, split):
    """Turning the rebuilt object about its hinge by d and closing the door by d leaves the labelled
    hinge line and the door's direction where the stored labels put them; unturned, it renders the
    stored mask and depth."""
    config, a = _images(split)
    i = 0
    obj = _turned(bench, config, a, i)
    q = float(a["q"][i, 0])
    depth, mask, _ = obj.render(0.0, q)
    assert np.array_equal(mask, a["mask"][i])
    assert np.abs(depth - a["depth"][i]).max() <= config.depth_quantum_m  # the stored depth is rounded
    R = quat_to_matrix(a["axis_pose"][i, 0, 3:].astype(np.float64))
    up = float(np.sign(R[2, 2]))
    door = R @ np.array([math.cos(q), math.sin(q), 0.0])
    for d in (-0.3, 0.2):
        pose = obj.turned_pose(d)
        obj.placer.place(object_in_camera(pose))
        labels = read_object_labels(obj.model, obj.data, obj.info, config.obj_class)
        assert labels["axis_pose"][0, :3] == pytest.approx(a["axis_pose"][i, 0, :3], abs=1e-5)
        Rt = quat_to_matrix(np.asarray(labels["axis_pose"][0, 3:], dtype=np.float64))
        qt = q - up * d
        assert Rt @ np.array([math.cos(qt), math.sin(qt), 0.0]) == pytest.approx(door, abs=1e-5)
        assert pose["yaw_rad"] == pytest.approx(float(np.ravel(a["object_yaw"][i])[0]) + d)


def test_hidden_and_visible_bodies(bench, split):
    """Where the door hides the body the image leaves a range of q that holds the truth; where the
    body shows thousands of pixels, only the truth is kept."""
    config, a = _images(split)
    body = a["visible_pixels"][:, 0]
    step = math.radians(1.0)
    for i, many in ((int(np.nonzero(body == 0)[0][0]), True), (int(np.argmax(body)), False)):
        obj = _turned(bench, config, a, i)
        q = float(a["q"][i, 0])
        up = float(np.sign(quat_to_matrix(a["axis_pose"][i, 0, 3:].astype(np.float64))[2, 2]))
        kept = bench.image_floor(obj, q, up, config.table, step, a["mask"][i])
        assert np.isclose(kept, q).any()
        if many:
            assert len(kept) > 3 and kept.max() - kept.min() > math.radians(3.0)
            # every kept turn renders without a body pixel
            d = (q - kept[0]) / up
            _, mask, _ = obj.render(d, kept[0])
            assert not (mask == 1).any()
        else:
            assert len(kept) == 1


def test_the_script_as_a_user_runs_it(bench, split, tmp_path, capsys):
    out = tmp_path / "p.h5"
    r = CliRunner().invoke(main, ["predict", "--model", "dense", str(split), "--out", str(out), "--no-mirror",
                                  "--threads", "1", "-q"])
    assert r.exit_code == 0, r.output
    assert bench.main(["--truth", str(split), "--predictions", str(out), "--max-body-px", "0", "--step-deg", "2",
                       "--quiet"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("cabinet: 48 images, 4 searched (at most 0 body pixels)")
    assert "floor of the mean configuration error" in text and "the model's: configuration" in text
    floor = float(text.split("rotation error (deg): ")[1].split()[0])
    assert 0.0 < floor < 45.0
    # a class with two doors, or a bad step: one line, exit 2
    other = generated_split(tmp_path / "c2", "cabinet2", 1, seed=6)
    for argv in (["--truth", str(other)], ["--truth", str(split), "--step-deg", "0"]):
        assert bench.main(argv + ["--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("hidden_body_floor: error: ") and "\n" not in err
