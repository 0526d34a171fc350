"""Scene context and occluders: ``generate --scene kitchen|room``, ``--occluders N``.

Every class is generated with a kitchen, with a room and two occluders, and with three
occluders alone; the stored labels must explain the object's pixels image by image (scene
and occluder pixels excluded), the occlusion labels must match a render of the object alone
rebuilt independently, and everything must be seeded, recorded and verifiable.
"""

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes
from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig, backproject
from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.format import open_split, read_manifest
from articulated_dataset.format.manifest import SplitConfig
from articulated_dataset.format.schema import (
    CONTEXT_FORMAT_VERSION,
    MASK_BODY,
    MASK_OCCLUDER,
    MASK_SCENE,
    OPTIONAL_FIELDS,
    visible_pixels,
)
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample, render_object, stored_sample
from articulated_dataset.generation.context_labels import (
    OCCLUDER_SHOW_RGB,
    SCENE_SHOW_RGB,
    VISIBLE_FRACTION_RANGE,
    object_depth,
    tint_context,
    visible_fraction,
)
from articulated_dataset.generation.render import process_renderer
from articulated_dataset.generation.scenes import MAX_SUPPORT_HEIGHT_M, MIN_CAMERA_HEIGHT_M, layout_boxes, scene_layout
from articulated_dataset.generation.viewpoint import HEAD_HEIGHT_M, mid_height_m
from articulated_dataset.tools.verify import verify_split
from helpers_core import IMAGE_CHECK_FIELDS, ROOT, assert_one_line_error, check_stored_images, compile_object, render_at

CLASSES = all_classes()
#: (scene, occluders, camera mount) of each generated setting.
SETTINGS = {"kitchen": ("kitchen", 0, "fixed"), "room+2": ("room", 2, "fixed"), "occluders3": ("none", 3, "fixed"),
            "head+kitchen+2": ("kitchen", 2, "head")}
OCCLUSION_FIELDS = tuple(f.name for f in OPTIONAL_FIELDS)


@pytest.fixture(scope="module")
def context_root(tmp_path_factory):
    """``root/<setting>/<class>/train``: 2 objects x 16 images of every class per setting."""
    root = tmp_path_factory.mktemp("context")
    for key, (scene, occluders, mount) in SETTINGS.items():
        for c in CLASSES:
            generate_split(GenerationConfig(c.name, n_objects=2, objects_per_shard=2, scene=scene, occluders=occluders,
                                            camera=CameraConfig(mount=mount)), root / key)
    return root


def _read(split_dir, fields):
    manifest, shards = open_split(split_dir)
    a = {k: np.concatenate([s.read(k) for s in shards]) for k in fields}
    K, attrs = np.asarray(shards[0].K), shards[0].attrs
    for s in shards:
        s.close()
    return manifest, a, K, attrs


