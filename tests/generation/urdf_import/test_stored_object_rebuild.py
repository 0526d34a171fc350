"""Rebuilding a stored third-party URDF object (``show --rgb``, ``plan``) from a URDF the user
names with ``--urdf``: the recorded path outside the split folder is never opened, the named
file is used only when its sha256 is the one the split recorded."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.generation import urdf_import
from helpers_core import ROOT, assert_one_line_error, flap_split_outside, load_script, write_flap_urdf

BENCHMARK = ROOT / "benchmarks" / "manipulation.py"


@pytest.fixture(scope="module")
def flap(tmp_path_factory) -> dict:
    """A one-object, one-image split generated from a URDF that lies outside the split folder."""
    root = tmp_path_factory.mktemp("flap")
    mp = pytest.MonkeyPatch()
    mp.setenv(urdf_import.CACHE_ENV, str(root / "cache"))
    urdf, split = flap_split_outside(root, "test")
    yield {"split": split, "urdf": urdf}
    mp.undo()


def _rebuild(how: str, split: Path, out: Path, *extra: str):
    """``show --rgb`` or ``plan`` of image 0 of ``split``, writing ``out``."""
    if how == "show-rgb":
        args = ["show", str(split), "--rgb", "--n", "1", "--out", str(out)]
    else:
        args = ["plan", str(split), "--index", "0", "--out", str(out)]
    return CliRunner().invoke(main, [*args, "-q", *extra])


@pytest.mark.parametrize("how", ["show-rgb", "plan"])
def test_without_urdf_the_refusal_names_the_option(flap, tmp_path, how):
    out = tmp_path / ("g.png" if how == "show-rgb" else "plan.json")
    assert_one_line_error(_rebuild(how, flap["split"], out), "outside the split folder", "--urdf FILE")
    assert not out.exists()


@pytest.mark.parametrize("how", ["show-rgb", "plan"])
def test_the_named_urdf_rebuilds_the_object(flap, tmp_path, how):
    out = tmp_path / ("g.png" if how == "show-rgb" else "plan.json")
    result = _rebuild(how, flap["split"], out, "--urdf", str(flap["urdf"]))
    assert result.exit_code == 0, result.output
    assert out.stat().st_size > 0


@pytest.mark.parametrize("how", ["show-rgb", "plan"])
def test_a_changed_copy_of_the_urdf_is_refused_by_its_sha256(flap, tmp_path, how):
    copy = Path(shutil.copy(flap["urdf"], tmp_path / "flap.urdf"))
    copy.write_text(copy.read_text().replace('upper="1.5"', 'upper="1.4"'))
    out = tmp_path / ("g.png" if how == "show-rgb" else "plan.json")
    assert_one_line_error(_rebuild(how, flap["split"], out, "--urdf", str(copy)),
                          f"{copy} is not the URDF this split was generated from (sha256 differs)")
    assert not out.exists()


def test_a_mesh_root_needs_its_urdf(flap, tmp_path):
    assert_one_line_error(_rebuild("plan", flap["split"], tmp_path / "plan.json", "--mesh-root", str(tmp_path)),
                          "--urdf FILE")


def test_the_python_api_takes_the_urdf(flap):
    from articulated_dataset.manipulation import load_true_object, split_row_labels

    manifest, labels = split_row_labels(flap["split"], 0)
    obj = load_true_object(manifest, labels, split_dir=flap["split"], urdf=flap["urdf"])
    assert obj.n_joints == 1


def test_the_manipulation_benchmark_takes_a_class_urdf(flap):
    """benchmarks/manipulation.py rebuilds a third-party class from ``--urdf CLASS=FILE``; without
    it the run stops with one line naming that option."""
    bench = load_script(BENCHMARK, "manipulation_benchmark")
    root, cls = flap["split"].parent.parent, flap["split"].parent.name
    args = ["--data", str(root), "--split", "test", "--objects", "1", "-q"]
    with pytest.raises(SystemExit) as refused:
        bench.main([*args, "--classes", cls])
    assert "outside the split folder" in str(refused.value.code) and f"--urdf {cls}=FILE" in str(refused.value.code)
    with pytest.raises(SystemExit) as stopped:  # rebuilt; the test object has no handle to grasp
        bench.main([*args, "--urdf", f"{cls}={flap['urdf']}"])
    assert "_handle" in str(stopped.value.code), stopped.value.code


def test_a_mesh_folder_is_named_with_its_urdf(tmp_path, monkeypatch):
    """A split generated with --mesh-root (its mesh outside the URDF's folder) rebuilds from the
    URDF and mesh folder named; a copy whose mesh changed is refused by its sha256."""
    import trimesh

    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))
    source = tmp_path / "object"
    urdf = write_flap_urdf(source / "urdf")
    urdf.write_text(urdf.read_text().replace('<box size="0.02 0.4 0.4"/>', '<mesh filename="../meshes/flap.obj"/>'))
    (source / "meshes").mkdir()
    trimesh.creation.box(extents=[0.02, 0.4, 0.4]).export(str(source / "meshes" / "flap.obj"))
    result = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--mesh-root", str(source), "--n", "1",
                                       "--images", "1", "--out", str(tmp_path / "out"), "-q", "--workers", "1"])
    assert result.exit_code == 0, result.output
    (split,) = [p.parent for p in (tmp_path / "out").glob("*/train/manifest.json")]
    out = tmp_path / "plan.json"
    assert _rebuild("plan", split, out, "--urdf", str(urdf)).exit_code == 2  # its mesh lies outside the URDF's folder
    result = _rebuild("plan", split, out, "--urdf", str(urdf), "--mesh-root", str(source))
    assert result.exit_code == 0, result.output
    assert out.is_file()
    copy = Path(shutil.copytree(source, tmp_path / "copy"))
    with open(copy / "meshes" / "flap.obj", "a") as f:
        f.write("# changed\n")
    assert_one_line_error(_rebuild("plan", split, tmp_path / "other.json", "--urdf", str(copy / "urdf" / "flap.urdf"),
                                   "--mesh-root", str(copy)), "sha256 differs")
