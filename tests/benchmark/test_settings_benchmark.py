"""benchmarks/settings.py: the "object mask" copy of a scene or occluder split keeps exactly the
object's pixels (a room around a microwave changes none of them: its copy is the isolated split's
depth), stays a valid split, and is reused; the table lists every (setting, model) row."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import Split
from articulated_dataset.tools.verify import verify_split
from helpers_core import ROOT, load_script


def load_benchmark():
    return load_script(ROOT / "benchmarks" / "settings.py", "settings_benchmark")


@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    root = tmp_path_factory.mktemp("settings")
    bench = load_benchmark()
    out = {}
    for setting in ("default", "room", "occluders2"):
        result = CliRunner().invoke(main, ["generate", "--class", "microwave", "--n", "1", "--images", "3", "--split", "test",
                                           "--seed", "2026", "--workers", "1", "--out", str(root / setting), "-q",
                                           *bench.SETTINGS[setting]])
        assert result.exit_code == 0, result.output
        out[setting] = root / setting / "microwave" / "test"
    return bench, root, out


def fields(split_dir, names=("depth", "mask")):
    return Split(split_dir).read_fields(names)


def test_masked_copy_keeps_the_objects_pixels_only(splits):
    bench, root, out = splits
    for setting in ("room", "occluders2"):
        copy = bench.masked_copy(out[setting], root / f"{setting}-masked" / "microwave" / "test")
        before, after = fields(out[setting]), fields(copy)
        obj = (before["mask"] >= 1) & (before["mask"] <= 2)  # body, door
        assert 0 < obj.mean() < 0.5 and (before["mask"] >= 254).any()  # the copy has something to remove
        assert np.array_equal(after["depth"], np.where(obj, before["depth"], 0))
        assert np.array_equal(after["mask"], np.where(obj, before["mask"], 0))
        assert verify_split(copy).ok, setting
    # a room hides none of a microwave's pixels: its masked copy is the isolated object's depth
    isolated = fields(out["default"])["depth"]
    assert np.array_equal(fields(root / "room-masked" / "microwave" / "test")["depth"], isolated)
    assert not np.array_equal(fields(root / "occluders2-masked" / "microwave" / "test")["depth"], isolated)


def test_masked_copy_is_reused_only_for_the_same_split(splits):
    bench, root, out = splits
    dest = root / "reuse" / "microwave" / "test"
    bench.masked_copy(out["room"], dest)
    (dest / "marker").write_text("kept")
    bench.masked_copy(out["room"], dest)
    assert (dest / "marker").exists()
    manifest = json.loads((dest / "manifest.json").read_text())
    manifest["masked_from"] = ["another split"]
    (dest / "manifest.json").write_text(json.dumps(manifest))
    bench.masked_copy(out["room"], dest)
    assert not (dest / "marker").exists() and verify_split(dest).ok


def test_table_has_a_row_per_setting_and_model():
    bench = load_benchmark()
    rows = [{"class": c, "setting": s, "model": m, "axis_position_error_cm": 1.0 + i, "axis_rotation_error_deg": 2.0,
             "configuration_error": 3.0, "coverage_90": 0.9, "images": 16}
            for i, (c, s, m) in enumerate([("microwave", "default", "dense"), ("drawer", "default", "dense"),
                                           ("microwave", "kitchen (object mask)", "ckpt")])]
    text = bench.markdown(rows)
    assert "| default | dense | 1.00 | 2.00 |" in text and "| kitchen (object mask) | ckpt | 3.00 | - |" in text
    assert text.count("| setting | model | microwave | drawer |") == len(bench.METRICS)
    one_model = bench.markdown(rows[:2])
    assert "| setting | microwave | drawer |" in one_model and "| default | 1.00 | 2.00 |" in one_model
