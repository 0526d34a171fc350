"""One class's estimator trained by its method (:mod:`.protocol`): ``artdata train`` turns its
options into :class:`~.protocol.TrainSettings` and calls :func:`train_model`.  Imports torch
when training starts."""

from __future__ import annotations

import logging
from typing import Callable

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import KINDS, TrainingInterrupted, TrainingRun, TrainSettings, get_method

log = logging.getLogger(__name__)


def train_model(kind: str, settings: TrainSettings, *, resume: bool = False, progress: bool = False,
                echo: Callable[[str], None] | None = None) -> TrainingRun:
    """Train a ``kind`` (a registered method: ``mdn`` or ``dense``) network with ``settings``
    (class, training split folders, checkpoint file and the method's settings; ``None`` takes the
    method's defaults).  Settings of another method are a one-line :class:`UserError`
    (:meth:`~.protocol.Method.check_train_settings`).  Ctrl-C raises :class:`TrainingInterrupted`."""
    method = get_method(kind)
    if settings.max_objects is not None and settings.max_objects <= 0:
        raise UserError(f"{option('max_objects')} must be positive, got {settings.max_objects}")
    method.check_train_settings(settings)
    return method.train(settings, resume=resume, progress=progress, echo=echo)


__all__ = ["KINDS", "TrainSettings", "TrainingInterrupted", "TrainingRun", "train_model"]
