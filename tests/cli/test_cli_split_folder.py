"""Every command names the split it reads as its positional DIR; ``--data DIR`` still works for
one minor version, with a warning, and the folder given twice or not at all is one line."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.cli.options import DATA_OPTION_REMOVED_IN
from helpers_core import assert_one_line_error


def _args(command: str, split, tmp_path) -> list[str]:
    return {"predict": ["predict", "--model", "mdn-small", "--out", str(tmp_path / "p.h5"), "-q"],
            "plan": ["plan", "--index", "0", "-q"],
            "train": ["train", "--model", "mdn", "--class", "drawer", "--out", str(tmp_path / "m.pt"), "--small",
                      "--epochs", "1", "-q"]}[command]


@pytest.mark.parametrize("command", ["predict", "plan", "train"])
def test_the_split_folder_is_the_argument_and_data_is_deprecated(tiny_root, tmp_path, command):
    split = str(tiny_root / "drawer" / ("train" if command == "train" else "test"))
    args = _args(command, split, tmp_path)
    new = CliRunner().invoke(main, [*args, split])
    assert new.exit_code == 0, new.output
    assert "deprecated" not in new.output
    args = _args(command, split, tmp_path / "old")
    (tmp_path / "old").mkdir()
    old = CliRunner().invoke(main, [*args, "--data", split])
    assert old.exit_code == 0, old.output
    warning = [line for line in old.output.splitlines() if line.startswith("artdata: warning:")]
    assert len(warning) == 1 and "--data is deprecated" in warning[0] and DATA_OPTION_REMOVED_IN in warning[0]
    assert f"artdata {command} {split}" in warning[0]
    assert_one_line_error(CliRunner().invoke(main, [*args, split, "--data", split]), "given twice")
    assert_one_line_error(CliRunner().invoke(main, args), "missing the split folder DIR")
