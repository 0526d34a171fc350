"""Generation on Ray: byte-identical to the local executor, retried when a worker dies."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.pool import RAY_INSTALL_HELP, RayExecutor, get_executor
from articulated_dataset.format import TMP_SUFFIX, shard_name
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.generation.urdf_import import CACHE_ENV, import_urdf

#: Small split: 4 shards of one object, so both Ray workers get work and one task can fail.
ARGS = ["--class", "drawer", "--n", "4", "--images", "4", "--objects-per-shard", "1", "--seed", "3", "--quiet"]
CONFIG = GenerationConfig("drawer", n_objects=4, images_per_object=4, objects_per_shard=1, seed=3)
#: Shard whose first attempt is killed.
CRASH_SHARD = 1


def _files(split_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(split_dir.iterdir())}


def test_missing_ray_is_one_line_with_the_install_command(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # "import ray" raises ImportError
    r = CliRunner().invoke(main, ["generate", *ARGS, "--out", str(tmp_path), "--executor", "ray"])
    assert r.exit_code == 2
    line = f"artdata: error: {RAY_INSTALL_HELP}".replace(option("executor"), "--executor")  # the flag of the quantity
    assert line in r.output.splitlines() and "Traceback" not in r.output
    assert "pip install" in RAY_INSTALL_HELP


def test_executor_choice_errors(tmp_path):
    with pytest.raises(UserError, match="unknown executor 'dask'; choose from: local, ray"):
        get_executor("dask")
    with pytest.raises(UserError, match="address is for executor ray"):
        get_executor("local", 2, "auto")
    r = CliRunner().invoke(main, ["generate", *ARGS, "--out", str(tmp_path), "--executor", "ray", "--address", "nohost"])
    assert r.exit_code == 2 and "--address must be auto, HOST:PORT" in r.output
    assert isinstance(get_executor("ray", None, "auto"), RayExecutor)  # Ray is only contacted on use


@pytest.fixture(scope="module")
def ray_local(tmp_path_factory):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    # the crash wrapper below lives in this test module, which Ray workers cannot import
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    reference = generate_split(CONFIG, tmp_path_factory.mktemp("local"))
    yield ray, reference
    ray.shutdown()


@pytest.mark.slow
def test_cli_ray_executor_gives_the_local_bytes(ray_local, tmp_path):
    _, reference = ray_local
    r = CliRunner().invoke(main, ["generate", *ARGS, "--out", str(tmp_path / "local"), "--workers", "1"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["generate", *ARGS, "--out", str(tmp_path / "ray"), "--executor", "ray"])
    assert r.exit_code == 0, r.output
    local, ray_out = _files(tmp_path / "local" / "drawer" / "train"), _files(tmp_path / "ray" / "drawer" / "train")
    assert sorted(ray_out) == ["manifest.json"] + [shard_name(i) for i in range(4)]
    assert ray_out == local == _files(reference)


def _crash_first_attempt(marker: str, fn, task):
    """Kill this worker process on the first attempt of shard CRASH_SHARD, leaving a half-written
    shard behind (as a worker killed while writing would); run ``fn`` otherwise."""
    _, index, split_dir = task
    if index == CRASH_SHARD and not os.path.exists(marker):
        Path(marker).write_text("crashed once")
        (Path(split_dir) / (shard_name(index) + TMP_SUFFIX)).write_bytes(b"truncated")
        os._exit(1)
    return fn(task)


class _CrashingRay:
    """The Ray executor with every task wrapped by :func:`_crash_first_attempt`."""

    def __init__(self, marker: Path, max_retries: int):
        self.inner = RayExecutor(max_retries=max_retries)
        self.marker = str(marker)

    def map_unordered(self, fn, tasks, progress=None):
        return self.inner.map_unordered(functools.partial(_crash_first_attempt, self.marker, fn), tasks, progress)


def test_killed_worker_is_retried_and_output_is_identical(ray_local, tmp_path):
    _, reference = ray_local
    marker = tmp_path / "crashed"
    split = generate_split(CONFIG, tmp_path / "out", executor=_CrashingRay(marker, max_retries=2))
    assert marker.exists()  # the first attempt did die
    assert not list(split.glob(f"*{TMP_SUFFIX}"))
    assert _files(split) == _files(reference)


def test_without_retries_the_crash_surfaces(ray_local, tmp_path):
    ray, _ = ray_local
    with pytest.raises(ray.exceptions.RayError):
        generate_split(CONFIG, tmp_path / "out", executor=_CrashingRay(tmp_path / "crashed", max_retries=0))


def _box_urdf(folder: Path) -> Path:
    """A box with a door hinged on its left front edge, from OBJ meshes."""
    import trimesh

    folder.mkdir()
    body = trimesh.creation.box(extents=[0.4, 0.5, 0.6])
    body.apply_translation([0, 0, 0.3])
    body.export(str(folder / "body.obj"))
    door = trimesh.creation.box(extents=[0.02, 0.5, 0.6])
    door.apply_translation([-0.01, -0.25, 0.3])
    door.export(str(folder / "door.obj"))
    path = folder / "box.urdf"
    path.write_text(
        '<robot name="box"><link name="base"><visual><geometry><mesh filename="body.obj"/></geometry></visual></link>'
        '<link name="door"><visual><geometry><mesh filename="door.obj"/></geometry></visual></link>'
        '<joint name="hinge" type="revolute"><parent link="base"/><child link="door"/><origin xyz="-0.2 0.25 0"/>'
        '<axis xyz="0 0 -1"/><limit lower="0" upper="1.2"/></joint></robot>')
    return path


@pytest.mark.slow
def test_urdf_object_on_ray_and_changed_files_are_refused(ray_local, tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))  # forwarded to the Ray workers
    path = _box_urdf(tmp_path / "box")
    obj = import_urdf(path, class_name="raybox")
    cfg = GenerationConfig("raybox", n_objects=2, images_per_object=4, objects_per_shard=1, third_party=obj.definition)
    local = generate_split(cfg, tmp_path / "local")
    on_ray = generate_split(cfg, tmp_path / "ray", executor=RayExecutor())  # workers rebuild the class
    assert _files(on_ray) == _files(local)
    # A class imported, then a mesh changed before the workers (which build each class once)
    # first see it: they refuse to render something other than what the driver imported.
    other = import_urdf(path, class_name="raybox2")
    with open(path.parent / "door.obj", "a") as f:
        f.write("v 0 0 2\n")
    cfg2 = GenerationConfig("raybox2", n_objects=1, images_per_object=4, third_party=other.definition)
    with pytest.raises(UserError, match="differ from the files the generation was started with"):
        generate_split(cfg2, tmp_path / "changed", executor=RayExecutor())
