"""Data from strangers, read by the loaders, the scorer, ``info``, ``show``, ``plan``, ``train``
and ``predict``: colour images of the wrong shape or type, indices past int64, names holding
control characters, CSV cells a spreadsheet would evaluate, predicted values no object has, a
third-party URDF path recorded in a manifest, splits without one valid depth pixel; and a Ray
address where nothing listens.  Each ends in one ``artdata: error:`` line (or escaped output),
never in a traceback, a hang or a file opened outside the folder the user named."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark.predictions import read_predictions, write_predictions
from articulated_dataset.cli import main
from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.core.pool import RAY_CONNECT_TIMEOUT_S
from articulated_dataset.format import MANIFEST_NAME
from articulated_dataset.generation import GenerationConfig, generate_split, urdf_import
from articulated_dataset.training.loaders import ShardReader
from helpers_core import assert_one_line_error, flap_split_outside, split_copy_with

#: Bytes that would move a terminal's cursor and clear its screen, and a line break.
TERMINAL_CONTROL = "\x1b[2J\x1b[H"


@pytest.fixture(scope="module")
def rgb_split(tmp_path_factory) -> Path:
    """A --rgb drawer test split: one object, two images (colour images stored)."""
    config = GenerationConfig("drawer", split="test", n_objects=1, images_per_object=2, rgb=True)
    return generate_split(config, tmp_path_factory.mktemp("rgb"))


@pytest.fixture(scope="module")
def drawer_train(tmp_path_factory) -> Path:
    """A drawer training split: two objects of two images."""
    config = GenerationConfig("drawer", split="train", n_objects=2, images_per_object=2)
    return generate_split(config, tmp_path_factory.mktemp("train"))


def _with_rgb(src: Path, dst: Path, rgb) -> Path:
    """A copy of split ``src`` whose shards' ``rgb`` dataset is replaced by ``rgb(old)`` (None: removed)."""
    shutil.copytree(src, dst)
    for shard in dst.glob("shard-*.h5"):
        with h5py.File(shard, "r+") as f:
            old = f["rgb"][()]
            del f["rgb"]
            if rgb is not None:
                f.create_dataset("rgb", data=rgb(old))
    return dst


def _edit_manifest(split: Path, edit) -> None:
    path = split / MANIFEST_NAME
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


# --------------------------------------------------------------------------------------
# Colour images: (H, W, 3) uint8 or refused
# --------------------------------------------------------------------------------------

RGB_DAMAGE = {
    "four-channels": lambda a: np.concatenate([a, a[..., :1]], -1),
    "float32": lambda a: a.astype(np.float32),
    "missing": None,
}


@pytest.mark.parametrize("damage", list(RGB_DAMAGE))
def test_colour_images_of_another_shape_or_type_are_one_line(rgb_split, tmp_path, damage):
    split = _with_rgb(rgb_split, tmp_path / "bad", RGB_DAMAGE[damage])
    shard = str(next(split.glob("shard-*.h5")))
    result = CliRunner().invoke(main, ["show", str(split), "--rgb", "--out", str(tmp_path / "g.png"), "-q"])
    assert_one_line_error(result, shard)
    with pytest.raises(DataFormatError, match="'rgb'") as info:
        ShardReader(split)[0]
    assert shard in str(info.value)


# --------------------------------------------------------------------------------------
# Sample indices past int64
# --------------------------------------------------------------------------------------

def test_an_unsigned_index_past_int64_does_not_wrap_to_the_last_sample(rgb_split):
    from articulated_dataset.training.loaders.torch import DepthDataset

    huge = np.array([np.iinfo(np.uint64).max], np.uint64)  # as int64: -1, the last sample
    with pytest.raises(IndexError, match="out of range"):
        ShardReader(rgb_split).get_batch(huge)
    with pytest.raises(IndexError, match="out of range"):
        DepthDataset(rgb_split, fields=["depth"])[huge]


# --------------------------------------------------------------------------------------
# Names from data never reach the terminal raw; CSV cells are never formulas
# --------------------------------------------------------------------------------------

@pytest.fixture()
def control_named_split(rgb_split, tmp_path) -> Path:
    """A copy of the split in a folder, and under a split name, holding terminal control characters."""
    name = f"te{TERMINAL_CONTROL}st\nFAKE LINE"
    split = tmp_path / "root" / "drawer" / name
    shutil.copytree(rgb_split, split)

    def rename(m):
        m["split"] = name
        m["config"]["split"] = name

    _edit_manifest(split, rename)
    return split


