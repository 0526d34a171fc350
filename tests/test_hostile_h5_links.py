"""Hostile HDF5 link layouts: hard-link aliases.

A few hundred hard links to one group at each of three levels make a 100 KB file whose
recursive layout check visited every path (300^3 = 2.7e7, about an hour; 1000 per level: days):
``artdata score`` and every shard reader hung in ``check_h5_layout``.  Files written by artdata
link every object once, so an object reached by a second link is refused when the file is opened.
"""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.generation import GenerationConfig, generate_split

#: Links per level: small enough that the unfixed walk ends (40^3 paths, a few seconds).
FAN_OUT = 40


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    root = tmp_path_factory.mktemp("links")
    return generate_split(GenerationConfig("drawer", split="test", n_objects=1, images_per_object=2), root)


def _fan_out(f: h5py.Group, leaf: h5py.Group) -> None:
    """``leaf`` gets FAN_OUT links to one of its datasets; two groups above it FAN_OUT links each."""
    ds = leaf[next(iter(leaf))]
    for i in range(FAN_OUT):
        leaf[f"alias{i}"] = ds
    mid = f.create_group("zmid")
    for i in range(FAN_OUT):
        mid[f"leaf{i}"] = leaf
    top = f.create_group("ztop")
    for i in range(FAN_OUT):
        top[f"mid{i}"] = mid


def _one_line(args) -> str:
    result = CliRunner().invoke(main, [str(a) for a in args])
    err = result.stderr.strip()
    assert result.exit_code == 2 and len(err.splitlines()) == 1 and err.startswith("artdata: error:"), \
        (result.exit_code, err, result.exception)
    return err


def test_a_predictions_file_of_hard_link_aliases_is_refused(split, tmp_path):
    preds = tmp_path / "p.h5"
    with h5py.File(preds, "w") as f:
        f.attrs.update(format_version="1.0", method="hostile")
        g = f.create_group("drawer")
        g["sample_id"] = np.arange(2, dtype=np.int64)
        _fan_out(f, g)
    err = _one_line(["score", preds, "--truth", split])
    assert "second link" in err


def test_a_shard_of_hard_link_aliases_is_refused(split, tmp_path):
    copy = tmp_path / "drawer" / "test"
    shutil.copytree(split, copy)
    shard = copy / json.loads((copy / "manifest.json").read_text())["shards"][0]["file"]
    with h5py.File(shard, "a") as f:
        leaf = f.create_group("zleaf")
        leaf["x"] = np.zeros(1)
        _fan_out(f, leaf)
    err = _one_line(["info", copy])
    assert "second link" in err


@pytest.mark.parametrize("args", [["info", "{split}"], ["baseline", "mean", "--train", "{split}", "--test", "{split}",
                                                         "--out", "{tmp}/p.h5", "-q"],
                                  ["plan", "{split}", "--index", "0", "-q"]], ids=["info", "baseline", "plan"])
def test_a_shard_that_is_a_fifo_is_refused_not_waited_on(split, tmp_path, args):
    """A named pipe in place of a shard: opening it blocked until a writer appeared (every shard
    reader hung); it is refused like a predictions file that is not a regular file."""
    import os
    import subprocess
    import sys

    copy = tmp_path / "drawer" / "test"
    shutil.copytree(split, copy)
    shard = copy / json.loads((copy / "manifest.json").read_text())["shards"][0]["file"]
    shard.unlink()
    os.mkfifo(shard)
    argv = [a.format(split=copy, tmp=tmp_path) for a in args]
    r = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *argv], capture_output=True, text=True,
                       timeout=60, stdin=subprocess.DEVNULL)
    lines = r.stderr.splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("artdata: error: "), r.stderr
    assert "not a regular file" in lines[0], lines[0]
