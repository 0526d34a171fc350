"""Checkpoints, splits and output paths from strangers, given to the dense model's commands (train,
predict, estimate, show): each ends in one line, exit 2 (or a UserError), never a traceback or a
replaced input."""

from __future__ import annotations

import json
import os
import shutil

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from articulated_dataset.cli import EXIT_USER_ERROR, main
from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint
from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file
from articulated_dataset.methods.shipped import WEIGHTS_DIR
from helpers_core import assert_one_line_error

# --- Dense checkpoints holding numbers no float holds (a Python int such as 10**400 pickles fine):
# every one is a one-line error when the file is read, not an OverflowError from inside the checks,
# the refinement or the predictions file's attributes.
SHIPPED = WEIGHTS_DIR / "dense-microwave.safetensors"
HUGE = 10**400


def _huge_calibration(**kw):
    return lambda c: {**c, "calibration": {**c["calibration"], **kw}}


def _outlier(**kw):
    return lambda c: {**c, "calibration": {**c["calibration"], "outlier": {**c["calibration"]["outlier"], **kw}}}


def _refinement(**kw):
    return lambda c: {**c, "refinement": {**c["refinement"], **kw}}


HUGE_CASES = {
    "q_scale": (lambda c: {**c, "q_scale": [HUGE]}, "'q_scale'"),
    "spread factors": (_huge_calibration(spread_factor=[HUGE] * 17), "'calibration' is malformed"),
    "floors": (_huge_calibration(floor=[HUGE] * 17), "'calibration' is malformed"),
    "outlier weight": (_outlier(weight=HUGE), "'calibration' is malformed"),
    "outlier scales": (_outlier(scale=[HUGE] * 17), "'calibration' is malformed"),
    "refinement gate": (_refinement(max_turn_deg=HUGE), "'refinement' is malformed"),
    "refinement offset": (_refinement(hinge_offset_m=HUGE), "'refinement' is malformed"),
    "refinement face offsets": (_refinement(door_face_offsets_m=[HUGE, 0.0]), "'refinement' is malformed"),
    "refinement pixel count": (_refinement(min_door_px=HUGE), "'refinement' is malformed"),  # OverflowError in refine.door_angle
    "step": (lambda c: {**c, "step": HUGE}, "'step'"),  # TypeError writing predictions.h5's attribute
}


@pytest.fixture()
def crafted(tmp_path):
    def make(change) -> str:
        path = tmp_path / "bad.pt"
        torch.save(change(dict(read_checkpoint_file(SHIPPED))), path)
        return str(path)
    return make


@pytest.mark.parametrize("name", list(HUGE_CASES))
def test_a_number_no_float_holds_is_one_line(crafted, tmp_path, monkeypatch, name):
    change, needle = HUGE_CASES[name]
    path = crafted(change)
    with pytest.raises(UserError, match=needle):
        load_dense_checkpoint(path)
    monkeypatch.chdir(tmp_path)
    depth = np.zeros((108, 192))
    depth[30:80, 60:130] = 1.5  # a box seen face-on: an image estimate() takes
    np.save("d.npy", depth)
    (tmp_path / "camera.json").write_text('{"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5}')
    assert_one_line_error(CliRunner().invoke(main, ["estimate", "d.npy", "--class", "microwave", "--model", path]), needle)


# --- A checkpoint whose weights are meta tensors (shapes without values; torch.save writes them and
# weights_only loading reads them back) is a one-line error, not torch's RuntimeError from the
# finiteness check (``Tensor.item() cannot be called on meta tensors``).
def test_meta_weights_are_one_line(tmp_path, tiny_root):
    ckpt = dict(read_checkpoint_file(SHIPPED))
    state = dict(ckpt["model_state"])
    state["head.bias"] = torch.zeros(state["head.bias"].shape, device="meta")
    path = tmp_path / "meta.pt"
    torch.save({**ckpt, "model_state": state}, path)
    with pytest.raises(UserError, match="meta tensors"):
        load_dense_checkpoint(path)
    result = CliRunner().invoke(main, ["predict", "--model", str(path), str(tiny_root / "microwave" / "test"),
                                       "--out", str(tmp_path / "p.h5"), "-q"])
    assert_one_line_error(result, "meta tensors")
    assert not (tmp_path / "p.h5").exists()


# --- A dense checkpoint whose weights are finite but overflow float32 in the network (a stem weight
# of 1e38 passes the load-time check for NaN/inf weights) is a one-line error in predict (in the
# command's process and in its workers) and estimate, not torch's LinAlgError from the
# refinement's eigendecomposition of NaN votes.
@pytest.fixture()
def overflowing(tmp_path) -> str:
    ckpt = dict(read_checkpoint_file(SHIPPED))
    state = dict(ckpt["model_state"])
    state["stem.0.weight"] = state["stem.0.weight"].float() * 1e38
    path = tmp_path / "overflow.pt"
    torch.save({**ckpt, "model_state": state}, path)
    return str(path)