@pytest.mark.parametrize("setting", list(SETTINGS))
@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_labels_explain_the_visible_object_pixels(context_root, setting, obj_class):
    """Body and part pixels obey the labels as in isolation (check_stored_images, with its
    negative control); scene pixels never fall inside the object's closed box; occluder
    pixels are all nearer than every object pixel of their image."""
    manifest, a, K, attrs = _read(context_root / setting / obj_class.name / "train",
                                  IMAGE_CHECK_FIELDS + ("visible_pixels",) + OCCLUSION_FIELDS)
    scene, occluders, mount = SETTINGS[setting]
    checked, detected, n_body = check_stored_images(obj_class, a, K)
    assert checked > 0 and detected >= 0.9 * checked and n_body > 100
    n_scene = n_occluder = 0
    for i in range(len(a["q"])):
        pose = a["object_pose"][i].astype(np.float64)
        R, t = quat_to_matrix(pose[3:]), pose[:3]
        d, w, h = a["geometry"][i, :3].astype(np.float64)
        mask, depth = a["mask"][i], a["depth"][i]
        pts = (backproject(depth, K, mask == MASK_SCENE) - t) @ R
        interior = np.all((pts > np.array([-d / 2, -w / 2, 0]) + 0.01) & (pts < np.array([d / 2, w / 2, h]) - 0.01), axis=1)
        assert not interior.any(), (obj_class.name, i)
        n_scene += len(pts)
        occ = depth[mask == MASK_OCCLUDER]
        obj = depth[(mask >= MASK_BODY) & (mask < MASK_OCCLUDER)]
        if len(occ):
            assert occ.max() < obj.min()
        n_occluder += len(occ)
    assert (n_scene > 0) == (scene != "none") and (n_occluder > 0) == (occluders > 0)
    assert ("scene" in attrs) == (scene != "none") and ("occluders" in attrs) == (occluders > 0)


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_occlusion_labels_match_a_render_of_the_object_alone(context_root, setting):
    """unoccluded_pixels equals the pixel counts of the object rebuilt alone from its stored
    sample (no scene, no occluders); visible_fraction is the ratio and within the bound."""
    fractions = []
    for obj_class in CLASSES:
        split = context_root / setting / obj_class.name / "train"
        manifest, a, K, _ = _read(split, ("object_pose", "object_yaw", "q", "visible_pixels", "mask") + OCCLUSION_FIELDS)
        config = GenerationConfig.from_dict(manifest["config"])
        J = obj_class.n_joints
        for k in range(2):
            rows = slice(16 * k, 16 * k + 16)
            if config.camera.mount == "head":  # the sample as rendered, with its level-frame pose and views
                _, sample, _ = render_object(object_sample(config, k), config, process_renderer(config.camera))
            else:
                sample = stored_sample(config, k, a["object_pose"][rows][0], float(a["object_yaw"][rows][0]))
            alone = GenerationConfig(obj_class.name, n_objects=2, camera=config.camera)
            for i in (0, 7, 15):
                _, model, data, info, _ = compile_object(alone, sample, image=i)
                _, alone_mask = render_at(config, model, data, info, a["q"][rows][i].astype(np.float64))
                assert np.array_equal(visible_pixels(alone_mask, J), a["unoccluded_pixels"][rows][i])
        assert np.all(a["unoccluded_pixels"] >= a["visible_pixels"])
        assert np.array_equal(a["visible_fraction"], visible_fraction(a["visible_pixels"], a["unoccluded_pixels"]))
        assert a["visible_fraction"][:, 1:].min() >= VISIBLE_FRACTION_RANGE[0]
        fractions.append(a["visible_fraction"][:, 1:].ravel())
    fractions = np.concatenate(fractions)
    if SETTINGS[setting][1]:  # occluders really hide parts of the moving parts
        assert np.mean(fractions < 0.9) > 0.3
    assert fractions.max() <= 1.0


def test_splits_verify_and_tampered_occlusion_labels_fail(context_root, tmp_path):
    for key in SETTINGS:
        for c in CLASSES:
            report = verify_split(context_root / key / c.name / "train")
            assert report.ok, (key, c.name, report.problems)
    # negative controls: a wrong fraction, and an occluder code in a split without occluders
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(context_root / "room+2" / "drawer" / "train", bad)
    with h5py.File(bad / "shard-00000.h5", "r+") as f:
        f["visible_fraction"][0, 1] = 0.99 if f["visible_fraction"][0, 1] < 0.9 else 0.5
    problems = " ".join(str(p) for p in verify_split(bad).problems)
    assert "visible_fraction" in problems
    bad2 = tmp_path / "bad2"
    shutil.copytree(context_root / "kitchen" / "drawer" / "train", bad2)
    with h5py.File(bad2 / "shard-00000.h5", "r+") as f:
        m = f["mask"][0]
        m[0, 0] = MASK_OCCLUDER
        f["mask"][0] = m
    assert "mask: values above" in " ".join(str(p) for p in verify_split(bad2).problems)


@pytest.mark.slow
def test_same_objects_same_bytes_any_workers_and_shards(tmp_path):
    """The scene and occluder streams are the object's own: bytes independent of the shard
    layout and the worker count; the objects (geometry, q, x, y, yaw) are the default's."""
    kw = dict(class_name="cabinet2", n_objects=3, scene="kitchen", occluders=2)
    a = generate_split(GenerationConfig(**kw, objects_per_shard=1), tmp_path / "a", workers=1)
    b = generate_split(GenerationConfig(**kw, objects_per_shard=1), tmp_path / "b", workers=2)
    c = generate_split(GenerationConfig(**kw, objects_per_shard=3), tmp_path / "c", workers=1)
    assert [s["sha256"] for s in read_manifest(a)["shards"]] == [s["sha256"] for s in read_manifest(b)["shards"]]
    plain = generate_split(GenerationConfig("cabinet2", n_objects=3, objects_per_shard=3), tmp_path / "plain")
    _, ma, _, _ = _read(a, ("depth", "mask", "geometry", "q", "object_pose", "object_yaw") + OCCLUSION_FIELDS)
    _, mc, _, _ = _read(c, ("depth", "mask", "geometry", "q", "object_pose", "object_yaw") + OCCLUSION_FIELDS)
    for k in ma:
        assert np.array_equal(ma[k], mc[k]), k
    _, p, _, _ = _read(plain, ("geometry", "q", "object_pose", "object_yaw"))
    assert np.array_equal(ma["geometry"], p["geometry"]) and np.array_equal(ma["q"], p["q"])
    # x, y and yaw as drawn; the base height is redrawn only where the floor would be above the camera
    assert np.allclose(ma["object_pose"][:, :2], p["object_pose"][:, :2], atol=1e-6)
    assert np.allclose(ma["object_yaw"], p["object_yaw"], atol=1e-6)
    other = generate_split(GenerationConfig(**kw, objects_per_shard=3, seed=5), tmp_path / "seed5")
    _, o, _, _ = _read(other, ("geometry",))
    assert not np.array_equal(o["geometry"], ma["geometry"])


