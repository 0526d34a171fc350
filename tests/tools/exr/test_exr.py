"""EXR interchange: export then import reproduces every array (and the shard files) exactly;
broken folders give one-line errors naming the file."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import OpenEXR
import pytest
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.core.images.exr import DEPTH_CHANNEL, INDEX_NAME, read_depth_exr, sample_stem, write_depth_exr
from articulated_dataset.format import FIELDS, LABEL_FIELDS, open_split
from helpers_core import PROGRESS_FRAME, assert_one_line_error


def run(*args):
    result = CliRunner().invoke(main, [*map(str, args)])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert "Traceback" not in result.output
    return result


@pytest.fixture(scope="module")
def exported(tiny_root, tmp_path_factory):
    """tiny cabinet2 (train + test, J = 2) and drawer/test (prismatic) exported to EXR."""
    out = tmp_path_factory.mktemp("exr")
    assert run("export", tiny_root / "cabinet2", out, "--format", "exr", "-q").exit_code == 0
    assert run("export", tiny_root / "drawer" / "test", out, "-q").exit_code == 0
    return out


SPLITS = [("cabinet2", "train"), ("cabinet2", "test"), ("drawer", "test")]


def test_round_trip_is_exact(tiny_root, exported, tmp_path):
    result = run("import-exr", exported, "--out", tmp_path / "back")
    assert result.exit_code == 0, result.output
    assert "imported 192 images into 3 split(s)" in result.output  # (6 + 3 + 3) objects x 16
    for cls, split in SPLITS:
        m0, shards0 = open_split(tiny_root / cls / split)
        m1, shards1 = open_split(tmp_path / "back" / cls / split)
        assert len(shards0) == len(shards1)
        for a, b in zip(shards0, shards1):
            for f in FIELDS:
                x, y = a.read(f.name), b.read(f.name)
                assert x.dtype == y.dtype and x.shape == y.shape
                assert x.tobytes() == y.tobytes(), (cls, split, f.name)  # bit-exact, NaN-safe
            np.testing.assert_array_equal(a.K, b.K)
            assert a.attrs == b.attrs
        # the writer, attribute order and manifest are the generator's: identical files
        assert [r["sha256"] for r in m0["shards"]] == [r["sha256"] for r in m1["shards"]]
        assert (tiny_root / cls / split / "manifest.json").read_bytes() == \
            (tmp_path / "back" / cls / split / "manifest.json").read_bytes()
    assert run("verify", tmp_path / "back", "--workers", "1", "-q").exit_code == 0


def test_exported_files_are_standard(tiny_root, exported):
    folder = exported / "drawer" / "test"
    _, shards = open_split(tiny_root / "drawer" / "test")
    sample = shards[0].sample(21)
    stem = sample_stem(sample["object_index"], sample["image_index"])
    assert stem == "o000001_i005"
    with OpenEXR.File(str(folder / f"{stem}.exr")) as f:
        header, channels = f.header(), f.channels()
        assert list(channels) == [DEPTH_CHANNEL]
        assert channels[DEPTH_CHANNEL].type() == OpenEXR.FLOAT
        assert header["compression"] == OpenEXR.ZIP_COMPRESSION
        np.testing.assert_array_equal(channels[DEPTH_CHANNEL].pixels, sample["depth"])
    with Image.open(folder / f"{stem}.mask.png") as im:
        assert im.mode == "L"
        np.testing.assert_array_equal(np.asarray(im), sample["mask"])
    labels = json.loads((folder / f"{stem}.json").read_text())
    assert set(LABEL_FIELDS) <= set(labels) and labels["class"] == "drawer"
    np.testing.assert_array_equal(np.float32(labels["q"]), sample["q"])
    np.testing.assert_array_equal(labels["K"], shards[0].K)
    index = json.loads((folder / INDEX_NAME).read_text())
    assert index["manifest"]["class_name"] == "drawer" and index["shards"][0]["samples"][21] == stem
    shards[0].close()


def test_exr_float32_round_trip_extremes(tmp_path):
    d = np.array([[0.0, 2.0**-13, 1.0 / 3.0, 11.999], [np.float32(1e-30), 3.4e38, 7.0, 0.5]], np.float32)
    write_depth_exr(tmp_path / "x.exr", d)
    assert read_depth_exr(tmp_path / "x.exr").tobytes() == d.tobytes()


def test_existing_output_is_refused(tiny_root, exported, tmp_path):
    result = run("export", tiny_root / "drawer" / "test", exported)
    assert result.exit_code == 2 and "not empty; pass --overwrite" in result.output
    assert run("export", tiny_root / "drawer" / "test", exported, "--overwrite", "-q").exit_code == 0
    (tmp_path / "back" / "drawer" / "test").mkdir(parents=True)
    (tmp_path / "back" / "drawer" / "test" / "keep.txt").write_text("x")
    result = run("import-exr", exported / "drawer" / "test", "--out", tmp_path / "back")
    assert result.exit_code == 2 and "not empty" in result.output


def _broken(exported, tmp_path, damage):
    folder = tmp_path / "drawer" / "test"
    shutil.copytree(exported / "drawer" / "test", folder)
    damage(folder)
    return run("import-exr", tmp_path, "--out", tmp_path / "out")


def _exr_other_channel(folder):
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"R": np.zeros((108, 192), np.float32)}) as f:
        f.write(str(folder / "o000002_i003.exr"))


def _label_wrong_shape(folder):
    p = folder / "o000000_i004.json"
    lab = json.loads(p.read_text())
    lab["axis_direction"] = [0.0, 0.0, 1.0]  # should be (J, 3) = (1, 3)
    p.write_text(json.dumps(lab))


@pytest.mark.parametrize("damage, needle", [
    (lambda f: (f / "o000001_i007.exr").unlink(), "o000001_i007.exr: missing depth image"),
    (lambda f: (f / "o000001_i007.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\0" * 40), "o000001_i007.exr: not a readable OpenEXR file"),
    (lambda f: (f / "o000000_i000.exr").write_bytes((f / "o000000_i000.exr").read_bytes()[:300]), "o000000_i000.exr: not a readable OpenEXR file"),
    (_exr_other_channel, "o000002_i003.exr: no 'Z' channel"),
    (lambda f: Image.new("L", (10, 10)).save(f / "o000002_i015.mask.png"), "o000002_i015.mask.png: mask is 10x10 px, expected 192x108"),
    (lambda f: Image.new("RGB", (192, 108)).save(f / "o000002_i015.mask.png"), "mask must be an 8-bit greyscale PNG"),
    (lambda f: (f / "o000000_i004.json").write_text("{"), "o000000_i004.json: corrupt label file"),
    (_label_wrong_shape, "o000000_i004.json: label 'axis_direction' has shape (3,), expected (1, 3)"),
    (lambda f: (f / INDEX_NAME).write_text('{"format": "something-else"}'), "not an articulated_dataset EXR export"),
    (lambda f: (f / INDEX_NAME).unlink(), "no exported split found"),
], ids=["missing-exr", "garbage-exr", "truncated-exr", "channel", "mask-size", "mask-mode", "json", "label-shape",
        "index-format", "no-index"])
def test_broken_folder_is_a_one_line_error(exported, tmp_path, damage, needle):
    assert_one_line_error(_broken(exported, tmp_path, damage), needle, ignore=(PROGRESS_FRAME,))
    assert not (tmp_path / "out" / "drawer" / "test" / "manifest.json").exists()  # nothing half-written


def test_bad_paths(tmp_path):
    assert run("export", tmp_path / "nothing", tmp_path / "o").exit_code == 2
    assert run("import-exr", tmp_path / "nothing", "--out", tmp_path / "o").exit_code == 2
    assert run("export", tmp_path, tmp_path / "o", "--format", "tiff").exit_code == 2


def test_hdf5_attrs_identical_after_import(tiny_root, exported, tmp_path):
    run("import-exr", exported / "drawer" / "test", "--out", tmp_path, "-q")
    with h5py.File(tiny_root / "drawer" / "test" / "shard-00000.h5") as a, h5py.File(tmp_path / "drawer" / "test" / "shard-00000.h5") as b:
        assert dict(a.attrs) .keys() == dict(b.attrs).keys()
        for k in a.attrs:
            assert type(a.attrs[k]) is type(b.attrs[k]) and np.all(a.attrs[k] == b.attrs[k]), k
