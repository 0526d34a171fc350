"""What ``artdata estimate`` finds beside a depth image: the label file 'artdata export' writes
holds the intrinsics it needs, and a split's shard is named for what it is."""

from __future__ import annotations

from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.tools.exr import export_split
from helpers_core import assert_one_line_error


def test_an_exported_image_is_estimated_without_camera(tiny_root, tmp_path):
    exported = export_split(tiny_root / "drawer" / "test", tmp_path / "exp")
    image = sorted(exported.glob("*.exr"))[0]
    result = CliRunner().invoke(main, ["estimate", str(image), "--class", "drawer", "--json"])
    assert result.exit_code == 0, result.output
    assert '"q_m"' in result.output


def test_a_shard_is_named_as_a_shard(tiny_root):
    shard = sorted((tiny_root / "drawer" / "test").glob("shard-*.h5"))[0]
    line = assert_one_line_error(CliRunner().invoke(main, ["estimate", str(shard), "--class", "drawer"]),
                                 "is a shard of a split", "artdata predict")
    assert "intrinsics" not in line
