"""Varied structure: ``generate --table varied`` (classes/varied.py, classes/varied.xacro).

The cabinets' varied tables add structure variables (overlay or inset doors, face frame,
plinth or legs, countertop, shelves, handle kinds) drawn from each object's structure stream.
Checked here: the varied templates' defaults build the paper's objects (the paper's data against
the committed golden digests: tests/project/test_golden_bytes.py), every structure option generates, verifies and
has labels that explain its pixels, the draws are seeded and independent of the workers and
of how the table was stored, and a class without a varied table or a malformed table is
refused in one line.
"""

import json
from dataclasses import replace

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes, get_class
from articulated_dataset.classes.varied import CABINET_STRUCTURE
from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.tables import SamplingTable
from articulated_dataset.format import open_split, read_manifest
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample
from articulated_dataset.generation.compiled import compile_object
from articulated_dataset.generation.labels import read_object_labels
from articulated_dataset.generation.mujoco_scene import OBJECT_PREFIX, ORIGIN_POSE
from articulated_dataset.generation.sampling import draw_structure, object_rng, sample_object
from articulated_dataset.generation.templating import object_urdf, render_urdf, template_arguments
from articulated_dataset.tools.verify import verify_split
from helpers_core import ROOT, assert_one_line_error, check_forced_split

VARIED = [c for c in all_classes() if c.varied_table is not None]
#: Classes built by classes/varied.xacro (the cabinets' structure variables), which the
#: forced structures below are written for; other classes force theirs in their own tests.
CABINETS = [c for c in VARIED if c.varied_table.structure.keys() == CABINET_STRUCTURE.keys()]
#: Overrides that force every option of every structure variable at least once (each
#: probability to 0 and 1, each option weight to 1), a few at a time.
FORCED = {
    "inset+frame+plinth+top+2 shelves+vertical bar": {
        "door_inset_p": 1, "face_frame_p": 1, "base_weights": {"plinth": 1}, "countertop_p": 1,
        "shelves_weights": {"2": 1}, "handle_weights": {"bar_vertical": 1}},
    "overlay+frameless+legs+1 shelf+horizontal bar": {
        "door_inset_p": 0, "face_frame_p": 0, "base_weights": {"legs": 1}, "countertop_p": 0,
        "shelves_weights": {"1": 1}, "handle_weights": {"bar_horizontal": 1}},
    "overlay+frame+top+no base+knob": {
        "door_inset_p": 0, "face_frame_p": 1, "base_weights": {"none": 1}, "countertop_p": 1,
        "shelves_weights": {"0": 1}, "handle_weights": {"knob": 1}},
    "inset+frameless+plinth+no handle": {
        "door_inset_p": 1, "face_frame_p": 0, "base_weights": {"plinth": 1}, "countertop_p": 0,
        "shelves_weights": {"2": 1}, "handle_weights": {"none": 1}},
}
#: Geoms each forced structure must have (and must not have), by name.
EXPECTED_GEOMS = {
    "inset+frame+plinth+top+2 shelves+vertical bar": ({"frame_left", "plinth", "countertop", "shelf_1"}, {"leg_front_left"}),
    "overlay+frameless+legs+1 shelf+horizontal bar": ({"leg_back_right", "shelf_0"}, {"frame_top", "countertop", "shelf_1"}),
    "overlay+frame+top+no base+knob": ({"frame_top", "countertop"}, {"plinth", "leg_front_left", "shelf_0"}),
    "inset+frameless+plinth+no handle": ({"plinth", "shelf_1"}, {"frame_left", "countertop"}),
}


def _geoms(model) -> dict:
    """{geom name: (size, world position, world rotation)} of a compiled model at q = 0."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return {model.geom(g).name.removeprefix(OBJECT_PREFIX): (model.geom_size[g].copy(), data.geom_xpos[g].copy(), data.geom_xmat[g].copy())
            for g in range(model.ngeom)}


# --------------------------------------------------------------------------------------
# The paper's objects and data are unchanged
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("obj_class", VARIED, ids=lambda c: c.name)
def test_the_varied_templates_defaults_build_the_paper_objects(obj_class):
    """A paper sample built from the varied template with every structure argument at its
    default: the same geoms (names, sizes, places), joints and labels as the paper template's."""
    config = GenerationConfig(obj_class.name, n_objects=4, images_per_object=2)
    camera = CameraConfig()
    for k in range(4):
        sample = object_sample(config, k)
        paper = compile_object(obj_class, object_urdf(obj_class, sample, config.table), sample.pose, camera).model
        varied_urdf = render_urdf(obj_class.template_path(varied=True), template_arguments(sample, config.table))
        varied = compile_object(obj_class, varied_urdf, sample.pose, camera).model
        a, b = _geoms(paper), _geoms(varied)
        assert a.keys() == b.keys()
        for name in a:
            for x, y in zip(a[name], b[name]):
                assert np.allclose(x, y, rtol=0, atol=1e-12), (obj_class.name, k, name)
        assert np.allclose(paper.jnt_pos, varied.jnt_pos, atol=1e-12) and np.array_equal(paper.jnt_axis, varied.jnt_axis)
        assert np.array_equal(paper.jnt_range, varied.jnt_range)
        la, lb = (read_object_labels(m, mujoco.MjData(m), compile_object(obj_class, u, sample.pose, camera).info, obj_class)
                  for m, u in ((paper, object_urdf(obj_class, sample, config.table)), (varied, varied_urdf)))
        for key in la:
            assert np.allclose(la[key], lb[key], rtol=0, atol=1e-12), (obj_class.name, k, key)


