"""Colour images (RGB-D): ``generate --rgb``.

An --rgb split must hold exactly the depth, mask and labels of the same split without it,
plus colour images whose object pixels are exactly the pixels the depth has; for every class,
with a scene and occluders and with the head camera; seeded (any workers), recorded only
when used, verifiable, exported and served by the loaders.
"""

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes
from articulated_dataset.cli import main
from articulated_dataset.format import open_split, read_manifest
from articulated_dataset.format.manifest import SplitConfig
from articulated_dataset.format.schema import RGB_FORMAT_VERSION
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.generation.appearance import APPEARANCE_TABLE
from helpers_core import ROOT

CLASSES = all_classes()


def _shards(split_dir):
    manifest = read_manifest(split_dir)
    return manifest, [split_dir / r["file"] for r in manifest["shards"]]


def _check_colour_covers_exactly_the_depth(rgb, depth):
    """RGB non-background (not (0, 0, 0)) exactly where the depth hit something."""
    assert rgb.dtype == np.uint8 and rgb.shape == depth.shape + (3,)
    lit = rgb.max(axis=-1) > 0
    hit = depth > 0
    assert hit.any()
    assert np.array_equal(lit, hit), f"{int((lit != hit).sum())} pixels differ"
    return int(hit.sum())


def test_rgb_split_is_the_depth_split_plus_colour(tmp_path):
    """Same datasets and attributes as without --rgb (bar format_version and appearance);
    colour exactly where depth; the negative control: a shifted image fails the check."""
    kw = dict(class_name="microwave", n_objects=3, images_per_object=4, objects_per_shard=2)
    a = generate_split(GenerationConfig(**kw, rgb=True), tmp_path / "rgb", workers=1)
    b = generate_split(GenerationConfig(**kw), tmp_path / "plain", workers=1)
    ma, fa = _shards(a)
    mb, fb = _shards(b)
    assert ma["format_version"] == RGB_FORMAT_VERSION and mb["format_version"] == "1.0"
    assert ma["config"].pop("rgb") is True and "rgb" not in mb["config"]
    ma["config"].pop("format_version"), mb["config"].pop("format_version")
    assert ma["config"] == mb["config"]
    for pa, pb in zip(fa, fb):
        with h5py.File(pa) as x, h5py.File(pb) as y:
            assert set(x) - set(y) == {"rgb"}
            for k in y:
                assert np.array_equal(x[k][()], y[k][()]), k
            assert set(x.attrs) - set(y.attrs) == {"appearance"}
            for k in y.attrs:
                if k != "format_version":
                    assert str(x.attrs[k]) == str(y.attrs[k]), k
            assert json.loads(x.attrs["appearance"])["ranges"]["ambient"] == list(APPEARANCE_TABLE["ambient"])
            rgb, depth = x["rgb"][()], x["depth"][()]
            assert x["rgb"].chunks == (1,) + rgb.shape[1:]
            for i in range(len(depth)):
                _check_colour_covers_exactly_the_depth(rgb[i], depth[i])
            with pytest.raises(AssertionError):  # the check can fail
                _check_colour_covers_exactly_the_depth(np.roll(rgb[0], 3, axis=1), depth[0])
    # randomised: the colours differ between objects and between an object's images (lights)
    with h5py.File(fa[0]) as x:
        rgb, mask = x["rgb"][()], x["mask"][()]
    body = [rgb[i][mask[i] == 1].mean(axis=0) for i in range(len(rgb))]
    assert len({tuple(np.round(c)) for c in body}) > len(body) // 2


@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_every_class_with_scene_and_occluders(tmp_path, obj_class):
    split = generate_split(GenerationConfig(obj_class.name, n_objects=1, images_per_object=3, scene="kitchen",
                                            occluders=2, rgb=True), tmp_path, workers=1)
    _, files = _shards(split)
    with h5py.File(files[0]) as f:
        rgb, depth, mask = f["rgb"][()], f["depth"][()], f["mask"][()]
        assert "visible_fraction" in f and f.attrs["format_version"] == RGB_FORMAT_VERSION
    for i in range(len(depth)):
        _check_colour_covers_exactly_the_depth(rgb[i], depth[i])
    # the scene and the occluders have colour too, and the whole image is covered by the scene
    assert (rgb[mask >= 254].max(axis=-1) > 0).all()


def test_head_camera_and_plain_every_class_in_one_shard(tmp_path):
    for c in CLASSES:
        split = generate_split(GenerationConfig(c.name, n_objects=1, images_per_object=2, rgb=True,
                                                camera=GenerationConfig(c.name).camera.__class__(mount="head")),
                               tmp_path / c.name, workers=1)
        _, files = _shards(split)
        with h5py.File(files[0]) as f:
            for i in range(2):
                _check_colour_covers_exactly_the_depth(f["rgb"][i], f["depth"][i])


