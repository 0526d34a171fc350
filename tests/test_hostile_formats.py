"""Hostile files and arguments: JSON nested past the parser's recursion limit, label numbers
nested hundreds deep, YAML keys that are not text, names that are not UTF-8, a manifest listing a
shard twice, loaders given non-integer batch sizes and indices, ``ingest --append`` with another
training camera.  Each is one line (exit 2) or a clear exception, never a traceback or a silently
wrong result."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split
from helpers_real import write_capture

#: Nesting far past Python's recursion limit (the JSON parser recurses once per level).
DEEP = 100_000


def _run(args):
    r = CliRunner().invoke(main, [str(a) for a in args])
    return r.exit_code, r.output


def _one_line(code, text, needle=""):
    assert code == 2 and text.count("\n") == 1 and text.startswith("artdata: error:") and needle in text, (code, text)


@pytest.fixture
def split(tiny_root, tmp_path):
    """A writable copy of the tiny microwave test split."""
    dst = tmp_path / "data" / "microwave" / "test"
    shutil.copytree(tiny_root / "microwave" / "test", dst)
    return dst


def test_json_nested_past_the_recursion_limit(split):
    manifest = json.loads((split / "manifest.json").read_text())
    text = json.dumps({**manifest, "zz": []})
    (split / "manifest.json").write_text(text.replace('"zz": []', '"zz": ' + "[" * DEEP + "]" * DEEP))
    for command in ("info", "show"):
        _one_line(*_run([command, split, *(["--out", split.parent / "g.png"] if command == "show" else [])]))
    code, text = _run(["verify", split])
    assert code != 0 and "Traceback" not in text and "corrupt JSON" in text, text


def test_a_shard_attribute_nested_past_the_recursion_limit(split):
    shard = next(split.glob("shard-*.h5"))
    with h5py.File(shard, "r+") as f:
        f.attrs["joint_types"] = "[" * DEEP + "]" * DEEP
    code, text = _run(["info", split])  # the summary leaves the joints out (it was a RecursionError)
    assert code in (0, 2) and "Traceback" not in text and "RecursionError" not in text, text
    code, text = _run(["verify", split])
    assert code != 0 and "Traceback" not in text and "joint_types" in text, text


def test_a_manifest_listing_a_shard_twice_is_refused_by_the_readers(split):
    from articulated_dataset.training.loaders.reader import ShardReader

    manifest = json.loads((split / "manifest.json").read_text())
    manifest["shards"].append(dict(manifest["shards"][0]))
    (split / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(UserError, match="listed twice"):
        ShardReader(split)  # it served the shard's images twice
    _one_line(*_run(["info", split]), "listed twice")


def test_loaders_refuse_non_integer_batch_sizes_and_indices(split):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import DepthDataset, make_loader

    for bad in (0, 1.5, True):
        with pytest.raises(UserError, match="batch size"):
            make_loader(split, batch_size=bad)  # 0 gave one batch of every image
    ds = DepthDataset(split)
    for bad in ([0.4, 1.9], 1.5, "1"):
        with pytest.raises((TypeError, UserError)):
            ds[bad]  # [0.4, 1.9] read samples 0 and 1
    assert len(ds[[0, 1]]["depth"]) == 2


def _capture(tiny_root, folder, labels=None, camera=None):
    _, shards = open_split(tiny_root / "microwave" / "test")
    sh = shards[0]
    write_capture(folder, "frame", sh.sample(0), sh.K, labels)
    if camera is not None:
        (folder / "camera.json").write_text(camera)
    return folder


def test_ingest_refuses_deep_numbers_text_free_keys_and_non_utf8_names(tiny_root, tmp_path):
    deep = _capture(tiny_root, tmp_path / "deep", labels=None, camera='{"fx": ' + "[" * 600 + "100" + "]" * 600
                    + ', "fy": 100, "cx": 95.5, "cy": 53.5}')
    _one_line(*_run(["ingest", deep, "--class", "microwave", "--out", tmp_path / "o1", "-q"]), "nested")
    keys = _capture(tiny_root, tmp_path / "keys")
    (keys / "frame.labels.yaml").write_text("q: [0.1]\n1: 2\n")
    _one_line(*_run(["ingest", keys / "frame.png", "--labels", keys / "frame.labels.yaml", "--class", "microwave",
                     "--out", tmp_path / "o2", "-q"]), "keys must be names")
    good = _capture(tiny_root, tmp_path / "good")
    _one_line(*_run(["ingest", good, "--class", "microwave", "--out", tmp_path / "o3", "--split", "r\udcff", "-q"]),
              "invalid split name")
    if os.name == "posix":  # a file name that is not UTF-8 (bytes a Linux file system allows)
        bad = tmp_path / "badname"
        shutil.copytree(good, bad)
        for p in bad.glob("frame*"):
            os.rename(os.fsencode(p), os.fsencode(p).replace(b"frame", b"fr\xffme"))
        _one_line(*_run(["ingest", bad, "--class", "microwave", "--out", tmp_path / "o4", "-q"]), "UTF-8")
    assert not any((tmp_path / o).exists() for o in ("o1", "o2", "o3", "o4"))


def test_generate_refuses_a_split_name_that_is_not_utf8(tmp_path):
    _one_line(*_run(["generate", "--class", "microwave", "--n", "1", "--images", "4", "--split", "t\udcff",
                     "--out", tmp_path]), "invalid split name")


def test_ingest_append_refuses_another_training_camera(tiny_root, tmp_path):
    caps = _capture(tiny_root, tmp_path / "caps")
    assert _run(["ingest", caps, "--class", "microwave", "--out", tmp_path / "o", "-q"])[0] == 0
    manifest = tmp_path / "o" / "microwave" / "real" / "manifest.json"
    before = manifest.read_bytes()
    more = tmp_path / "more"
    shutil.copytree(caps, more)
    for p in more.glob("frame*"):
        p.rename(p.with_name(p.name.replace("frame", "other")))
    _one_line(*_run(["ingest", more, "--class", "microwave", "--out", tmp_path / "o", "--append", "--vfov", "70", "-q"]),
              "--like")
    assert manifest.read_bytes() == before  # its camera was rewritten to 70 deg
    assert _run(["ingest", more, "--class", "microwave", "--out", tmp_path / "o", "--append", "-q"])[0] == 0
    assert Path(manifest).read_bytes() != before


def test_import_exr_of_a_label_beyond_float32_is_one_line(split, tmp_path):
    """A label of 1e300 is refused in one line, without numpy's overflow warning before it."""
    import subprocess
    import sys

    assert _run(["export", split, tmp_path / "exp", "-q"])[0] == 0
    label = next((tmp_path / "exp").rglob("o000000_i000.json"))
    data = json.loads(label.read_text())
    data["q"] = [1e300] * len(data["q"])
    label.write_text(json.dumps(data))
    r = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", "import-exr", str(label.parent), "--out",
                        str(tmp_path / "back"), "-q"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and r.stderr.startswith("artdata: error:"), r.stderr


