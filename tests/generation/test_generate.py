"""Generation end to end: determinism, split disjointness, shard contents, the CLI."""

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset import FORMAT_VERSION
from articulated_dataset.classes.registry import class_names
from articulated_dataset.cli import main
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig
from articulated_dataset.format import FIELDS, open_split, read_manifest, sha256_file
from articulated_dataset.generation import GenerationConfig, generate_split
from helpers_core import assert_one_line_error


def _checksums(split_dir):
    return [(s["file"], s["sha256"]) for s in read_manifest(split_dir)["shards"]]


def test_same_seed_gives_identical_bytes_and_other_seeds_differ(tmp_path):
    cfg = GenerationConfig("microwave", n_objects=5, objects_per_shard=2)
    a = generate_split(cfg, tmp_path / "a")
    b = generate_split(cfg, tmp_path / "b", workers=2)
    c = generate_split(GenerationConfig("microwave", n_objects=5, objects_per_shard=2, seed=1), tmp_path / "c")
    assert _checksums(a) == _checksums(b)
    for s in read_manifest(a)["shards"]:
        assert sha256_file(a / s["file"]) == s["sha256"]
    assert all(x != y for x, y in zip(_checksums(a), _checksums(c)))


def test_object_k_does_not_depend_on_how_work_is_split(tmp_path):
    a = generate_split(GenerationConfig("drawer", n_objects=6, objects_per_shard=6), tmp_path / "a")
    b = generate_split(GenerationConfig("drawer", n_objects=6, objects_per_shard=4), tmp_path / "b")
    la = np.concatenate([sh.read("depth") for sh in open_split(a)[1]])
    lb = np.concatenate([sh.read("depth") for sh in open_split(b)[1]])
    assert np.array_equal(la, lb)


def test_train_and_test_splits_share_no_object(tiny_root):
    for name in class_names():
        geo = {}
        for split in ("train", "test"):
            _, shards = open_split(tiny_root / name / split)
            geo[split] = (np.concatenate([s.read("sample_id") for s in shards]),
                          np.concatenate([s.read("geometry")[:, :3] for s in shards]))
        assert not set(geo["train"][0]) & set(geo["test"][0])
        assert not {tuple(g) for g in geo["train"][1]} & {tuple(g) for g in geo["test"][1]}


def test_shards_hold_every_schema_field_and_camera(tiny_root):
    manifest, shards = open_split(tiny_root / "cabinet2" / "train")
    assert manifest["complete"] and manifest["n_objects"] == 6 and manifest["n_images"] == 96
    with h5py.File(shards[0].path) as f:
        for field in FIELDS:
            assert f[field.name].dtype == np.dtype(field.dtype)
        assert f["depth"].chunks == (1, 108, 192) and f["depth"].compression == "gzip"
        assert np.allclose(f["K"][()], CameraConfig().K) and np.allclose(f["R_camera_to_optical"][()], R_CAMERA_TO_OPTICAL)
        assert f.attrs["format_version"] == FORMAT_VERSION and f.attrs["class_name"] == "cabinet2"
        assert json.loads(f.attrs["sampling_table"])["q"] == [[0.0, np.pi / 2]] * 2
        assert f["q"].shape == (64, 2) and f["axis_pose"].shape == (64, 2, 7)
        assert set(f["image_index"][()]) == set(range(16))


def test_mean_object_has_centre_geometry(tmp_path):
    split = generate_split(GenerationConfig("toaster", n_objects=1, mean=True), tmp_path)
    assert split.name == "mean"
    g = open_split(split)[1][0].read("geometry")
    assert g[0, :3] == pytest.approx([0.35, 0.50, 0.35], abs=1e-6)


def _run(args):
    return CliRunner().invoke(main, args)


