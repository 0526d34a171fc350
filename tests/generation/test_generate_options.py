"""``artdata generate``'s option rules as library functions (the command only parses, calls
and prints): the camera, the sampling table and the config its options name, with the
same one-line errors the command gives (tests/generation/test_generate_refusals.py checks them end to end)."""

from __future__ import annotations

import json

import pytest

from articulated_dataset.classes.registry import get_class
from articulated_dataset.core.camera import (
    DEFAULT_HEIGHT_PX,
    INTRINSICS_PRESETS,
    MAX_IMAGE_SIDE_PX,
    camera_from_options,
)
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.tables import table_from_options
from articulated_dataset.generation.request import DEFAULT_N_OBJECTS, UrdfOptions, config_from_options, joint_names


def test_camera_from_options():
    vga = camera_from_options(None, None, "640x480", None, None)
    assert (vga.width_px, vga.height_px, vga.intrinsics) == (640, 480, None)
    d435 = camera_from_options(None, None, None, None, "d435")
    assert (d435.width_px, d435.height_px) == (INTRINSICS_PRESETS["d435"].width_px, INTRINSICS_PRESETS["d435"].height_px)
    assert camera_from_options(320, None, None, None, None).height_px == DEFAULT_HEIGHT_PX
    assert camera_from_options(None, None, None, 60.0, None, "head").mount == "head"
    with pytest.raises(UserError, match="either resolution or width/height"):
        camera_from_options(100, None, "640x480", None, None)
    with pytest.raises(UserError, match="vfov is for the paper's camera"):
        camera_from_options(None, None, None, 60.0, "kinect2")
    with pytest.raises(UserError, match=f"height {MAX_IMAGE_SIDE_PX + 1} px is larger"):
        camera_from_options(None, MAX_IMAGE_SIDE_PX + 1, None, None, None)
    with pytest.raises(UserError, match="image size must be positive"):
        camera_from_options(0, 10, None, None, None)


def test_table_from_options(tmp_path):
    drawer = get_class("drawer")
    assert table_from_options(drawer, ()) == drawer.table
    assert table_from_options(drawer, ("realistic",)) == drawer.realistic_table
    override = tmp_path / "tall.json"
    override.write_text(json.dumps({"geometry": {"height_m": [1.5, 1.8]}}))
    table = table_from_options(drawer, (str(override),))  # the paper's table, overridden
    assert table.geometry["height_m"] == (1.5, 1.8) and table.q == drawer.table.q
    assert table_from_options(drawer, ("paper", str(override))) == table
    with pytest.raises(UserError, match="give one table name"):
        table_from_options(drawer, ("paper", "realistic"))
    with pytest.raises(UserError, match="unknown sampling table 'tall'"):
        table_from_options(drawer, ("tall",))
    with pytest.raises(UserError, match="sampling table file not found"):
        table_from_options(drawer, (str(tmp_path / "missing.toml"),))


def test_config_from_options():
    camera = camera_from_options(None, None, None, None, None)
    config = config_from_options("drawer", UrdfOptions(), camera, ("realistic",), n_objects=None, mean=False,
                                 split="val", seed=3)
    assert (config.class_name, config.split, config.seed, config.n_objects) == ("drawer", "val", 3, DEFAULT_N_OBJECTS)
    assert config.table == get_class("drawer").realistic_table and config.third_party is None
    mean = config_from_options("drawer", UrdfOptions(), camera, (), n_objects=None, mean=True)
    assert mean.mean and mean.n_objects == 1
    with pytest.raises(UserError, match="drop n_objects 5"):
        config_from_options("drawer", UrdfOptions(), camera, (), n_objects=5, mean=True)
    with pytest.raises(UserError, match="missing class_name NAME"):
        config_from_options(None, UrdfOptions(), camera, (), n_objects=None, mean=False)
    with pytest.raises(UserError, match="give either class_name or urdf_path"):
        config_from_options("drawer", UrdfOptions(path="x.urdf"), camera, (), n_objects=None, mean=False)
    with pytest.raises(UserError, match="scale is for urdf_path objects"):
        config_from_options("drawer", UrdfOptions(scale=2.0), camera, (), n_objects=None, mean=False)
    assert joint_names(" a, b ,") == ["a", "b"] and joint_names(None) is None
    with pytest.raises(UserError, match="joints needs at least one joint name"):
        joint_names(" , ")
