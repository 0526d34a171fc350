"""Varied structure of the drawer: ``generate --class drawer --table varied``
(classes/drawer/__init__.py, classes/drawer/drawer_varied.urdf.xacro).

The structure variables build the labelled drawer into a carcass: overlay or inset fronts, a
column of closed drawers around it (a stack, a drawer over a door, a drawer column beside a
door), a tray drawer with a low front, bar, knob, recessed or no handles, a countertop and a
plinth or legs.  That the template's defaults build the paper's drawer, the paper's labels
keep their digests and the draws come from the structure stream is checked for every varied
class in tests/classes/test_varied_tables.py.  Checked here: every option builds what it names; the
labels follow it (``geometry`` the sampled box of every fixed part, the axis at the labelled
front, q within the box's full extension); forced options render, verify and their labels
explain their pixels.
"""

import math

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner
from test_varied_tables import _geoms

from articulated_dataset.classes.drawer import (
    DRAWER_Q_M,
    DRAWER_STRUCTURE,
    FLOOR_STANDING_M,
    VARIED_TABLE,
    shortest_box_m,
)
from articulated_dataset.classes.registry import get_class
from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.labels import read_object_labels
from articulated_dataset.generation.mujoco_scene import OBJECT_PREFIX, ORIGIN_POSE, set_configuration
from articulated_dataset.generation.sampling import sample_object
from articulated_dataset.generation.scenes import _draws, layout_boxes
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.tools.verify import verify_split
from helpers_core import check_forced_split

DRAWER = get_class("drawer")
#: Forced structures (every option of every variable over the four).
FORCED = {
    "inset stack+plinth+top+bar": {
        "front_inset_p": 1, "layout_weights": {"stack": 1}, "base_weights": {"plinth": 1}, "countertop_p": 1,
        "handle_weights": {"bar": 1}, "tray_p": 0},
    "overlay over door+legs+knob": {
        "front_inset_p": 0, "layout_weights": {"over_door": 1}, "base_weights": {"legs": 1}, "countertop_p": 0,
        "handle_weights": {"knob": 1}, "tray_p": 0, "door_left_p": 1},
    "overlay beside door+top+recessed": {
        "front_inset_p": 0, "layout_weights": {"beside_door": 1}, "base_weights": {"none": 1}, "countertop_p": 1,
        "handle_weights": {"recessed": 1}, "tray_p": 0, "door_left_p": 0},
    "inset tray beside door+no handle": {
        "front_inset_p": 1, "layout_weights": {"beside_door": 1}, "base_weights": {"plinth": 1}, "countertop_p": 0,
        "handle_weights": {"none": 1}, "tray_p": 1, "door_left_p": 1},
}
#: Objects compiled per forced structure (compiled only, not rendered).
N_COMPILED = 16
#: Geoms of the labelled drawer's box (its front and handle apart).
BOX_GEOMS = ("drawer_bottom", "drawer_left", "drawer_right", "drawer_back")


def _forced(**structure):
    return VARIED_TABLE.override({"structure": structure})


def _compiled(table, k: int):
    """(sample, compiled object, geoms at q = 0, labels) of object ``k`` of ``table``, built at the origin."""
    sample = object_sample(GenerationConfig("drawer", n_objects=k + 1, table=table), k)
    obj = compile_object(DRAWER, object_urdf(DRAWER, sample, table), ORIGIN_POSE, CameraConfig())
    labels = read_object_labels(obj.model, mujoco.MjData(obj.model), obj.info, DRAWER)
    return sample, obj, _geoms(obj.model), labels


def _x_extent(geom) -> tuple[float, float]:
    """Front and back x of an axis-aligned box geom (size, position, rotation)."""
    size, pos, _ = geom
    return pos[0] - size[0], pos[0] + size[0]


def _z_extent(geom) -> tuple[float, float]:
    size, pos, _ = geom
    return pos[2] - size[2], pos[2] + size[2]


