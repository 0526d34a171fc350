"""The registry is the one place a class name resolves: the built-in generators are data it
lists and loads (they import no registry, so nothing it loads imports it back), and a
third-party URDF class is registered by its definition like a built-in."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import pytest
from click.testing import CliRunner

from articulated_dataset import classes as generators
from articulated_dataset.classes import registry
from articulated_dataset.classes.base import ObjectClass
from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.generation import GenerationConfig
from articulated_dataset.generation.config import resolve
from articulated_dataset.generation.urdf_import import import_urdf
from helpers_core import write_flap_urdf

#: Modules of classes/ beside the class folders: the class types, the registry, shared values,
#: the realistic and varied tables.
NOT_CLASSES = {"base", "common", "realistic", "registry", "varied"}


def test_every_class_folder_is_listed_and_is_data():
    """A class is a folder (package) of classes/; every folder is registered, and the modules
    beside the folders are the shared ones."""
    modules = {m.name for m in pkgutil.iter_modules(generators.__path__) if m.ispkg}
    assert {m.name for m in pkgutil.iter_modules(generators.__path__) if not m.ispkg} == NOT_CLASSES
    assert set(registry.BUILTIN_GENERATORS) == modules
    for name in registry.BUILTIN_GENERATORS:
        obj_class = __import__(f"articulated_dataset.classes.{name}", fromlist=["CLASS"]).CLASS
        assert isinstance(obj_class, ObjectClass) and obj_class.name == name
        assert registry.get_class(name) is obj_class
    assert registry.class_names() == ["cabinet", "drawer", "microwave", "toaster", "cabinet2", "refrigerator",
                                      "oven", "dishwasher", "lidded_box"]


def test_what_the_registry_loads_never_imports_it_back():
    """No cycle: the generators, urdf_import (the third-party builder) and the stages it uses
    load without the registry, which imports them (a generator that registered itself by
    importing the registry would fail this)."""
    loaded = ["articulated_dataset.classes." + n for n in registry.BUILTIN_GENERATORS] + [
        "articulated_dataset.generation.urdf_import", "articulated_dataset.generation.labels", "articulated_dataset.generation.mujoco_scene",
        "articulated_dataset.generation.sampling", "articulated_dataset.classes.base"]
    code = "import sys\n" + "".join(f"import {m}\n" for m in loaded) + "print('articulated_dataset.classes.registry' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    check = subprocess.run([sys.executable, "-c", "import sys, articulated_dataset.generation.pipeline\n"
                            "print('articulated_dataset.classes.registry' in sys.modules)"], capture_output=True, text=True)
    assert check.stdout.strip() == "True"  # the check can fail: the generator does import the registry


def test_third_party_classes_register_by_definition(tmp_path, monkeypatch):
    from articulated_dataset.generation import urdf_import

    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))
    path = write_flap_urdf(tmp_path / "flap")
    small = import_urdf(path, class_name="flap")
    big = import_urdf(path, class_name="flap", scale=2.0)
    assert small.definition != big.definition
    resolved = resolve("flap", small.definition)
    assert resolved == small.obj_class and resolve("flap", small.definition) is resolved
    assert resolve("flap", big.definition) == big.obj_class != resolved  # one name, two definitions
    config = GenerationConfig("flap", n_objects=1, third_party=small.definition)
    assert config.obj_class is resolved and config.table == resolved.table
    assert "flap" not in registry.class_names()  # the built-in listing stays the paper's classes
    with pytest.raises(UserError, match="unknown object class 'flap'"):
        registry.get_class("flap")  # a third-party class resolves by its definition, not its name alone


def test_a_third_party_class_cannot_take_a_builtin_name(tmp_path, monkeypatch):
    from articulated_dataset.generation import urdf_import

    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))
    path = write_flap_urdf(tmp_path / "flap")
    imported = import_urdf(path, class_name="drawer")
    with pytest.raises(UserError, match="'drawer' is a built-in class; pass another urdf_class_name"):
        resolve("drawer", imported.definition)
    res = CliRunner().invoke(main, ["generate", "--urdf", str(path), "--class-name", "drawer", "--n", "1",
                                    "--out", str(tmp_path / "out"), "-q"])
    assert res.exit_code == 2 and "is a built-in class" in res.output, res.output
    assert not (tmp_path / "out").exists()