def test_same_bytes_any_workers(tmp_path):
    kw = dict(class_name="drawer", n_objects=3, images_per_object=2, objects_per_shard=1, rgb=True)
    a = generate_split(GenerationConfig(**kw), tmp_path / "a", workers=1)
    b = generate_split(GenerationConfig(**kw), tmp_path / "b", workers=2)
    assert [s["sha256"] for s in read_manifest(a)["shards"]] == [s["sha256"] for s in read_manifest(b)["shards"]]
    c = generate_split(GenerationConfig(**kw, seed=1), tmp_path / "c", workers=1)
    with h5py.File(_shards(a)[1][0]) as x, h5py.File(_shards(c)[1][0]) as y:
        assert not np.array_equal(x["rgb"][()], y["rgb"][()])


def test_cli_records_rgb_verifies_and_refuses_mismatched_resume(tmp_path):
    args = ["generate", "--class", "toaster", "--n", "2", "--images", "2", "--out", str(tmp_path), "-q", "--workers", "1"]
    r = CliRunner().invoke(main, args + ["--rgb"])
    assert r.exit_code == 0, r.output
    split = tmp_path / "toaster" / "train"
    m = read_manifest(split)
    assert m["config"]["rgb"] is True and SplitConfig.from_dict(m["config"]).rgb is True
    _, shards = open_split(split)
    assert shards[0].read("rgb").shape == (4, 108, 192, 3)
    shards[0].close()
    r = CliRunner().invoke(main, ["verify", str(split)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, args + ["--rgb", "--resume"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, args + ["--resume"])
    assert r.exit_code == 2 and "different settings" in r.output and len(r.output.strip().splitlines()) == 1


def test_config_refuses_an_rgb_flag_that_is_not_a_boolean():
    from articulated_dataset.core.errors import UserError

    for v in (1, "yes", None):
        with pytest.raises(UserError):
            GenerationConfig("drawer", n_objects=1, rgb=v)


@pytest.fixture(scope="module")
def rgb_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("rgb")
    return generate_split(GenerationConfig("cabinet", n_objects=2, images_per_object=3, objects_per_shard=1, rgb=True), root)


def test_loaders_serve_rgb_only_where_every_split_has_it(rgb_split, tmp_path):
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.training.loaders.reader import DEFAULT_FIELDS, ShardReader

    r = ShardReader(rgb_split)
    assert r.fields == DEFAULT_FIELDS + ("rgb",)
    b = r.get_batch([4, 0, 5])
    _, files = _shards(rgb_split)
    with h5py.File(files[0]) as f0, h5py.File(files[1]) as f1:
        want = np.stack([f1["rgb"][1], f0["rgb"][0], f1["rgb"][2]])
    assert b["rgb"].dtype == np.uint8 and np.array_equal(b["rgb"], want)
    plain = generate_split(GenerationConfig("cabinet", n_objects=1, images_per_object=2), tmp_path)
    assert "rgb" not in ShardReader(plain).fields and "rgb" not in ShardReader([rgb_split, plain]).fields
    with pytest.raises(UserError, match="no 'rgb' images"):
        ShardReader([rgb_split, plain], fields=["depth", "rgb"])
    # a crop cuts the colour image with the depth
    from articulated_dataset.training.transforms import Crop, apply_to_batch

    out = apply_to_batch(Crop(10, 20, 50, 60), r.get_batch([1, 2], fields=["depth", "rgb"]), np.array([1, 2]), seed=0, epoch=0)
    assert out["rgb"].shape == (2, 50, 60, 3) and np.array_equal(out["rgb"][0], r[1]["rgb"][10:60, 20:80])
    torch = pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import make_loader

    batch = next(iter(make_loader(rgb_split, batch_size=2, shuffle=False, num_workers=0)))
    assert isinstance(batch["rgb"], torch.Tensor) and tuple(batch["rgb"].shape) == (2, 108, 192, 3)


def test_jax_loader_serves_rgb(rgb_split):
    pytest.importorskip("jax")
    from articulated_dataset.training.loaders.jax import JaxLoader

    batch = next(iter(JaxLoader(rgb_split, batch_size=2, shuffle=False)))
    assert tuple(batch["rgb"].shape) == (2, 108, 192, 3)


def test_verify_catches_colour_that_does_not_match_the_depth(rgb_split, tmp_path):
    import shutil

    from articulated_dataset.tools.verify import verify_split

    bad = tmp_path / "bad"
    shutil.copytree(rgb_split, bad)
    _, files = _shards(bad)
    with h5py.File(files[1], "r+") as f:
        a = f["rgb"][()]
        a[0] = np.roll(a[0], 5, axis=1)
        f["rgb"][...] = a
    report = verify_split(bad, content=True)
    assert not report.ok and "rgb/depth" in str(report.problems)
    assert verify_split(rgb_split, content=True).ok
    with h5py.File(files[0], "r+") as f:
        del f["rgb"]
    assert "missing dataset 'rgb'" in str(verify_split(bad, content=True).problems)
    with h5py.File(files[0], "r+") as f:
        del f.attrs["appearance"]
    problems = str(verify_split(bad, content=True).problems)
    assert "missing dataset 'rgb'" not in problems and "config has rgb = true but the shard has no attribute" in problems


def test_export_writes_rgb_png_and_import_restores_the_split(rgb_split, tmp_path):
    from PIL import Image

    r = CliRunner().invoke(main, ["export", str(rgb_split), str(tmp_path / "exr"), "-q"])
    assert r.exit_code == 0, r.output
    pngs = sorted((tmp_path / "exr").rglob("*.rgb.png"))
    assert len(pngs) == 6
    _, files = _shards(rgb_split)
    with h5py.File(files[0]) as f:
        first = f["rgb"][0]
    with Image.open(pngs[0]) as im:
        assert im.mode == "RGB" and np.array_equal(np.asarray(im), first)
    r = CliRunner().invoke(main, ["import-exr", str(tmp_path / "exr"), "--out", str(tmp_path / "back"), "-q"])
    assert r.exit_code == 0, r.output
    back = next((tmp_path / "back").rglob("manifest.json")).parent
    for a, b in zip(_shards(rgb_split)[1], _shards(back)[1]):
        with h5py.File(a) as x, h5py.File(b) as y:
            assert np.array_equal(x["rgb"][()], y["rgb"][()])


def test_show_draws_the_stored_colour_panel(rgb_split, tmp_path):
    from articulated_dataset.tools.viz import make_gallery

    panels = make_gallery([rgb_split], out=tmp_path / "g.png", n=2, cols=2)
    assert sorted(p.kind for p in panels) == ["depth", "depth", "rgb", "rgb"]


def test_third_party_urdf_and_mean_object(tmp_path):
    """A --urdf object (its own rendering context for its assets) and the mean object take --rgb."""
    from articulated_dataset.tools.verify import verify_split
    from helpers_core import write_flap_urdf

    urdf = write_flap_urdf(tmp_path / "urdf")
    out = tmp_path / "tp"
    r = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--n", "1", "--images", "3", "--out", str(out), "-q",
                                  "--workers", "1", "--rgb", "--occluders", "1"])
    assert r.exit_code == 0, r.output
    (split,) = [p.parent for p in out.glob("*/train/manifest.json")]
    report = verify_split(split)
    assert report.ok, report.problems
    with h5py.File(_shards(split)[1][0]) as f:
        for i in range(3):
            _check_colour_covers_exactly_the_depth(f["rgb"][i], f["depth"][i])
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--mean", "--images", "2", "--out", str(tmp_path / "m"),
                                  "-q", "--workers", "1", "--rgb"])
    assert r.exit_code == 0, r.output
    assert verify_split(tmp_path / "m" / "drawer" / "mean").ok


