"""``artdata generate --framing``: ``whole`` keeps every object pixel off the image's border in
every image (the paper's "view frustum" sentence), its depth range reaches only as far as the
object's size needs, labels still explain the pixels, the manifest and ``info`` say so; the
default ``table4`` is the data it always was."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes
from articulated_dataset.cli import main
from articulated_dataset.core.camera import project
from articulated_dataset.format import MASK_BODY, MASK_FIRST_PART, object_on_border, open_split, read_manifest
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample, pipeline
from articulated_dataset.generation import framing as framing_module
from articulated_dataset.generation.framing import (
    FRAMING_DEPTH_MARGIN_M,
    Framing,
    extent_points,
    fit_depth_m,
    framed_table,
    in_view,
)
from articulated_dataset.generation.render import process_renderer
from articulated_dataset.generation.sampling import sample_pose
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.tools.verify import verify_split
from helpers_core import IMAGE_CHECK_FIELDS, assert_one_line_error, check_stored_images, write_flap_urdf

CLASSES = all_classes()
#: Objects and images per class of the framed splits (small: the rule holds per image).
N_OBJECTS = 2
N_IMAGES = 4


def _framed(class_name: str, **settings) -> GenerationConfig:
    """A small ``--framing whole`` test split of ``class_name`` (``settings`` replace the sizes)."""
    sizes = {"n_objects": N_OBJECTS, "images_per_object": N_IMAGES, "objects_per_shard": N_OBJECTS}
    return GenerationConfig(class_name, split="test", framing="whole", **{**sizes, **settings})


@pytest.fixture(scope="module")
def whole_root(tmp_path_factory):
    """``root/<class>/test``: 2 objects x 4 images of every class with ``--framing whole``."""
    root = tmp_path_factory.mktemp("whole")
    for c in CLASSES:
        generate_split(_framed(c.name), root)
    return root


def _object_on_edge(mask: np.ndarray, n_joints: int) -> np.ndarray:
    """Per image: a body or part pixel (codes 1 .. 1 + J) on row 0, row H-1, column 0 or column W-1."""
    obj = (mask >= MASK_BODY) & (mask < MASK_FIRST_PART + n_joints)
    edges = np.concatenate([obj[:, 0, :], obj[:, -1, :], obj[:, :, 0], obj[:, :, -1]], axis=1)
    return edges.any(axis=1)


@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_whole_framing_keeps_every_object_pixel_off_the_border(whole_root, obj_class):
    manifest, shards = open_split(whole_root / obj_class.name / "test")
    mask = np.concatenate([sh.read("mask") for sh in shards])
    assert mask.shape[0] == N_OBJECTS * N_IMAGES
    assert (mask >= MASK_BODY).any(axis=(1, 2)).all()  # the object is in every image
    assert not _object_on_edge(mask, obj_class.n_joints).any()
    assert not object_on_border(mask).any()


def test_the_default_framing_cuts_tall_objects_off():
    """The check above can fail: Table 4's ranges put a metre-high cabinet's pixels on the border."""
    config = GenerationConfig("cabinet", split="test", n_objects=N_OBJECTS, images_per_object=N_IMAGES)
    renderer = process_renderer(config.camera)
    masks = [pipeline.render_object(object_sample(config, k), config, renderer)[0]["mask"] for k in range(N_OBJECTS)]
    on_edge = _object_on_edge(np.concatenate(masks), 1)
    assert on_edge.any()
    assert np.array_equal(on_edge, object_on_border(np.concatenate(masks)))


def test_default_framing_is_byte_identical_to_no_option(tmp_path):
    base = ["generate", "--class", "drawer", "--n", "2", "--images", "2", "--objects-per-shard", "1", "-q"]
    for out, extra in (("a", []), ("b", ["--framing", "table4"])):
        r = CliRunner().invoke(main, base + ["--out", str(tmp_path / out)] + extra)
        assert r.exit_code == 0, r.output
    a, b = (tmp_path / x / "drawer" / "train" for x in "ab")
    assert (a / "manifest.json").read_bytes() == (b / "manifest.json").read_bytes()
    for s in read_manifest(a)["shards"]:
        assert (a / s["file"]).read_bytes() == (b / s["file"]).read_bytes()
        with h5py.File(a / s["file"], "r") as f:
            assert "framing" not in f.attrs
    assert "framing" not in read_manifest(a)["config"]
    assert "framing" not in GenerationConfig("drawer").to_dict()


def test_manifest_records_the_framing_and_info_shows_it(whole_root, tmp_path):
    split_dir = whole_root / "cabinet" / "test"
    manifest = read_manifest(split_dir)
    assert manifest["config"]["framing"] == "whole"
    assert GenerationConfig.from_dict(manifest["config"]) == _framed("cabinet")
    _, shards = open_split(split_dir)
    record = json.loads(shards[0].attrs["framing"])
    assert record == {"framing": "whole", "depth_margin_m": FRAMING_DEPTH_MARGIN_M, "border_px": 1.0}
    r = CliRunner().invoke(main, ["info", str(split_dir)])
    assert r.exit_code == 0 and "  framing whole" in r.output.splitlines(), r.output
    r = CliRunner().invoke(main, ["info", str(split_dir), "--json"])
    assert json.loads(r.output)[0]["framing"] == "whole"
    default = generate_split(GenerationConfig("toaster", n_objects=1, images_per_object=1), tmp_path)
    r = CliRunner().invoke(main, ["info", str(default)])
    assert r.exit_code == 0 and "framing" not in r.output
    assert json.loads(CliRunner().invoke(main, ["info", str(default), "--json"]).output)[0]["framing"] == "table4"


def test_resume_keeps_the_framing_apart(tmp_path):
    args = ["generate", "--class", "toaster", "--n", "1", "--images", "1", "--out", str(tmp_path), "-q"]
    assert CliRunner().invoke(main, args + ["--framing", "whole"]).exit_code == 0
    assert CliRunner().invoke(main, args + ["--framing", "whole", "--resume"]).exit_code == 0
    assert_one_line_error(CliRunner().invoke(main, args + ["--resume"]), "different settings")


@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_whole_framing_labels_agree_with_pixels(whole_root, obj_class):
    split_dir = whole_root / obj_class.name / "test"
    report = verify_split(split_dir)
    assert report.ok, report.problems
    _, shards = open_split(split_dir)
    a = {k: np.concatenate([sh.read(k) for sh in shards]) for k in IMAGE_CHECK_FIELDS}
    checked, detected, n_body = check_stored_images(obj_class, a, np.asarray(shards[0].K))
    assert n_body > 0 and detected >= 0.9 * checked


def test_whole_framing_reaches_beyond_the_tables_depth_for_tall_objects(whole_root):
    """A cabinet fits only beyond Table 4's 2 m in most draws; verify accepts the extended depth."""
    _, shards = open_split(whole_root / "cabinet" / "test")
    x = np.concatenate([sh.read("object_pose")[:, 0] for sh in shards])
    assert x.max() > GenerationConfig("cabinet").table.pose["x_m"][1]


