"""The generation package's stages: one compiler for every rebuild, the object's
generator state kept for pose redraws, stage 1 free of Xacro, the scene free of sampling, one
builder of shard attributes."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

import articulated_dataset
from articulated_dataset.format import records
from articulated_dataset.generation import GenerationConfig, object_sample, render_object, sampling, shard_attrs
from articulated_dataset.generation import objects as objects_module
from articulated_dataset.generation import pipeline as pipeline_module
from articulated_dataset.generation.mujoco_scene import yaw_quaternion
from articulated_dataset.generation.render import process_renderer
from articulated_dataset.generation.sampling import ObjectSample, sample_object, sample_pose

PACKAGE = Path(articulated_dataset.__file__).parent


def _calls(name: str) -> list[str]:
    """Package modules (relative paths) that call a function named ``name``."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                if (isinstance(f, ast.Name) and f.id == name) or (isinstance(f, ast.Attribute) and f.attr == name):
                    found.append(str(path.relative_to(PACKAGE)))
                    break
    return found


@pytest.mark.slow
def test_objects_are_compiled_in_one_place():
    """Everyone who rebuilds an object (pipeline, viz, urdf_import, manipulation) calls
    compile_object; only it builds the scene and indexes the model."""
    assert _calls("build_model") == ["generation/compiled.py"]
    assert _calls("model_info") == ["generation/compiled.py"]
    users = set(_calls("compile_object"))
    assert {"generation/pipeline.py", "tools/viz/data.py", "generation/urdf_import/build.py", "manipulation/true_object.py"} <= users


def _imported_names(path: Path) -> set[tuple[str, str]]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            out |= {((node.module or ""), a.name) for a in node.names}
    return out


def test_stages_keep_to_their_inputs():
    """Stage 1 formats no Xacro arguments; the scene (stage 3) imports nothing from sampling."""
    assert not hasattr(ObjectSample, "template_mappings")
    assert "xacro" not in (PACKAGE / "generation" / "sampling.py").read_text(encoding="utf-8").lower()
    for name in ("mujoco_scene.py", "scenes.py"):
        imported = _imported_names(PACKAGE / "generation" / name)
        assert not any(mod == "sampling" and n == "yaw_quaternion" for mod, n in imported)
    # MuJoCo's quaternion is bit for bit the one the package computed by hand before
    for yaw in (0.0, 0.3, -1.2, math.pi / 2, 3.0):
        assert np.array_equal(yaw_quaternion(yaw), [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def test_a_rejected_pose_is_redrawn_from_the_kept_state(monkeypatch):
    """Toaster object 1 (4 images) needs a second pose: it is the next draw of the object's
    own generator after stage 1, taken from the state the sample keeps, never by replaying
    sample_object (which fails here if called)."""
    config = GenerationConfig("toaster", n_objects=2, images_per_object=4)
    renderer = process_renderer(config.camera)
    first = object_sample(config, 1)
    _, rng = sample_object(config.obj_class, config.table, seed=config.seed, split=config.split, object_index=1,
                           n_images=config.images_per_object)
    expected = sample_pose(rng, config.table)
    assert sample_pose(first.pose_generator(), config.table) == expected

    def replay(*args, **kwargs):
        raise AssertionError("sample_object replayed to redraw a pose")

    monkeypatch.setattr(sampling, "sample_object", replay)
    monkeypatch.setattr(objects_module, "sample_object", replay)
    monkeypatch.setattr(pipeline_module, "sample_object", replay, raising=False)
    arrays, final, attempts = render_object(first, config, renderer)
    assert attempts == 2 and final.pose == expected
    again, final_again, _ = render_object(first, config, renderer)  # the kept state is not consumed
    assert final_again.pose == final.pose
    assert np.array_equal(again["depth"], arrays["depth"])
    with pytest.raises(ValueError):  # the mean object keeps no state: it is never redrawn
        object_sample(GenerationConfig("toaster", n_objects=1, mean=True), 0).pose_generator()


def test_generated_shard_attributes_come_from_the_format_builder():
    """The default split's attributes are the format's builder's, with nothing added; the
    options add their records on top."""
    config = GenerationConfig("cabinet", n_objects=3, objects_per_shard=2)
    objects = config.shard_objects(1)
    assert shard_attrs(config, objects) == records.shard_attrs(config, config.obj_class, objects)
    kitchen = GenerationConfig("cabinet", n_objects=3, objects_per_shard=2, scene="kitchen", occluders=1)
    extra = set(shard_attrs(kitchen, objects)) - set(records.shard_attrs(kitchen, kitchen.obj_class, objects))
    assert extra == {"scene", "occluders"}
    manifest = records.split_manifest(config, [{"object_start": 0, "object_stop": 2, "n_images": 32}])
    assert (manifest["complete"], manifest["n_objects"], manifest["n_images"], manifest["n_shards_expected"]) == (False, 2, 32, 2)