def test_docs_state_the_ranges_the_code_uses():

    from articulated_dataset.generation.appearance import SHADOW_SIZE_PX, TEXTURES

    root = ROOT
    gen = (root / "docs" / "generation.md").read_text()
    t = APPEARANCE_TABLE
    r = lambda key: "{:g}-{:g}".format(*t[key])  # noqa: E731
    assert f"each channel {t['material_rgb'][0]:g}-{t['material_rgb'][1]:.1f}" in gen
    assert f"| {r('specular')}, {r('shininess')}, {r('reflectance')} |" in gen
    assert f"{t['texture_probability'] * 100:g}%: one of {['', 'one', 'two', 'three', 'four'][len(TEXTURES)]} grey" in gen
    assert f"from {r('key_light_elevation_deg')} deg above the camera" in gen
    assert "-{:g}..{:g} deg".format(-t["key_light_azimuth_deg"][0], t["key_light_azimuth_deg"][1]) in gen
    assert f"intensity {r('key_light_intensity')} |" in gen and f"intensity {r('fill_light_intensity')} |" in gen
    (x, y, z) = t["fill_light_pos_m"]
    assert f"at x {x[0]:g}..{x[1]:.1f} m, y {y[0]:g}..{y[1]:g} m, z {z[0]:g}..{z[1]:g} m" in gen
    assert f"each channel {r('light_rgb')}" in gen and f"grey {r('ambient')} |" in gen
    assert f"{SHADOW_SIZE_PX} px" in gen
