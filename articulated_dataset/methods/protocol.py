"""What every learned method is: one :class:`Method` protocol, the settings it is given, and the
registry of methods by kind.

A method (``dense``: :mod:`.dense.method`; ``mdn``: :mod:`.mdn.method`) trains a class's model
from split folders (:meth:`Method.train`), reads and checks its checkpoints
(:meth:`Method.load_checkpoint`), predicts a split (:meth:`Method.predict_split`) and, where it
can, estimates one depth image.  The command line, :func:`articulated_dataset.load_model`,
``estimate``, ``export-model`` and the manipulation wing pick the method from the registry
(:func:`get_method`, :func:`method_of_format`): adding a method means adding a module that
implements the protocol and one line in :data:`METHOD_MODULES`.

Settings a method does not use are refused by the method (:meth:`Method.check_train_settings`,
:meth:`Method.check_predict_settings`), each with its own one-line message.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

from articulated_dataset.core.errors import QuantityMessage, UserError

#: Kind -> module defining ``METHOD`` (an object implementing :class:`Method`).  Importing a
#: module imports no torch: each method imports it when it trains, loads or predicts.
METHOD_MODULES = {"mdn": "articulated_dataset.methods.mdn.method", "dense": "articulated_dataset.methods.dense.method"}
#: The method kinds, in the order the command line lists them.
KINDS = tuple(METHOD_MODULES)


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run is given (``artdata train``'s options as quantities).  ``None``
    takes the method's default; a setting the method does not use is refused by it."""

    class_name: str
    data: tuple[Path, ...]
    out: Path
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    val_fraction: float | None = None
    max_objects: int | None = None
    seed: int = 0
    device: str = "auto"
    # mdn
    small: bool = False
    components: int | None = None
    # dense
    width: int | None = None
    init_from: str | None = None
    origin_weight: float | None = None
    noise: str | None = None
    noise_fraction: float | None = None
    mix_weights: tuple[float, ...] | None = None
    prompts: tuple[str, ...] | None = None

    def given(self, names) -> list[str]:
        """Those of ``names`` set away from their defaults."""
        defaults = {f.name: f.default for f in fields(self)}
        return [n for n in names if getattr(self, n) != defaults[n]]


@dataclass(frozen=True)
class PredictSettings:
    """Everything a split prediction is given (``artdata predict``'s options as quantities)."""

    estimate: str = "mean-of-best"
    snap_to_cloud: bool = False
    object_mask: bool = False
    #: the dense model: each image's object segmented from a simulated prompt (methods/prompts.py
    #: PROMPT_KINDS); None: none (``object_mask`` is the ``mask`` prompt)
    prompt: str | None = None
    batch_size: int | None = None
    device: str = "auto"
    mirror: bool = True
    workers: int | None = None
    precision: str = "float32"
    method: str | None = None


@dataclass(frozen=True)
class TrainingRun:
    """The checkpoint a training run wrote and a one-line description of it."""

    ckpt: Mapping[str, Any]
    summary: str


class TrainingInterrupted(QuantityMessage):
    """Training stopped by the user (Ctrl-C); the message says where the last checkpoint is and how to go on."""


@runtime_checkable
class Method(Protocol):
    """A learned method: its kind, its checkpoint format, and what it can do."""

    kind: str
    #: The ``format`` field of its checkpoints.
    checkpoint_format: str
    #: Whether it estimates one depth image (``estimate``, ``load_model(...).estimate``).
    single_image: bool
    #: Whether ``export-model --format onnx`` covers its network.
    onnx_export: bool

    def check_train_settings(self, settings: TrainSettings) -> None:
        """Refuse, in one line, the settings of other methods."""

    def train(self, settings: TrainSettings, *, resume: bool, progress: bool,
              echo: Callable[[str], None] | None) -> TrainingRun:
        """Train and write ``settings.out``; Ctrl-C raises :class:`TrainingInterrupted`."""

    def load_checkpoint(self, path: Path) -> dict:
        """A checkpoint file read and checked (any problem: one-line :class:`UserError`)."""

    def build_network(self, ckpt: dict):
        """The PyTorch network of a checkpoint, in eval mode."""

    def display_name(self, ckpt: dict) -> str:
        """The method's name in predictions files for a checkpoint file of this kind."""

    def check_predict_settings(self, settings: PredictSettings) -> None:
        """Refuse, in one line, the prediction settings of other methods."""

    def predict_split(self, ref, data, settings: PredictSettings, *, progress: bool,
                      as_class: str | None) -> tuple[str, str, dict, dict]:
        """Predict every image of the split ``data`` with the resolved model ``ref``
        (:class:`~articulated_dataset.methods.shipped.ModelRef`): (method name, class name,
        arrays, file attributes)."""


_METHODS: dict[str, Method] = {}


def get_method(kind: str) -> Method:
    """The registered method of ``kind``; an unknown kind is a one-line :class:`UserError`."""
    if kind not in METHOD_MODULES:
        raise UserError(f"unknown model kind {kind!r}; expected one of {', '.join(KINDS)}")
    if kind not in _METHODS:
        method = importlib.import_module(METHOD_MODULES[kind]).METHOD
        if not isinstance(method, Method) or method.kind != kind:
            raise TypeError(f"{METHOD_MODULES[kind]}.METHOD must implement Method with kind {kind!r}")
        _METHODS[kind] = method
    return _METHODS[kind]


def all_methods() -> list[Method]:
    """Every registered method, in :data:`KINDS` order."""
    return [get_method(kind) for kind in KINDS]


def method_of_format(checkpoint_format) -> Method | None:
    """The method whose checkpoints carry ``format`` ``checkpoint_format`` (None: no method's)."""
    for method in all_methods():
        if checkpoint_format == method.checkpoint_format:
            return method
    return None