# --------------------------------------------------------------------------------------
# Built as named, labelled as built (compiled, not rendered)
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("label", FORCED)
def test_every_option_builds_what_it_names(label):
    structure = FORCED[label]
    layout = next(iter(structure["layout_weights"]))
    handle = next(iter(structure["handle_weights"]))
    base = next(iter(structure["base_weights"]))
    layouts = set()
    for k in range(N_COMPILED):
        sample, _, geoms, _ = _compiled(_forced(**structure), k)
        names = set(geoms)
        standing = sample.geometry["height_m"] >= FLOOR_STANDING_M  # a single drawer's shell has neither
        assert ("countertop" in names) == (standing and bool(structure["countertop_p"]))
        assert ("plinth" in names) == (standing and base == "plinth")
        assert ("leg_front_left" in names) == (standing and base == "legs")
        doors = {n for n in names if n.startswith("door_") and not n.endswith("_handle")}
        fronts = {n for n in names if n.startswith("front_") and n.endswith("_front")}
        built = "stack" if not doors else ("beside_door" if "partition" in names else "over_door")
        layouts.add(built)
        assert built in ("stack", layout)  # a door under 20 cm falls back to a stack
        if built == "over_door":
            assert not fronts  # one drawer row over the door(s)
        handles = {n for n in names if n.endswith("_handle")}
        grips = {n for n in names if n.endswith("_grip")}
        assert bool(handles) == (handle in ("bar", "knob")) and bool(grips) == (handle == "recessed")
        if handle in ("bar", "knob"):  # every front and door carries one
            carrying = {n.removesuffix("_front") for n in fronts} | doors | {"drawer"}
            assert handles == {f"{n}_handle" for n in carrying}
        if handle == "recessed":  # a channel along every drawer front's top edge
            assert grips == {f"{n}_grip" for n in (*fronts, "drawer_front")}
        if handle == "knob":
            size = geoms["drawer_handle"][0]
            assert math.isclose(2 * size[1], sample.structure["knob_m"]) and math.isclose(2 * size[2], sample.structure["knob_m"])
        rails = {n for n in names if n.startswith("rail_")}
        if structure["front_inset_p"]:
            assert len(rails) == len(fronts) + (built == "over_door")  # one between each two rows
        else:
            assert not rails
    assert layout in layouts


def test_closed_fronts_are_flush_with_the_labelled_one_and_the_box_is_every_fixed_part():
    """``geometry`` is the sampled box, whatever leads in front of the carcass (countertop,
    closed overlay fronts and their handles); every front's face lies in one plane; the
    labelled axis is the front's face centre, pointing out of the front."""
    seen = set()
    for label, structure in FORCED.items():
        for k in range(N_COMPILED):
            sample, _, geoms, labels = _compiled(_forced(**structure), k)
            g = sample.geometry
            d, w, h = g["depth_m"], g["width_m"], g["height_m"]
            assert np.allclose(labels["geometry"], (d, w, h, 0), atol=1e-9), (label, k)
            faces = {round(_x_extent(geoms[n])[0], 9) for n in geoms if n.endswith("_front") or n.startswith("door_")
                     and not n.endswith("_handle")}
            assert len(faces) == 1, (label, k, faces)
            front = geoms["drawer_front"]
            assert np.allclose(labels["axis_direction"][0], (-1, 0, 0))
            assert math.isclose(labels["axis_origin"][0, 0], _x_extent(front)[0], abs_tol=1e-9)
            if "recessed" not in label:  # a recessed grip's strip is part of the front's box
                assert np.allclose(labels["axis_origin"][0, 1:], front[1][1:], atol=1e-9)
            neighbours = any(n.startswith(("front_", "door_")) for n in geoms)
            seen.add(neighbours)
            carcass_front = _x_extent(geoms["shell_left"])[0]
            if neighbours and not structure["front_inset_p"]:
                assert carcass_front > -d / 2 + sample.structure["front_thickness_m"] - 1e-9
    assert seen == {True, False}


@pytest.mark.parametrize("slot, row", [(0.0, "top"), (1.0, "bottom")])
def test_slot_frac_picks_the_labelled_row(slot, row):
    table = _forced(layout_weights={"stack": 1}, tray_p=0, slot_frac=[slot, slot], front_height_m=[0.1, 0.1],
                    handle_weights={"bar": 1})
    n_stacked = 0
    for k in range(N_COMPILED):
        _, _, geoms, _ = _compiled(table, k)
        others = [_z_extent(geoms[n])[0] for n in geoms if n.startswith("front_") and n.endswith("_front")]
        if not others:
            continue
        n_stacked += 1
        z = _z_extent(geoms["drawer_front"])[0]
        assert (z > max(others)) if row == "top" else (z < min(others))
        heights = [2 * geoms[n][0][2] for n in geoms if n.endswith("_front")]
        assert np.allclose(heights, heights[0]) and 0.066 <= heights[0] <= 0.2  # rows of about 10 cm
    assert n_stacked > N_COMPILED // 2


def test_a_tray_has_a_low_front_at_the_bottom_of_an_open_row():
    for k in range(N_COMPILED):
        sample, _, geoms, _ = _compiled(_forced(tray_p=1, layout_weights={"stack": 1}, handle_weights={"knob": 1}), k)
        s = sample.structure
        size = geoms["drawer_front"][0]
        assert 2 * size[2] <= s["tray_front_m"] + 1e-9
        box_top = max(_z_extent(geoms[n])[1] for n in BOX_GEOMS)
        assert box_top <= _z_extent(geoms["drawer_front"])[1] + 1e-9


