"""The reference model: a per-class ResNet-18 mixture density network (docs/model.md).

* :mod:`.model`: ResNet backbone (1 depth channel + optional mask/coordinate channels) and
  the mixture heads (weights, means, scales).
* :mod:`.loss`: mixture log-likelihood (log-sum-exp), point estimates (mean of the best
  component, mixture mode).
* :mod:`.preprocess`: depth image -> network input.
* :mod:`.config`: presets (``full``, ``small``) and the training settings.
* :mod:`.data`: the training split in memory, validation objects, anchored/active target columns.
* :mod:`.checkpoint`: saving, reading and checking checkpoints; the model rebuilt from one.
* :mod:`.train`: the training loop.
* :mod:`.predict`: inference on a split -> ``predictions.h5`` arrays.

These modules import torch; importing this package does not (torch is optional).
"""

from __future__ import annotations

__all__ = ["model", "loss", "preprocess", "config", "data", "checkpoint", "train", "predict"]
