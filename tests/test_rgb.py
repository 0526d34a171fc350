"""Colour images (issue 18, RGB-D): ``generate --rgb``.

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

from articulated_dataset.cli import main
from articulated_dataset.format.manifest import SplitConfig
from articulated_dataset.format.schema import RGB_FORMAT_VERSION
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.generation.appearance import APPEARANCE_TABLE
from articulated_dataset.registry import all_classes
from articulated_dataset.shards import open_split, read_manifest

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


def test_config_refuses_hostile_values():
    from articulated_dataset.errors import UserError

    for v in (1, "yes", None):
        with pytest.raises(UserError):
            GenerationConfig("drawer", n_objects=1, rgb=v)