def test_the_drawer_never_leaves_its_carcass():
    """Full extension: at the table's widest opening the box's back is still inside the
    carcass, for the shallowest carcass and every structure; closed, the box stays inside."""
    lo_m = VARIED_TABLE.geometry["depth_m"][0]
    assert DRAWER_Q_M[1] <= shortest_box_m(lo_m, DRAWER_STRUCTURE)
    assert VARIED_TABLE.q == (DRAWER_Q_M,)
    # the shallowest carcass, any width and height, uniform (no size classes)
    shallow = {"shape": None, "geometry": {"depth_m": [lo_m, lo_m]}, "structure": {
        "carcass_m": [0.019, 0.019], "front_thickness_m": [0.022, 0.022], "handle_standoff_m": [0.038, 0.038],
        "countertop_overhang_m": [0.04, 0.04]}}
    for label, structure in FORCED.items():
        table = VARIED_TABLE.override({**shallow, "structure": {**shallow["structure"], **structure}})
        for k in range(6):
            sample, obj, geoms, _ = _compiled(table, k)
            model = obj.model
            assert math.isclose(sample.geometry["depth_m"], lo_m)
            carcass_front, back = _x_extent(geoms["shell_left"])[0], _x_extent(geoms["shell_back"])[0]
            assert _x_extent(geoms["drawer_back"])[1] <= back + 1e-9
            assert np.allclose(model.jnt_range, [DRAWER_Q_M])
            data = mujoco.MjData(model)
            set_configuration(model, data, obj.info.joint_ids, np.array([DRAWER_Q_M[1]]))
            g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, OBJECT_PREFIX + "drawer_back")
            assert data.geom_xpos[g][0] + model.geom_size[g][0] >= carcass_front, (label, k)


def test_structure_comes_from_its_own_stream():
    """Forcing the layout and the handle leaves sizes, pose, configurations and every other
    structure value unchanged."""
    forced = _forced(layout_weights={"beside_door": 1}, handle_weights={"recessed": 1})
    kept = set(DRAWER_STRUCTURE) - {"layout_weights", "handle_weights"}
    for k in range(20):
        a, _ = sample_object(DRAWER, VARIED_TABLE, seed=3, split="train", object_index=k, n_images=4)
        b, _ = sample_object(DRAWER, forced, seed=3, split="train", object_index=k, n_images=4)
        assert a.geometry == b.geometry and a.chirality == b.chirality and a.pose == b.pose and np.array_equal(a.q, b.q)
        assert b.structure["layout_weights"] == "beside_door" and b.structure["handle_weights"] == "recessed"
        assert {n: a.structure[n] for n in kept} == {n: b.structure[n] for n in kept}


def test_a_carcass_as_tall_as_the_counter_stands_on_the_floor_of_a_kitchen_scene():
    """``--scene kitchen`` puts a drawer under a counter top on a base unit; a varied carcass
    reaching the floor (a kitchen drawer base, a chest) gets no base unit, so no empty box."""
    rng = np.random.default_rng(0)
    for height_m in (0.2, 1.0, 1.2):  # a shell; carcasses taller than any counter top
        for _ in range(10):
            boxes, floor = layout_boxes("kitchen", "drawer", {"depth_m": 0.6, "width_m": 0.6, "height_m": height_m}, _draws(rng))
            assert all(min(b.half) > 0 for b in boxes), height_m
            assert (floor == 0.0) == (not any(b.name == "scene_base_unit" for b in boxes))
            assert floor <= 0.0 and (floor < 0.0) == (height_m < 0.5)


# --------------------------------------------------------------------------------------
# Rendered: forced options generate, verify, and their labels explain their pixels
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def forced_root(tmp_path_factory):
    """``root/<label>/drawer/train``: 2 objects x 4 images per forced structure."""
    root = tmp_path_factory.mktemp("varied_drawer")
    for label, structure in FORCED.items():
        generate_split(GenerationConfig("drawer", n_objects=2, images_per_object=4, table=_forced(**structure)), root / label)
    return root


@pytest.mark.parametrize("label", FORCED)
def test_forced_structures_verify_and_their_labels_explain_their_pixels(forced_root, label):
    # the closed object's box reaches the front of the thickest front and farthest handle
    for _, a, _, _ in check_forced_split(forced_root / label / "drawer" / "train", DRAWER, _forced(**FORCED[label]),
                                         front_m=DRAWER_STRUCTURE["front_thickness_m"][1],
                                         standoff_m=DRAWER_STRUCTURE["handle_standoff_m"][1], min_body_px=500):
        assert np.all((a["q"] >= 0) & (a["q"] <= DRAWER_Q_M[1]))


def test_a_varied_mean_drawer_verifies(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--table", "varied", "--mean", "--images", "4",
                                  "--out", str(tmp_path), "-q"])
    assert r.exit_code == 0, r.output
    assert verify_split(tmp_path / "drawer" / "mean").ok
