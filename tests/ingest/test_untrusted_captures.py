"""Captures from strangers: ``artdata ingest`` of label files, camera files and depth arrays that no
reader should trust ends in one line ``artdata: error: ...`` (exit 2) and writes nothing.

Values whose arithmetic overflows give the error line alone, without numpy's RuntimeWarning (two
more stderr lines) before it: an axis direction or quaternion of 1e300 components in a label
file, a ``.npy`` header declaring a shape whose size overflows.  Numbers nested hundreds deep,
YAML keys that are not text and names that are not UTF-8 are refused; ``--append`` never rewrites
the split's training camera.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from articulated_dataset.format import open_split
from helpers_core import assert_one_line_error, run_cli
from helpers_real import write_capture

CAMERA = {"fx": 100.0, "fy": 100.0, "cx": 95.5, "cy": 53.5, "width": 192, "height": 108}


def _capture(folder, labels=None, npy_header=None):
    folder.mkdir()
    depth = np.zeros((108, 192), np.uint16)
    depth[40:70, 80:120] = 1500
    if npy_header is None:
        Image.fromarray(depth).save(folder / "frame.png")
    else:
        import numpy.lib.format as F

        with open(folder / "frame.npy", "wb") as fh:
            F.write_array_header_1_0(fh, npy_header)
    (folder / "camera.json").write_text(json.dumps(CAMERA))
    if labels is not None:
        (folder / "frame.labels.json").write_text(json.dumps(labels))
    return folder


def _tiny_capture(tiny_root, folder, labels=None, camera=None):
    """A capture of the tiny microwave test split's first image (``frame``); ``camera``: the
    camera file's text instead of the split's intrinsics."""
    _, shards = open_split(tiny_root / "microwave" / "test")
    sh = shards[0]
    write_capture(folder, "frame", sh.sample(0), sh.K, labels)
    if camera is not None:
        (folder / "camera.json").write_text(camera)
    return folder


def _ingest_quietly(*args):
    """``artdata ingest ARGS`` in one line: no RuntimeWarning recorded, as a shell would print it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_cli("ingest", *args)
    printed = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not printed, printed
    return assert_one_line_error(result)


@pytest.mark.parametrize("labels", [{"axis_direction": [[1e300, 1e300, 0]]},
                                    {"axis_pose": [[1.5, 0, 0, 1e200, 1e200, 0, 0]]},
                                    {"object_pose": [1.5, 0, 0, 1e300, 1e300, 0, 0]}],
                         ids=["direction", "axis quaternion", "object quaternion"])
def test_a_label_vector_whose_length_overflows_is_one_line(tmp_path, labels):
    folder = _capture(tmp_path / "cap", labels=labels)
    err = _ingest_quietly(folder, "--class", "cabinet", "--out", tmp_path / "out", "-q")
    assert "frame.labels.json" in err
    assert not (tmp_path / "out").exists()


def test_an_npy_header_whose_size_overflows_is_one_line(tmp_path):
    folder = _capture(tmp_path / "cap", npy_header={"descr": "<f8", "fortran_order": False, "shape": (2**62, 2**62)})
    err = _ingest_quietly(folder, "--class", "cabinet", "--out", tmp_path / "out", "-q")
    assert "frame.npy" in err


def test_ingest_refuses_deep_numbers_text_free_keys_and_non_utf8_names(tiny_root, tmp_path):
    deep = _tiny_capture(tiny_root, tmp_path / "deep", labels=None, camera='{"fx": ' + "[" * 600 + "100" + "]" * 600
                         + ', "fy": 100, "cx": 95.5, "cy": 53.5}')
    assert_one_line_error(run_cli("ingest", deep, "--class", "microwave", "--out", tmp_path / "o1", "-q"), "nested")
    keys = _tiny_capture(tiny_root, tmp_path / "keys")
    (keys / "frame.labels.yaml").write_text("q: [0.1]\n1: 2\n")
    assert_one_line_error(run_cli("ingest", keys / "frame.png", "--labels", keys / "frame.labels.yaml", "--class",
                                  "microwave", "--out", tmp_path / "o2", "-q"), "keys must be names")
    good = _tiny_capture(tiny_root, tmp_path / "good")
    assert_one_line_error(run_cli("ingest", good, "--class", "microwave", "--out", tmp_path / "o3", "--split", "r\udcff",
                                  "-q"), "invalid split name")
    if os.name == "posix":  # a file name that is not UTF-8 (bytes a Linux file system allows)
        bad = tmp_path / "badname"
        shutil.copytree(good, bad)
        for p in bad.glob("frame*"):
            os.rename(os.fsencode(p), os.fsencode(p).replace(b"frame", b"fr\xffme"))
        assert_one_line_error(run_cli("ingest", bad, "--class", "microwave", "--out", tmp_path / "o4", "-q"), "UTF-8")
    assert not any((tmp_path / o).exists() for o in ("o1", "o2", "o3", "o4"))


def test_ingest_append_refuses_another_training_camera(tiny_root, tmp_path):
    caps = _tiny_capture(tiny_root, tmp_path / "caps")
    assert run_cli("ingest", caps, "--class", "microwave", "--out", tmp_path / "o", "-q").exit_code == 0
    manifest = tmp_path / "o" / "microwave" / "real" / "manifest.json"
    before = manifest.read_bytes()
    more = tmp_path / "more"
    shutil.copytree(caps, more)
    for p in more.glob("frame*"):
        p.rename(p.with_name(p.name.replace("frame", "other")))
    assert_one_line_error(run_cli("ingest", more, "--class", "microwave", "--out", tmp_path / "o", "--append",
                                  "--vfov", "70", "-q"), "--like")
    assert manifest.read_bytes() == before  # its camera is not rewritten to 70 deg
    assert run_cli("ingest", more, "--class", "microwave", "--out", tmp_path / "o", "--append", "-q").exit_code == 0
    assert Path(manifest).read_bytes() != before
