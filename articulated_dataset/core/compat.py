"""Old import paths of the modules that moved in 0.2, kept working until 0.3.

``import articulated_dataset.registry`` (or any old path of :data:`MOVED`) gives the module at
its new path, the same module object, with a :class:`DeprecationWarning` naming the new path.
The finder answers only for the names of :data:`MOVED`; CHANGELOG.md (0.2.0) lists them.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

PACKAGE = "articulated_dataset"

#: Old module path (below the package) -> new module path, for the modules moved in 0.2.
MOVED = {
    "baselines": "methods.baselines",
    "baselines.clouds": "methods.baselines.clouds",
    "baselines.common": "methods.baselines.common",
    "baselines.icp": "methods.baselines.icp",
    "baselines.icp_model": "methods.baselines.icp_model",
    "baselines.mean": "methods.baselines.mean",
    "baselines.nn": "methods.baselines.nn",
    "camera": "core.camera",
    "errors": "core.errors",
    "executors": "core.pool",
    "exr": "tools.exr",
    "exr.export": "tools.exr.export",
    "exr.files": "core.images.exr",
    "exr.restore": "tools.exr.restore",
    "generators": "classes",
    "generators.cabinet": "classes.cabinet",
    "generators.cabinet2": "classes.cabinet2",
    "generators.common": "classes.common",
    "generators.drawer": "classes.drawer",
    "generators.microwave": "classes.microwave",
    "generators.realistic": "classes.realistic",
    "generators.refrigerator": "classes.refrigerator",
    "generators.toaster": "classes.toaster",
    "generators.varied": "classes.varied",
    "loaders": "training.loaders",
    "loaders.batch": "training.loaders.batch",
    "loaders.epoch": "training.loaders.epoch",
    "loaders.jax": "training.loaders.jax",
    "loaders.reader": "training.loaders.reader",
    "loaders.torch": "training.loaders.torch",
    "generation.scene": "generation.mujoco_scene",
    "manipulation.estimates": "manipulation.hypotheses",
    "manipulation.estimators": "manipulation.sources",
    "models": "methods",
    "models.dense": "methods.dense",
    "models.dense.aggregate": "methods.dense.aggregate",
    "models.dense.checkpoint": "methods.dense.checkpoint",
    "models.dense.data": "methods.dense.data",
    "models.dense.features": "methods.dense.features",
    "models.dense.fit": "methods.dense.fit",
    "models.dense.handle": "methods.dense.handle",
    "models.dense.mirror": "methods.dense.mirror",
    "models.dense.model": "methods.dense.model",
    "models.dense.predict": "methods.dense.predict",
    "models.dense.refine": "methods.dense.refine",
    "models.dense.train": "methods.dense.train",
    "models.estimation": "methods.estimation",
    "models.export": "methods.export",
    "models.load": "methods.load",
    "models.mdn": "methods.mdn",
    "models.mdn.checkpoint": "methods.mdn.checkpoint",
    "models.mdn.config": "methods.mdn.config",
    "models.mdn.data": "methods.mdn.data",
    "models.mdn.loss": "methods.mdn.loss",
    "models.mdn.model": "methods.mdn.model",
    "models.mdn.predict": "methods.mdn.predict",
    "models.mdn.preprocess": "methods.mdn.preprocess",
    "models.mdn.train": "methods.mdn.train",
    "models.predict": "methods.predict",
    "models.safetensors_checkpoint": "methods.safetensors_checkpoint",
    "models.shipped": "methods.shipped",
    "models.train": "methods.train",
    "mujoco_support": "core.mujoco_support",
    "real": "ingest",
    "real.captures": "ingest.captures",
    "real.ground_truth": "ingest.ground_truth",
    "real.ingest": "ingest.capture",
    "real.ingest_split": "ingest.split",
    "real.intrinsics": "core.images.intrinsics",
    "real.noise": "core.noise",
    "real.readers": "ingest.readers",
    "real.resample": "core.images.resample",
    "real.write": "ingest.write",
    "registry": "classes.registry",
    "rotations": "core.rotations",
    "safeio": "core.safeio",
    "tables": "core.tables",
    "targets": "training.targets",
    "transforms": "training.transforms",
    "units": "core.units",
    "urdf_import": "generation.urdf_import",
    "urdf_import.build": "generation.urdf_import.build",
    "urdf_import.panel": "generation.urdf_import.panel",
    "urdf_import.parse": "generation.urdf_import.parse",
    "urdf_import.process": "generation.urdf_import.process",
    "urdf_import.ranges": "generation.urdf_import.ranges",
    "verify": "tools.verify",
    "verify.content": "tools.verify.content",
    "verify.manifest": "tools.verify.manifest",
    "verify.shard": "tools.verify.shard",
    "verify.split": "tools.verify.split",
    "viz": "tools.viz",
    "viz.data": "tools.viz.data",
    "viz.drawing": "tools.viz.drawing",
    "viz.gallery": "tools.viz.gallery",
    "viz.style": "tools.viz.style",
}

#: The release that removes the old paths.
REMOVED_IN = "0.3"


class MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old module path to the module at its new path (one object, two names)."""

    def find_spec(self, fullname, path=None, target=None):
        """A module spec loaded by this finder for an old (moved) module path of the package; None for any other
        name."""
        old = fullname[len(PACKAGE) + 1:] if fullname.startswith(PACKAGE + ".") else None
        if old not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec):
        """None: the default module creation is used."""
        return None

    def exec_module(self, module):
        """Warn (DeprecationWarning) that the old path is deprecated and bind the old name in ``sys.modules`` to the
        module at its new path."""
        old = module.__name__[len(PACKAGE) + 1:]
        new = f"{PACKAGE}.{MOVED[old]}"
        warnings.warn(f"{module.__name__} is now {new}; the old path is removed in {REMOVED_IN}",
                      DeprecationWarning, stacklevel=2)
        # The import system returns what sys.modules holds under the old name after this call.
        sys.modules[module.__name__] = importlib.import_module(new)


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once), before the finders that would load a
    second copy of a moved module under its old name."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())


def moved_attribute(name: str):
    """``articulated_dataset.<name>`` for a moved top-level module (the package's
    ``__getattr__``), imported through the finder."""
    if name not in MOVED:
        raise AttributeError(f"module {PACKAGE!r} has no attribute {name!r}")
    return importlib.import_module(f"{PACKAGE}.{name}")
