"""``artdata verify``: a clean dataset passes; each kind of damage is reported per shard."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import class_names
from articulated_dataset.cli import main
from articulated_dataset.format import MANIFEST_NAME, sha256_file
from articulated_dataset.tools.verify import check_shard, quat_rotate_z, verify_split
from helpers_core import assert_one_line_error

#: The split every damage test starts from: 6 objects in shards of 4 -> 2 shards, J = 2.
SOURCE = ("cabinet2", "train")


def run_verify(*args):
    result = CliRunner().invoke(main, ["verify", *map(str, args)])
    # never a traceback: click exits through SystemExit, nothing else escapes
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert "Traceback" not in result.output
    return result


@pytest.fixture()
def split(tiny_root, tmp_path):
    """A private copy of one tiny split (the shared fixture is read-only)."""
    dst = tmp_path / SOURCE[0] / SOURCE[1]
    shutil.copytree(tiny_root / SOURCE[0] / SOURCE[1], dst)
    return dst


def rehash(split_dir):
    """Update the manifest's sizes and checksums after editing shards in place, so that
    only the format/content checks can catch the edit."""
    path = split_dir / MANIFEST_NAME
    m = json.loads(path.read_text())
    for rec in m["shards"]:
        f = split_dir / rec["file"]
        rec["bytes"], rec["sha256"] = f.stat().st_size, sha256_file(f)
    path.write_text(json.dumps(m))


def edit(split_dir, shard, fn):
    with h5py.File(split_dir / shard, "r+") as f:
        fn(f)
    rehash(split_dir)


def assert_reported(result, shard, *needles):
    assert result.exit_code == 1, result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip().startswith(shard + ":")]
    assert lines, result.output
    for needle in needles:
        assert any(needle in ln for ln in lines), (needle, result.output)


def test_clean_dataset_verifies(tiny_root):
    result = run_verify(tiny_root, "--workers", "1")
    assert result.exit_code == 0, result.output
    n_splits = 2 * len(class_names())  # train and test of every class
    assert f"all {n_splits} split(s) OK" in result.output
    assert result.output.count(": OK,") == n_splits


def test_clean_split_in_worker_processes_and_json(tiny_root):
    result = run_verify(tiny_root / "refrigerator" / "train", "--workers", "2", "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["ok"] and report["splits"][0]["images"] == 6 * 16 and report["splits"][0]["shards"] == 2


def test_flipped_bytes(split):
    path = split / "shard-00001.h5"
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(b ^ 0xFF for b in data[mid:mid + 64])
    path.write_bytes(bytes(data))
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00001.h5", "sha256")
    assert "shard-00000.h5" not in result.output  # the intact shard is not blamed


def test_truncated_shard(split):
    path = split / "shard-00000.h5"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00000.h5", "truncated", "not a readable HDF5 file")


def test_foreign_hdf5_file(split):
    path = split / "shard-00001.h5"
    path.unlink()
    with h5py.File(path, "w") as f:
        f["images"] = np.zeros((4, 8, 8), np.float32)
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00001.h5", "not an articulated_dataset shard", "sha256")


def test_not_hdf5_at_all(split):
    (split / "shard-00000.h5").write_text("this is not a shard\n")
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00000.h5", "not a readable HDF5 file")


def _scale_axis(f):
    a = f["axis_direction"][()]
    a[3, 1] *= 1.5
    f["axis_direction"][...] = a


def _scale_quaternion(f):
    a = f["axis_pose"][()]
    a[5, 0, 3:] *= 0.9
    f["axis_pose"][...] = a


def _q_beyond_limit(f):
    q = f["q"][()]
    q[7, 1] = np.pi  # the table allows [0, pi/2]
    f["q"][...] = q


def _mask_out_of_range(f):
    m = f["mask"][()]
    m[2, 0, 0] = 9  # J = 2: values 0..3
    f["mask"][...] = m


def _negative_depth(f):
    d = f["depth"][()]
    d[1][d[1] > 0] *= -1
    f["depth"][...] = d


def _nan_origin(f):
    a = f["axis_origin"][()]
    a[0, 0, 0] = np.nan
    f["axis_origin"][...] = a


def _nan_depth(f):
    d = f["depth"][()]
    d[9, 50, 90] = np.nan
    f["depth"][...] = d


def _float64_q(f):
    q = f["q"][()].astype(np.float64)
    del f["q"]
    f["q"] = q


def _wrong_class(f):
    c = f["class"][()]
    c[4] = b"drawer"
    f["class"][...] = c


def _shuffled_ids(f):
    ids = f["sample_id"][()]
    f["sample_id"][...] = ids[::-1]


def _moved_object(f):
    p = f["object_pose"][()]
    p[16:32, 0] = 9.0  # x beyond the table's [1, 2] m, for every image of object 1
    f["object_pose"][...] = p


def _visible_pixels_off(f):
    v = f["visible_pixels"][()]
    v[0, 0] += 1
    f["visible_pixels"][...] = v


@pytest.mark.parametrize("damage, needles", [
    (lambda f: f.__delitem__("q"), ["missing dataset 'q'"]),
    (_scale_axis, ["axis_direction: not unit length", "first: image 3"]),
    (_scale_quaternion, ["axis_pose: quaternion not normalised", "first: image 5"]),
    (_q_beyond_limit, ["q[1]: outside the table's limits", "first: image 7"]),
    (_mask_out_of_range, ["mask: values above 3"]),
    (_negative_depth, ["depth: negative values", "first: image 1"]),
    (_nan_origin, ["axis_origin: non-finite values"]),
    (_nan_depth, ["depth: non-finite values", "first: image 9"]),
    (_float64_q, ["dataset 'q' has dtype float64, expected float32"]),
    (_wrong_class, ["class: differs from the shard's class 'cabinet2'"]),
    (_shuffled_ids, ["sample_id: differs from sample_id(class, split, seed, object, image)"]),
    (_moved_object, ["object_pose: x outside the table's [1, 2] m", "first: image 16"]),
    (_visible_pixels_off, ["visible_pixels: differ from the mask's pixel counts"]),
], ids=["deleted-dataset", "non-unit-axis", "quaternion", "q-limits", "mask", "depth", "nan", "nan-depth", "dtype", "class",
        "sample-id", "pose", "visible-pixels"])
def test_format_and_label_damage(split, damage, needles):
    edit(split, "shard-00001.h5", damage)
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00001.h5", *needles)
    assert "sha256" not in result.output  # rehashed: only the content check can see it
    assert "shard-00000.h5" not in result.output


def test_quick_mode_skips_content_but_not_format(split):
    edit(split, "shard-00000.h5", _scale_axis)
    assert run_verify(split, "--workers", "1", "--quick").exit_code == 0
    edit(split, "shard-00000.h5", lambda f: f.__delitem__("mask"))
    assert_reported(run_verify(split, "--workers", "1", "--quick"), "shard-00000.h5", "missing dataset 'mask'")


def test_sample_id_repeated_across_shards(split):
    with h5py.File(split / "shard-00000.h5", "r") as f:
        ids = f["sample_id"][:32]
    edit(split, "shard-00001.h5", lambda f: f["sample_id"].__setitem__(slice(None), ids))
    result = run_verify(split, "--workers", "1")
    assert result.exit_code == 1
    assert "ids appear in more than one shard of the split" in result.output


def test_corrupt_manifest(split):
    (split / MANIFEST_NAME).write_text('{"format_version": "1.0", "shards": [')
    result = run_verify(split, "--workers", "1")
    assert_reported(result, MANIFEST_NAME, "corrupt JSON")
    assert len(result.stdout.splitlines()) == 3  # split header, the problem, the summary


def test_manifest_with_wrong_types(split):
    m = json.loads((split / MANIFEST_NAME).read_text())
    m["shards"][0]["n_images"] = "64"
    (split / MANIFEST_NAME).write_text(json.dumps(m))
    result = run_verify(split, "--workers", "1")
    assert_reported(result, MANIFEST_NAME, "corrupt shard list")


def test_mean_object_split_verifies(tmp_path):
    gen = CliRunner().invoke(main, ["generate", "--class", "refrigerator", "--mean", "--out", str(tmp_path),
                                    "--workers", "1", "--quiet"])
    assert gen.exit_code == 0, gen.output
    result = run_verify(tmp_path / "refrigerator" / "mean", "--workers", "1")
    assert result.exit_code == 0, result.output


def test_missing_manifest_still_checks_shards(split):
    (split / MANIFEST_NAME).unlink()
    (split / "shard-00001.h5").write_bytes(b"\0" * 100)
    result = run_verify(split, "--workers", "1")
    assert_reported(result, MANIFEST_NAME, "missing")
    assert_reported(result, "shard-00001.h5", "not a readable HDF5 file")


def test_shard_list_and_counts(split):
    (split / "shard-00001.h5").rename(split / "shard-00007.h5")
    result = run_verify(split, "--workers", "1")
    assert_reported(result, "shard-00001.h5", "listed in the manifest but missing")
    assert_reported(result, "shard-00007.h5", "not listed in the manifest")


def test_incomplete_split_is_reported(split):
    m = json.loads((split / MANIFEST_NAME).read_text())
    last = m["shards"].pop()
    m["n_images"] -= last["n_images"]
    m["n_objects"] -= last["object_stop"] - last["object_start"]
    m["complete"] = False
    (split / MANIFEST_NAME).write_text(json.dumps(m))
    (split / last["file"]).unlink()
    result = run_verify(split, "--workers", "1")
    assert_reported(result, MANIFEST_NAME, "incomplete split: 1 of 2 shards", "--resume")


def test_leftover_partial_file_is_only_a_warning(split):
    (split / "shard-00002.h5.partial").write_bytes(b"half a shard")
    result = run_verify(split, "--workers", "1")
    assert result.exit_code == 0, result.output
    assert "warning: leftover temporary file" in result.output


@pytest.mark.parametrize("make_path", [
    lambda tmp: tmp / "does-not-exist",
    lambda tmp: (tmp / "empty").mkdir() or tmp / "empty",
    lambda tmp: (tmp / "file.txt").write_text("x") and tmp / "file.txt",
])
def test_usage_errors_exit_2(tmp_path, make_path):
    result = run_verify(make_path(tmp_path))
    assert_one_line_error(result)


def test_bad_workers_is_usage_error(split):
    assert run_verify(split, "--workers", "0").exit_code == 2


def test_check_shard_api_and_quaternion_axis():
    # hand-worked: a rotation of +90 deg about x maps z to -y; identity keeps z.
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quat_rotate_z(np.array([[s, s, 0, 0], [1, 0, 0, 0]])), [[0, -1, 0], [0, 0, 1]], atol=1e-12)
    res = check_shard("/nonexistent/shard-00000.h5")
    assert res.problems == ["listed in the manifest but missing"]


def test_verify_split_api_reports_file_names(split):
    edit(split, "shard-00000.h5", _scale_axis)
    report = verify_split(split)
    assert not report.ok
    assert {p.where for p in report.errors} == {"shard-00000.h5"}
    assert report.n_images == 6 * 16 and report.n_shards == 2


# --------------------------------------------------------------------------------------
# Ingested real splits: valid by their own rules, and corruption in them is still caught
# --------------------------------------------------------------------------------------

def _real_capture(folder, name, s, K, labels=None):
    """A capture at the training resolution: 16-bit PNG depth (mm), binary mask, K, labels."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.rint(s["depth"].astype(np.float64) * 1000).astype(np.uint16)).save(folder / f"{name}.png")
    Image.fromarray((s["mask"] > 0).astype(np.uint8) * 255).save(folder / f"{name}.mask.png")
    (folder / f"{name}.camera.json").write_text(json.dumps(
        {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": s["depth"].shape[1],
         "height": s["depth"].shape[0]}))
    if labels is not None:
        (folder / f"{name}.labels.json").write_text(json.dumps(labels))


