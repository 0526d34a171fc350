"""Imported (URDF) objects are labelled by the built-in classes' conventions: the hinge side
(chirality) from geometry, the axis frame's reference direction from the panel without its
handle, q = 0 closed with positive q opening, and ``--scale auto:CLASS`` sizes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from articulated_dataset.benchmark.scoring import image_metrics
from articulated_dataset.classes.registry import get_class
from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.rotations import matrix_to_quat, quat_to_matrix
from articulated_dataset.format import MASK_FIRST_PART
from articulated_dataset.generation import urdf_import
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.labels import geom_corners_world, read_object_labels
from articulated_dataset.generation.mujoco_scene import set_configuration
from articulated_dataset.generation.urdf_import import import_urdf
from helpers_core import assert_one_line_error

# Body (depth, width, height), door panel thickness, and a bar handle standing off the door's
# face near its free edge: (standoff, bar width, bar length) and its distance from the hinge.
D, W, H, PANEL = 0.4, 0.5, 0.7, 0.02
STANDOFF, BAR, BAR_LEN, HANDLE_AT = 0.04, 0.02, 0.15, 0.45
TOL_M = 1e-6


def _box(size, xyz):
    return (f'<visual><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}"/>'
            f'<geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></visual>')


def _door_parts(side: int):
    """(panel, handle) boxes (size, centre) in the door frame; ``side`` +1: the door extends
    to +y of its hinge (hinged on the right), -1: to -y (hinged on the left)."""
    panel = ((PANEL, W, H), (-PANEL / 2, side * W / 2, H / 2))
    handle = ((STANDOFF, BAR, BAR_LEN), (-PANEL - STANDOFF / 2, side * HANDLE_AT, H / 2))
    return panel, handle


def _write_door(folder: Path, side: int, *, mesh: bool = False, limits=(-1.6, 0.0), axis_z=-1) -> Path:
    """A body and a door hinged on its front edge (right: ``side`` +1, left: -1), the door
    modelled closed, with a protruding handle (two boxes, or one OBJ mesh with ``mesh``)."""
    folder.mkdir(parents=True, exist_ok=True)
    panel, handle = _door_parts(side)
    if mesh:
        parts = [trimesh.creation.box(extents=s, transform=trimesh.transformations.translation_matrix(c))
                 for s, c in (panel, handle)]
        trimesh.util.concatenate(parts).export(str(folder / "door.obj"))
        door = '<visual><geometry><mesh filename="door.obj"/></geometry></visual>'
    else:
        door = _box(*panel) + _box(*handle)
    path = folder / "door.urdf"
    path.write_text(f"""<robot name="door">
  <link name="base">{_box((D, W, H), (0, 0, H / 2))}</link>
  <link name="door">{door}</link>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="door"/>
    <origin xyz="{-D / 2} {-side * W / 2} 0"/><axis xyz="0 0 {axis_z}"/>
    <limit lower="{limits[0]}" upper="{limits[1]}" effort="1" velocity="1"/></joint>
</robot>""")
    return path


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))


def _compiled(path: Path, **kw):
    """(imported object, model, data at q = 0, info, labels) at the identity pose."""
    obj = import_urdf(path, **kw)
    c = obj.obj_class
    compiled = compile_object(c, Path(c.template).read_text(), {"x_m": 0.0, "y_m": 0.0, "z_m": 0.0, "yaw_rad": 0.0},
                              CameraConfig())
    data = mujoco.MjData(compiled.model)
    labels = read_object_labels(compiled.model, data, compiled.info, c)
    return obj, compiled.model, data, compiled.info, labels


@pytest.mark.parametrize("mesh", [False, True], ids=["boxes", "mesh"])
@pytest.mark.parametrize("side, chirality", [(1, 1), (-1, 0)], ids=["right", "left"])
def test_hinge_side_comes_from_geometry(tmp_path, side, chirality, mesh):
    limits, axis_z = ((-1.6, 0.0), -1) if side == 1 else ((0.0, 1.6), -1)
    *_, labels = _compiled(_write_door(tmp_path / "obj", side, mesh=mesh, limits=limits, axis_z=axis_z))
    assert labels["geometry"][3] == chirality


def test_a_horizontal_hinge_has_no_side(tmp_path):
    folder = tmp_path / "lid"
    folder.mkdir()
    path = folder / "lid.urdf"  # a lid hinged along the back top edge (axis along y)
    path.write_text(f"""<robot name="lid">
  <link name="base">{_box((D, W, H), (0, 0, H / 2))}</link>
  <link name="lid">{_box((D, W, PANEL), (-D / 2, 0, PANEL / 2))}</link>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="lid"/>
    <origin xyz="{D / 2} {-W / 4} {H}"/><axis xyz="0 1 0"/><limit lower="0" upper="1.2" effort="1" velocity="1"/></joint>