def test_paper_and_realistic_tables_hold_no_structure():
    for c in all_classes():
        assert "structure" not in c.table.to_dict()
        if c.realistic_table is not None:
            assert "structure" not in c.realistic_table.to_dict()
        assert object_sample(GenerationConfig(c.name, n_objects=1), 0).structure is None


# --------------------------------------------------------------------------------------
# Sampling: its own stream, seeded, the same read back from a manifest
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("obj_class", CABINETS, ids=lambda c: c.name)
def test_structure_comes_from_its_own_stream(obj_class):
    """Sizes, chirality, configurations and pose are drawn as without structure; forcing one
    variable leaves the others' values unchanged."""
    table = obj_class.varied_table
    bare = replace(table, structure={})
    forced = table.override({"structure": {"countertop_p": 1, "handle_weights": {"knob": 1}}})
    for k in range(20):
        a, _ = sample_object(obj_class, table, seed=3, split="train", object_index=k, n_images=4)
        b, _ = sample_object(obj_class, bare, seed=3, split="train", object_index=k, n_images=4)
        c, _ = sample_object(obj_class, forced, seed=3, split="train", object_index=k, n_images=4)
        assert a.geometry == b.geometry and a.chirality == b.chirality and a.pose == b.pose
        assert np.array_equal(a.q, b.q) and b.structure is None
        assert c.structure["countertop_p"] == 1 and c.structure["handle_weights"] == "knob"
        assert {n: v for n, v in a.structure.items() if n not in ("countertop_p", "handle_weights")} == \
               {n: v for n, v in c.structure.items() if n not in ("countertop_p", "handle_weights")}


def test_a_table_read_back_from_its_json_draws_the_same_structure():
    """The stored table (JSON, keys sorted) draws each object's options as the class's own."""
    table = get_class("cabinet").varied_table
    back = SamplingTable.from_dict(json.loads(table.to_json()))
    assert back == table
    for k in range(50):
        rng = lambda: object_rng(0, "cabinet", "train", k, stream=6)  # noqa: E731
        assert draw_structure(rng(), back.structure) == draw_structure(rng(), table.structure)


def test_options_are_drawn_as_often_as_their_weights():
    structure = get_class("cabinet").varied_table.structure
    n = 2000
    draws = [draw_structure(object_rng(0, "cabinet", "train", k, stream=6), structure) for k in range(n)]
    for name in ("handle_weights", "base_weights", "shelves_weights"):
        weights = structure[name]
        total = sum(weights.values())
        for option, w in weights.items():
            p = w / total
            count = sum(d[name] == option for d in draws)
            assert abs(count - n * p) <= 4 * np.sqrt(n * p * (1 - p)) + 1, (name, option, count)
    for name, value in structure.items():
        if name.endswith("_m") or name.endswith("_frac"):
            got = np.array([d[name] for d in draws])
            assert value[0] <= got.min() and got.max() <= value[1], name


# --------------------------------------------------------------------------------------
# Rendered: every option generates, verifies, and its labels explain its pixels
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def forced_root(tmp_path_factory):
    """``root/<label>/<class>/train``: 2 objects x 6 images of each cabinet class per forced structure."""
    root = tmp_path_factory.mktemp("varied")
    for label, structure in FORCED.items():
        for c in CABINETS:
            table = c.varied_table.override({"structure": structure})
            generate_split(GenerationConfig(c.name, n_objects=2, images_per_object=6, table=table), root / label)
    return root


@pytest.mark.parametrize("label", FORCED)
@pytest.mark.parametrize("obj_class", CABINETS, ids=lambda c: c.name)
def test_every_structure_verifies_and_its_labels_explain_its_pixels(forced_root, obj_class, label):
    table = obj_class.varied_table.override({"structure": FORCED[label]})
    for config, _, sample, _ in check_forced_split(forced_root / label / obj_class.name / "train", obj_class, table):
        names = set(_geoms(compile_object(obj_class, object_urdf(obj_class, sample, config.table), ORIGIN_POSE,
                                          config.camera).model))
        present, absent = EXPECTED_GEOMS[label]
        assert present <= names and not absent & names, (label, names)
        assert any(n.endswith("_handle") for n in names) == (FORCED[label]["handle_weights"] != {"none": 1})


