"""Varied structure of the microwave and the toaster oven (``generate --table varied``;
classes/microwave/__init__.py, classes/toaster/__init__.py, classes/{microwave,toaster}_varied.urdf.xacro).

Checked here: every option of every structure variable generates, verifies and has labels
that explain its pixels; the microwave's hinge side is the label's chirality and the keypad
sits on the other side; a toaster oven's hinge sits on top of a panel below the door or of
the rail under it, not at the body's bottom; a window is a pane set back in the door's
frame; structure draws leave the other draws unchanged.  (That the templates' defaults build
the paper's objects is checked for every varied class in tests/classes/test_varied_tables.py.)
"""

import math

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import get_class
from articulated_dataset.cli import main
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.mujoco_scene import OBJECT_PREFIX, ORIGIN_POSE
from articulated_dataset.generation.sampling import sample_object
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.tools.verify import verify_split
from helpers_core import check_forced_split

#: Forced structures (table overrides) covering every option of every flag and option
#: variable of the two classes, with the geoms each must have and must not have.
FORCED = {
    "microwave": {
        "window+bar+feet": ({"chirality_p": 0.0, "structure": {
            "window_p": 1, "handle_weights": {"bar": 1}, "trim_p": 0, "feet_p": 1}},
            {"door_window", "door_frame_free", "door_handle", "foot_front_left", "control_panel"},
            {"door_panel", "trim_left", "grip_pocket", "door_release_button"}),
        "flat+recess+trim, hinged right": ({"chirality_p": 1.0, "structure": {
            "window_p": 0, "handle_weights": {"recess": 1}, "trim_p": 1, "feet_p": 1}},
            {"door_panel", "grip_pocket", "trim_left", "trim_bottom"},
            {"door_window", "foot_front_left", "door_handle", "door_release_button"}),
        "window+button, no feet": ({"chirality_p": 0.0, "structure": {
            "window_p": 1, "handle_weights": {"button": 1}, "trim_p": 0, "feet_p": 0}},
            {"door_window", "door_release_button"},
            {"door_handle", "foot_front_left", "trim_top", "grip_pocket"}),
    },
    "toaster": {
        "side panel+window+feet": ({"structure": {"panel_weights": {"side": 1}, "window_p": 1, "feet_p": 1}},
                                   {"control_panel", "door_rail", "door_window", "door_handle", "foot_back_right"},
                                   {"door_panel"}),
        "panel below+flat door": ({"structure": {"panel_weights": {"below": 1}, "window_p": 0, "feet_p": 0}},
                                  {"control_panel", "door_panel", "door_handle"},
                                  {"door_rail", "door_window", "foot_front_left"}),
        "panel above+window+feet": ({"structure": {"panel_weights": {"above": 1}, "window_p": 1, "feet_p": 1}},
                                    {"control_panel", "door_rail", "door_frame_top", "foot_front_left"},
                                    {"door_panel"}),
    },
}
CASES = [(c, label) for c in FORCED for label in FORCED[c]]


def _table(class_name, label):
    return get_class(class_name).varied_table.override(FORCED[class_name][label][0])


def _compiled(obj_class, sample, table):
    """(model, data, info) of the object built at the origin, at q = 0."""
    obj = compile_object(obj_class, object_urdf(obj_class, sample, table), ORIGIN_POSE, GenerationConfig(obj_class.name).camera)
    data = mujoco.MjData(obj.model)
    mujoco.mj_forward(obj.model, data)
    return obj.model, data, obj.info


def _in_base(data, info, point):
    """A world point in the object's frame (origin at the base's bottom centre, x to the back)."""
    return (point - data.xpos[info.base_body]) @ data.xmat[info.base_body].reshape(3, 3)


def _has(model, name):
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, OBJECT_PREFIX + name) >= 0


def _geom(model, data, info, name):
    """(centre in the object frame, half sizes) of the geom ``name`` at q = 0, axis-aligned."""
    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, OBJECT_PREFIX + name)
    assert g >= 0, name
    return _in_base(data, info, data.geom_xpos[g]), model.geom_size[g].copy()


@pytest.fixture(scope="module")
def forced_root(tmp_path_factory):
    """``root/<class>/<label>/<class>/train``: 3 objects x 6 images per forced structure."""
    root = tmp_path_factory.mktemp("varied_appliances")
    for class_name, label in CASES:
        generate_split(GenerationConfig(class_name, n_objects=3, images_per_object=6, table=_table(class_name, label)),
                       root / class_name / label)
    return root


@pytest.mark.parametrize("class_name, label", CASES)
def test_every_structure_verifies_and_its_labels_explain_its_pixels(forced_root, class_name, label):
    obj_class = get_class(class_name)
    # a closed door stands in front of the body: the checked box reaches the thickest door
    # and the farthest handle of the table
    structure = obj_class.varied_table.structure
    present, absent = FORCED[class_name][label][1:]
    for config, a, sample, rows in check_forced_split(forced_root / class_name / label / class_name / "train", obj_class,
                                                      _table(class_name, label),
                                                      front_m=structure["door_thickness_m"][1],
                                                      standoff_m=structure["handle_standoff_m"][1]):
        assert np.all(a["geometry"][rows, 3] == (sample.chirality if obj_class.sided else 0))
        assert np.all(a["q"][rows, 0] <= config.table.q[0][1] + 1e-6)
        model, _, _ = _compiled(obj_class, sample, config.table)
        names = {model.geom(g).name.removeprefix(OBJECT_PREFIX) for g in range(model.ngeom)}
        assert present <= names and not absent & names, (label, names)