@pytest.mark.parametrize("workers", ["1", "2"])
def test_predict_with_overflowing_weights_is_one_line(overflowing, tiny_root, tmp_path, workers):
    result = CliRunner().invoke(main, ["predict", "--model", overflowing, str(tiny_root / "microwave" / "test"),
                                       "--out", str(tmp_path / "p.h5"), "--workers", workers, "--threads", "2", "-q"])
    assert_one_line_error(result, "NaN or infinite outputs")
    assert not (tmp_path / "p.h5").exists()


def test_estimate_with_overflowing_weights_is_one_line(overflowing, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    depth = np.zeros((108, 192))
    depth[30:80, 60:130] = 1.5
    np.save("d.npy", depth)
    (tmp_path / "camera.json").write_text('{"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5}')
    assert_one_line_error(CliRunner().invoke(main, ["estimate", "d.npy", "--class", "microwave", "--model", overflowing]),
              "NaN or infinite outputs")



def test_estimate_with_weights_that_compute_nonsense_is_one_line(tmp_path, monkeypatch):
    """Batch normalisation variances of 0 pass the checkpoint's checks and give finite outputs, but
    axis origins of 1e33 m: estimate checks its arrays as a predictions file is checked (it does
    not print them, with NaN uncertainties that are not JSON)."""
    ckpt = dict(read_checkpoint_file(SHIPPED))
    state = {k: torch.zeros_like(v) if k.endswith("running_var") else v for k, v in ckpt["model_state"].items()}
    torch.save({**ckpt, "model_state": state}, tmp_path / "bn0.pt")
    monkeypatch.chdir(tmp_path)
    depth = np.zeros((108, 192))
    depth[30:80, 60:130] = 1.5
    np.save("d.npy", depth)
    (tmp_path / "camera.json").write_text('{"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5}')
    assert_one_line_error(CliRunner().invoke(main, ["estimate", "d.npy", "--class", "microwave", "--model", "bn0.pt", "--json"]),
              "the model's estimate is not usable")

# --- A dense checkpoint's calibration with finite but absurd numbers (a spread factor, floor or
# outlier scale of 1e300) is refused when the file is read: estimate must not print
# RuntimeWarnings and an uncertainty of "Infinity" with exit 0, nor predict refuse its own
# predictions file in three lines after predicting the whole split.
def _absurd_calibration(**kw):
    return lambda c: {**c, "calibration": {**c["calibration"], **kw}}


ABSURD_CASES = {
    "spread factors 1e300": _absurd_calibration(spread_factor=[1e300] * 17),
    "floors 1e300": _absurd_calibration(floor=[1e300] * 17),
    "outlier scales 1e300": lambda c: {**c, "calibration": {**c["calibration"], "outlier": {
        **c["calibration"]["outlier"], "scale": [1e300] * 17}}},
}


@pytest.mark.parametrize("name", list(ABSURD_CASES))
@pytest.mark.parametrize("command", ["estimate", "predict"])
def test_an_absurd_calibration_is_one_line(tmp_path, tiny_root, monkeypatch, name, command):
    monkeypatch.chdir(tmp_path)
    ckpt = dict(read_checkpoint_file(SHIPPED))
    torch.save(ABSURD_CASES[name](ckpt), "bad.pt")
    if command == "estimate":
        depth = np.zeros((108, 192))
        depth[30:80, 60:130] = 1.5
        np.save("d.npy", depth)
        (tmp_path / "camera.json").write_text('{"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5}')
        args = ["estimate", "d.npy", "--class", "microwave", "--model", "bad.pt", "--json"]
    else:
        args = ["predict", "--model", "bad.pt", str(tiny_root / "microwave" / "test"), "--out", "p.h5", "-q"]
    assert_one_line_error(CliRunner().invoke(main, args), "'calibration' is malformed")
    assert not (tmp_path / "p.h5").exists()


# --- A split whose manifest records its generation settings in a form predict does not expect
# (occluders as text or a list, the whole config a list) is predicted; the record is only read to
# warn about scenes and occluders (no ValueError, TypeError or AttributeError traceback from
# ``int(config.get("occluders"))``).
@pytest.mark.parametrize("change", [lambda m: m["config"].update(occluders="abc"),
                                    lambda m: m["config"].update(occluders=[1]),
                                    lambda m: m.update(config=[1])], ids=["occluders text", "occluders list",
                                                                          "config list"])
def test_odd_generation_records_do_not_stop_predict(split_copy, tmp_path, monkeypatch, change):
    monkeypatch.chdir(tmp_path)
    split = split_copy()
    manifest = json.loads((split / "manifest.json").read_text())
    change(manifest)
    (split / "manifest.json").write_text(json.dumps(manifest))
    result = CliRunner().invoke(main, ["predict", "--model", "dense", str(split), "--out", "p.h5", "-q"])
    if result.exit_code == EXIT_USER_ERROR:  # a reader that refuses the manifest must do so in one line
        assert_one_line_error(result)
    else:
        assert result.exit_code == 0, (result.output, result.exception)
        assert (tmp_path / "p.h5").is_file()


# --- predict's --out where no file can be written (under a file, in /proc): one line before the
# split is predicted, not an h5py OSError or a FileExistsError traceback after it.
@pytest.mark.parametrize("out", ["f/p.h5", "f/sub/p.h5", "/proc/artdata-p.h5"])
def test_an_unwritable_out_is_one_line(tiny_root, tmp_path, monkeypatch, out):
    if out.startswith("/proc") and not os.path.isdir("/proc"):
        pytest.skip("needs /proc (Linux)")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "f").write_text("a file, not a folder")
    result = CliRunner().invoke(main, ["predict", "--model", "dense", str(tiny_root / "microwave" / "test"),
                                       "--out", out, "-q"])
    assert assert_one_line_error(result).startswith("artdata: error: cannot write")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