def test_cabinet_chirality_is_the_hinge_side_of_a_varied_door(forced_root):
    """Chirality 1 (hinge on the object's right, -y) exactly where the sample put the hinge
    there, with the hinge set in from the body's side by an inset door or a partial overlay."""
    for label in FORCED:
        split = forced_root / label / "cabinet" / "train"
        manifest, shards = open_split(split)
        config = GenerationConfig.from_dict(manifest["config"])
        g, idx = shards[0].read("geometry"), shards[0].read("object_index")
        shards[0].close()
        for k in np.unique(idx):
            assert int(g[idx == k][0, 3]) == object_sample(config, int(k)).chirality


def test_varied_bytes_are_seeded_and_independent_of_workers(tmp_path):
    def run(out, *extra):
        r = CliRunner().invoke(main, ["generate", "--class", "cabinet", "--table", "varied", "--n", "3", "--images", "2",
                                      "--objects-per-shard", "1", "--out", str(out), "-q", *extra])
        assert r.exit_code == 0, r.output
        return [s["sha256"] for s in read_manifest(out / "cabinet" / "train")["shards"]]

    one = run(tmp_path / "a", "--workers", "1")
    assert run(tmp_path / "b", "--workers", "2") == one
    assert run(tmp_path / "c", "--workers", "1", "--seed", "5") != one
    stored = read_manifest(tmp_path / "a" / "cabinet" / "train")["config"]["table"]
    assert stored == get_class("cabinet").varied_table.to_dict() and "structure" in stored


def test_a_varied_mean_object_verifies(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "cabinet2", "--table", "varied", "--mean", "--images", "4",
                                  "--out", str(tmp_path), "-q"])
    assert r.exit_code == 0, r.output
    assert verify_split(tmp_path / "cabinet2" / "mean").ok


# --------------------------------------------------------------------------------------
# Refusals, one line each
# --------------------------------------------------------------------------------------

def without_varied_table(name: str = "drawer"):
    """A stand-in class without a varied table (every built-in class has one; third-party and
    future classes may not)."""
    from dataclasses import replace

    return replace(get_class(name), varied_table=None, varied_template=None)


def test_a_class_without_a_varied_table_refuses_it_naming_those_with_one():
    with pytest.raises(UserError, match="'drawer' has no varied table") as e:
        without_varied_table().named_table("varied")
    assert ", ".join(sorted(c.name for c in VARIED)) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("structure, needle", [
    ({"door_inset_p": 1.5}, "structure.door_inset_p must be a probability in [0, 1]"),
    ({"overlay_m": [0.03, 0.01]}, "structure.overlay_m must satisfy low <= high"),
    ({"overlay_m": [-0.01, 0.01]}, "structure.overlay_m must lie in"),
    ({"handle_z_frac": [0.5, 1.5]}, "structure.handle_z_frac must lie in [0.0, 1.0]"),
    ({"handle_weights": {"lever": 1}}, "structure.handle_weights has no option 'lever'"),
    ({"handle_weights": {"knob": 0}}, "structure.handle_weights needs one option of positive weight"),
    ({"handle_weights": {"knob": -1}}, "structure.handle_weights.knob must be a weight"),
    ({"countertop_p": "yes"}, "structure.countertop_p must be a number"),
    ({"door_hinges_p": 0.5}, "unknown structure variable structure.door_hinges_p"),
    ({"base_weights": [1, 2]}, "structure.base_weights must be a table"),
])
def test_malformed_structure_is_one_line_naming_the_variable(tmp_path, structure, needle):
    override = tmp_path / "t.json"
    override.write_text(json.dumps({"structure": structure}))
    r = CliRunner().invoke(main, ["generate", "--class", "cabinet", "--table", "varied", "--table", str(override),
                                  "--n", "1", "--out", str(tmp_path), "-q"])
    assert_one_line_error(r, needle)


def test_structure_on_a_table_without_it_is_refused(tmp_path):
    override = tmp_path / "t.json"
    override.write_text(json.dumps({"structure": {"countertop_p": 1}}))
    r = CliRunner().invoke(main, ["generate", "--class", "cabinet", "--table", str(override), "--n", "1",
                                  "--out", str(tmp_path), "-q"])
    assert_one_line_error(r, "unknown structure variable structure.countertop_p", "--table varied")
    # a whole table (as a manifest stores one) for a class without structure variables
    stored = {**get_class("drawer").table.to_dict(), "structure": {"countertop_p": 1}}
    with pytest.raises(UserError, match="class 'drawer' has no structure variables"):
        without_varied_table().check_structure(SamplingTable.from_dict(stored))


def test_structure_variable_names_say_their_kind():
    with pytest.raises(UserError, match=r"structure.overlay must end in one of _p, _m, _frac, _weights"):
        SamplingTable.from_dict({**get_class("cabinet").varied_table.to_dict(), "structure": {"overlay": [0, 1]}})


def test_docs_list_every_structure_variable():

    text = (ROOT / "docs" / "generation.md").read_text(encoding="utf-8")
    assert "Varied structure (--table varied)" in text
    for c in VARIED:
        for name in c.varied_table.structure:
            assert f"`{name}`" in text, name