# ---- baselines, score, show, training options ----------------------------------------------------

def test_a_baseline_or_a_report_never_replaces_a_shard_of_its_inputs(tiny_root, split, tmp_path):
    train = tmp_path / "data" / "microwave" / "train"
    shutil.copytree(tiny_root / "microwave" / "train", train)
    shard = next(split.glob("shard-*.h5"))
    before = shard.read_bytes()
    _one_line(*_run(["baseline", "mean", "--train", train, "--test", split, "--out", shard, "--overwrite"]),
              "inside the input folder")
    preds = tmp_path / "mean.h5"
    assert _run(["baseline", "mean", "--train", train, "--test", split, "--out", preds])[0] == 0
    _one_line(*_run(["score", preds, "--truth", split, "--csv", shard]), "inside the input folder")
    assert shard.read_bytes() == before  # both replaced the truth's shard, exit 0
    if Path("/proc/version").exists():  # a report that cannot be written: neither is, not one of two
        _one_line(*_run(["score", preds, "--truth", split, "--json", tmp_path / "r.json", "--csv", "/proc/version"]))
        assert not (tmp_path / "r.json").exists()
    if hasattr(os, "mkfifo"):  # a FIFO (or a device, or a link to standard output) was replaced by a file
        fifo = tmp_path / "fifo"
        os.mkfifo(fifo)
        _one_line(*_run(["score", preds, "--truth", split, "--json", fifo]), "not a regular file")
        assert fifo.is_fifo()



@pytest.mark.parametrize("where", ["mean", ".mean-object"])
def test_icp_never_replaces_the_mean_object_it_finds(tiny_root, split, tmp_path, where):
    """Without --mean-object, ICP reads <train>/../mean or its cache <train>/../.mean-object/: an
    --out there is refused, since replacing the mean object's shard with the predictions would make
    every later ICP run of the class fail until the cache is deleted by hand."""
    train = tmp_path / "data" / "microwave" / "train"
    shutil.copytree(tiny_root / "microwave" / "train", train)
    args = ["baseline", "icp", "--train", train, "--test", split, "--limit", 1, "--workers", 1, "-q"]
    assert _run(args + ["--out", tmp_path / "first.h5"])[0] == 0  # renders the cache
    cache = train.parent / ".mean-object" / "microwave" / "mean"
    mean = cache if where == ".mean-object" else train.parent / "mean"
    if where == "mean":
        shutil.copytree(cache, mean)
    shard = next(mean.glob("shard-*.h5"))
    before = shard.read_bytes()
    _one_line(*_run(args + ["--out", shard, "--overwrite"]), "inside the input folder")
    assert shard.read_bytes() == before


