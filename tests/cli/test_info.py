"""``artdata info``: every label row names its column and unit; real splits with partial labels
summarise the labelled values only (valid JSON, no NaN)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import Split
from helpers_real import ingest_uneven_cabinet2


def run_info(*args):
    result = CliRunner().invoke(main, ["info", *map(str, args)])
    assert result.exit_code == 0, result.output
    return result.output


def _no_nan(token):
    raise ValueError(f"JSON constant {token} (not valid JSON)")


def test_rows_name_columns_and_units(tiny_root):
    split = tiny_root / "cabinet2" / "test"
    lines = run_info(split).splitlines()
    rows = {line[2:].split("  ")[0]: line.split()[-3:] for line in lines[3:]}
    want = ["q left_door_hinge (rad)", "q right_door_hinge (rad)", "origin left_door_hinge.x (m)",
            "origin right_door_hinge.z (m)", "geometry depth (m)", "geometry chirality (0: hinge left, 1: right)",
            "object yaw (rad)", "visible body (px)", "visible right_door_hinge (px)"]
    assert all(w in rows for w in want), sorted(rows)
    assert len(rows) == 2 + 6 + 4 + 1 + 3 and "labelled" not in lines[2]
    summary = json.loads(run_info("--json", split), parse_constant=_no_nan)[0]
    q = summary["labels"]["q"]
    assert [c["name"] for c in q["columns"]] == ["q left_door_hinge", "q right_door_hinge"]
    assert {c["unit"] for c in q["columns"]} == {"rad"} and q["n_labelled"] == [48, 48]
    ref = Split(split).read_fields(["q"])["q"]
    assert q["max"] == [round(float(x), 4) for x in ref.max(0)]
    assert rows["q left_door_hinge (rad)"][2] == f"{ref[:, 0].max():.3f}"
    assert summary["labels"]["axis_origin"]["columns"][3] == {"name": "origin right_door_hinge.x", "unit": "m"}


def test_drawer_q_is_in_metres(tiny_root):
    summary = json.loads(run_info("--json", tiny_root / "drawer" / "test"))[0]
    assert summary["labels"]["q"]["columns"] == [{"name": "q drawer_slide", "unit": "m"}]


@pytest.fixture(scope="module")
def real_split(tiny_root, tmp_path_factory):
    return ingest_uneven_cabinet2(tiny_root, tmp_path_factory.mktemp("real_info"))


def test_real_split_summarises_labelled_values_only(real_split):
    summary = json.loads(run_info("--json", real_split), parse_constant=_no_nan)[0]
    labels = summary["labels"]
    ref = Split(real_split).read_fields(["q"])["q"]
    assert np.isnan(ref).any() and not np.isnan(ref).all()
    assert labels["q"]["n_labelled"] == [2, 2]
    assert labels["q"]["mean"] == [round(float(np.nanmean(ref[:, j])), 4) for j in range(2)]
    assert labels["object_yaw"]["n_labelled"] == [0] and labels["object_yaw"]["min"] == [None]
    assert labels["visible_pixels"]["n_labelled"] == [3, 3, 3]
    lines = run_info(real_split).splitlines()
    assert lines[2].split()[-1] == "labelled" and not any("nan" in line for line in lines)
    yaw = next(line for line in lines if line.lstrip().startswith("object yaw (rad)"))
    assert yaw.split()[-4:] == ["-", "-", "-", "0"]


@pytest.fixture(scope="module")
def option_splits(tmp_path_factory):
    """One tiny microwave split per option line: a kitchen with two occluders, the head camera
    with a sensor's intrinsics."""
    root = tmp_path_factory.mktemp("info_options")
    options = {"context": ["--scene", "kitchen", "--occluders", "2"],
               "robot": ["--camera", "head", "--intrinsics", "d435", "--resolution", "96x54"]}
    for name, extra in options.items():
        result = CliRunner().invoke(main, ["generate", "--class", "microwave", "--n", "1", "--images", "2", "--workers", "1",
                                           "--out", str(root / name), "-q", *extra])
        assert result.exit_code == 0, result.output
    return {name: root / name / "microwave" / "train" for name in options}


def test_scene_and_occluders_are_printed(option_splits):
    split = option_splits["context"]
    lines = run_info(split).splitlines()
    assert lines[2] == "  scene kitchen, 2 occluders per image"
    summary = json.loads(run_info("--json", split))[0]
    assert (summary["scene"], summary["occluders"], summary["camera_mount"], summary["intrinsics"]) == ("kitchen", 2, "fixed", None)
    fraction = summary["labels"]["visible_fraction"]
    assert [c["name"] for c in fraction["columns"]] == ["visible fraction body", "visible fraction door_hinge"]
    ref = Split(split).read_fields(["visible_fraction"])["visible_fraction"]
    assert fraction["min"] == [round(float(x), 4) for x in ref.min(0)]
    assert 0.3 <= fraction["min"][1] <= fraction["max"][1] <= 1.0  # the occluders' bound on a moving part
    rows = {line[2:].split("  ")[0]: line.split()[-3:] for line in lines[4:]}
    assert rows["visible fraction door_hinge"] == [f"{v:.3f}" for v in (ref[:, 1].min(), ref[:, 1].mean(), ref[:, 1].max())]


def test_camera_options_are_printed(option_splits):
    lines = run_info(option_splits["robot"]).splitlines()
    assert lines[1].endswith("96x54 px") and lines[2] == "  camera head, intrinsics d435"
    summary = json.loads(run_info("--json", option_splits["robot"]))[0]
    assert (summary["scene"], summary["occluders"], summary["camera_mount"], summary["intrinsics"]) == ("none", 0, "head", "d435")
    assert "visible_fraction" not in summary["labels"]


def test_the_papers_setting_prints_no_option_line(tiny_root):
    lines = run_info(tiny_root / "microwave" / "test").splitlines()
    assert lines[2].split() == ["label", "min", "mean", "max"]
    summary = json.loads(run_info("--json", tiny_root / "microwave" / "test"))[0]
    assert (summary["scene"], summary["occluders"], summary["camera_mount"], summary["intrinsics"]) == ("none", 0, "fixed", None)
    assert "visible_fraction" not in summary["labels"]