def test_cli_generates_and_refuses_to_clobber(tmp_path):
    out = str(tmp_path)
    r = _run(["generate", "--class", "drawer", "--n", "3", "--out", out, "--quiet", "--workers", "1"])
    assert r.exit_code == 0, r.output
    msg = assert_one_line_error(_run(["generate", "--class", "drawer", "--n", "3", "--out", out, "--quiet"]))
    assert "--resume" in msg and "--overwrite" in msg
    # other splits and classes under the same --out are fine
    assert _run(["generate", "--class", "drawer", "--split", "test", "--n", "2", "--out", out, "--quiet", "--workers", "1"]).exit_code == 0
    assert _run(["generate", "--class", "toaster", "--n", "2", "--out", out, "--quiet", "--workers", "1"]).exit_code == 0
    before = _checksums(tmp_path / "drawer" / "train")
    assert _run(["generate", "--class", "drawer", "--n", "3", "--out", out, "--quiet", "--resume"]).exit_code == 0
    assert _checksums(tmp_path / "drawer" / "train") == before
    assert _run(["generate", "--class", "drawer", "--n", "3", "--out", out, "--quiet", "--overwrite", "--workers", "1"]).exit_code == 0
    assert _checksums(tmp_path / "drawer" / "train") == before
    r = _run(["info", str(tmp_path)])
    assert r.exit_code == 0 and "drawer" in r.output and "toaster" in r.output and "images" in r.output


@pytest.mark.parametrize("args", [
    ["--class", "sofa", "--n", "3"],
    ["--class", "drawer", "--n", "0"],
    ["--class", "drawer", "--n", "-4"],
    ["--class", "drawer", "--n", "2", "--images", "0"],
    ["--class", "drawer", "--n", "2", "--width", "0"],
    ["--class", "drawer", "--n", "2", "--table", "/nonexistent/table.json"],
])
def test_cli_bad_arguments_give_one_line_errors(tmp_path, args):
    assert_one_line_error(_run(["generate", *args, "--out", str(tmp_path), "--quiet"]))


def test_cli_unwritable_output(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    msg = assert_one_line_error(_run(["generate", "--class", "drawer", "--n", "1", "--out", str(blocker / "sub"), "--quiet"]))
    assert "a-file" in msg


def test_cli_resume_with_different_settings_is_refused(tmp_path):
    assert _run(["generate", "--class", "drawer", "--n", "2", "--out", str(tmp_path), "--quiet", "--workers", "1"]).exit_code == 0
    assert_one_line_error(_run(["generate", "--class", "drawer", "--n", "2", "--seed", "5", "--out", str(tmp_path), "--quiet", "--resume"]))


def test_info_on_missing_or_foreign_folder(tmp_path):
    assert_one_line_error(_run(["info", str(tmp_path / "nothing")]))
    (tmp_path / "x" / "train").mkdir(parents=True)
    (tmp_path / "x" / "train" / "manifest.json").write_text("{broken")
    assert_one_line_error(_run(["info", str(tmp_path / "x" / "train")]))


def test_console_script_runs_as_a_user_would(tmp_path):
    """The installed `artdata` entry point, in a fresh process."""
    exe = [sys.executable, "-m", "articulated_dataset.cli"]
    ok = subprocess.run(exe + ["generate", "--class", "cabinet", "--n", "2", "--out", str(tmp_path), "--workers", "1"],
                        capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "images/s" in ok.stdout and "bytes/image" in ok.stdout
    bad = subprocess.run(exe + ["generate", "--class", "cabinet", "--n", "2", "--out", str(tmp_path)], capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(subprocess.run("ldconfig -p | grep -q libOSMesa.so", shell=True).returncode != 0,
                    reason="libOSMesa not installed (scripts/setup.sh installs it)")
def test_osmesa_fallback_gives_the_same_bytes_as_egl(tmp_path):
    """MUJOCO_GL selects the backend; both software rasterisers produce identical shards."""
    import os

    sums = {}
    for backend in ("egl", "osmesa"):
        env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
        out = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", "generate", "--class", "toaster", "--n", "2",
                              "--out", str(tmp_path / backend), "--workers", "1", "--quiet"],
                             env=env, capture_output=True, text=True)
        assert out.returncode == 0 and out.stderr == "", out.stderr
        sums[backend] = _checksums(tmp_path / backend / "toaster" / "train")
    assert sums["egl"] == sums["osmesa"]