def test_placement_keeps_the_camera_above_the_floor_and_outside_the_scene():
    rng = np.random.default_rng(0)
    geometry = {"depth_m": 0.6, "width_m": 1.0, "height_m": 1.2}
    for scene in ("kitchen", "room"):
        for name in ("cabinet", "drawer", "microwave", "refrigerator"):
            for z in (-1.4, -0.5, 0.0, 0.3):
                placed = scene_layout(scene, name, {"x_m": 1.0, "y_m": 0.0, "z_m": z, "yaw_rad": 0.3}, geometry,
                                      (-1.5, 0.3), rng)
                assert placed is not None
                pose, boxes = placed
                floor = next(b for b in boxes if b.name == "scene_floor")
                floor_z = floor.centre[2] + floor.half[2]  # the floor's top, object frame
                assert pose["z_m"] + floor_z <= -MIN_CAMERA_HEIGHT_M + 1e-9
                assert pose["z_m"] == z or z + floor_z > -MIN_CAMERA_HEIGHT_M  # kept where possible
                assert -1.5 <= pose["z_m"] <= 0.3  # within the table's range
    # a table whose whole height range puts the floor above the camera has no layout
    assert scene_layout("room", "cabinet", {"x_m": 1.0, "y_m": 0.0, "z_m": 0.2, "yaw_rad": 0.0}, geometry,
                        (0.1, 0.3), rng) is None
    boxes, floor = layout_boxes("kitchen", "cabinet", geometry, {"wall_gap_m": 0.0, "counter_height_m": 0.9,
                                "counter_thickness_m": 0.04, "counter_overhang_m": 0.02, "counter_depth_m": 0.6,
                                "left_m": 0.5, "right_m": 0.5})
    assert floor == 0.0 and {b.name for b in boxes} >= {"scene_counter_top", "scene_left_unit", "scene_right_unit",
                                                        "scene_floor", "scene_wall"}


def test_with_the_head_camera_the_robot_stands_on_the_scene_floor():
    """The head camera's level frame is :func:`mid_height_m` above the scene's floor whatever the
    table's height: the base sits on its support, and each image's camera height (drawn in
    HEAD_HEIGHT_M) is then its height above that floor."""
    rng = np.random.default_rng(1)
    geometry = {"depth_m": 0.5, "width_m": 0.6, "height_m": 0.4}
    for scene in ("kitchen", "room"):
        for name in ("cabinet", "drawer", "microwave", "refrigerator"):
            for z in (-1.4, 0.3):
                pose, boxes = scene_layout(scene, name, {"x_m": 1.5, "y_m": 0.0, "z_m": z, "yaw_rad": 0.2}, geometry,
                                           (-1.5, 0.3), rng, head=True)
                floor = next(b for b in boxes if b.name == "scene_floor")
                floor_z = floor.centre[2] + floor.half[2]
                assert pose["z_m"] + floor_z == pytest.approx(-mid_height_m())
                assert 0.0 <= -floor_z <= MAX_SUPPORT_HEIGHT_M
    assert HEAD_HEIGHT_M[0] < mid_height_m() < HEAD_HEIGHT_M[1]


# --------------------------------------------------------------------------------------
# CLI, format, show
# --------------------------------------------------------------------------------------