</robot>""")
    *_, labels = _compiled(path)
    assert labels["geometry"][3] == 0


@pytest.mark.parametrize("mesh", [False, True], ids=["boxes", "mesh"])
def test_reference_direction_runs_to_the_panel_without_its_handle(tmp_path, mesh):
    side = 1
    _, model, data, info, labels = _compiled(_write_door(tmp_path / "obj", side, mesh=mesh))
    part = info.geom_part == MASK_FIRST_PART
    assert (part & info.geom_is_handle).any() and (part & ~info.geom_is_handle).any()
    # the handle, and only it, is left out: the panel's box is the door's extent
    corners = geom_corners_world(model, data, np.nonzero(part & ~info.geom_is_handle)[0])
    hinge = np.array([-D / 2, -side * W / 2, 0.0])
    (size, centre_door) = _door_parts(side)[0]
    np.testing.assert_allclose(corners.min(0), hinge + np.array(centre_door) - np.array(size) / 2, atol=TOL_M)
    np.testing.assert_allclose(corners.max(0), hinge + np.array(centre_door) + np.array(size) / 2, atol=TOL_M)

    centre = hinge + np.array(centre_door)
    origin = np.array([hinge[0], hinge[1], centre[2]])  # on the hinge line, nearest the panel's centre
    axis = np.array([0.0, 0.0, 1.0])  # flipped by the import: positive q opens towards the front (-x)
    x = (centre - origin) / np.linalg.norm(centre - origin)
    R = np.stack([x, np.cross(axis, x), axis], axis=1)
    np.testing.assert_allclose(labels["axis_origin"][0], origin, atol=TOL_M)
    np.testing.assert_allclose(labels["axis_direction"][0], axis, atol=TOL_M)
    np.testing.assert_allclose(quat_to_matrix(labels["axis_pose"][0, 3:]), R, atol=TOL_M)
    np.testing.assert_allclose(labels["part_offset"][0], R.T @ (centre - origin), atol=TOL_M)

    # the axis read off the door's geometry scores 0 rotation error and the right side
    def one(quat, offset):
        return {"axis_pose": np.concatenate([origin, quat])[None, None], "q": np.zeros((1, 1)),
                "part_offset": offset[None, None], "geometry": np.array([[D, W, H, 1.0]])}

    truth = one(labels["axis_pose"][0, 3:], labels["part_offset"][0])
    per_image, _ = image_metrics(one(matrix_to_quat(R), R.T @ (centre - origin)), truth, ("revolute",))
    assert per_image["axis_rotation_error_deg"][0] < 1e-4
    assert per_image["mechanism_side_accuracy"][0] == 1.0
    # ... where a direction to the centre of panel and handle together would not
    whole = geom_corners_world(model, data, np.nonzero(part)[0])
    centre_all = 0.5 * (whole.min(0) + whole.max(0))
    x_all = centre_all - origin
    x_all = (x_all - (x_all @ axis) * axis) / np.linalg.norm(x_all - (x_all @ axis) * axis)
    assert math.degrees(math.acos(np.clip(x_all @ x, -1, 1))) > 2.0


@pytest.mark.parametrize("limits, axis_z, flipped", [((-1.6, 0.0), -1, True), ((-0.2, 1.4), 1, False),
                                                     ((-1.4, 0.2), -1, True)],
                         ids=["opens-negative", "closed-at-lower", "closed-at-upper"])
def test_q_zero_is_closed_and_positive_q_opens(tmp_path, limits, axis_z, flipped):
    """A right-hinged door modelled closed; URDF axis and limits in several writings: q = 0 is
    the limit nearer the URDF zero (the modelled pose), positive q swings the door out front."""
    side = 1
    obj, model, data, info, labels = _compiled(_write_door(tmp_path / "obj", side, limits=limits, axis_z=axis_z))
    lo, hi = limits
    closed = lo if abs(lo) <= abs(hi) else hi
    assert obj.obj_class.table.q[0] == pytest.approx((0.0, hi - lo))
    assert any(("flipped" in n) == flipped for n in obj.notes if n.startswith("hinge"))
    panel = np.nonzero((info.geom_part == MASK_FIRST_PART) & ~info.geom_is_handle)[0]
    hinge = np.array([-D / 2, -side * W / 2, 0.0])

    def door_points(q):
        set_configuration(model, data, info.joint_ids, [q])
        return geom_corners_world(model, data, panel)

    # at q = 0 the door is at the closed limit: the modelled pose turned by that limit about the URDF axis
    size, centre = _door_parts(side)[0]
    modelled = np.array(centre) + (np.array(list(np.ndindex(2, 2, 2))) - 0.5) * np.array(size)
    turn = trimesh.transformations.rotation_matrix(closed, [0, 0, axis_z])[:3, :3]
    expected = hinge + modelled @ turn.T
    np.testing.assert_allclose(np.sort(door_points(0.0), axis=0), np.sort(expected, axis=0), atol=1e-5)
    front = [door_points(q)[:, 0].min() for q in (0.0, 0.3, 0.6)]
    assert front[0] > front[1] > front[2]  # opening: the free edge comes out towards the front (-x)


def _unit_cabinet(folder: Path, width: float, height: float) -> Path:
    """A normalised cabinet (PartNet-Mobility style: about unit size) of front ``width`` x ``height``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "mobility.urdf"
    depth = 0.5 * width
    path.write_text(f"""<robot name="unit">
  <link name="base">{_box((depth, width, height), (0, 0, height / 2))}</link>
  <link name="door">{_box((PANEL, width, height), (-PANEL / 2, width / 2, height / 2))}</link>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="door"/>
    <origin xyz="{-depth / 2} {-width / 2} 0"/><axis xyz="0 0 1"/><limit lower="0" upper="1.5" effort="1" velocity="1"/></joint>
</robot>""")
    return path