def test_show_refuses_huge_ranges_and_non_ascii_digits(split, tmp_path):
    for option, value in (("--objects", "0-99999999999999999"), ("--images", "0-99999999"), ("--objects", "\u0661")):
        _one_line(*_run(["show", split, option, value, "--out", tmp_path / "g.png"]), option)


def test_training_refuses_absurd_epochs_and_a_resume_on_another_split(tiny_root, tmp_path):
    pytest.importorskip("torch")
    from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense

    for model in ("dense", "mdn"):
        _one_line(*_run(["train", "--model", model, "--class", "drawer", tiny_root / "drawer" / "train",
                         "--out", tmp_path / f"{model}.pt", "--epochs", str(10 ** 20)]), "--epochs")
    cfg = DenseTrainConfig("drawer", epochs=2, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    out = tmp_path / "d.pt"
    train_dense(tiny_root / "drawer" / "train", out, cfg, progress=False, stop_after_steps=1)
    with pytest.raises(UserError, match="was trained on another split"):  # it trained on the test split, silently
        train_dense(tiny_root / "drawer" / "test", out, cfg, progress=False, resume=True)
    moved = tmp_path / "moved" / "drawer" / "train"  # the same split in another folder resumes
    shutil.copytree(tiny_root / "drawer" / "train", moved)
    assert train_dense(moved, out, cfg, progress=False, resume=True, stop_after_steps=2)["step"] == 2


def test_a_mixture_of_no_column_is_refused(tiny_root, tmp_path):
    from articulated_dataset.benchmark.predictions import write_predictions

    _, shards = open_split(tiny_root / "microwave" / "test")
    ids = shards[0].read("sample_id").astype(np.int64)
    n = len(ids)
    arrays = {"sample_id": ids, "axis_pose": shards[0].read("axis_pose"),
              "q": shards[0].read("q"), "mixture_weights": np.ones((n, 1)), "mixture_means": np.zeros((n, 1, 0)),
              "mixture_scales": np.ones((n, 1, 0)), "mixture_layout": []}
    with pytest.raises(UserError, match="names no column"):  # it scored NLL 0.00 +/- 0.00
        write_predictions(tmp_path / "p.h5", "hostile", {"microwave": arrays})


def test_opd_success_is_undefined_where_the_truth_gives_no_axis():
    from articulated_dataset.benchmark.metrics import opd_success

    got = opd_success(np.array([1.0, np.nan, 1.0, 1.0]), np.array([1.0, 1.0, np.nan, 99.0]),
                      np.array([1.0, 1.0, 1.0, 1.0]), np.array([True, True, True, True]))
    assert got[0] == 1.0 and np.isnan(got[1]) and np.isnan(got[2]) and got[3] == 0.0  # it was 0: a failure
    prismatic = opd_success(np.array([1.0]), np.array([np.nan]), np.array([np.nan]), np.array([False]))
    assert prismatic[0] == 1.0  # a prismatic origin is not checked


@pytest.mark.parametrize("edit", ["bytes", "n_images", "width_px"])
def test_info_on_counts_beyond_a_float_is_one_line(split, edit):
    """info divided a byte count of 10**400 by the image count: OverflowError (a traceback)."""
    m = json.loads((split / "manifest.json").read_text())
    target = {"bytes": m["shards"][0], "n_images": m, "width_px": m["config"]["camera"]}[edit]
    target[edit] = 10**400
    (split / "manifest.json").write_text(json.dumps(m))
    result = CliRunner().invoke(main, ["info", str(split)])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("artdata: error: "), result.output


@pytest.mark.parametrize("value", ["no", 0, None, [False]])
def test_a_manifest_complete_flag_that_is_not_a_boolean_is_refused(split, value):
    """'complete': "no" read as complete (bool("no") is true) in info and every reader."""
    m = json.loads((split / "manifest.json").read_text())
    m["complete"] = value
    (split / "manifest.json").write_text(json.dumps(m))
    result = CliRunner().invoke(main, ["info", str(split)])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and "field 'complete'" in lines[0], result.output
