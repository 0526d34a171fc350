"""One class's estimator trained, either kind: the options turned into the dense or the MDN
training configuration, the options of the other kind refused (``artdata train`` parses its
options and calls :func:`train_model`).  Imports torch."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import UserError

log = logging.getLogger(__name__)

KINDS = ("mdn", "dense")


class TrainingInterrupted(Exception):
    """Training stopped by the user (Ctrl-C); the message says where the last checkpoint is and how to go on."""


@dataclass(frozen=True)
class TrainingRun:
    """The checkpoint :func:`train_model` wrote and a one-line description of it."""

    ckpt: dict
    summary: str


def train_model(kind: str, class_name: str, data: str | Path | list, out: str | Path, *, small: bool = False,
                epochs: int | None = None, batch_size: int | None = None, lr: float | None = None,
                components: int | None = None, width: int | None = None, init_from: str | None = None,
                origin_weight: float | None = None, val_fraction: float | None = None, max_objects: int | None = None, seed: int = 0,
                noise: str | None = None, noise_fraction: float | None = None,
                device: str = "auto", resume: bool = False, progress: bool = False,
                echo: Callable[[str], None] | None = None, mix_weights: list[float] | None = None) -> TrainingRun:
    """Train a ``kind`` (``mdn`` or ``dense``) network for ``class_name`` on the training split
    ``data`` into the checkpoint ``out``.  ``None`` settings take the kind's defaults (mdn: the
    ``small`` or full preset and 10% validation objects; dense: :class:`DenseTrainConfig`'s).
    ``small``/``components`` belong to mdn, ``width``/``init_from``/``origin_weight``/``noise``/``noise_fraction``
    to dense: given to the other
    kind they are a :class:`UserError`.  ``data`` may be a list of splits, mixed by ``mix_weights``
    (dense only: :func:`~.dense.train.train_dense`).  Ctrl-C raises :class:`TrainingInterrupted`."""
    if kind not in KINDS:
        raise UserError(f"unknown model kind {kind!r}; expected one of {', '.join(KINDS)}")
    if max_objects is not None and max_objects <= 0:
        raise UserError(f"--max-objects must be positive, got {max_objects}")
    if kind == "dense":
        if small or components is not None:
            raise UserError("--small and --components belong to --model mdn")
        from .dense.train import DenseTrainConfig, train_dense

        given = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "width": width, "val_fraction": val_fraction,
                 "origin_weight": origin_weight, "noise": noise, "noise_fraction": noise_fraction}
        config = DenseTrainConfig(class_name=class_name, max_objects=max_objects, seed=seed, init_from=init_from,
                                  **{k: v for k, v in given.items() if v is not None})
        try:
            ckpt = train_dense(data, out, config, resume=resume, progress=progress, echo=echo, device=device,
                               mix_weights=mix_weights)
        except KeyboardInterrupt:
            raise TrainingInterrupted(f"interrupted; the last checkpoint is in {out}. Continue with the same command "
                                      f"plus --resume") from None
        return TrainingRun(ckpt, f"dense {ckpt['class_name']}, {ckpt['step']} steps ({ckpt['data']['n_train_images']} "
                                 f"training / {ckpt['data']['n_val_images']} validation images)")
    if width is not None or init_from is not None or origin_weight is not None or noise is not None \
            or noise_fraction is not None:
        raise UserError("--width, --init-from, --origin-weight, --noise and --noise-fraction belong to --model dense")
    if isinstance(data, (list, tuple)):
        if len(data) != 1:
            raise UserError("--model mdn trains on one split; give one split folder (--model dense trains on several)")
        data = data[0]
    if mix_weights is not None:
        raise UserError("--mix-weights belongs to --model dense")
    from .mdn.config import TrainConfig
    from .mdn.train import train

    config = TrainConfig(class_name=class_name, preset="small" if small else "full", epochs=epochs, batch_size=batch_size,
                         lr=lr, val_fraction=0.1 if val_fraction is None else val_fraction, seed=seed,
                         n_components=components, max_objects=max_objects)
    try:
        ckpt = train(data, out, config, device=device, resume=resume, progress=progress, echo=echo)
    except KeyboardInterrupt:
        raise TrainingInterrupted(f"interrupted; the last finished epoch is in {out}. Continue with the same command "
                                  f"plus --resume") from None
    return TrainingRun(ckpt, f"{ckpt['class_name']}, {ckpt['epoch']} epochs ({ckpt['data']['n_train']} training / "
                             f"{ckpt['data']['n_val']} validation images)")
