"""The learned methods and their weights (docs/model.md, docs/dense.md).

* :mod:`.mdn`: the paper's reference network, a per-class mixture density network.
* :mod:`.dense`: the package's own per-pixel voting estimator.
* :mod:`.shipped`: ``--model`` resolved to a checkpoint: the shipped weights (package data in
  ``articulated_dataset/methods/weights/``) or a file written by ``artdata train``.
* :mod:`.estimation`: one depth image in, an :class:`~.estimation.Estimate` out
  (``articulated_dataset.estimate``).

Importing this package imports no torch; :mod:`.mdn`, :mod:`.dense` and :mod:`.estimation`
import it when they are used.
"""

from articulated_dataset.methods.shipped import (
                      FORMATS,
                      MODELS_MANIFEST,
                      SHIPPED,
                      WEIGHTS_DIR,
                      ModelRef,
                      resolve_model,
                      shipped_models,
                      strip_for_shipping,
)

__all__ = ["FORMATS", "MODELS_MANIFEST", "SHIPPED", "WEIGHTS_DIR", "ModelRef", "resolve_model", "shipped_models",
           "strip_for_shipping"]
