"""Varied structure of the refrigerator: ``generate --class refrigerator --table varied``
(classes/refrigerator/__init__.py, classes/refrigerator/refrigerator_varied.urdf.xacro).

The structure variables build top- or bottom-freezer refrigerators (the freezer's door the
small one, joint 0 still the lower door), insulated walls and a mullion, thick doors whose
hinge is set in from the body's side, a toe grille, shelves and bar handles of any length
or none, opening to 130 degrees.  That the template's defaults build the paper's object
and the paper's labels keep their digests is checked for every varied class in
tests/classes/test_varied_tables.py.  Checked here: every option builds what it names and the labels
(sizes, hinge line, chirality, opening) follow it; forced options render, verify and their
labels explain their pixels; the draws come from the structure stream.
"""

import math

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner
from test_varied_tables import _geoms

from articulated_dataset.classes.refrigerator import REFRIGERATOR_STRUCTURE
from articulated_dataset.classes.registry import get_class
from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.labels import read_object_labels
from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE
from articulated_dataset.generation.sampling import sample_object
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.tools.verify import verify_split
from helpers_core import check_forced_split

FRIDGE = get_class("refrigerator")
#: Forced structures rendered (every option of every variable over the two, shelves apart).
FORCED = {
    "top freezer+grille+3 shelves+bar": {
        "layout_weights": {"top_freezer": 1}, "grille_p": 1, "shelves_weights": {"3": 1}, "handle_weights": {"bar_vertical": 1}},
    "bottom freezer+no grille+no shelf+no handle": {
        "layout_weights": {"bottom_freezer": 1}, "grille_p": 0, "shelves_weights": {"0": 1}, "handle_weights": {"none": 1}},
}
#: Objects compiled per check.
N_COMPILED = 24
#: The template's gap between the doors (m) and longest handle as a share of its door's height.
GAP_M = 0.004
HANDLE_MAX_FRAC = 0.8


def _compiled(table, k: int):
    """(sample, geoms at q = 0, labels) of object ``k`` of ``table``, built at the origin."""
    config = GenerationConfig("refrigerator", n_objects=k + 1, table=table)
    sample = object_sample(config, k)
    obj = compile_object(FRIDGE, object_urdf(FRIDGE, sample, table), ORIGIN_POSE, CameraConfig())
    labels = read_object_labels(obj.model, mujoco.MjData(obj.model), obj.info, FRIDGE)
    return sample, _geoms(obj.model), labels


def _forced(**structure):
    return FRIDGE.varied_table.override({"structure": structure})


# --------------------------------------------------------------------------------------
# Built as named, labelled as built (compiled, not rendered)
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", ["top_freezer", "bottom_freezer"])
def test_the_freezer_door_is_the_small_one_and_joint_0_the_lower(layout):
    table = _forced(layout_weights={layout: 1})
    for k in range(N_COMPILED):
        sample, geoms, labels = _compiled(table, k)
        s = sample.structure
        lower_h, upper_h = (2 * geoms[f"{door}_door_panel"][0][2] for door in ("lower", "upper"))
        freezer_h, fresh_h = (upper_h, lower_h) if layout == "top_freezer" else (lower_h, upper_h)
        span_h = lower_h + upper_h + GAP_M
        assert math.isclose(freezer_h / span_h, s["freezer_frac"], abs_tol=0.01), (k, freezer_h, span_h)
        assert freezer_h < fresh_h
        # joint order: the lower door's hinge line below the upper door's, both vertical
        assert labels["axis_origin"][0, 2] < labels["axis_origin"][1, 2]
        assert np.allclose(np.abs(labels["axis_direction"][:, 2]), 1.0)
        # the mullion sits behind the gap between the doors
        gap_z = geoms["lower_door_panel"][1][2] + lower_h / 2 + GAP_M / 2
        assert math.isclose(geoms["mullion"][1][2], gap_z, abs_tol=1e-9)


def test_geometry_is_the_fixed_body_and_the_hinge_is_set_in_from_its_side():
    """``geometry`` is the sampled box (cabinet and toe grille, doors in front of it); the
    hinge line lies ``hinge_inset_m`` in from the body's side, across the door's thickness as
    ``hinge_depth_frac`` says, and chirality is the side it lies on."""
    sides = set()
    for k in range(N_COMPILED):
        sample, geoms, labels = _compiled(FRIDGE.varied_table, k)
        s, g = sample.structure, sample.geometry
        d, w, h = g["depth_m"], g["width_m"], g["height_m"]
        assert np.allclose(labels["geometry"][:3], (d, w, h), atol=1e-9)
        side = 1 - 2 * sample.chirality
        assert int(labels["geometry"][3]) == sample.chirality
        sides.add(side)
        t = s["door_thickness_m"]
        for j in range(2):
            x, y, _ = labels["axis_origin"][j]
            assert math.isclose(y, side * (w / 2 - s["hinge_inset_m"]), abs_tol=1e-9)
            assert math.isclose(x, -d / 2 - t + s["hinge_depth_frac"] * t, abs_tol=1e-9)
        assert ("toe_grille" in geoms) == bool(s["grille_p"])
        door_bottom = geoms["lower_door_panel"][1][2] - geoms["lower_door_panel"][0][2]
        assert math.isclose(door_bottom, s["grille_height_m"] if s["grille_p"] else 0.0, abs_tol=1e-9)
    assert sides == {1, -1}