@pytest.fixture(scope="module")
def real_split_source(tiny_root, tmp_path_factory):
    """A cabinet2 real split of three captures: full labels, labels without part_offset /
    object_pose (the docs' example), and none; the last with a crop fit in a second shard."""
    from articulated_dataset.format import open_split

    root = tmp_path_factory.mktemp("real")
    _, shards = open_split(tiny_root / "cabinet2" / "test")
    sh = shards[0]
    K = sh.K
    s0, s1, s2 = (sh.sample(i) for i in (0, 5, 9))
    full = {k: s0[k].tolist() for k in ("q", "axis_pose", "part_offset", "geometry", "object_pose")}
    full["object"] = "kitchen"
    docs_like = {"q": s1["q"].tolist(), "axis_pose": s1["axis_pose"].tolist(), "geometry": s1["geometry"].tolist(),
                 "object": "kitchen"}
    _real_capture(root / "caps", "a", s0, K, full)
    _real_capture(root / "caps", "b", s1, K, docs_like)
    _real_capture(root / "more", "c", s2, K)
    for args in (["caps"], ["more", "--fit", "crop", "--append"]):
        res = CliRunner().invoke(main, ["ingest", str(root / args[0]), "--class", "cabinet2", "--out", str(root / "out"),
                                        "-q", *args[1:]])
        assert res.exit_code == 0, res.output
    return root / "out" / "cabinet2" / "real"


