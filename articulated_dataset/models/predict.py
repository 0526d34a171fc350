"""A split predicted by a ``--model`` (shipped name or checkpoint file) into ``predictions.h5``:
the choice between the dense and the MDN predictor, the method's name and the file's attributes
(``artdata predict`` parses its options and calls :func:`predict_to_file`).  Imports torch."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from ..errors import UserError

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
                    as_class: str | None = None) -> PredictionRun:
    """Predict every image of the split ``data`` with ``model`` and write ``out`` (``predictions.h5``).

    The dense model: batches of 128 by default, its heaviest vote mode, ``object_mask`` keeps
    the object's pixels only, ``mirror=False`` skips the refinement's mirror image (where the
    model uses it: one network pass instead of two, 1.1-1.5x the speed, a 4-6% higher position error),
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
    from ..benchmark.predictions import write_predictions
    from .mdn.data import resolve_split_dir, split_class
    from .shipped import SHIPPED, resolve_model

    if as_class is None:
        ref = resolve_model(model, split_class(resolve_split_dir(data)))
    else:
        from ..registry import get_class

        as_class = get_class(as_class).name  # an unknown name: one line listing the classes
        ref = resolve_model(model, as_class if model in SHIPPED else None)  # a checkpoint file: its own class
        if ref.class_name != as_class:
            raise UserError(f"--as-class {as_class}: {model} is a {ref.class_name!r} model")
    if ref.kind == "dense":
        if snap_to_cloud:
            raise UserError("--snap-to-cloud applies to MDN models; the dense model's origins are already point votes")
        if estimate != "mean-of-best":
            raise UserError("--estimate applies to MDN models; the dense model always gives its heaviest vote mode")
        if device not in ("auto", "cpu"):
            raise UserError(f"--device {device}: the dense model runs on the CPU (--device applies to MDN models)")
        from .dense.predict import predict_split as predict_dense
        from .dense.checkpoint import load_dense_checkpoint

        ckpt = load_dense_checkpoint(ref.path)
        name = method or ref.name  # dense, dense-kinect2 (shipped) or dense (a checkpoint file)
        class_name, arrays = predict_dense(ckpt, data, batch_size=128 if batch_size is None else batch_size,
                                           object_mask=object_mask, mirror=mirror, workers=workers, precision=precision,
                                           progress=progress, as_class=as_class)
        attrs = {"model": str(model), **({"as_class": as_class} if as_class else {}), "estimate": "heaviest-mode", "steps": int(ckpt["step"]),
                 "object_mask": int(object_mask), "mirror": int(mirror), "precision": precision}
    else:
        if object_mask:
            raise UserError("--object-mask applies to the dense model")
        if not mirror:
            raise UserError("--no-mirror applies to the dense model")
        if workers is not None:
            raise UserError("--workers applies to the dense model (the MDN uses torch's threads)")
        if precision != "float32":
            raise UserError("--precision applies to the dense model (the MDN uses bfloat16 on a GPU by itself)")
        from .mdn.checkpoint import load_checkpoint
        from .mdn.predict import predict_split

        ckpt = load_checkpoint(ref.path)
        preset = ckpt["train_config"].get("preset", "full")
        name = method or ("MDN" if preset == "full" else f"MDN-{preset}")
        class_name, arrays = predict_split(ref.path, data, estimate=estimate, snap_to_cloud=snap_to_cloud,
                                           batch_size=256 if batch_size is None else batch_size, device=device,
                                           progress=progress, as_class=as_class)
        attrs = {"model": str(model), **({"as_class": as_class} if as_class else {}), "estimate": estimate, "snap_to_cloud": int(snap_to_cloud),
                 "epochs": int(ckpt["epoch"]), "preset": preset}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_predictions(out, name, {class_name: arrays}, attrs=attrs)
    log.info("%s: %d %s images predicted by %s", out, len(arrays["sample_id"]), class_name, name)
    return PredictionRun(name, class_name, len(arrays["sample_id"]))
