"""PyTorch is an optional dependency (the torch extra): without it, every command and API that
needs it fails with one line naming what needs it and the command that installs PyTorch's CPU
build, before importing it, and the commands that do not need it still work."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from click.testing import CliRunner

import articulated_dataset
from articulated_dataset.cli import main
from articulated_dataset.core.errors import TORCH_INSTALL, UserError
from helpers_core import assert_one_line_error

#: The command that installs PyTorch's CPU build (a bare 'pip install torch' pulls CUDA).
CPU_INDEX = "--index-url https://download.pytorch.org/whl/cpu"


@pytest.fixture
def no_torch(monkeypatch):
    """``import torch`` fails as where PyTorch is not installed (modules already imported hidden)."""
    for name in list(sys.modules):
        if name == "torch" or name.startswith("torch."):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "torch", None)


@pytest.fixture(scope="module")
def depth_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("notorch")
    depth_m = np.zeros((108, 192), np.float32)
    depth_m[30:80, 60:140] = 1.5  # a box 1.5 m away: an isolated object
    np.save(folder / "d.npy", depth_m)
    (folder / "camera.json").write_text('{"fx": 365.0, "fy": 365.0, "cx": 96.0, "cy": 54.0}')
    return folder / "d.npy"


def test_the_install_command_is_the_cpu_build():
    assert CPU_INDEX in TORCH_INSTALL and "torch==" not in TORCH_INSTALL


def test_estimate_without_torch_is_one_line(no_torch, depth_file):
    result = CliRunner().invoke(main, ["estimate", str(depth_file), "--class", "drawer"])
    assert_one_line_error(result, "artdata estimate needs torch", CPU_INDEX)
    result = CliRunner().invoke(main, ["estimate", str(depth_file), "--class", "drawer", "--precision", "bfloat16"])
    assert_one_line_error(result, "needs torch", CPU_INDEX)


def test_estimate_api_without_torch_is_a_user_error(no_torch, depth_file):
    K = [[365.0, 0.0, 96.0], [0.0, 365.0, 54.0], [0.0, 0.0, 1.0]]
    with pytest.raises(UserError, match="needs torch") as e:
        articulated_dataset.estimate(np.load(depth_file), K, "drawer")
    assert "\n" not in str(e.value) and CPU_INDEX in str(e.value)


@pytest.mark.parametrize("command", [
    ["predict", "--model", "dense", "{split}", "--out", "{tmp}/p.h5"],
    ["train", "--class", "drawer", "{split}", "--out", "{tmp}/c.pt"],
])
def test_model_commands_without_torch_are_one_line(no_torch, tiny_root, tmp_path, command):
    args = [a.format(split=tiny_root / "drawer" / "train", tmp=tmp_path) for a in command]
    result = CliRunner().invoke(main, args)
    assert_one_line_error(result, f"artdata {command[0]} needs torch", CPU_INDEX)
    assert not list(tmp_path.iterdir())  # refused before anything was written


def test_commands_without_torch_still_work(no_torch, tiny_root, tmp_path):
    split = tiny_root / "drawer" / "test"
    for args in (["info", str(split)], ["models"],
                 ["baseline", "mean", "--train", str(tiny_root / "drawer" / "train"), "--test", str(split),
                  "--out", str(tmp_path / "mean.h5"), "-q"]):
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, (args, result.output)
    assert "torch" not in sys.modules or sys.modules["torch"] is None
