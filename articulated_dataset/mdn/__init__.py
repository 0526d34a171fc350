"""The reference model: a per-class ResNet-18 mixture density network (docs/model.md).

* :mod:`.model`: ResNet backbone (1 depth channel + optional mask/coordinate channels) and
  the mixture heads (weights, means, scales).
* :mod:`.loss`: mixture log-likelihood (log-sum-exp), point estimates (mean of the best
  component, mixture mode).
* :mod:`.preprocess`: depth image -> network input.
* :mod:`.train`: training loop, presets (``full``, ``small``), checkpoints.
* :mod:`.predict`: inference on a split -> ``predictions.h5`` arrays.

These modules import torch; importing this package does not (torch is optional).
"""

from __future__ import annotations

__all__ = ["model", "loss", "preprocess", "train", "predict"]