@pytest.mark.parametrize("command", ["info", "verify"])
def test_info_and_verify_escape_control_characters_in_names(control_named_split, command):
    result = CliRunner().invoke(main, [command, str(control_named_split.parent.parent)])
    assert "\x1b" not in result.output and "\nFAKE LINE" not in result.output, result.output
    assert "\\x1b[2J" in result.output


def _perfect_predictions(split: Path, path: Path, method: str) -> None:
    with h5py.File(next(split.glob("shard-*.h5"))) as f:
        arrays = {k: f[k][()] for k in ("sample_id", "axis_pose", "q", "geometry")}
    write_predictions(path, method, {"drawer": arrays})


#: Method names a spreadsheet would evaluate: (name, CSV cell).  A plain number stays a number.
FORMULA_CELLS = [('=HYPERLINK("http://x.invalid","y")', '\'=HYPERLINK("http://x.invalid","y")'),
                 ("+1+cmd|' /C calc'!A0", "'+1+cmd|' /C calc'!A0"), ("@SUM(A1:A9)", "'@SUM(A1:A9)"),
                 ("-2+3", "'-2+3"), ("-2.5", "-2.5")]


def test_score_csv_cells_are_never_formulas(rgb_split, tmp_path):
    paths = []
    for k, (method, _) in enumerate(FORMULA_CELLS):
        paths.append(tmp_path / f"p{k}.h5")
        _perfect_predictions(rgb_split, paths[-1], method)
    result = CliRunner().invoke(main, ["score", *map(str, paths), "--truth", str(rgb_split.parent.parent),
                                       "--csv", "-"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert [r["method"] for r in rows] == [cell for _, cell in FORMULA_CELLS]
    assert all(float(r["axis_position_error_cm_mean"]) == 0.0 for r in rows)


def test_the_score_table_escapes_control_characters(control_named_split, tmp_path):
    _perfect_predictions(control_named_split, tmp_path / "p.h5", "m")
    result = CliRunner().invoke(main, ["score", str(tmp_path / "p.h5"), "--truth", str(control_named_split.parent.parent),
                                       "--split", control_named_split.name])
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.output and "\nFAKE LINE" not in result.output, result.output


# --------------------------------------------------------------------------------------
# Predicted values no object has
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("column, value, needle", [(3, 2.0, "chirality"), (3, -0.5, "chirality"),
                                                   (0, -0.3, "depth below 0"), (2, -1e-3, "height below 0")])
def test_predicted_geometry_outside_its_range_is_refused(rgb_split, tmp_path, column, value, needle):
    good = tmp_path / "good.h5"
    _perfect_predictions(rgb_split, good, "m")
    bad = tmp_path / "bad.h5"
    shutil.copy(good, bad)
    with h5py.File(bad, "r+") as f:
        g = f["drawer/geometry"][()]
        g[0, column] = value
        f["drawer/geometry"][...] = g
    with pytest.raises(DataFormatError, match=needle):
        read_predictions(bad)
    result = CliRunner().invoke(main, ["score", str(bad), "--truth", str(rgb_split.parent.parent)])
    assert_one_line_error(result, needle)
    _, per_class = read_predictions(good)
    per_class["drawer"]["geometry"][0, column] = value
    with pytest.raises(UserError, match=needle):
        write_predictions(tmp_path / "w.h5", "m", per_class)


# --------------------------------------------------------------------------------------
# A third-party URDF recorded in a manifest is opened only inside the folder given
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def flap_split(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("flap")
    mp = pytest.MonkeyPatch()
    mp.setenv(urdf_import.CACHE_ENV, str(root / "cache"))
    urdf, split = flap_split_outside(root, "train")
    yield {"split": split, "urdf": urdf}
    mp.undo()


def _rebuild(how: str, split: Path, tmp_path: Path):
    if how == "show-rgb":
        return CliRunner().invoke(main, ["show", str(split), "--rgb", "--n", "1", "--out", str(tmp_path / "g.png"), "-q"])
    return CliRunner().invoke(main, ["plan", str(split), "--index", "0", "-q"])


@pytest.mark.parametrize("how", ["show-rgb", "plan"])
def test_a_recorded_urdf_outside_the_split_is_never_opened(flap_split, tmp_path, how, monkeypatch):
    from articulated_dataset.generation.urdf_import import parse

    def never(*args, **kwargs):
        raise AssertionError("the manifest's URDF was opened")

    monkeypatch.setattr(parse, "load_structure", never)
    monkeypatch.setattr(urdf_import.build, "load_structure", never)
    assert_one_line_error(_rebuild(how, flap_split["split"], tmp_path), "outside the split folder")
    fifo = tmp_path / "fifo.urdf"  # opening it would wait for a writer
    os.mkfifo(fifo)
    split = shutil.copytree(flap_split["split"], tmp_path / "copy")
    _edit_manifest(split, lambda m: m["config"]["third_party"].update(urdf=str(fifo)))
    assert_one_line_error(_rebuild(how, split, tmp_path), "outside the split folder")


def test_a_recorded_urdf_inside_the_split_still_rebuilds(flap_split, tmp_path):
    split = shutil.copytree(flap_split["split"], tmp_path / "copy")
    inside = shutil.copy(flap_split["urdf"], split / "flap.urdf")  # the same bytes: the same sha256
    _edit_manifest(split, lambda m: m["config"]["third_party"].update(urdf=str(Path(inside).resolve())))
    result = _rebuild("show-rgb", split, tmp_path)
    assert result.exit_code == 0, result.output


# --------------------------------------------------------------------------------------
# Splits without one valid depth pixel: nothing to train on or predict from
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("value", [np.nan, 0.0])
@pytest.mark.parametrize("command", ["train-mdn", "train-dense", "predict-dense", "predict-mdn"])
def test_a_split_without_valid_depth_is_one_line(drawer_train, tmp_path, command, value):
    split = split_copy_with(drawer_train, tmp_path / "empty", "depth", value)
    out = tmp_path / "out.pt"
    if command.startswith("train"):
        kind = command.split("-")[1]
        extra = ["--small", "--components", "3"] if kind == "mdn" else ["--width", "4"]
        args = ["train", "--model", kind, "--class", "drawer", str(split), "--out", str(out),
                "--epochs", "1", "--batch-size", "4", "-q", *extra]
    else:
        model = "dense" if command.endswith("dense") else "mdn-small"
        args = ["predict", "--model", model, str(split), "--out", str(tmp_path / "p.h5"), "-q"]
    result = CliRunner().invoke(main, args)
    assert_one_line_error(result, "valid depth pixel")
    assert not out.exists() and not (tmp_path / "p.h5").exists()


# --------------------------------------------------------------------------------------
# A Ray address where nothing listens: one line within seconds, not endless retries
# --------------------------------------------------------------------------------------

def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_ray_address_where_nothing_listens_is_one_line(tmp_path):
    pytest.importorskip("ray")
    port = _free_loopback_port()
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", "generate", "--class", "drawer", "--n", "1",
                           "--images", "1", "--executor", "ray", "--address", f"127.0.0.1:{port}", "--out",
                           str(tmp_path), "-q"], capture_output=True, text=True, timeout=RAY_CONNECT_TIMEOUT_S + 50)
    assert_one_line_error(proc, "cannot connect to the Ray cluster", f"127.0.0.1:{port}")
    assert time.monotonic() - t0 < RAY_CONNECT_TIMEOUT_S + 50


@pytest.mark.parametrize("answer", [b"", b"SSH-2.0-OpenSSH_9.2\r\n"], ids=["silent", "not-http2"])
def test_a_ray_address_where_something_else_listens_is_one_line(answer):
    """A listener that is not a gRPC server (Ray's head node is one) is refused after at most
    the connect timeout; ray.init waited on it without end."""
    import socket
    import threading

    from articulated_dataset.core.errors import UserError
    from articulated_dataset.core.pool import check_reachable

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    accepted = []

    def serve():
        conn, _ = server.accept()
        accepted.append(conn)
        if answer:
            conn.sendall(answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(UserError, match="not as a Ray cluster"):
            check_reachable(f"127.0.0.1:{port}", timeout_s=2.0)
    finally:
        server.close()
        for conn in accepted:
            conn.close()
    assert time.monotonic() - t0 < 10.0
