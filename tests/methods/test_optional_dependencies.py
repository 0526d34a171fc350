"""Optional dependencies other than PyTorch and scipy (tests/methods/test_optional_torch.py,
tests/core/test_optional_scipy.py): without each, the command that needs it says so in one line
with the command that installs it, and writes nothing."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from helpers_core import assert_one_line_error


def _hide(monkeypatch, top: str) -> None:
    for name in list(sys.modules):
        if name == top or name.startswith(top + "."):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, top, None)  # "import top" raises ImportError


@pytest.mark.parametrize("hidden", ["onnx", "onnxruntime"])
def test_onnx_export_without_onnx_is_one_line(monkeypatch, tmp_path, hidden):
    _hide(monkeypatch, hidden)
    out = tmp_path / "m.onnx"
    result = CliRunner().invoke(main, ["export-model", "--model", "dense", "--class", "drawer", "--format", "onnx",
                                       "--out", str(out)])
    assert_one_line_error(result, f"needs {hidden}", "pip install", ".[onnx]")
    assert not out.exists()


def test_shipped_models_without_safetensors_are_one_line(monkeypatch, tmp_path):
    from articulated_dataset.methods import estimation

    _hide(monkeypatch, "safetensors")
    monkeypatch.setattr(estimation, "_MODEL_CACHE", {})  # a model loaded by an earlier test is not read again
    depth_m = np.zeros((108, 192), np.float32)
    depth_m[30:80, 60:140] = 1.5
    np.save(tmp_path / "d.npy", depth_m)
    (tmp_path / "camera.json").write_text('{"fx": 365.0, "fy": 365.0, "cx": 96.0, "cy": 54.0}')
    result = CliRunner().invoke(main, ["estimate", str(tmp_path / "d.npy"), "--class", "drawer"])
    assert_one_line_error(result, "needs safetensors", "pip install")
