"""Inputs from strangers to articulated_dataset.estimate and artdata estimate: a UserError or one line, exit 2."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

import articulated_dataset as ad
from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from helpers_core import assert_one_line_error, png_header

# --- articulated_dataset.estimate raises UserError, never another exception, for inputs a caller can
# get wrong: a class name that is a list (TypeError: unhashable), a ragged or text mask (ValueError,
# or every pixel read as object), a NaN mask; and one depth pixel of 1e300 m (an estimate of
# infinite axis origin, returned without error) is refused as the file readers refuse it.
K = np.array([[105.3, 0.0, 95.5], [0.0, 105.3, 53.5], [0.0, 0.0, 1.0]])


def _object_depth() -> np.ndarray:
    depth = np.zeros((108, 192))
    depth[30:80, 60:130] = 1.5
    return depth


def _far_pixel() -> np.ndarray:
    depth = _object_depth()
    depth[50, 100] = 1e300
    return depth


API_CASES = {
    "class a list": (dict(class_name=["microwave"]), "unknown object class"),
    "class a dict": (dict(class_name={"microwave": 1}), "unknown object class"),
    "mask ragged": (dict(mask=[[1, 0], [1]]), "mask"),
    "mask text": (dict(mask=np.full((108, 192), "a")), "mask"),
    "mask objects": (dict(mask=np.full((108, 192), None)), "mask"),
    "mask NaN": (dict(mask=np.full((108, 192), np.nan)), "mask"),
    "one pixel at 1e300 m": (dict(depth_m=_far_pixel()), "not plausible"),
}


@pytest.mark.parametrize("name", list(API_CASES))
def test_estimate_raises_user_error(name):
    kwargs, needle = API_CASES[name]
    args = {"depth_m": _object_depth(), "K": K, "class_name": "microwave", **kwargs}
    with pytest.raises(UserError, match=needle):
        ad.estimate(**args)


def test_boolean_and_numeric_masks_still_work():
    depth = _object_depth()
    for mask in (depth > 0, (depth > 0).astype(np.uint8) * 255, (depth > 0).astype(np.float32)):
        est = ad.estimate(depth, K, "microwave", mask=mask)
        assert np.isfinite(est.axis_origin_m).all()


# --- Depth and mask files that ended in a traceback or in more than one stderr line: a .npz archive
# named .npy (np.load returns an NpzFile: an AttributeError on its ndim), and a PNG declaring 90-120
# million pixels (PIL's DecompressionBombWarning printed two lines above the error).
CAMERA = {"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5}


def _file_depth() -> np.ndarray:
    depth = np.zeros((108, 192))
    depth[30:80, 60:130] = 1.5
    return depth


def _npz_named_npy(tmp_path):
    np.savez(tmp_path / "d.npz", depth=_file_depth())
    (tmp_path / "d.npz").rename(tmp_path / "d.npy")
    return ["d.npy"], ".npz archive"


def _bomb_depth(tmp_path):
    (tmp_path / "d.png").write_bytes(png_header(10000, 10000, 16))
    return ["d.png"], "d.png"


def _bomb_mask(tmp_path):
    np.save(tmp_path / "d.npy", _file_depth())
    (tmp_path / "m.png").write_bytes(png_header(10000, 10000, 8))
    return ["d.npy", "--mask", "m.png"], "m.png"


@pytest.mark.parametrize("make", [_npz_named_npy, _bomb_depth, _bomb_mask], ids=["npz named npy", "100 MP depth PNG",
                                                                                  "100 MP mask PNG"])
def test_estimate_file_is_one_line(tmp_path, monkeypatch, make):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "camera.json").write_text(json.dumps(CAMERA))
    args, needle = make(tmp_path)
    with warnings.catch_warnings(record=True) as caught:  # a warning is stderr lines in a terminal
        warnings.simplefilter("always")
        result = CliRunner().invoke(main, ["estimate", *args, "--class", "microwave"])
    assert not [w for w in caught if "decompression bomb" in str(w.message)], [str(w.message) for w in caught]
    assert_one_line_error(result, needle)
