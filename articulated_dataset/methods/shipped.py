"""Shipped (pretrained) models and checkpoint files: one place that turns ``--model`` into a network.

The package carries, as package data under ``articulated_dataset/methods/weights/``, one checkpoint per
class for each shipped model (``dense``: the per-pixel voting network; ``dense-kinect2``: the same
network continued on renders half of which pass through the Kinect v2 depth-noise model, for
real sensors' depth (docs/real_data.md); ``mdn-small``: the
paper's mixture density network at the ``--small`` preset) and ``models.json`` describing
them: files, SHA-256s, sizes, training data (command, seed, objects), epochs/steps, wall time,
machine and test figures.  Each checkpoint is a pair, ``NAME.safetensors`` (the weights) and
``NAME.json`` (its configuration, calibration and refinement), read without pickle
(:mod:`.safetensors_checkpoint`); both files are checked against their SHA-256 before loading.

``--model`` accepts a shipped model's name or a checkpoint path: a ``.pt`` file written by
``artdata train`` (read with ``torch.load(weights_only=True)``: no code runs from it) or a
``.safetensors`` file with its ``.json`` beside it (``artdata export-model --format
safetensors``); either kind, the kind read from the file.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import all_methods, get_method, method_of_format

log = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
MODELS_MANIFEST = WEIGHTS_DIR / "models.json"
#: Shipped model names -> checkpoint kind.
SHIPPED = {"dense": "dense", "dense-kinect2": "dense", "mdn-small": "mdn"}
#: Checkpoint ``format`` field -> kind (from the method registry).
FORMATS = {method.checkpoint_format: method.kind for method in all_methods()}


@dataclass(frozen=True)
class ModelRef:
    """A resolved ``--model``: its kind (``dense`` or ``mdn``), file, display name and class."""

    kind: str
    path: Path
    name: str
    class_name: str


def shipped_models() -> list[dict]:
    """Entries of ``weights/models.json`` (empty when no weights are shipped)."""
    if not MODELS_MANIFEST.is_file():
        return []
    with open(MODELS_MANIFEST, encoding="utf-8") as fh:
        return list(json.load(fh).get("models", []))


def _sha256(path: Path) -> str:
    from articulated_dataset.format import sha256_file

    return sha256_file(path)


_RESOLVED: dict = {}


def _file_key(path: Path):
    """A checkpoint's state: its path, modification time and size, and those of a safetensors
    file's configuration beside it (where there is one)."""
    from articulated_dataset.methods.safetensors_checkpoint import config_path, is_safetensors_path

    files = [path, config_path(path)] if is_safetensors_path(path) else [path]
    return tuple((str(p.resolve()), p.stat().st_mtime_ns, p.stat().st_size) if p.is_file() else (str(p), None, None)
                 for p in files)


def shipped_files(entry: dict) -> list[tuple[Path, str]]:
    """The files of a ``models.json`` entry with their SHA-256: the weights (``file``) and, for a
    safetensors pair, its configuration (``config``)."""
    files = [(WEIGHTS_DIR / entry["file"], entry["sha256"])]
    if "config" in entry:
        files.append((WEIGHTS_DIR / entry["config"], entry["config_sha256"]))
    return files


def resolve_model(spec: str, class_name: str | None) -> ModelRef:
    """The model that ``--model spec`` names, for ``class_name`` (None: take the file's class).

    A shipped name needs the class; a path is read and its kind and class taken from it.  A
    class that differs from the checkpoint's is a one-line :class:`UserError`.  Results are
    cached per file state (path, modification time, size), so repeated calls cost nothing.
    """
    if not isinstance(spec, (str, os.PathLike)):
        raise UserError(f"a model is a shipped model's name ({', '.join(SHIPPED)}) or a checkpoint's path, "
                        f"got {type(spec).__name__}")
    if spec in SHIPPED:
        entry = next((m for m in shipped_models() if m["name"] == spec and m["class_name"] == class_name), None)
        target = WEIGHTS_DIR / entry["file"] if entry is not None else None
    else:
        target = Path(spec)
    key = (spec, class_name, _file_key(target)) if target is not None and target.is_file() else None
    if key is not None and key in _RESOLVED:
        return _RESOLVED[key]
    ref = _resolve(spec, class_name)
    if key is not None:
        _RESOLVED[key] = ref
    return ref


def _resolve(spec: str, class_name: str | None) -> ModelRef:
    if spec in SHIPPED:
        if class_name is None:
            raise UserError(f"{option('model')} {spec} needs the object class")
        entry = next((m for m in shipped_models() if m["name"] == spec and m["class_name"] == class_name), None)
        if entry is None:
            have = sorted({m["class_name"] for m in shipped_models() if m["name"] == spec})
            from articulated_dataset.classes.registry import class_names

            third_party = ("" if class_name in class_names()
                           else f"; a third-party object of one of them: pass {option('as_class')} CLASS")
            raise UserError(f"no shipped {spec!r} model for class {class_name!r}"
                            + (f" (shipped: {', '.join(have)}{third_party})" if have else " (this installation ships no weights)"))
        for path, digest in shipped_files(entry):
            if not path.is_file():
                raise UserError(f"shipped model file missing: {path} (reinstall the package)")
            if _sha256(path) != digest:
                raise UserError(f"shipped model file {path} does not match its checksum (reinstall the package)")
        return ModelRef(SHIPPED[spec], WEIGHTS_DIR / entry["file"], spec, class_name)
    path = Path(spec)
    if not path.is_file():
        raise UserError(f"{option('model')} {spec!r}: neither a shipped "
                        f"model ({', '.join(SHIPPED)}) nor a checkpoint file")
    from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file

    ckpt = read_checkpoint_file(path)
    method = method_of_format(ckpt.get("format")) if isinstance(ckpt, dict) else None
    if method is None:
        raise UserError(f"{path}: not a checkpoint written by 'artdata train'")
    file_class = str(ckpt.get("class_name"))
    if class_name is not None and file_class != class_name:
        raise UserError(f"{path}: a {file_class!r} model, but the data is {class_name!r}")
    return ModelRef(method.kind, path, method.display_name(ckpt), file_class)


#: The parts of a training checkpoint that only continuing its training reads.
TRAINING_STATE_KEYS = ("optimizer_state", "scheduler_state", "scaler_state", "rng_state")


def without_training_state(ckpt: dict) -> dict:
    """A checkpoint without its :data:`TRAINING_STATE_KEYS` (what inference needs)."""
    return {k: v for k, v in ckpt.items() if k not in TRAINING_STATE_KEYS}


def strip_for_shipping(ckpt: dict) -> dict:
    """A checkpoint without optimizer, schedule and RNG state (:func:`without_training_state`),
    its floating-point weights stored as float16 (half the size; loading casts them back to
    float32: ``load_state_dict`` copies into the float32 parameters)."""
    out = without_training_state(ckpt)
    out["model_state"] = {k: (v.half() if v.is_floating_point() else v) for k, v in ckpt["model_state"].items()}
    out["weights_dtype"] = "float16"
    return out


def load_model_checkpoint(ref: ModelRef) -> dict:
    """The checkpoint of a resolved model, read and checked by its kind's loader (the dense
    model's or the MDN's); any problem is a one-line :class:`UserError`."""
    return get_method(ref.kind).load_checkpoint(ref.path)