@pytest.mark.parametrize("n", ["0", "1", "2", "3"])
def test_shelves_lie_in_the_fresh_food_compartment(n):
    for layout in ("top_freezer", "bottom_freezer"):
        sample, geoms, _ = _compiled(_forced(shelves_weights={n: 1}, layout_weights={layout: 1}), 0)
        shelves = sorted(name for name in geoms if name.startswith("shelf_"))
        assert shelves == [f"shelf_{i}" for i in range(int(n))]
        split = geoms["mullion"][1][2]
        for name in shelves:
            assert (geoms[name][1][2] < split) == (layout == "top_freezer"), (layout, name)


def test_handles_are_vertical_bars_on_the_free_side_of_each_door():
    for k in range(N_COMPILED):
        sample, geoms, _ = _compiled(_forced(handle_weights={"bar_vertical": 1}), k)
        s, side = sample.structure, 1 - 2 * sample.chirality
        w = sample.geometry["width_m"]
        for door in ("lower", "upper"):
            (size, pos, _), (panel, ppos, _) = geoms[f"{door}_door_handle"], geoms[f"{door}_door_panel"]
            assert size[2] > size[1]  # vertical
            assert math.isclose(2 * size[2], min(s["handle_length_m"], HANDLE_MAX_FRAC * 2 * panel[2]), abs_tol=1e-9)
            assert math.isclose(pos[1], -side * (w / 2 - s["handle_inset_m"]), abs_tol=1e-9)  # free side
            assert ppos[2] - panel[2] - 1e-9 <= pos[2] - size[2] and pos[2] + size[2] <= ppos[2] + panel[2] + 1e-9
    _, geoms, _ = _compiled(_forced(handle_weights={"none": 1}), 0)
    assert not any(name.endswith("_handle") for name in geoms)


def test_doors_open_to_130_degrees():
    assert FRIDGE.varied_table.q == ((0.0, math.radians(130.0)),) * 2
    obj = compile_object(FRIDGE, object_urdf(FRIDGE, object_sample(GenerationConfig("refrigerator", table=FRIDGE.varied_table), 0),
                                             FRIDGE.varied_table), ORIGIN_POSE, CameraConfig())
    assert np.allclose(obj.model.jnt_range, [[0.0, math.radians(130.0)]] * 2)


def test_structure_comes_from_its_own_stream():
    """Forcing the layout and the handle leaves sizes, pose, configurations and every other
    structure value unchanged."""
    table = FRIDGE.varied_table
    forced = table.override({"structure": {"layout_weights": {"bottom_freezer": 1}, "handle_weights": {"none": 1}}})
    kept = set(REFRIGERATOR_STRUCTURE) - {"layout_weights", "handle_weights"}
    for k in range(20):
        a, _ = sample_object(FRIDGE, table, seed=3, split="train", object_index=k, n_images=4)
        b, _ = sample_object(FRIDGE, forced, seed=3, split="train", object_index=k, n_images=4)
        assert a.geometry == b.geometry and a.chirality == b.chirality and a.pose == b.pose and np.array_equal(a.q, b.q)
        assert b.structure["layout_weights"] == "bottom_freezer" and b.structure["handle_weights"] == "none"
        assert {n: a.structure[n] for n in kept} == {n: b.structure[n] for n in kept}


# --------------------------------------------------------------------------------------
# Rendered: forced options generate, verify, and their labels explain their pixels
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def forced_root(tmp_path_factory):
    """``root/<label>/refrigerator/train``: 2 objects x 6 images per forced structure."""
    root = tmp_path_factory.mktemp("varied_refrigerator")
    for label, structure in FORCED.items():
        generate_split(GenerationConfig("refrigerator", n_objects=2, images_per_object=6, table=_forced(**structure)), root / label)
    return root


@pytest.mark.parametrize("label", FORCED)
def test_forced_structures_verify_and_their_labels_explain_their_pixels(forced_root, label):
    # the closed object's box reaches the front of the thickest door and farthest handle
    for _, a, sample, rows in check_forced_split(forced_root / label / "refrigerator" / "train", FRIDGE,
                                                 _forced(**FORCED[label]),
                                                 front_m=REFRIGERATOR_STRUCTURE["door_thickness_m"][1],
                                                 standoff_m=REFRIGERATOR_STRUCTURE["handle_standoff_m"][1]):
        assert np.all(a["geometry"][rows, 3] == sample.chirality)


def test_a_varied_mean_refrigerator_verifies(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "refrigerator", "--table", "varied", "--mean", "--images", "4",
                                  "--out", str(tmp_path), "-q"])
    assert r.exit_code == 0, r.output
    assert verify_split(tmp_path / "refrigerator" / "mean").ok