def test_verify_reports_an_object_pixel_on_a_framed_images_border(whole_root, tmp_path):
    import shutil

    split_dir = shutil.copytree(whole_root / "toaster" / "test", tmp_path / "toaster" / "test")
    shard = split_dir / read_manifest(split_dir)["shards"][0]["file"]
    with h5py.File(shard, "r+") as f:
        mask = f["mask"][()]
        mask[1, 0, 0] = MASK_BODY
        f["mask"][...] = mask
    problems = verify_split(split_dir).problems
    assert any("border" in p.message and "image 1" in p.message for p in problems), problems


def test_verify_reports_a_shard_whose_framing_differs_from_the_manifest(whole_root, tmp_path):
    import shutil

    split_dir = shutil.copytree(whole_root / "cabinet" / "test", tmp_path / "cabinet" / "test")
    shard = split_dir / read_manifest(split_dir)["shards"][0]["file"]
    with h5py.File(shard, "r+") as f:
        del f.attrs["framing"]
    problems = [p.message for p in verify_split(split_dir).problems]
    assert any("attribute framing says 'table4', the manifest's config 'whole'" in p for p in problems), problems
    assert any("object_pose: x outside the table's [1, 2] m" in p for p in problems), problems


def test_fitting_depth_is_the_nearest_depth_that_fits():
    """No pose nearer than the fitting depth keeps the object in view; the extended range does,
    and every point of an accepted pose projects inside the border pixels' centres."""
    config = _framed("cabinet")
    sample = object_sample(config, 0)
    urdf = object_urdf(config.obj_class, sample, config.table)
    points = extent_points(config.obj_class, urdf, sample.q, config.camera)
    fit = fit_depth_m(points, config.table, config.camera)
    table = framed_table(config.table, fit)
    x_lo, x_hi = config.table.pose["x_m"]
    assert table.pose["x_m"] == (x_lo, max(x_hi, fit + FRAMING_DEPTH_MARGIN_M))
    rng = np.random.default_rng(0)
    nearer = [{**sample_pose(rng, config.table), "x_m": float(rng.uniform(0.3, fit - 0.01))} for _ in range(3000)]
    assert not any(in_view(points, pose, config.camera) for pose in nearer)
    framing = Framing.of(points, config.table, config.camera)
    W, H = config.camera.width_px, config.camera.height_px
    for _ in range(5):
        pose, draws = framing.draw(rng)
        assert pose is not None and pose["x_m"] >= fit and draws >= 1
        c, s = np.cos(pose["yaw_rad"]), np.sin(pose["yaw_rad"])
        placed = points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [pose["x_m"], pose["y_m"], pose["z_m"]]
        uv, _ = project(placed, config.camera.K)
        assert uv.min(axis=0).min() >= 0.5 and uv[:, 0].max() <= W - 1.5 and uv[:, 1].max() <= H - 1.5


