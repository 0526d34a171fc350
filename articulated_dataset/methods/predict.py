"""A split predicted by a ``--model`` (shipped name or checkpoint file) into ``predictions.h5``:
the model's method (:mod:`.protocol`) predicts, and the file gets the method's name and attributes
(``artdata predict`` parses its options and calls :func:`predict_to_file`).  Imports torch."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import PredictSettings, get_method

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PredictionRun:
    """What :func:`predict_to_file` wrote: the method's name, the split's class and its image count."""

    method: str
    class_name: str
    n_images: int


def predict_to_file(model: str, data: str | Path, out: str | Path, *, estimate: str = "mean-of-best",
                    snap_to_cloud: bool = False, object_mask: bool = False, method: str | None = None,
                    batch_size: int | None = None, device: str = "auto", mirror: bool = True,
                    workers: int | None = None, precision: str = "float32", progress: bool = False,
                    as_class: str | None = None, prompt: str | None = None) -> PredictionRun:
    """Predict every image of the split ``data`` with ``model`` and write ``out`` (``predictions.h5``).

    The dense model: batches of 128 by default, its heaviest vote mode, ``object_mask`` keeps
    the object's pixels only, ``mirror=False`` skips the refinement's mirror image (where the
    model uses it: one network pass instead of two, 1.1-1.5x the speed, a 4-6% higher position error),
    ``prompt`` (``point``, ``box``, ``mask``, ``none``) segments each image's object from the prompt
    a click or a detector would give (:mod:`~articulated_dataset.methods.prompts`; ``mask`` is
    ``object_mask``; recorded as the file's ``prompt`` attribute),
    ``workers`` processes share the images (None: one per torch thread where the split has 4,096
    images or more, :func:`~.dense.predict.default_workers`), ``precision`` is the network's
    arithmetic (``"float32"`` or ``"bfloat16"``); the MDN: batches of 256,
    ``estimate`` and ``snap_to_cloud``.  An
    option of the other kind is a :class:`UserError`.  ``method`` names the method in the
    file (default: the shipped model's name, else ``dense``, ``MDN`` or ``MDN-<preset>``).
    ``as_class``: the split is a third-party object (``generate --urdf``) of that built-in class
    (the same joint types, in order), predicted by the class's model and written under the
    split's own class (:func:`~.mdn.data.checked_split_class`), so ``score`` compares them with
    its labels."""
    from articulated_dataset.benchmark.predictions import write_predictions
    from articulated_dataset.methods.mdn.data import resolve_split_dir, split_class
    from articulated_dataset.methods.shipped import SHIPPED, resolve_model

    if as_class is None:
        ref = resolve_model(model, split_class(resolve_split_dir(data)))
    else:
        from articulated_dataset.classes.registry import get_class

        as_class = get_class(as_class).name  # an unknown name: one line listing the classes
        ref = resolve_model(model, as_class if model in SHIPPED else None)  # a checkpoint file: its own class
        if ref.class_name != as_class:
            raise UserError(f"{option('as_class')} {as_class}: {model} is a {ref.class_name!r} model")
    method_impl = get_method(ref.kind)
    settings = PredictSettings(estimate=estimate, snap_to_cloud=snap_to_cloud, object_mask=object_mask, prompt=prompt,
                               batch_size=batch_size, device=device, mirror=mirror, workers=workers,
                               precision=precision, method=method)
    method_impl.check_predict_settings(settings)
    name, class_name, arrays, method_attrs = method_impl.predict_split(ref, data, settings, progress=progress,
                                                                      as_class=as_class)
    attrs = {"model": str(model), **({"as_class": as_class} if as_class else {}), **method_attrs}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_predictions(out, name, {class_name: arrays}, attrs=attrs)
    log.info("%s: %d %s images predicted by %s", out, len(arrays["sample_id"]), class_name, name)
    return PredictionRun(name, class_name, len(arrays["sample_id"]))