def test_microwave_doors_open_past_a_right_angle():
    assert math.degrees(get_class("microwave").varied_table.q[0][1]) == pytest.approx(105.0)
    assert get_class("microwave").table.q == get_class("microwave").realistic_table.q  # the paper's, unchanged


@pytest.mark.parametrize("chirality_p", [0.0, 1.0])
def test_microwave_hinge_side_is_the_chirality_and_the_keypad_is_on_the_other_side(chirality_p):
    obj_class = get_class("microwave")
    table = obj_class.varied_table.override({"chirality_p": chirality_p})
    for k in range(6):
        sample, _ = sample_object(obj_class, table, seed=0, split="train", object_index=k, n_images=2)
        model, data, info = _compiled(obj_class, sample, table)
        hinge_y = _in_base(data, info, data.xanchor[info.joint_ids[0]])[1]
        keypad_y = _geom(model, data, info, "control_panel")[0][1]
        door_y = _geom(model, data, info, "door_panel" if _has(model, "door_panel") else "door_window")[0][1]
        left = sample.chirality == 0
        assert (hinge_y > door_y) == left and (keypad_y < door_y) == left
        assert hinge_y * keypad_y < 0


@pytest.mark.parametrize("panel", ["side", "above", "below"])
def test_toaster_hinge_sits_on_the_panel_or_rail_below_the_door(panel):
    """The door's hinge line is its front bottom edge: on top of a panel below the door (a
    share of the shell's height), else on top of the rail under the door; feet raise both."""
    obj_class = get_class("toaster")
    table = obj_class.varied_table.override({"structure": {"panel_weights": {panel: 1}}})
    for k in range(6):
        sample, _ = sample_object(obj_class, table, seed=0, split="train", object_index=k, n_images=2)
        s, h = sample.structure, sample.geometry["height_m"]
        model, data, info = _compiled(obj_class, sample, table)
        hinge = _in_base(data, info, data.xanchor[info.joint_ids[0]])
        feet = s["foot_height_m"] if s["feet_p"] else 0.0
        expected = feet + (s["panel_height_frac"] * (h - feet) if panel == "below" else s["door_rail_m"])
        assert hinge[2] == pytest.approx(expected, abs=1e-9)
        assert hinge[0] == pytest.approx(-sample.geometry["depth_m"] / 2 - s["door_thickness_m"], abs=1e-9)
        if panel == "below":
            assert hinge[2] >= 0.12 * (h - feet)
        # the door's top edge: below the panel above it, else the body's top
        door = _geom(model, data, info, "door_panel" if _has(model, "door_panel") else "door_frame_top")
        top = door[0][2] + door[1][2]
        panel_top = s["panel_height_frac"] * (h - feet) if panel == "above" else 0.0
        assert top == pytest.approx(h - panel_top, abs=1e-9)


@pytest.mark.parametrize("class_name", ["microwave", "toaster"])
def test_a_window_is_a_pane_set_back_in_the_doors_frame(class_name):
    obj_class = get_class(class_name)
    table = obj_class.varied_table.override({"structure": {"window_p": 1}})
    for k in range(4):
        sample, _ = sample_object(obj_class, table, seed=1, split="train", object_index=k, n_images=2)
        model, data, info = _compiled(obj_class, sample, table)
        (pc, ps), (fc, fs) = _geom(model, data, info, "door_window"), _geom(model, data, info, "door_frame_top")
        recess = (pc[0] - ps[0]) - (fc[0] - fs[0])  # x runs from the front to the back
        assert recess == pytest.approx(sample.structure["window_recess_m"], abs=1e-9) and recess > 0
        assert pc[0] + ps[0] == pytest.approx(fc[0] + fs[0], abs=1e-9)  # the same back face


@pytest.mark.parametrize("class_name", ["microwave", "toaster"])
def test_forcing_one_structure_variable_leaves_every_other_draw_unchanged(class_name):
    obj_class = get_class(class_name)
    table = obj_class.varied_table
    forced = table.override({"structure": {"window_p": 0, "feet_p": 1}})
    for k in range(10):
        a, _ = sample_object(obj_class, table, seed=3, split="train", object_index=k, n_images=4)
        b, _ = sample_object(obj_class, forced, seed=3, split="train", object_index=k, n_images=4)
        assert a.geometry == b.geometry and a.chirality == b.chirality and a.pose == b.pose and np.array_equal(a.q, b.q)
        assert b.structure["window_p"] == 0 and b.structure["feet_p"] == 1
        assert {n: v for n, v in a.structure.items() if n not in ("window_p", "feet_p")} == \
               {n: v for n, v in b.structure.items() if n not in ("window_p", "feet_p")}


@pytest.mark.parametrize("class_name", ["microwave", "toaster"])
def test_a_varied_mean_object_verifies(tmp_path, class_name):
    r = CliRunner().invoke(main, ["generate", "--class", class_name, "--table", "varied", "--mean", "--images", "4",
                                  "--out", str(tmp_path), "-q"])
    assert r.exit_code == 0, r.output
    assert verify_split(tmp_path / class_name / "mean").ok