def test_a_render_on_the_border_is_redrawn(monkeypatch):
    """Without the projection check every framed draw is rendered; the render's own check
    still redraws those with an object pixel on the border."""
    monkeypatch.setattr(framing_module, "in_view", lambda points, pose, camera: True)
    renders = []
    render_images = pipeline.render_images
    monkeypatch.setattr(pipeline, "render_images", lambda *a, **k: renders.append(1) or render_images(*a, **k))
    config = _framed("microwave", n_objects=6)
    renderer = process_renderer(config.camera)
    for k in range(config.n_objects):
        arrays, _, draws = pipeline.render_object(object_sample(config, k), config, renderer)
        assert not object_on_border(arrays["mask"]).any()
        assert draws >= 1
    assert len(renders) > config.n_objects


def test_whole_framing_is_deterministic_and_independent_of_sharding(tmp_path):
    a = generate_split(_framed("cabinet2", images_per_object=2, objects_per_shard=1), tmp_path / "a")
    b = generate_split(_framed("cabinet2", images_per_object=2, objects_per_shard=2), tmp_path / "b")
    c = generate_split(_framed("cabinet2", images_per_object=2, objects_per_shard=1), tmp_path / "c", workers=2)
    depth = [np.concatenate([sh.read("depth") for sh in open_split(d)[1]]) for d in (a, b)]
    assert np.array_equal(*depth)
    assert [s["sha256"] for s in read_manifest(a)["shards"]] == [s["sha256"] for s in read_manifest(c)["shards"]]


def test_a_third_party_object_can_be_framed_whole(tmp_path):
    urdf = write_flap_urdf(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--class-name", "flap", "--n", "2", "--images", "2",
                                  "--framing", "whole", "--out", str(out), "-q"])
    assert r.exit_code == 0, r.output
    split_dir = out / "flap" / "train"
    _, shards = open_split(split_dir)
    assert not object_on_border(np.concatenate([sh.read("mask") for sh in shards])).any()
    assert verify_split(split_dir).ok


@pytest.mark.parametrize("args, needle", [
    (["--camera", "head"], "--camera fixed"),
    (["--scene", "room"], "drop --scene"),
    (["--occluders", "1"], "drop --scene and --occluders"),
    (["--mean"], "drop --framing whole"),
    (["--resolution", "2x2"], "at least 3 x 3 px"),
])
def test_whole_framing_refuses_what_it_cannot_frame(tmp_path, args, needle):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--images", "1", "--framing", "whole",
                                  "--out", str(tmp_path), "-q"] + (["--n", "1"] if "--mean" not in args else []) + args)
    assert_one_line_error(r, needle)
    assert not any(tmp_path.iterdir())


def test_an_unknown_framing_is_refused(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--framing", "frustum", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "frustum" in r.output
