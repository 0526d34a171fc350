"""The supported MuJoCo releases: declared once, checked before rendering, recorded in every
generated split's manifest and compared by ``generate --resume``, ``verify`` and ``info``."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib
from click.testing import CliRunner

import articulated_dataset
from articulated_dataset.cli import main
from articulated_dataset.core.errors import RenderError, UserError
from articulated_dataset.core.mujoco_support import (
    MANIFEST_KEY,
    MUJOCO_REQUIREMENT,
    installed_mujoco_version,
    unsupported_mujoco,
)
from articulated_dataset.format import read_manifest
from articulated_dataset.format.manifest import write_manifest
from articulated_dataset.generation import GenerationConfig, generate_split
from helpers_core import ROOT, assert_one_line_error, generated_split, tree_snapshot

#: The range as the messages name it.
RANGE = MUJOCO_REQUIREMENT.removeprefix("mujoco")
#: A release before the supported range (its ``MjSpec.add_light`` refuses the scenes' light type).
OLD_RELEASE = "3.4.0"
#: A supported release other than the installed one, as another machine's manifest records it.
OTHER_RELEASE = "3.8.1" if installed_mujoco_version() != "3.8.1" else "3.9.0"


def test_pyproject_declares_the_supported_range():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert [d for d in deps if d.startswith("mujoco")] == [MUJOCO_REQUIREMENT]


def test_installed_mujoco_is_supported():
    assert unsupported_mujoco(installed_mujoco_version()) is None


@pytest.mark.parametrize("release", ["3.5.0", "3.8.1", "3.17.0", "4.0.0", "4.0.1", "4.0.2.dev1"])
def test_releases_in_the_range_are_accepted(release):
    assert unsupported_mujoco(release) is None


@pytest.mark.parametrize("release", ["3.2.7", "3.3.7", OLD_RELEASE, "4.1.0", "5.0.0", "unknown"])
def test_releases_outside_the_range_are_named_with_the_range(release):
    message = unsupported_mujoco(release)
    assert message is not None and release in message and RANGE in message and "\n" not in message


def test_generate_with_an_unsupported_mujoco_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr("articulated_dataset.cli.installed_mujoco_version", lambda: OLD_RELEASE)
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--images", "1", "--out",
                                  str(tmp_path / "out"), "-q"])
    assert_one_line_error(r, OLD_RELEASE, RANGE, code=3)
    assert not (tmp_path / "out").exists()


def test_building_a_scene_with_an_unsupported_mujoco_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr("articulated_dataset.core.mujoco_support.installed_mujoco_version", lambda: OLD_RELEASE)
    with pytest.raises(RenderError, match=RANGE.replace(".", r"\.")) as exc:
        generate_split(GenerationConfig("drawer", n_objects=1, images_per_object=1), tmp_path)
    assert "\n" not in str(exc.value)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def split_dir(tmp_path_factory) -> Path:
    return generated_split(tmp_path_factory.mktemp("mujoco"), "drawer", 1, 0)


def _copy_recording(split_dir: Path, dst: Path, recorded) -> Path:
    """A copy at ``dst/drawer/test`` of ``split_dir`` whose manifest records MuJoCo ``recorded``."""
    copy = shutil.copytree(split_dir, dst / "drawer" / "test")
    manifest = read_manifest(copy)
    manifest[MANIFEST_KEY] = recorded
    write_manifest(copy, manifest)
    return copy


def test_manifest_records_the_mujoco_and_package_versions(split_dir):
    manifest = read_manifest(split_dir)
    assert manifest[MANIFEST_KEY] == installed_mujoco_version()
    assert manifest["package_version"] == articulated_dataset.__version__


def test_info_shows_the_recorded_mujoco(split_dir):
    r = CliRunner().invoke(main, ["info", str(split_dir)])
    assert r.exit_code == 0, r.output
    assert f", MuJoCo {installed_mujoco_version()}, complete" in r.output.splitlines()[0]
    r = CliRunner().invoke(main, ["info", "--json", str(split_dir)])
    assert f'"mujoco_version": "{installed_mujoco_version()}"' in r.output


def test_resume_continues_a_split_of_the_same_mujoco(split_dir, tmp_path):
    shutil.copytree(split_dir, tmp_path / "drawer" / "test")
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--split", "test", "--seed", "0",
                                  "--out", str(tmp_path), "-q", "--resume"])
    assert r.exit_code == 0, r.output


def test_resume_refuses_a_split_of_another_mujoco(split_dir, tmp_path):
    copy = _copy_recording(split_dir, tmp_path, OTHER_RELEASE)
    before = tree_snapshot(tmp_path)
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--split", "test", "--seed", "0",
                                  "--out", str(tmp_path), "-q", "--resume"])
    assert_one_line_error(r, str(copy), OTHER_RELEASE, installed_mujoco_version(), "--overwrite")
    assert tree_snapshot(tmp_path) == before


def test_verify_notes_another_mujoco_in_one_line(split_dir, tmp_path):
    copy = _copy_recording(split_dir, tmp_path, OTHER_RELEASE)
    r = CliRunner().invoke(main, ["verify", "--workers", "1", str(copy)])
    assert r.exit_code == 0, r.output
    notes = [line for line in r.output.splitlines() if OTHER_RELEASE in line]
    assert len(notes) == 1 and "warning" in notes[0] and installed_mujoco_version() in notes[0]
    r = CliRunner().invoke(main, ["verify", "--workers", "1", str(split_dir)])
    assert r.exit_code == 0 and "MuJoCo" not in r.output


@pytest.mark.parametrize("recorded", [12, "\x1b[31m4.0.1", "x" * 200])
def test_a_recorded_version_that_is_no_version_is_one_line(split_dir, tmp_path, recorded):
    copy = _copy_recording(split_dir, tmp_path, recorded)
    r = CliRunner().invoke(main, ["verify", "--workers", "1", str(copy)])
    assert r.exit_code == 1 and MANIFEST_KEY in r.output and "\x1b" not in r.output
    assert_one_line_error(CliRunner().invoke(main, ["info", str(copy)]), MANIFEST_KEY)
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--split", "test", "--seed", "0",
                                  "--out", str(tmp_path), "-q", "--resume"])
    assert_one_line_error(r, MANIFEST_KEY)


def test_a_ray_node_with_another_mujoco_is_refused():
    from articulated_dataset.core.pool import _ray_task

    with pytest.raises(UserError, match=f"MuJoCo {installed_mujoco_version()}.*MuJoCo {OTHER_RELEASE}"):
        _ray_task(len, "ab", articulated_dataset.__version__, OTHER_RELEASE)
    assert _ray_task(len, "ab", articulated_dataset.__version__, installed_mujoco_version()) == 2


#: A process that creates a renderer whose GL library, like MuJoCo 3.x's EGL module, registers an
#: exit hook (terminating its display) when the first context is created.
_EXIT_ORDER_SCRIPT = """
import atexit
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.generation import render

class Context:
    def __init__(self, width, height):
        atexit.register(print, "display terminated", flush=True)
    def make_current(self):
        pass
    def free(self):
        print("context freed", flush=True)

render._make_gl_context = Context
render.process_renderer(CameraConfig())
"""


def test_gl_contexts_are_freed_before_the_gl_library_exit_hooks():
    out = subprocess.run([sys.executable, "-c", _EXIT_ORDER_SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["context freed", "display terminated"], out.stdout