def test_cli_records_scene_and_occluders_in_manifest_and_shards(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "toaster", "--n", "2", "--images", "2", "--out", str(tmp_path),
                                  "-q", "--workers", "1", "--scene", "kitchen", "--occluders", "2"])
    assert r.exit_code == 0, r.output
    split = tmp_path / "toaster" / "train"
    m = read_manifest(split)
    assert (m["config"]["scene"], m["config"]["occluders"], m["format_version"]) == ("kitchen", 2, CONTEXT_FORMAT_VERSION)
    _, shards = open_split(split)
    attrs = shards[0].attrs
    assert attrs["format_version"] == CONTEXT_FORMAT_VERSION
    assert json.loads(attrs["scene"])["placement"] == "on_counter" and json.loads(attrs["occluders"])["n"] == 2
    assert shards[0].read("visible_fraction").shape == (4, 2)
    shards[0].close()
    assert SplitConfig.from_dict(m["config"]).scene == "kitchen"
    r = CliRunner().invoke(main, ["verify", str(split)])
    assert r.exit_code == 0, r.output
    # --resume of the same command is accepted, a different --occluders is refused
    r = CliRunner().invoke(main, ["generate", "--class", "toaster", "--n", "2", "--images", "2", "--out", str(tmp_path),
                                  "-q", "--workers", "1", "--scene", "kitchen", "--occluders", "2", "--resume"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["generate", "--class", "toaster", "--n", "2", "--images", "2", "--out", str(tmp_path),
                                  "-q", "--workers", "1", "--scene", "kitchen", "--occluders", "1", "--resume"])
    assert r.exit_code == 2 and "different settings" in r.output
    # the default split is as it was: no new keys, no optional fields, format 1.0
    r = CliRunner().invoke(main, ["generate", "--class", "toaster", "--n", "1", "--images", "2", "--out", str(tmp_path),
                                  "-q", "--workers", "1", "--split", "plain"])
    assert r.exit_code == 0, r.output
    m = read_manifest(tmp_path / "toaster" / "plain")
    assert "scene" not in m["config"] and "occluders" not in m["config"] and m["format_version"] == "1.0"
    _, shards = open_split(tmp_path / "toaster" / "plain")
    assert "scene" not in shards[0].attrs and "visible_fraction" not in shards[0].file
    shards[0].close()


@pytest.mark.parametrize("args", [
    ["--occluders", "-1"],
    ["--occluders", "9"],
    ["--occluders", "two"],
    ["--scene", "garden"],
    ["--scene", ""],
    ["--scene", "kitchen", "--mean"],
    ["--occluders", "1", "--mean"],
    ["--scene", "kitchen", "--framing", "whole"],
    ["--occluders", "2", "--camera", "head", "--framing", "whole"],
])
def test_cli_refuses_bad_scene_options_in_one_line(tmp_path, args):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--out", str(tmp_path), "-q", *args])
    assert_one_line_error(r)
    assert not any(tmp_path.iterdir())


def test_config_refuses_occluder_counts_and_scenes_of_the_wrong_type():
    from articulated_dataset.core.errors import UserError

    for kw in ({"occluders": True}, {"occluders": 1.5}, {"occluders": "2"}, {"scene": None}, {"scene": "Kitchen"}):
        with pytest.raises(UserError):
            GenerationConfig("drawer", n_objects=1, **kw)


@pytest.mark.slow
def test_show_draws_scene_and_occluder_pixels_in_their_own_colours(context_root, tmp_path):
    mask = np.array([[0, 1, 2, MASK_SCENE, MASK_OCCLUDER]], np.uint8)
    depth = np.array([[0.0, 1.0, 1.0, 2.0, 0.5]], np.float32)
    rgb = np.full((1, 5, 3), 0.5)
    out = tint_context(rgb, mask)
    assert np.allclose(out[0, :3], 0.5) and np.allclose(out[0, 3], SCENE_SHOW_RGB) and np.allclose(out[0, 4], OCCLUDER_SHOW_RGB)
    assert np.array_equal(object_depth(depth, mask), [[0.0, 1.0, 1.0, 0.0, 0.0]])
    png = tmp_path / "g.png"
    r = CliRunner().invoke(main, ["show", str(context_root / "room+2" / "cabinet" / "train"), "--out", str(png)])
    assert r.exit_code == 0, r.output
    assert png.stat().st_size > 10_000


def test_docs_state_the_ranges_the_code_uses():
    """docs/generation.md and DATASHEET.md quote the scene and occluder ranges and the bound
    as the modules define them, and hold the same counts table."""

    from articulated_dataset.format.manifest import MAX_OCCLUDERS
    from articulated_dataset.generation.occluders import OCCLUDER_TABLE
    from articulated_dataset.generation.scenes import CAMERA_CLEARANCE_M, MAX_LAYOUT_TRIES, SCENE_TABLE

    root = ROOT
    gen, sheet = (root / "docs" / "generation.md").read_text(), (root / "DATASHEET.md").read_text()
    cm = lambda key: "{:g}-{:g} cm".format(*(round(100 * v, 1) for v in SCENE_TABLE[key]))  # noqa: E731
    for key in ("counter_height_m", "sideboard_height_m", "chest_base_m", "counter_thickness_m", "counter_overhang_m",
                "neighbour_width_m", "counter_depth_m", "wall_gap_m"):
        assert cm(key) in gen, (key, cm(key))
    occ = lambda key: "{:g}-{:g}".format(*(round(100 * v, 1) for v in OCCLUDER_TABLE[key]))  # noqa: E731
    assert f"half sizes {occ('half_size_m')} cm" in gen and f"links {occ('arm_link_length_m')} cm" in gen
    assert f"at {occ('depth_fraction')}% of the depth" in gen
    assert f"at most {OCCLUDER_TABLE['max_tries']} draws" in gen and f"(0-{MAX_OCCLUDERS})" in gen
    assert f"at least {VISIBLE_FRACTION_RANGE[0] * 100:g}% of its pixels" in gen and f">= {VISIBLE_FRACTION_RANGE[0]:g}" in sheet
    assert f"{MIN_CAMERA_HEIGHT_M * 100:g} cm above the floor and {CAMERA_CLEARANCE_M * 100:g} cm clear" in gen
    assert f"at most {MAX_LAYOUT_TRIES} times" in gen
    table = [line for line in gen.splitlines() if line.startswith("| cabinet | 1.00 (")]
    assert len(table) == 1 and table[0] in sheet


def test_the_most_occluders_and_a_third_party_urdf(tmp_path):
    """--occluders 8 (the most) still leaves every moving part identifiable (draws shrink);
    a --urdf object takes occluders (not a scene) and its split verifies."""
    from articulated_dataset.format.manifest import MAX_OCCLUDERS
    from helpers_core import write_flap_urdf

    split = generate_split(GenerationConfig("toaster", n_objects=2, images_per_object=4, occluders=MAX_OCCLUDERS,
                                            scene="kitchen"), tmp_path / "most")
    assert verify_split(split).ok
    _, a, _, _ = _read(split, ("visible_fraction", "mask"))
    assert a["visible_fraction"][:, 1:].min() >= VISIBLE_FRACTION_RANGE[0] and (a["mask"] == MASK_OCCLUDER).any()
    urdf = write_flap_urdf(tmp_path / "urdf")
    out = tmp_path / "tp"
    r = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--n", "2", "--images", "4", "--out", str(out), "-q",
                                  "--workers", "1", "--occluders", "2"])
    assert r.exit_code == 0, r.output
    (split,) = [p.parent for p in out.glob("*/train/manifest.json")]
    report = verify_split(split)
    assert report.ok, report.problems
    _, a, _, _ = _read(split, ("visible_fraction", "mask"))
    assert (a["mask"] == MASK_OCCLUDER).any() and a["visible_fraction"][:, 1:].min() >= VISIBLE_FRACTION_RANGE[0]
    r = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--n", "1", "--out", str(tmp_path / "tp2"), "-q",
                                  "--scene", "room"])
    assert_one_line_error(r)


@pytest.mark.parametrize("option", [["--scene", "room"], ["--scene", "kitchen"], ["--occluders", "1"]],
                         ids=lambda o: "".join(o).lstrip("-"))
@pytest.mark.slow
def test_cli_each_option_same_bytes_with_one_or_two_workers(tmp_path, option):
    runs = []
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}"
        r = CliRunner().invoke(main, ["generate", "--class", "cabinet2", "--n", "2", "--images", "4", "--objects-per-shard",
                                      "1", "--out", str(out), "-q", "--workers", workers, *option])
        assert r.exit_code == 0, r.output
        runs.append(read_manifest(out / "cabinet2" / "train"))
        r = CliRunner().invoke(main, ["verify", str(out / "cabinet2" / "train"), "-q"])
        assert r.exit_code == 0, r.output
    assert [s["sha256"] for s in runs[0]["shards"]] == [s["sha256"] for s in runs[1]["shards"]]
    key, value = option[0].lstrip("-"), option[1]
    assert str(runs[0]["config"][key]) == value and runs[0]["format_version"] == CONTEXT_FORMAT_VERSION
