"""A predictions file's ``mixture_layout`` stored as an array of byte strings that are not UTF-8
is one line naming the attribute, not a UnicodeDecodeError traceback."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark.predictions import read_predictions, validate_class
from articulated_dataset.cli import main
from articulated_dataset.core.errors import DataFormatError


def _write(path, layout) -> None:
    with h5py.File(path, "w") as f:
        f.attrs.update(format_version="1.0", method="hostile")
        g = f.create_group("cabinet")
        g["sample_id"] = np.arange(2, dtype=np.int64)
        g["axis_pose"] = np.tile([1.0, 0, 0, 1, 0, 0, 0], (2, 1, 1))
        g["q"] = np.zeros((2, 1))
        g["mixture_weights"] = np.ones((2, 1))
        g["mixture_means"] = np.zeros((2, 1, 1))
        g["mixture_scales"] = np.ones((2, 1, 1))
        g.attrs["mixture_layout"] = layout


@pytest.mark.parametrize("layout", [np.array([b"\xff"], dtype="S1"), np.array([b"j0.q", b"\xc3("], dtype="S4")],
                         ids=["one", "second"])
def test_a_layout_array_that_is_not_utf8_is_one_line(tmp_path, layout):
    path = tmp_path / "p.h5"
    _write(path, layout)
    with pytest.raises(DataFormatError, match="mixture_layout"):
        read_predictions(path)
    result = CliRunner().invoke(main, ["score", str(path), "--truth", str(tmp_path)])
    err = result.stderr.strip()
    assert result.exit_code == 2 and len(err.splitlines()) == 1 and err.startswith("artdata: error:"), err
    assert "mixture_layout" in err


def test_layout_bytes_given_to_validate_class(tmp_path):
    """The Python API takes the layout as bytes too (a JSON text of it)."""
    arrays = {"sample_id": np.arange(1), "axis_pose": np.array([[[0, 0, 0, 1.0, 0, 0, 0]]]), "q": np.zeros((1, 1)),
              "mixture_weights": np.ones((1, 1)), "mixture_means": np.zeros((1, 1, 1)),
              "mixture_scales": np.ones((1, 1, 1)), "mixture_layout": b'["\xff"]'}
    with pytest.raises(DataFormatError, match="UTF-8"):
        validate_class("x", arrays)
