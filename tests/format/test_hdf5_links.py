"""HDF5 files from strangers: hard-link aliases, and a FIFO where a shard should be.

A few hundred hard links to one group at each of three levels make a 100 KB file whose
recursive layout check visited every path (300^3 = 2.7e7, about an hour; 1000 per level: days):
``artdata score`` and every shard reader hung in ``check_h5_layout``.  Files written by artdata
link every object once, so an object reached by a second link is refused when the file is opened.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from helpers_core import assert_one_line_error

#: Links per level: small enough that the unfixed walk ends (40^3 paths, a few seconds).
FAN_OUT = 40


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


def _one_line(*args) -> str:
    return assert_one_line_error(CliRunner().invoke(main, [str(a) for a in args]))


def test_a_predictions_file_of_hard_link_aliases_is_refused(tiny_root, tmp_path):
    preds = tmp_path / "p.h5"
    with h5py.File(preds, "w") as f:
        f.attrs.update(format_version="1.0", method="crafted")
        g = f.create_group("drawer")
        g["sample_id"] = np.arange(2, dtype=np.int64)
        _fan_out(f, g)
    err = _one_line("score", preds, "--truth", tiny_root / "drawer" / "test")
    assert "second link" in err


def test_a_shard_of_hard_link_aliases_is_refused(split_copy):
    copy = split_copy("drawer", "test")
    shard = copy / json.loads((copy / "manifest.json").read_text())["shards"][0]["file"]
    with h5py.File(shard, "a") as f:
        leaf = f.create_group("zleaf")
        leaf["x"] = np.zeros(1)
        _fan_out(f, leaf)
    err = _one_line("info", copy)
    assert "second link" in err


@pytest.mark.parametrize("args", [["info", "{split}"], ["baseline", "mean", "--train", "{split}", "--test", "{split}",
                                                         "--out", "{tmp}/p.h5", "-q"],
                                  ["plan", "{split}", "--index", "0", "-q"]], ids=["info", "baseline", "plan"])
def test_a_shard_that_is_a_fifo_is_refused_not_waited_on(split_copy, tmp_path, args):
    """A named pipe in place of a shard: opening it blocked until a writer appeared (every shard
    reader hung); it is refused like a predictions file that is not a regular file."""
    import os
    import subprocess
    import sys

    copy = split_copy("drawer", "test")
    shard = copy / json.loads((copy / "manifest.json").read_text())["shards"][0]["file"]
    shard.unlink()
    os.mkfifo(shard)
    argv = [a.format(split=copy, tmp=tmp_path) for a in args]
    r = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *argv], capture_output=True, text=True,
                       timeout=60, stdin=subprocess.DEVNULL)
    assert_one_line_error(r, "not a regular file")