def test_scale_auto_gives_a_standard_size_of_the_class(tmp_path):
    comp = get_class("cabinet").realistic_table.shape.components[0]
    W0, H0 = min(comp.sizes_m["width_m"]), min(comp.sizes_m["height_m"])
    norm = max(W0, H0)  # the file's body: the standard proportions at unit size
    path = _unit_cabinet(tmp_path / "cab", W0 / norm, H0 / norm)
    obj = import_urdf(path, scale="auto:cabinet")
    assert obj.definition["scale"] == pytest.approx(norm, rel=1e-5)
    g = obj.obj_class.table.geometry
    assert g["width_m"][0] == pytest.approx(W0, rel=1e-4) and g["height_m"][0] == pytest.approx(H0, rel=1e-4)
    assert any(n.startswith("--scale auto:cabinet") for n in obj.notes)
    again = import_urdf(path, scale="auto:cabinet")
    assert again.definition == obj.definition  # deterministic


def test_scale_auto_on_the_command_line(tmp_path):
    path = _unit_cabinet(tmp_path / "cab", 0.5, 0.9)
    r = CliRunner().invoke(main, ["generate", "--urdf", str(path), "--scale", "auto:cabinet", "--n", "1", "--images", "1",
                                  "--split", "test", "--out", str(tmp_path / "out"), "-q"])
    assert r.exit_code == 0, r.output
    manifest = json.loads((tmp_path / "out" / "cab-mobility" / "test" / "manifest.json").read_text())
    scale = manifest["config"]["third_party"]["scale"]
    assert scale == import_urdf(path, scale="auto:cabinet").definition["scale"] and scale > 1.0


@pytest.mark.parametrize("value, needle", [("auto:nothing", "names a built-in class"), ("big", "not a number")])
def test_scale_auto_refuses_unknown_values(tmp_path, value, needle):
    path = _unit_cabinet(tmp_path / "cab", 0.5, 0.9)
    r = CliRunner().invoke(main, ["generate", "--urdf", str(path), "--scale", value, "--n", "1", "--out", str(tmp_path)])
    if needle == "not a number":  # click's own usage error
        assert r.exit_code == 2 and needle in r.output
    else:
        assert_one_line_error(r, needle)