@pytest.fixture()
def real_split(real_split_source, tmp_path):
    dst = tmp_path / "cabinet2" / "real"
    shutil.copytree(real_split_source, dst)
    return dst


def test_ingested_real_split_verifies(real_split_source):
    result = run_verify(real_split_source, "--workers", "1")
    assert result.exit_code == 0, result.output
    assert "OK, 2 shards, 3 images" in result.output


def _set(name, index, value):
    def fn(f):
        a = f[name][()]
        a[index] = value
        f[name][...] = a
    return fn


def _set_attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


@pytest.mark.parametrize("damage, needles", [
    (_set("q", (0, 1), 100.0), ["q[1]: outside the class's joint range", "first: image 0"]),
    (_set("q", (1, 0), -5.0), ["q[0]: outside the class's joint range", "first: image 1"]),
    (_set("q", (0, 0), np.inf), ["q: infinite values"]),
    (_set("part_offset", (0, 0, 1), np.nan), ["part_offset: partly NaN"]),
    (_set("axis_origin", (1, 0, 1), np.nan), ["axis_origin: partly NaN", "axis_pose: position differs from axis_origin"]),
    (_set("geometry", (1, 3), 0.5), ["geometry: chirality not 0 or 1"]),
    (_set("geometry", (0, 0), -0.3), ["geometry: body dimensions not in (0, 5] m"]),
    (_set("object_pose", (0, 0), 500.0), ["object_pose: position farther than 20 m"]),
    (_set("axis_direction", (0, 0), 3.0), ["axis_direction: not unit length"]),
    (_set("sample_id", 1, 12345), ["sample_id: differs from real_sample_id"]),
    (_set("object_index", 0, 7), ["object_index: outside the shard's objects"]),
    (_set("depth", (0, 50, 90), -1.0), ["depth: negative values"]),
    (_set_attr("has_ground_truth", np.array([1, 0], np.int8)), ["labels present although has_ground_truth is 0"]),
    (_set_attr("capture_names", json.dumps(["a", "x"])), ["capture_names differs from the manifest",
                                                          "sample_id: differs from real_sample_id"]),
    (_set_attr("real", 0), ["the manifest describes ingested real data"]),
    (lambda f: f["K"].__setitem__((1, 1), f["K"][1, 1] * 1.5), ["gives a vertical field of view"]),
], ids=["q-high", "q-negative", "q-inf", "offset-part-nan", "origin-part-nan", "chirality", "geometry", "far-pose",
        "non-unit-axis", "sample-id", "object-index", "depth", "gt-flag", "capture-names", "real-attr", "K"])
def test_real_split_damage_is_reported(real_split, damage, needles):
    edit(real_split, "shard-00000.h5", damage)
    result = run_verify(real_split, "--workers", "1")
    assert_reported(result, "shard-00000.h5", *needles)
    assert "shard-00001.h5" not in result.output


def test_real_manifest_damage_is_reported(real_split):
    m = json.loads((real_split / MANIFEST_NAME).read_text())
    m["real"]["captures"][2] = "a"
    m["n_objects"] = 5
    (real_split / MANIFEST_NAME).write_text(json.dumps(m))
    result = run_verify(real_split, "--workers", "1")
    assert_reported(result, MANIFEST_NAME, "real.captures names a capture twice", "n_objects is 5 but real.objects lists 2")
    assert_reported(result, "shard-00001.h5", "capture_names differs from the manifest")