# --- show never writes its gallery over the predictions file it draws (an --out of the same name
# replaced predictions.h5 with a PNG and exited 0).
def test_show_refuses_to_write_over_its_predictions(tiny_root, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    split = str(tiny_root / "microwave" / "test")
    assert CliRunner().invoke(main, ["predict", "--model", "dense", split, "--out", "p.h5", "-q"]).exit_code == 0
    shutil.copy("p.h5", "p.png")  # a predictions file of any name
    kept = (tmp_path / "p.png").read_bytes()
    result = CliRunner().invoke(main, ["show", split, "--predictions", "p.png", "--out", "p.png", "--n", "2", "-q"])
    assert_one_line_error(result, "also an input")
    assert (tmp_path / "p.png").read_bytes() == kept


# --- Shards whose depth dataset is not (images, height, width), whose camera matrices are missing
# or not 3x3 finite floats, or whose n_joints attribute is not a whole number: one line from every
# reader (predict, show, info), not a ValueError from unpacking the depth's shape, an int() of the
# attribute, or a KeyError/IndexError where K is first used.
def _replace(name, value):
    def edit(f):
        del f[name]
        if value is not None:
            f[name] = value
    return edit


def _attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


EDITS = {
    "depth 2-D": (_replace("depth", np.zeros((108, 192), np.float32)), "'depth'"),
    "depth 4-D": (_replace("depth", np.zeros((32, 108, 192, 2), np.float32)), "'depth'"),
    "depth scalar": (_replace("depth", np.float32(1)), "'depth'"),
    "K missing": (_replace("K", None), "'K'"),
    "K 9 numbers": (_replace("K", np.zeros(9)), "'K'"),
    "K 4x4": (_replace("K", np.eye(4)), "'K'"),
    "K text": (_replace("K", np.full((3, 3), b"a")), "'K'"),
    "K NaN": (_replace("K", np.full((3, 3), np.nan)), "'K'"),
    "R missing": (_replace("R_camera_to_optical", None), "'R_camera_to_optical'"),
    "n_joints text": (_attr("n_joints", "abc"), "'n_joints'"),
    "n_joints NaN": (_attr("n_joints", np.nan), "'n_joints'"),
    "n_joints array": (_attr("n_joints", np.arange(3)), "'n_joints'"),
}


@pytest.mark.parametrize("name", list(EDITS))
@pytest.mark.parametrize("command", ["predict", "show", "info"])
def test_a_malformed_shard_camera_or_shape_is_one_line(split_copy, tmp_path, monkeypatch, name, command):
    monkeypatch.chdir(tmp_path)
    split = split_copy()
    edit, needle = EDITS[name]
    for shard in sorted(split.glob("shard-*.h5")):
        with h5py.File(shard, "r+") as f:
            edit(f)
    args = {"predict": ["predict", "--model", "dense", str(split), "--out", "p.h5", "-q"],
            "show": ["show", str(split), "--out", "g.png", "-q"],
            "info": ["info", str(split)]}[command]
    assert_one_line_error(CliRunner().invoke(main, args), needle)
    assert not (tmp_path / "p.h5").exists() and not (tmp_path / "g.png").exists()


# --- Training options no run can use and a resume on another split: one line (an --epochs of 10**20
# overflowed inside the schedule) and a UserError (a resume on the test split trained on it silently).
def test_training_refuses_absurd_epochs_and_a_resume_on_another_split(tiny_root, tmp_path):
    from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense

    for model in ("dense", "mdn"):
        assert_one_line_error(CliRunner().invoke(main, ["train", "--model", model, "--class", "drawer",
                                                        str(tiny_root / "drawer" / "train"), "--out",
                                                        str(tmp_path / f"{model}.pt"), "--epochs", str(10 ** 20)]),
                              "--epochs")
    cfg = DenseTrainConfig("drawer", epochs=2, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    out = tmp_path / "d.pt"
    train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False, stop_after_steps=1)
    with pytest.raises(UserError, match="was trained on another split"):
        train_dense(tiny_root / "drawer" / "test", out, cfg, progress=False, resume=True)
    moved = tmp_path / "moved" / "drawer" / "train"  # the same split in another folder resumes
    shutil.copytree(tiny_root / "drawer" / "train", moved)
    assert train_dense(moved, out, cfg, progress=False, resume=True, stop_after_steps=2)["step"] == 2
